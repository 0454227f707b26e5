"""``tidee eval tidy``: tidy episodes on held-out rooms, scored by the simulated judge.

Runs each requested agent variant on the same messy configurations of a split (test by
default: 20 rooms x 5 messes), once under each requested condition (``--conditions``: clean,
noisy pose, estimated or noisy depth; one report row each, named as in the paper, e.g.
"TIDEE +noisy pose"), on worker processes or Ray actors (``tidee.batch``: one simulator
and one set of loaded models per worker), streams each episode's record to
``OUT/episodes.jsonl`` (``--resume`` skips the episodes already there), and writes
``report.json``, ``report.md`` and PNG plots through ``tidee.agent.evaluation.report``.
Ground truth is read only here, after each episode, to score it (and by the agent itself
only when perception is "oracle", which every report names).
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tidee import batch
from tidee.agent.config import REFERENCE_VARIANTS, AgentConfig, check_variant_built
from tidee.agent.evaluation.conditions import CONDITION_MEANINGS, Condition, apply_condition, row_name
from tidee.agent.evaluation.config import TidyEvalConfig
from tidee.agent.perception import DETECTOR_SETS
from tidee.batch import Backend, worker_transport
from tidee.protocol.messages import EpisodeSpec
from tidee.server.config import TRAINED_RENDERER

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
    """One episode of the eval: the agent and the episode, as the config objects themselves, and
    the condition (``tidee.agent.evaluation.conditions``) they were built for."""

    agent: AgentConfig
    spec: EpisodeSpec
    split: str
    renderer: str
    log_dir: Path | None = None
    condition: Condition = "clean"

    @property
    def row(self) -> str:
        """The report row: the variant's name, with the condition's suffix unless clean."""
        return row_name(self.agent.variant, self.condition)

    def key(self) -> str:
        """The episode's key in ``episodes.jsonl``: agent, room, seed, mess and a digest of every
        option that shapes the episode (a resumed run with other options runs it again; each
        condition changes the agent's depth or the episode's noise, so the digest)."""
        shape: dict[str, Any] = {
            "agent": asdict(self.agent),
            "spec": asdict(self.spec),
            "split": self.split,
            "renderer": self.renderer,
        }
        if self.agent.preferences:  # a profile file written again with other sentences is another episode
            prefs = Path(self.agent.preferences)
            shape["preferences_text"] = prefs.read_text() if prefs.is_file() else None
        digest = hashlib.sha1(json.dumps(shape, sort_keys=True, default=str).encode()).hexdigest()[:10]
        s = self.spec
        return f"{self.agent.variant}/{s.room_type}/{s.seed}/mess{s.mess_index}/{digest}"

    def label(self, record: dict[str, Any]) -> dict[str, Any]:
        """``record`` (this job's episode) with its row and condition: ``variant`` the report row,
        ``agent_variant`` the agent, and the condition's settings."""
        return dict(
            record,
            variant=self.row,
            agent_variant=self.agent.variant,
            condition=self.condition,
            pose_noise=self.spec.pose_noise,
            depth_noise=self.spec.depth_noise,
            depth=self.agent.depth,
            split=self.split,
        )


def _run_one(job: TidyJob) -> dict[str, Any]:
    """One episode in this worker's own simulator with its loaded models (module-level so it pickles)."""
    from tidee.agent.runner import EpisodeRunner, worker_models

    cfg, spec = job.agent, job.spec
    transport = worker_transport(job.renderer)
    runner = EpisodeRunner(cfg, transport, session="eval", log_dir=job.log_dir, models=worker_models(cfg))
    suffix = "" if job.condition == "clean" else f"_{job.condition}"
    res = runner.run(
        spec,
        evaluate=True,
        episode_name=f"{cfg.variant}{suffix}_{spec.room_type}_{spec.seed}_mess{spec.mess_index}",
    )
    assert res.record is not None
    record = job.label(res.record)
    record["timing_ms"] = {k: float(np.median(v)) if v else None for k, v in res.timings.items()}
    return record


UNCACHED_COST = 1000.0  # above any room's object count: a reset that generates its room runs physics


def episode_cost(spec: EpisodeSpec) -> float:
    """An estimate of an episode's run time, to start the longest first: the number of objects in
    its room (over the 100 test configurations TIDEE's episode wall time rises with it, Spearman
    0.71), read from the scene cache; a room not cached costs more than any (its reset generates it)."""
    return _room_cost(spec.room_type, spec.seed)


@functools.lru_cache(maxsize=256)
def _room_cost(room_type: str, seed: int) -> float:
    from tidee.server.scene_cache import SceneCache

    scene = SceneCache().load(room_type, seed, None)
    return UNCACHED_COST if scene is None else float(len(scene["objects"]))


def _job_cost(job: TidyJob) -> float:
    return episode_cost(job.spec)


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
    """Every job's episode record, in job order (``tidee.batch.run_jobs`` with this eval's episode)."""
    return batch.run_jobs(
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
        cost=_job_cost,
    )


def agent_variants(cfg: TidyEvalConfig) -> list[str]:
    """The agents among ``cfg.variants`` (not the reference rows), each checked to be built."""
    agents = [v for v in cfg.variants if v not in REFERENCE_VARIANTS]
    for v in agents:
        check_variant_built(v)  # reads the placement registry: a registered variant of yours is an agent
    if not agents:
        raise ValueError("give at least one agent variant (the reference rows need an agent's episodes)")
    return agents


def build_jobs(cfg: TidyEvalConfig, configs: list[Any] | None = None) -> list[TidyJob]:
    """Every episode of the eval, without running any: per configuration, each agent under each
    condition (``configs``: ``select_configs(cfg.split, cfg.episodes)`` when None)."""
    agent = cfg.agent  # "auto" OOP resolved, a bad threshold or missing_top refused: before any episode
    agents = agent_variants(cfg)
    if configs is None:
        configs = select_configs(cfg.split, cfg.episodes)
    log_dir = Path(cfg.out) / "logs" if cfg.keep_logs else None
    jobs = []
    for c in configs:
        base = EpisodeSpec(
            room_type=c.room_type,
            seed=c.seed,
            mess_index=c.mess_index,
            resolution=cfg.resolution,
            max_steps=cfg.max_steps,
        )
        for v in agents:
            for condition in cfg.conditions:
                row_agent, spec = apply_condition(condition, replace(agent, variant=v, seed=c.index), base)
                jobs.append(TidyJob(row_agent, spec, cfg.split, cfg.renderer, log_dir, condition))
    return jobs


# the agent options the report's command names whatever their value (the rest: when not default)
_SPELLED_OUT = ("variant", "perception", "oop", "depth", "explorer", "missing_top", "detection_threshold")


def run_tidy_eval(cfg: TidyEvalConfig) -> dict[str, Any]:

    from tidee.agent.evaluation.report import agent_flags, machine_note, with_references, write_report

    agent = cfg.agent
    split, variants, workers, renderer = cfg.split, list(cfg.variants), cfg.workers, cfg.renderer
    perception, oop, depth, explorer = agent.perception, agent.oop, agent.depth, agent.explorer
    missing_top, detection_threshold = agent.policy.missing_top, agent.detection_threshold
    resolution, max_steps, progress = cfg.resolution, cfg.max_steps, cfg.progress
    conditions = list(cfg.conditions)
    agents = agent_variants(cfg)
    if cfg.batch.backend == "ray":
        batch.import_ray()  # not installed: say how, before any episode
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    configs = select_configs(split, cfg.episodes)
    jobs = build_jobs(cfg, configs)
    t0 = time.time()
    episodes_file = out / EPISODES_FILE
    resumed = batch.stored_jobs(jobs, episodes_file) if cfg.batch.resume else 0
    records = run_jobs(
        jobs,
        workers,
        renderer,
        progress,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        out_jsonl=episodes_file,
        resume=cfg.batch.resume,
    )
    records = [j.label(r) for j, r in zip(jobs, records, strict=True)]  # resumed records too
    retries = sum(int(r.get("retries", 0)) for r in records)
    # The reference rows depend on the mess only, not on the agent's perception: built once per
    # configuration, from a clean record where there is one.
    ordered = sorted(records, key=lambda r: r["condition"] != "clean")
    all_records = records + with_references(ordered)[len(ordered) :]
    rows = [j.row for j in jobs]
    keep = set(variants) | set(rows)
    if not any(v in REFERENCE_VARIANTS for v in variants):
        keep |= set(REFERENCE_VARIANTS)  # the reference rows are always part of Table 1
    all_records = [r for r in all_records if r["variant"] in keep]
    timing = {
        k: float(np.median([r["timing_ms"][k] for r in records if r.get("timing_ms", {}).get(k) is not None]))
        for k in ("perception_ms", "mapping_ms", "planning_ms", "step_ms", "sim_ms")
    }
    notes = [
        f"split={split}, {len(configs)} messy configurations x {len(agents)} agents"
        + (f" x {len(conditions)} conditions" if len(conditions) > 1 else "")
        + f", resolution {resolution}, max {max_steps} steps, OOP detector '{oop}', explorer '{explorer}', "
        f"missing top receptacle: {missing_top}",
        f"perception: {perception}"
        + (
            " (ORACLE: detections from the simulator's segmentation)"
            if perception == "oracle"
            else " (the shipped RGB-D detector)"
        )
        + (
            f", detector {agent.detector}, frames drawn by {renderer}"
            if (agent.detector, renderer) != (DETECTOR_SETS[0], TRAINED_RENDERER)
            else ""
        )
        + f", depth: {depth}"
        + (" (the est-depth rows: estimated)" if depth != "estimated" and "est-depth" in conditions else "")
        + (f", detection threshold {detection_threshold}" if detection_threshold is not None else ""),
        "conditions (one row per agent and condition): "
        + "; ".join(f"{row_name('VARIANT', c)}: {c}, {CONDITION_MEANINGS[c]}" for c in conditions)
        + (
            "; the reference rows come once per configuration from "
            + ("its clean episodes" if "clean" in conditions else "its first episode")
            + " (they depend on the mess only)"
            if conditions != ["clean"]
            else ""
        ),
        "median per-step agent time (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in timing.items()),
        f"command: tidee eval tidy --split {split} --episodes {len(configs)} --variants {','.join(variants)} "
        + (f"--conditions {','.join(conditions)} " if conditions != ["clean"] else "")
        + f"--perception {perception} --oop {oop} --depth {depth} --explorer {explorer} "
        f"--missing-top {missing_top} "
        + (f"--detection-threshold {detection_threshold} " if detection_threshold is not None else "")
        + agent_flags(agent, skip=_SPELLED_OUT)
        + f"--max-steps {max_steps} --resolution {resolution} --workers {workers} "
        + (f"--renderer {renderer} " if renderer != TRAINED_RENDERER else "")
        + (f"--backend {cfg.batch.backend} " if cfg.batch.backend != "local" else "")
        + f"--out {out}",
        f"total wall time {time.time() - t0:.0f} s with {workers} worker(s), backend {cfg.batch.backend}"
        + (f" ({cfg.batch.ray_address})" if cfg.batch.ray_address else "")
        + f"; {retries} episode retries after a worker died"
        + (f"; {resumed} episodes resumed from {EPISODES_FILE}" if resumed else ""),
        machine_note(),
    ]
    return write_report(all_records, out, title=f"Tidy evaluation ({split} rooms)", notes=notes)
