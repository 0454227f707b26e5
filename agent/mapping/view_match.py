"""Where an object seen in an earlier frame lies now, from a frame taken from the same pose.

A view of an object keeps its points (start frame) and their colours. A later frame from the
same pose (the agent moves on a lattice from one start pose, so a pose recurs exactly) shows
the object wherever it lies now; the turn about its middle and the shift over the floor under
which the remembered points, projected into the new frame, land on the same colours at the
same depth say how far it is from where it lay. Both frames see the object alike, so the
errors of depth, masks and footprints that make a place estimated from other views a few
centimetres off cancel: only the object's own move shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tidee.agent.mapping.geometry import project, unproject

MAX_POINTS = 400  # a view keeps at most this many of its points (evenly spaced)
SEARCH_M = 0.12  # shifts tried, each way (x and y)
RIM_QUANT_RGB = 4.0  # the colours round a region's box, rounded to this (RGB 0-255) ...
RIM_GAP_RGB = 24.0  # ... a pixel differing from each by this much in some channel is the object's ...
FOREGROUND_SHARE = 0.15  # ... when at least this share of the region's pixels are
# the search, coarse to fine: (turn step, turns each way of the last best (the first stage: all
# round), shift step, shifts each way of the last best, points tried), degrees and metres
STAGES = (
    (10.0, 180.0, 0.015, SEARCH_M, 100),
    (2.0, 10.0, 0.005, 0.015, 200),
    (0.5, 2.0, 0.00125, 0.005, MAX_POINTS),
)
COLOUR_SCALE = 64.0  # mean absolute RGB difference (0-255) at which a point's colour misfit is full
DEPTH_SCALE_M = 0.03  # depth difference at which its depth misfit is full
GRIP_MISFIT = 0.2  # a point this well fitted is on the object (``grip_pixel``)
PRIOR = 0.01  # misfit added for the largest turn (180 degrees) and, again, for the largest shift


@dataclass(frozen=True)
class ObjectView:
    """One frame's view of an object: the agent's pose (x, y, yaw and pitch in degrees, start
    frame), and the object's points (Nx3, start frame) with their colours (Nx3, RGB 0-255)."""

    pose: tuple[float, float, float, float]
    points: np.ndarray
    colours: np.ndarray

    def within(self, box_min: np.ndarray, box_max: np.ndarray, margin: float, above: float) -> ObjectView:
        """The points inside the box grown by ``margin`` and ``above`` over its base (a box
        mask's pixels of the wall behind the object or the surface under it are not it)."""
        p = self.points
        keep = np.all((p >= box_min - margin) & (p <= box_max + margin), axis=1) & (
            p[:, 2] >= box_min[2] + above
        )
        return ObjectView(self.pose, p[keep], self.colours[keep])

    @property
    def centre(self) -> np.ndarray:
        """The middle (x, y) its points turn about."""
        return self.points[:, :2].mean(axis=0)


@dataclass(frozen=True)
class FrameCrop:
    """The part of a frame round an object's region, kept as it was seen: the view is made
    from it only when wanted (``view``), so a walk keeps every frame's objects cheaply."""

    pose: tuple[float, float, float, float]
    rgb: np.ndarray
    depth: np.ndarray
    region: np.ndarray
    intrinsics: np.ndarray  # of the crop: the principal point moved with its corner
    camera_pose: np.ndarray

    @staticmethod
    def of(
        rgb: np.ndarray,
        depth: np.ndarray,
        intrinsics: np.ndarray,
        camera_pose: np.ndarray,
        region: np.ndarray,
        pose: tuple[float, float, float, float],
    ) -> FrameCrop | None:
        """The crop of a frame round ``region`` (bool HxW); None when it is empty."""
        rows, cols = np.nonzero(region)
        if len(rows) == 0:
            return None
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        k = np.array(intrinsics, dtype=np.float64, copy=True)
        k[0, 2] -= c0
        k[1, 2] -= r0
        return FrameCrop(
            tuple(float(v) for v in pose),  # type: ignore[arg-type]
            np.array(np.asarray(rgb)[r0:r1, c0:c1]),
            np.array(np.asarray(depth)[r0:r1, c0:c1]),
            np.array(np.asarray(region)[r0:r1, c0:c1]),
            k,
            np.array(camera_pose, dtype=np.float64, copy=True),
        )

    def view(self) -> ObjectView | None:
        """The view of the object: the region's pixels unlike the colours round its rim
        (``foreground``); None when no pixel has depth."""
        pts, pix = unproject(
            self.depth, self.intrinsics, self.camera_pose, mask=foreground(self.rgb, self.region)
        )
        if len(pts) == 0:
            return None
        keep = _evenly(len(pts), MAX_POINTS)
        colours = np.asarray(self.rgb).reshape(-1, 3)[pix[keep]].astype(np.float32)
        return ObjectView(self.pose, pts[keep].astype(np.float64), colours)


def foreground(rgb: np.ndarray, region: np.ndarray) -> np.ndarray:
    """The pixels of ``region`` whose colour is unlike every colour on the rim of its
    bounding box (the table top round a phone lying on it, the wall behind a vase): the
    object's own. ``region`` itself when that leaves fewer than ``FOREGROUND_SHARE`` of it
    (an object that fills its box, or one coloured like what it stands on)."""
    rows, cols = np.nonzero(region)
    if len(rows) == 0:
        return region
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    box = np.asarray(rgb)[r0 : r1 + 1, c0 : c1 + 1].astype(np.float32)
    rim = np.concatenate([box[0], box[-1], box[:, 0], box[:, -1]])
    palette = np.unique(np.round(rim / RIM_QUANT_RGB), axis=0) * RIM_QUANT_RGB
    inside = region[r0 : r1 + 1, c0 : c1 + 1]
    pixels = box[inside]
    far = np.ones(len(pixels), bool)
    for k in range(0, len(palette), 64):
        gap = np.abs(pixels[:, None, :] - palette[None, k : k + 64, :]).max(axis=2)
        far &= gap.min(axis=1) > RIM_GAP_RGB
    if far.sum() < FOREGROUND_SHARE * len(pixels):
        return region
    keep = np.zeros_like(region)
    sub = np.zeros(inside.shape, bool)
    sub[inside] = far
    keep[r0 : r1 + 1, c0 : c1 + 1] = sub
    return keep


@dataclass(frozen=True)
class ViewMatch:
    """How the object lies now against the view: ``shift`` (x, y metres) and ``turn_deg``
    (counter-clockwise, about ``ObjectView.centre``, [-180, 180)); ``misfit`` is the best
    hypothesis's mean point misfit (0: every point on its colour at its depth; 1: none),
    ``still_misfit`` the same for no shift and no turn, ``seen`` the share of points that land
    in the frame in front of what it shows there."""

    shift: np.ndarray
    turn_deg: float
    misfit: float
    still_misfit: float
    seen: float

    def moved_to(self, centre: np.ndarray, point: np.ndarray) -> np.ndarray:
        """Where ``point`` (x, y) of the object as the view saw it lies now (``centre``: the
        view's, the turn's pivot)."""
        return turned(point[None, :2] - centre, self.turn_deg)[0] + centre + self.shift

    def moved_from(self, centre: np.ndarray, point: np.ndarray) -> np.ndarray:
        """Where the view saw the part of the object that lies at ``point`` (x, y) now: a put
        that landed the object at a point lands it on the view's place when aimed here."""
        return turned(point[None, :2] - self.shift - centre, -self.turn_deg)[0] + centre


def turned(xy: np.ndarray, deg: float) -> np.ndarray:
    """Points (Nx2) turned counter-clockwise by ``deg`` about the origin."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return xy @ np.array([[c, s], [-s, c]])


def _point_misfits(
    points: np.ndarray,
    colours: np.ndarray,
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each point's misfit in the frame (0: on its colour at its depth; 1: out of the frame,
    behind something nearer, or nothing alike), whether it lies in front of what the frame
    shows, and its pixel (u, v). ``points`` Mx3, ``colours`` Mx3."""
    h, w = depth.shape
    u, v, d = project(points, intrinsics, camera_pose)
    with np.errstate(invalid="ignore"):
        inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1) & (d > 0)
    u, v = np.where(inside, u, 0.0), np.where(inside, v, 0.0)
    # bilinear: the misfit then changes smoothly with a shift of a fraction of a pixel
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    corners = (
        (v0, u0, (1 - fu) * (1 - fv)),
        (v0, u0 + 1, fu * (1 - fv)),
        (v0 + 1, u0, (1 - fu) * fv),
        (v0 + 1, u0 + 1, fu * fv),
    )
    shown = sum(depth[a, b] * wt[:, 0] for a, b, wt in corners)
    seen_rgb = sum(rgb[a, b] * wt for a, b, wt in corners)
    gap = np.abs(shown - d)
    colour = np.abs(seen_rgb - colours).mean(axis=1)
    m = 0.5 * np.minimum(colour / COLOUR_SCALE, 1.0) + 0.5 * np.minimum(gap / DEPTH_SCALE_M, 1.0)
    front = inside & (shown > d - DEPTH_SCALE_M)
    return np.where(front, m, 1.0), front, u, v


def _moved(view: ObjectView, turn_deg: float, shifts: np.ndarray) -> np.ndarray:
    """The view's points turned about its centre and shifted by each of ``shifts``: SxNx3."""
    centre = view.centre
    xy = turned(view.points[:, :2] - centre, turn_deg) + centre
    moved = np.empty((len(shifts), len(xy), 3))
    moved[..., :2] = xy[None] + shifts[:, None, :]
    moved[..., 2] = view.points[None, :, 2]
    return moved


def _misfits(
    view: ObjectView,
    turns: np.ndarray,
    shifts: np.ndarray,
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(mean misfit, share seen), each (len(turns), len(shifts)), of the view's points turned
    about its centre and shifted (x, y), projected into the frame."""
    cost = np.empty((len(turns), len(shifts)))
    seen = np.empty_like(cost)
    colours = np.tile(view.colours, (len(shifts), 1))
    for i, deg in enumerate(turns):
        moved = _moved(view, float(deg), shifts).reshape(-1, 3)
        m, front, _, _ = _point_misfits(moved, colours, rgb, depth, intrinsics, camera_pose)
        cost[i] = m.reshape(len(shifts), -1).mean(axis=1)
        seen[i] = front.reshape(len(shifts), -1).mean(axis=1)
    size = np.hypot(shifts[:, 0], shifts[:, 1]) / (SEARCH_M * math.sqrt(2))
    cost += PRIOR * (np.abs(turns)[:, None] / 180.0 + size[None, :])
    return cost, seen


def grip_pixel(
    view: ObjectView,
    match: ViewMatch,
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
) -> tuple[int, int] | None:
    """A pixel (u, v) on the object where ``match`` says it lies: of the view's points, moved
    so, those that fit the frame (misfit under ``GRIP_MISFIT``), the one nearest their middle;
    None when none fits. A thin thing's top, projected alone, can miss it and hit the wall."""
    moved = _moved(view, match.turn_deg, match.shift[None, :])[0]
    rgb, depth = _as_frame(rgb, depth)
    m, _, u, v = _point_misfits(moved, view.colours, rgb, depth, intrinsics, camera_pose)
    fit = m < GRIP_MISFIT
    if not fit.any():
        return None
    uu, vv = u[fit], v[fit]
    k = int(np.argmin(np.hypot(uu - np.median(uu), vv - np.median(vv))))
    return int(round(float(uu[k]))), int(round(float(vv[k])))


def _as_frame(rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A frame as the misfits read it: RGB as float, depth with no return as 0."""
    return np.asarray(rgb, dtype=np.float32), np.nan_to_num(
        np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0
    )


def _evenly(n: int, most: int) -> np.ndarray:
    """Indices of at most ``most`` of ``n`` items, evenly spaced."""
    return np.linspace(0, n - 1, min(n, most)).round().astype(int)


def _grid(step: float, half: float) -> np.ndarray:
    n = int(round(half / step))
    a = np.arange(-n, n + 1) * step
    return np.stack(np.meshgrid(a, a, indexing="ij"), axis=-1).reshape(-1, 2)


def match_view(
    view: ObjectView,
    rgb: np.ndarray,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
) -> ViewMatch:
    """The turn and shift that best carry ``view``'s points onto the frame (``rgb`` HxWx3,
    ``depth`` HxW metres, taken from the view's pose): turns all round, shifts within
    ``SEARCH_M``, searched coarse to fine (``STAGES``)."""
    rgb, depth = _as_frame(rgb, depth)
    best_turn, best_shift = 0.0, np.zeros(2)
    for k, (turn_step, turn_half, shift_step, shift_half, points) in enumerate(STAGES):
        few = _evenly(len(view.points), points)
        part = ObjectView(view.pose, view.points[few], view.colours[few])
        if k == 0:
            turns = np.arange(-180.0, 180.0, turn_step)
        else:
            turns = best_turn + np.arange(-turn_half, turn_half + 1e-9, turn_step)
        shifts = best_shift + _grid(shift_step, shift_half)
        cost, seen = _misfits(part, turns, shifts, rgb, depth, intrinsics, camera_pose)
        i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
        best_turn, best_shift = float(turns[i]), shifts[j].copy()
    still, _ = _misfits(view, np.zeros(1), np.zeros((1, 2)), rgb, depth, intrinsics, camera_pose)
    turn = (best_turn + 180.0) % 360.0 - 180.0
    return ViewMatch(best_shift, turn, float(cost[i, j]), float(still[0, 0]), float(seen[i, j]))
