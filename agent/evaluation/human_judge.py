"""The human judge: Housekeep's crowd annotations of where household objects belong.

For each object category and room type, 10 annotators sorted every receptacle into *correct*
(where it belongs after tidying), *misplaced* (plausible before tidying) or *implausible*
(Kant et al., ECCV 2022; MIT; ``agent/data/housekeep/README.md``). Nobody on this project
wrote them, which is the point: the catalog judge grades the agent by the priors the rooms
were generated from; these grade it by what people said.

tidee's names reach Housekeep's through ``agent/data/housekeep/mapping.json``, written from the
names alone, each entry with a tier (exact, close, approximate, none). A placement is *judged*
when its object and its receptacle both map (tier other than none); its tier is the looser of
the two. A judged placement is

* **correct** when at least 5 of 10 annotators said correct (Housekeep's own ground truth);
* **plausible** when at least 5 of 10 said correct or misplaced (closer to "in place" in
  TIDEE's sense: Housekeep's annotators read "tidy" as "put away");
* scored by its **relative votes**: correct votes for the chosen receptacle / the most correct
  votes any receptacle present in the room got (None when no present receptacle got any).

An object still held at the end (no receptacle) is judged and wrong. These annotations are test
data: only evaluation reads them (``tests/test_layout.py`` checks that nothing that generates
data or trains does).
"""

from __future__ import annotations

import csv
import functools
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scipy.stats import binomtest

HOUSEKEEP_DIR = Path(__file__).resolve().parents[1] / "data" / "housekeep"
TIERS = ("exact", "close", "approximate")  # judged tiers, tightest first; "none" is not judged
VOTES_NEEDED = 5  # of 10 annotators (Housekeep's threshold for "correct")


@dataclass(frozen=True)
class Votes:
    correct: int
    misplaced: int
    implausible: int


@dataclass(frozen=True)
class Judgement:
    """What the annotators said of one placement."""

    correct: bool
    plausible: bool
    relative: float | None  # correct votes / best correct votes among the present receptacles
    votes: Votes | None  # None: nothing to vote on (the object is still held)
    tier: str  # the looser of the object's and the receptacle's mapping tier


class HumanJudge:
    """Scores placements with the Housekeep table through the reviewed name mapping."""

    def __init__(self, table: Mapping[tuple[str, str, str], Votes], mapping: Mapping[str, Any]) -> None:
        self.table = table
        self.rooms: dict[str, str] = dict(mapping["rooms"])
        self.objects: dict[str, Mapping[str, Any]] = dict(mapping["objects"])
        self.receptacles: dict[str, dict[str, Mapping[str, Any]]] = {
            room: dict(entries) for room, entries in mapping["receptacles"].items()
        }

    @classmethod
    @functools.lru_cache(maxsize=1)
    def load(cls, directory: Path = HOUSEKEEP_DIR) -> HumanJudge:
        table: dict[tuple[str, str, str], Votes] = {}
        with open(directory / "housekeep_orr_4rooms.csv", newline="") as f:
            for row in csv.DictReader(f):
                votes = Votes(int(row["n_correct"]), int(row["n_misplaced"]), int(row["n_implausible"]))
                table[(row["room"], row["receptacle"], row["object"])] = votes
        mapping = json.loads((directory / "mapping.json").read_text())
        return cls(table, mapping)

    # ------------------------------------------------------------------ names
    def object_name(self, category: str, variant: str | None) -> tuple[str, str] | None:
        """(Housekeep object, tier) for a tidee category (a variant's own entry first)."""
        entry = self.objects.get(f"{category}/{variant}") if variant else None
        entry = entry or self.objects.get(category)
        if not entry or not entry.get("housekeep") or entry.get("tier") not in TIERS:
            return None
        return str(entry["housekeep"]), str(entry["tier"])

    def receptacle_name(self, room_type: str, receptacle: str) -> tuple[str, str] | None:
        """(Housekeep receptacle, tier) for a tidee receptacle type in a room type."""
        entry = self.receptacles.get(room_type, {}).get(receptacle)
        if not entry or not entry.get("housekeep") or entry.get("tier") not in TIERS:
            return None
        return str(entry["housekeep"]), str(entry["tier"])

    def votes(self, category: str, variant: str | None, room_type: str, receptacle: str) -> Votes | None:
        obj, rec = self.object_name(category, variant), self.receptacle_name(room_type, receptacle)
        if obj is None or rec is None:
            return None
        return self.table.get((self.rooms[room_type], rec[0], obj[0]))

    # ------------------------------------------------------------------ judging
    def judge(
        self,
        category: str,
        variant: str | None,
        room_type: str,
        receptacle: str | None,
        present: Sequence[str],
    ) -> Judgement | None:
        """The annotators' verdict on ``category`` resting on ``receptacle``; None when the
        placement cannot be judged (the object or the receptacle has no counterpart)."""
        obj = self.object_name(category, variant)
        if obj is None:
            return None
        if receptacle is None:  # still held at the end: nobody calls that tidy
            return Judgement(False, False, 0.0, None, obj[1])
        rec = self.receptacle_name(room_type, receptacle)
        if rec is None:
            return None
        votes = self.table.get((self.rooms[room_type], rec[0], obj[0]))
        if votes is None:
            return None
        best = max(
            (v.correct for r in {*present, receptacle} if (v := self.votes(category, variant, room_type, r))),
            default=0,
        )
        return Judgement(
            correct=votes.correct >= VOTES_NEEDED,
            plausible=votes.correct + votes.misplaced >= VOTES_NEEDED,
            relative=votes.correct / best if best else None,
            votes=votes,
            tier=_looser(obj[1], rec[1]),
        )


def _looser(a: str, b: str) -> str:
    return max(a, b, key=TIERS.index)


# ---------------------------------------------------------------------------- metrics


def _new() -> dict[str, Any]:
    return {"placements": 0, "judged": 0, "correct": 0, "plausible": 0, "relative": [], "tiers": {}}


def _add(acc: dict[str, Any], j: Judgement | None) -> None:
    acc["placements"] += 1
    if j is None:
        return
    acc["judged"] += 1
    acc["correct"] += int(j.correct)
    acc["plausible"] += int(j.plausible)
    if j.relative is not None:
        acc["relative"].append(j.relative)
    acc["tiers"][j.tier] = acc["tiers"].get(j.tier, 0) + 1


def _summary(acc: Mapping[str, Any]) -> dict[str, Any]:
    judged, rel = acc["judged"], acc["relative"]
    return {
        "placements": acc["placements"],
        "judged": judged,
        "coverage": judged / acc["placements"] if acc["placements"] else None,
        "by_tier": {t: acc["tiers"].get(t, 0) for t in TIERS},
        "correct": acc["correct"] / judged if judged else None,
        "plausible": acc["plausible"] / judged if judged else None,
        "relative_mean": sum(rel) / len(rel) if rel else None,
    }


def human_metrics(records: Iterable[Mapping[str, Any]], judge: HumanJudge | None = None) -> dict[str, Any]:
    """The human columns of a tidy report.

    ``variants``: per variant, the final placements of the objects the mess-up moved.
    ``tidy_rooms``: every pickupable object where the tidy room had it (its original receptacle),
    once per configuration: how far the generator's own rooms are from people's idea of tidy.
    Each holds ``placements``, ``judged``, ``coverage``, ``by_tier``, ``correct`` and ``plausible``
    (shares of the judged placements) and ``relative_mean``.
    """
    judge = judge or HumanJudge.load()
    recs = list(records)
    per: dict[str, dict[str, Any]] = {}
    tidy = _new()
    seen: set[tuple[Any, ...]] = set()
    for rec in recs:
        acc = per.setdefault(rec["variant"], _new())
        present = rec["present_receptacles"]
        for obj in rec["objects"]:
            if obj["moved"]:
                _add(
                    acc,
                    judge.judge(
                        obj["type"], obj["variant"], rec["room_type"], obj["final_parent_type"], present
                    ),
                )
        key = (rec.get("split"), rec["room_type"], rec["seed"], rec["mess_index"])
        if key not in seen:
            seen.add(key)
            for obj in rec["objects"]:
                _add(
                    tidy,
                    judge.judge(
                        obj["type"], obj["variant"], rec["room_type"], obj["original_parent_type"], present
                    ),
                )
    return {"variants": {v: _summary(a) for v, a in per.items()}, "tidy_rooms": _summary(tidy)}


def human_pairwise(
    records: Iterable[Mapping[str, Any]],
    variants: Sequence[str],
    margin: int = 1,
    judge: HumanJudge | None = None,
) -> dict[str, dict[str, dict[str, Any]]]:
    """Pairwise preference by human votes: over the configurations both agents ran, the objects
    moved by the mess-up and picked by both whose two final placements can both be judged;
    A wins an object when its receptacle got at least ``margin`` more correct votes than B's
    (``margin`` 2: the two-vote variant), loses when B's got ``margin`` more, ties otherwise.
    ``pref_a`` = (wins + ties / 2) / n; ``p_value``: two-sided exact binomial test of wins
    against losses (ties excluded)."""
    judge = judge or HumanJudge.load()
    by: dict[str, dict[tuple[Any, ...], Mapping[str, Any]]] = {}
    for rec in records:
        by.setdefault(rec["variant"], {})[
            (rec.get("split"), rec["room_type"], rec["seed"], rec["mess_index"])
        ] = rec
    names = [v for v in variants if v in by]
    return {a: {b: _compare(by[a], by[b], margin, judge) for b in names if b != a} for a in names}


def _held_votes(j: Judgement) -> int:
    return j.votes.correct if j.votes is not None else -1  # held beats nothing


def _compare(
    a_runs: Mapping[Any, Any], b_runs: Mapping[Any, Any], margin: int, judge: HumanJudge
) -> dict[str, Any]:
    wins = ties = losses = unjudged = 0
    for key, ra in a_runs.items():
        rb = b_runs.get(key)
        if rb is None:
            continue
        b_objs = {o["id"]: o for o in rb["objects"]}
        for oa in ra["objects"]:
            ob = b_objs.get(oa["id"])
            if ob is None or not (oa["moved"] and oa["picked"] and ob["picked"]):
                continue
            ja = judge.judge(
                oa["type"], oa["variant"], ra["room_type"], oa["final_parent_type"], ra["present_receptacles"]
            )
            jb = judge.judge(
                ob["type"], ob["variant"], rb["room_type"], ob["final_parent_type"], rb["present_receptacles"]
            )
            if ja is None or jb is None:
                unjudged += 1
                continue
            d = _held_votes(ja) - _held_votes(jb)
            if d >= margin:
                wins += 1
            elif d <= -margin:
                losses += 1
            else:
                ties += 1
    n, decided = wins + ties + losses, wins + losses
    return {
        "n": n,
        "wins": wins,
        "ties": ties,
        "losses": losses,
        "unjudged": unjudged,
        "pref_a": (wins + ties / 2) / n if n else None,
        "p_value": float(binomtest(wins, decided, 0.5).pvalue) if decided else 1.0,
    }


# ---------------------------------------------------------------------------- disagreements


def disagreements(
    records: Iterable[Mapping[str, Any]], judge: HumanJudge | None = None, top: int = 25
) -> list[dict[str, Any]]:
    """Where the catalog's placement prior and the annotators disagree most.

    For each (object, room type) among the records' moved objects, over the receptacles those
    rooms had (Floor included): the prior's most likely receptacle with its correct votes,
    beside the receptacle people voted for most. Sorted by the vote gap, largest first.
    """
    from tidee.server.catalog import receptacle_weights

    judge = judge or HumanJudge.load()
    present: dict[tuple[str, str | None, str], set[str]] = {}
    for rec in records:
        for obj in rec["objects"]:
            if obj["moved"]:
                key = (obj["type"], obj["variant"], rec["room_type"])
                present.setdefault(key, {"Floor"}).update(rec["present_receptacles"])
    rows = []
    for (category, variant, room_type), here in sorted(present.items(), key=str):
        votes = {r: v.correct for r in sorted(here) if (v := judge.votes(category, variant, room_type, r))}
        if not votes:
            continue
        weights = receptacle_weights(category, variant, room_type, sorted(here))
        ranked = sorted((r for r in weights if r in votes), key=lambda r: -weights[r])
        if not ranked:
            continue
        prior_top, people_top = ranked[0], max(votes, key=lambda r: votes[r])
        rows.append(
            {
                "object": category + (f"/{variant}" if variant else ""),
                "room_type": room_type,
                "prior_top": prior_top,
                "prior_top_votes": votes[prior_top],
                "people_top": people_top,
                "people_top_votes": votes[people_top],
                "gap": votes[people_top] - votes[prior_top],
            }
        )
    rows.sort(key=lambda r: (-r["gap"], r["prior_top_votes"], r["object"], r["room_type"]))
    return rows[:top]


# ---------------------------------------------------------------------------- tidee eval human


def run_human_eval(reports: Sequence[str], out: Path, command: str = "") -> dict[str, Any]:
    """Score the episodes of ``tidee eval tidy`` reports with the human judge: ``human.json``,
    ``human.md`` and ``human.png`` in ``out``. The reports' variants must not overlap."""
    from tidee.protocol.episode_log import write_atomic

    from .judge import REFERENCE_VARIANTS
    from .report import _human_section, load_report

    records: list[Mapping[str, Any]] = []
    origin: dict[str, str] = {}
    for src in reports:
        for rec in load_report(src)["episodes"]:
            v = rec["variant"]
            if origin.setdefault(v, str(src)) != str(src):
                raise ValueError(f"variant {v!r} is in both {origin[v]} and {src}; give each variant once")
            records.append(rec)
    if not records:
        raise ValueError("no episodes in the reports")
    judge = HumanJudge.load()
    agents = [v for v in dict.fromkeys(r["variant"] for r in records) if v not in REFERENCE_VARIANTS]
    agents += [v for v in REFERENCE_VARIANTS if v in origin]
    human: dict[str, Any] = {
        "source": "Housekeep human annotations (MIT), agent/data/housekeep",
        "reports": list(map(str, reports)),
        "command": command,
        "metrics": human_metrics(records, judge),
        "pairwise": human_pairwise(records, agents, judge=judge),
        "pairwise_margin2": human_pairwise(records, agents, margin=2, judge=judge),
        "disagreements": disagreements(records, judge),
    }
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Tidy placements judged by people",
        "",
        f"Episodes of {', '.join(f'`{r}`' for r in human['reports'])}, scored with the Housekeep "
        "annotations; the catalog judge's figures are in those reports.",
        *_human_section(human),
        "",
        "## Where the catalog prior and the annotators disagree most",
        "",
        "For objects the mess-up moved, over the receptacles those rooms had: the prior's first choice "
        "and the receptacle most annotators called correct, with their correct votes (of 10).",
        "",
        "| Object | Room | Prior's first choice (votes) | People's first choice (votes) |",
        "|---|---|---|---|",
    ]
    for d in human["disagreements"]:
        lines.append(
            f"| {d['object']} | {d['room_type']} | {d['prior_top']} ({d['prior_top_votes']}) "
            f"| {d['people_top']} ({d['people_top_votes']}) |"
        )
    lines += ["", f"Command: `{command}`" if command else "", ""]
    write_atomic(out / "human.md", "\n".join(lines).encode())
    write_atomic(out / "human.json", json.dumps(human, indent=1).encode())
    write_atomic(out / "human.png", _plot(human["metrics"]))
    return human


def _plot(metrics: Mapping[str, Any]) -> bytes:
    import io

    import numpy as np
    from matplotlib.figure import Figure

    rows = {**metrics["variants"], "tidy rooms": metrics["tidy_rooms"]}
    names = list(rows)
    fig = Figure(figsize=(max(6.0, 1.4 * len(names) + 2), 4.2))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(names))
    for k, (key, label) in enumerate(
        (("correct", "correct (>= 5/10)"), ("plausible", "plausible (>= 5/10)"))
    ):
        vals = [np.nan if rows[n][key] is None else 100 * rows[n][key] for n in names]
        ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=20, ha="right")
    ax.set_ylim(0, 100)
    ax.set_ylabel("% of judged placements")
    ax.set_title("Placements judged by people (Housekeep annotations)")
    ax.legend(loc="lower right", framealpha=0.9, fontsize="small")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    return buf.getvalue()
