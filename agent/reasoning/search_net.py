"""The visual search network (paper §3.4 and supplement "Visual search network").

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
once for all the categories of a map, which keeps CPU training cheap.

Targets: for every category present in the room, max over its instances of
exp(-d^2 / 2 sigma^2), d the distance (metres, start frame) from a cell centre to the
instance's footprint rectangle (ground-truth position, size and yaw; sigma 0.3 m).
Loss: binary cross-entropy on every cell with positives weighted (``pos_weight``).

Search points (``search_points``): threshold the heatmap, farthest-point-sample the cells
above it (non-maximum suppression), rank by heat. ``VisualSearch.points`` snaps them to
cells the agent can reach.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from tidee.agent.classes import CLASS_INDEX, CLASSES, PICKUPABLE
from tidee.agent.learning import WEIGHTS_DIR
from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.mapping.maps import SemanticMapper
from tidee.agent.perception import TRAINED_RENDERER
from tidee.server.scene import quat_yaw
from tidee.server.splits import ROOM_TYPES, split_of

DEFAULT_WEIGHTS = WEIGHTS_DIR / "search_net.pt"
DOCS_LOSS_PNG = Path(__file__).resolve().parents[2] / "docs" / "models" / "search_net_loss.png"
Z_BINS = 4
C_IN = len(CLASSES) + Z_BINS + 1
IN_SIZE = 128  # input cells per side (the voxel grid)
OUT_SIZE = 64  # output cells per side
TARGET_SIGMA_M = 0.3
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


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255).astype(np.uint8)


def out_grid(mapper_grid: GridSpec | None = None) -> GridSpec:
    """The 64 x 64 output grid (20 cm cells) over the same square as the voxel grid."""
    g = mapper_grid or GridSpec.centred(IN_SIZE, 0.1)
    cell = g.cell * g.shape[0] / OUT_SIZE
    return GridSpec(g.origin, cell, (OUT_SIZE, OUT_SIZE))


# --------------------------------------------------------------------------- targets (ground truth)
def room_instances(state: dict[str, Any]) -> np.ndarray:
    """float32 [M, 6] rows (class index, cx, cy, half x, half y, yaw) of every object whose type is a
    detector class, in the episode's start frame. Reads the simulator's privileged state: for
    training targets and evaluation only."""
    start = state["start"]
    t0 = math.radians(start["yaw_deg"])
    c, s = math.cos(t0), math.sin(t0)
    rows = []
    for o in state["objects"]:
        k = CLASS_INDEX.get(o["type"])
        if k is None:
            continue
        dx, dy = o["position"][0] - start["x"], o["position"][1] - start["y"]
        sx, sy = float(o["size"][0]), float(o["size"][1])
        rows.append((k, c * dx + s * dy, -s * dx + c * dy, sx / 2, sy / 2, quat_yaw(o["orientation"]) - t0))
    return np.asarray(rows, np.float32).reshape(-1, 6)


def footprint_distance(inst: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """float32 [M, N]: distance (metres) from points xy [N, 2] to each instance's footprint rectangle."""
    d = xy[None, :, :] - inst[:, None, 1:3]
    c, s = np.cos(inst[:, 5])[:, None], np.sin(inst[:, 5])[:, None]
    u = np.abs(c * d[..., 0] + s * d[..., 1]) - inst[:, None, 3]
    v = np.abs(-s * d[..., 0] + c * d[..., 1]) - inst[:, None, 4]
    return np.hypot(np.maximum(u, 0), np.maximum(v, 0)).astype(np.float32)


_OUT_XY = out_grid().cell_to_world(
    np.stack(np.meshgrid(np.arange(OUT_SIZE), np.arange(OUT_SIZE), indexing="ij"), -1).reshape(-1, 2)
)


def target_heat(inst: np.ndarray, classes: Sequence[int], sigma: float = TARGET_SIGMA_M) -> np.ndarray:
    """float32 [K, 64, 64]: per class, the max over its instances of exp(-d^2 / 2 sigma^2)."""
    out = np.zeros((len(classes), OUT_SIZE * OUT_SIZE), np.float32)
    for k, c in enumerate(classes):
        rows = inst[inst[:, 0] == c]
        if len(rows):
            d = footprint_distance(rows, _OUT_XY).min(axis=0)
            out[k] = np.exp(-0.5 * (d / sigma) ** 2)
    return out.reshape(len(classes), OUT_SIZE, OUT_SIZE)


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
            nn.init.constant_(self.head[-1].bias, -3.0)  # start near the positives' rarity

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


# --------------------------------------------------------------------------- data generation
@dataclass
class SearchGenConfig:
    out: str = "data/search"
    split: str = "train"  # train (seeds 0-19 then the pool) | test (held-out evaluation sets only)
    rooms_per_type: int = 20
    messes_per_room: int = 1  # messy configurations per room, besides the tidy one
    snapshots: int = 4  # map snapshots per configuration
    max_steps: int = 200  # exploration steps per configuration
    perception: str = "oracle"
    resolution: int = 256
    seed: int = 0
    workers: int = 2
    room_types: tuple[str, ...] = ROOM_TYPES

    def __post_init__(self) -> None:
        if self.split not in ("train", "test", "val"):
            raise ValueError(f"split must be train, val or test, got {self.split!r}")
        if self.snapshots < 1 or self.max_steps < 20:
            raise ValueError(
                f"need snapshots >= 1 and max_steps >= 20, got {self.snapshots}, {self.max_steps}"
            )
        if not 1 <= self.workers <= 2:
            raise ValueError(f"workers must be 1 or 2 (this machine's budget), got {self.workers}")


def _jobs(cfg: SearchGenConfig) -> list[tuple[str, int, int | None]]:
    from tidee.agent.perception.dataset import room_seeds

    jobs: list[tuple[str, int, int | None]] = []
    for seed in room_seeds(cfg.split, cfg.rooms_per_type):
        if cfg.split == "train" and split_of(seed) not in ("train", "train_pool"):
            raise ValueError(
                f"seed {seed} is a {split_of(seed)} room: training data only comes from training rooms"
            )
        for rt in cfg.room_types:
            jobs.append((rt, seed, None))
            jobs += [(rt, seed, m) for m in range(cfg.messes_per_room)]
    return jobs


def _explore_skill(body: Any, rng: np.random.Generator) -> Any:
    """Mapping as the agent does it: look around, then frontier or random unexplored goals."""
    from tidee.agent.navigation.explore import FrontierExplorer, sample_reachable_goal, sample_unexplored_goal
    from tidee.agent.policy.skills import frontier_goal, look_around, navigate, reachable_mask

    yield from look_around(body)
    explorer = FrontierExplorer(body.mapper.grid)
    while body.steps_left() > 1:
        reach = None
        if rng.random() < 0.5:
            goal = frontier_goal(body, explorer)
        else:
            reach = reachable_mask(body)
            goal = sample_unexplored_goal(body.mapper.explored, reach, body.mapper.grid, rng, tuple(body.xy))
        if goal is None:
            reach = reachable_mask(body) if reach is None else reach
            goal = sample_reachable_goal(reach, body.mapper.grid, rng, tuple(body.xy))
            if goal is None:
                return False
        yield from navigate(body, goal_xy=goal, budget=40)
        if rng.random() < 0.5:
            yield from look_around(body, pitches=(30.0,))
    return True


def snapshot_config(
    job: tuple[str, int, int | None], cfg: SearchGenConfig, transport: Any = None, perception: Any = None
) -> dict[str, Any]:
    """Explore one room configuration; map snapshots at random steps with their ground-truth instances."""
    from tidee.agent.perception import make_perception
    from tidee.agent.policy.search import SkillDriver
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport

    rt, seed, mess = job
    rng = np.random.default_rng([cfg.seed, seed, ROOM_TYPES.index(rt), 0 if mess is None else mess + 1])
    transport = transport or InProcessTransport(renderer=TRAINED_RENDERER)
    perception = perception or make_perception(cfg.perception)
    driver = SkillDriver(transport, perception)
    spec = EpisodeSpec(
        room_type=rt, seed=seed, mess_index=mess, resolution=cfg.resolution, max_steps=cfg.max_steps
    )
    body = driver.reset(spec)
    inst = room_instances(transport.state())
    # Early maps matter most (a search starts after one look-around): half the snapshots in the first 60 steps.
    early = rng.integers(8, 60, size=cfg.snapshots // 2)
    late = rng.integers(60, cfg.max_steps, size=cfg.snapshots - len(early))
    when = set(int(s) for s in np.concatenate([early, late]))
    xs, steps, seen = [], [], []

    def on_step(b: Any) -> None:
        if int(b.obs.step) in when:
            xs.append(to_uint8(search_input(b.mapper)))
            steps.append(int(b.obs.step))
            seen.append(sorted({CLASS_INDEX[o.label] for o in b.mapper.memory if o.label in CLASS_INDEX}))

    driver.run(_explore_skill(body, rng), on_step)
    return {
        "x": np.stack(xs) if xs else np.zeros((0, C_IN, IN_SIZE, IN_SIZE), np.uint8),
        "inst": inst,
        "steps": steps,
        "seen": seen,
        "room_type": rt,
        "seed": seed,
        "mess_index": mess,
    }


def _gen_worker(args: tuple[tuple[str, int, int | None], SearchGenConfig]) -> dict[str, Any]:
    from tidee.agent.perception import make_perception
    from tidee.protocol.transport import InProcessTransport

    job, cfg = args
    global _WORKER
    try:
        transport, perception = _WORKER
    except NameError:
        transport, perception = _WORKER = (
            InProcessTransport(renderer=TRAINED_RENDERER),
            make_perception(cfg.perception),
        )
    return snapshot_config(job, cfg, transport, perception)


def _shard_name(rt: str, seed: int, mess: int | None) -> str:
    return f"{rt}_{seed}_{'tidy' if mess is None else f'mess{mess}'}.npz"


def generate_search_data(cfg: SearchGenConfig, command: str = "", progress: bool = True) -> dict[str, Any]:
    """Write one shard per room configuration to ``cfg.out`` (existing shards are kept: resumable)
    and ``manifest.json``. Deterministic in ``cfg``."""
    import concurrent.futures as cf
    import multiprocessing as mp

    from tqdm import tqdm

    from tidee.protocol.episode_log import write_json_atomic
    from tidee.threads import threads_per_process, use_threads

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = _jobs(cfg)
    todo = [j for j in jobs if not (out / _shard_name(*j)).exists()]
    t0 = time.time()
    n_snap = 0

    def save(res: dict[str, Any]) -> None:
        nonlocal n_snap
        path = out / _shard_name(res["room_type"], res["seed"], res["mess_index"])
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(
            tmp,
            x=res["x"],
            inst=res["inst"],
            steps=np.asarray(res["steps"], np.int32),
            seen=json.dumps(res["seen"]),
            room_type=res["room_type"],
            seed=res["seed"],
            mess_index=-1 if res["mess_index"] is None else res["mess_index"],
        )
        tmp.replace(path)
        n_snap += len(res["x"])

    bar = tqdm(total=len(todo), desc=f"search data ({cfg.split})", disable=not progress)
    if cfg.workers > 1 and len(todo) > 1:
        ctx = mp.get_context("spawn")
        with cf.ProcessPoolExecutor(
            cfg.workers, mp_context=ctx, initializer=use_threads, initargs=(threads_per_process(cfg.workers),)
        ) as pool:
            for res in pool.map(_gen_worker, [(j, cfg) for j in todo]):
                save(res)
                bar.update()
    else:
        for j in todo:
            save(_gen_worker((j, cfg)))
            bar.update()
    bar.close()
    manifest = {
        "command": command,
        "config": asdict(cfg),
        "configurations": len(jobs),
        "seeds": sorted({s for _, s, _ in jobs}),
        "perception": cfg.perception,
        "snapshots_written_now": n_snap,
        "seconds_now": round(time.time() - t0, 1),
        "note": (
            "maps built by the agent's own mapping with "
            + (
                "ORACLE detections (the simulator's segmentation)"
                if cfg.perception == "oracle"
                else "the shipped learned detector"
            )
            + "; targets from the simulator's ground-truth object poses"
        ),
    }
    write_json_atomic(out / "manifest.json", manifest)
    return manifest


def load_search_data(path: str | Path) -> dict[str, Any]:
    """All shards of a directory: x uint8 [N, C_IN, 128, 128], inst (list of [M, 6] per shard), owner [N]
    (shard index of each snapshot), seen (list of class lists per snapshot)."""
    files = sorted(Path(path).glob("*.npz"))
    files = [f for f in files if not f.name.endswith(".tmp.npz")]
    if not files:
        raise FileNotFoundError(f"no search-data shards in {path}; run `tidee gen search` first")
    xs, insts, owner, seen, rooms = [], [], [], [], []
    for i, f in enumerate(files):
        with np.load(f) as z:
            xs.append(z["x"])
            insts.append(z["inst"])
            owner += [i] * len(z["x"])
            seen += json.loads(str(z["seen"]))
            rooms.append((str(z["room_type"]), int(z["seed"]), int(z["mess_index"])))
    return {"x": np.concatenate(xs), "inst": insts, "owner": np.asarray(owner), "seen": seen, "rooms": rooms}


# --------------------------------------------------------------------------- training
@dataclass
class SearchTrainConfig:
    data: str = "data/search"
    out: str = str(DEFAULT_WEIGHTS)
    work_dir: str = "runs/search/train"
    steps: int = 1200
    batch_size: int = 8
    classes_per_map: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    pos_weight: float = 10.0
    width: int = 32
    embed: int = 48
    val_fraction: float = 0.1  # of training *rooms*, held out to pick the threshold and report
    seed: int = 0
    threads: int = 2
    log_every: int = 20
    ckpt_every: int = 100
    extra: dict[str, Any] = field(default_factory=dict)


def _augment(x: np.ndarray, inst: np.ndarray, k: int, flip: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the map by k*90 degrees about the start pose (and mirror y); the same for the instances."""
    inst = inst.copy()
    if flip:  # y -> -y
        x = x[:, :, ::-1]
        inst[:, 2] *= -1
        inst[:, 5] *= -1
    for _ in range(k):  # (x, y) -> (-y, x): rotate +90 degrees
        x = np.rot90(x, 1, axes=(1, 2))
        cx, cy = inst[:, 1].copy(), inst[:, 2].copy()
        inst[:, 1], inst[:, 2] = -cy, cx
        inst[:, 5] += math.pi / 2
    return np.ascontiguousarray(x), inst


def _batch(
    data: dict[str, Any], idx: Sequence[int], rng: np.random.Generator, k_cls: int, augment: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, cs, ts = [], [], []
    for i in idx:
        x = data["x"][i].astype(np.float32) / 255.0
        inst = data["inst"][data["owner"][i]]
        if augment:
            x, inst = _augment(x, inst, int(rng.integers(4)), bool(rng.integers(2)))
        present = np.unique(inst[:, 0]).astype(np.int64)
        cls = rng.choice(present, size=k_cls, replace=len(present) < k_cls)
        xs.append(x)
        cs.append(cls)
        ts.append(target_heat(inst, cls))
    return np.stack(xs), np.stack(cs), np.stack(ts)


def split_rooms(data: dict[str, Any], val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Snapshot indices (train, val): whole rooms (room type, seed) go to one side."""
    rooms = sorted({(r[0], r[1]) for r in data["rooms"]})
    rng = np.random.default_rng(seed)
    n_val = int(round(val_fraction * len(rooms)))
    val_rooms = {rooms[i] for i in rng.permutation(len(rooms))[:n_val]}
    is_val = np.array([(data["rooms"][o][0], data["rooms"][o][1]) in val_rooms for o in data["owner"]])
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def train_search_net(
    cfg: SearchTrainConfig,
    command: str = "",
    resume: bool = True,
    progress: bool = True,
    data: dict[str, Any] | None = None,
    ship: bool = True,
    docs_png: Path | None = DOCS_LOSS_PNG,
) -> dict[str, Any]:
    """Train from shards (or ``data``); ship weights + manifest when ``ship``. Returns a summary."""
    import torch
    from tqdm import tqdm

    from tidee.agent.learning import load_checkpoint, save_checkpoint, save_loss_curve, write_manifest

    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    data = data if data is not None else load_search_data(cfg.data)
    tr_idx, va_idx = split_rooms(data, cfg.val_fraction, cfg.seed)
    if len(tr_idx) == 0:
        raise ValueError("no training snapshots left after holding out validation rooms")
    model = _build_model(cfg.width, cfg.embed)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    rng = np.random.default_rng(cfg.seed)
    history: list[dict[str, float]] = []
    step = 0
    work = Path(cfg.work_dir)
    ckpt_path = work / "checkpoint.pt"
    if resume and (ck := load_checkpoint(ckpt_path)) is not None and ck.get("cfg") == asdict(cfg):
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        rng.bit_generator.state = ck["rng"]
        history, step = ck["history"], ck["step"]
    pos_weight = torch.tensor(cfg.pos_weight)
    t0 = time.time()
    model.train()
    bar = tqdm(total=cfg.steps, initial=step, desc="train search net", disable=not progress)
    running = []
    while step < cfg.steps:
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps))
        for g in opt.param_groups:
            g["lr"] = lr
        idx = rng.choice(tr_idx, size=min(cfg.batch_size, len(tr_idx)), replace=False)
        x, c, t = _batch(data, idx, rng, cfg.classes_per_map, augment=True)
        logits = model(torch.from_numpy(x), torch.from_numpy(c))
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            logits, torch.from_numpy(t), pos_weight=pos_weight
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        running.append(float(loss.detach()))
        bar.update()
        if step % cfg.log_every == 0 or step == cfg.steps:
            history.append({"step": step, "train_bce": float(np.mean(running))})
            bar.set_postfix(loss=f"{np.mean(running):.4f}")
            running = []
        if step % cfg.ckpt_every == 0 or step == cfg.steps:
            save_checkpoint(
                ckpt_path,
                model=model.state_dict(),
                opt=opt.state_dict(),
                rng=rng.bit_generator.state,
                history=history,
                step=step,
                cfg=asdict(cfg),
            )
    bar.close()
    model.eval()
    summary: dict[str, Any] = {
        "steps": step,
        "seconds": round(time.time() - t0, 1),
        "history": history,
        "train_snapshots": int(len(tr_idx)),
        "val_snapshots": int(len(va_idx)),
    }
    if len(va_idx):
        vs = VisualSearch(model)
        summary["val"] = heldout_metrics(vs, _as_eval_set(data, va_idx))
        summary["val_bce"] = _mean_bce(model, data, va_idx, cfg)
    save_loss_curve(history, work / "search_net_loss.png", "visual search network (weighted BCE)")
    if ship:
        out = Path(cfg.out)
        save_checkpoint(
            out,
            model=model.state_dict(),
            config={"width": cfg.width, "embed": cfg.embed},
            threshold=0.5,
            classes=list(CLASSES),
            c_in=C_IN,
        )
        if docs_png is not None:
            save_loss_curve(history, docs_png, "visual search network (weighted BCE)")
        rooms = sorted({(r[0], r[1]) for r in data["rooms"]})
        write_manifest(
            out,
            command=command,
            data={
                "dir": cfg.data,
                "snapshots": int(len(data["x"])),
                "configurations": len(data["rooms"]),
                "room_seeds": sorted({s for _, s in rooms}),
                "gen_manifest": _read_gen_manifest(cfg.data),
            },
            metrics={k: summary[k] for k in ("val", "val_bce") if k in summary},
            train={
                **asdict(cfg),
                "seconds": summary["seconds"],
                "final_train_bce": history[-1]["train_bce"] if history else None,
            },
        )
        summary["out"] = str(out)
    return summary


def _read_gen_manifest(path: str | Path) -> dict[str, Any] | None:
    p = Path(path) / "manifest.json"
    if not p.exists():
        return None
    m = json.loads(p.read_text())
    return {k: m.get(k) for k in ("command", "perception", "seeds", "configurations", "note")}


def _mean_bce(model: Any, data: dict[str, Any], idx: np.ndarray, cfg: SearchTrainConfig) -> float:
    import torch

    rng = np.random.default_rng(12345)
    losses = []
    with torch.no_grad():
        for s in range(0, len(idx), cfg.batch_size):
            x, c, t = _batch(data, idx[s : s + cfg.batch_size], rng, cfg.classes_per_map, augment=False)
            losses.append(
                float(
                    torch.nn.functional.binary_cross_entropy_with_logits(
                        model(torch.from_numpy(x), torch.from_numpy(c)),
                        torch.from_numpy(t),
                        pos_weight=torch.tensor(cfg.pos_weight),
                    )
                )
            )
    return float(np.mean(losses))


# --------------------------------------------------------------------------- held-out metrics
def _as_eval_set(data: dict[str, Any], idx: Sequence[int]) -> list[dict[str, Any]]:
    return [{"x": data["x"][i], "inst": data["inst"][data["owner"][i]], "seen": data["seen"][i]} for i in idx]


def occupancy_heat(x: np.ndarray) -> np.ndarray:
    """The trivial baseline's [64, 64] heat: class-agnostic clutter (occupancy above the floor band,
    Gaussian-blurred): "objects are where stuff is"."""
    n = len(CLASSES)
    occ = np.asarray(x[n : n + Z_BINS], np.float32)
    if occ.max() > 1:
        occ = occ / 255.0
    clutter = occ.max(axis=0)
    small = clutter.reshape(OUT_SIZE, 2, OUT_SIZE, 2).mean(axis=(1, 3))
    return ndimage.gaussian_filter(small, 1.5)


def _average_precision(score: np.ndarray, positive: np.ndarray) -> float:
    order = np.argsort(-score, kind="stable")
    pos = positive[order]
    if not pos.any():
        return float("nan")
    hits = np.cumsum(pos)
    precision = hits / np.arange(1, len(pos) + 1)
    return float(precision[pos].mean())


def heldout_metrics(
    search: VisualSearch | None, samples: list[dict[str, Any]], k: int = 3, hit_radius: float = 1.0
) -> dict[str, Any]:
    """Per (map, present category): cell AP (targets >= 0.5 positive) and hit@k (one of the top-k
    search points within ``hit_radius`` of an instance footprint), for the network and the
    occupancy baseline; also over the categories not yet in the agent's memory ("unseen")."""
    import torch

    grid = out_grid()
    res: dict[str, dict[str, list[float]]] = {
        m: {"ap": [], "hit": [], "ap_unseen": [], "hit_unseen": []} for m in ("network", "occupancy")
    }
    for s in samples:
        x = np.asarray(s["x"], np.float32)
        if x.max() > 1.0:
            x = x / 255.0
        inst = s["inst"]
        present = np.unique(inst[:, 0]).astype(np.int64)
        targets = target_heat(inst, present)
        heats = {"occupancy": np.repeat(occupancy_heat(x)[None], len(present), 0)}
        if search is not None:
            logits = search.logits_for(x, [CLASSES[c] for c in present])
            heats["network"] = torch.sigmoid(torch.from_numpy(logits)).numpy()
        for j, c in enumerate(present):
            unseen = int(c) not in set(s["seen"])
            rows = inst[inst[:, 0] == c]
            for name, h in heats.items():
                ap = _average_precision(h[j].ravel(), targets[j].ravel() >= 0.5)
                pts, _ = search_points(h[j], grid, threshold=0.5 if name == "network" else np.inf, k=k)
                hit = float(len(pts) > 0 and footprint_distance(rows, pts).min() <= hit_radius)
                res[name]["ap"].append(ap)
                res[name]["hit"].append(hit)
                if unseen:
                    res[name]["ap_unseen"].append(ap)
                    res[name]["hit_unseen"].append(hit)
    out: dict[str, Any] = {"maps": len(samples)}
    for name, r in res.items():
        if search is None and name == "network":
            continue
        out[name] = {f"{m}": round(float(np.nanmean(v)), 4) if v else None for m, v in r.items()}
        out[name]["n"] = len(r["ap"])
        out[name]["n_unseen"] = len(r["ap_unseen"])
    return out


def time_inference(search: VisualSearch, repeats: int = 20) -> dict[str, float]:
    """Median ms of ``heatmap`` on one thread for a fresh (empty) map, input building included."""
    import torch

    from tidee.agent.mapping.maps import SemanticMapper

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mapper = SemanticMapper(classes=CLASSES, passable=PICKUPABLE)
        search.heatmap(mapper, CLASSES[0])
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            search.heatmap(mapper, CLASSES[0])
            ts.append((time.perf_counter() - t0) * 1e3)
    finally:
        torch.set_num_threads(threads)
    return {"heatmap_ms_median": round(float(np.median(ts)), 1), "threads": 1}


__all__ = [
    "C_IN",
    "DEFAULT_WEIGHTS",
    "SearchGenConfig",
    "SearchTrainConfig",
    "VisualSearch",
    "farthest_point_sampling",
    "footprint_distance",
    "generate_search_data",
    "heldout_metrics",
    "load_search_data",
    "occupancy_heat",
    "room_instances",
    "search_input",
    "search_points",
    "snap_to_mask",
    "target_heat",
    "time_inference",
    "train_search_net",
]
