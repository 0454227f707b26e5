"""``tidee eval tidy``: tidy episodes on held-out rooms, scored by the simulated judge.

Runs each requested agent variant on the same messy configurations of a split (test by
default: 20 rooms x 5 messes) on worker processes or Ray actors (``backends``: one simulator
and one set of loaded models per worker), streams each episode's record to
``OUT/episodes.jsonl`` (``--resume`` skips the episodes already there), and writes
``report.json``, ``report.md`` and PNG plots through ``tidee.agent.evaluation.report``.
Ground truth is read only here, after each episode, to score it (and by the agent itself
only when perception is "oracle", which every report names).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.config import REFERENCE_VARIANTS, AgentConfig, check_variant_built
from tidee.agent.evaluation import backends
from tidee.agent.evaluation.backends import Backend, worker_models, worker_transport
from tidee.agent.evaluation.config import TidyEvalConfig
from tidee.protocol.messages import EpisodeSpec

EPISODES_FILE = "episodes.jsonl"  # in OUT: every episode's record as it finishes (--resume reads it)


def select_configs(split: str, episodes: int | None) -> list[Any]:
    """``episodes`` configurations spread evenly over the split (all of them when None)."""
    from tidee.server.splits import mess_config, num_configs

    n = num_configs(split)
    if episodes is None or episodes >= n:
        idx = list(range(n))
    else:
        if episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {episodes}")
        idx = sorted({int(round(i)) for i in np.linspace(0, n - 1, episodes)})
    return [mess_config(split, i) for i in idx]


@dataclass(frozen=True)
class TidyJob:
    """One episode of the eval: the agent and the episode, as the config objects themselves."""

    agent: AgentConfig
    spec: EpisodeSpec
    split: str
    renderer: str
    log_dir: Path | None = None

    def key(self) -> str:
        """The episode's key in ``episodes.jsonl``: agent, room, seed, mess and a digest of every
        option that shapes the episode (a resumed run with other options runs it again)."""
        shape = {
            "agent": asdict(self.agent),
            "spec": asdict(self.spec),
            "split": self.split,
            "renderer": self.renderer,
        }
        digest = hashlib.sha1(json.dumps(shape, sort_keys=True, default=str).encode()).hexdigest()[:10]
        s = self.spec
        return f"{self.agent.variant}/{s.room_type}/{s.seed}/mess{s.mess_index}/{digest}"


def _run_one(job: TidyJob) -> dict[str, Any]:
    """One episode in this worker's own simulator with its loaded models (module-level so it pickles)."""
    from tidee.agent.runner import EpisodeRunner

    cfg, spec = job.agent, job.spec
    transport = worker_transport(job.renderer)
    runner = EpisodeRunner(cfg, transport, session="eval", log_dir=job.log_dir, models=worker_models(cfg))
    res = runner.run(
        spec,
        evaluate=True,
        episode_name=f"{cfg.variant}_{spec.room_type}_{spec.seed}_mess{spec.mess_index}",
    )
    assert res.record is not None
    record = dict(res.record, split=job.split)
    record["timing_ms"] = {k: float(np.median(v)) if v else None for k, v in res.timings.items()}
    return record


def run_jobs(
    jobs: list[TidyJob],
    workers: int,
    renderer: str,
    progress: bool = True,
    *,
    backend: Backend = "local",
    ray_address: str | None = None,
    out_jsonl: Path | None = None,
    resume: bool = False,
) -> list[dict[str, Any]]:
    """Every job's episode record, in job order (``backends.run_jobs`` with this eval's episode)."""
    return backends.run_jobs(
        jobs,
        _run_one,
        workers=workers,
        renderer=renderer,
        backend=backend,
        ray_address=ray_address,
        progress=progress,
        out_jsonl=out_jsonl,
        resume=resume,
        desc="tidy episodes",
    )


def run_tidy_eval(cfg: TidyEvalConfig) -> dict[str, Any]:

    from tidee.agent.evaluation.report import with_references, write_report

    agent = cfg.agent  # "auto" OOP resolved, a bad threshold or missing_top refused: before any episode
    split, variants, workers, renderer = cfg.split, list(cfg.variants), cfg.workers, cfg.renderer
    perception, oop, depth, explorer = agent.perception, agent.oop, agent.depth, agent.explorer
    missing_top, detection_threshold = agent.policy.missing_top, agent.detection_threshold
    resolution, max_steps, progress = cfg.resolution, cfg.max_steps, cfg.progress
    agents = [v for v in variants if v not in REFERENCE_VARIANTS]
    for v in agents:
        check_variant_built(v)  # reads the placement registry: a registered variant of yours is an agent
    if not agents:
        raise ValueError("give at least one agent variant (the reference rows need an agent's episodes)")
    if cfg.ray_address is not None and cfg.backend != "ray":
        raise ValueError("--ray-address is for --backend ray")
    if cfg.backend == "ray":
        backends.import_ray()  # not installed: say how, before any episode
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    configs = select_configs(split, cfg.episodes)
    jobs = [
        TidyJob(
            agent=replace(agent, variant=v, seed=c.index),
            spec=EpisodeSpec(
                room_type=c.room_type,
                seed=c.seed,
                mess_index=c.mess_index,
                resolution=resolution,
                max_steps=max_steps,
            ),
            split=split,
            renderer=renderer,
            log_dir=out / "logs" if cfg.keep_logs else None,
        )
        for c in configs
        for v in agents
    ]
    t0 = time.time()
    episodes_file = out / EPISODES_FILE
    resumed = len({j.key() for j in jobs} & set(backends.read_records(episodes_file))) if cfg.resume else 0
    records = run_jobs(
        jobs,
        workers,
        renderer,
        progress,
        backend=cfg.backend,
        ray_address=cfg.ray_address,
        out_jsonl=episodes_file,
        resume=cfg.resume,
    )
    retries = sum(int(r.get("retries", 0)) for r in records)
    all_records = with_references(records)
    keep = set(variants) | set(agents)
    if not any(v in REFERENCE_VARIANTS for v in variants):
        keep |= set(REFERENCE_VARIANTS)  # the reference rows are always part of Table 1
    all_records = [r for r in all_records if r["variant"] in keep]
    timing = {
        k: float(np.median([r["timing_ms"][k] for r in records if r.get("timing_ms", {}).get(k) is not None]))
        for k in ("perception_ms", "mapping_ms", "planning_ms", "step_ms", "sim_ms")
    }
    notes = [
        f"split={split}, {len(configs)} messy configurations x {len(agents)} agents, "
        f"resolution {resolution}, max {max_steps} steps, OOP detector '{oop}', explorer '{explorer}', "
        f"missing top receptacle: {missing_top}",
        f"perception: {perception}"
        + (
            " (ORACLE: detections from the simulator's segmentation)"
            if perception == "oracle"
            else " (the shipped RGB-D detector)"
        )
        + f", depth: {depth}"
        + (f", detection threshold {detection_threshold}" if detection_threshold is not None else ""),
        "median per-step agent time (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in timing.items()),
        f"command: tidee eval tidy --split {split} --episodes {len(configs)} --variants {','.join(variants)} "
        f"--perception {perception} --oop {oop} --depth {depth} --explorer {explorer} "
        f"--missing-top {missing_top} "
        + (f"--detection-threshold {detection_threshold} " if detection_threshold is not None else "")
        + f"--max-steps {max_steps} --resolution {resolution} --workers {workers} "
        + (f"--backend {cfg.backend} " if cfg.backend != "local" else "")
        + f"--out {out}",
        f"total wall time {time.time() - t0:.0f} s with {workers} worker(s), backend {cfg.backend}"
        + (f" ({cfg.ray_address})" if cfg.ray_address else "")
        + f"; {retries} episode retries after a worker died"
        + (f"; {resumed} episodes resumed from {EPISODES_FILE}" if resumed else ""),
    ]
    return write_report(all_records, out, title=f"Tidy evaluation ({split} rooms)", notes=notes)
