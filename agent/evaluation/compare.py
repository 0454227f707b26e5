"""Two runs of one evaluation, episode by episode: what a change to the agent did.

``tidee eval compare --before A --after B --out DIR`` reads two reports of ``tidee eval
tidy`` or ``tidee eval rearrange`` (a directory with ``report.json`` or ``report.json.gz``, or
the file) and matches their episodes by row and configuration:

- tidy: (agent variant, condition, room type, seed, messy configuration); an episode's score
  is the number of moved objects that end somewhere plausible (object success), its course
  the steps and every object's final receptacle;
- rearrange: (row, room type, seed, rearrangement index); its score is FixedStrict, then
  the energy left (lower is better), its course the steps and every object's end state.

Each row gets the episodes that scored better, worse, the same after another course, and
identically, with the row's metric over the episodes both reports ran. ``compare.json`` and
``compare.md`` are written to ``DIR``. The per-episode lists name each changed episode, so
a reader can rerun it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tidee.agent.evaluation.conditions import row_name
from tidee.agent.evaluation.rearrange_metrics import aggregate
from tidee.agent.evaluation.report import load_report, variant_metrics
from tidee.protocol.episode_log import write_atomic

Key = tuple[Any, ...]


def report_kind(report: dict[str, Any], name: str) -> str:
    """``"tidy"`` or ``"rearrange"`` from the first episode's keys; ValueError otherwise."""
    episodes = report["episodes"]
    if not episodes:
        raise ValueError(f"{name}: the report has no episodes")
    first = episodes[0]
    if isinstance(first, dict) and "rearrange" in first and "row" in first:
        return "rearrange"
    if isinstance(first, dict) and "mess_index" in first and "objects" in first:
        return "tidy"
    raise ValueError(f"{name}: neither a tidy nor a rearrangement report (episode keys: {sorted(first)[:8]})")


def _tidy_key(e: dict[str, Any]) -> Key:
    return (e["variant"], e.get("condition") or "clean", e["room_type"], e["seed"], e["mess_index"])


def _tidy_score(e: dict[str, Any]) -> tuple[float, ...]:
    return (float(sum(bool(o["plausible"]) for o in e["objects"] if o["moved"])),)


def _tidy_course(e: dict[str, Any]) -> Any:
    return e["steps"], sorted((o["id"], o["final_parent_type"]) for o in e["objects"])


def _tidy_row(key: Key) -> str:
    """The report's row name: an agent's already names its condition (``TIDEE +est. depth``), a
    reference row's does not (its records are kept once per condition)."""
    variant, condition = key[0], key[1]
    try:
        named = variant.endswith(row_name("", condition))
    except ValueError:  # a condition this version does not know
        named = False
    return variant if named else f"{variant} ({condition})"


def _tidy_name(key: Key) -> str:
    return f"{key[2]} {key[3]} mess {key[4]}"


def _rearrange_key(e: dict[str, Any]) -> Key:
    return (e["row"], e["room_type"], e["seed"], e["rearrange_index"])


def _rearrange_score(e: dict[str, Any]) -> tuple[float, ...]:
    m = e["rearrange"]
    return (float(m["fixed_strict"] or 0.0), -float(m["energy"] or 0.0))  # None: nothing to fix


def _rearrange_course(e: dict[str, Any]) -> Any:
    objects = e["rearrange"].get("objects") or e.get("objects") or []
    return e["steps"], sorted((o["id"], o["misplaced_end"], round(o["energy_end"], 4)) for o in objects)


def _rearrange_row(key: Key) -> str:
    return str(key[0])


def _rearrange_name(key: Key) -> str:
    return f"{key[1]} {key[2]} rearrangement {key[3]}"


KINDS: dict[str, dict[str, Callable[..., Any]]] = {
    "tidy": {
        "key": _tidy_key,
        "score": _tidy_score,
        "course": _tidy_course,
        "row": _tidy_row,
        "name": _tidy_name,
    },
    "rearrange": {
        "key": _rearrange_key,
        "score": _rearrange_score,
        "course": _rearrange_course,
        "row": _rearrange_row,
        "name": _rearrange_name,
    },
}
SCORE_NAMES = {"tidy": "moved objects ending plausible", "rearrange": "FixedStrict, then energy"}
METRIC_NAMES = {
    "object_success_pct": "object success %",
    "moved_objects": "moved objects",
    "false_picks": "false picks",
    "fixed_strict_pct": "FixedStrict %",
    "success_pct": "Success %",
    "energy_pct": "Energy %",
}
LISTED = 20  # episodes only in one report, named in the Markdown


def _by_key(
    report: dict[str, Any], key: Callable[[dict[str, Any]], Key], name: str
) -> dict[Key, dict[str, Any]]:
    out: dict[Key, dict[str, Any]] = {}
    for e in report["episodes"]:
        try:
            k = key(e)
        except (KeyError, TypeError) as err:
            raise ValueError(f"{name}: an episode lacks {err} (not a report of this kind)") from None
        if k in out:
            raise ValueError(f"{name}: two episodes of {k}: a merged or resumed report with duplicates")
        out[k] = e
    return out


def _row_metric(kind: str, episodes: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """The row's headline over ``episodes``, as the reports compute it: tidy object success (%,
    ``variant_metrics``, the judge) and false picks; for a rearrangement, FixedStrict, Success and
    Energy (%, RoomR's means, ``aggregate``)."""
    if kind == "tidy":
        m = next(iter(variant_metrics(episodes).values()))
        success = m["object_success"]
        return {
            "object_success_pct": None if success is None else round(100.0 * success, 1),
            "moved_objects": float(m["moved"]),
            "false_picks": float(m["false_picks"]),
        }
    a = aggregate([e["rearrange"] for e in episodes])
    return {
        f"{key}_pct": None if a[key] is None else round(100.0 * a[key], 1)
        for key in ("fixed_strict", "success", "energy")
    }


def compare_reports(before: str | os.PathLike[str], after: str | os.PathLike[str]) -> dict[str, Any]:
    """The comparison of two reports of one kind (see the module's docstring); ValueError with
    one line saying what is wrong when they cannot be compared."""
    a, b = load_report(before), load_report(after)
    kind_a, kind_b = report_kind(a, str(before)), report_kind(b, str(after))
    if kind_a != kind_b:
        raise ValueError(
            f"{before} is a {kind_a} report and {after} a {kind_b} report: compare like with like"
        )
    kind = KINDS[kind_a]
    ea, eb = _by_key(a, kind["key"], str(before)), _by_key(b, kind["key"], str(after))
    both = [k for k in ea if k in eb]
    if not both:
        raise ValueError(f"{before} and {after} share no episode (other rows, split or configurations)")
    rows: dict[str, dict[str, Any]] = {}
    for k in both:
        row = rows.setdefault(
            kind["row"](k),
            {
                "episodes": 0,
                "better": [],
                "worse": [],
                "same_score_other_course": [],
                "identical": 0,
                "keys": [],
            },
        )
        row["episodes"] += 1
        row["keys"].append(k)
        sa, sb = kind["score"](ea[k]), kind["score"](eb[k])
        change = {"episode": kind["name"](k), "before": list(sa), "after": list(sb)}
        if sb > sa:
            row["better"].append(change)
        elif sb < sa:
            row["worse"].append(change)
        elif kind["course"](ea[k]) != kind["course"](eb[k]):
            change["steps"] = [ea[k]["steps"], eb[k]["steps"]]
            row["same_score_other_course"].append(change)
        else:
            row["identical"] += 1
    for row in rows.values():
        keys = row.pop("keys")
        row["metric_before"] = _row_metric(kind_a, [ea[k] for k in keys])
        row["metric_after"] = _row_metric(kind_a, [eb[k] for k in keys])
    only = {
        "before": sorted(kind["name"](k) + f" [{kind['row'](k)}]" for k in ea if k not in eb),
        "after": sorted(kind["name"](k) + f" [{kind['row'](k)}]" for k in eb if k not in ea),
    }
    return {
        "kind": kind_a,
        "before": str(before),
        "after": str(after),
        "score": SCORE_NAMES[kind_a],
        "rows": rows,
        "only_in_one": only,
        "notes": {"before": a.get("notes", []), "after": b.get("notes", [])},
    }


def _num(x: float | None) -> str:
    return "–" if x is None else f"{x:g}"


def format_markdown(result: dict[str, Any]) -> str:
    rows = result["rows"]
    metric_names = list(next(iter(rows.values()))["metric_before"])
    lines = [
        f"# {result['kind'].capitalize()} episodes compared: `{result['before']}` → `{result['after']}`",
        "",
        f"An episode is better or worse by its score ({result['score']}); the same score after another "
        "course means other steps or other end states.",
        "",
        "| row | episodes in both | better | worse | same score, other course | identical | "
        + " | ".join(METRIC_NAMES[m] for m in metric_names)
        + " |",
        "|---|---:|---:|---:|---:|---:|" + "---:|" * len(metric_names),
    ]
    for name, row in rows.items():
        metrics = " | ".join(
            f"{_num(row['metric_before'][m])} → {_num(row['metric_after'][m])}" for m in metric_names
        )
        lines.append(
            f"| {name} | {row['episodes']} | {len(row['better'])} | {len(row['worse'])} | "
            f"{len(row['same_score_other_course'])} | {row['identical']} | {metrics} |"
        )
    for name, row in rows.items():
        changed = [("better", c) for c in row["better"]] + [("worse", c) for c in row["worse"]]
        if not changed:
            continue
        lines += ["", f"## {name}: changed scores", "", "| episode | | before | after |", "|---|---|---|---|"]
        for how, c in changed:
            was, now = (", ".join(f"{v:g}" for v in c[side]) for side in ("before", "after"))
            lines.append(f"| {c['episode']} | {how} | {was} | {now} |")
    for side in ("before", "after"):
        only = result["only_in_one"][side]
        if only:
            more = f"; and {len(only) - LISTED} more" if len(only) > LISTED else ""
            lines += ["", f"Only in {side} ({len(only)}): " + "; ".join(only[:LISTED]) + more]
    lines += [""]
    for side in ("before", "after"):
        commands = [n for n in result["notes"][side] if isinstance(n, str) and n.startswith("command: ")]
        lines.append(
            f"- {side}: " + (", ".join(f"`{c[len('command: ') :]}`" for c in commands) or "no command noted")
        )
    return "\n".join(lines) + "\n"


def write_comparison(result: dict[str, Any], out_dir: str | os.PathLike[str]) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "compare.json", (json.dumps(result, indent=1) + "\n").encode())
    write_atomic(out / "compare.md", format_markdown(result).encode())
    return out / "compare.md"


__all__ = ["compare_reports", "format_markdown", "report_kind", "write_comparison"]
