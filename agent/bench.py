"""``tidee bench agent``: how long the agent's own work takes per step, and whole episodes.

Runs a few test-room episodes in process (pinned to one CPU core where the OS allows it,
as the targets are stated per core) and reports medians of perception, mapping,
planning (OOP scoring + policy + FMM) and the whole agent step (their sum), the
simulator's step time, and episode wall time. Writes JSON + Markdown.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from tidee.agent.config import AgentConfig
from tidee.agent.evaluation.report import machine_note
from tidee.agent.evaluation.tidy_eval import select_configs
from tidee.agent.perception import TRAINED_RENDERER
from tidee.agent.runner import EpisodeRunner
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.transport import InProcessTransport


def run_agent_bench(
    out: str,
    episodes: int = 3,
    resolution: int = 256,
    variant: str = "TIDEE",
    max_steps: int = 1000,
    one_core: bool = True,
    perception: str = "learned",
) -> dict[str, Any]:
    from tidee.server.bench_sim import write_report

    pinned = False
    if one_core and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        pinned = True
        import torch

        torch.set_num_threads(1)
    load_before = os.getloadavg()
    cfg = AgentConfig(variant=variant, perception=perception)
    per: dict[str, list[float]] = {}
    walls, steps = [], []
    with InProcessTransport(renderer=TRAINED_RENDERER) as transport:
        runner = EpisodeRunner(cfg, transport, session="bench")
        for c in select_configs("test", episodes):
            spec = EpisodeSpec(
                room_type=c.room_type,
                seed=c.seed,
                mess_index=c.mess_index,
                resolution=resolution,
                max_steps=max_steps,
            )
            t0 = time.perf_counter()
            res = runner.run(spec)
            walls.append(time.perf_counter() - t0)
            steps.append(res.steps)
            for k, v in res.timings.items():
                per.setdefault(k, []).extend(v)
    load_after = os.getloadavg()
    med = {k: round(float(np.median(v)), 2) for k, v in per.items() if v}
    p90 = {k: round(float(np.percentile(v, 90)), 2) for k, v in per.items() if v}
    top = {k: round(float(np.max(v)), 2) for k, v in per.items() if v}
    result = {
        "resolution": resolution,
        "episodes": len(walls),
        "variant": variant,
        "perception": perception,
        "pinned_to_one_core": pinned,
        "perception_ms_median": med.get("perception_ms"),
        "mapping_ms_median": med.get("mapping_ms"),
        "planning_ms_median": med.get("planning_ms"),
        "mapping_plus_planning_ms_median": round(
            float(np.median(np.add(per["mapping_ms"], per["planning_ms"]))), 2
        ),
        "agent_step_ms_median": med.get("step_ms"),
        "agent_step_ms_p90": p90.get("step_ms"),
        "agent_step_ms_max": top.get("step_ms"),
        "sim_step_ms_median": med.get("sim_ms"),
        "episode_wall_s_median": round(float(np.median(walls)), 1),
        "episode_steps_median": float(np.median(steps)),
        "targets": {
            "agent_step_ms": 20.0,
            "mapping_plus_planning_ms": 20.0,
            "episode_wall_s": 60.0,
            "perception_ms": 30.0,
        },
        "load_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
        "machine": machine_note().removeprefix("machine: "),
        "command": f"tidee bench agent --episodes {episodes} --resolution {resolution} --variant {variant} "
        f"--perception {perception} --max-steps {max_steps} --out {out}",
    }
    write_report(out, result, f"Agent benchmark ({perception} perception, in-process simulator, one core)")
    return result
