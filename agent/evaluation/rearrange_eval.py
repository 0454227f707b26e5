"""``tidee eval rearrange``: the 2-phase rearrangement task on held-out rooms (the paper's Table 4).

Each configuration of the split (test: 20 rooms x 5 rearrangements) is played by the reduced
TIDEE agent (``tidee.agent.policy.rearrange``) under each requested row:

==============  ===========================================================================
clean           learned perception (the shipped detector), sensor depth, exact odometry
noisy-pose      + LoCoBot-like pose noise (0.005 m per move, 0.5 deg per turn; the paper's)
est-depth       depth estimated from RGB by the shipped depth network, never the sensor
noisy-depth     + multiplicative depth noise on the sensor
oracle          ORACLE perception: detections from the simulator's segmentation
do-nothing      no agent: the shuffled room as it is (the metrics' floor)
==============  ===========================================================================

Episodes are scored after they end with RoomR's metrics
(``tidee.agent.evaluation.rearrange_metrics``) against the server's privileged goal, start
and end states: the only reads of ground truth, apart from the oracle row's perception.
Writes ``report.json`` (every episode record and the per-row means), ``report.md`` (the
table beside the paper's and RoomR's figures) and ``report.png``.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.config import AgentConfig
from tidee.agent.evaluation.config import RearrangeEvalConfig
from tidee.agent.evaluation.rearrange_fates import OPENABLE_FATES, PICKUPABLE_FATES, sum_counts
from tidee.agent.evaluation.rearrange_metrics import aggregate, episode_metrics
from tidee.batch import run_jobs, stored_jobs, worker_transport
from tidee.protocol.episode_log import write_atomic
from tidee.protocol.messages import Action, ActionName, EpisodeSpec

# The paper's Table 4 (RoomR 2022 test set) and Table S1 (2021): FixedStrict, Success, Energy,
# Misplaced, in percent; and the best 2-phase FixedStrict on RoomR's 2022 leaderboard.
PAPER_TABLE4 = {
    "clean": (11.6, 2.4, 93, 94),
    "noisy-pose": (7.7, 1.2, 101, 101),
    "est-depth": (5.9, 0.6, 97, 97),
    "noisy-depth": (11.4, 2.0, 94, 95),
}
PAPER_TABLE_S1 = {
    "clean": (8.9, 2.6, 93, 95),
    "noisy-pose": (6.6, 1.9, 97, 98),
    "est-depth": (5.5, 1.4, 96, 97),
    "noisy-depth": (8.9, 2.3, 93, 95),
}
ROOMR_BASELINE = (0.5, 0.0, 110, 110)  # Weihs et al.'s PPO+IL agent, in the paper's Table 4
ROOMR_LEADERBOARD_BEST_FIXED_STRICT = 28.9
ROW_TITLES = {
    "clean": "TIDEE (learned perception)",
    "noisy-pose": "TIDEE +noisy pose",
    "est-depth": "TIDEE +est. depth",
    "noisy-depth": "TIDEE +noisy depth",
    "oracle": "TIDEE, ORACLE perception",
    "do-nothing": "do nothing",
    "commonsense": "TIDEE + commonsense for unmatched objects",
}


@dataclass(frozen=True)
class RearrangeJob:
    """One episode of one row."""

    row: str
    agent: AgentConfig | None  # None: the do-nothing row
    spec: EpisodeSpec
    split: str
    index: int  # the configuration's index in the split
    renderer: str
    log_dir: Path | None = None

    def key(self) -> str:
        shape = {
            "agent": asdict(self.agent) if self.agent else None,
            "spec": asdict(self.spec),
            "renderer": self.renderer,
        }
        digest = hashlib.sha1(json.dumps(shape, sort_keys=True, default=str).encode()).hexdigest()[:10]
        s = self.spec
        return f"{self.row}/{s.room_type}/{s.seed}/rearrange{s.rearrange_index}/{digest}"


def row_setup(row: str, agent: AgentConfig, spec: EpisodeSpec) -> tuple[AgentConfig | None, EpisodeSpec]:
    """The agent and episode of ``row`` from the clean ones (the noise and depth rows are the
    conditions of ``tidee.agent.evaluation.conditions``, shared with ``eval tidy``)."""
    from tidee.agent.evaluation.conditions import CONDITIONS, apply_condition

    if row == "do-nothing":
        return None, spec
    if row in CONDITIONS:
        return apply_condition(row, agent, spec)
    if row == "oracle":  # no scores to threshold: a --detection-threshold is the learned rows'
        return replace(agent, perception="oracle", oop="auto", detection_threshold=None), spec
    if row == "commonsense":
        return replace(agent, policy=replace(agent.policy, unmatched="commonsense")), spec
    return agent, spec


def _run_one(job: RearrangeJob) -> dict[str, Any]:
    """One episode in this worker's simulator (module-level so it pickles)."""
    transport = worker_transport(job.renderer)
    spec = job.spec
    if job.agent is None:
        t0 = time.perf_counter()
        transport.reset(spec)
        goal = transport.state()
        transport.begin_unshuffle()
        start = transport.state()
        obs = transport.step(Action(ActionName.Done))
        record: dict[str, Any] = {
            "variant": "Rearrange",
            "perception": None,
            "room_type": spec.room_type,
            "seed": spec.seed,
            "rearrange_index": spec.rearrange_index,
            "walkthrough_steps": 0,
            "steps": int(obs.step),
            "wall_s": round(time.perf_counter() - t0, 2),
            "end_reason": "did nothing",
            "believed_moved": 0,
            "believed_toggled": 0,
            "changed_found": 0,
            "false_beliefs": 0,
            "rearrange": episode_metrics(goal["objects"], start["objects"], transport.state()["objects"]),
        }
    else:
        from tidee.agent.runner import EpisodeRunner, worker_models

        runner = EpisodeRunner(
            job.agent, transport, session="eval", log_dir=job.log_dir, models=worker_models(job.agent)
        )
        res = runner.run(
            spec,
            evaluate=True,
            episode_name=f"{job.row}_{spec.room_type}_{spec.seed}_rearrange{spec.rearrange_index}",
        )
        assert res.record is not None
        record = dict(res.record)
        record["timing_ms"] = {k: float(np.median(v)) if v else None for k, v in res.timings.items()}
    record.update(row=job.row, split=job.split, index=job.index)
    return record


def row_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means of RoomR's metrics over a row's episodes, with steps and wall time."""
    out = aggregate([r["rearrange"] for r in records])
    out["steps_median"] = float(np.median([r["steps"] + (r.get("walkthrough_steps") or 0) for r in records]))
    # How long the walkthrough looked: it ends before its cap once the survey has been to every
    # waypoint it drew from the reachable map.
    walked = [r["walkthrough_steps"] for r in records if r.get("walkthrough_steps")]
    out["walkthrough_steps_median"] = float(np.median(walked)) if walked else None
    walls = [r["wall_s"] for r in records]
    out["wall_s_median"] = float(np.median(walls))
    out["wall_s_p90"] = float(np.percentile(walls, 90))
    out["wall_s_max"] = float(np.max(walls))
    for kind in ("pickupable", "openable"):
        # A kind's own FixedStrict, over the episodes in which something of that kind was changed
        # (RoomR counts an episode with nothing to fix as fully fixed).
        had = [
            r["rearrange"]["by_kind"][kind]
            for r in records
            if r["rearrange"]["by_kind"][kind]["start_misplaced"]
        ]
        out[f"fixed_strict_{kind}"] = float(np.mean([k["fixed_strict"] for k in had])) if had else None
        out[f"episodes_{kind}"] = len(had)
    out["changed"] = int(sum(r["rearrange"]["start_misplaced"] for r in records))
    out["changed_found"] = int(sum(r.get("changed_found", 0) for r in records))
    out["false_beliefs"] = int(sum(r.get("false_beliefs", 0) for r in records))
    out["believed_moved"] = int(sum(r["believed_moved"] for r in records))
    out["believed_toggled"] = int(sum(r["believed_toggled"] for r in records))
    with_fates = [r["fates"] for r in records if r.get("fates")]
    out["fates"] = sum_counts(with_fates) if with_fates else None
    out["put_off"] = put_errors([c for f in with_fates for c in f["changes"]])
    out["by_receptacle"] = by_receptacle([c for f in with_fates for c in f["changes"]])
    return out


def by_receptacle(changes: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, int]]]:
    """The moved pickupables' fates by what held them: ``{"goal_on" | "start_on": {type: {fate: n,
    "n": n}}}`` (rows without the field, from older records, are left out)."""
    out: dict[str, dict[str, dict[str, int]]] = {"goal_on": {}, "start_on": {}}
    for c in changes:
        for side, table in out.items():
            if c.get("kind") != "pickupable" or c.get(side) is None:
                continue
            cell = table.setdefault(str(c[side]), {"n": 0})
            cell["n"] += 1
            cell[c["fate"]] = cell.get(c["fate"], 0) + 1
    return out


def _count(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f}"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def format_markdown(report: dict[str, Any]) -> str:
    rows = report["rows"]
    lines = [
        f"# 2-phase rearrangement ({report['split']} rooms, {report['configurations']} configurations)",
        "",
        "RoomR's metrics (Weihs et al. 2021; `agent/evaluation/rearrange_metrics.py`), means over episodes "
        "in percent: FixedStrict and Success higher is better, Energy and Misplaced lower is better. "
        "The pickupable and openable columns are FixedStrict over those objects alone, averaged over the "
        "episodes that changed some (n in brackets). Changes found: changed objects the agent believed "
        "moved or toggled; false beliefs: unchanged objects it believed changed (scored after the episode).",
        "",
        "| row | FixedStrict | Success | Energy | Misplaced | FixedStrict, pickupable "
        "| FixedStrict, openable | changes found | false beliefs | episodes | steps (median) "
        "| walkthrough steps (median) | wall s (median / p90 / max) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in rows.items():
        pick, opn = m["fixed_strict_pickupable"], m["fixed_strict_openable"]
        lines.append(
            f"| {ROW_TITLES.get(name, name)} | {_pct(m['fixed_strict'])} | {_pct(m['success'])} | "
            f"{_pct(m['energy'])} | {_pct(m['misplaced'])} | {_pct(pick)} ({m['episodes_pickupable']}) | "
            f"{_pct(opn)} ({m['episodes_openable']}) | {m['changed_found']} of {m['changed']} | "
            f"{m['false_beliefs']} | {m['episodes']} | "
            f"{m['steps_median']:.0f} | "
            f"{_count(m['walkthrough_steps_median'])} | "
            f"{m['wall_s_median']:.1f} / {m['wall_s_p90']:.1f} / {m['wall_s_max']:.1f} |"
        )
    lines += fates_markdown(rows)
    lines += receptacles_markdown(rows)
    lines += [
        "",
        "For comparison (not the same rooms: AI2THOR's RoomR test sets, with the paper's own agent and "
        "perception):",
        "",
        "| paper | FixedStrict | Success | Energy | Misplaced |",
        "|---|---|---|---|---|",
    ]
    for name, (fs, su, en, mi) in PAPER_TABLE4.items():
        lines.append(f"| Table 4 (RoomR 2022): {ROW_TITLES[name]} | {fs} | {su} | {en} | {mi} |")
    for name, (fs, su, en, mi) in PAPER_TABLE_S1.items():
        lines.append(f"| Table S1 (RoomR 2021): {ROW_TITLES[name]} | {fs} | {su} | {en} | {mi} |")
    fs, su, en, mi = ROOMR_BASELINE
    lines.append(f"| Table 4: Weihs et al. (RoomR's PPO+IL baseline) | {fs} | {su} | {en} | {mi} |")
    lines.append(f"| RoomR 2022 leaderboard, best 2-phase | {ROOMR_LEADERBOARD_BEST_FIXED_STRICT} | | | |")
    lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]]
    return "\n".join(lines) + "\n"


PUT_ERRORS = ("position_cm", "yaw_deg", "iou", "estimate_cm", "landed_cm")


def put_errors(changes: list[dict[str, Any]]) -> dict[str, float | None]:
    """Medians of the put-off objects' errors (``rearrange_fates``), None where none has one."""
    off = [c for c in changes if c["fate"] == "put_off"]
    return {
        k: float(np.median([c[k] for c in off if k in c])) if any(k in c for c in off) else None
        for k in PUT_ERRORS
    }


def fates_markdown(rows: dict[str, Any]) -> list[str]:
    """The table of where each row's changes went (``rearrange_fates``), empty when no row has it."""
    rows = {n: m for n, m in rows.items() if m.get("fates")}
    if not rows:
        return []
    cols = [("pickupable", f) for f in PICKUPABLE_FATES] + [("openable", f) for f in OPENABLE_FATES]
    head = [f"{'object' if k == 'pickupable' else 'openable'}: {f.replace('_', ' ')}" for k, f in cols]
    lines = [
        "",
        "## Where the score goes",
        "",
        "Each changed object's fate, the first that applies (`agent/evaluation/rearrange_fates.py`), "
        "and the objects in place at the start that ended misplaced (newly misplaced: picked by the "
        "agent / an openable it believed toggled / disturbed). Put off: put down, not in place; the "
        "medians of its x-y distance from the goal (cm), folded yaw (degrees) and IoU, and of the x-y "
        "error's parts: the point the put aimed at from the goal, where it came to rest from that.",
        "",
        "| row | " + " | ".join(head) + " | newly: picked / believed / disturbed "
        "| put off: cm / yaw / IoU | parts: estimate / landed cm |",
        "|---|" + "---|" * (len(cols) + 3),
    ]

    def cm(x: float | None, fmt: str = ".1f") -> str:
        return "-" if x is None else format(x, fmt)

    for name, m in rows.items():
        f, po = m["fates"], m["put_off"]
        newly = f["newly"]
        lines.append(
            f"| {ROW_TITLES.get(name, name)} | "
            + " | ".join(str(f[k][c]) for k, c in cols)
            + f" | {newly['picked']} / {newly['believed']} / {newly['disturbed']} "
            f"| {cm(po['position_cm'])} / {cm(po['yaw_deg'], '.0f')} / {cm(po['iou'], '.2f')} "
            f"| {cm(po['estimate_cm'])} / {cm(po['landed_cm'])} |"
        )
    return lines


RECEPTACLE_ROWS = 8  # receptacles listed per side, most moved objects first
RECEPTACLE_FATES = ("fixed", "missed_walkthrough", "missed_unshuffle")


def receptacles_markdown(rows: dict[str, Any]) -> list[str]:
    """Where the moved pickupables lay in the goal state and after the shuffle, with each row's
    fixed / missed-walkthrough / missed-unshuffle counts there (empty without ``by_receptacle``)."""
    rows = {n: m for n, m in rows.items() if (m.get("by_receptacle") or {}).get("goal_on")}
    if not rows:
        return []
    head = " | ".join(f"{ROW_TITLES.get(n, n)}: fixed / missed walkthrough / missed unshuffle" for n in rows)
    lines = [
        "",
        "## Where the moved objects lay",
        "",
        "The receptacles that held the moved pickupables in the goal state and after the shuffle "
        f"(the {RECEPTACLE_ROWS} with the most of each), with each row's counts of three fates there.",
        "",
        f"| held by | objects | {head} |",
        "|---|---|" + "---|" * len(rows),
    ]
    first = next(iter(rows.values()))["by_receptacle"]
    for side, title in (("goal_on", "goal"), ("start_on", "shuffled")):
        ranked = sorted(first[side].items(), key=lambda kv: (-kv[1]["n"], kv[0]))[:RECEPTACLE_ROWS]
        for rec, cell in ranked:
            counts = []
            for m in rows.values():
                c = m["by_receptacle"][side].get(rec, {})
                counts.append(" / ".join(str(c.get(f, 0)) for f in RECEPTACLE_FATES))
            lines.append(f"| {title}: {rec} | {cell['n']} | " + " | ".join(counts) + " |")
    return lines


def _plot(report: dict[str, Any]) -> bytes:
    from matplotlib.figure import Figure

    from tidee.agent.evaluation.report import _png

    names = list(report["rows"])
    keys = [
        ("fixed_strict", "FixedStrict"),
        ("success", "Success"),
        ("energy", "Energy"),
        ("misplaced", "Misplaced"),
    ]
    fig = Figure(figsize=(max(6.0, 1.5 * len(names) + 2), 4.5))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(names))
    width = 0.8 / len(keys)
    for k, (key, label) in enumerate(keys):
        vals = [
            np.nan if report["rows"][n][key] is None else 100 * float(report["rows"][n][key]) for n in names
        ]
        ax.bar(x + (k - (len(keys) - 1) / 2) * width, vals, width, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels([ROW_TITLES.get(n, n) for n in names], rotation=20, ha="right", fontsize="small")
    ax.set_ylim(0, 120)
    ax.set_ylabel("%")
    ax.set_title(
        f"2-phase rearrangement, {report['split']} rooms ({report['configurations']} configurations)"
    )
    ax.legend(loc="upper center", ncol=len(keys), fontsize="small", frameon=False)
    fig.tight_layout()
    return _png(fig)


def run_rearrange_eval(cfg: RearrangeEvalConfig) -> dict[str, Any]:
    from tidee.agent.evaluation.report import agent_flags, machine_note
    from tidee.agent.evaluation.tidy_eval import episode_cost, select_configs

    agent = cfg.agent
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    configs = select_configs(cfg.split, cfg.episodes)
    jobs = []
    for c in configs:
        base = EpisodeSpec(
            room_type=c.room_type,
            seed=c.seed,
            rearrange_index=c.mess_index,
            resolution=cfg.resolution,
            max_steps=cfg.max_steps,
            walkthrough_steps=cfg.walkthrough_steps,
        )
        for row in cfg.rows:
            row_agent, spec = row_setup(row, agent, base)
            jobs.append(
                RearrangeJob(
                    row,
                    row_agent,
                    spec,
                    cfg.split,
                    c.index,
                    cfg.renderer,
                    out / "logs" if cfg.keep_logs else None,
                )
            )
    t0 = time.time()
    episodes_file = out / "episodes.jsonl"
    resumed = stored_jobs(jobs, episodes_file) if cfg.batch.resume else 0
    records = run_jobs(
        jobs,
        _run_one,
        workers=cfg.workers,
        renderer=cfg.renderer,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        progress=cfg.progress,
        out_jsonl=episodes_file,
        resume=cfg.batch.resume,
        desc="rearrangement episodes",
        cost=lambda job: episode_cost(job.spec),
    )
    wall = time.time() - t0
    rows = {row: row_summary([r for r in records if r["row"] == row]) for row in cfg.rows}
    command = (
        f"tidee eval rearrange --split {cfg.split} --episodes {len(configs)} --rows {','.join(cfg.rows)} "
        f"--resolution {cfg.resolution} --walkthrough-steps {cfg.walkthrough_steps} "
        f"--max-steps {cfg.max_steps} "
        # the rows set perception and depth; a rearrangement has no out-of-place detector
        + agent_flags(cfg.agent, skip=("perception", "depth", "oop"))
        + f"--workers {cfg.workers} --renderer {cfg.renderer} --out {out}"
    )
    notes = [
        f"command: {command}",
        f"total wall time {wall:.0f} s with {cfg.workers} worker(s) ({cfg.batch.backend} backend), "
        f"{sum(r.get('retries', 0) for r in records)} retried episode(s)"
        + (f"; {resumed} episode(s) resumed from episodes.jsonl (made by an earlier run)" if resumed else ""),
        machine_note(),
        "configurations: `tidee.server.shuffle` (goal: the tidy room with 0-2 openables open; shuffled: "
        "0-3 openables toggled, 1-5 pickupables moved by placement or the mess-up's physics)",
        "the agent: `tidee.agent.policy.rearrange` (walkthrough, then unshuffle: match the two object "
        "memories, restore openness, put moved objects back where the walkthrough saw them)",
        "ground truth is read only to score episodes, and by the oracle row's perception",
    ]
    report = {
        "split": cfg.split,
        "configurations": len(configs),
        "rows": rows,
        "paper": {"table4": PAPER_TABLE4, "table_s1": PAPER_TABLE_S1, "roomr_baseline": ROOMR_BASELINE},
        "notes": notes,
        "episodes": records,
    }
    write_atomic(out / "report.json", json.dumps(report, indent=1, default=str).encode())
    write_atomic(out / "report.md", format_markdown(report).encode())
    write_atomic(out / "report.png", _plot(report))
    return report
