"""Out-of-place samples from the agent's own object memory (``tidee gen oop-memory``).

The language OOP head was first trained on relation paragraphs from ground-truth boxes.
The agent reads paragraphs of its *tracked* objects instead: boxes grown from partial
views and depth, receptacles seen as slabs, relations that differ from the true ones.
This module runs the agent's mapping phase (Algorithm 1's look-around and exploration,
then a few search goals) in messy configurations, writes the paragraph of every tracked
pickupable object at a few moments, and labels it by matching the track to the
simulator's objects: the mess-up's ``moved`` flag of the nearest object of the same class.

Labels read the simulator's state, as every training target does; the agent itself
never does. Training configurations come from the training rooms only; ``--split test``
writes held-out samples for evaluation (``tidee eval oop-memory``, :func:`.eval.run_memory_eval`),
never for training.

Output: ``DIR/samples.jsonl`` (one JSON object per line: paragraph, label, category,
room_type, config, snapshot, feature) and ``DIR/meta.json`` (command, seeds, counts),
both written atomically.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tidee.agent.classes import PICKUPABLE
from tidee.agent.mapping.geometry import start_to_world_xy
from tidee.agent.reasoning.language_oop.config import MemoryGenConfig
from tidee.protocol.vocab import ROOM_TYPES

if TYPE_CHECKING:
    from tidee.agent.config import PerceptionMode

MATCH_M = 0.5  # a track matches an object of its class whose centroid is this near in (x, y)
SNAPSHOT_GOALS = 2  # search goals after mapping, each followed by a snapshot


def match_tracks(
    tracks: Sequence[Any], objects: Sequence[dict[str, Any]], start: dict[str, float], max_m: float = MATCH_M
) -> dict[int, dict[str, Any]]:
    """{track id: object record} one to one, nearest pairs first, same class within ``max_m``.

    ``objects``: records with ``type`` and world ``centroid``; tracks are in the start frame."""
    pairs = []
    for t in tracks:
        xy = start_to_world_xy(start, np.asarray(t.centroid, float))
        for j, o in enumerate(objects):
            if o["type"] == t.label:
                d = float(np.hypot(*(xy - np.asarray(o["centroid"][:2], float))))
                if d <= max_m:
                    pairs.append((d, t.id, j))
    used_t: set[int] = set()
    used_o: set[int] = set()
    out = {}
    for _, tid, j in sorted(pairs):
        if tid in used_t or j in used_o:
            continue
        used_t.add(tid)
        used_o.add(j)
        out[tid] = objects[j]
    return out


def config_memory_samples(
    transport: Any,
    room_type: str,
    seed: int,
    mess_index: int,
    perception: PerceptionMode = "oracle",
    resolution: int = 256,
    max_steps: int = 600,
    agent_seed: int = 0,
) -> list[dict[str, Any]]:
    """Run the mapping phase (+ ``SNAPSHOT_GOALS`` search goals) in one messy configuration;
    the labelled paragraphs of its tracked pickupable objects, one per track and snapshot
    (a track whose paragraph did not change since the last snapshot is written once)."""
    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.navigation.explore import sample_reachable_goal
    from tidee.agent.perception import make_perception
    from tidee.agent.policy.skills import Body, look_around, navigate, reachable_mask
    from tidee.agent.policy.tidy import TidyPolicy
    from tidee.agent.reasoning.language_oop.data import object_record
    from tidee.agent.reasoning.language_oop.paragraphs import object_paragraph
    from tidee.agent.reasoning.oop import as_ref
    from tidee.protocol.messages import EpisodeSpec

    cfg = AgentConfig(variant="CommonMemory", perception=perception, oop="language", seed=agent_seed)
    det = make_perception(perception)
    gt = det.needs_ground_truth
    obs = transport.reset(
        EpisodeSpec(
            room_type=room_type, seed=seed, mess_index=mess_index, resolution=resolution, max_steps=max_steps
        ),
        ground_truth=gt,
    )
    state = transport.state()
    moved = {m["id"] for m in state.get("mess", [])}
    objects = []
    for o in state["objects"]:
        if o["type"] in PICKUPABLE:
            rec = object_record({**o, "moved": o["id"] in moved})
            objects.append(rec)
    mapper = SemanticMapper(cfg.map, CLASSES, passable=PICKUPABLE)
    body = Body(mapper)
    policy = TidyPolicy(cfg, body, oop=None, placement=None, room_type=room_type)  # type: ignore[arg-type]
    rng = np.random.default_rng(agent_seed)
    samples: list[dict[str, Any]] = []
    last: dict[int, str] = {}

    def snapshot(k: int) -> None:
        objs = list(mapper.memory)
        refs = [as_ref(o) for o in objs]
        tracks = [o for o in objs if o.label in PICKUPABLE]
        matched = match_tracks(tracks, objects, state["start"])
        for t in tracks:
            o = matched.get(t.id)
            if o is None:
                continue
            para = object_paragraph(as_ref(t), refs)
            if last.get(t.id) == para:
                continue
            last[t.id] = para
            feat = None if t.feature is None else [round(float(v), 4) for v in np.asarray(t.feature).ravel()]
            samples.append(
                {
                    "paragraph": para,
                    "label": int(o["moved"]),
                    "category": t.label,
                    "room_type": room_type,
                    "config": f"{room_type}:{seed}:{mess_index}",
                    "object": o["id"],
                    "snapshot": k,
                    "feature": feat,
                    "visual_oop": None if t.oop_prob is None else round(float(t.oop_prob), 4),
                }
            )

    def drive(gen: Any) -> None:
        nonlocal obs
        while True:
            dets = det.detect(obs)
            mapper.update(obs, dets)
            body.obs, body.detections = obs, dets
            if obs.done:
                return
            try:
                action = next(gen)
            except StopIteration:
                return
            obs = transport.step(action, ground_truth=gt)

    policy.state.phase = "mapping"
    drive(_chain(look_around(body), policy.map_room()))
    snapshot(0)
    for k in range(1, SNAPSHOT_GOALS + 1):
        if body.steps_left() <= 30:
            break
        goal = sample_reachable_goal(reachable_mask(body), mapper.grid, rng, tuple(body.xy))
        if goal is None:
            break
        drive(
            _chain(
                navigate(body, goal_xy=goal, budget=cfg.policy.goal_step_budget),
                look_around(body, pitches=(30.0,)),
            )
        )
        snapshot(k)
    return samples


def _chain(*gens: Any) -> Any:
    for g in gens:
        yield from g


def _job_samples(transport: Any, job: dict[str, Any]) -> list[dict[str, Any]]:
    return config_memory_samples(
        transport,
        job["room_type"],
        job["seed"],
        job["mess_index"],
        job["perception"],
        job["resolution"],
        agent_seed=job["agent_seed"],
    )


def _run_one(job: dict[str, Any]) -> dict[str, Any]:
    """One configuration's samples (a batch job, in this worker's simulator)."""
    from tidee.batch import worker_transport

    return {"samples": _job_samples(worker_transport(job["renderer"]), job)}


def _job_key(job: dict[str, Any]) -> str:
    return "{room_type}/{seed}/mess{mess_index}/{perception}/{resolution}/{renderer}/{agent_seed}".format(
        **job
    )


JOBS_FILE = "jobs.jsonl"  # in OUT: each configuration's samples as it ends (--resume reads it)


def gen_memory_samples(
    cfg: MemoryGenConfig, command: str = "tidee gen oop-memory", progress: bool = True
) -> dict[str, Any]:
    """Memory paragraphs of ``rooms_per_type`` x 4 room types x ``messes`` configurations, on
    local workers or Ray (``tidee.batch``); ``samples.jsonl`` in configuration order."""
    from tidee.agent.perception import TRAINED_RENDERER
    from tidee.agent.perception.detector.config import room_seeds
    from tidee.agent.reasoning.stats import _ranges
    from tidee.batch import import_ray, run_jobs
    from tidee.protocol.episode_log import write_json_atomic

    if cfg.batch.backend == "ray":
        import_ray()  # not installed: say how, before anything runs
    split, first_mess, messes = cfg.split, cfg.first_mess, cfg.messes
    seeds = room_seeds(split, cfg.rooms_per_type, cfg.skip_rooms)
    jobs = [
        {
            "room_type": rt,
            "seed": s,
            "mess_index": m,
            "perception": cfg.perception,
            "resolution": cfg.resolution,
            "renderer": TRAINED_RENDERER,
            "agent_seed": 1000 * s + 10 * i + m,
        }
        for s in seeds
        for i, rt in enumerate(ROOM_TYPES)
        for m in range(first_mess, first_mess + messes)
    ]
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    records = run_jobs(
        jobs,
        _run_one,
        workers=cfg.workers,
        renderer=TRAINED_RENDERER,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        progress=progress,
        out_jsonl=out / JOBS_FILE,
        resume=cfg.batch.resume,
        key=_job_key,
        desc=f"mapping {split} configurations",
    )
    rows = [row for r in records for row in r["samples"]]
    tmp = out / "samples.jsonl.tmp"
    with tmp.open("w") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    tmp.replace(out / "samples.jsonl")
    meta = {
        "command": command,
        "split": split,
        "perception": cfg.perception,
        "seeds": _ranges(seeds),
        "skip_rooms": cfg.skip_rooms,
        "rooms_per_type": cfg.rooms_per_type,
        "messes": [first_mess, first_mess + messes - 1],
        "configurations": len(jobs),
        "samples": len(rows),
        "out_of_place": sum(r["label"] for r in rows),
        "resolution": cfg.resolution,
        "wall_s": round(time.time() - t0, 1),
    }
    write_json_atomic(out / "meta.json", meta)
    return meta


def load_memory_samples(path: str | Path, split: str | None = "train") -> list[dict[str, Any]]:
    """Samples of a ``tidee gen oop-memory`` directory; refuses another split than ``split``."""
    path = Path(path)
    meta_file = path / "meta.json"
    if not meta_file.is_file():
        raise FileNotFoundError(f"no memory OOP samples at {path}; generate them with `tidee gen oop-memory`")
    meta = json.loads(meta_file.read_text())
    if split is not None and meta.get("split") != split:
        raise ValueError(f"{path} holds {meta.get('split')!r} samples; this needs {split!r} ones")
    rows = []
    with (path / "samples.jsonl").open() as f:
        for n, line in enumerate(f, 1):
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError as e:
                raise ValueError(f"{path / 'samples.jsonl'} line {n} is not JSON: {e}") from None
    return rows


def memory_meta(path: str | Path) -> dict[str, Any]:
    """The ``meta.json`` of a samples directory (command, split, seeds, counts)."""
    return json.loads((Path(path) / "meta.json").read_text())


def memory_features(rows: Sequence[dict[str, Any]], dim: int) -> np.ndarray:
    """float32 N x ``dim``: the samples' track features (zeros where a track had none)."""
    from tidee.agent.reasoning.language_oop.model import feature_matrix

    return feature_matrix(
        [None if r["feature"] is None else np.asarray(r["feature"], np.float32) for r in rows], dim
    )
