"""``tidee bench scale``: tidy episodes per hour with 1 and 2 workers, local processes and Ray
actors, side by side on the same configurations.

The job is ``tidee eval tidy``'s (the first ``configs`` configurations of the split spread over
the room types, each agent of ``variants``), run through ``tidee.batch.run_jobs`` exactly as the
eval runs it (longest first by the scene's object count). Each (backend, workers) pair runs in a
fresh process, so each pays what a command pays: interpreter and imports, worker processes or a
local Ray, loading the models; the pairs alternate their order over ``repeats``. The scenes are
put in the scene cache first, so no run generates a room another did not.

Each episode records when it started and ended (after its worker had loaded the models, so
loading is start-up, not episode time) and on which worker. From these, per run:

* ``command_s``: the whole process, as a user waits for it; ``episodes_per_hour`` from it;
* ``setup_s``: process start to the first episode's start (imports, workers or Ray, models);
* ``window_s``: first episode start to last episode end; ``steady_episodes_per_hour`` from it
  (what a long evaluation approaches, where start-up is spread over thousands of episodes);
* ``tail_idle_s``: per worker, from its last episode's end to the run's last end (stragglers).

A lone local worker runs twice: with what ``--workers 1`` gives it (every core: its episodes
are shorter where torch uses both) and with one thread, as each of 2 workers on 2 cores has. The
first is what the 1 to 2 speedup is measured against; the second tells whether two workers slow
each other down (memory bandwidth, caches), which the first cannot.

Reported: each, median / p90 / max over the repeats; the 1 to 2 worker speedup of each backend;
Ray's overhead per episode against local at equal workers; episodes per hour per core for each
agent from the 2-worker local runs (a worker per core, one thread each: its mean episode time);
a worker's peak memory (resident set, 2-worker runs); the load average. Every run's
episodes are checked equal (wall times aside) to the first run's: the same records on either
backend.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

from tidee.protocol.episode_log import write_atomic

# (backend, workers, threads of a lone in-process worker: None for what the command gives it, all
# the cores). One worker with one thread measures whether workers get in each other's way; one
# with every core is what `--workers 1` gives and the 1-to-2 speedup is measured against.
Run = tuple[str, int, int | None]
ORDER: tuple[Run, ...] = (
    ("local", 1, None),
    ("local", 1, 1),
    ("local", 2, None),
    ("ray", 1, None),
    ("ray", 2, None),
)


def _name(run: Run) -> str:
    backend, workers, threads = run
    return f"{backend}_{workers}" + ("" if threads is None else f"_{threads}_thread")


def _warm_scene_cache(split: str, configs: int) -> None:
    from tidee.agent.evaluation.tidy_eval import select_configs
    from tidee.server.bench_reset import reset_times
    from tidee.server.scene_cache import SceneCache

    chosen = select_configs(split, configs)
    reset_times([(c.room_type, c.seed, c.mess_index) for c in chosen], SceneCache())


def _timed_episode(job: Any) -> dict[str, Any]:
    """One eval-tidy episode (a batch job) with its start and end time and its worker; the
    worker's models and simulator are made before the clock starts."""
    from tidee.agent.evaluation.tidy_eval import _run_one
    from tidee.agent.runner import worker_models
    from tidee.batch import worker_transport

    worker_models(job.agent)
    worker_transport(job.renderer)
    t0 = time.time()
    record = _run_one(job)
    t1 = time.time()
    same = {k: v for k, v in record.items() if k not in ("wall_s", "timing_ms")}
    digest = hashlib.sha1(json.dumps(same, sort_keys=True, default=str).encode()).hexdigest()[:12]
    return {
        "variant": record["variant"],
        "t_start": t0,
        "t_end": t1,
        "worker": os.getpid(),
        "wall_s": float(record["wall_s"]),
        "digest": digest,
        "worker_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def _child(
    backend: str, workers: int, threads: int | None, split: str, configs: int, variants: list[str]
) -> None:
    """The measured run, in a fresh process: prints one JSON line of episode timings."""
    from tidee.agent.evaluation.config import TidyEvalConfig
    from tidee.agent.evaluation.tidy_eval import _job_cost, build_jobs
    from tidee.batch import BatchConfig, init_worker, run_jobs

    if threads is not None:  # the lone worker is this process
        init_worker(None, threads)

    with tempfile.TemporaryDirectory(prefix="tidee-bench-scale-") as out:
        cfg = TidyEvalConfig(
            out=out,  # type: ignore[arg-type]
            split=split,  # type: ignore[arg-type]
            episodes=configs,
            variants=tuple(variants),
            workers=workers,
            batch=BatchConfig(backend=backend),  # type: ignore[arg-type]
            progress=False,
        )
        jobs = build_jobs(cfg)
        episodes = run_jobs(
            jobs,
            _timed_episode,
            workers=workers,
            renderer=cfg.renderer,
            backend=backend,  # type: ignore[arg-type]
            progress=False,
            cost=_job_cost,
        )
    print(json.dumps({"episodes": episodes}))


def _measure(run: Run, split: str, configs: int, variants: list[str]) -> dict[str, Any]:
    backend, workers, threads = run
    code = "import json, sys\nfrom tidee.agent.bench_scale import _child\n_child(*json.loads(sys.argv[1]))\n"
    args = json.dumps([backend, workers, threads, split, configs, variants])
    t0 = time.time()
    r = subprocess.run([sys.executable, "-c", code, args], capture_output=True, text=True, timeout=6 * 3600)
    t1 = time.time()
    if r.returncode != 0:
        raise RuntimeError(f"bench scale: {_name(run)} failed: {r.stderr[-1500:]}")
    episodes = json.loads(r.stdout.strip().splitlines()[-1])["episodes"]
    first = min(e["t_start"] for e in episodes)
    last = max(e["t_end"] for e in episodes)
    ends: dict[int, float] = {}
    for e in episodes:
        ends[e["worker"]] = max(ends.get(e["worker"], 0.0), e["t_end"])
    return {
        "run": _name(run),
        "episodes": episodes,
        "command_s": t1 - t0,
        "setup_s": first - t0,
        "window_s": last - first,
        "tail_idle_s": float(np.mean([last - end for end in ends.values()] + [0.0] * (workers - len(ends)))),
    }


def _spread(xs: list[float], digits: int = 1) -> dict[str, float]:
    from tidee.server.bench_sim import spread

    return spread(xs, digits)


def run_scale_bench(
    out: str,
    configs: int = 8,
    variants: str = "TIDEE",
    repeats: int = 1,
    split: str = "test",
    backends: tuple[str, ...] = ("local", "ray"),
) -> dict[str, Any]:
    agents = [v for v in variants.split(",") if v]
    if "ray" in backends:
        from tidee.batch import import_ray

        import_ray()  # not installed: say how, before any run
    _warm_scene_cache(split, configs)
    load0 = os.getloadavg()
    order = [run for run in ORDER if run[0] in backends]
    runs: dict[Run, list[dict[str, Any]]] = {run: [] for run in order}
    for k in range(repeats):
        for run in order if k % 2 == 0 else order[::-1]:
            runs[run].append(_measure(run, split, configs, agents))
    load1 = os.getloadavg()
    reference = [e["digest"] for e in runs[order[0]][0]["episodes"]]
    same = all([e["digest"] for e in r["episodes"]] == reference for rs in runs.values() for r in rs)
    n = len(reference)
    result: dict[str, Any] = {
        "split": split,
        "configurations": configs,
        "agents": ",".join(agents),
        "episodes_per_run": n,
        "repeats": repeats,
        "same_episodes_every_run": same,
    }
    per_hour: dict[str, float] = {}
    steady: dict[str, float] = {}
    command: dict[str, float] = {}
    for run, rs in runs.items():
        name = _name(run)
        per_hour[name] = float(np.median([3600.0 * n / r["command_s"] for r in rs]))
        steady[name] = float(np.median([3600.0 * n / r["window_s"] for r in rs]))
        command[name] = float(np.median([r["command_s"] for r in rs]))
        result[f"{name}_episodes_per_hour"] = round(per_hour[name], 1)
        result[f"{name}_steady_episodes_per_hour"] = round(steady[name], 1)
        for key in ("command_s", "setup_s", "window_s", "tail_idle_s"):
            result[f"{name}_{key}"] = _spread([r[key] for r in rs])
        result[f"{name}_episode_wall_s"] = _spread([e["wall_s"] for r in rs for e in r["episodes"]])
    for backend in dict.fromkeys(b for b, _, _ in order):
        one, two = f"{backend}_1", f"{backend}_2"
        if one in per_hour and two in per_hour:
            result[f"{backend}_speedup_1_to_2"] = round(per_hour[two] / per_hour[one], 2)
            result[f"{backend}_steady_speedup_1_to_2"] = round(steady[two] / steady[one], 2)
    if "local_1_1_thread" in steady and "local_2" in steady:  # a core per worker in both
        result["local_steady_speedup_1_to_2_one_thread_each"] = round(
            steady["local_2"] / steady["local_1_1_thread"], 2
        )
    for workers in (1, 2):
        local, ray = command.get(f"local_{workers}"), command.get(f"ray_{workers}")
        if local is not None and ray is not None:
            result[f"ray_overhead_per_episode_{workers}_workers_s"] = round((ray - local) / n, 2)
            result[f"ray_overhead_{workers}_workers_pct"] = round(100.0 * (ray - local) / local, 1)
            result[f"ray_steady_overhead_{workers}_workers_pct"] = round(
                100.0 * (steady[f"local_{workers}"] / steady[f"ray_{workers}"] - 1.0), 1
            )
    result["worker_peak_rss_mb"] = _spread(
        [e["worker_peak_rss_mb"] for run in runs if run[1] == 2 for r in runs[run] for e in r["episodes"]], 0
    )
    for agent in agents:  # 2 workers on 2 cores: each worker a core (one thread) all the time
        walls = [
            e["wall_s"]
            for r in runs.get(("local", 2, None), [])
            for e in r["episodes"]
            if e["variant"] == agent
        ]
        if walls:
            result[f"{agent}_episodes_per_hour_per_core"] = round(3600.0 / float(np.mean(walls)), 1)
    result["machine"] = f"{platform.machine()} {os.cpu_count()} cores"
    result["load_avg_1m_5m_before"] = [round(load0[0], 2), round(load0[1], 2)]
    result["load_avg_1m_5m_after"] = [round(load1[0], 2), round(load1[1], 2)]
    result["command"] = (
        f"tidee bench scale --configs {configs} --variants {','.join(agents)} --repeats {repeats} "
        f"--split {split} --backends {','.join(backends)} --out {out}"
    )
    from tidee.server.bench_sim import write_report

    write_report(
        out,
        result,
        "Scaling benchmark (`tidee bench scale`): tidy episodes per hour, 1 vs 2 workers, local and Ray",
    )
    write_atomic(
        os.path.splitext(out)[0] + "_runs.json",
        json.dumps({_name(run): rs for run, rs in runs.items()}, indent=1).encode(),
    )
    return result
