"""``tidee gen search``: the search network's data, and its targets from the simulator's ground truth.

Each room configuration (tidy, or one of its messes) is explored the way the agent maps a
room; map snapshots (``model.search_input``) are kept at random steps, half of them in the
first 60 steps, with every object instance's footprint in the episode's start frame.

Targets: for every category present in the room, max over its instances of
exp(-d^2 / 2 sigma^2), d the distance (metres, start frame) from a cell centre to the
instance's footprint rectangle (ground-truth position, size and yaw; sigma 0.3 m).
Ground truth is privileged: this module serves training and evaluation, never the agent.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import CLASS_INDEX
from tidee.agent.perception import TRAINED_RENDERER
from tidee.agent.reasoning.search.config import SearchGenConfig
from tidee.agent.reasoning.search.model import C_IN, IN_SIZE, OUT_SIZE, out_grid, search_input
from tidee.protocol.vocab import ROOM_TYPES
from tidee.server.scene import quat_yaw
from tidee.server.splits import split_of

TARGET_SIGMA_M = 0.3


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


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255).astype(np.uint8)


# --------------------------------------------------------------------------- data generation
def _jobs(cfg: SearchGenConfig) -> list[tuple[str, int, int | None]]:
    from tidee.agent.perception.detector.config import room_seeds

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
    # Early maps matter most (a search starts after one look-around): half the snapshots in the
    # first 60 steps.
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


def worker_perception(mode: str) -> Any:
    """This batch worker's perception for ``mode``, made once (``tidee.batch.worker_state``)."""
    from tidee.agent.perception import make_perception
    from tidee.batch import worker_state

    made: dict[str, Any] = worker_state().setdefault("perception", {})
    if mode not in made:
        made[mode] = make_perception(mode)
    return made[mode]


def _shard_name(rt: str, seed: int, mess: int | None) -> str:
    return f"{rt}_{seed}_{'tidy' if mess is None else f'mess{mess}'}.npz"


# What picks the configurations, not what is in their shards: left out of a job's key.
_SELECTION = ("out", "split", "rooms_per_type", "messes_per_room", "room_types", "workers", "batch")


def _job_key(args: tuple[tuple[str, int, int | None], SearchGenConfig]) -> str:
    from tidee.batch import config_digest

    return f"{_shard_name(*args[0])}/{config_digest(args[1], _SELECTION)}"


def _gen_one(args: tuple[tuple[str, int, int | None], SearchGenConfig]) -> dict[str, Any]:
    """One configuration's shard (a batch job: this worker's simulator and perception)."""
    from tidee.batch import npz_bytes, worker_transport

    job, cfg = args
    res = snapshot_config(job, cfg, worker_transport(TRAINED_RENDERER), worker_perception(cfg.perception))
    arrays = {
        "x": res["x"],
        "inst": res["inst"],
        "steps": np.asarray(res["steps"], np.int32),
        "seen": json.dumps(res["seen"]),
        "room_type": res["room_type"],
        "seed": res["seed"],
        "mess_index": -1 if res["mess_index"] is None else res["mess_index"],
    }
    return {"files": {_shard_name(*job): npz_bytes(arrays)}, "snapshots": len(res["x"])}


JOBS_FILE = "jobs.jsonl"  # in OUT: each configuration's record and its shard's digest (--resume reads it)


def generate_search_data(cfg: SearchGenConfig, command: str = "", progress: bool = True) -> dict[str, Any]:
    """Write one shard per room configuration to ``cfg.out`` and ``manifest.json`` (``tidee.batch``:
    local workers or Ray; with ``cfg.batch.resume`` the intact shards of an interrupted run are
    kept). Deterministic in ``cfg``: the same shards, byte for byte, on either backend."""
    from tidee.batch import files_intact, import_ray, read_records, run_jobs
    from tidee.protocol.episode_log import write_json_atomic

    if cfg.batch.backend == "ray":
        import_ray()  # not installed: say how, before anything runs
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(j, cfg) for j in _jobs(cfg)]
    stored = read_records(out / JOBS_FILE) if cfg.batch.resume else {}
    before = {k for k, r in stored.items() if files_intact(out, r)}
    t0 = time.time()
    records = run_jobs(
        jobs,
        _gen_one,
        workers=cfg.workers,
        renderer=TRAINED_RENDERER,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        progress=progress,
        out_jsonl=out / JOBS_FILE,
        resume=cfg.batch.resume,
        key=_job_key,
        desc=f"search data ({cfg.split})",
        files_dir=out,
    )
    n_snap = sum(r["snapshots"] for (j, r) in zip(jobs, records) if _job_key(j) not in before)
    manifest = {
        "command": command,
        "config": asdict(cfg),
        "configurations": len(jobs),
        "seeds": sorted({s for (_, s, _), _ in jobs}),
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


__all__ = [
    "footprint_distance",
    "generate_search_data",
    "load_search_data",
    "room_instances",
    "snapshot_config",
    "target_heat",
    "to_uint8",
]
