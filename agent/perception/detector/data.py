"""Detector data: RGB-D frames from random walks through rooms, with instance targets.

``tidee gen detection`` (options: ``config.GenDetectionConfig``) walks an agent at random
through tidy and messy configurations of *training* rooms (seeds 0-19 and the training pool;
never val or test) and writes shards of frames with the simulator's instance masks, classes
and in/out-of-place labels. The same
generator, called by the evaluation commands with ``split="test"``, builds held-out frames
from the test rooms on the fly; those are never written next to training data.

A shard ``shard_00012.npz`` holds N frames:
  rgb    uint8   N x H x W x 3
  depth  float16 N x H x W       metres
  inst   int16   N x H x W       per-frame instance index (-1: none / not a class)
  and one row per visible instance (M rows in all):
  obj_frame int32 (frame index in the shard), obj_cls int16 (``CLASSES`` index),
  obj_box float32 x0,y0,x1,y1 (half-open pixels), obj_oop uint8 (1: moved by the mess-up),
  obj_pix int32 (visible pixels), obj_inst int16 (value in ``inst``), obj_id str (scene object id).
``manifest.json`` records the command, the rooms, seeds and counts.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import CLASS_INDEX, CLASSES
from tidee.agent.perception import TRAINED_RENDERER
from tidee.agent.perception.detector.config import GenConfig, GenDetectionConfig, room_seeds
from tidee.protocol.vocab import HELD_OUT_SPLITS, ROOM_TYPES, HeldOutSplit, Renderer
from tidee.server.splits import MESSES_PER_ROOM, split_of

# A random walk: mostly forward, with turns and looks, like an exploring agent.
WALK_ACTIONS = (
    "MoveAhead",
    "MoveAhead",
    "MoveAhead",
    "RotateLeft",
    "RotateRight",
    "MoveLeft",
    "MoveRight",
    "LookDown",
    "LookUp",
)
# the rooms a `tidee gen detection` directory holds (its models' manifests record it)
TRAIN_ROOMS = "train (seeds 0-19 + pool 10000...), never val/test"
MIN_PIXELS = 12  # at 256^2 (scaled with resolution): smaller instances are not targets


def configs(cfg: GenConfig) -> list[tuple[str, int, int | None]]:
    """(room type, seed, mess index or None) for every configuration the generator visits."""
    out: list[tuple[str, int, int | None]] = []
    limit = MESSES_PER_ROOM["train" if cfg.split == "train" else cfg.split]
    if cfg.messes_per_room > limit:
        raise ValueError(
            f"{cfg.split} rooms have {limit} messy configurations; asked for {cfg.messes_per_room}"
        )
    for seed in room_seeds(cfg.split, cfg.rooms_per_type, cfg.skip_rooms):
        for rt in cfg.room_types:
            if cfg.tidy:
                out.append((rt, seed, None))
            out += [(rt, seed, m) for m in range(cfg.messes_per_room)]
    return out


def frame_targets(
    inst_seg: np.ndarray, objects: list[dict], depth: np.ndarray, min_pixels: int = MIN_PIXELS
) -> tuple[np.ndarray, list[dict]]:
    """(inst int16 HxW, one dict per visible instance) from the simulator's segmentation."""
    h = inst_seg.shape[0]
    min_px = max(4, int(min_pixels * (h / 256.0) ** 2))
    inst = np.full(inst_seg.shape, -1, np.int16)
    valid = (inst_seg >= 0) & (depth > 0.05)
    ids, counts = np.unique(inst_seg[valid], return_counts=True)
    rows: list[dict] = []
    for k, n in zip(ids.tolist(), counts.tolist()):
        o = objects[k]
        if o["type"] not in CLASS_INDEX or n < min_px:
            continue
        m = (inst_seg == k) & valid
        ys, xs = np.nonzero(m)
        j = len(rows)
        inst[m] = j
        rows.append(
            {
                "cls": CLASS_INDEX[o["type"]],
                "box": [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1],
                "oop": int(bool(o.get("moved"))),
                "pix": int(n),
                "inst": j,
                "id": o["id"],
            }
        )
    return inst, rows


def iter_frames(
    cfg: GenConfig,
    jobs: list[tuple[str, int, int | None]] | None = None,
    progress: bool = True,
    episode: Any = None,
) -> Iterator[dict]:
    """Frames with targets, deterministic in ``cfg`` (one Episode, rooms in order; ``episode``:
    one to reuse, e.g. a batch worker's, left open; default: a new one, closed at the end)."""
    from tqdm import tqdm

    from tidee.protocol.messages import Action, EpisodeSpec
    from tidee.server.episode import Episode

    jobs = configs(cfg) if jobs is None else jobs
    for _, seed, _ in jobs:
        if cfg.split == "train" and split_of(seed) not in ("train", "train_pool"):
            raise ValueError(
                f"seed {seed} is a {split_of(seed)} room: detector training data only comes from "
                "training rooms"
            )
    ep = episode if episode is not None else Episode(renderer=cfg.renderer)
    try:
        for _j, (rt, seed, mess) in enumerate(
            tqdm(jobs, desc=f"{cfg.split} configurations", disable=not progress)
        ):
            rng = np.random.default_rng(
                [cfg.seed, seed, ROOM_TYPES.index(rt), 0 if mess is None else mess + 1]
            )
            in_config = 0
            for w in range(cfg.walks_per_config):
                if cfg.per_config is not None and in_config >= cfg.per_config:
                    break
                spec = EpisodeSpec(
                    room_type=rt,
                    seed=seed,
                    mess_index=mess,
                    resolution=cfg.resolution,
                    start_seed=int(rng.integers(1 << 30)),
                    max_steps=10_000,
                )
                obs = ep.reset(spec, ground_truth=True)
                kept = 0
                for t in range(cfg.frames_per_walk * cfg.stride * 3):
                    if t % cfg.stride == cfg.stride - 1:
                        inst, rows = frame_targets(
                            obs.ground_truth.instance_seg, obs.ground_truth.objects, obs.depth
                        )
                        keep = bool(rows) and (not cfg.oop_views_only or any(r["oop"] for r in rows))
                        if keep:
                            kept += 1
                            in_config += 1
                            yield {
                                "rgb": obs.rgb,
                                "depth": obs.depth,
                                "inst": inst,
                                "objects": rows,
                                "room_type": rt,
                                "seed": seed,
                                "mess_index": mess,
                                "walk": w,
                                "pose": obs.agent_pose,
                            }
                            if kept >= cfg.frames_per_walk or in_config == cfg.per_config:
                                break
                    name = WALK_ACTIONS[int(rng.integers(len(WALK_ACTIONS)))]
                    if name == "LookUp" and ep.pitch <= 0:
                        name = "LookDown"  # the agent rarely looks above the horizon
                    # only the frame the next iteration keeps is rendered (Episode.act skips the rest)
                    ok, _, _ = ep.act(Action(name=name))
                    if not ok and name == "MoveAhead":
                        ep.act(Action(name="RotateLeft" if rng.random() < 0.5 else "RotateRight"))
                    if (t + 1) % cfg.stride == cfg.stride - 1:
                        obs = ep.observe(ground_truth=True)
    finally:
        if episode is None:
            ep.close()


def pack(frames: list[dict]) -> dict[str, np.ndarray]:
    rows = [(i, r) for i, f in enumerate(frames) for r in f["objects"]]
    return {
        "rgb": np.stack([f["rgb"] for f in frames]),
        "depth": np.stack([f["depth"] for f in frames]).astype(np.float16),
        "inst": np.stack([f["inst"] for f in frames]),
        "obj_frame": np.array([i for i, _ in rows], np.int32),
        "obj_cls": np.array([r["cls"] for _, r in rows], np.int16),
        "obj_box": np.array([r["box"] for _, r in rows], np.float32).reshape(-1, 4),
        "obj_oop": np.array([r["oop"] for _, r in rows], np.uint8),
        "obj_pix": np.array([r["pix"] for _, r in rows], np.int32),
        "obj_inst": np.array([r["inst"] for _, r in rows], np.int16),
        "obj_id": np.array([r["id"] for _, r in rows], dtype=str),
        "frame_room": np.array([f"{f['room_type']}:{f['seed']}:{f['mess_index']}" for f in frames]),
    }


def frames_per_config(cfg: GenConfig) -> int:
    """The most frames one configuration gives."""
    most = cfg.walks_per_config * cfg.frames_per_walk
    return most if cfg.per_config is None else min(most, cfg.per_config)


@dataclass(frozen=True)
class ShardJob:
    """One shard of ``tidee gen detection``: the frames of a fixed group of configurations, so
    that the shards are the same whichever worker makes them, on either backend."""

    gen: GenConfig
    index: int
    configs: tuple[tuple[str, int, int | None], ...]

    @property
    def name(self) -> str:
        return f"shard_{self.index:05d}.npz"

    def key(self) -> str:
        from tidee.batch import config_digest

        # every field: which configurations fall in a shard depends on them all
        return f"{self.name}/{config_digest(self.gen)}"


def shard_jobs(cfg: GenConfig) -> list[ShardJob]:
    """The configurations in order, cut into groups of at most ``shard_size`` frames."""
    jobs = configs(cfg)
    per_shard = max(1, cfg.shard_size // frames_per_config(cfg))
    return [
        ShardJob(cfg, k, tuple(jobs[start : start + per_shard]))
        for k, start in enumerate(range(0, len(jobs), per_shard))
    ]


def _make_shard(job: ShardJob) -> dict[str, Any]:
    """One shard's frames (a batch job, in this worker's simulator): its file and counts."""
    from tidee.batch import npz_bytes, worker_transport

    episode = worker_transport(job.gen.renderer).episode
    frames = list(iter_frames(job.gen, list(job.configs), progress=False, episode=episode))
    return {
        "files": {job.name: npz_bytes(pack(frames))} if frames else {},
        "frames": len(frames),
        "instances": sum(len(f["objects"]) for f in frames),
        "oop_instances": sum(r["oop"] for f in frames for r in f["objects"]),
    }


JOBS_FILE = "jobs.jsonl"  # in OUT: each shard's record and digest (--resume reads it)


def generate(cfg: GenDetectionConfig, command: str = "", progress: bool = True) -> dict:
    """Write shards + manifest.json under ``cfg.out_dir`` on local workers or Ray (``tidee.batch``;
    with ``cfg.batch.resume`` the intact shards of an interrupted run are kept); returns the
    manifest. Deterministic in ``cfg.gen``: the same shards, byte for byte, on either backend."""
    from tidee.batch import import_ray, run_jobs

    gen = cfg.gen
    if gen.split != "train":
        raise ValueError(
            "tidee gen detection writes training data only (split train); evaluation builds "
            "its test frames itself"
        )
    if gen.renderer == "auto":
        raise ValueError("--renderer auto: name the renderer (tiny or egl), so the data says which drew it")
    if cfg.batch.backend == "ray":
        import_ray()  # not installed: say how, before anything runs
    out = cfg.out_dir
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    jobs = shard_jobs(gen)
    records = run_jobs(
        jobs,
        _make_shard,
        workers=cfg.workers,
        renderer=gen.renderer,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        progress=progress,
        out_jsonl=out / JOBS_FILE,
        resume=cfg.batch.resume,
        desc="detection shards",
        files_dir=out,
    )
    manifest = {
        "command": command,
        "config": asdict(gen),
        "classes": list(CLASSES),
        "shards": [name for r in records for name in r["files"]],
        "frames": sum(r["frames"] for r in records),
        "instances": sum(r["instances"] for r in records),
        "oop_instances": sum(r["oop_instances"] for r in records),
        "rooms": sorted({f"{rt}:{s}" for j in jobs for rt, s, _ in j.configs}),
        "configurations": sum(len(j.configs) for j in jobs),
        "seconds": round(time.time() - t0, 1),
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _read_manifest(root: Path) -> dict:
    manifest = json.loads((root / "manifest.json").read_text())
    if manifest.get("classes") != list(CLASSES):
        raise ValueError(f"{root} was generated for a different class list; regenerate it")
    return manifest


def _concat_shards(
    paths: list[Path], with_inst: bool, limit: int | None
) -> tuple[dict[str, np.ndarray], int]:
    """Shard files in order, concatenated (object frame indices rebased), until ``limit`` frames;
    also how many of ``paths`` were read."""
    parts: dict[str, list[np.ndarray]] = {}
    base = read = 0
    for path in paths:
        with np.load(path) as z:
            d = {k: z[k] for k in z.files if with_inst or k != "inst"}
        d["obj_frame"] = d["obj_frame"] + base
        base += len(d["rgb"])
        read += 1
        for k, v in d.items():
            parts.setdefault(k, []).append(v)
        if limit is not None and base >= limit:
            break
    return {k: np.concatenate(v) for k, v in parts.items()}, read


def load_shards(root: str | Path, with_inst: bool = False, limit: int | None = None) -> dict[str, np.ndarray]:
    """All shards listed in ``root/manifest.json``, concatenated (object frame indices rebased)."""
    root = Path(root)
    return _concat_shards([root / name for name in _read_manifest(root)["shards"]], with_inst, limit)[0]


def split_data_spec(spec: str | Path | list[str]) -> list[Path]:
    """The directories of a ``--data`` value: one, or several comma-separated (blanks dropped)."""
    items = spec if isinstance(spec, list) else str(spec).split(",")
    return [Path(str(x).strip()) for x in items if str(x).strip()]


def data_dirs(spec: str | Path | list[str]) -> list[Path]:
    """``--data`` names one directory of shards or several, comma-separated; each must have a manifest."""
    dirs = split_data_spec(spec)
    if not dirs:
        raise ValueError(f"--data names no directory: {spec!r}")
    for d in dirs:
        if not (d / "manifest.json").exists():
            raise ValueError(
                f"--data {d}: no manifest.json there (make it with `tidee gen detection --out {d}`)"
            )
    return dirs


def load_datasets(
    spec: str | Path | list[str], with_inst: bool = False, limit: int | None = None
) -> tuple[dict[str, np.ndarray], list[dict]]:
    """Shards of one or several ``tidee gen detection`` directories, concatenated, with their manifests.

    The directories must hold different rooms: a room in two of them would count twice."""
    dirs = data_dirs(spec)
    manifests = [_read_manifest(d) for d in dirs]
    seen: dict[str, Path] = {}
    for d, m in zip(dirs, manifests):
        for room in m.get("rooms", []):
            if room in seen:
                raise ValueError(
                    f"room {room} is in both {seen[room]} and {d}; "
                    "generate the second with --skip-rooms past the first"
                )
            seen[room] = d
    shards = [(i, d / name) for i, (d, m) in enumerate(zip(dirs, manifests)) for name in m["shards"]]
    data, read = _concat_shards([p for _, p in shards], with_inst, limit)
    # a --limit-frames run may stop before the last directory: only the manifests it read
    return data, manifests[: shards[read - 1][0] + 1] if read else []


def held_out_frames(
    split: HeldOutSplit = "test",
    rooms_per_type: int = 5,
    messes: int = 2,
    walks: int = 1,
    frames_per_walk: int = 5,
    seed: int = 7,
    oop_views_only: bool = False,
    tidy: bool = True,
    per_config: int | None = None,
    resolution: int = 256,
    renderer: Renderer = TRAINED_RENDERER,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Frames of the val or test rooms, rendered now and packed like a shard (evaluation only;
    never written next to training data). ``per_config`` caps the frames of a configuration."""
    if split not in HELD_OUT_SPLITS:
        raise ValueError(f"evaluation frames come from the val or test rooms, not {split!r}")
    cfg = GenConfig(
        split=split,
        rooms_per_type=rooms_per_type,
        messes_per_room=messes,
        walks_per_config=walks,
        frames_per_walk=frames_per_walk,
        seed=seed,
        oop_views_only=oop_views_only,
        tidy=tidy,
        per_config=per_config,
        resolution=resolution,
        renderer=renderer,
    )
    frames = list(iter_frames(cfg, progress=progress))
    if not frames:
        raise ValueError(f"no {split} frames with objects in view")
    return pack(frames)


def describe(cfg: GenConfig) -> str:
    n = len(configs(cfg))
    return (
        f"{n} configurations x {cfg.walks_per_config} walks x up to {cfg.frames_per_walk} frames "
        f"= at most {n * cfg.walks_per_config * cfg.frames_per_walk} frames at {cfg.resolution}^2"
    )


__all__ = [
    "TRAIN_ROOMS",
    "configs",
    "frame_targets",
    "iter_frames",
    "generate",
    "load_shards",
    "held_out_frames",
    "pack",
    "describe",
    "shard_jobs",
    "ShardJob",
    "MIN_PIXELS",
    "split_data_spec",
    "data_dirs",
    "load_datasets",
]
