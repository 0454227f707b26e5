"""A small object's footprint (centre, long axis) from the depth points of one view, pooled over views."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tidee.agent.mapping.footprint import Footprint, FootprintVotes, axis_gap, footprint


def box_view(
    centre: tuple[float, float],
    size: tuple[float, float, float],
    heading_deg: float,
    table_z: float = 0.75,
    camera_side: float = -1.0,
    surround: float = 0.06,
    step: float = 0.004,
) -> np.ndarray:
    """Points a camera sees of a box on a table: its top face, the side facing the camera
    (along -y local when ``camera_side`` is -1) and the table around it (a depth-cut box mask)."""
    sx, sy, sz = size
    t = math.radians(heading_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    pts = []
    for lx in np.arange(-sx / 2, sx / 2 + 1e-9, step):
        for ly in np.arange(-sy / 2, sy / 2 + 1e-9, step):
            pts.append((lx, ly, table_z + sz))
        for lz in np.arange(0.0, sz, step):
            pts.append((lx, camera_side * sy / 2, table_z + lz))
    out = np.array(pts)
    out[:, :2] = out[:, :2] @ rot.T + centre
    gx = np.arange(-sx / 2 - surround, sx / 2 + surround, step)
    gy = np.arange(-sy / 2 - surround, sy / 2 + surround, step)
    ring = np.array([(x, y) for x in gx for y in gy if max(abs(x) - sx / 2, abs(y) - sy / 2) > 0.0])
    if not len(ring):
        return out
    table = np.column_stack([ring @ rot.T + centre, np.full(len(ring), table_z)])
    return np.vstack([out, table])


@pytest.mark.parametrize("heading", [0.0, 30.0, 100.0, 165.0])
def test_a_long_box_gives_its_centre_and_heading_not_the_table_around_it(heading: float) -> None:
    fp = footprint(box_view((1.2, -0.4), (0.16, 0.05, 0.03), heading))
    assert fp is not None
    assert np.linalg.norm(fp.centre - [1.2, -0.4]) < 0.006  # the seen side face does not pull it
    assert abs(axis_gap(fp.axis_deg, heading % 180.0)) < 3.0
    assert fp.elongation > 0.5


def test_the_centre_is_the_middle_of_the_extent_not_the_mean_of_the_points() -> None:
    pts = box_view((0.0, 0.0), (0.10, 0.10, 0.10), 0.0, surround=0.0)
    # the side face facing the camera (at -y) adds as many points as the top face
    assert pts[:, 1].mean() < -0.01
    fp = footprint(pts)
    assert fp is not None and np.linalg.norm(fp.centre) < 0.005


def test_a_flat_thing_is_all_points_and_too_few_points_are_nothing() -> None:
    flat = box_view((0.5, 0.5), (0.12, 0.04, 0.002), 45.0, surround=0.0)
    fp = footprint(flat)
    assert fp is not None and abs(axis_gap(fp.axis_deg, 45.0)) < 3.0
    assert footprint(flat[:5]) is None


def _fp(centre: tuple[float, float], axis: float, elongation: float, n: int) -> Footprint:
    return Footprint(np.array(centre), axis, elongation, n)


def test_votes_pool_views_by_their_points_and_axes_by_elongation_too() -> None:
    v = FootprintVotes()
    assert v.centre is None and v.axis_deg() is None
    v.add(_fp((0.0, 0.0), 178.0, 0.8, 300))  # near view: 178 and 4 degrees are one axis
    v.add(_fp((0.04, 0.0), 4.0, 0.8, 100))
    v.add(_fp((0.0, 0.0), 90.0, 0.0, 200))  # a view where it looked square: no say in the axis
    assert np.allclose(v.centre, [0.04 * 100 / 600, 0.0])
    axis = v.axis_deg()
    assert axis is not None and abs(axis_gap(axis, 179.5)) < 0.6


def test_no_axis_when_the_views_disagree_or_the_thing_is_round() -> None:
    split = FootprintVotes()
    split.add(_fp((0, 0), 0.0, 0.9, 100))
    split.add(_fp((0, 0), 90.0, 0.9, 100))
    assert split.axis_deg() is None
    round_ = FootprintVotes()
    round_.add(_fp((0, 0), 33.0, 0.05, 500))
    assert round_.axis_deg() is None


@pytest.mark.parametrize(
    "a, b, turn", [(10.0, 0.0, 10.0), (0.0, 170.0, 10.0), (170.0, 0.0, -10.0), (90.0, 0.0, -90.0)]
)
def test_axis_gap_is_the_shortest_turn_between_two_axes(a: float, b: float, turn: float) -> None:
    assert axis_gap(a, b) == pytest.approx(turn)
