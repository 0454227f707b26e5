"""Object graphs for placement reasoning: scene graphs and the Memex (the runtime half).

The paper's rGCN (§3.3, supplement "Relational graph convolutional network", "Memex
graph") infers where a picked-up object belongs from two graphs:

* the **scene graph** of the room the agent is tidying: one node per object it has
  mapped, edges for the spatial relations between their 3D boxes;
* the **Memex**: the same kind of graph over the objects of a few *memory rooms* of
  every room type (training rooms; here 5 per type), built once and shipped with the
  model. It is a memory of typical arrangements ("mugs sit on counters next to coffee
  machines").

A node is a category plus a small appearance vector. We describe appearance by the
object's 3D box (``GEOM_FEATURES``): the box is what separates the sub-category
variants whose home differs (a tall floor lamp from a desk lamp, a large vase from a
small one). The detector's 64-d features are not used: training graphs come from
simulator boxes, which have no rendered features (see ``model`` for the consequence).

Edges: the relations of :func:`tidee.agent.reasoning.relations.box_relations` —
above, below, supported_by, next_to, aligned_with, facing. Memex boxes come from the
simulator (oriented: all six relations). Scene boxes come from the agent's object
memory, which keeps axis-aligned boxes without a front, so scene graphs use
:func:`aabb_relations` (the first five, vectorised; equal to ``box_relations`` on
yaw-0 boxes, which a test checks). Training scene graphs are built the same way from
the simulator's boxes made axis-aligned (:mod:`.data`), so the model sees at test time
what it saw in training.

This module reads no torch and no simulator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tidee.agent.classes import CLASS_INDEX, CLASSES, PLACEABLE_RECEPTACLES
from tidee.agent.reasoning.relations import Box3D, box_relations
from tidee.protocol.vocab import ROOM_TYPES

RELATIONS = ("above", "below", "supported_by", "next_to", "aligned_with", "facing")
REL_INDEX = {r: i for i, r in enumerate(RELATIONS)}
FLOOR = "Floor"
# What the model ranks: every receptacle an object is put on or in, and the floor.
PLACE_CLASSES: tuple[str, ...] = tuple(sorted(PLACEABLE_RECEPTACLES)) + (FLOOR,)
PLACE_INDEX = {c: i for i, c in enumerate(PLACE_CLASSES)}
GEOM_FEATURES = ("log_long_side", "log_short_side", "log_height", "z_bottom", "z_top")


@dataclass(frozen=True)
class GraphNode:
    """One object: category, axis-aligned box (metres, floor at z = 0) and, when known, yaw."""

    label: str
    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]
    yaw: float | None = None  # radians; None: unknown (the agent's boxes)
    size: tuple[float, float, float] | None = None  # oriented extents when yaw is known

    def geom(self) -> np.ndarray:
        lo, hi = np.asarray(self.box_min, float), np.asarray(self.box_max, float)
        ext = np.maximum(hi - lo, 1e-3)
        if self.size is not None:
            ext = np.maximum(np.asarray(self.size, float), 1e-3)
        long_side, short_side = max(ext[0], ext[1]), min(ext[0], ext[1])
        return np.array(
            [math.log(long_side), math.log(short_side), math.log(ext[2]), lo[2], hi[2]], np.float32
        )


@dataclass
class Graph:
    """Nodes as arrays plus (src, relation, dst) edges: "src <relation> dst"."""

    labels: np.ndarray  # int64 N: CLASS_INDEX
    geom: np.ndarray  # float32 N x len(GEOM_FEATURES)
    edges: np.ndarray  # int64 E x 3: src, relation index, dst
    room: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # int64 N: room type index

    def __post_init__(self) -> None:
        n = len(self.labels)
        if self.geom.shape != (n, len(GEOM_FEATURES)):
            raise ValueError(f"geom must be {n} x {len(GEOM_FEATURES)}, got {self.geom.shape}")
        if self.edges.size and (self.edges[:, [0, 2]].max() >= n or self.edges.min() < 0):
            raise ValueError(f"edges reference nodes outside 0..{n - 1}")
        if self.room.size and len(self.room) != n:
            raise ValueError(f"room must have one entry per node ({n}), got {len(self.room)}")

    def __len__(self) -> int:
        return len(self.labels)


def _box3d(n: GraphNode) -> Box3D:
    lo, hi = np.asarray(n.box_min, float), np.asarray(n.box_max, float)
    centre = (lo + hi) / 2.0
    if n.yaw is not None and n.size is not None:
        return Box3D(center=tuple(centre), size=tuple(max(s, 1e-3) for s in n.size), yaw=n.yaw)
    return Box3D(center=tuple(centre), size=tuple(np.maximum(hi - lo, 1e-3)), yaw=0.0)


def aabb_relations(
    nodes: Sequence[GraphNode],
    vertical_tol: float = 0.05,
    contact_tol: float = 0.05,
    support_margin: float = 0.02,
    next_to_m: float = 0.5,
    align_plane_m: float = 0.1,
    align_max_gap_m: float = 1.0,
) -> np.ndarray:
    """int64 E x 3 (i, relation, j) for axis-aligned boxes: above, below, supported_by, next_to,
    aligned_with — the rules of ``box_relations`` (same defaults) for yaw-0 boxes, vectorised."""
    n = len(nodes)
    if n < 2:
        return np.zeros((0, 3), np.int64)
    lo = np.array([nd.box_min for nd in nodes], float)
    hi = np.array([nd.box_max for nd in nodes], float)
    eps = 1e-6
    # footprints share area (separating axis with eps, as relations._polys_overlap)
    ox = np.minimum(hi[:, None, 0], hi[None, :, 0]) - np.maximum(lo[:, None, 0], lo[None, :, 0])
    oy = np.minimum(hi[:, None, 1], hi[None, :, 1]) - np.maximum(lo[:, None, 1], lo[None, :, 1])
    overlap = (ox > eps) & (oy > eps)
    above = (lo[:, None, 2] >= hi[None, :, 2] - vertical_tol) & overlap  # i above j
    below = above.T
    cx, cy = (lo[:, 0] + hi[:, 0]) / 2, (lo[:, 1] + hi[:, 1]) / 2
    inside = (
        np.abs(cx[:, None] - (lo[None, :, 0] + hi[None, :, 0]) / 2)
        <= (hi[None, :, 0] - lo[None, :, 0]) / 2 + support_margin
    ) & (
        np.abs(cy[:, None] - (lo[None, :, 1] + hi[None, :, 1]) / 2)
        <= (hi[None, :, 1] - lo[None, :, 1]) / 2 + support_margin
    )
    supported = above & (np.abs(lo[:, None, 2] - hi[None, :, 2]) <= contact_tol) & inside
    gap_x = np.maximum(0.0, -ox)
    gap_y = np.maximum(0.0, -oy)
    gap = np.where((ox >= 0) & (oy >= 0), 0.0, np.hypot(gap_x, gap_y))
    z_over = (
        np.maximum(lo[:, None, 2], lo[None, :, 2])
        <= np.minimum(hi[:, None, 2], hi[None, :, 2]) + vertical_tol
    )
    next_to = ~above & ~below & z_over & (gap <= next_to_m)
    planes = []
    for ax in (0, 1):
        for a in (lo, hi):
            for b in (lo, hi):
                planes.append(np.abs(a[:, None, ax] - b[None, :, ax]) <= align_plane_m)
    aligned = np.logical_or.reduce(planes) & (gap <= align_max_gap_m)
    out = []
    off_diag = ~np.eye(n, dtype=bool)
    for rel, m in (
        ("above", above),
        ("below", below),
        ("supported_by", supported),
        ("next_to", next_to),
        ("aligned_with", aligned),
    ):
        i, j = np.nonzero(m & off_diag)
        out.append(np.stack([i, np.full_like(i, REL_INDEX[rel]), j], axis=1))
    e = np.concatenate(out).astype(np.int64)
    return e[np.lexsort((e[:, 1], e[:, 2], e[:, 0]))]


def oriented_relations(nodes: Sequence[GraphNode]) -> np.ndarray:
    """int64 E x 3: all six relations of ``box_relations`` on the nodes' oriented boxes."""
    triples = box_relations([(nd.label, _box3d(nd)) for nd in nodes])
    if not triples:
        return np.zeros((0, 3), np.int64)
    return np.array([(i, REL_INDEX[r], j) for i, r, j in triples], np.int64)


def make_graph(nodes: Sequence[GraphNode], edges: np.ndarray, room_type: str | None = None) -> Graph:
    unknown = sorted({nd.label for nd in nodes} - set(CLASS_INDEX))
    if unknown:
        raise ValueError(f"graph nodes of unknown classes {unknown}; known: the {len(CLASSES)} CLASSES")
    room = (
        np.full(len(nodes), ROOM_TYPES.index(room_type), np.int64)
        if room_type is not None
        else np.zeros(0, np.int64)
    )
    geom = np.stack([nd.geom() for nd in nodes]) if nodes else np.zeros((0, len(GEOM_FEATURES)), np.float32)
    return Graph(
        labels=np.array([CLASS_INDEX[nd.label] for nd in nodes], np.int64),
        geom=geom,
        edges=np.asarray(edges, np.int64).reshape(-1, 3),
        room=room,
    )


def corner(v: Any) -> tuple[float, float, float]:
    """A box corner (any 3-sequence) as three floats."""
    return float(v[0]), float(v[1]), float(v[2])


def memory_nodes(memory, exclude_id: int | None = None) -> list[GraphNode]:
    """GraphNodes of the agent's ``ObjectMemory`` (start frame; heights are world heights)."""
    return [
        GraphNode(o.label, corner(o.box_min), corner(o.box_max))
        for o in memory
        if o.id != exclude_id and o.label in CLASS_INDEX
    ]
