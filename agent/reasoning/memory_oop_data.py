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
writes held-out samples for evaluation (``tidee eval oop-memory``), never for training.

Output: ``DIR/samples.jsonl`` (one JSON object per line: paragraph, label, category,
room_type, config, snapshot, feature) and ``DIR/meta.json`` (command, seeds, counts),
both written atomically.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import multiprocessing as mp
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import PICKUPABLE
from tidee.agent.mapping.geometry import start_to_world_xy

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
    perception: str = "oracle",
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
    from tidee.agent.reasoning.language_oop import _record, object_paragraph
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
            rec = _record({**o, "moved": o["id"] in moved})
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


_WORKER: dict[str, Any] = {}  # this process's simulator, reused by every configuration it samples


def _worker(job: dict[str, Any]) -> list[dict[str, Any]]:
    from tidee.protocol.transport import InProcessTransport

    transport = _WORKER.get("transport")
    if transport is None:
        transport = _WORKER["transport"] = InProcessTransport(renderer=job["renderer"])
    return config_memory_samples(
        transport,
        job["room_type"],
        job["seed"],
        job["mess_index"],
        job["perception"],
        job["resolution"],
        agent_seed=job["agent_seed"],
    )


def gen_memory_samples(
    out: str | Path,
    split: str = "train",
    rooms_per_type: int = 20,
    messes: int = 2,
    perception: str = "oracle",
    workers: int = 1,
    resolution: int = 256,
    first_mess: int = 0,
    skip_rooms: int = 0,
    command: str = "tidee gen oop-memory",
    progress: bool = True,
) -> dict[str, Any]:
    """Memory paragraphs of ``rooms_per_type`` x 4 room types x ``messes`` configurations."""
    from tqdm import tqdm

    from tidee.agent.perception import TRAINED_RENDERER
    from tidee.agent.perception.dataset import room_seeds
    from tidee.agent.reasoning.stats import _ranges
    from tidee.protocol.episode_log import write_json_atomic
    from tidee.protocol.messages import ROOM_TYPES
    from tidee.server.splits import MESSES_PER_ROOM

    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be train, val or test, got {split!r}")
    if perception not in ("oracle", "learned"):
        raise ValueError(f"perception must be oracle or learned, got {perception!r}")
    if not 0 <= first_mess < first_mess + messes <= MESSES_PER_ROOM[split]:
        raise ValueError(
            f"{split} rooms have messes 0-{MESSES_PER_ROOM[split] - 1}; "
            f"asked for {first_mess}..{first_mess + messes - 1}"
        )
    seeds = room_seeds(split, rooms_per_type, skip_rooms)
    jobs = [
        {
            "room_type": rt,
            "seed": s,
            "mess_index": m,
            "perception": perception,
            "resolution": resolution,
            "renderer": TRAINED_RENDERER,
            "agent_seed": 1000 * s + 10 * i + m,
        }
        for s in seeds
        for i, rt in enumerate(ROOM_TYPES)
        for m in range(first_mess, first_mess + messes)
    ]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    rows: list[dict[str, Any]] = []
    bar = tqdm(total=len(jobs), desc=f"mapping {split} configurations", disable=not progress)
    if workers <= 1:
        for job in jobs:
            rows += _worker(job)
            bar.update()
    else:
        from tidee.threads import threads_per_process, use_threads

        with cf.ProcessPoolExecutor(
            workers,
            mp_context=mp.get_context("spawn"),
            initializer=use_threads,
            initargs=(threads_per_process(workers),),
        ) as pool:
            for part in pool.map(_worker, jobs):
                rows += part
                bar.update()
    bar.close()
    tmp = out / "samples.jsonl.tmp"
    with tmp.open("w") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    tmp.replace(out / "samples.jsonl")
    meta = {
        "command": command,
        "split": split,
        "perception": perception,
        "seeds": _ranges(seeds),
        "skip_rooms": skip_rooms,
        "rooms_per_type": rooms_per_type,
        "messes": [first_mess, first_mess + messes - 1],
        "configurations": len(jobs),
        "samples": len(rows),
        "out_of_place": sum(r["label"] for r in rows),
        "resolution": resolution,
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
    from tidee.agent.reasoning.language_oop import _features

    return _features(
        [None if r["feature"] is None else np.asarray(r["feature"], np.float32) for r in rows], dim
    )


def evaluate_memory(classifier: Any, path: str | Path, split: str = "test") -> dict[str, Any]:
    """Object-level AP of a language / fused classifier on held-out memory samples: how well
    it separates moved from in-place objects as the agent describes them (per room type too)."""
    rows = load_memory_samples(path, split=split)
    if not rows:
        raise ValueError(f"{path} holds no samples")
    visual = memory_features(rows, classifier.visual_dim) if getattr(classifier, "visual_dim", 0) else None
    probs = classifier.predict([r["paragraph"] for r in rows], visual)
    return {"data": str(path), "split": split, **_scores(probs, rows)}


def _scores(probs: np.ndarray, rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    from tidee.agent.reasoning.language_oop import object_ap

    labels = np.array([r["label"] for r in rows])
    out = {"samples": len(rows), **object_ap(probs, labels)}
    per: dict[str, Any] = {}
    for rt in sorted({r["room_type"] for r in rows}):
        idx = [i for i, r in enumerate(rows) if r["room_type"] == rt]
        per[rt] = object_ap(probs[idx], labels[idx])
    out["per_room_type"] = per
    at = probs >= 0.5
    out["at_0.5"] = {
        "flagged": int(at.sum()),
        "true": int((at & (labels == 1)).sum()),
        "false": int((at & (labels == 0)).sum()),
    }
    return out


def _cmd_gen(args: Any) -> int:
    meta = gen_memory_samples(
        args.out,
        args.split,
        args.rooms_per_type,
        args.messes,
        args.perception,
        args.workers,
        args.resolution,
        args.first_mess,
        args.skip_rooms,
        command="tidee gen oop-memory " + " ".join(sys.argv[3:]),
    )
    print(json.dumps(meta, indent=1))
    return 0


def run_memory_eval(out: str | Path, data: str | Path, weights: Sequence[str]) -> dict[str, Any]:
    """``tidee eval oop-memory``: each classifier's AP on held-out memory samples; JSON + Markdown."""
    from tidee.agent.reasoning.language_oop import LanguageOOPClassifier
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = memory_meta(data)
    rows = {}
    samples = load_memory_samples(data, split=meta["split"])
    if samples and all(r.get("visual_oop") is not None for r in samples):
        # learned perception: the detector's OOP head (running mean over the track's views)
        rows["visual (detector OOP head)"] = _scores(np.array([r["visual_oop"] for r in samples]), samples)
    for w in weights:
        rows[Path(w).name] = evaluate_memory(LanguageOOPClassifier.load(w), data, split=meta["split"])
    report = {"data": meta, "classifiers": rows}
    write_json_atomic(out / "report.json", report)
    lines = [
        "# OOP classifiers on the agent's own memory paragraphs",
        "",
        f"Samples: `{data}` ({meta['split']} rooms, {meta['configurations']} configurations, "
        f"{meta['samples']} samples, {meta['out_of_place']} out of place; perception {meta['perception']}; "
        f"made by `{meta['command']}`). Each sample is the paragraph of one tracked object after the agent's "
        "mapping phase or a later search goal, labelled by the simulator's mess-up (evaluation only).",
        "",
        "| Classifier | mAP | AP out-of-place | AP in-place | flagged at 0.5 | of them in place |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        a = r["at_0.5"]
        lines.append(
            f"| {name} | {100 * r['map']:.1f} | {100 * r['ap_out_of_place']:.1f} | "
            f"{100 * r['ap_in_place']:.1f} | {a['flagged']} | {a['false']} |"
        )
    lines += ["", "command: `tidee eval oop-memory " + " ".join(sys.argv[3:]) + "`"]
    write_atomic(out / "report.md", ("\n".join(lines) + "\n").encode())
    return report


def _cmd_eval(args: Any) -> int:
    run_memory_eval(args.out, args.data, args.weights)
    print((Path(args.out) / "report.md").read_text())
    return 0


def register(gen_sub: Any, eval_sub: Any) -> None:
    """``tidee gen oop-memory`` and ``tidee eval oop-memory``."""
    p = gen_sub.add_parser(
        "oop-memory", help="OOP samples from the agent's own object memory (mapping phase)"
    )
    p.add_argument(
        "--split",
        choices=("train", "val", "test"),
        default="train",
        help="train: training data; val/test: held-out samples for evaluation only",
    )
    p.add_argument("--rooms-per-type", type=int, default=20)
    p.add_argument("--messes", type=int, default=2, help="messy configurations per room")
    p.add_argument("--first-mess", type=int, default=0)
    p.add_argument(
        "--skip-rooms",
        type=int,
        default=0,
        help="start after this many rooms per type (60: rooms the shipped detector never saw)",
    )
    p.add_argument("--perception", choices=("oracle", "learned"), default="oracle")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_gen)

    p = eval_sub.add_parser(
        "oop-memory", help="OOP classifiers on held-out paragraphs of the agent's own memory"
    )
    p.add_argument("--data", required=True, help="`tidee gen oop-memory --split test` output")
    p.add_argument("--weights", nargs="+", default=["agent/weights/language_oop.pt"])
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_eval)
