"""Telemetry -> 3D geometry for the scene: boxes, polylines, frusta, floor planes, camera.

Everything is in the episode's start frame (x forward, y left, z up, metres), which is
also the viewer's world frame (viser is told +z is up). Pure numpy; no viser.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

# The 12 edges of a box whose 8 corners are indexed by bits (x: 1, y: 2, z: 4) of
# the corner number: corner k takes max along an axis where its bit is set.
BOX_EDGES = np.array([(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit], dtype=np.int64)
_CORNER_BITS = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], dtype=bool)


def box_corners(box_min: Sequence[float], box_max: Sequence[float]) -> np.ndarray:
    """``8x3`` corners of an axis-aligned box; corner k has bit a set where it takes max on axis a."""
    lo, hi = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,):
        raise ValueError(f"box_min and box_max must be 3 numbers each, got {lo.shape} and {hi.shape}")
    return np.where(_CORNER_BITS, hi, lo)


def boxes_segments(box_mins: np.ndarray, box_maxs: np.ndarray) -> np.ndarray:
    """``(12 N)x2x3`` wireframe segments of N axis-aligned boxes (N x 3 mins and maxes)."""
    lo = np.asarray(box_mins, np.float32).reshape(-1, 3)
    hi = np.asarray(box_maxs, np.float32).reshape(-1, 3)
    if lo.shape != hi.shape:
        raise ValueError(f"box mins and maxes differ in shape: {lo.shape} vs {hi.shape}")
    corners = np.where(_CORNER_BITS[None], hi[:, None, :], lo[:, None, :])  # N x 8 x 3
    return corners[:, BOX_EDGES].reshape(-1, 2, 3)


def oriented_box_segments(center: Sequence[float], size: Sequence[float], rotation: np.ndarray) -> np.ndarray:
    """``12x2x3`` segments of a box of ``size`` centred at ``center``, rotated by ``rotation`` (3x3)."""
    half = np.asarray(size, np.float64) / 2.0
    local = np.where(_CORNER_BITS, half, -half)
    corners = local @ np.asarray(rotation, np.float64).T + np.asarray(center, np.float64)
    return corners[BOX_EDGES].astype(np.float32)


def polyline_segments(points: np.ndarray | None, z: float = 0.02) -> np.ndarray:
    """``(N-1)x2x3`` segments joining N points (``Nx2`` at height ``z``, or ``Nx3``)."""
    if points is None:
        return np.zeros((0, 2, 3), np.float32)
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise ValueError(f"a polyline must be Nx2 or Nx3, got shape {pts.shape}")
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.full((len(pts), 1), z, np.float32)], axis=1)
    if len(pts) < 2:
        return np.zeros((0, 2, 3), np.float32)
    return np.stack([pts[:-1], pts[1:]], axis=1)


def rotation_to_wxyz(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix (Shepperd's method, stable)."""
    m = np.asarray(rotation, np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"a rotation must be 3x3, got {m.shape}")
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    arr = np.asarray(q)
    arr /= np.linalg.norm(arr)
    if arr[0] < 0:
        arr = -arr
    return float(arr[0]), float(arr[1]), float(arr[2]), float(arr[3])


def quat_xyzw_to_matrix(q: Sequence[float]) -> np.ndarray:
    """3x3 rotation of a quaternion given as (x, y, z, w) (PyBullet's and the scene export's order)."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n == 0:
        raise ValueError("a zero quaternion is not a rotation")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class Frustum:
    """What viser's camera frustum needs: vertical fov (rad), aspect (w/h), pose in the world."""

    fov: float
    aspect: float
    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]


def frustum(camera_pose: np.ndarray, intrinsics: np.ndarray, width: int, height: int) -> Frustum:
    """A frustum from an OpenCV camera (optical frame -> start frame pose, 3x3 intrinsics).

    viser's frusta use the OpenCV convention too, so the pose's rotation is used as is.
    """
    pose, k = np.asarray(camera_pose, np.float64), np.asarray(intrinsics, np.float64)
    if pose.shape != (4, 4) or k.shape != (3, 3):
        raise ValueError(f"camera_pose must be 4x4 and intrinsics 3x3, got {pose.shape} and {k.shape}")
    if width <= 0 or height <= 0 or k[1, 1] <= 0:
        raise ValueError(f"need a positive image size and focal length, got {width}x{height}, fy={k[1, 1]}")
    fov = 2.0 * math.atan(height / (2.0 * k[1, 1]))
    pos = pose[:3, 3]
    return Frustum(
        fov, width / height, rotation_to_wxyz(pose[:3, :3]), (float(pos[0]), float(pos[1]), float(pos[2]))
    )


def camera_pose_from_agent(x: float, y: float, yaw_deg: float, pitch_deg: float, height: float) -> np.ndarray:
    """4x4 optical (x right, y down, z forward) -> start frame, for a camera at (x, y, height)
    looking along ``yaw_deg`` (counter-clockwise from +x) and pitched *down* by ``pitch_deg``."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = (
        right,
        np.cross(forward, right),
        forward,
        (x, y, height),
    )
    return pose


def start_from_world(start_x: float, start_y: float, start_yaw_deg: float) -> np.ndarray:
    """4x4 transform from the world frame to the episode start frame (a yaw about z plus a shift)."""
    yaw = math.radians(start_yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    t = np.eye(4)
    rot: list[list[float]] = [[c, s, 0], [-s, c, 0], [0, 0, 1]]  # R(-yaw)
    t[:3, :3] = rot
    t[:3, 3] = t[:3, :3] @ np.array([-start_x, -start_y, 0.0])
    return t


@dataclass(frozen=True)
class FloorPlane:
    """Where a top-down grid lies on the floor: its centre and its extent along x and y."""

    center: tuple[float, float, float]
    size_x: float
    size_y: float


def grid_plane(origin: Sequence[float], cell: float, shape: tuple[int, ...], z: float = 0.01) -> FloorPlane:
    """The floor rectangle a top-down grid (axis 0 along +x, axis 1 along +y) covers."""
    if cell <= 0 or len(shape) < 2 or shape[0] <= 0 or shape[1] <= 0:
        raise ValueError(f"need a positive cell and a non-empty 2D grid, got cell={cell}, shape={shape}")
    sx, sy = shape[0] * cell, shape[1] * cell
    return FloorPlane((float(origin[0]) + sx / 2.0, float(origin[1]) + sy / 2.0, z), sx, sy)


def known_plane(
    origin: Sequence[float], cell: float, occupancy: np.ndarray, margin: float = 0.5, z: float = 0.01
) -> FloorPlane | None:
    """The floor rectangle around a grid's known cells (occupancy > 0), ``margin`` metres
    wider on each side; None when nothing is known yet."""
    known = np.argwhere(np.asarray(occupancy) > 0)
    if known.size == 0 or cell <= 0:
        return None
    lo = np.asarray(origin[:2], float) + known.min(axis=0) * cell - margin
    hi = np.asarray(origin[:2], float) + (known.max(axis=0) + 1) * cell + margin
    return FloorPlane(
        (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, z), float(hi[0] - lo[0]), float(hi[1] - lo[1])
    )


@dataclass(frozen=True)
class CameraView:
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]


def overview_camera(plane: FloorPlane) -> CameraView:
    """A view a person can read at once: from behind the start pose (-x), a little to the
    right (-y), about 65 degrees above the floor (the floor layers, heatmap and paths, show
    between the walls), far enough to see the whole map, looking at its centre."""
    cx, cy, _ = plane.center
    extent = max(plane.size_x, plane.size_y, 2.0)
    return CameraView((cx - 0.55 * extent, cy - 0.35 * extent, 1.4 * extent), (cx, cy, 0.0))


# --- screen-sized labels ----------------------------------------------------------------------


@dataclass(frozen=True)
class ScreenView:
    """A pinhole camera, enough to lay out labels drawn at a fixed screen size: its
    position, its OpenCV axes in the world (columns: right, down, forward) and its focal
    length in pixels."""

    position: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...]  # 3x3 rows of the rotation matrix
    focal_px: float

    def rotation(self) -> np.ndarray:
        return np.asarray(self.axes, np.float64)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Nx2`` pixel offsets from the image centre (x right, y down) and ``N`` depths."""
        cam = (np.asarray(points, np.float64).reshape(-1, 3) - np.asarray(self.position)) @ self.rotation()
        depth = cam[:, 2]
        safe = np.where(depth > 1e-6, depth, 1e-6)
        return cam[:, :2] * (self.focal_px / safe)[:, None], depth


def screen_view(
    position: Sequence[float], wxyz: Sequence[float], fov_y: float, image_height: int
) -> ScreenView:
    """The view of a viser client camera (its ``position``, ``wxyz``, vertical ``fov`` and canvas height)."""
    if not 0 < fov_y < math.pi or image_height <= 0:
        raise ValueError(
            f"need a vertical fov in (0, pi) and a positive image height, got {fov_y}, {image_height}"
        )
    w, x, y, z = (float(v) for v in wxyz)
    rot = quat_xyzw_to_matrix((x, y, z, w))
    return ScreenView(
        cast("tuple[float, float, float]", tuple(float(v) for v in position)),
        tuple(cast("tuple[float, float, float]", tuple(float(v) for v in row)) for row in rot),
        image_height / (2.0 * math.tan(fov_y / 2.0)),
    )


def screen_view_looking_at(
    view: CameraView, fov_y: float, image_height: int, up: Sequence[float] = (0.0, 0.0, 1.0)
) -> ScreenView:
    """The view of a camera at ``view.position`` looking at ``view.look_at`` with ``up`` up
    (the page's initial camera, before any client has reported its own)."""
    eye, target = np.asarray(view.position, np.float64), np.asarray(view.look_at, np.float64)
    forward = target - eye
    if np.linalg.norm(forward) < 1e-9:
        raise ValueError("the camera's position and look_at coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: any right will do
        right = np.cross(forward, (1.0, 0.0, 0.0))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward], axis=1)
    return screen_view(view.position, rotation_to_wxyz(rot), fov_y, image_height)


def place_labels(
    anchors: np.ndarray, sizes_px: np.ndarray, view: ScreenView, gap_px: float = 3.0
) -> np.ndarray:
    """Where to draw labels so that none overlaps another on screen: ``Nx3`` world positions.

    ``anchors`` (``Nx3``, in priority order) are the points the labels belong to; each label is
    a box of ``sizes_px`` (``Nx2``: width, height in pixels) drawn above its point (anchored
    bottom-centre). Greedy and deterministic: in order, a label stays on its point unless its
    box comes within ``gap_px`` of one already placed; then it is lifted, on screen, to just
    above the highest box it meets, until it meets none. The lift goes back into the world at
    the anchor's depth along the camera's up axis, so for this view the label lands on that
    screen spot. Labels behind the camera stay on their points.
    """
    pts = np.asarray(anchors, np.float64).reshape(-1, 3)
    sizes = np.asarray(sizes_px, np.float64).reshape(-1, 2)
    if len(sizes) != len(pts):
        raise ValueError(f"need one size per anchor, got {len(sizes)} sizes for {len(pts)} anchors")
    uv, depth = view.project(pts)
    out = pts.copy()
    placed = label_boxes(uv[:0], sizes[:0])
    up_world = -view.rotation()[:, 1]
    for i in range(len(pts)):
        if depth[i] <= 1e-6:
            continue
        (w, h), (u, v) = sizes[i], uv[i]
        x0, x1, bottom = u - w / 2, u + w / 2, v
        while True:
            hits = placed[
                (placed[:, 0] < x1 + gap_px)
                & (x0 - gap_px < placed[:, 2])
                & (placed[:, 1] < bottom + gap_px)
                & (bottom - h - gap_px < placed[:, 3])
            ]
            if not len(hits):
                break
            bottom = float(hits[:, 1].min()) - gap_px  # just above the highest box it meets
        placed = np.vstack([placed, (x0, bottom - h, x1, bottom)])
        out[i] = pts[i] + up_world * ((v - bottom) * depth[i] / view.focal_px)
    return out


def label_boxes(uv: np.ndarray, sizes_px: np.ndarray) -> np.ndarray:
    """``Nx4`` screen boxes (x0, y0, x1, y1; y down) of labels anchored bottom-centre at ``uv``."""
    uv, sizes = np.asarray(uv, np.float64).reshape(-1, 2), np.asarray(sizes_px, np.float64).reshape(-1, 2)
    return np.stack(
        [uv[:, 0] - sizes[:, 0] / 2, uv[:, 1] - sizes[:, 1], uv[:, 0] + sizes[:, 0] / 2, uv[:, 1]], axis=1
    )


def unproject_depth(
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
    stride: int = 1,
    max_depth: float = 6.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Start-frame points of a depth image (every ``stride``-th pixel with depth in
    (0, ``max_depth``]): ``Nx3`` float32 points and the ``Nx2`` (row, column) of their pixels.
    ``camera_pose`` maps the optical frame to the start frame (protocol/messages.py)."""
    d = np.asarray(depth, np.float32)
    k, pose = np.asarray(intrinsics, np.float64), np.asarray(camera_pose, np.float64)
    if d.ndim != 2 or k.shape != (3, 3) or pose.shape != (4, 4):
        raise ValueError(
            f"need an HxW depth, 3x3 intrinsics and a 4x4 pose, got {d.shape}, {k.shape}, {pose.shape}"
        )
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    rows, cols = np.mgrid[0 : d.shape[0] : stride, 0 : d.shape[1] : stride]
    z = d[rows, cols]
    valid = np.isfinite(z) & (z > 0) & (z <= max_depth)
    rows, cols, z = rows[valid], cols[valid], z[valid].astype(np.float64)
    x = (cols - k[0, 2]) * z / k[0, 0]  # pixel (u, v) -> d (u - cx) / fx: the protocol's convention
    y = (rows - k[1, 2]) * z / k[1, 1]
    pts = np.stack([x, y, z], axis=1) @ pose[:3, :3].T + pose[:3, 3]
    return pts.astype(np.float32), np.stack([rows, cols], axis=1)
