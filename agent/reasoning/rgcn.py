"""Memex + rGCN: where does a picked-up object belong? (paper §3.3, supplement "Relational
graph convolutional network")

The network, for one out-of-place (OOP) object in a room:

1. **Memex** (``memex.build_memex``: 5 memory rooms per type): node = class embedding +
   box features + the memory room's type; two relational graph convolutions over its six
   relations (above, below, supported_by, next_to, aligned_with, facing). The result is
   summarised per class: ``M[c]`` = mean of the memex nodes of class c.
2. **Bridge edges** into the query graph: OOP node <- memex nodes of its class (``M``),
   OOP node <- scene nodes (mean and max pooled), OOP node <- room-type node, scene node
   <- memex nodes of the same class (``M``), scene node <- OOP node; plus the scene graph's
   own relations (five: the agent's boxes have no front). Two rounds of messages.
3. An MLP on the OOP node: logits over ``PLACE_CLASSES`` (placeable receptacles + Floor),
   trained with cross-entropy on other training rooms (``memex.room_samples``).

**WithoutMemex** is the same network with step 1 and its bridge edges removed (its own
weights). ``RGCNPlacement`` wraps either as a ``PlacementModel`` for the policy: the scene
graph is built from the agent's object memory (detected objects, estimated boxes).

Messages are relation-specific linear maps averaged per (node, relation), as in R-GCN
(Schlichtkrull et al. 2018), with a self connection. Everything runs on the CPU in
milliseconds per query.

Commands: ``tidee train rgcn [--without-memex]`` and ``tidee eval placement``.
"""

from __future__ import annotations

import math
import pickle
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tidee.agent.classes import CLASS_INDEX, CLASSES
from tidee.agent.learning import (
    WEIGHTS_DIR,
    load_checkpoint,
    read_manifest,
    save_checkpoint,
    save_loss_curve,
    write_manifest,
)
from tidee.agent.reasoning.memex import (
    GEOM_FEATURES,
    MEMORY_SEEDS,
    PLACE_CLASSES,
    RELATIONS,
    ROOM_TYPES,
    Graph,
    GraphNode,
    RoomSamples,
    aabb_relations,
    build_memex,
    check_seeds,
    generate_rooms,
    make_graph,
    memory_nodes,
    room_samples,
)
from tidee.agent.reasoning.stats import _ranges

DEFAULT_WEIGHTS = WEIGHTS_DIR / "rgcn.pt"
DEFAULT_WITHOUT_MEMEX = WEIGHTS_DIR / "rgcn_without_memex.pt"
DEFAULT_CACHE = Path("runs/cache/rgcn")
SCENE_RELATIONS = 5  # the agent's axis-aligned boxes give every relation but "facing"


@dataclass
class RGCNConfig:
    hidden: int = 64
    use_memex: bool = True
    dropout: float = 0.1


# --------------------------------------------------------------------- message passing
def relational_mean(x: torch.Tensor, edges: torch.Tensor, weight: torch.Tensor, n_out: int) -> torch.Tensor:
    """Sum over relations r of the mean over (j, r, i) edges of ``x[j] @ weight[r]``, per node i.

    x: N x H_in; edges: E x 3 (src, relation, dst); weight: R x H_in x H_out. Nodes
    without an edge of relation r get nothing from r."""
    out = x.new_zeros(n_out, weight.shape[2])
    if edges.numel() == 0:
        return out
    src, rel, dst = edges[:, 0], edges[:, 1], edges[:, 2]
    xw = torch.einsum("nh,rhk->rnk", x, weight)  # R x N x H_out
    msg = xw[rel, src]  # E x H_out
    key = dst * weight.shape[0] + rel
    count = torch.zeros(n_out * weight.shape[0], dtype=x.dtype, device=x.device)
    count.index_add_(0, key, torch.ones_like(key, dtype=x.dtype))
    out.index_add_(0, dst, msg / count[key].unsqueeze(1))
    return out


class RGCNLayer(nn.Module):
    def __init__(self, hidden: int, relations: int) -> None:
        super().__init__()
        self.self_loop = nn.Linear(hidden, hidden)
        self.weight = nn.Parameter(torch.randn(relations, hidden, hidden) / math.sqrt(hidden))

    def forward(self, x: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        return self.self_loop(x) + relational_mean(x, edges, self.weight, x.shape[0])


def segment_pool(x: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    """Mean and max of the rows of x per segment id (0..n-1): n x 2H (zeros for empty segments)."""
    h = x.shape[1]
    s = x.new_zeros(n, h).index_add_(0, seg, x)
    c = x.new_zeros(n).index_add_(0, seg, torch.ones_like(seg, dtype=x.dtype)).clamp(min=1).unsqueeze(1)
    m = x.new_full((n, h), -1e4).scatter_reduce(0, seg.unsqueeze(1).expand(-1, h), x, reduce="amax")
    m = torch.where(m <= -1e4 + 1, torch.zeros_like(m), m)
    return torch.cat([s / c, m], dim=1)


class PlacementRGCN(nn.Module):
    def __init__(self, cfg: RGCNConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or RGCNConfig()
        h = cfg.hidden
        self.cls = nn.Embedding(len(CLASSES), h)
        self.geom = nn.Sequential(nn.Linear(len(GEOM_FEATURES), h), nn.ReLU(), nn.Linear(h, h))
        self.room = nn.Embedding(len(ROOM_TYPES), h)
        if cfg.use_memex:
            self.mem_layers = nn.ModuleList([RGCNLayer(h, len(RELATIONS)) for _ in range(2)])
            self.mem_to_scene = nn.ModuleList([nn.Linear(h, h) for _ in range(2)])
            self.mem_to_oop = nn.ModuleList([nn.Linear(h, h) for _ in range(2)])
        self.scene_layers = nn.ModuleList([RGCNLayer(h, SCENE_RELATIONS) for _ in range(2)])
        self.oop_to_scene = nn.ModuleList([nn.Linear(h, h) for _ in range(2)])
        self.oop_self = nn.ModuleList([nn.Linear(h, h) for _ in range(2)])
        self.scene_to_oop = nn.ModuleList([nn.Linear(2 * h, h) for _ in range(2)])
        self.room_to_oop = nn.ModuleList([nn.Linear(h, h) for _ in range(2)])
        self.norm_s = nn.ModuleList([nn.LayerNorm(h) for _ in range(2)])
        self.norm_o = nn.ModuleList([nn.LayerNorm(h) for _ in range(2)])
        self.drop = nn.Dropout(cfg.dropout)
        self.head = nn.Sequential(nn.Linear(2 * h, h), nn.ReLU(), nn.Linear(h, len(PLACE_CLASSES)))
        self.register_buffer("mem_labels", torch.zeros(0, dtype=torch.long), persistent=True)
        self.register_buffer("mem_geom", torch.zeros(0, len(GEOM_FEATURES)), persistent=True)
        self.register_buffer("mem_room", torch.zeros(0, dtype=torch.long), persistent=True)
        self.register_buffer("mem_edges", torch.zeros(0, 3, dtype=torch.long), persistent=True)
        self._mem_cache: torch.Tensor | None = None

    def set_memex(self, memex: Graph) -> None:
        self.mem_labels = torch.as_tensor(memex.labels, dtype=torch.long)
        self.mem_geom = torch.as_tensor(memex.geom, dtype=torch.float32)
        self.mem_room = torch.as_tensor(memex.room, dtype=torch.long)
        self.mem_edges = torch.as_tensor(memex.edges, dtype=torch.long)
        self._mem_cache = None

    def embed(self, labels: torch.Tensor, geom: torch.Tensor) -> torch.Tensor:
        return self.cls(labels) + self.geom(geom)

    def memex_by_class(self) -> torch.Tensor:
        """C x H: the mean memex node embedding of each class after the memory's rGCN."""
        if not self.training and self._mem_cache is not None:
            return self._mem_cache
        if self.mem_labels.numel() == 0:
            raise ValueError("this rGCN uses the Memex but none was set (set_memex)")
        x = self.embed(self.mem_labels, self.mem_geom) + self.room(self.mem_room)
        for i, layer in enumerate(self.mem_layers):
            x = F.relu(layer(x, self.mem_edges)) + (x if i else 0)
        by_class = segment_pool(x, self.mem_labels, len(CLASSES))[:, : x.shape[1]]
        if not self.training:
            self._mem_cache = by_class.detach()
        return by_class

    def train(self, mode: bool = True) -> PlacementRGCN:
        self._mem_cache = None
        return super().train(mode)

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Logits B x len(PLACE_CLASSES). batch: scene_labels/geom/edges/seg (scene nodes of all
        samples, edges with global indices, seg = sample of each node), oop_labels/geom, room."""
        b = batch["oop_labels"].shape[0]
        xs = self.drop(self.embed(batch["scene_labels"], batch["scene_geom"]))
        # The object's own heights say where it lies *now* (out of place, or on its home in a
        # training room: a leak), not where it belongs; only its size is kept.
        oop_geom = torch.cat([batch["oop_geom"][:, :3], torch.zeros_like(batch["oop_geom"][:, 3:])], dim=1)
        xo = self.drop(self.embed(batch["oop_labels"], oop_geom))
        room = self.room(batch["room"])
        seg = batch["scene_seg"]
        mem = self.memex_by_class() if self.cfg.use_memex else None
        for k in range(2):
            pooled = segment_pool(xs, seg, b)
            s_in = self.scene_layers[k](xs, batch["scene_edges"]) + self.oop_to_scene[k](xo)[seg]
            o_in = self.oop_self[k](xo) + self.scene_to_oop[k](pooled) + self.room_to_oop[k](room)
            if mem is not None:
                s_in = s_in + self.mem_to_scene[k](mem[batch["scene_labels"]])
                o_in = o_in + self.mem_to_oop[k](mem[batch["oop_labels"]])
            xs = self.norm_s[k](F.relu(s_in) + xs)
            xo = self.norm_o[k](F.relu(o_in) + xo)
        return self.head(torch.cat([xo, room], dim=1))


# --------------------------------------------------------------------- batches
def collate(
    items: Sequence[tuple[Graph, int, np.ndarray | None, int]],
    keep: Sequence[np.ndarray] | None = None,
    oop_geom_override: Sequence[np.ndarray] | None = None,
) -> dict[str, torch.Tensor]:
    """One batch from (room graph, index of the OOP node or -1, OOP geom if not in the graph,
    room type index). The OOP node is taken out of its scene graph with its edges; ``keep``
    (bool per node) drops further scene nodes (training augmentation)."""
    labels, geom, edges, seg, o_lab, o_geom, rooms = [], [], [], [], [], [], []
    offset = 0
    for s, (g, t, tgeom, room) in enumerate(items):
        mask = np.ones(len(g), bool) if keep is None else keep[s].copy()
        if t >= 0:
            mask[t] = False
            o_lab.append(int(g.labels[t]))
            o_geom.append(g.geom[t] if oop_geom_override is None else oop_geom_override[s])
        else:
            if tgeom is None:
                raise ValueError("an OOP node outside the graph needs its geometry")
            o_lab.append(int(tgeom[0]))
            o_geom.append(tgeom[1:])
        idx = np.full(len(g), -1, np.int64)
        idx[mask] = np.arange(int(mask.sum())) + offset
        labels.append(g.labels[mask])
        geom.append(g.geom[mask])
        if g.edges.size:
            e = g.edges[mask[g.edges[:, 0]] & mask[g.edges[:, 2]]]
            edges.append(np.stack([idx[e[:, 0]], e[:, 1], idx[e[:, 2]]], axis=1))
        seg.append(np.full(int(mask.sum()), s, np.int64))
        rooms.append(room)
        offset += int(mask.sum())
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)
    return {
        "scene_labels": torch.as_tensor(cat(labels, (0,)), dtype=torch.long),
        "scene_geom": torch.as_tensor(cat(geom, (0, len(GEOM_FEATURES))), dtype=torch.float32),
        "scene_edges": torch.as_tensor(cat(edges, (0, 3)), dtype=torch.long).reshape(-1, 3),
        "scene_seg": torch.as_tensor(cat(seg, (0,)), dtype=torch.long),
        "oop_labels": torch.as_tensor(np.array(o_lab), dtype=torch.long),
        "oop_geom": torch.as_tensor(np.stack(o_geom), dtype=torch.float32),
        "room": torch.as_tensor(np.array(rooms), dtype=torch.long),
    }


# --------------------------------------------------------------------- data
@dataclass
class PlacementData:
    memex: Graph
    rooms: list[RoomSamples]
    memory_seeds: list[int]
    train_seeds: list[int]

    @property
    def n_samples(self) -> int:
        return int(sum(len(r.targets) for r in self.rooms))


def _seed_list(rooms_per_type: int, skip: int = 0) -> list[int]:
    from tidee.agent.perception.dataset import room_seeds

    return room_seeds("train", rooms_per_type, skip)


def placement_data(
    train_rooms_per_type: int = 200,
    memory_seeds: Sequence[int] = MEMORY_SEEDS,
    cache_dir: str | Path | None = DEFAULT_CACHE,
    progress: bool = True,
) -> PlacementData:
    """The Memex (memory rooms) and training samples (the next ``train_rooms_per_type`` training
    seeds of every type after the memory rooms). Cached as a pickle keyed by the seeds."""
    mem = list(memory_seeds)
    train = [s for s in _seed_list(train_rooms_per_type + len(mem)) if s not in set(mem)][
        :train_rooms_per_type
    ]
    check_seeds(mem, train)
    return _cached(
        f"train_m{mem[0]}-{mem[-1]}_n{len(train)}",
        cache_dir,
        lambda: PlacementData(
            build_memex(generate_rooms(ROOM_TYPES, mem, progress)),
            [room_samples(s) for s in generate_rooms(ROOM_TYPES, train, progress)],
            mem,
            train,
        ),
    )


def heldout_rooms(
    split: str = "test", cache_dir: str | Path | None = DEFAULT_CACHE, progress: bool = True
) -> list[RoomSamples]:
    """Samples of the tidy held-out rooms (evaluation only)."""
    from tidee.server.splits import SPLIT_SEEDS

    if split not in ("val", "test"):
        raise ValueError(f"evaluation rooms come from val or test, got {split!r}")
    seeds = list(SPLIT_SEEDS[split])
    return _cached(
        f"{split}", cache_dir, lambda: [room_samples(s) for s in generate_rooms(ROOM_TYPES, seeds, progress)]
    )


def _cached(key: str, cache_dir: str | Path | None, build):
    path = None if cache_dir is None else Path(cache_dir) / f"{key}.pkl"
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes())
    value = build()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps(value))
        tmp.replace(path)
    return value


def _augment(g: Graph, t: int, rng: np.random.Generator, drop: float) -> tuple[np.ndarray, np.ndarray]:
    """Scene nodes kept (the agent never maps every object) and the OOP box with estimation noise."""
    keep = rng.random(len(g)) >= drop
    geom = g.geom[t].copy()
    geom[:3] += rng.normal(0.0, 0.12, 3)  # log sizes: +-12 % (its heights are not read)
    return keep, geom


# --------------------------------------------------------------------- training
@dataclass
class RGCNTrainConfig:
    steps: int = 3000
    batch_size: int = 128
    lr: float = 2e-3
    weight_decay: float = 1e-4
    node_drop: float = 0.25
    seed: int = 0
    train_rooms_per_type: int = 200
    use_memex: bool = True
    hidden: int = 64
    threads: int = 2


def train_rgcn(
    cfg: RGCNTrainConfig,
    out: str | Path | None = None,
    loss_png: str | Path | None = None,
    command: str = "tidee train rgcn",
    data: PlacementData | None = None,
    progress: bool = True,
    cache_dir: str | Path | None = DEFAULT_CACHE,
) -> dict[str, Any]:
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    data = data or placement_data(cfg.train_rooms_per_type, cache_dir=cache_dir, progress=progress)
    index = [(r, k) for r, room in enumerate(data.rooms) for k in range(len(room.targets))]
    if not index:
        raise ValueError("no training samples: the training rooms have no pickupable object on a receptacle")
    model = PlacementRGCN(RGCNConfig(hidden=cfg.hidden, use_memex=cfg.use_memex))
    if cfg.use_memex:
        model.set_memex(data.memex)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    history: list[dict[str, float]] = []
    t0 = time.time()
    model.train()
    running = []
    bar = tqdm(
        range(cfg.steps), desc="rgcn" if cfg.use_memex else "rgcn (without memex)", disable=not progress
    )
    for step in bar:
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps))
        for group in opt.param_groups:
            group["lr"] = lr
        pick = rng.integers(0, len(index), cfg.batch_size)
        items, keep, geoms, ys = [], [], [], []
        for p in pick:
            r, k = index[p]
            room = data.rooms[r]
            t = int(room.targets[k])
            kp, geom = _augment(room.graph, t, rng, cfg.node_drop)
            items.append((room.graph, t, None, ROOM_TYPES.index(room.room_type)))
            keep.append(kp)
            geoms.append(geom)
            ys.append(int(room.labels[k]))
        batch = collate(items, keep, geoms)
        loss = F.cross_entropy(model(batch), torch.as_tensor(ys))
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        running.append(float(loss.detach()))
        if (step + 1) % 50 == 0 or step + 1 == cfg.steps:
            history.append({"step": step + 1, "cross_entropy": float(np.mean(running))})
            bar.set_postfix(loss=f"{np.mean(running):.3f}")
            running = []
    seconds = time.time() - t0
    result: dict[str, Any] = {
        "history": history,
        "seconds": round(seconds, 1),
        "samples": len(index),
        "memex_nodes": len(data.memex) if cfg.use_memex else 0,
        "model": model,
    }
    if out is not None:
        out = Path(out)
        save_checkpoint(out, state_dict=model.state_dict(), config=asdict(model.cfg))
        if loss_png is not None:
            save_loss_curve(
                history, loss_png, "rGCN placement" + ("" if cfg.use_memex else " (WithoutMemex)")
            )
        write_manifest(
            out,
            command=command,
            data={
                "memory_rooms": {"room_types": list(ROOM_TYPES), "seeds": data.memory_seeds},
                "training_rooms": {
                    "room_types": list(ROOM_TYPES),
                    "seeds": _ranges(data.train_seeds),
                    "n_per_type": len(data.train_seeds),
                },
                "samples": len(index),
                "memex_nodes": result["memex_nodes"],
                "memex_edges": int(len(data.memex.edges)) if cfg.use_memex else 0,
            },
            metrics={"final_train_cross_entropy": history[-1]["cross_entropy"]},
            train_config=asdict(cfg),
            train_seconds=round(seconds, 1),
            parameters=int(sum(p.numel() for p in model.parameters())),
        )
        result["out"] = str(out)
    return result


def load_rgcn(path: str | Path = DEFAULT_WEIGHTS) -> tuple[PlacementRGCN, dict[str, Any]]:
    manifest = read_manifest(path)
    ckpt = load_checkpoint(path)
    model = PlacementRGCN(RGCNConfig(**ckpt["config"]))
    sd = ckpt["state_dict"]
    for k in ("mem_labels", "mem_geom", "mem_room", "mem_edges"):  # buffers sized by the memex
        setattr(model, k, sd[k].clone())
    model.load_state_dict(sd)
    model.eval()
    return model, manifest


# --------------------------------------------------------------------- the policy's interface
class RGCNPlacement:
    """``PlacementModel``: ranks receptacle classes for a picked-up object from the agent's
    object memory (its scene graph) and, for TIDEE, the Memex."""

    def __init__(self, model: PlacementRGCN, manifest: dict[str, Any] | None = None) -> None:
        self.model = model.eval()
        self.manifest = manifest or {}
        self.name = "rGCN" if model.cfg.use_memex else "rGCN (WithoutMemex)"

    @staticmethod
    def load(path: str | Path = DEFAULT_WEIGHTS) -> RGCNPlacement:
        model, manifest = load_rgcn(path)
        return RGCNPlacement(model, manifest)

    def rank_nodes(
        self, label: str, geom: np.ndarray, scene: Sequence[GraphNode], room_type: str
    ) -> list[tuple[str, float]]:
        if label not in CLASS_INDEX:
            raise ValueError(f"unknown object class {label!r}")
        if room_type not in ROOM_TYPES:
            raise ValueError(f"room_type must be one of {ROOM_TYPES}, got {room_type!r}")
        g = make_graph(list(scene), aabb_relations(scene))
        tgeom = np.concatenate([[CLASS_INDEX[label]], np.asarray(geom, np.float32)])
        with torch.no_grad():
            p = torch.softmax(self.model(collate([(g, -1, tgeom, ROOM_TYPES.index(room_type))])), dim=1)[0]
        order = torch.argsort(p, descending=True).tolist()
        return [(PLACE_CLASSES[i], float(p[i])) for i in order]

    def predict(self, obj, memory, room_type: str) -> list[tuple[str, float]]:
        node = GraphNode(
            obj.label, tuple(float(v) for v in obj.box_min), tuple(float(v) for v in obj.box_max)
        )
        return self.rank_nodes(obj.label, node.geom(), memory_nodes(memory, exclude_id=obj.id), room_type)


def rank_rooms(model: PlacementRGCN, rooms: Sequence[RoomSamples], batch: int = 256) -> list[np.ndarray]:
    """Probabilities (S x K) for every sample of every room (the object taken out, no augmentation)."""
    model.eval()
    out = []
    with torch.no_grad():
        for room in rooms:
            items = [(room.graph, int(t), None, ROOM_TYPES.index(room.room_type)) for t in room.targets]
            probs = [
                torch.softmax(model(collate(items[i : i + batch])), dim=1).numpy()
                for i in range(0, len(items), batch)
            ]
            out.append(np.concatenate(probs) if probs else np.zeros((0, len(PLACE_CLASSES)), np.float32))
    return out


__all__ = [
    "RGCNConfig",
    "PlacementRGCN",
    "RGCNLayer",
    "relational_mean",
    "segment_pool",
    "collate",
    "PlacementData",
    "placement_data",
    "heldout_rooms",
    "RGCNTrainConfig",
    "train_rgcn",
    "load_rgcn",
    "RGCNPlacement",
    "rank_rooms",
    "DEFAULT_WEIGHTS",
    "DEFAULT_WITHOUT_MEMEX",
]


# --------------------------------------------------------------------- evaluation
def _choice(ranked: Sequence[str], present: Sequence[str]) -> str | None:
    """The receptacle the policy would go to with a complete map: the first ranked one in the room."""
    have = set(present) | {"Floor"}
    return next((r for r in ranked if r in have), None)


def evaluate_placement(rooms: Sequence[RoomSamples], rankers: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Per ranker: top-1 / top-3 accuracy against the receptacle each object had in the tidy
    held-out room, and the simulated judge's score (and plausible rate) of the receptacle the
    policy would choose. ``rankers``: name -> PlacementRGCN or a function
    (room, sample index) -> ranked receptacle names."""
    from tidee.agent.evaluation.judge import judge_score, plausible

    out: dict[str, dict[str, float]] = {}
    for name, ranker in rankers.items():
        if isinstance(ranker, PlacementRGCN):
            probs = rank_rooms(ranker, rooms)
            ranked_of = lambda r, k, probs=probs: [
                PLACE_CLASSES[i] for i in np.argsort(-probs[r][k], kind="stable")
            ]
        else:
            ranked_of = ranker
        top1 = top3 = judge = ok = n = 0.0
        for r, room in enumerate(rooms):
            for k in range(len(room.targets)):
                ranked = ranked_of(r, k)
                truth = PLACE_CLASSES[int(room.labels[k])]
                top1 += ranked[:1] == [truth]
                top3 += truth in ranked[:3]
                cat = CLASSES[int(room.graph.labels[int(room.targets[k])])]
                choice = _choice(ranked, room.present)
                judge += judge_score(cat, room.variants[k], room.room_type, choice, room.present)
                ok += plausible(cat, room.variants[k], room.room_type, choice, room.present)
                n += 1
        out[name] = {
            "top1": top1 / max(n, 1),
            "top3": top3 / max(n, 1),
            "judge_score": judge / max(n, 1),
            "plausible": ok / max(n, 1),
            "samples": int(n),
        }
    return out


def run_placement_eval(
    out: str | Path,
    split: str = "test",
    weights: str | Path = DEFAULT_WEIGHTS,
    without_memex: str | Path | None = DEFAULT_WITHOUT_MEMEX,
    cache_dir: str | Path | None = DEFAULT_CACHE,
    progress: bool = True,
    command: str = "tidee eval placement",
    record: bool = False,
) -> dict[str, Any]:
    """``tidee eval placement``: rGCN (TIDEE), WithoutMemex and CommonMemory on the tidy rooms of
    a held-out split; JSON + Markdown in ``out``."""
    from tidee.agent.learning import update_manifest_metrics
    from tidee.agent.reasoning.stats import PlacementStats
    from tidee.protocol.episode_log import write_json_atomic

    rooms = heldout_rooms(split, cache_dir, progress)
    stats = PlacementStats.load()
    names = {r: i for i, r in enumerate(PLACE_CLASSES)}

    def common(r: int, k: int) -> list[str]:
        cat = CLASSES[int(rooms[r].graph.labels[int(rooms[r].targets[k])])]
        return [c for c, _ in stats.ranked(cat) if c in names]

    rankers: dict[str, Any] = {"TIDEE (Memex + rGCN)": load_rgcn(weights)[0]}
    if without_memex is not None and Path(without_memex).exists():
        rankers["WithoutMemex (scene rGCN)"] = load_rgcn(without_memex)[0]
    rankers["CommonMemory"] = common
    result = evaluate_placement(rooms, rankers)
    report = {
        "command": command,
        "split": split,
        "rooms": len(rooms),
        "samples": next(iter(result.values()))["samples"],
        "rows": result,
        "note": "Scene graphs from the simulator's boxes made axis-aligned (a complete map); one sample "
        "per pickupable object of each tidy room, taken out of its graph. top-1/top-3: the "
        "receptacle type it had; judge: the simulated judge's score of the first ranked "
        "receptacle present in the room (what the policy would choose).",
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "report.json", report)
    lines = [
        f"# Placement: where does an object belong? ({split} rooms)",
        "",
        f"`{command}` — {len(rooms)} tidy rooms, {report['samples']} objects.",
        "",
        "| ranker | top-1 | top-3 | judge score | plausible |",
        "|---|---|---|---|---|",
    ]
    for name, m in result.items():
        lines.append(
            f"| {name} | {100 * m['top1']:.1f} | {100 * m['top3']:.1f} | {m['judge_score']:.3f} | "
            f"{100 * m['plausible']:.1f} |"
        )
    lines += ["", report["note"], ""]
    (out / "report.md").write_text("\n".join(lines))
    if record:
        for name, path in (("TIDEE (Memex + rGCN)", weights), ("WithoutMemex (scene rGCN)", without_memex)):
            if name in result and path is not None:
                update_manifest_metrics(
                    path,
                    {
                        f"{split}_{k}": round(v, 4) if isinstance(v, float) else v
                        for k, v in result[name].items()
                    },
                )
    return report
