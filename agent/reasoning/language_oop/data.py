"""Training and evaluation samples of the language OOP head from ground-truth rooms.

:func:`language_oop_samples` builds one paragraph per pickupable object of the messy
configurations of a split from ground-truth boxes (label: moved by the mess-up). The object
states of a configuration are cached on disk (the mess-up physics costs seconds).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from tidee.agent.classes import CLASSES, PICKUPABLE, RECEPTACLES
from tidee.agent.perception.detector.config import room_seeds
from tidee.agent.reasoning.language_oop.config import DEFAULT_CACHE_DIR
from tidee.agent.reasoning.language_oop.paragraphs import object_paragraph
from tidee.agent.reasoning.relations import ObjectRef
from tidee.protocol.vocab import ROOM_TYPES
from tidee.server.splits import MESSES_PER_ROOM


class OOPSample(NamedTuple):
    paragraph: str
    label: int  # 1: out of place (moved by the mess-up), 0: in place
    room_type: str
    category: str


def object_record(state: Mapping[str, Any]) -> dict[str, Any]:
    """A compact object record from an ``Episode.object_states()`` entry.

    ``position`` is the bottom-centre of the object's box in its own frame, ``size`` the
    box's extents and ``orientation`` a quaternion (x, y, z, w): the axis-aligned world box
    is the hull of the rotated corners; the centroid is its centre.
    """
    from scipy.spatial.transform import Rotation

    sx, sy, sz = (float(v) for v in state["size"])
    corners = np.array([[x, y, z] for x in (-sx / 2, sx / 2) for y in (-sy / 2, sy / 2) for z in (0.0, sz)])
    world = Rotation.from_quat(state["orientation"]).apply(corners) + np.asarray(state["position"], float)
    lo, hi = world.min(0), world.max(0)
    return {
        "id": str(state["id"]),
        "type": str(state["type"]),
        "moved": bool(state["moved"]),
        "centroid": [round(float(v), 5) for v in (lo + hi) / 2],
        "box_min": [round(float(v), 5) for v in lo],
        "box_max": [round(float(v), 5) for v in hi],
    }


def _config_key(room_type: str, seed: int, mess_index: int) -> str:
    return f"{room_type}:{int(seed)}:{int(mess_index)}"


class SceneSource:
    """Re-creates configurations in one simulator (opened on first use) and caches their
    object records on disk as ``<cache_dir>/scenes/<RoomType>_<seed>_<mess>.json``."""

    def __init__(self, cache_dir: str | Path | None = DEFAULT_CACHE_DIR) -> None:
        self.cache_dir = None if cache_dir is None else Path(cache_dir) / "scenes"
        self._episode: Any = None

    def records(self, room_type: str, seed: int, mess_index: int) -> list[dict[str, Any]]:
        path = (
            None
            if self.cache_dir is None
            else self.cache_dir / f"{room_type}_{int(seed)}_{int(mess_index)}.json"
        )
        if path is not None and path.is_file():
            return json.loads(path.read_text())["objects"]
        if self._episode is None:
            from tidee.server.episode import Episode

            self._episode = Episode(renderer="tiny")
        ep = self._episode
        # The scene library builds the tidy room, runs the mess-up and leaves the world in
        # that state; object_states() reads it. No render, no navigation grid.
        ep.scene = ep.library.scene(ep.world, room_type, int(seed), int(mess_index))
        recs = [object_record(s) for s in ep.object_states() if s["type"] in CLASSES]
        if path is not None:
            from tidee.protocol.episode_log import write_json_atomic

            path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, {"config": _config_key(room_type, seed, mess_index), "objects": recs})
        return recs

    def close(self) -> None:
        if self._episode is not None:
            self._episode.close()
            self._episode = None


def config_objects(
    room_type: str, seed: int, mess_index: int, cache_dir: str | Path | None = DEFAULT_CACHE_DIR
) -> list[dict[str, Any]]:
    """Ground-truth object records of one messy configuration (every object of a ``CLASSES``
    type): id, type, moved, centroid, box_min, box_max (world metres)."""
    src = SceneSource(cache_dir)
    try:
        return src.records(room_type, seed, mess_index)
    finally:
        src.close()


def object_refs(records: Sequence[Mapping[str, Any]]) -> list[ObjectRef]:
    """``ObjectRef`` s of object records; receptacle = the catalog flag (as the agent's ``as_ref``)."""
    return [
        ObjectRef(
            id=r["id"],
            label=r["type"],
            centroid=r["centroid"],
            box_min=r["box_min"],
            box_max=r["box_max"],
            receptacle=r["type"] in RECEPTACLES,
        )
        for r in records
    ]


def config_paragraphs(
    records: Sequence[Mapping[str, Any]], ids: Sequence[str] | None = None
) -> dict[str, tuple[str, int, str]]:
    """{object id: (paragraph, label, category)} with every other object as context.

    ``ids``: the objects to describe (default: every pickupable one)."""
    refs = object_refs(records)
    by_id = {r.id: (r, rec) for r, rec in zip(refs, records)}
    wanted = [r.id for r in refs if r.label in PICKUPABLE] if ids is None else list(ids)
    out = {}
    for oid in wanted:
        if oid not in by_id:
            raise KeyError(f"object {oid!r} is not in this configuration")
        ref, rec = by_id[oid]
        out[oid] = (object_paragraph(ref, refs), int(rec["moved"]), ref.label)
    return out


def split_configs(
    split: str, rooms_per_type: int, messes_per_room: int, room_types: Sequence[str] = ROOM_TYPES
) -> list[tuple[str, int, int]]:
    """(room type, seed, mess index) of the messy configurations, rooms in seed order."""
    limit = MESSES_PER_ROOM["train" if split == "train" else split]
    if not 1 <= messes_per_room <= limit:
        raise ValueError(f"{split} rooms have {limit} messy configurations each; asked for {messes_per_room}")
    bad = [rt for rt in room_types if rt not in ROOM_TYPES]
    if bad:
        raise ValueError(f"unknown room types {bad}; choose from {ROOM_TYPES}")
    return [
        (rt, s, m)
        for s in room_seeds(split, rooms_per_type)
        for rt in room_types
        for m in range(messes_per_room)
    ]


def language_oop_samples(
    split: str,
    rooms_per_type: int,
    messes_per_room: int,
    room_types: Sequence[str] = ROOM_TYPES,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    progress: bool = True,
) -> list[OOPSample]:
    """One sample per pickupable object of each messy configuration of ``split``.

    Paragraphs come from ground-truth boxes with all other objects as context; the label
    is the mess-up's ``moved`` flag. Out-of-place objects are ~20% of the samples.
    """
    from tqdm import tqdm

    jobs = split_configs(split, rooms_per_type, messes_per_room, room_types)
    src = SceneSource(cache_dir)
    out: list[OOPSample] = []
    try:
        for rt, seed, mess in tqdm(jobs, desc=f"{split} configurations", disable=not progress):
            for para, label, cat in config_paragraphs(src.records(rt, seed, mess)).values():
                out.append(OOPSample(para, label, rt, cat))
    finally:
        src.close()
    return out
