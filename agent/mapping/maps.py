"""Semantic mapping: a 2D navigation map, a labelled voxel map and the object memory.

Everything lives in the episode's *start frame* (x forward, y left, z up, metres, the
floor at z = 0). The maps are square, ``map_size_m`` on a side and centred on the start
pose; 2D grids and the voxel grid's (x, y) axes follow ``MapSnapshot``'s convention
(see ``geometry.GridSpec``): axis 0 along +x, axis 1 along +y, cell (0, 0) at the
(-x, -y) corner. The voxel grid's axis 2 runs along +z from ``voxel_z_range[0]``.

Per frame (``SemanticMapper.update``) the depth image is lifted to points (every
``stride``-th pixel) and accumulated:
  * voxel occupancy (any point in the voxel, ever) and a voxel label grid (the class of
    the last detection whose pixels hit the voxel, -1 for none);
  * 2D maps at ``nav_cell``: ``obstacle`` (a point in the ``obstacle_z`` height band),
    ``floor_seen`` (a point below ``floor_z``), ``seen_count`` (frames that put a point
    in the cell) and ``explored`` (``seen_count >= explored_threshold``);
  * with ``carve`` (noisy depth, such as estimated from RGB), an obstacle cell is taken away
    again once as many frames' rays have passed through it as frames put a point in it
    (counted per ``carve_z`` slab of the band; ``carve_min_hits`` frames make an obstacle);
  * the cells around each believed agent position (radius ``agent_free_radius``) are
    free: the agent stood there;
  * points inside the pixels of a detection whose class is ``passable`` (the small
    objects the body pushes past, not furniture) are mapped but never obstacles: a pen or
    a dumbbell on the floor, or one the agent just put down at its feet, must not wall it in.
Each detection becomes a 3D centroid (the point of the region's median-depth pixel, as
in the paper) and box (5th-95th percentiles of the region's points) merged into the
``ObjectMemory``.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from tidee.agent.mapping.config import MapConfig
from tidee.agent.mapping.geometry import GridSpec, column_percentiles, pixel_rays, valid_depth
from tidee.agent.mapping.memory import ObjectMemory, TrackedObject
from tidee.agent.perception.base import Detection
from tidee.protocol.messages import MapSnapshot, Observation

UNKNOWN, FREE, OBSTACLE = 0, 1, 2  # occupancy_grid values (as MapSnapshot)
_GAUSS_TRUNCATE = 4.0  # scipy's default: kernels reach 4 sigma


def _disk_kernel(radius: float, cell: float) -> np.ndarray:
    """uint8 (2r+1)^2 kernel: cells whose centres lie within ``radius`` metres of the centre."""
    r = int(math.floor(radius / cell + 1e-9))
    d = np.arange(-r, r + 1)
    return ((d[:, None] ** 2 + d[None, :] ** 2) * cell * cell <= radius * radius + 1e-12).astype(np.uint8)


def _gauss_peak(sigma: float) -> float:
    """The centre weight of scipy's normalised 1D Gaussian kernel (1 for sigma 0)."""
    if sigma <= 0:
        return 1.0
    r = int(_GAUSS_TRUNCATE * sigma + 0.5)
    x = np.arange(-r, r + 1)
    return float(1.0 / np.exp(-0.5 * (x / sigma) ** 2).sum())


@dataclass
class _ObjectStats:
    centroid: np.ndarray  # float64 3
    box_min: np.ndarray
    box_max: np.ndarray


def _count_once(counts: np.ndarray, flat: np.ndarray) -> None:
    """Add 1 (saturating) to each of ``counts``' cells named in the flat indices ``flat``, once
    however often it is named (-1: none): a frame counts once per cell."""
    once = np.zeros(counts.size, bool)
    once[flat[flat >= 0]] = True
    c = counts.reshape(-1)
    c += once & (c < np.iinfo(counts.dtype).max)


class SemanticMapper:
    """Accumulates observations into 2D/3D maps and the object memory (start frame, metres).

    ``classes``: the label vocabulary; a detection's voxel label and semantic channel is
    ``classes.index(label)``. Detections with labels outside ``classes`` are still tracked
    in the memory but label no voxels.

    The array attributes (``obstacle``, ``floor_seen``, ``seen_count``, ``occupancy``,
    ``voxel_labels``, ...) are the live maps: read them, do not write them.

    ``passable``: labels whose detected pixels never mark obstacles (the agent passes them:
    the pickupable classes, whose objects do not block the body's moves).
    """

    def __init__(
        self, config: MapConfig | None = None, classes: Sequence[str] = (), passable: Collection[str] = ()
    ) -> None:
        self.config = config if config is not None else MapConfig()
        self.classes = list(classes)
        self.passable = frozenset(passable)
        if len(set(self.classes)) != len(self.classes):
            dup = sorted({c for c in self.classes if self.classes.count(c) > 1})
            raise ValueError(f"classes must be unique; repeated: {dup}")
        self._class_index = {c: i for i, c in enumerate(self.classes)}
        if len(self.classes) > np.iinfo(np.int16).max:
            raise ValueError(f"at most {np.iinfo(np.int16).max} classes fit the int16 label grid")
        cfg = self.config
        half = cfg.map_size_m / 2
        self.grid = GridSpec((-half, -half), cfg.nav_cell, cfg.nav_shape)
        self.voxel_grid = GridSpec((-half, -half), cfg.voxel_xy, cfg.voxel_shape[:2])
        self.voxel_shape = cfg.voxel_shape
        small = (
            {} if cfg.small_merge_distance is None else dict.fromkeys(self.passable, cfg.small_merge_distance)
        )
        self.memory = ObjectMemory(cfg.merge_distance, cfg.box_merge, small)
        self._rays: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget every map and the object memory (a new episode)."""
        nx, ny = self.grid.shape
        self.obstacle = np.zeros((nx, ny), bool)
        cfg = self.config
        nz = int(math.ceil((cfg.obstacle_z[1] - cfg.obstacle_z[0]) / cfg.carve_z - 1e-9)) if cfg.carve else 0
        self.hit_frames = np.zeros((nx, ny, nz), np.uint16)  # carving: frames with a point in the slab
        self.pass_frames = np.zeros((nx, ny, nz), np.uint16)  # carving: frames whose rays crossed it
        self.stamped = np.zeros((nx, ny), bool)  # carving: obstacles stamped by a blocked move
        self.floor_seen = np.zeros((nx, ny), bool)
        self.seen_count = np.zeros((nx, ny), np.uint16)
        self.visited = np.zeros((nx, ny), bool)  # discs around believed agent positions
        self.stood = np.zeros((nx, ny), bool)  # cells the agent's centre has been in
        self.occupancy = np.zeros(self.voxel_shape, bool)
        self.voxel_labels = np.full(self.voxel_shape, -1, np.int16)
        self.memory.clear()
        self.last_track_ids: list[int | None] = []  # per detection of the last update
        self.steps = 0

    @property
    def explored(self) -> np.ndarray:
        """bool XxY: cells that received points in at least ``explored_threshold`` frames."""
        return self.seen_count >= self.config.explored_threshold

    # ------------------------------------------------------------------ update
    def update(self, obs: Observation, detections: Sequence[Detection] = ()) -> list[TrackedObject]:
        """Fold one observation and its detections into the maps and the memory.

        Returns the memory entries touched this frame (each once, in detection order);
        ``last_track_ids`` gives, per detection, the id it merged into (None if skipped).
        """
        cfg = self.config
        depth = np.asarray(obs.depth)
        if depth.ndim != 2:
            raise ValueError(f"Observation.depth must be HxW, got shape {depth.shape}")
        h, w = depth.shape
        k = np.asarray(obs.intrinsics, dtype=np.float64)
        pose = np.asarray(obs.camera_pose, dtype=np.float64)
        if k.shape != (3, 3) or pose.shape != (4, 4):
            raise ValueError(
                f"Observation needs 3x3 intrinsics and a 4x4 camera_pose, got {k.shape} and {pose.shape}"
            )
        rot, trans = pose[:3, :3], pose[:3, 3]
        depth_flat = depth.reshape(-1)

        rays, pix = self._lattice((h, w), k, int(cfg.stride))
        d = depth_flat[pix]
        keep = valid_depth(d, cfg.max_depth)
        pix = pix[keep]
        pts = (rays[keep] * d[keep, None]) @ rot.T + trans  # float64 Nx3, start frame

        regions = []
        for det in detections:
            region = np.asarray(det.region((h, w)), dtype=bool)
            if region.shape != (h, w):
                raise ValueError(
                    f"detection {det.label!r}: region shape {region.shape} does not "
                    f"match the depth image {(h, w)}"
                )
            regions.append(region.reshape(-1))
        passable = np.zeros(pix.shape[0], bool)
        for det, region_flat in zip(detections, regions):
            if det.label in self.passable:
                passable |= region_flat[pix]
        vflat = self._accumulate(pts, passable)
        if cfg.carve:
            cs = int(cfg.carve_stride)
            sub = ((pix % w) % cs == 0) & ((pix // w) % cs == 0)
            self._carve(trans, pts[sub])
        self._mark_agent(obs.agent_pose)

        touched: list[TrackedObject] = []
        self.last_track_ids = [None] * len(detections)
        if detections:
            valid_full = valid_depth(depth_flat, cfg.max_depth)
            # ascending score: where detections overlap, the most confident labels the voxels last
            order = sorted(range(len(detections)), key=lambda i: float(detections[i].score))
            for i in order:
                det, region_flat = detections[i], regions[i]
                stats = self._object_stats(region_flat, valid_full, depth_flat, k, rot, trans, w)
                if stats is None:
                    continue
                cls = self._class_index.get(det.label)
                if cls is not None:
                    self._label_voxels(cls, region_flat[pix], pts, vflat, stats)
                obj = self.memory.add_or_merge(
                    det.label,
                    det.score,
                    stats.centroid,
                    stats.box_min,
                    stats.box_max,
                    step=int(obs.step),
                    feature=det.feature,
                    oop_prob=det.oop_prob,
                )
                self.last_track_ids[i] = obj.id
            seen: set[int] = set()
            for tid in self.last_track_ids:
                if tid is not None and tid not in seen:
                    seen.add(tid)
                    touched.append(self.memory.get(tid))  # type: ignore[arg-type]
        self.steps += 1
        return touched

    def _lattice(self, shape: tuple[int, int], k: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
        key = (shape, stride, k.tobytes())
        hit = self._rays.get(key)
        if hit is None:
            if len(self._rays) >= 4:  # a few cameras at most; never grow without bound
                self._rays.clear()
            hit = self._rays[key] = pixel_rays(shape, k, stride)
        return hit

    def _voxel_index(self, pts: np.ndarray) -> np.ndarray:
        """int64 N flat voxel indices of points, -1 outside the voxel grid."""
        cfg = self.config
        nx, ny, nz = self.voxel_shape
        ox, oy = self.voxel_grid.origin
        ix = np.floor((pts[:, 0] - ox) / cfg.voxel_xy).astype(np.int64)
        iy = np.floor((pts[:, 1] - oy) / cfg.voxel_xy).astype(np.int64)
        iz = np.floor((pts[:, 2] - cfg.voxel_z_range[0]) / cfg.voxel_z).astype(np.int64)
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
        return np.where(inside, (ix * ny + iy) * nz + iz, -1)

    def _accumulate(self, pts: np.ndarray, passable: np.ndarray) -> np.ndarray:
        """Add start-frame points to the voxel and 2D maps (``passable`` points: not as
        obstacles); returns their flat voxel indices."""
        cfg = self.config
        vflat = self._voxel_index(pts)
        self.occupancy.reshape(-1)[vflat[vflat >= 0]] = True

        flat = self.grid.flat_index(pts)
        inside = flat >= 0
        flat = flat[inside]
        z = pts[inside, 2]
        _count_once(self.seen_count, flat)
        band = (z >= cfg.obstacle_z[0]) & (z < cfg.obstacle_z[1]) & ~passable[inside]
        if cfg.carve:
            _count_once(self.hit_frames, self._slab_index(flat[band], z[band]))
        else:
            self.obstacle.reshape(-1)[flat[band]] = True
        self.floor_seen.reshape(-1)[flat[z < cfg.floor_z]] = True
        return vflat

    def _carve(self, cam: np.ndarray, pts: np.ndarray) -> None:
        """Free-space carving (``MapConfig.carve``): count, per cell and ``carve_z`` slab of the
        obstacle band, this frame's rays that crossed it short of their point (stopping a cell
        and a half before it), and make ``obstacle`` the cells with a slab where frames with a
        point in it outnumber those and number at least ``carve_min_hits``. Slabs, not
        columns: a ray that passes over a table's edge to its top says nothing of the legs."""
        step = self.grid.cell
        d = pts - cam
        dist = np.sqrt((d * d).sum(axis=1))
        n = np.floor((dist - 1.5 * step) / step).astype(np.int64)  # samples s = step, 2 step, ...
        ok = n > 0
        if ok.any():
            n = n[ok]
            unit = (d[ok] / dist[ok, None]).astype(np.float32)
            ray = np.repeat(np.arange(n.size), n)
            s = (np.arange(1, int(n.sum()) + 1) - np.repeat(np.cumsum(n) - n, n)).astype(np.float32) * step
            along = np.stack([cam[a] + unit[ray, a] * s for a in range(3)], axis=1)
            _count_once(self.pass_frames, self._slab_index(self.grid.flat_index(along), along[:, 2]))
        held = (self.hit_frames > self.pass_frames) & (self.hit_frames >= self.config.carve_min_hits)
        self.obstacle = self.stamped | held.any(axis=2)

    def _slab_index(self, flat: np.ndarray, z: np.ndarray) -> np.ndarray:
        """int64 N flat indices into the carving grids (cell x slab) of points given by their
        flat 2D cell index (-1: off the map) and height; -1 outside the band or the map."""
        cfg = self.config
        nz = self.hit_frames.shape[2]
        k = np.floor((z - cfg.obstacle_z[0]) / cfg.carve_z).astype(np.int64)
        ok = (flat >= 0) & (k >= 0) & (k < nz) & (z < cfg.obstacle_z[1])
        return np.where(ok, flat * nz + k, -1)

    def _mark_agent(self, agent_pose: Sequence[float]) -> None:
        xy = np.array([float(agent_pose[0]), float(agent_pose[1])])
        cells = self.grid.disc(xy, self.config.agent_free_radius)
        self.visited[cells[:, 0], cells[:, 1]] = True
        c = self.grid.world_to_cell(xy)
        if self.grid.in_bounds(c)[0]:
            self.stood[c[0, 0], c[0, 1]] = True

    def _object_stats(
        self,
        region_flat: np.ndarray,
        valid_full: np.ndarray,
        depth_flat: np.ndarray,
        k: np.ndarray,
        rot: np.ndarray,
        trans: np.ndarray,
        width: int,
    ) -> _ObjectStats | None:
        """Centroid (the median-depth pixel's point) and 5-95 % box of a region, or None when
        fewer than ``min_object_points`` of its pixels have a valid depth."""
        cfg = self.config
        sel = np.flatnonzero(region_flat & valid_full)
        n = sel.size
        if n < cfg.min_object_points:
            return None
        ds = depth_flat[sel]
        med = sel[np.argpartition(ds, n // 2)[n // 2]]
        if n > cfg.max_object_points:
            sel = sel[:: int(math.ceil(n / cfg.max_object_points))]
        sel = np.concatenate((sel, [med]))
        u = (sel % width).astype(np.float64)
        v = (sel // width).astype(np.float64)
        dd = depth_flat[sel].astype(np.float64)
        cam = np.stack([dd * (u - k[0, 2]) / k[0, 0], dd * (v - k[1, 2]) / k[1, 1], dd], axis=1)
        p = cam @ rot.T + trans
        lo, hi = column_percentiles(p[:-1] if p.shape[0] > 1 else p, 5.0, 95.0)
        return _ObjectStats(centroid=p[-1].copy(), box_min=lo, box_max=hi)

    def _label_voxels(
        self, cls: int, in_region: np.ndarray, pts: np.ndarray, vflat: np.ndarray, stats: _ObjectStats
    ) -> None:
        """Label the voxels of this frame's map points that fall in the detection's pixels and
        within one voxel of its 3D box (drops most background behind a box-only detection)."""
        idx = np.flatnonzero(in_region)
        if idx.size == 0:
            return
        pad = (self.config.voxel_xy, self.config.voxel_xy, self.config.voxel_z)
        v = vflat[idx]
        ok = v >= 0
        for a in range(3):
            coord = pts[idx, a]
            ok &= (coord >= stats.box_min[a] - pad[a]) & (coord <= stats.box_max[a] + pad[a])
        self.voxel_labels.reshape(-1)[v[ok]] = cls

    # ------------------------------------------------------------------ navigation maps
    def _effective_obstacle(self) -> np.ndarray:
        return self.obstacle & ~self.visited

    def occupancy_grid(self) -> np.ndarray:
        """uint8 XxY at ``nav_cell``: 0 unknown, 1 free (explored or stood on, no obstacle),
        2 obstacle (as ``MapSnapshot.occupancy``)."""
        obstacle = self._effective_obstacle()
        out = np.zeros(self.grid.shape, np.uint8)
        out[self.explored | self.visited] = FREE
        out[obstacle] = OBSTACLE
        return out

    def traversible(self, agent_radius: float = 0.2) -> np.ndarray:
        """bool XxY: cells where the agent's centre may go: not within ``agent_radius`` metres
        of an obstacle cell. Unknown cells count as traversible (optimistic planning); cells
        the agent's centre has been in always do. The array covers exactly the map: anything
        outside it is not traversible (see ``traversible_at``)."""
        if agent_radius < 0:
            raise ValueError(f"agent_radius must be >= 0 metres, got {agent_radius}")
        obstacle = self._effective_obstacle()
        if agent_radius > 0:
            kernel = _disk_kernel(agent_radius, self.grid.cell)
            obstacle = cv2.dilate(obstacle.view(np.uint8), kernel).astype(bool)
        return ~obstacle | self.stood

    def traversible_at(self, xy: np.ndarray, agent_radius: float = 0.2) -> np.ndarray:
        """bool N: whether start-frame points xy (Nx2, metres) are traversible (False off the map)."""
        ij = self.grid.world_to_cell(xy)
        inside = self.grid.in_bounds(ij)
        out = np.zeros(ij.shape[0], bool)
        trav = self.traversible(agent_radius)
        out[inside] = trav[ij[inside, 0], ij[inside, 1]]
        return out

    def stamp_obstacle(self, xy: Sequence[float] | np.ndarray, radius: float = 0.1) -> None:
        """Mark cells within ``radius`` metres of start-frame ``xy`` as obstacle (e.g. after a
        blocked move); this overrides the free disc around earlier agent positions."""
        cells = self.grid.disc(xy, radius)
        self.obstacle[cells[:, 0], cells[:, 1]] = True
        self.stamped[cells[:, 0], cells[:, 1]] = True
        self.visited[cells[:, 0], cells[:, 1]] = False

    def clear_obstacle(self, xy: Sequence[float] | np.ndarray, radius: float) -> None:
        """Unmark obstacle cells within ``radius`` metres of start-frame ``xy`` (a later frame
        that sees an obstacle there marks it again)."""
        cells = self.grid.disc(xy, radius)
        self.obstacle[cells[:, 0], cells[:, 1]] = False
        self.stamped[cells[:, 0], cells[:, 1]] = False
        self.hit_frames[cells[:, 0], cells[:, 1]] = 0
        self.pass_frames[cells[:, 0], cells[:, 1]] = 0

    # ------------------------------------------------------------------ voxels and semantics
    def voxel_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Occupied voxels: (centres float32 Nx3 in the start frame, labels int16 N, -1 none)."""
        cfg = self.config
        flat = np.flatnonzero(self.occupancy.reshape(-1))
        ix, iy, iz = np.unravel_index(flat, self.voxel_shape)
        ox, oy = self.voxel_grid.origin
        centres = np.empty((flat.size, 3), np.float32)
        centres[:, 0] = ox + (ix + 0.5) * cfg.voxel_xy
        centres[:, 1] = oy + (iy + 0.5) * cfg.voxel_xy
        centres[:, 2] = cfg.voxel_z_range[0] + (iz + 0.5) * cfg.voxel_z
        return centres, self.voxel_labels.reshape(-1)[flat]

    def _coarse_occupancy(self, z_bins: int) -> np.ndarray:
        nx, ny, nz = self.voxel_shape
        if z_bins < 1 or nz % z_bins:
            raise ValueError(f"z_bins must divide the {nz} voxel heights, got {z_bins}")
        # 3D: numpy's stubs type a reduction along one axis as maybe a scalar
        occ = cast("np.ndarray", self.occupancy.reshape(nx, ny, z_bins, nz // z_bins).any(axis=3))
        return np.ascontiguousarray(occ.transpose(2, 0, 1), dtype=np.float32)  # z_bins x X x Y

    def _centroid_heat(self, label: str, z_bins: int) -> np.ndarray | None:
        """float32 z_bins x X x Y: the label's centroids counted per coarse voxel, Gaussian-blurred
        and scaled so that an isolated centroid peaks at 1; None when the label has no entry."""
        objs = self.memory.of_label(label)
        if not objs:
            return None
        cfg = self.config
        nx, ny, nz = self.voxel_shape
        bin_h = (cfg.voxel_z_range[1] - cfg.voxel_z_range[0]) / z_bins
        c = np.array([o.centroid for o in objs])
        ij = self.voxel_grid.world_to_cell(c[:, :2])
        inside = self.voxel_grid.in_bounds(ij)
        if not inside.any():
            return None
        iz = np.clip(np.floor((c[:, 2] - cfg.voxel_z_range[0]) / bin_h).astype(np.int64), 0, z_bins - 1)
        heat = np.zeros((z_bins, nx, ny), np.float32)
        np.add.at(heat, (iz[inside], ij[inside, 0], ij[inside, 1]), 1.0)
        s_xy = float(cfg.semantic_sigma_voxels)
        s_z = s_xy * cfg.voxel_xy / bin_h  # the same metric spread along z
        if s_xy > 0:
            heat = gaussian_filter(heat, sigma=(s_z, s_xy, s_xy), mode="constant", truncate=_GAUSS_TRUNCATE)
            heat /= _gauss_peak(s_z) * _gauss_peak(s_xy) ** 2
        return heat

    def semantic_volume(self, z_bins: int = 8, labels: Sequence[str] | None = None) -> np.ndarray:
        """float32 [C, z_bins, X, Y] (X = Y = 128 by default): per class (``classes``, or
        ``labels`` in that order) the paper's M^j = M^o + g(f(C^j)): the voxel occupancy
        coarsened to ``z_bins`` heights plus the class's memory centroids splatted into the
        coarse grid and Gaussian-dilated (an isolated centroid adds 1 at its voxel)."""
        names = self.classes if labels is None else list(labels)
        occ = self._coarse_occupancy(z_bins)
        vol = np.empty((len(names),) + occ.shape, np.float32)
        vol[:] = occ
        for ch, name in enumerate(names):
            heat = self._centroid_heat(name, z_bins)
            if heat is not None:
                vol[ch] += heat
        return vol

    def semantic_topdown(self, label: str, z_bins: int = 8, include_occupancy: bool = True) -> np.ndarray:
        """float32 X x Y: the max over heights of ``label``'s ``semantic_volume`` channel
        (without the occupancy term when ``include_occupancy`` is False)."""
        heat = self._centroid_heat(label, z_bins)
        base = self._coarse_occupancy(z_bins) if include_occupancy else None
        if heat is None:
            heat = np.zeros((z_bins,) + self.voxel_grid.shape, np.float32)
        vol = heat if base is None else heat + base
        return vol.max(axis=0)

    # ------------------------------------------------------------------ telemetry
    def snapshot(self, session: str, step: int) -> MapSnapshot:
        """The viewer's ``MapSnapshot`` of the current maps."""
        points, labels = self.voxel_points()
        return MapSnapshot(
            session=session,
            step=int(step),
            origin=self.grid.origin,
            cell=self.grid.cell,
            occupancy=self.occupancy_grid(),
            explored=self.explored.copy(),
            voxel_size=self.voxel_grid.cell,
            points=points,
            point_labels=labels,
            classes=list(self.classes),
        )
