"""The rGCN's data: tidy rooms from the simulator, as the Memex and as training or held-out samples.

Training samples (``room_samples``): in a tidy training room, each pickupable object in
turn is taken out of the scene graph; its receptacle type is the label. Memory rooms
and training rooms never overlap (``check_seeds``), and val/test rooms are refused.
Scene objects are privileged ground truth: this module serves training and evaluation,
never the agent.
"""

from __future__ import annotations

import math
import pickle
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tidee.agent.classes import CLASS_INDEX, PICKUPABLE
from tidee.agent.reasoning.rgcn.config import DEFAULT_CACHE
from tidee.agent.reasoning.rgcn.memex import (
    PLACE_INDEX,
    Graph,
    GraphNode,
    aabb_relations,
    make_graph,
    oriented_relations,
)
from tidee.protocol.vocab import HELD_OUT_SPLITS, ROOM_TYPES
from tidee.server.scene import quat_yaw

MEMORY_SEEDS = range(0, 5)  # per room type: the Memex rooms (train split)


# --------------------------------------------------------------------- from the simulator
def scene_nodes(scene) -> tuple[list[GraphNode], list]:
    """GraphNodes of a ``server.scene.Scene``'s objects (privileged: training and evaluation only),
    with the scene objects they came from. Boxes are world-frame, floor at z = 0."""
    nodes, objs = [], []
    for o in scene.objects:
        if o.type not in CLASS_INDEX:
            continue
        yaw = quat_yaw(o.orientation)
        sx, sy, sz = (float(v) for v in o.size)
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        hx, hy = (c * sx + s * sy) / 2, (s * sx + c * sy) / 2
        x, y, z = (float(v) for v in o.position)
        nodes.append(
            GraphNode(o.type, (x - hx, y - hy, z), (x + hx, y + hy, z + sz), yaw=yaw, size=(sx, sy, sz))
        )
        objs.append(o)
    return nodes, objs


def axis_aligned(nodes: Iterable[GraphNode]) -> list[GraphNode]:
    """The same boxes as the agent would keep them: axis-aligned, no yaw."""
    return [GraphNode(n.label, n.box_min, n.box_max) for n in nodes]


def check_seeds(memory_seeds: Iterable[int], train_seeds: Iterable[int]) -> None:
    """Memory rooms and training rooms are training seeds and never overlap."""
    from tidee.server.splits import SPLIT_SEEDS, split_of

    mem, train = set(memory_seeds), set(train_seeds)
    for name, seeds in (("memory", mem), ("training", train)):
        bad = sorted(s for s in seeds if split_of(s) not in ("train", "train_pool"))
        if bad:
            raise ValueError(
                f"{name} rooms must be training seeds ({SPLIT_SEEDS['train']} or the pool), got {bad[:5]}"
            )
    both = sorted(mem & train)
    if both:
        raise ValueError(
            f"seeds {both[:5]} are both Memex memory rooms and rGCN training rooms; they must differ"
        )


@dataclass
class RoomSamples:
    """One tidy room as the rGCN's training data: the full scene graph and, per sample, the
    object taken out and the receptacle it was on (PLACE_INDEX)."""

    room_type: str
    seed: int
    graph: Graph  # the whole room, axis-aligned boxes, five relations
    targets: np.ndarray  # int64 S: node index of the object taken out
    labels: np.ndarray  # int64 S: PLACE_INDEX of its receptacle
    variants: list[str | None]  # S: catalog variant (evaluation only: the judge needs it)
    present: list[str]  # receptacle types in the room (evaluation only)


def room_samples(scene) -> RoomSamples:
    nodes, objs = scene_nodes(scene)
    aa = axis_aligned(nodes)
    graph = make_graph(aa, aabb_relations(aa), scene.room_type)
    targets, labels, variants = [], [], []
    for i, o in enumerate(objs):
        if o.type in PICKUPABLE and o.pickupable and o.parent_type in PLACE_INDEX:
            targets.append(i)
            labels.append(PLACE_INDEX[o.parent_type])
            variants.append(o.variant)
    present = sorted({o.type for o in scene.objects if o.receptacle and not o.pickupable})
    return RoomSamples(
        scene.room_type,
        int(scene.seed),
        graph,
        np.array(targets, np.int64),
        np.array(labels, np.int64),
        variants,
        present,
    )


def build_memex(scenes: Iterable) -> Graph:
    """The Memex: the memory rooms' objects with oriented boxes and all six relations, one graph."""
    labels, geom, edges, room = [], [], [], []
    offset = 0
    for scene in scenes:
        nodes, _ = scene_nodes(scene)
        g = make_graph(nodes, oriented_relations(nodes), scene.room_type)
        labels.append(g.labels)
        geom.append(g.geom)
        room.append(g.room)
        e = g.edges.copy()
        e[:, [0, 2]] += offset
        edges.append(e)
        offset += len(g)
    return Graph(np.concatenate(labels), np.concatenate(geom), np.concatenate(edges), np.concatenate(room))


def generate_rooms(room_types: Sequence[str], seeds: Sequence[int], progress: bool = True) -> list:
    """Tidy training rooms (``server.rooms.generate_scene``) in one simulator."""
    from tqdm import tqdm

    from tidee.server.rooms import generate_scene
    from tidee.server.world import World

    world = World(renderer="tiny")
    try:
        jobs = [(rt, s) for s in seeds for rt in room_types]
        return [
            generate_scene(rt, s, world=world) for rt, s in tqdm(jobs, desc="rooms", disable=not progress)
        ]
    finally:
        world.close()


# --------------------------------------------------------------------- training and held-out sets
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
    from tidee.agent.perception.detector.config import room_seeds

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

    if split not in HELD_OUT_SPLITS:
        raise ValueError(f"evaluation rooms come from {' or '.join(HELD_OUT_SPLITS)}, got {split!r}")
    seeds = list(SPLIT_SEEDS[split])
    return _cached(
        f"{split}", cache_dir, lambda: [room_samples(s) for s in generate_rooms(ROOM_TYPES, seeds, progress)]
    )


def _cached(key: str, cache_dir: str | Path | None, build):
    path = None if cache_dir is None else Path(cache_dir) / f"{key}.pkl"
    if path is not None and path.is_file():
        try:
            return pickle.loads(path.read_bytes())
        except (ModuleNotFoundError, AttributeError, pickle.UnpicklingError, EOFError):
            pass  # written by code whose classes have moved or changed: generate the rooms again
    value = build()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps(value))
        tmp.replace(path)
    return value
