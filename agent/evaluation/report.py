"""Tidy-evaluation metrics, the pairwise preference table and the written report.

Input: **episode records**, plain JSON dicts, one per tidy episode::

    {"variant": "CommonMemory", "perception": "oracle", "split": "test", "room_type": "Kitchen",
     "seed": 200, "mess_index": 3, "steps": 412, "wall_s": 21.3, "end_reason": "no_oop_found",
     "present_receptacles": ["CounterTop", "Fridge", ...],
     "objects": [{"id": "Mug_2", "type": "Mug", "variant": null, "moved": true, "found": true,
                  "picked": true, "original_parent_type": "CounterTop",
                  "messy_parent_type": "Floor", "final_parent_type": "DiningTable"}, ...]}

Required record keys: :data:`RECORD_KEYS`; required object keys: :data:`OBJECT_KEYS`
(``perception``, ``split`` and ``end_reason`` are optional). ``objects`` lists every
pickupable object; ``moved``: moved by the mess-up; ``found``: the agent identified it
as out of place; ``picked``: the agent picked it up at some point. A
``final_parent_type`` of None (e.g. still held) scores 0 and is never plausible.

A **configuration** is ``(split, room_type, seed, mess_index)`` (``split`` None when a
record has none): the same scene and the same mess, so records of different variants
for one configuration can be compared object by object (objects match by ``id``).

The judge is simulated (see :mod:`tidee.agent.evaluation.judge`): placements are scored
by the catalog's placement priors, not by human raters as in the paper. Reference rows
(AI2THORPlacement, MessyPlacement) are included wherever their records are present; add
them with :func:`with_references`.
"""

from __future__ import annotations

import json
import math
import os
import shlex
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest

from tidee.protocol.episode_log import write_atomic

from .judge import DEFAULT_PLAUSIBILITY, REFERENCE_VARIANTS, judge_score, plausible, prefer, reference_records

__all__ = [
    "RECORD_KEYS",
    "OBJECT_KEYS",
    "config_key",
    "validate_records",
    "with_references",
    "variant_metrics",
    "pairwise_table",
    "write_report",
    "format_markdown",
    "load_report",
    "merge_reports",
]

RECORD_KEYS: tuple[str, ...] = (
    "variant",
    "room_type",
    "seed",
    "mess_index",
    "steps",
    "wall_s",
    "present_receptacles",
    "objects",
)
OBJECT_KEYS: tuple[str, ...] = (
    "id",
    "type",
    "variant",
    "moved",
    "found",
    "picked",
    "original_parent_type",
    "messy_parent_type",
    "final_parent_type",
)
_BOOL_KEYS = ("moved", "found", "picked")

Config = tuple[Any, str, Any, Any]


# -------------------------------------------------------------------- validation


def agent_flags(agent: Any, skip: Sequence[str] = ()) -> str:
    """The flags of an ``AgentConfig`` that differ from their defaults, each followed by a space
    (``skip``: field names the report's command already spells out): a report's command must
    rebuild the run it reports, ``--carve off`` or ``--localise scan`` included."""
    from tidee.options import to_argv

    return "".join(f"{shlex.quote(a)} " for a in to_argv(agent, skip=skip))


def machine_note() -> str:
    """What ran a report's episodes here, for its notes: the processor, its cores, torch and the
    precision the learned networks run in ("auto": bf16 where the CPU has it natively). Records
    made on another kind of processor, or another torch, can differ in a detection's last digits
    and so in an episode's path."""
    import platform

    import torch

    from tidee.agent.learning import resolve_precision
    from tidee.threads import available_cores

    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), model)
    except OSError:
        pass
    return (
        f"machine: {model} ({platform.machine()}), {os.cpu_count()} cores ({available_cores()} available), "
        f"torch {torch.__version__}, networks in {resolve_precision('auto', 'cpu')}"
    )


def _describe(i: int, rec: Mapping[str, Any]) -> str:
    return (
        f"record {i} (variant {rec.get('variant')!r}, room {rec.get('room_type')!r}, "
        f"seed {rec.get('seed')!r}, mess {rec.get('mess_index')!r})"
    )


def validate_records(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """Check every record has the required keys and sane values; return them as a list.

    Raises ValueError naming the record (its index and configuration), the object (its
    index and id) and the missing or bad key.
    """
    out = list(records)
    for i, rec in enumerate(out):
        if not isinstance(rec, Mapping):
            raise ValueError(f"record {i}: expected a dict, got {type(rec).__name__}")
        for key in RECORD_KEYS:
            if key not in rec:
                raise ValueError(f"{_describe(i, rec)} is missing key {key!r}")
        if not isinstance(rec["variant"], str) or not rec["variant"]:
            raise ValueError(f"{_describe(i, rec)}: 'variant' must be a non-empty string")
        for key in ("steps", "wall_s"):
            x = rec[key]
            if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
                raise ValueError(f"{_describe(i, rec)}: {key!r} must be a number, got {x!r}")
        if not isinstance(rec["present_receptacles"], (list, tuple)):
            raise ValueError(
                f"{_describe(i, rec)}: 'present_receptacles' must be a list, "
                f"got {type(rec['present_receptacles']).__name__}"
            )
        if not isinstance(rec["objects"], (list, tuple)):
            raise ValueError(
                f"{_describe(i, rec)}: 'objects' must be a list, got {type(rec['objects']).__name__}"
            )
        seen: set[Any] = set()
        for j, obj in enumerate(rec["objects"]):
            if not isinstance(obj, Mapping):
                raise ValueError(f"{_describe(i, rec)}: object {j} is not a dict")
            for key in OBJECT_KEYS:
                if key not in obj:
                    raise ValueError(
                        f"{_describe(i, rec)}: object {j} ({obj.get('id', '?')!r}) is missing key {key!r}"
                    )
            for key in _BOOL_KEYS:
                if not isinstance(obj[key], (bool, np.bool_)):
                    raise ValueError(
                        f"{_describe(i, rec)}: object {j} ({obj['id']!r}): {key!r} must "
                        f"be a bool, got {obj[key]!r}"
                    )
            if obj["id"] in seen:
                raise ValueError(f"{_describe(i, rec)}: object id {obj['id']!r} appears twice")
            seen.add(obj["id"])
    return out


def config_key(record: Mapping[str, Any]) -> Config:
    """The configuration a record ran: ``(split, room_type, seed, mess_index)``."""
    return (record.get("split"), record["room_type"], record["seed"], record["mess_index"])


def _variant_order(records: Sequence[Mapping[str, Any]]) -> list[str]:
    """Variants by first appearance, the reference rows last (AI2THOR, then Messy)."""
    order: list[str] = []
    for rec in records:
        if rec["variant"] not in order and rec["variant"] not in REFERENCE_VARIANTS:
            order.append(rec["variant"])
    present = {rec["variant"] for rec in records}
    return order + [v for v in REFERENCE_VARIANTS if v in present]


def with_references(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """``records`` plus one AI2THORPlacement and one MessyPlacement record per configuration.

    The references are built (:func:`reference_records`) from the first non-reference
    record of each configuration that does not already have them; existing reference
    records are kept as they are. The input records come first, in their order.
    """
    out = validate_records(records)
    have: dict[str, set[Config]] = {v: set() for v in REFERENCE_VARIANTS}
    for rec in out:
        if rec["variant"] in have:
            have[rec["variant"]].add(config_key(rec))
    added: list[Mapping[str, Any]] = []
    for rec in out:
        if rec["variant"] in REFERENCE_VARIANTS:
            continue
        key = config_key(rec)
        refs = reference_records(rec)
        for name in REFERENCE_VARIANTS:
            if key not in have[name]:
                have[name].add(key)
                added.append(refs[name])
    return out + added


# ----------------------------------------------------------------------- scoring


def _score(i: int, rec: Mapping[str, Any], obj: Mapping[str, Any], parent: Any) -> tuple[float, bool]:
    """(judge score, plausible) of ``obj`` resting on ``parent`` in ``rec``'s room."""
    try:
        s = judge_score(obj["type"], obj["variant"], rec["room_type"], parent, rec["present_receptacles"])
        ok = plausible(obj["type"], obj["variant"], rec["room_type"], parent, rec["present_receptacles"])
    except KeyError as e:
        raise ValueError(f"{_describe(i, rec)}: object {obj['id']!r} cannot be judged: {e}") from e
    return s, ok


def _mean(xs: Sequence[float]) -> float | None:
    return float(sum(xs) / len(xs)) if xs else None


def _ratio(a: int, b: int) -> float | None:
    return a / b if b else None


def variant_metrics(records: Iterable[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per-variant tidying metrics, keyed by variant (first appearance, references last).

    For each variant:

    * ``episodes``: number of records;
    * ``moved``: objects moved by the mess-up; ``found``: moved objects the agent found;
      ``picked``: objects the agent picked (moved or not); ``false_picks``: picked objects
      that were not moved; ``plausible``: moved objects whose final parent is plausible;
    * ``object_success`` = plausible / moved;
    * ``episode_success``: fraction of episodes in which every moved object ends on a
      plausible receptacle (an episode without moved objects counts as a success);
    * ``found_rate`` = found / moved;
    * ``false_pick_rate`` = false_picks / picked: how often the agent disturbed an object
      the mess-up had not moved; 0.0 when it picked nothing;
    * ``mean_judge_score``: mean :func:`judge_score` of the final placements of moved
      objects;
    * ``steps_mean``, ``wall_s_mean``: means over episodes;
    * ``end_reasons``: ``{end_reason: count}`` (records without one count as "unknown").

    Rates over zero moved objects are None. Raises ValueError on records missing
    required keys (naming the key and the record) and on objects the judge cannot score.
    """
    recs = validate_records(records)
    acc: dict[str, dict[str, Any]] = {}
    for v in _variant_order(recs):
        acc[v] = {
            "episodes": 0,
            "moved": 0,
            "found": 0,
            "picked": 0,
            "false_picks": 0,
            "plausible": 0,
            "ok_episodes": 0,
            "scores": [],
            "steps": [],
            "wall_s": [],
            "end_reasons": {},
        }
    for i, rec in enumerate(recs):
        a = acc[rec["variant"]]
        a["episodes"] += 1
        a["steps"].append(float(rec["steps"]))
        a["wall_s"].append(float(rec["wall_s"]))
        reason = str(rec.get("end_reason") or "unknown")
        a["end_reasons"][reason] = a["end_reasons"].get(reason, 0) + 1
        all_ok = True
        for obj in rec["objects"]:
            if obj["picked"]:
                a["picked"] += 1
                if not obj["moved"]:
                    a["false_picks"] += 1
            if not obj["moved"]:
                continue
            a["moved"] += 1
            a["found"] += int(bool(obj["found"]))
            s, ok = _score(i, rec, obj, obj["final_parent_type"])
            a["scores"].append(s)
            a["plausible"] += int(ok)
            all_ok = all_ok and ok
        a["ok_episodes"] += int(all_ok)
    out: dict[str, dict[str, Any]] = {}
    for v, a in acc.items():
        out[v] = {
            "episodes": a["episodes"],
            "object_success": _ratio(a["plausible"], a["moved"]),
            "episode_success": _ratio(a["ok_episodes"], a["episodes"]),
            "found_rate": _ratio(a["found"], a["moved"]),
            "false_pick_rate": a["false_picks"] / a["picked"] if a["picked"] else 0.0,
            "mean_judge_score": _mean(a["scores"]),
            "steps_mean": _mean(a["steps"]),
            "wall_s_mean": _mean(a["wall_s"]),
            "moved": a["moved"],
            "found": a["found"],
            "picked": a["picked"],
            "false_picks": a["false_picks"],
            "plausible": a["plausible"],
            "end_reasons": dict(sorted(a["end_reasons"].items())),
        }
    return out


def _index(recs: Sequence[Mapping[str, Any]]) -> dict[str, dict[Config, tuple[int, Mapping[str, Any]]]]:
    by: dict[str, dict[Config, tuple[int, Mapping[str, Any]]]] = {}
    for i, rec in enumerate(recs):
        key = config_key(rec)
        slot = by.setdefault(rec["variant"], {})
        if key in slot:
            raise ValueError(
                f"{_describe(i, rec)} repeats the configuration of record {slot[key][0]} "
                f"(split, room, seed, mess = {key}); pairwise comparison needs one record "
                f"per variant and configuration (build references once per configuration, "
                f"e.g. with with_references)"
            )
        slot[key] = (i, rec)
    return by


def _compare(
    a_runs: Mapping[Config, tuple[int, Mapping[str, Any]]],
    b_runs: Mapping[Config, tuple[int, Mapping[str, Any]]],
    judge: Callable[..., float] | None = None,
) -> dict[str, Any]:
    wins = ties = losses = configs = 0
    sum_a = sum_b = 0.0
    groups: dict[tuple[str, str | None, str | None, str], int] = {}
    for key, (ia, ra) in a_runs.items():
        if key not in b_runs:
            continue
        ib, rb = b_runs[key]
        configs += 1
        b_objs = {o["id"]: o for o in rb["objects"]}
        for oa in ra["objects"]:
            ob = b_objs.get(oa["id"])
            if ob is None:
                continue
            if bool(oa["moved"]) != bool(ob["moved"]) or oa["type"] != ob["type"]:
                raise ValueError(
                    f"object {oa['id']!r} differs between {_describe(ia, ra)} and "
                    f"{_describe(ib, rb)} (moved {oa['moved']} vs {ob['moved']}, type "
                    f"{oa['type']!r} vs {ob['type']!r}) although they ran the same "
                    f"configuration"
                )
            if not (oa["moved"] and oa["picked"] and ob["picked"]):
                continue
            if judge is None:
                sa, _ = _score(ia, ra, oa, oa["final_parent_type"])
                sb, _ = _score(ib, rb, ob, ob["final_parent_type"])
            else:
                sa = judge(
                    oa["type"],
                    oa["variant"],
                    ra["room_type"],
                    oa["final_parent_type"],
                    ra["present_receptacles"],
                )
                sb = judge(
                    ob["type"],
                    ob["variant"],
                    rb["room_type"],
                    ob["final_parent_type"],
                    rb["present_receptacles"],
                )
            sum_a += sa
            sum_b += sb
            p = prefer(sa, sb)
            if p == 1.0:
                wins += 1
            elif p == 0.0:
                losses += 1
            else:
                ties += 1
            if p != 0.5:
                k = (oa["type"], oa["final_parent_type"], ob["final_parent_type"], "A" if p == 1.0 else "B")
                groups[k] = groups.get(k, 0) + 1
    n = wins + ties + losses
    decided = wins + losses
    return {
        "n": n,
        "wins": wins,
        "ties": ties,
        "losses": losses,
        "pref_a": (wins + ties / 2) / n if n else None,
        "mean_a": sum_a / n if n else None,
        "mean_b": sum_b / n if n else None,
        "p_value": float(binomtest(wins, decided, 0.5, alternative="two-sided").pvalue) if decided else 1.0,
        "configurations": configs,
        # the decided objects grouped by (type, A's receptacle, B's receptacle): what the preference rests on
        "decided": [
            {"type": t, "a": a, "b": b, "winner": w, "n": c}
            for (t, a, b, w), c in sorted(groups.items(), key=lambda kv: (-kv[1], kv[0][3], str(kv[0])))
        ],
    }


def pairwise_table(
    records: Iterable[Mapping[str, Any]],
    variants: Sequence[str] | None = None,
    judge: Callable[..., float] | None = None,
) -> dict[str, dict[str, dict[str, Any]]]:
    """The simulated judge's pairwise preferences, as in the paper's Table 1.

    Returns ``{A: {B: cell}}`` for every ordered pair of distinct variants A, B: the
    given ``variants`` (None: all non-reference variants in the records, by first
    appearance) followed by AI2THORPlacement and MessyPlacement whenever records of
    theirs are present. A cell compares, over the configurations both ran, the moved
    objects *picked by both* (as in the paper; reference rows pick every moved object),
    and the judge prefers A's final placement over B's when A's :func:`judge_score` is
    higher (:func:`prefer`; equal scores tie, counting half):

    * ``n`` objects compared, ``wins``, ``ties``, ``losses`` (from A's side);
    * ``pref_a`` = (wins + ties / 2) / n (None when n = 0);
    * ``mean_a``, ``mean_b``: each side's mean judge score over the n objects (None when n = 0);
    * ``p_value``: two-sided exact binomial test (``scipy.stats.binomtest``, p = 0.5) of
      ``wins`` out of ``wins + losses``; ties are excluded, since they favour neither
      side (1.0 when nothing was decided);
    * ``configurations``: how many configurations both variants ran;
    * ``decided``: the won and lost objects grouped by (object type, A's final receptacle,
      B's final receptacle, winner "A" or "B"), most frequent first, each with its count ``n``.

    ``judge``: another scorer ``(category, variant, room type, receptacle type, present) ->
    score`` to use instead of :func:`judge_score` (``tidee eval ceiling``'s observed judge).

    Raises ValueError for a named variant without records, for two records of one
    variant in one configuration, and for records missing required keys.
    """
    recs = validate_records(records)
    by = _index(recs)
    if variants is None:
        names = [v for v in _variant_order(recs) if v not in REFERENCE_VARIANTS]
    else:
        names = list(dict.fromkeys(variants))
        missing = [v for v in names if v not in by]
        if missing:
            raise ValueError(
                f"pairwise_table: no records for variant(s) {missing}; the records have {sorted(by)}"
            )
    names += [v for v in REFERENCE_VARIANTS if v in by and v not in names]
    return {a: {b: _compare(by[a], by[b], judge) for b in names if b != a} for a in names}


# ------------------------------------------------------------------------ report


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f}%"


def _num(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _p(p: float) -> str:
    return f"{p:.2g}" if p < 0.01 else f"{p:.2f}"


def _cell(c: Mapping[str, Any]) -> str:
    if not c["n"]:
        return "– (n=0)"
    return f"{100 * c['pref_a']:.1f}% (n={c['n']}, p={_p(c['p_value'])})"


def _auto_notes(recs: Sequence[Mapping[str, Any]], order: Sequence[str]) -> list[str]:
    notes = [
        "The judge is simulated, not human: each final placement is scored from the catalog's placement "
        "priors for its room (prior weight of the receptacle the object ended on / weight of the "
        "object's most likely receptacle among those present in the room; 1 = most likely place, "
        f"0 = no prior weight). A placement is plausible when its score is >= {DEFAULT_PLAUSIBILITY:g}. "
        "The paper's Table 1 used human raters instead.",
        "Pairwise cells: share of objects (moved by the mess-up and picked by both agents, in the "
        "configurations both ran) whose final placement the judge prefers for the row agent (A) over the "
        "column agent (B); ties count half. p: two-sided exact binomial test of A's wins against its "
        "losses (ties excluded) under p = 0.5.",
    ]
    per: dict[str, set[str]] = {}
    for rec in recs:
        if rec["variant"] in REFERENCE_VARIANTS:
            continue
        per.setdefault(rec["variant"], set()).add(str(rec.get("perception") or "not recorded"))
    kinds = set().union(*per.values()) if per else set()
    if kinds == {"oracle"}:
        notes.append("Perception was oracle (ground truth from the simulator) for every agent variant.")
    elif not kinds:
        notes.append("Perception: no agent records, only reference rows.")
    else:
        parts = "; ".join(f"{v}: {', '.join(sorted(per[v]))}" for v in order if v in per)
        notes.append(f"Perception was not oracle for every variant. Perception per variant: {parts}.")
    if any(rec["variant"] in REFERENCE_VARIANTS for rec in recs):
        notes.append(
            "AI2THORPlacement puts every moved object back at its original receptacle; "
            "MessyPlacement leaves it where the mess-up put it. "
            "Both pick exactly the moved objects."
        )
    return notes


def format_markdown(report: Mapping[str, Any]) -> str:
    """The Markdown text of a report dict as built by :func:`write_report`."""
    metrics: Mapping[str, Mapping[str, Any]] = report["metrics"]
    table: Mapping[str, Mapping[str, Mapping[str, Any]]] = report["pairwise"]
    lines = [
        f"# {report['title']}",
        "",
        f"{report['config']['n_episodes']} episodes, {report['config']['n_configurations']} "
        f"configurations, room types: {', '.join(report['config']['room_types']) or '–'}.",
        "",
        "## Metrics per variant",
        "",
        "| Variant | Episodes | Object success | Episode success | Found rate | False-pick rate "
        "| Mean judge score | Steps (mean) | Wall s (mean) | Moved | Found | Picked |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for v, m in metrics.items():
        lines.append(
            f"| {v} | {m['episodes']} | {_pct(m['object_success'])} | {_pct(m['episode_success'])} "
            f"| {_pct(m['found_rate'])} | {_pct(m['false_pick_rate'])} "
            f"| {_num(m['mean_judge_score'], 3)} | {_num(m['steps_mean'], 1)} "
            f"| {_num(m['wall_s_mean'], 1)} | {m['moved']} | {m['found']} | {m['picked']} |"
        )
    names = list(table)
    lines += [
        "",
        "## Pairwise preference (simulated judge)",
        "",
        "Row A vs column B: % of objects whose final placement the judge prefers for A "
        "(n objects picked by both, p from a two-sided binomial test).",
        "",
    ]
    if names:
        lines.append("| A \\ B | " + " | ".join(names) + " |")
        lines.append("|---|" + "---:|" * len(names))
        for a in names:
            cells = ["—" if b == a else _cell(table[a][b]) for b in names]
            lines.append(f"| {a} | " + " | ".join(cells) + " |")
    else:
        lines.append("(no variants)")
    lines += _decided_section(table, [n for n in names if n not in REFERENCE_VARIANTS])
    if report.get("human"):
        lines += _human_section(report["human"])
    lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    return "\n".join(lines)


def _human_section(human: Mapping[str, Any]) -> list[str]:
    """The human judge's columns (``human_judge.py``) and its pairwise preferences."""
    m = human["metrics"]
    lines = [
        "",
        "## Human judge (Housekeep annotations)",
        "",
        "10 annotators per object and room type said where it belongs (Kant et al., ECCV 2022); "
        "tidee's names map onto theirs with a tier (`agent/data/housekeep/mapping.json`). Correct: "
        ">= 5 of 10 said correct; plausible: >= 5 of 10 said correct or misplaced; relative: correct "
        "votes for the chosen receptacle / the best present receptacle's. Shares are of the judged "
        "placements; coverage is judged / all.",
        "",
        "| Placements of moved objects | Judged (coverage) | exact / close / approximate | Correct "
        "| Plausible | Relative votes |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    rows = [*m["variants"].items(), ("tidy rooms (every object where the room had it)", m["tidy_rooms"])]
    for name, r in rows:
        t = r["by_tier"]
        lines.append(
            f"| {name} | {r['judged']} / {r['placements']} ({_pct(r['coverage'])}) "
            f"| {t['exact']} / {t['close']} / {t['approximate']} | {_pct(r['correct'])} "
            f"| {_pct(r['plausible'])} | {_num(r['relative_mean'], 3)} |"
        )
    for key, what in (("pairwise", "one vote"), ("pairwise_margin2", "two votes")):
        table = human.get(key) or {}
        names = list(table)
        if len(names) < 2:
            continue
        lines += [
            "",
            f"Pairwise by human votes (a win needs {what} more for the row agent's receptacle; objects "
            "picked by both whose placements can both be judged):",
            "",
            "| A \\ B | " + " | ".join(names) + " |",
            "|---|" + "---:|" * len(names),
        ]
        for a in names:
            cells = ["—" if b == a else _cell(table[a][b]) for b in names]
            lines.append(f"| {a} | " + " | ".join(cells) + " |")
    return lines


def _decided_section(
    table: Mapping[str, Mapping[str, Mapping[str, Any]]], agents: Sequence[str], top: int = 8
) -> list[str]:
    """For the first agent against each other agent: the placements that won and lost it the
    judge's preference, the most frequent first (ties, most objects, are left out)."""
    if len(agents) < 2:
        return []
    a = agents[0]
    lines = [
        "",
        f"## What decided the judge: {a} against the other agents",
        "",
        "Objects the judge did not score equal, grouped by (object, where A put it, where B put it); "
        f"at most {top} groups each way.",
        "",
    ]
    for b in agents[1:]:
        cell = table[a][b]
        groups = cell.get("decided")
        if groups is None:
            continue
        lines.append(f"- **{a} vs {b}**: {cell['wins']} won, {cell['losses']} lost, {cell['ties']} tied.")
        for winner, word in (("A", "won"), ("B", "lost")):
            g = [d for d in groups if d["winner"] == winner][:top]
            if g:
                lines.append(
                    f"  - {word}: " + "; ".join(f"{d['type']} {d['a']} vs {d['b']} ×{d['n']}" for d in g)
                )
    return lines


def _png(fig: Any) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    return buf.getvalue()


def _plot_metrics(metrics: Mapping[str, Mapping[str, Any]], title: str) -> bytes:
    from matplotlib.figure import Figure

    keys = [
        ("object_success", "object success"),
        ("episode_success", "episode success"),
        ("found_rate", "found rate"),
        ("mean_judge_score", "mean judge score"),
    ]
    names = list(metrics)
    fig = Figure(figsize=(max(6.0, 1.6 * len(names) + 2), 4.5))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(names))
    width = 0.8 / len(keys)
    for k, (key, label) in enumerate(keys):
        vals = [np.nan if metrics[v][key] is None else float(metrics[v][key]) for v in names]
        ax.bar(x + (k - (len(keys) - 1) / 2) * width, vals, width, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=20, ha="right")
    ax.set_ylim(0, 1.2)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.set_ylabel("fraction / score")
    ax.set_title(f"{title}: metrics per variant")
    ax.legend(loc="upper center", ncol=len(keys), fontsize="small", frameon=False)
    fig.tight_layout()
    return _png(fig)


def _plot_pairwise(table: Mapping[str, Mapping[str, Mapping[str, Any]]], title: str) -> bytes:
    from matplotlib.figure import Figure

    names = list(table)
    k = len(names)
    grid = np.full((k, k), np.nan)
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if a != b and table[a][b]["pref_a"] is not None:
                grid[i, j] = 100 * table[a][b]["pref_a"]
    size = max(4.5, 1.3 * k + 2.5)
    fig = Figure(figsize=(size, size * 0.85))
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(grid, vmin=0, vmax=100, cmap="RdBu")
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if a == b:
                continue
            c = table[a][b]
            text = "n=0" if not c["n"] else f"{grid[i, j]:.1f}%\nn={c['n']}"
            dark = c["n"] and abs(grid[i, j] - 50) > 30
            ax.text(j, i, text, ha="center", va="center", fontsize=8, color="white" if dark else "black")
    ax.set_xticks(range(k))
    ax.set_xticklabels(names, rotation=30, ha="right")
    ax.set_yticks(range(k))
    ax.set_yticklabels(names)
    ax.set_xlabel("B")
    ax.set_ylabel("A")
    ax.set_title(f"{title}: judge prefers A over B (%)")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    return _png(fig)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (set, frozenset)):
        return sorted(x)
    raise TypeError(f"report.json: cannot serialise {type(x).__name__} value {x!r}")


def _clean(x: Any) -> Any:
    """Plain JSON values: NaN/inf floats become None (JSON has no NaN), tuples lists."""
    if isinstance(x, Mapping):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    return x


def write_report(
    records: Iterable[Mapping[str, Any]],
    out_dir: str | os.PathLike[str],
    title: str,
    notes: Sequence[str] = (),
) -> dict[str, Any]:
    """Write the tidy-evaluation report to ``out_dir`` and return it as a dict.

    Files (each written atomically: temporary file + ``os.replace``):

    * ``report.json``: ``title``, ``config`` (episode and configuration counts, variants,
      room types, splits, perception per variant, the judge's description), ``notes``,
      ``metrics`` (:func:`variant_metrics`), ``pairwise`` (:func:`pairwise_table`), and
      ``episodes``: every record with its objects, each object annotated with its final
      placement's ``judge_score`` and ``plausible``;
    * ``report.md``: the metrics table, the pairwise preference matrix (rows A, columns
      B, cells "62.5% (n=16, p=0.23)") and the notes;
    * ``metrics.png``: grouped bars of object success, episode success, found rate and
      mean judge score per variant; ``pairwise.png``: heatmap of ``pref_a``.

    The notes are the automatic ones (the judge is simulated from the placement priors;
    whether perception was oracle; the pairwise definitions) followed by ``notes``.
    Reference rows appear only if their records are in ``records`` (see
    :func:`with_references`). Raises ValueError on malformed records.
    """
    recs = validate_records(records)
    if not recs:
        raise ValueError("write_report: no episode records")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = variant_metrics(recs)
    table = pairwise_table(recs)
    order = list(metrics)
    perception: dict[str, list[str]] = {}
    for rec in recs:
        p = str(rec.get("perception") or "not recorded")
        if p not in perception.setdefault(rec["variant"], []):
            perception[rec["variant"]].append(p)
    episodes = []
    for i, rec in enumerate(recs):
        ep = _clean(dict(rec))
        for obj in ep["objects"]:
            s, ok = _score(i, rec, obj, obj["final_parent_type"])
            obj["judge_score"] = s
            obj["plausible"] = ok
        episodes.append(ep)
    from .human_judge import human_metrics, human_pairwise

    agents = list(table)
    human = {
        "source": "Housekeep human annotations (MIT), agent/data/housekeep",
        "metrics": human_metrics(recs),
        "pairwise": human_pairwise(recs, agents),
        "pairwise_margin2": human_pairwise(recs, agents, margin=2),
    }
    report: dict[str, Any] = {
        "title": title,
        "config": {
            "n_episodes": len(recs),
            "n_configurations": len({config_key(r) for r in recs}),
            "variants": order,
            "reference_variants": [v for v in REFERENCE_VARIANTS if v in metrics],
            "room_types": sorted({str(r["room_type"]) for r in recs}),
            "splits": sorted({str(r.get("split")) for r in recs}),
            "perception": {v: perception[v] for v in order},
            "judge": {
                "kind": "simulated",
                "source": "catalog placement priors (receptacle_weights)",
                "score": "prior weight of the final receptacle / largest weight in the room",
                "plausibility_threshold": DEFAULT_PLAUSIBILITY,
                "pairwise_objects": "moved by the mess-up and picked by both variants",
                "p_value": "two-sided exact binomial test, wins vs losses, ties excluded",
            },
        },
        "notes": _auto_notes(recs, order) + [str(n) for n in notes],
        "metrics": metrics,
        "pairwise": table,
        "human": human,
        "episodes": episodes,
        "files": ["report.json", "report.md", "metrics.png", "pairwise.png"],
    }
    report = _clean(report)
    text = json.dumps(report, indent=1, allow_nan=False, default=_json_default)
    write_atomic(out / "report.md", format_markdown(report).encode())
    write_atomic(out / "metrics.png", _plot_metrics(metrics, title))
    write_atomic(out / "pairwise.png", _plot_pairwise(table, title))
    write_atomic(out / "report.json", (text + "\n").encode())
    return report


# ------------------------------------------------------------------------ merging


def load_report(source: str | os.PathLike[str]) -> dict[str, Any]:
    """A report written by :func:`write_report`: ``source`` is its directory (``report.json``
    or, as committed under docs/, ``report.json.gz``) or the file itself. Raises ValueError
    when there is none, it is not JSON, or it has no ``episodes`` list."""
    import gzip

    path = Path(source)
    if path.is_dir():
        found = [path / n for n in ("report.json", "report.json.gz") if (path / n).is_file()]
        if not found:
            raise ValueError(f"{path}: no report.json or report.json.gz (the output of tidee eval tidy)")
        path = found[0]
    elif not path.is_file():
        raise ValueError(f"{path}: no such report directory or file")
    try:
        raw = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
        report = json.loads(raw)
    except (OSError, EOFError, ValueError) as e:
        raise ValueError(f"{path}: not a readable tidy report ({e})") from None
    if not isinstance(report, dict) or not isinstance(report.get("episodes"), list):
        raise ValueError(f"{path}: not a tidy report (no 'episodes' list)")
    return report


def merge_reports(
    sources: Sequence[str | os.PathLike[str] | tuple[str | os.PathLike[str], Sequence[str]]],
    out_dir: str | os.PathLike[str],
    variants: Sequence[str] | None = None,
    command: str = "",
) -> dict[str, Any]:
    """One report from the episodes of several ``tidee eval tidy`` runs, e.g. a new agent's run
    against the records of an earlier run of CommonMemory, without running the latter again.

    A source is a report directory or file, or a pair (source, the variants to take from it).
    Takes every agent variant's records from each source (only ``variants`` when given), drops
    the reference rows (rebuilt from the merged records) and the judge's annotations (scored
    again), and writes the report to ``out_dir`` with :func:`write_report`. Pairwise cells compare
    the configurations both variants ran. A variant may come from one source only: the error
    names both sources. Each source's notes that say how it was run are kept, prefixed with
    its path, so the merged report says which command produced which rows.
    """
    if not sources:
        raise ValueError("merge: give at least one report directory")
    wanted = None if variants is None else list(dict.fromkeys(variants))
    records: list[dict[str, Any]] = []
    origin: dict[str, str] = {}
    notes: list[str] = []
    for item in sources:
        src, own = item if isinstance(item, tuple) else (item, None)
        report = load_report(src)
        taken: set[str] = set()
        if own is not None:
            absent = [
                v
                for v in own
                if v not in {r.get("variant") for r in report["episodes"] if isinstance(r, dict)}
            ]
            if absent:
                raise ValueError(f"merge: no records of {absent} in {src}")
        for i, rec in enumerate(report["episodes"]):
            if not isinstance(rec, dict):
                raise ValueError(f"merge: {src}: episode {i} is not a record (got {type(rec).__name__})")
            v = rec.get("variant")
            if (
                v in REFERENCE_VARIANTS
                or (wanted is not None and v not in wanted)
                or (own is not None and v not in own)
            ):
                continue
            if v in origin and origin[v] != str(src):
                raise ValueError(
                    f"merge: variant {v!r} is in both {origin[v]} and {src}; "
                    f"say which to take from each (--from DIR=VARIANT+VARIANT,...)"
                )
            origin.setdefault(str(v), str(src))
            taken.add(str(v))
            rec = dict(rec)
            if isinstance(rec.get("objects"), list):  # validate_records reports anything else
                rec["objects"] = [
                    {k: x for k, x in o.items() if k not in ("judge_score", "plausible")}
                    if isinstance(o, dict)
                    else o
                    for o in rec["objects"]
                ]
            records.append(rec)
        kept = [
            n
            for n in report.get("notes", [])
            if isinstance(n, str) and n.startswith(("command:", "split=", "perception:"))
        ]
        notes += [f"{src} ({', '.join(sorted(taken)) or 'nothing taken'}): {n}" for n in kept]
    missing = [v for v in (wanted or []) if v not in origin and v not in REFERENCE_VARIANTS]
    if missing:
        raise ValueError(f"merge: no records of {missing} in {[str(s) for s in sources]}")
    if not records:
        raise ValueError(f"merge: no agent records in {[str(s) for s in sources]}")
    if command:
        notes.append(f"command: {command}")
    splits = sorted({str(r.get("split")) for r in records})
    return write_report(
        with_references(records),
        out_dir,
        title=f"Tidy evaluation ({', '.join(splits)} rooms, merged)",
        notes=notes,
    )
