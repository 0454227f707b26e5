"""The skills' pure choices: where a retried approach may stand, which pixel a put aims at."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.perception.base import Detection
from tidee.agent.policy.skills import EDGE_MARGIN, aim_region, mask_away_from, other_receptacles


def _centres(grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    xs = grid.origin[0] + (np.arange(grid.shape[0]) + 0.5) * grid.cell
    ys = grid.origin[1] + (np.arange(grid.shape[1]) + 0.5) * grid.cell
    return np.meshgrid(xs, ys, indexing="ij")


def test_a_retry_stands_at_least_half_a_metre_from_every_spot_already_tried() -> None:
    grid = GridSpec((-2.0, -2.0), 0.05, (80, 80))
    x, y = _centres(grid)
    ring = (np.hypot(x, y) > 0.4) & (np.hypot(x, y) <= 1.0)  # a goal ring around an object at (0, 0)
    tried = [np.array([0.7, 0.0]), (0.0, -0.7)]
    away = mask_away_from(ring, grid, tried)
    gaps = np.min([np.hypot(x - p[0], y - p[1]) for p in tried], axis=0)
    assert away.any() and not (away & ~ring).any()  # only cells of the goal region
    assert gaps[away].min() >= 0.5  # none within 0.5 m of a tried spot
    assert (ring & (gaps >= 0.5) & ~away).sum() == 0  # and every other cell kept
    assert (ring & (gaps < 0.5)).any()  # (there were cells to remove)
    # a wider keep-away; no spot tried yet leaves the region as it is (a copy)
    assert mask_away_from(ring, grid, tried, min_m=1.0).sum() < away.sum()
    same = mask_away_from(ring, grid, [])
    assert np.array_equal(same, ring) and same is not ring
    # every cell near a tried spot: empty (the caller falls back on its region)
    assert not mask_away_from(ring, grid, [(0.0, 0.0)], min_m=1.5).any()


def test_a_put_aims_off_the_frame_border_and_off_other_receptacles() -> None:
    h = w = 100
    table = np.zeros((h, w), bool)
    table[40:100, 0:60] = True  # reaches the bottom and left borders
    inner = aim_region(table)
    m = int(np.ceil(EDGE_MARGIN * h))
    assert inner.any() and not inner[h - m :].any() and not inner[:, :m].any()
    assert np.array_equal(inner, table & _inner(h, w, m))
    # the bed beside the table: its mask covers the table's left part; those pixels are not aimed at
    bed = np.zeros((h, w), bool)
    bed[30:100, 0:25] = True
    aim = aim_region(table, bed)
    assert aim.any() and not (aim & bed).any() and np.array_equal(aim, table & _inner(h, w, m) & ~bed)
    # a region entirely at the border keeps its pixels (nothing else to aim at)
    sliver = np.zeros((h, w), bool)
    sliver[0:3, 10:20] = True
    assert np.array_equal(aim_region(sliver), sliver)
    # a neighbour covering nearly all of the target (one depth, one mask): ignored, not a sliver
    over = np.zeros((h, w), bool)
    over[38:100, 0:58] = True
    assert np.array_equal(aim_region(table, over), table & _inner(h, w, m))


def _inner(h: int, w: int, m: int) -> np.ndarray:
    out = np.zeros((h, w), bool)
    out[m : h - m, m : w - m] = True
    return out


def test_other_receptacles_are_every_other_detection_of_the_labels() -> None:
    shape = (40, 40)
    table = Detection("SideTable", 0.9, (20, 20, 30, 30))
    bed = Detection("Bed", 0.8, (0, 10, 20, 40))
    mug = Detection("Mug", 0.9, (22, 22, 25, 25))  # not a receptacle: aimed at freely
    body = SimpleNamespace(obs=SimpleNamespace(depth=np.zeros(shape)), detections=[table, bed, mug])
    others = other_receptacles(body, table, frozenset({"SideTable", "Bed"}))
    assert others is not None and np.array_equal(others, bed.region(shape))
    body.detections = [table, mug]
    assert other_receptacles(body, table, frozenset({"SideTable", "Bed"})) is None
