"""Scan matching: the agent corrects a drifting odometry against its own map.

With pose noise (``EpisodeSpec.pose_noise``: every move and turn off by a little, as a real
base's wheels are) the poses the observations report drift from the true ones, and a map
built on them smears: walls double, and an object seen twice lands in two places. Before
each frame is mapped, ``ScanLocaliser.correct`` lifts the frame's points in the obstacle
height band to the floor plane and looks for the small turn and shift of the believed pose
(``MAX_TURN_DEG``, ``MAX_SHIFT_M``: a few times one step's noise) that lays them best on the
points of the frames before it (the mean distance to the nearest one on a ``CELL`` grid, cut
at ``CUT_CELLS``). It takes that correction only when the frame sees enough of the mapped
room (``MIN_POINTS`` cells, ``MIN_NEAR`` of them near mapped points) and the fit beats the
uncorrected pose's by ``MIN_GAIN_CELLS``; the corrections add up. The pitch and the camera's
height are exact, so a point's height does not depend on the correction and the search is
over (turn, x, y) only.

A rearrangement's unshuffle starts at the true start pose: the correction starts again from
nothing, and the map of the walkthrough stays the reference (walls and furniture have not
moved), so both phases' poses agree with one map, which is what comparing their object
memories and putting things back at walkthrough places need.

Everything it reads is the agent's own: the depth images and the reported poses.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from tidee.agent.mapping.geometry import GridSpec, pixel_rays, valid_depth
from tidee.protocol.messages import Observation

MAX_TURN_DEG = 1.5  # the widest turn searched per frame (one turn's noise: 0.5 deg, one sigma)
TURN_STEPS = 13  # turns tried, evenly over [-MAX_TURN_DEG, MAX_TURN_DEG]
MAX_SHIFT_M = 0.05  # the widest shift searched per frame along x and along y
SHIFT_STEPS = 9  # shifts tried per axis
STRIDE = 4  # pixel lattice for the frame's points
CELL = 0.02  # the localiser's own map of the frames so far: finer than the agent's 5 cm
COARSE_CELL = 0.05  # one point of a frame per cell this size...
MAX_POINTS = 600  # ...and at most this many in the fit
MIN_POINTS = 60  # fewer obstacle cells in view: no correction this frame
MIN_NEAR = 0.4  # share of them within NEAR_CELLS of a mapped point, under the best fit
NEAR_CELLS = 2.0  # (cells: 4 cm)
MIN_GAIN_CELLS = 0.1  # the best fit's mean distance must beat the uncorrected one's by this
CUT_CELLS = 10.0  # distances to the nearest mapped obstacle are cut here (cells)
TIE_CELLS = 0.01  # per cell of shift and per turn step: of two fits as good, the smaller correction


def wants_localiser(mode: str, pose_noise: bool) -> bool:
    """Whether the agent corrects its odometry (``AgentConfig.localise``): "scan" always, "auto"
    when the episode has pose noise (the agent asked for a noisy base, so it knows), "off" never."""
    return mode == "scan" or (mode == "auto" and pose_noise)


@dataclasses.dataclass
class Correction:
    """A rigid motion of the floor plane: p -> R(turn) p + shift (start frame)."""

    turn: float = 0.0  # radians
    shift: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))

    def apply_xy(self, xy: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.turn), math.sin(self.turn)
        return np.asarray(xy, dtype=np.float64) @ np.array([[c, s], [-s, c]]) + self.shift

    def matrix(self) -> np.ndarray:
        """The 4x4 start-frame transform (a turn about z, then the shift)."""
        c, s = math.cos(self.turn), math.sin(self.turn)
        t = np.eye(4)
        t[:2, :2] = [[c, -s], [s, c]]
        t[:2, 3] = self.shift
        return t

    def then(self, turn: float, about: np.ndarray, shift: np.ndarray) -> Correction:
        """This correction followed by a turn about the point ``about`` and a shift."""
        return Correction(self.turn + turn, _turned(self.shift, turn, about, shift))


class ScanLocaliser:
    """Keeps the episode's odometry correction (see the module docstring)."""

    def __init__(self, grid: GridSpec, obstacle_z: tuple[float, float], max_depth: float) -> None:
        self.obstacle_z = obstacle_z
        self.max_depth = max_depth
        self.correction = Correction()
        self.applied = 0  # frames whose fit moved the correction
        self._rays: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._origin = np.asarray(grid.origin, dtype=np.float64)
        n = grid.shape
        # over the agent's map's extent, in CELL cells: where the frames so far put band points
        self._map = np.zeros((int(round(n[0] * grid.cell / CELL)), int(round(n[1] * grid.cell / CELL))), bool)

    def new_phase(self) -> None:
        """The agent is back at its true start pose (a rearrangement's unshuffle): no drift
        yet. The map of the walkthrough stays: the room's walls and furniture have not moved,
        and both phases' poses then agree with one map."""
        self.correction = Correction()

    def correct(self, obs: Observation) -> Observation:
        """``obs`` with its poses corrected: the correction so far, refined by this frame's fit
        to the frames before it; the frame then joins the localiser's map."""
        believed = self._corrected(obs)
        pts = self._points(believed)
        step = self._fit(believed, pts)
        if step is not None:
            self.correction = self.correction.then(*step)
            self.applied += 1
            believed = self._corrected(obs)
            pts = _turned(pts, *step)  # the frame's points at the corrected pose
        self._remember(pts)
        return believed

    def _corrected(self, obs: Observation) -> Observation:
        c = self.correction
        if c.turn == 0.0 and not c.shift.any():
            return obs
        x, y, heading, pitch = (float(v) for v in obs.agent_pose)
        cx, cy = c.apply_xy(np.array([x, y]))
        heading = (heading + math.degrees(c.turn) + 180.0) % 360.0 - 180.0
        cam = c.matrix() @ np.asarray(obs.camera_pose, dtype=np.float64)
        return dataclasses.replace(obs, camera_pose=cam, agent_pose=(float(cx), float(cy), heading, pitch))

    def _points(self, obs: Observation) -> np.ndarray:
        """The frame's points in the obstacle band, on the floor plane (start frame, N x 2)."""
        depth = np.asarray(obs.depth)
        k = np.asarray(obs.intrinsics, dtype=np.float64)
        key = (depth.shape, k.tobytes())
        if key not in self._rays:
            self._rays = {key: pixel_rays(depth.shape, k, STRIDE)}
        rays, pix = self._rays[key]
        d = depth.reshape(-1)[pix]
        keep = valid_depth(d, self.max_depth)
        pose = np.asarray(obs.camera_pose, dtype=np.float64)
        pts = (rays[keep] * d[keep, None]) @ pose[:3, :3].T + pose[:3, 3]
        band = (pts[:, 2] >= self.obstacle_z[0]) & (pts[:, 2] < self.obstacle_z[1])
        return pts[band, :2]

    def _fit(self, obs: Observation, pts: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
        """(turn, about, shift) that lays this frame's points ``pts`` best on the localiser's
        map, or None."""
        if not self._map.any():
            return None
        pts = _one_per_cell(pts, self._origin, COARSE_CELL, MAX_POINTS)
        if len(pts) < MIN_POINTS:
            return None
        about = np.array([float(obs.agent_pose[0]), float(obs.agent_pose[1])])
        search = _Search(_distance(self._map), self._origin, CELL)
        turns = np.radians(np.linspace(-MAX_TURN_DEG, MAX_TURN_DEG, TURN_STEPS))
        offs = np.linspace(-MAX_SHIFT_M, MAX_SHIFT_M, SHIFT_STEPS)
        fit, turn, shift, near = search.best(pts, about, turns, offs, offs)
        if near < MIN_NEAR or fit > search.score(pts) - MIN_GAIN_CELLS:
            return None
        return turn, about, shift

    def _remember(self, pts: np.ndarray) -> None:
        """Add a frame's obstacle-band points, at its corrected pose, to the localiser's map."""
        ij = np.floor((pts - self._origin) / CELL).astype(np.int64)
        n = self._map.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < n[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < n[1])
        self._map[ij[inside, 0], ij[inside, 1]] = True


def _turned(pts: np.ndarray, turn: float, about: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Floor-plane points turned by ``turn`` (radians) about ``about``, then shifted."""
    c, s = math.cos(turn), math.sin(turn)
    return (pts - about) @ np.array([[c, s], [-s, c]]) + about + shift


def _one_per_cell(pts: np.ndarray, origin: np.ndarray, cell: float, most: int) -> np.ndarray:
    """One point per floor-plane cell (a near wall fills many pixels of few cells), at most
    ``most`` of them, spread over the frame."""
    ij = np.floor((pts - origin) / cell).astype(np.int64)
    _, first = np.unique(ij[:, 0] * 100_003 + ij[:, 1], return_index=True)
    pts = pts[np.sort(first)]
    if len(pts) > most:
        pts = pts[np.linspace(0, len(pts) - 1, most).astype(np.int64)]
    return pts


def _distance(obstacle: np.ndarray) -> np.ndarray:
    """Cells to the nearest obstacle cell, cut at ``CUT_CELLS`` (float32)."""
    free = np.where(obstacle, 0, 255).astype(np.uint8)
    return np.minimum(cv2.distanceTransform(free, cv2.DIST_L2, 3), CUT_CELLS).astype(np.float32)


@dataclasses.dataclass
class _Search:
    """Scores of a frame's floor-plane points on one distance map."""

    dist: np.ndarray
    origin: np.ndarray
    cell: float

    def _at(self, xy: np.ndarray) -> np.ndarray:
        nx, ny = self.dist.shape
        i = np.clip(np.floor((xy[..., 0] - self.origin[0]) / self.cell).astype(np.int64), 0, nx - 1)
        j = np.clip(np.floor((xy[..., 1] - self.origin[1]) / self.cell).astype(np.int64), 0, ny - 1)
        return self.dist[i, j]

    def score(self, pts: np.ndarray) -> float:
        return float(self._at(pts).mean())

    def best(
        self, pts: np.ndarray, about: np.ndarray, turns: np.ndarray, xs: np.ndarray, ys: np.ndarray
    ) -> tuple[float, float, np.ndarray, float]:
        """(mean distance, turn, shift, share within ``NEAR_CELLS``) of the best turn about ``about``
        and shift over the grid ``turns`` x ``xs`` x ``ys``."""
        shifts = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
        cost = TIE_CELLS * np.abs(shifts).sum(axis=1) / self.cell
        turn_step = float(np.abs(np.diff(turns)).min()) if len(turns) > 1 else 1.0
        best = (np.inf, 0.0, np.zeros(2), 0.0)
        for turn in turns:
            turned = _turned(pts, turn, about, np.zeros(2))
            d = self._at(turned[None, :, :] + shifts[:, None, :])  # shifts x points
            score = d.mean(axis=1) + cost + TIE_CELLS * abs(turn) / turn_step
            k = int(np.argmin(score))
            if score[k] < best[0]:
                best = (float(score[k]), float(turn), shifts[k].copy(), float((d[k] <= NEAR_CELLS).mean()))
        return best
