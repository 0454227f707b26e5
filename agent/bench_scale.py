"""``tidee bench scale``: tidy episodes per minute with 1 and with 2 worker processes.

The same ``tidee eval tidy`` job (the first ``configs`` test configurations spread over
the room types, the given agents) runs as a fresh command with ``--workers 1`` and with
``--workers 2``, in alternating order over ``repeats``. The configurations' scenes are
put in the scene cache first, so neither run pays for generating rooms the other did not.
Writes JSON and Markdown: the command wall times (median, p90, max), episodes per minute,
the 2-worker / 1-worker ratio of throughput, per-episode wall times, and the load average.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np


def _warm_scene_cache(split: str, configs: int) -> None:
    from tidee.agent.evaluation.tidy_eval import select_configs
    from tidee.server.bench_reset import reset_times
    from tidee.server.scene_cache import SceneCache

    reset_times([(c.room_type, c.seed, c.mess_index) for c in select_configs(split, configs)], SceneCache())


def _eval(workers: int, split: str, configs: int, variants: str) -> dict[str, Any]:
    from tidee.agent.evaluation.report import load_report

    with tempfile.TemporaryDirectory(prefix="tidee-bench-scale-") as out:
        t0 = time.perf_counter()
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "tidee.cli",
                "eval",
                "tidy",
                "--split",
                split,
                "--episodes",
                str(configs),
                "--variants",
                variants,
                "--workers",
                str(workers),
                "--out",
                out,
            ],
            capture_output=True,
            text=True,
            timeout=7200,
        )
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise RuntimeError(f"tidee eval tidy --workers {workers} failed: {r.stderr[-1500:]}")
        report = load_report(out)
    agents = [v for v in variants.split(",") if v]
    episodes = [e for e in report["episodes"] if e["variant"] in agents]
    return {
        "wall_s": wall,
        "episodes": len(episodes),
        "episode_wall_s": [float(e["wall_s"]) for e in episodes],
    }


def run_scale_bench(
    out: str, configs: int = 4, variants: str = "TIDEE", repeats: int = 1, split: str = "test"
) -> dict[str, Any]:
    from tidee.server.bench_sim import spread, write_report

    _warm_scene_cache(split, configs)
    load0 = os.getloadavg()[0]
    runs: dict[int, list[dict[str, Any]]] = {1: [], 2: []}
    for k in range(repeats):
        for workers in (1, 2) if k % 2 == 0 else (2, 1):
            runs[workers].append(_eval(workers, split, configs, variants))
    result: dict[str, Any] = {
        "split": split,
        "configurations": configs,
        "agents": variants,
        "repeats": repeats,
    }
    for workers, rs in runs.items():
        result[f"workers_{workers}_command_s"] = spread([r["wall_s"] for r in rs])
        result[f"workers_{workers}_episode_wall_s"] = spread([w for r in rs for w in r["episode_wall_s"]])
        result[f"workers_{workers}_episodes_per_min"] = round(
            float(np.median([60.0 * r["episodes"] / r["wall_s"] for r in rs])), 2
        )
    result["speedup_1_to_2"] = round(
        result["workers_2_episodes_per_min"] / result["workers_1_episodes_per_min"], 2
    )
    result["machine"] = f"{platform.machine()} {os.cpu_count()} cores"
    result["load_avg_1m_before_after"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    result["command"] = (
        f"tidee bench scale --configs {configs} --variants {variants} --repeats {repeats} "
        f"--split {split} --out {out}"
    )
    write_report(out, result, "Scaling benchmark (`tidee bench scale`): tidy episodes with 1 vs 2 workers")
    return result
