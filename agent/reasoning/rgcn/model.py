"""Memex + rGCN: where does a picked-up object belong? (paper §3.3, supplement "Relational
graph convolutional network"). The network and the agent's placement model (runtime).

The network, for one out-of-place (OOP) object in a room:

1. **Memex** (``data.build_memex``: 5 memory rooms per type): node = class embedding +
   box features + the memory room's type; two relational graph convolutions over its six
   relations (above, below, supported_by, next_to, aligned_with, facing). The result is
   summarised per class: ``M[c]`` = mean of the memex nodes of class c.
2. **Bridge edges** into the query graph: OOP node <- memex nodes of its class (``M``),
   OOP node <- scene nodes (mean and max pooled), OOP node <- room-type node, scene node
   <- memex nodes of the same class (``M``), scene node <- OOP node; plus the scene graph's
   own relations (five: the agent's boxes have no front). Two rounds of messages.
3. An MLP on the OOP node: logits over ``PLACE_CLASSES`` (placeable receptacles + Floor),
   trained with cross-entropy on other training rooms (``data.room_samples``, ``train``).

**WithoutMemex** is the same network with step 1 and its bridge edges removed (its own
weights). ``RGCNPlacement`` wraps either as a ``PlacementModel`` for the policy: the scene
graph is built from the agent's object memory (detected objects, estimated boxes).

Messages are relation-specific linear maps averaged per (node, relation), as in R-GCN
(Schlichtkrull et al. 2018), with a self connection. Everything runs on the CPU in
milliseconds per query.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tidee.agent.classes import CLASS_INDEX, CLASSES
from tidee.agent.learning import WEIGHTS_DIR, load_checkpoint, read_manifest
from tidee.agent.reasoning.rgcn.config import RGCNConfig
from tidee.agent.reasoning.rgcn.memex import (
    GEOM_FEATURES,
    PLACE_CLASSES,
    RELATIONS,
    Graph,
    GraphNode,
    aabb_relations,
    corner,
    make_graph,
    memory_nodes,
)
from tidee.protocol.vocab import ROOM_TYPES

DEFAULT_WEIGHTS = WEIGHTS_DIR / "rgcn.pt"
DEFAULT_WITHOUT_MEMEX = WEIGHTS_DIR / "rgcn_without_memex.pt"
SCENE_RELATIONS = 5  # the agent's axis-aligned boxes give every relation but "facing"


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
        node = GraphNode(obj.label, corner(obj.box_min), corner(obj.box_max))
        return self.rank_nodes(obj.label, node.geom(), memory_nodes(memory, exclude_id=obj.id), room_type)


__all__ = [
    "DEFAULT_WEIGHTS",
    "DEFAULT_WITHOUT_MEMEX",
    "PlacementRGCN",
    "RGCNConfig",
    "RGCNLayer",
    "RGCNPlacement",
    "collate",
    "load_rgcn",
    "relational_mean",
    "segment_pool",
]
