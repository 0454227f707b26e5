"""The camera-coloured point cloud: the agent's RGB-D frames fused into coloured voxels.

Each frame's depth is unprojected into the start frame (``geometry.unproject_depth``) and
its pixels' colours go into a voxel grid, the latest colour winning per voxel. Memory and
the browser's load stay bounded: at most ``cap`` voxels are kept, the most recently seen
first. Pure numpy (vectorised), no viser.
"""

from __future__ import annotations

import numpy as np

from tidee.viewer import geometry

_BIAS = 1 << 20  # voxel indices in [-2^20, 2^20) pack into 21 bits each


class ColourCloud:
    """Voxel centres and colours of what the camera has seen.

    ``floor_z`` and ``ceiling_z`` drop the floor (as the semantic map does, so the grid, paths
    and heatmap on it stay visible) and anything above the walls.
    """

    def __init__(
        self,
        voxel: float = 0.05,
        cap: int = 150_000,
        stride: int = 2,
        max_depth: float = 6.0,
        floor_z: float = 0.05,
        ceiling_z: float = 2.4,
    ) -> None:
        if voxel <= 0 or cap < 1 or stride < 1:
            raise ValueError(f"need voxel > 0, cap >= 1 and stride >= 1, got {voxel}, {cap}, {stride}")
        self.voxel, self.cap, self.stride, self.max_depth = (
            float(voxel),
            int(cap),
            int(stride),
            float(max_depth),
        )
        self.floor_z, self.ceiling_z = float(floor_z), float(ceiling_z)
        self.frames = 0  # frames added since the last clear
        self.clear()

    def clear(self) -> None:
        self._keys = np.zeros(0, np.int64)
        self._colors = np.zeros((0, 3), np.uint8)
        self._stamps = np.zeros(0, np.int64)  # the frame that last coloured each voxel
        # (the three arrays are kept sorted by voxel key)
        self.frames = 0

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, rgb: np.ndarray, depth: np.ndarray, camera_pose: np.ndarray, intrinsics: np.ndarray) -> int:
        """Fuse one frame; returns the number of voxels kept."""
        img = np.asarray(rgb, np.uint8)
        d = np.asarray(depth, np.float32)
        if img.shape[:2] != d.shape:  # an image and depth of different sizes: pick depth's pixels
            rows = np.arange(d.shape[0]) * img.shape[0] // d.shape[0]
            cols = np.arange(d.shape[1]) * img.shape[1] // d.shape[1]
            img = img[rows][:, cols]
        pts, pix = geometry.unproject_depth(d, intrinsics, camera_pose, self.stride, self.max_depth)
        keep = (pts[:, 2] >= self.floor_z) & (pts[:, 2] <= self.ceiling_z)
        pts, pix = pts[keep], pix[keep]
        self.frames += 1
        if not len(pts):
            return len(self)
        keys = self._pack(np.floor(pts / self.voxel).astype(np.int64))
        colors = img[pix[:, 0], pix[:, 1]]
        # this frame's voxels, one colour each (the last pixel's)
        keys, last = np.unique(keys[::-1], return_index=True)
        colors = colors[::-1][last]
        # merge into the sorted voxels kept so far: seen ones take the new colour, new ones go in
        at = np.searchsorted(self._keys, keys)
        seen = at < len(self._keys)
        seen[seen] = self._keys[at[seen]] == keys[seen]
        self._colors[at[seen]] = colors[seen]
        self._stamps[at[seen]] = self.frames
        fresh = ~seen
        self._keys = np.insert(self._keys, at[fresh], keys[fresh])
        self._colors = np.insert(self._colors, at[fresh], colors[fresh], axis=0)
        self._stamps = np.insert(self._stamps, at[fresh], self.frames)
        if len(self._keys) > self.cap:  # over the cap: the most recently seen voxels stay
            cut = np.partition(self._stamps, len(self._stamps) - self.cap)[len(self._stamps) - self.cap]
            keep = self._stamps > cut
            ties = np.flatnonzero(self._stamps == cut)[: self.cap - int(keep.sum())]
            keep[ties] = True
            self._keys, self._colors, self._stamps = self._keys[keep], self._colors[keep], self._stamps[keep]
        return len(self)

    def points(self) -> np.ndarray:
        """``Nx3`` float32 voxel centres (start frame, metres)."""
        return ((self._unpack(self._keys) + 0.5) * self.voxel).astype(np.float32)

    def colors(self) -> np.ndarray:
        """``Nx3`` uint8 RGB, one per point."""
        return self._colors

    @staticmethod
    def _pack(idx: np.ndarray) -> np.ndarray:
        idx = np.clip(idx, -_BIAS, _BIAS - 1) + _BIAS
        return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]

    @staticmethod
    def _unpack(keys: np.ndarray) -> np.ndarray:
        mask = (1 << 21) - 1
        return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], axis=1) - _BIAS
