"""``tidee eval ceiling``: how far a placement model that learns the tidy rooms can go with the judge.

The simulated judge (:mod:`tidee.agent.evaluation.judge`) scores a placement by the catalog's
placement prior. Every placement model learns from tidy training rooms instead, and those do not
follow the prior exactly: a receptacle with little room (a side table with a lamp on it) takes
fewer objects than the prior sends it, and the generator puts them elsewhere. This command measures
what that costs, on the objects of a tidy report that TIDEE and CommonMemory both picked (the
population of the report's preference, :func:`tidee.agent.evaluation.report.pairwise_table`):

1. **Survey.** Tidy rooms of the training pool (seeds from :data:`SURVEY_FIRST_SEED` on, after every
   seed a shipped placement model or the placement statistics used), of one generator version
   (:func:`tidee.server.rooms.rooms_version`): objects per room, and the total-variation distance
   between where the rooms hold each (room type, category) and where the prior would put them.
2. **Preference ceilings**, each a pair of counterfactual agents whose placements replace the report's:
   * *rooms learner*: TIDEE places each object on the receptacle the survey rooms hold its (room
     type, category, variant) on most often, among those present; CommonMemory on the survey's most
     frequent receptacle for the category over every room (the first present). This is a perfect
     learner of the rooms against a perfect CommonMemory of the same rooms;
   * *prior learner*: the same two read from the catalog prior itself, i.e. what rooms that followed
     the prior exactly would teach.
3. **Observed judge.** The report's own placements scored by the survey's frequencies (the share of
   the most frequent receptacle present) instead of by the prior.

Evaluation only: it reads the catalog prior and the episodes' ground truth. JSON + Markdown in ``--out``.
The command and its options: :mod:`tidee.agent.reasoning.rgcn.commands`, ``CeilingConfig``.
"""

from __future__ import annotations

import copy
import gzip
import json
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from tidee.agent.reasoning.rgcn.config import SURVEY_FIRST_SEED, CeilingConfig
from tidee.server.scene_cache import SceneCache

A, B = "TIDEE", "CommonMemory"

Key = tuple[str, str, Any]  # (room type, category, variant)


def _load_report(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if path.is_dir():
        for name in ("report.json", "report.json.gz"):
            if (path / name).is_file():
                path = path / name
                break
    if not path.is_file():
        raise FileNotFoundError(
            f"no tidy report at {path} (give report.json, report.json.gz or their folder)"
        )
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        report = json.load(f)
    if not isinstance(report, Mapping) or not isinstance(report.get("episodes"), list):
        raise ValueError(f"{path} is not a tidy report: it has no 'episodes' list")
    variants = {e.get("variant") for e in report["episodes"]}
    missing = [v for v in (A, B) if v not in variants]
    if missing:
        raise ValueError(
            f"{path} has no episodes of {missing}; the ceiling compares {A} with {B} "
            f"(run `tidee eval tidy --variants {A},{B}`)"
        )
    return dict(report)


# ------------------------------------------------------------------------ survey
def survey(
    rooms_per_type: int,
    version: int,
    first_seed: int = SURVEY_FIRST_SEED,
    progress: bool = True,
    cache: SceneCache | None | Literal["default"] = "default",
) -> dict[str, Any]:
    """Where tidy rooms of generator ``version`` hold their objects.

    The rooms come from the scene cache (``cache``: a :class:`SceneCache`, None for none, or the
    user's default one) when it has them, else they are generated (physics and all) and stored:
    a second survey of the same rooms skips the physics.

    Returns ``counts`` {(room type, category, variant): Counter(receptacle type)}, ``objects_per_room``,
    ``tv`` (the total-variation distance between the rooms' receptacle counts per (room type,
    category) and the prior's, restricted to each room's receptacles and summed over its objects;
    weighted by objects), ``tv_by_room_type``, the seeds and the time taken."""
    from tqdm import tqdm

    from tidee.protocol.messages import ROOM_TYPES
    from tidee.server.catalog import receptacle_weights
    from tidee.server.episode import SceneLibrary
    from tidee.server.rooms import rooms_version
    from tidee.server.splits import TRAIN_POOL
    from tidee.server.world import World

    version = rooms_version(version)
    library = SceneLibrary(capacity=1, disk=cache, version=version)
    if rooms_per_type < 1:
        raise ValueError(f"--rooms-per-type must be >= 1, got {rooms_per_type}")
    seeds = range(first_seed, first_seed + rooms_per_type)
    if seeds[0] not in TRAIN_POOL or seeds[-1] not in TRAIN_POOL:
        raise ValueError(f"survey seeds {seeds[0]}-{seeds[-1]} leave the training pool {TRAIN_POOL}")
    counts: dict[Key, Counter] = defaultdict(Counter)
    observed: dict[tuple[str, str], Counter] = defaultdict(Counter)
    expected: dict[tuple[str, str], dict[str, float]] = defaultdict(lambda: defaultdict(float))
    per_room: list[int] = []
    t0 = time.time()
    world = World(renderer="tiny")
    try:
        jobs = [(rt, s) for rt in ROOM_TYPES for s in seeds]
        for rt, seed in tqdm(jobs, desc=f"survey rooms (generator {version})", disable=not progress):
            scene = library.tidy_scene(world, rt, seed)
            present = sorted({o.type for o in scene.objects if o.receptacle and not o.pickupable})
            n = 0
            for o in scene.objects:
                if not (o.pickupable and o.parent_type):
                    continue
                n += 1
                counts[(rt, o.type, o.variant)][o.parent_type] += 1
                observed[(rt, o.type)][o.parent_type] += 1
                for r, w in receptacle_weights(o.type, o.variant, rt, present).items():
                    expected[(rt, o.type)][r] += w
            per_room.append(n)
    finally:
        world.close()
    dist: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    for key, c in observed.items():
        e = expected[key]
        # sorted: a set's order changes with the hash seed, and with it the float sum's last bits
        d = 0.5 * sum(abs(c.get(r, 0) - e.get(r, 0.0)) for r in sorted(set(c) | set(e)))
        dist[key[0]][0] += d
        dist[key[0]][1] += sum(c.values())
    total = sum(n for _, n in dist.values())
    return {
        "counts": dict(counts),
        "rooms_version": version,
        "rooms": len(per_room),
        "seeds": [seeds[0], seeds[-1]],
        "objects": sum(per_room),
        "objects_per_room": sum(per_room) / len(per_room),
        "tv": sum(d for d, _ in dist.values()) / total if total else None,
        "tv_by_room_type": {rt: d / n for rt, (d, n) in dist.items() if n},
        "seconds": round(time.time() - t0, 1),
    }


# --------------------------------------------------------------- counterfactuals
Chooser = Callable[[str, str, Any, Sequence[str]], "str | None"]


def _present(record: Mapping[str, Any]) -> set[str]:
    return set(record["present_receptacles"]) | {"Floor"}


def _present_counts(counts: Mapping[Any, Counter], key: Any, present: Sequence[str]) -> dict[str, int]:
    """The survey's counts for ``key`` on the receptacle types present (and the floor)."""
    have = set(present) | {"Floor"}
    return {r: n for r, n in counts.get(key, Counter()).items() if r in have}


def rooms_choosers(counts: Mapping[Key, Counter]) -> tuple[Chooser, Chooser]:
    """(TIDEE, CommonMemory) of a perfect learner of the surveyed rooms."""
    pooled: dict[str, Counter] = defaultdict(Counter)
    for (_, cat, _), c in counts.items():
        pooled[cat].update(c)

    def tidee(rt: str, cat: str, variant: Any, present: Sequence[str]) -> str | None:
        # never seen in this room type: fall back on the category's pooled counts
        c = _present_counts(counts, (rt, cat, variant), present) or _present_counts(pooled, cat, present)
        return max(sorted(c), key=lambda r: c[r]) if c else None

    def common(rt: str, cat: str, variant: Any, present: Sequence[str]) -> str | None:
        have = set(present) | {"Floor"}
        return next(
            (
                r
                for r, _ in sorted(pooled.get(cat, Counter()).items(), key=lambda kv: (-kv[1], kv[0]))
                if r in have
            ),
            None,
        )

    return tidee, common


def prior_choosers() -> tuple[Chooser, Chooser]:
    """(TIDEE, CommonMemory) that learned rooms following the catalog prior exactly: TIDEE takes the
    prior's favourite present; CommonMemory ranks by the prior pooled over room types (weighted by
    how often each room type has the category) and variants, and takes the first present."""
    from tidee.protocol.messages import ROOM_TYPES
    from tidee.server.catalog import ROOM_TEMPLATES, receptacle_weights, variant_weights

    def marginal(cat: str, rt: str) -> dict[str, float]:
        out: dict[str, float] = defaultdict(float)
        for v, wv in variant_weights(cat, rt).items():
            for r, w in receptacle_weights(cat, v, rt).items():
                out[r] += wv * w
        return out

    pooled: dict[str, list[str]] = {}

    def ranking(cat: str) -> list[str]:
        if cat not in pooled:
            tot: dict[str, float] = defaultdict(float)
            for rt in ROOM_TYPES:
                small = ROOM_TEMPLATES[rt]["small"]
                if cat in small:
                    for r, w in marginal(cat, rt).items():
                        tot[r] += small[cat] / sum(small.values()) * w
            pooled[cat] = sorted(tot, key=lambda r: (-tot[r], r))
        return pooled[cat]

    def tidee(rt: str, cat: str, variant: Any, present: Sequence[str]) -> str | None:
        w = receptacle_weights(cat, variant, rt, list(present))
        return max(sorted(w), key=lambda r: w[r]) if w else None

    def common(rt: str, cat: str, variant: Any, present: Sequence[str]) -> str | None:
        have = set(present) | {"Floor"}
        return next((r for r in ranking(cat) if r in have), None)

    return tidee, common


def counterfactual(
    records: Sequence[Mapping[str, Any]], variant: str, choose: Chooser
) -> list[dict[str, Any]]:
    """Copies of ``variant``'s records with every picked object's final receptacle chosen by ``choose``."""
    out = []
    for rec in records:
        if rec["variant"] != variant:
            continue
        copied = copy.deepcopy(dict(rec))
        for obj in copied["objects"]:
            if obj["picked"]:
                obj["final_parent_type"] = choose(
                    copied["room_type"], obj["type"], obj["variant"], copied["present_receptacles"]
                )
        out.append(copied)
    return out


def observed_judge(counts: Mapping[Key, Counter]) -> Callable[..., float]:
    """A judge that scores by the surveyed rooms: the receptacle's count for (room type, category,
    variant) over the largest count among the receptacles present (1 when the survey never saw the
    object in this room type and the receptacle is present)."""

    def score(
        category: str, variant: Any, room_type: str, parent: str | None, present: Sequence[str]
    ) -> float:
        if parent is None:
            return 0.0
        c = _present_counts(counts, (room_type, category, variant), present)
        if not c:
            return 1.0 if parent in set(present) | {"Floor"} else 0.0
        return c.get(parent, 0) / max(c.values())

    return score


def _cell(records: Sequence[Mapping[str, Any]], judge: Callable[..., float] | None = None) -> dict[str, Any]:
    """TIDEE against CommonMemory (:func:`tidee.agent.evaluation.report.pairwise_table`), with each
    side's mean judge score over the objects compared."""
    from tidee.agent.evaluation.report import pairwise_table

    cell = pairwise_table(records, [A, B], judge=judge)[A][B]
    return {
        **{k: cell[k] for k in ("n", "wins", "ties", "losses", "pref_a", "p_value")},
        "mean_judge": {A: cell["mean_a"], B: cell["mean_b"]},
    }


def ceilings(report: Mapping[str, Any], counts: Mapping[Key, Counter]) -> dict[str, Any]:
    """The report's preference of TIDEE over CommonMemory, the two counterfactual ceilings and the
    observed judge's preference (see the module docstring)."""
    records = [e for e in report["episodes"] if e["variant"] in (A, B)]
    out: dict[str, Any] = {"report": _cell(records)}
    for name, (ta, cb) in (("rooms_learner", rooms_choosers(counts)), ("prior_learner", prior_choosers())):
        out[name] = _cell(counterfactual(records, A, ta) + counterfactual(records, B, cb))
    out["observed_judge"] = _cell(records, judge=observed_judge(counts))
    return out


# ------------------------------------------------------------------------ command
def run_ceiling(
    cfg: CeilingConfig, command: str = "tidee eval ceiling", progress: bool = True
) -> dict[str, Any]:
    """Survey, then the ceilings of every report of ``cfg``; ceiling.json and ceiling.md in ``cfg.out``."""
    from tidee.protocol.episode_log import write_json_atomic

    loaded = [(str(p), _load_report(p)) for p in cfg.report]  # fail on a bad report before the survey
    s = survey(cfg.rooms_per_type, cfg.rooms_version, first_seed=cfg.first_seed, progress=progress)
    result = {
        "command": command,
        "judge": "catalog placement priors (receptacle_weights)",
        "survey": {k: v for k, v in s.items() if k != "counts"},
        "reports": [
            {
                "path": p,
                "split": ",".join(r.get("config", {}).get("splits", [])) or None,
                **ceilings(r, s["counts"]),
            }
            for p, r in loaded
        ],
    }
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "ceiling.json", result)
    (out / "ceiling.md").write_text(markdown(result))
    return result


ROW_NAMES = {
    "report": "the report's placements",
    "rooms_learner": "rooms learner (perfect learner of the surveyed rooms, both agents)",
    "prior_learner": "prior learner (rooms that follow the prior exactly)",
    "observed_judge": "the report's placements, observed judge",
}


def markdown(result: Mapping[str, Any]) -> str:
    s = result["survey"]
    lines = [
        "# How far can a learner of the tidy rooms go with the judge?",
        "",
        f"`{result['command']}`",
        "",
        f"Survey: {s['rooms']} tidy rooms of generator version {s['rooms_version']} (training-pool seeds "
        f"{s['seeds'][0]}-{s['seeds'][1]} per room type), {s['objects_per_room']:.1f} objects per room. "
        f"Total-variation distance between where they hold each (room type, category) and the catalog "
        f"prior: **{s['tv']:.3f}** ("
        + ", ".join(f"{k} {v:.3f}" for k, v in s["tv_by_room_type"].items())
        + f"). {s['seconds']:.0f} s.",
        "",
    ]
    for rep in result["reports"]:
        lines += [
            f"## {rep['path']}" + (f" ({rep['split']})" if rep.get("split") else ""),
            "",
            "TIDEE against CommonMemory on the objects both picked (ties count half).",
            "",
            "| placements | n | won / tied / lost | preference | mean judge TIDEE "
            "| mean judge CommonMemory |",
            "|---|---|---|---|---|---|",
        ]
        for key, name in ROW_NAMES.items():
            c = rep[key]
            pref = "–" if c["pref_a"] is None else f"{100 * c['pref_a']:.1f} %"
            m = c["mean_judge"]
            fmt = lambda x: "–" if x is None else f"{x:.3f}"  # noqa: E731
            lines.append(
                f"| {name} | {c['n']} | {c['wins']} / {c['ties']} / {c['losses']} | {pref} | "
                f"{fmt(m[A])} | {fmt(m[B])} |"
            )
        lines.append("")
    lines += [
        "The first three rows use the simulated judge (the catalog prior); the last scores by the "
        "surveyed rooms' frequencies. Learners know each object's category and variant, and the "
        "receptacle types present in its room.",
        "",
    ]
    return "\n".join(lines)


__all__ = [
    "SURVEY_FIRST_SEED",
    "ceilings",
    "counterfactual",
    "observed_judge",
    "prior_choosers",
    "rooms_choosers",
    "run_ceiling",
    "survey",
]
