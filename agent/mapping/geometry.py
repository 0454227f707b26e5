"""Camera geometry and top-down grids.

Frames (see ``protocol/messages.py``):
  * the camera *optical frame* is OpenCV's: x right, y down, z forward, metres;
  * the *start frame* is the agent's pose at reset: x forward, y left, z up, metres,
    origin on the floor under the agent (so the floor is z = 0);
  * ``camera_pose`` is the 4x4 transform optical frame -> start frame, and a pixel
    (u, v) (column, row) with depth d (metres along the optical axis) is the point
    ``camera_pose @ [d (u - cx) / fx, d (v - cy) / fy, d, 1]``.

Grids follow ``MapSnapshot``'s convention: a grid with ``origin`` (x0, y0) and ``cell``
c has cell (i, j) covering [x0 + i c, x0 + (i + 1) c) x [y0 + j c, y0 + (j + 1) c);
axis 0 runs along +x and axis 1 along +y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_DEPTH = 0.05  # metres: depths at or below this are "no return"


def _check_camera(intrinsics: np.ndarray, camera_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = np.asarray(intrinsics, dtype=np.float64)
    t = np.asarray(camera_pose, dtype=np.float64)
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics must be 3x3, got shape {k.shape}")
    if t.shape != (4, 4):
        raise ValueError(f"camera_pose must be 4x4, got shape {t.shape}")
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"intrinsics focal lengths must be > 0, got fx={k[0, 0]}, fy={k[1, 1]}")
    return k, t


def pixel_rays(
    shape: tuple[int, int], intrinsics: np.ndarray, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Optical-frame rays scaled to unit depth for a strided pixel lattice.

    Returns ``(rays, pixel_index)``: rays float64 Nx3 with z = 1 (so depth * ray is the
    optical-frame point), and the flat pixel indices ``v * W + u`` they belong to, in
    row-major order of the lattice ``v = 0, stride, ...``, ``u = 0, stride, ...``.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    h, w = int(shape[0]), int(shape[1])
    k = np.asarray(intrinsics, dtype=np.float64)
    vs = np.arange(0, h, stride)
    us = np.arange(0, w, stride)
    vv, uu = np.meshgrid(vs, us, indexing="ij")
    rays = np.empty((vv.size, 3))
    rays[:, 0] = (uu.ravel() - k[0, 2]) / k[0, 0]
    rays[:, 1] = (vv.ravel() - k[1, 2]) / k[1, 1]
    rays[:, 2] = 1.0
    return rays, (vv * w + uu).ravel()


def start_to_world_xy(start: dict, p) -> np.ndarray:
    """(x, y) in the world of a start-frame point; ``start`` = the episode's start pose
    ``{"x", "y", "yaw_deg"}`` in the world (the server's state)."""
    t = np.radians(float(start["yaw_deg"]))
    c, s = np.cos(t), np.sin(t)
    return np.array([start["x"] + c * p[0] - s * p[1], start["y"] + s * p[0] + c * p[1]])


def valid_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """bool mask of usable depths: finite, > MIN_DEPTH (0.05 m) and <= ``max_depth`` metres."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > MIN_DEPTH) & (depth <= max_depth)


def column_percentiles(points: np.ndarray, lo_q: float, hi_q: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``lo_q`` and ``hi_q`` percentiles (0-100) of each column of an NxD float array:
    the values of ``np.percentile(points, [lo_q, hi_q], axis=0)`` (its default linear method,
    the same rounding) found by one partition of the transposed columns, in about half its
    time for a few thousand points. NaNs are not handled (``np.percentile`` returns NaN)."""
    n = points.shape[0]
    if n == 0:
        raise ValueError("column_percentiles needs at least one point")
    cols = np.ascontiguousarray(points.T)
    picks = []
    for q in (lo_q, hi_q):
        virtual = (q / 100.0) * (n - 1)
        below = int(np.floor(virtual))
        picks.append((below, min(below + 1, n - 1), virtual - below))
    cols.partition(sorted({i for b, a, _ in picks for i in (b, a)}), axis=1)
    out = []
    for below, above, gamma in picks:
        a, b = cols[:, below], cols[:, above]
        diff = b - a
        # numpy's _lerp: from the lower value below the midpoint, from the upper one from it on
        out.append(b - diff * (1.0 - gamma) if gamma >= 0.5 else a + diff * gamma)
    return out[0], out[1]


def unproject(
    depth: np.ndarray,
    intrinsics: np.ndarray,
    camera_pose: np.ndarray,
    stride: int = 1,
    max_depth: float = 10.0,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Lift a depth image to 3D points in the start frame.

    ``depth``: HxW metres along the optical axis (0, negative, inf or nan: no return;
    depths <= 0.05 m or > ``max_depth`` are dropped). ``stride`` keeps every stride-th
    row and column. ``mask`` (bool HxW) optionally restricts the pixels.

    Returns ``(points, pixel_index)``: points float32 Nx3 in the start frame (metres) and
    int64 N flat pixel indices ``v * W + u`` (row v, column u) of the pixels they come from.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be HxW, got shape {depth.shape}")
    if mask is not None and np.shape(mask) != depth.shape:
        raise ValueError(f"mask shape {np.shape(mask)} does not match depth shape {depth.shape}")
    k, t = _check_camera(intrinsics, camera_pose)
    if mask is not None and stride == 1:  # a few pixels of a large image: rays for those alone
        pix = np.flatnonzero(np.asarray(mask, dtype=bool))
        w = depth.shape[1]
        rays = np.empty((pix.size, 3))
        rays[:, 0] = (pix % w - k[0, 2]) / k[0, 0]
        rays[:, 1] = (pix // w - k[1, 2]) / k[1, 1]
        rays[:, 2] = 1.0
    else:
        rays, pix = pixel_rays(depth.shape, k, stride)
    d = depth.ravel()[pix]
    keep = valid_depth(d, max_depth)
    if mask is not None and stride != 1:
        keep &= np.asarray(mask, dtype=bool).ravel()[pix]
    pix = pix[keep]
    cam = rays[keep] * d[keep, None].astype(np.float64)
    points = cam @ t[:3, :3].T + t[:3, 3]
    return points.astype(np.float32), pix


def project(
    points: np.ndarray, intrinsics: np.ndarray, camera_pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project start-frame points (Nx3, metres) into the image.

    Returns float64 arrays ``(u, v, z)``: pixel column, pixel row and depth along the
    optical axis (metres). Points with z <= 0 are behind the camera; their u and v are nan.
    """
    k, t = _check_camera(intrinsics, camera_pose)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rot, trans = t[:3, :3], t[:3, 3]
    # inverse of a rigid transform: R^T (p - t); as row vectors (p - t) @ R
    cam = (p - trans) @ rot
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), np.nan)
    u = k[0, 0] * cam[:, 0] * inv_z + k[0, 2]
    v = k[1, 1] * cam[:, 1] * inv_z + k[1, 2]
    return u, v, z


@dataclass(frozen=True)
class GridSpec:
    """A top-down grid over the start frame's (x, y) plane.

    ``origin`` is the (x, y) corner of cell (0, 0) in metres, ``cell`` the cell edge in
    metres, ``shape`` the number of cells along x (axis 0) and y (axis 1).
    """

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not self.cell > 0:
            raise ValueError(f"GridSpec.cell must be > 0 metres, got {self.cell}")
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise ValueError(f"GridSpec.shape must be two positive ints, got {self.shape}")
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) in metres."""
        x0, y0 = self.origin
        return x0, x0 + self.shape[0] * self.cell, y0, y0 + self.shape[1] * self.cell

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The cells' centres in metres, broadcasting to the grid: x as a column (shape[0] x 1),
        y as a row (1 x shape[1])."""
        x = self.origin[0] + (np.arange(self.shape[0])[:, None] + 0.5) * self.cell
        y = self.origin[1] + (np.arange(self.shape[1])[None, :] + 0.5) * self.cell
        return x, y

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """int64 Nx2 cell indices (i, j) of start-frame points xy (Nx2 or Nx3, metres).

        Points outside the grid get out-of-range indices; check them with ``in_bounds``.
        """
        p = np.asarray(xy, dtype=np.float64)
        if p.ndim == 1:
            p = p[None]
        q = (p[:, :2] - np.asarray(self.origin)) / self.cell
        return np.floor(q).astype(np.int64)

    def flat_index(self, xy: np.ndarray) -> np.ndarray:
        """int64 N: the row-major flat index of the cell holding each start-frame point (Nx2 or
        Nx3, metres), -1 off the grid."""
        ij = self.world_to_cell(xy)
        return np.where(self.in_bounds(ij), ij[:, 0] * self.shape[1] + ij[:, 1], -1)

    @staticmethod
    def centred(size: int = 256, cell: float = 0.05) -> GridSpec:
        """A ``size`` x ``size`` grid of ``cell`` metres centred on the start pose."""
        half = size * cell / 2.0
        return GridSpec((-half, -half), cell, (size, size))

    def to_cell(self, xy) -> tuple[int, int]:
        """Cell (i, j) containing one world point ``xy``; may be out of bounds."""
        i, j = self.world_to_cell(np.asarray(xy, dtype=np.float64)[:2])[0]
        return int(i), int(j)

    def to_world(self, ij) -> tuple[float, float]:
        """World centre (x, y) metres of one cell ``ij``."""
        x, y = self.cell_to_world(np.asarray(ij)[:2])[0]
        return float(x), float(y)

    def cell_to_world(self, ij: np.ndarray) -> np.ndarray:
        """float64 Nx2: the start-frame (x, y) centres of cells ij (Nx2)."""
        c = np.asarray(ij, dtype=np.float64)
        if c.ndim == 1:
            c = c[None]
        return np.asarray(self.origin) + (c + 0.5) * self.cell

    def in_bounds(self, ij: np.ndarray) -> np.ndarray:
        """bool N: whether each cell index (Nx2) lies inside the grid."""
        c = np.asarray(ij)
        if c.ndim == 1:
            c = c[None]
        return (c[:, 0] >= 0) & (c[:, 0] < self.shape[0]) & (c[:, 1] >= 0) & (c[:, 1] < self.shape[1])

    def disc(self, center_xy: tuple[float, float] | np.ndarray, radius: float) -> np.ndarray:
        """int64 Mx2 in-bounds cells whose centres lie within ``radius`` metres of ``center_xy``,
        always including the cell that contains the centre (when it is in bounds)."""
        if radius < 0:
            raise ValueError(f"radius must be >= 0 metres, got {radius}")
        c = np.asarray(center_xy, dtype=np.float64).reshape(-1)[:2]
        centre_cell = self.world_to_cell(c)[0]
        r = int(np.ceil(radius / self.cell)) + 1
        di, dj = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
        cells = np.stack([di.ravel(), dj.ravel()], axis=1) + centre_cell
        d2 = ((self.cell_to_world(cells) - c) ** 2).sum(axis=1)
        keep = (d2 <= radius * radius) | ((cells == centre_cell).all(axis=1))
        cells = cells[keep]
        return cells[self.in_bounds(cells)]
