"""Where to go next while exploring: random unexplored goals (TIDEE) and frontiers (Yamauchi).

TIDEE explores by repeatedly sampling a reachable, not yet explored map location and
navigating to it; its out-of-place search phase samples random reachable locations.
:class:`FrontierExplorer` is the classic alternative (Yamauchi, "A frontier-based approach
for autonomous exploration", 1997): go to the nearest boundary between known free space
and unknown space.

All grids are bool (nx, ny) arrays on the grid described in ``navigation/fmm.py`` (axis 0
along +x, axis 1 along +y, world point of a cell = its centre, metres, start frame).
Randomness comes only from the ``np.random.Generator`` passed in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.navigation.fmm import FMMPlanner

__all__ = [
    "unexplored_fraction",
    "sample_unexplored_goal",
    "sample_reachable_goal",
    "FrontierCluster",
    "FrontierExplorer",
]

_EIGHT = np.ones((3, 3), dtype=bool)
_FOUR = ndimage.generate_binary_structure(2, 1)


def _check_grids(shape: tuple[int, int] | None, **grids: np.ndarray) -> tuple[int, int]:
    for name, g in grids.items():
        if g.dtype != np.bool_ or g.ndim != 2:
            raise ValueError(f"{name} must be a 2D bool grid, got {g.dtype} with ndim {g.ndim}")
        if shape is None:
            shape = g.shape
        elif g.shape != tuple(shape):
            raise ValueError(f"{name} has shape {g.shape}, expected {tuple(shape)}")
    assert shape is not None
    return (int(shape[0]), int(shape[1]))


def _far_enough(
    shape: tuple[int, int], grid: GridSpec, agent_xy: Sequence[float], min_dist_m: float
) -> np.ndarray:
    """bool grid: cells whose centres are at least ``min_dist_m`` metres from the agent."""
    x = grid.origin[0] + (np.arange(shape[0]) + 0.5) * grid.cell - float(agent_xy[0])
    y = grid.origin[1] + (np.arange(shape[1]) + 0.5) * grid.cell - float(agent_xy[1])
    return np.hypot(x[:, None], y[None, :]) >= min_dist_m


def _pick(candidates: np.ndarray, grid: GridSpec, rng: np.random.Generator) -> tuple[float, float]:
    idx = np.flatnonzero(candidates)  # row-major order: deterministic for a given rng state
    k = int(idx[int(rng.integers(len(idx)))])
    i, j = divmod(k, candidates.shape[1])
    p = grid.cell_to_world(np.array([[i, j]]))[0]
    return (float(p[0]), float(p[1]))


def unexplored_fraction(explored: np.ndarray, reachable: np.ndarray) -> float:
    """Fraction in [0, 1] of reachable cells that are not explored; 0.0 if nothing is reachable."""
    _check_grids(None, explored=explored, reachable=reachable)
    n = int(reachable.sum())
    if n == 0:
        return 0.0
    return float((reachable & ~explored).sum()) / n


def sample_unexplored_goal(
    explored: np.ndarray,
    reachable: np.ndarray,
    grid: GridSpec,
    rng: np.random.Generator,
    agent_xy: Sequence[float],
    min_dist_m: float = 0.5,
) -> tuple[float, float] | None:
    """A random reachable, unexplored cell centre (x, y) metres at least ``min_dist_m`` away.

    Cells 8-adjacent to explored space are preferred (sampled from first when any exist):
    they are where the map actually grows, not deep in unknown space the agent cannot
    see yet. None when no reachable unexplored cell is far enough.
    """
    shape = _check_grids(tuple(grid.shape), explored=explored, reachable=reachable)
    candidates = reachable & ~explored & _far_enough(shape, grid, agent_xy, min_dist_m)
    if not candidates.any():
        return None
    border = candidates & ndimage.binary_dilation(explored, structure=_EIGHT)
    return _pick(border if border.any() else candidates, grid, rng)


def sample_reachable_goal(
    reachable: np.ndarray,
    grid: GridSpec,
    rng: np.random.Generator,
    agent_xy: Sequence[float],
    min_dist_m: float = 1.0,
) -> tuple[float, float] | None:
    """A random reachable cell centre (x, y) metres at least ``min_dist_m`` from the agent, or None."""
    shape = _check_grids(tuple(grid.shape), reachable=reachable)
    candidates = reachable & _far_enough(shape, grid, agent_xy, min_dist_m)
    if not candidates.any():
        return None
    return _pick(candidates, grid, rng)


@dataclass(frozen=True)
class FrontierCluster:
    """One 8-connected group of frontier cells.

    cells: int (N, 2) cell indices, row-major order. centroid_xy: mean of the cell centres
    (metres, may lie off the frontier). goal_xy: centre of the member cell nearest the
    centroid (metres): where to go.
    """

    cells: np.ndarray
    centroid_xy: tuple[float, float]
    goal_xy: tuple[float, float]

    @property
    def size(self) -> int:
        return int(len(self.cells))


class FrontierExplorer:
    """Frontier-based exploration (Yamauchi 1997) on bool grids.

    Args:
        grid: grid geometry (``origin``, ``cell``, ``shape``).
        min_cluster_cells: clusters with fewer cells are noise and dropped.
        min_goal_dist_m: clusters whose goal is closer than this (metres, euclidean) to
            the agent are skipped by ``next_goal``: going there teaches nothing new.
    """

    def __init__(self, grid: GridSpec, min_cluster_cells: int = 5, min_goal_dist_m: float = 0.25) -> None:
        if min_cluster_cells < 1:
            raise ValueError(f"min_cluster_cells must be >= 1, got {min_cluster_cells}")
        self.grid = grid
        self.shape = (int(grid.shape[0]), int(grid.shape[1]))
        self.min_cluster_cells = int(min_cluster_cells)
        self.min_goal_dist_m = float(min_goal_dist_m)

    def frontier_mask(self, free: np.ndarray, known: np.ndarray, obstacle: np.ndarray) -> np.ndarray:
        """bool grid: known, free, non-obstacle cells 4-adjacent to an unknown cell.

        Off-grid neighbours do not count as unknown (the map edge is no frontier).
        """
        _check_grids(self.shape, free=free, known=known, obstacle=obstacle)
        unknown = ~known
        near_unknown = ndimage.binary_dilation(unknown, structure=_FOUR, border_value=0)
        return free & known & ~obstacle & near_unknown

    def frontiers(self, free: np.ndarray, known: np.ndarray, obstacle: np.ndarray) -> list[FrontierCluster]:
        """The frontier clusters (8-connected, >= ``min_cluster_cells``), largest first.

        Ties in size keep label order (row-major position of the first cell).
        """
        mask = self.frontier_mask(free, known, obstacle)
        labels, n = ndimage.label(mask, structure=_EIGHT)
        if n == 0:
            return []
        flat = labels.ravel()
        order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=n + 1)
        starts = np.concatenate([[0], np.cumsum(counts)])
        clusters: list[FrontierCluster] = []
        for lab in range(1, n + 1):
            if counts[lab] < self.min_cluster_cells:
                continue
            k = order[starts[lab] : starts[lab + 1]]
            cells = np.stack(np.divmod(k, self.shape[1]), axis=1)
            pts = self.grid.cell_to_world(cells)
            c = pts.mean(axis=0)
            nearest = int(np.argmin(np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1])))
            clusters.append(
                FrontierCluster(
                    cells=cells,
                    centroid_xy=(float(c[0]), float(c[1])),
                    goal_xy=(float(pts[nearest, 0]), float(pts[nearest, 1])),
                )
            )
        clusters.sort(key=lambda cl: -cl.size)  # stable: ties keep label order
        return clusters

    def next_goal(
        self,
        free: np.ndarray,
        known: np.ndarray,
        obstacle: np.ndarray,
        distance_from_agent: FMMPlanner | np.ndarray,
        agent_xy: Sequence[float],
    ) -> tuple[float, float] | None:
        """Goal (x, y) metres of the geodesically nearest frontier cluster, or None.

        ``distance_from_agent`` is a geodesic distance field *seeded at the agent* (float
        (nx, ny) metres, inf where unreachable), or an ``FMMPlanner`` whose goal was set to
        the agent's position. A cluster's distance is the minimum over its cells (the
        snapped centroid itself may sit on a dilated-obstacle cell). Ties go to the larger
        cluster, then to the one nearer in straight line. None when no frontier remains or
        none is reachable.
        """
        if isinstance(distance_from_agent, FMMPlanner):
            field = distance_from_agent.distance_field
        else:
            field = np.asarray(distance_from_agent, dtype=np.float64)
        if field.shape != self.shape:
            raise ValueError(f"distance field has shape {field.shape}, expected {self.shape}")
        ax, ay = float(agent_xy[0]), float(agent_xy[1])
        best: tuple[float, int, float] | None = None
        best_goal: tuple[float, float] | None = None
        for cl in self.frontiers(free, known, obstacle):
            gx, gy = cl.goal_xy
            euclid = math.hypot(gx - ax, gy - ay)
            if euclid < self.min_goal_dist_m:
                continue
            geo = float(field[cl.cells[:, 0], cl.cells[:, 1]].min())
            if not math.isfinite(geo):
                continue
            key = (geo, -cl.size, euclid)
            if best is None or key < best:
                best, best_goal = key, cl.goal_xy
        return best_goal
