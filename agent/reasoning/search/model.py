"""The visual search network (paper §3.4 and supplement "Visual search network"): the network
and ``VisualSearch``, what the agent runs.

``f_search(M, r)``: given the agent's semantic map M and a target category r, a top-down
heatmap of where instances of r are likely to be, in the room the agent is mapping.

Input (``search_input``), float32 [C_IN, 128, 128] on the mapper's voxel grid (10 cm cells,
the 12.8 m map centred on the start pose). The paper tiles all C x D (116 x 64) class-height
channels; that is 7424 input channels, too many for a CPU. We coarsen, keeping what
matters for "where is r":
  * one channel per detector class (92): the max over heights of the class, i.e. its
    voxels' top-down footprint (``voxel_labels``) max-combined with the memory centroids
    Gaussian-dilated (sigma 1.5 voxels, peak 1) as in ``SemanticMapper.semantic_volume``.
    Objects' heights carry little information for a top-down prior: the classes do;
  * voxel occupancy at Z_BINS = 4 height bands (0.8 m each: floor/low furniture, tables and
    counters, wall cabinets, ceiling), which is the room's shape and clutter;
  * the explored fraction of each cell (the 5 cm ``explored`` map pooled 2x2), so the net
    knows which emptiness is real.
Output: logits at 64 x 64 (20 cm cells over the same 12.8 m square); ``VisualSearch``
upsamples the probabilities to the 128 x 128 voxel grid.

Architecture (``SearchNet``): a small UNet (4 stride-2 stages, 128 -> 8 cells, ~1 M
parameters) computes class-agnostic features F [D, 64, 64] once per map; the learned
category embedding e_r gives a per-channel scale and shift (FiLM, the paper's "multiplied
with the feature map"), followed by a 3x3 and a 1x1 conv to the heatmap. The UNet runs
once for all the categories of a map, which keeps CPU training cheap. Its targets and
loss: :mod:`.data` and :mod:`.train`.

Search points (``search_points``): threshold the heatmap, farthest-point-sample the cells
above it (non-maximum suppression), rank by heat. ``VisualSearch.points`` snaps them to
cells the agent can reach.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from tidee.agent.classes import CLASS_INDEX, CLASSES
from tidee.agent.learning import WEIGHTS_DIR
from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.mapping.maps import SemanticMapper

DEFAULT_WEIGHTS = WEIGHTS_DIR / "search_net.pt"
Z_BINS = 4
C_IN = len(CLASSES) + Z_BINS + 1
IN_SIZE = 128  # input cells per side (the voxel grid)
OUT_SIZE = 64  # output cells per side
_CENTROID_SIGMA = 1.5  # voxels, as MapConfig.semantic_sigma_voxels


# --------------------------------------------------------------------------- inputs
def _gauss_stamp(sigma: float) -> np.ndarray:
    r = int(math.ceil(3 * sigma))
    d = np.arange(-r, r + 1)
    return np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma * sigma)).astype(np.float32)


_STAMP = _gauss_stamp(_CENTROID_SIGMA)


def search_input(mapper: SemanticMapper) -> np.ndarray:
    """float32 [C_IN, 128, 128] in [0, 1]: the network's view of the agent's map (see module doc)."""
    nx, ny, nz = mapper.voxel_shape
    if (nx, ny) != (IN_SIZE, IN_SIZE) or nz % Z_BINS:
        raise ValueError(
            f"the search network reads a {IN_SIZE}x{IN_SIZE} voxel grid with a multiple of {Z_BINS} "
            f"heights (the default MapConfig), got {mapper.voxel_shape}"
        )
    n_cls = len(CLASSES)
    x = np.zeros((C_IN, nx, ny), np.float32)
    lab = mapper.voxel_labels
    ix, iy, iz = np.nonzero(lab >= 0)
    if ix.size:
        cls = lab[ix, iy, iz].astype(np.int64)
        if mapper.classes != list(CLASSES):  # map the mapper's vocabulary to ours
            names = np.array([CLASS_INDEX.get(c, -1) for c in mapper.classes])
            cls = names[cls]
            ok = cls >= 0
            ix, iy, cls = ix[ok], iy[ok], cls[ok]
        x[cls, ix, iy] = 1.0
    r = _STAMP.shape[0] // 2
    for obj in mapper.memory:
        c = CLASS_INDEX.get(obj.label)
        if c is None:
            continue
        i, j = mapper.voxel_grid.world_to_cell(obj.centroid[:2])[0]
        if not (0 <= i < nx and 0 <= j < ny):
            continue
        i0, i1, j0, j1 = max(i - r, 0), min(i + r + 1, nx), max(j - r, 0), min(j + r + 1, ny)
        patch = _STAMP[i0 - (i - r) : i1 - (i - r), j0 - (j - r) : j1 - (j - r)]
        np.maximum(x[c, i0:i1, j0:j1], patch, out=x[c, i0:i1, j0:j1])
    occ = mapper.occupancy.reshape(nx, ny, Z_BINS, nz // Z_BINS).any(axis=3)
    x[n_cls : n_cls + Z_BINS] = occ.transpose(2, 0, 1)
    ex = mapper.explored
    fx, fy = ex.shape[0] // nx, ex.shape[1] // ny
    x[-1] = ex.reshape(nx, fx, ny, fy).mean(axis=(1, 3))
    return x


def out_grid(mapper_grid: GridSpec | None = None) -> GridSpec:
    """The 64 x 64 output grid (20 cm cells) over the same square as the voxel grid."""
    g = mapper_grid or GridSpec.centred(IN_SIZE, 0.1)
    cell = g.cell * g.shape[0] / OUT_SIZE
    return GridSpec(g.origin, cell, (OUT_SIZE, OUT_SIZE))


# --------------------------------------------------------------------------- the network
def _build_model(width: int = 32, embed: int = 48) -> Any:
    import torch
    from torch import nn

    def block(i: int, o: int, stride: int = 1) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)
        )

    class SearchNet(nn.Module):
        """Semantic map [B, C_IN, 128, 128] + class ids [B, K] -> logits [B, K, 64, 64]."""

        def __init__(self) -> None:
            super().__init__()
            w = width
            self.config = {"width": width, "embed": embed}
            self.enc0 = nn.Sequential(block(C_IN, w, 2), block(w, w))  # 64
            self.enc1 = nn.Sequential(block(w, 2 * w, 2), block(2 * w, 2 * w))  # 32
            self.enc2 = nn.Sequential(block(2 * w, 3 * w, 2), block(3 * w, 3 * w))  # 16
            self.enc3 = nn.Sequential(block(3 * w, 4 * w, 2), block(4 * w, 4 * w))  # 8
            self.dec2 = block(7 * w, 3 * w)
            self.dec1 = block(5 * w, 2 * w)
            self.dec0 = block(3 * w, embed)
            self.film = nn.Embedding(len(CLASSES), 2 * embed)
            nn.init.zeros_(self.film.weight)
            self.head = nn.Sequential(
                nn.Conv2d(embed, 16, 3, 1, 1), nn.ReLU(inplace=True), nn.Conv2d(16, 1, 1)
            )
            last = self.head[-1]
            assert isinstance(last, nn.Conv2d) and last.bias is not None
            nn.init.constant_(last.bias, -3.0)  # start near the positives' rarity

        @staticmethod
        def _up(x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
            return torch.cat([nn.functional.interpolate(x, size=skip.shape[-2:], mode="nearest"), skip], 1)

        def features(self, x: torch.Tensor) -> torch.Tensor:
            e0 = self.enc0(x)
            e1 = self.enc1(e0)
            e2 = self.enc2(e1)
            e3 = self.enc3(e2)
            d2 = self.dec2(self._up(e3, e2))
            d1 = self.dec1(self._up(d2, e1))
            return self.dec0(self._up(d1, e0))

        def condition(self, feats: torch.Tensor, cls: torch.Tensor) -> torch.Tensor:
            b, k = cls.shape
            gamma, beta = self.film(cls).chunk(2, dim=-1)  # [B, K, D]
            f = feats[:, None] * (1 + gamma[..., None, None]) + beta[..., None, None]
            f = torch.relu(f.flatten(0, 1))
            return self.head(f).view(b, k, *feats.shape[-2:])

        def forward(self, x: torch.Tensor, cls: torch.Tensor) -> torch.Tensor:
            return self.condition(self.features(x), cls)

    return SearchNet()


# --------------------------------------------------------------------------- search points
def farthest_point_sampling(points: np.ndarray, k: int, first: int = 0, min_dist: float = 0.0) -> np.ndarray:
    """int64 indices of up to ``k`` points of ``points`` [N, D], each the farthest from those already
    chosen, starting from ``points[first]``; stops early when the farthest is closer than
    ``min_dist`` (non-maximum suppression). Empty input or k <= 0 gives no indices."""
    pts = np.asarray(points, np.float64)
    n = len(pts)
    if n == 0 or k <= 0:
        return np.zeros(0, np.int64)
    if not 0 <= first < n:
        raise ValueError(f"first must index the {n} points, got {first}")
    pts = pts.reshape(n, -1)
    chosen = [int(first)]
    dist = np.linalg.norm(pts - pts[first], axis=1)
    while len(chosen) < min(k, n):
        i = int(np.argmax(dist))
        if dist[i] <= 0 or dist[i] < min_dist:
            break
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[i], axis=1))
    return np.asarray(chosen, np.int64)


def search_points(
    heatmap: np.ndarray,
    grid: GridSpec,
    threshold: float = 0.5,
    k: int = 3,
    valid: np.ndarray | None = None,
    min_dist_m: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Ranked search points from a heatmap on ``grid``: (float64 [K, 2] start-frame metres, heat [K]).

    Cells with heat >= ``threshold`` (where ``valid``, a bool mask on the same grid, allows),
    or, when none passes, those within half the maximum heat; farthest point sampling from
    the hottest cell picks up to ``k`` at least ``min_dist_m`` apart, each then moved to the
    hottest candidate nearer to it than to the others; they are returned hottest first.
    """
    heat = np.asarray(heatmap, np.float64)
    if heat.shape != tuple(grid.shape):
        raise ValueError(f"heatmap shape {heat.shape} does not match the grid {grid.shape}")
    if valid is not None:
        if valid.shape != heat.shape:
            raise ValueError(f"valid mask shape {valid.shape} does not match the heatmap {heat.shape}")
        heat = np.where(valid, heat, -np.inf)
    top = float(heat.max()) if heat.size else -np.inf
    if not np.isfinite(top):
        return np.zeros((0, 2)), np.zeros(0)
    cand = heat >= threshold
    if not cand.any():
        cand = np.isfinite(heat) & (heat >= 0.5 * top)
    ij = np.argwhere(cand)
    scores = heat[cand]  # row-major, as argwhere
    xy = grid.cell_to_world(ij)
    idx = farthest_point_sampling(xy, k, first=int(np.argmax(scores)), min_dist=min_dist_m)
    # FPS picks spread-out cells (often a blob's rim); move each to the hottest cell of its Voronoi region.
    nearest = np.argmin(np.linalg.norm(xy[:, None, :] - xy[idx][None, :, :], axis=2), axis=1)
    best = np.array(
        [np.flatnonzero(nearest == r)[np.argmax(scores[nearest == r])] for r in range(len(idx))], np.int64
    ).reshape(-1)
    order = best[np.argsort(-scores[best], kind="stable")]
    return xy[order], scores[order]


# --------------------------------------------------------------------------- inference
class VisualSearch:
    """The shipped search network behind a numpy API (one thread, CPU).

    ``heatmap(mapper, label)``: float32 [128, 128] probabilities on ``mapper.voxel_grid``.
    ``points(mapper, label, agent_xy, k)``: up to k reachable navigation goals (x, y), best first.
    """

    def __init__(
        self,
        model: Any,
        manifest: dict[str, Any] | None = None,
        threshold: float = 0.5,
        explored_discount: float = 0.0,
    ) -> None:
        self.model = model.eval()
        self.manifest = manifest or {}
        self.threshold = threshold
        # points(): heat scaled by (1 - discount * explored fraction) before picking search points
        self.explored_discount = float(explored_discount)

    @classmethod
    def load(
        cls, path: str | Path = DEFAULT_WEIGHTS, verify: bool = True, explored_discount: float = 0.0
    ) -> VisualSearch:
        from tidee.agent.learning import load_checkpoint, read_manifest

        manifest = read_manifest(path, verify=verify)
        ckpt = load_checkpoint(path)
        assert ckpt is not None
        model = _build_model(**ckpt["config"])
        model.load_state_dict(ckpt["model"])
        return cls(
            model, manifest, threshold=float(ckpt.get("threshold", 0.5)), explored_discount=explored_discount
        )

    def logits_for(self, x: np.ndarray, labels: Sequence[str]) -> np.ndarray:
        """float32 [K, 64, 64] logits for one input map [C_IN, 128, 128] and K class labels."""
        import torch

        unknown = [lbl for lbl in labels if lbl not in CLASS_INDEX]
        if unknown:
            raise ValueError(f"unknown categories {unknown}: the search network knows the detector's CLASSES")
        with torch.no_grad():
            xt = torch.from_numpy(np.ascontiguousarray(x, np.float32))[None]
            ct = torch.tensor([[CLASS_INDEX[lbl] for lbl in labels]])
            return self.model(xt, ct)[0].numpy()

    def heatmap(self, mapper: SemanticMapper, label: str) -> np.ndarray:
        """float32 [128, 128] probabilities on ``mapper.voxel_grid`` (bilinear from 64 x 64)."""
        import torch

        logit = self.logits_for(search_input(mapper), [label])
        prob = torch.sigmoid(torch.from_numpy(logit))[None]
        up = torch.nn.functional.interpolate(
            prob, size=mapper.voxel_grid.shape, mode="bilinear", align_corners=False
        )
        return up[0, 0].numpy()

    def points(
        self,
        mapper: SemanticMapper,
        label: str,
        agent_xy: Sequence[float],
        k: int = 3,
        visited: Sequence[Sequence[float]] = (),
        visit_radius: float = 1.0,
        agent_radius: float = 0.2,
        heat: np.ndarray | None = None,
    ) -> list[tuple[float, float]]:
        """Up to ``k`` navigation goals (start-frame metres), hottest first: search points of the
        heatmap away from ``visited`` points (within ``visit_radius``), each snapped to the nearest
        nav cell reachable from ``agent_xy``."""
        from tidee.agent.navigation.fmm import FMMPlanner

        if heat is None:  # a caller that also shows the heatmap passes it in: one inference
            heat = self.heatmap(mapper, label)
        vg = mapper.voxel_grid
        if self.explored_discount > 0:  # prefer likely places the camera has not covered yet
            ex = mapper.explored
            fx, fy = ex.shape[0] // heat.shape[0], ex.shape[1] // heat.shape[1]
            heat = heat * (
                1.0 - self.explored_discount * ex.reshape(heat.shape[0], fx, heat.shape[1], fy).mean((1, 3))
            )
        valid = np.ones(heat.shape, bool)
        if len(visited):
            centres = vg.cell_to_world(np.argwhere(valid)).reshape(*heat.shape, 2)
            for v in visited:
                valid &= np.hypot(centres[..., 0] - v[0], centres[..., 1] - v[1]) > visit_radius
        pts, _ = search_points(heat, vg, self.threshold, k, valid=valid)
        if len(pts) == 0:
            return []
        reach = FMMPlanner(mapper.traversible(agent_radius), mapper.grid).reachable_from(tuple(agent_xy))
        return snap_to_mask(pts, reach, mapper.grid)


def snap_to_mask(points: np.ndarray, mask: np.ndarray, grid: GridSpec) -> list[tuple[float, float]]:
    """Each point moved to the centre of the nearest cell of ``mask`` (dropped when the mask is empty);
    points that land on the same cell are kept once."""
    if not mask.any():
        return []
    _, (ii, jj) = ndimage.distance_transform_edt(~mask, return_indices=True)
    ij = grid.world_to_cell(np.asarray(points)[:, :2])
    ij = np.clip(ij, 0, np.asarray(mask.shape) - 1)
    out: list[tuple[float, float]] = []
    for i, j in ij:
        p = grid.to_world((ii[i, j], jj[i, j]))
        if p not in out:
            out.append(p)
    return out


__all__ = [
    "C_IN",
    "DEFAULT_WEIGHTS",
    "IN_SIZE",
    "OUT_SIZE",
    "VisualSearch",
    "farthest_point_sampling",
    "out_grid",
    "search_input",
    "search_points",
    "snap_to_mask",
]
