"""Placement statistics of the training rooms: how often each category rests on each receptacle.

The non-learned twins of the commonsense models read these counts:
  * the relation-statistics OOP detector (an object is out of place when the receptacle
    it is supported by is rare for its category in rooms of this type), and
  * CommonMemory (the most common receptacle for the category, whatever the room).

Built by ``tidee gen stats`` from the tidy *training* rooms only (never val or test);
the result ships as ``agent/data/placement_stats.json`` with its command and checksum.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tidee.batch import BackendConfig

DEFAULT_PATH = Path(__file__).resolve().parent.parent / "data" / "placement_stats.json"
ALL_ROOMS = "*"


@dataclass(frozen=True)
class PlacementStats:
    """``counts[room_type or "*"][category][receptacle_type] -> int``."""

    counts: dict[str, dict[str, dict[str, int]]]
    meta: dict[str, Any]

    @staticmethod
    def load(path: str | Path = DEFAULT_PATH) -> PlacementStats:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no placement statistics at {path}; build them with `tidee gen stats`")
        data = json.loads(path.read_text())
        return PlacementStats(counts=data["counts"], meta=data.get("meta", {}))

    def table(self, category: str, room_type: str | None = None, min_samples: int = 5) -> dict[str, int]:
        """Counts for the category in this room type, or over all rooms when there are too few."""
        if room_type is not None:
            t = self.counts.get(room_type, {}).get(category, {})
            if sum(t.values()) >= min_samples:
                return t
        return self.counts.get(ALL_ROOMS, {}).get(category, {})

    def rarity(self, category: str, receptacle: str, room_type: str | None = None) -> float:
        """count(receptacle) / count(most common receptacle) for the category: 0 = never seen there."""
        t = self.table(category, room_type)
        if not t:
            return 1.0  # a category never seen in training: no evidence that any place is wrong
        return t.get(receptacle, 0) / max(t.values())

    def ranked(self, category: str, room_type: str | None = None) -> list[tuple[str, float]]:
        """Receptacle types by decreasing frequency, with relative frequencies summing to 1."""
        t = self.table(category, room_type)
        total = sum(t.values())
        return sorted(((k, v / total) for k, v in t.items()), key=lambda kv: (-kv[1], kv[0])) if total else []


def _room_placements(job: tuple[str, int]) -> dict[str, Any]:
    """(category, receptacle type) of every pickupable object of one tidy room (a batch job, in
    this worker's world)."""
    from tidee.batch import worker_state
    from tidee.server.rooms import generate_scene

    state = worker_state()
    if "stats_world" not in state:
        from tidee.server.world import World

        state["stats_world"] = World(renderer="tiny")
    scene = generate_scene(*job, world=state["stats_world"])
    return {"placements": [[o.type, o.parent_type] for o in scene.objects if o.pickupable and o.parent_type]}


def build_stats(
    seeds: list[int],
    out: str | Path = DEFAULT_PATH,
    progress: bool = True,
    command: str = "tidee gen stats",
    workers: int = 1,
    backend: BackendConfig | None = None,
) -> dict[str, Any]:
    """Generate the tidy training rooms for ``seeds`` (every room type) and count placements, on
    ``workers`` local processes or Ray actors (``tidee.batch``).

    ``seeds`` must be training seeds (the train split or the training pool); val and test
    rooms are refused so no statistic ever sees them.
    """
    from tidee.server.splits import SPLIT_SEEDS, TRAIN_POOL

    held_out = set(SPLIT_SEEDS["val"]) | set(SPLIT_SEEDS["test"])
    bad = sorted(set(seeds) & held_out)
    if bad:
        raise ValueError(
            f"seeds {bad[:5]} are val/test rooms; statistics may only use the train split "
            f"{SPLIT_SEEDS['train']} or the training pool {TRAIN_POOL}"
        )
    from tidee.batch import BackendConfig, import_ray, run_jobs
    from tidee.protocol.messages import ROOM_TYPES

    backend = backend or BackendConfig()
    if backend.backend == "ray":
        import_ray()  # not installed: say how, before anything runs
    counts: dict[str, dict[str, Counter]] = defaultdict(lambda: defaultdict(Counter))
    t0 = time.time()
    jobs = [(r, s) for r in ROOM_TYPES for s in seeds]
    records = run_jobs(
        jobs,
        _room_placements,
        workers=workers,
        renderer=None,
        backend=backend.backend,
        ray_address=backend.ray_address,
        progress=progress,
        desc="training rooms",
    )
    for (room_type, _), record in zip(jobs, records, strict=True):
        for category, receptacle in record["placements"]:
            counts[room_type][category][receptacle] += 1
            counts[ALL_ROOMS][category][receptacle] += 1
    plain = {
        r: {c: dict(sorted(t.items())) for c, t in sorted(cats.items())} for r, cats in sorted(counts.items())
    }
    digest = hashlib.sha256(json.dumps(plain, sort_keys=True).encode()).hexdigest()
    data = {
        "meta": {
            "command": command,
            "split": "train",
            "seeds": _ranges(seeds),
            "room_types": list(ROOM_TYPES),
            "rooms": len(seeds) * len(ROOM_TYPES),
            "build_s": round(time.time() - t0, 1),
            "sha256_counts": digest,
        },
        "counts": plain,
    }
    from tidee.protocol.episode_log import write_json_atomic  # OpenCV: only when writing

    write_json_atomic(out, data)
    return data


def _ranges(seeds: list[int]) -> list[list[int]]:
    """[[first, last], ...] runs of consecutive seeds (compact in the manifest)."""
    out: list[list[int]] = []
    for s in sorted(seeds):
        if out and s == out[-1][1] + 1:
            out[-1][1] = s
        else:
            out.append([s, s])
    return out
