"""``tidee eval tidy``: tidy episodes on held-out rooms, scored by the simulated judge.

Runs each requested agent variant on the same messy configurations of a split (test by
default: 20 rooms x 5 messes), in-process (one simulator per worker process), and writes
``report.json``, ``report.md`` and PNG plots through ``tidee.agent.evaluation.report``.
Ground truth is read only here, after each episode, to score it (and by the agent itself
only when perception is "oracle", which every report names).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.config import REFERENCE_VARIANTS, AgentConfig, check_variant_built
from tidee.agent.evaluation.config import TidyEvalConfig
from tidee.protocol.messages import EpisodeSpec
from tidee.threads import threads_per_process


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


def _run_one(job: TidyJob) -> dict[str, Any]:
    """One episode in this worker's own simulator (module-level so it pickles)."""
    from tidee.agent.runner import AgentModels, EpisodeRunner
    from tidee.protocol.transport import InProcessTransport

    transport = _WORKER.get("transport")
    if transport is None:  # a caller that did not run _init_worker: make this process's simulator now
        transport = _WORKER["transport"] = InProcessTransport(renderer=job.renderer)
    cfg, spec = job.agent, job.spec
    models = _WORKER.setdefault("models", {})
    key = AgentModels.key_of(cfg)
    if key not in models:
        models[key] = AgentModels.load(cfg)
    runner = EpisodeRunner(cfg, transport, session="eval", log_dir=job.log_dir, models=models[key])
    res = runner.run(
        spec,
        evaluate=True,
        episode_name=f"{cfg.variant}_{spec.room_type}_{spec.seed}_mess{spec.mess_index}",
    )
    assert res.record is not None
    record = dict(res.record, split=job.split)
    record["timing_ms"] = {k: float(np.median(v)) if v else None for k, v in res.timings.items()}
    return record


_WORKER: dict[str, Any] = {}  # this process's simulator and loaded models, reused by every episode it runs


def _init_worker(renderer: str, threads: int) -> None:
    """Set up a worker process: its share of the cores (tidee.threads) and its own simulator."""
    from tidee.protocol.transport import InProcessTransport
    from tidee.threads import use_threads

    use_threads(threads)
    _WORKER["transport"] = InProcessTransport(renderer=renderer)


def run_jobs(jobs: list[TidyJob], workers: int, renderer: str, progress: bool = True) -> list[dict[str, Any]]:
    """Every job's episode record, in job order: in this process (``workers`` 1) or in a pool of
    worker processes, each with its own simulator and its loaded models."""
    from tqdm import tqdm

    records: list[dict[str, Any]] = []
    bar = tqdm(total=len(jobs), desc="tidy episodes", disable=not progress)
    threads = threads_per_process(max(1, workers))
    if workers <= 1:
        if "transport" not in _WORKER:
            _init_worker(renderer, threads)
        for job in jobs:
            records.append(_run_one(job))
            bar.update()
    else:
        with cf.ProcessPoolExecutor(
            workers,
            mp_context=mp.get_context("spawn"),
            initializer=_init_worker,
            initargs=(renderer, threads),
        ) as pool:
            for rec in pool.map(_run_one, jobs):
                records.append(rec)
                bar.update()
    bar.close()
    return records


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
    records = run_jobs(jobs, workers, renderer, progress)
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
        + f"--max-steps {max_steps} --resolution {resolution} --workers {workers} --out {out}",
        f"total wall time {time.time() - t0:.0f} s with {workers} worker(s)",
    ]
    return write_report(all_records, out, title=f"Tidy evaluation ({split} rooms)", notes=notes)
