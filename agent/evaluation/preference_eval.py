"""``tidee eval preferences``: does the agent do what a household asks, and nothing else?

For each test configuration the agents first run without preferences. From that run (the
evaluation may read it; the agent never does) a scripted profile of three sentences is written:

* **asked**: a category the mess-up moved goes on another receptacle the room has than where the
  tidy room kept it, one the catalog finds plausible for it ("the mug goes on the dining table",
  never "the plate goes on the coffee machine"), and one where every object of that category fits
  at once (:mod:`tidee.agent.evaluation.feasibility`: a box 48 cm long is never asked onto a side
  table 40 cm wide);
* **never**: a moved category may not go where the agent put it without preferences ("never put
  the apple on the counter top");
* **group**: a group phrase whose MiniLM members include a moved category the sentence does not
  name goes on a receptacle the room has that holds all the group's objects in the room at once
  ("dishes go on the shelf").

Then the same episodes run with the profile (``--preferences``). Reported per agent: the share of
the asked and never objects placed as asked; the share of the group's unnamed members placed as
asked; the side effects: the share of the other objects (named by no preference) whose final
receptacle differs between the two runs; and how many of the asked objects the agent found and
picked up (an object never picked is lost to perception or approach, not to the preference).

Side effects have a floor that no preference causes: any change of course (another walk, one
more object looked at) changes what the learned detector sees for the rest of the episode, so
other objects end elsewhere too. ``--reseeded`` (on by default) runs every episode once more
without preferences under another agent seed (``RESEED_OFFSET``) and reports the same share
between the two runs without a profile: the run-to-run variation beside the side effects.
JSON, Markdown and PNG; ``--keep-logs`` keeps every episode's log to read why.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import PLACEABLE_RECEPTACLES
from tidee.agent.evaluation.config import PreferenceEvalConfig
from tidee.agent.evaluation.judge import plausible
from tidee.agent.evaluation.report import machine_note
from tidee.agent.evaluation.tidy_eval import EPISODES_FILE, TidyJob, run_jobs, select_configs
from tidee.agent.reasoning.relations import words
from tidee.batch import import_ray
from tidee.protocol.messages import EpisodeSpec

# Group phrases a household might use; each configuration takes the first whose members include
# one of its moved categories.
GROUP_PHRASES = (
    "dishes",
    "food",
    "fruit and vegetables",
    "kitchen utensils",
    "toys",
    "electronics",
    "writing things",
    "bathroom things",
    "sports equipment",
)
SENTENCES = ("asked", "never", "group")  # a profile's sentences, in this order
RESEED_OFFSET = 1000  # the reseeded run's agent seed: the configuration's index plus this
SURFACES = sorted(PLACEABLE_RECEPTACLES - {"GarbageCan", "Toilet", "ToiletPaperHanger", "TowelHolder"})


def placement_check() -> Any:
    """The simulator check that a scripted preference can be carried out (a seam for tests)."""
    from tidee.agent.evaluation.feasibility import PlacementCheck

    return PlacementCheck()


def _key(rec: Mapping[str, Any]) -> tuple[Any, ...]:
    return (rec["room_type"], rec["seed"], rec["mess_index"])


def script_profile(
    rec: Mapping[str, Any],
    members: Mapping[str, Sequence[str]],
    seed: int,
    fits: Callable[[str | tuple[str, ...], str], bool] | None = None,
) -> dict[str, Any]:
    """The three scripted preferences for one configuration, from an agent's run without them.
    ``fits(categories, receptacle)``: whether the simulator can put every object of those
    categories there (:mod:`tidee.agent.evaluation.feasibility`); a preference it cannot carry
    out is not asked, and listed under ``"unfit"``. None: no check."""
    rng = np.random.default_rng([seed, rec["seed"], 0 if rec["mess_index"] is None else rec["mess_index"]])
    moved = [o for o in rec["objects"] if o["moved"]]
    cats = sorted({o["type"] for o in moved})
    present = sorted(set(rec["present_receptacles"]) & set(SURFACES))
    out: dict[str, Any] = {"asked": None, "never": None, "group": None, "unfit": []}
    used: set[str] = set()

    def can(kind: str, cats: str | tuple[str, ...], r: str) -> bool:
        ok = fits is None or fits(cats, r)
        if not ok:
            out["unfit"].append(
                {"kind": kind, "categories": [cats] if isinstance(cats, str) else list(cats), "receptacle": r}
            )
        return ok

    for c in rng.permutation(cats).tolist():
        origin = {o["original_parent_type"] for o in moved if o["type"] == c}
        variant = next(o["variant"] for o in moved if o["type"] == c)
        # somewhere else a household might keep it: a receptacle the catalog finds plausible for it
        options = [
            r
            for r in present
            if r not in origin
            and plausible(c, variant, rec["room_type"], r, rec["present_receptacles"])
            and can("asked", c, r)
        ]
        if options:
            r = options[int(rng.integers(len(options)))]
            out["asked"] = {"text": f"the {words(c)} goes on the {words(r)}", "category": c, "receptacle": r}
            used.add(c)
            break
    for c in rng.permutation(cats).tolist():
        finals = sorted({o["final_parent_type"] for o in moved if o["type"] == c and o["final_parent_type"]})
        if c not in used and finals:
            r = finals[0]
            out["never"] = {
                "text": f"never put the {words(c)} on the {words(r)}",
                "category": c,
                "receptacle": r,
            }
            used.add(c)
            break
    for phrase in GROUP_PHRASES:
        unnamed = [c for c in members[phrase] if c in cats and c not in used]
        options = [r for r in present if can(phrase, tuple(members[phrase]), r)] if unnamed else []
        if options:
            r = options[int(rng.integers(len(options)))]
            verb = "go" if phrase.endswith("s") else "goes"
            out["group"] = {
                "text": f"{phrase} {verb} on the {words(r)}",
                "categories": list(members[phrase]),
                "unnamed": unnamed,
                "receptacle": r,
            }
            break
    return out


def _placed(objs: Sequence[Mapping[str, Any]], category: str, receptacle: str, asked: bool) -> list[bool]:
    return [
        (o["final_parent_type"] == receptacle) == asked for o in objs if o["moved"] and o["type"] == category
    ]


def _others(
    rec: Mapping[str, Any], other: Mapping[str, Any], named: set[str]
) -> list[tuple[Mapping[str, Any], Mapping[str, Any]]]:
    """The objects named by no preference: (in ``rec``, the same object in ``other``)."""
    before = {o["id"]: o for o in other["objects"]}
    return [(o, before[o["id"]]) for o in rec["objects"] if o["type"] not in named and o["id"] in before]


def _ok(o: Mapping[str, Any], r: Mapping[str, Any]) -> bool:
    """Whether the catalog judge finds object ``o`` of run ``r`` plausibly placed."""
    return plausible(
        o["type"], o["variant"], r["room_type"], o["final_parent_type"], r["present_receptacles"]
    )


def _changed(
    rec: Mapping[str, Any], other: Mapping[str, Any], named: set[str], worse: bool = False
) -> list[bool]:
    """Per object named by no preference: whether its final receptacle differs between the
    runs (``worse``: whether it ends where the catalog judge finds it implausible in ``rec``
    but plausible in ``other``)."""
    return [
        (not _ok(o, rec) and _ok(b, other)) if worse else o["final_parent_type"] != b["final_parent_type"]
        for o, b in _others(rec, other, named)
    ]


def _named(prof: Mapping[str, Any]) -> set[str]:
    """The categories a configuration's scripted profile names (its group: every member)."""
    named = {prof[k]["category"] for k in ("asked", "never") if prof[k]}
    return named | (set(prof["group"]["categories"]) if prof["group"] else set())


def side_effect_list(
    without: Sequence[Mapping[str, Any]], with_: Sequence[Mapping[str, Any]], profiles: Mapping[Any, Any]
) -> list[dict[str, Any]]:
    """Every side effect, object by object: the other objects whose final receptacle differs
    between the runs without and with the profile (what ``--keep-logs`` episodes explain)."""
    base = {(r["variant"], _key(r)): r for r in without}
    out = []
    for rec in with_:
        first = base[(rec["variant"], _key(rec))]
        for o, b in _others(rec, first, _named(profiles[_key(rec)])):
            if o["final_parent_type"] != b["final_parent_type"]:
                out.append(
                    {
                        "variant": rec["variant"],
                        "configuration": "{}_{}_mess{}".format(*_key(rec)),
                        "object": o["id"],
                        "without": b["final_parent_type"],
                        "with": o["final_parent_type"],
                        "moved_by_mess": bool(o["moved"]),
                        "worse": not _ok(o, rec) and _ok(b, first),
                    }
                )
    return sorted(out, key=lambda d: (d["variant"], d["configuration"], d["object"]))


def score(
    without: Sequence[Mapping[str, Any]],
    with_: Sequence[Mapping[str, Any]],
    profiles: Mapping[Any, Any],
    reseeded: Sequence[Mapping[str, Any]] = (),
) -> dict[str, Any]:
    """Per variant: asked / never / group obeyed, side effects, and (``reseeded``: the same
    episodes without preferences under another agent seed) the run-to-run share ``side_rerun``
    over the same objects (see the module docstring)."""
    base = {(r["variant"], _key(r)): r for r in without}
    again = {(r["variant"], _key(r)): r for r in reseeded}
    per: dict[str, dict[str, list[bool]]] = {}
    for rec in with_:
        acc = per.setdefault(
            rec["variant"],
            {
                "asked": [],
                "never": [],
                "group": [],
                "side": [],
                "side_worse": [],
                "side_rerun": [],
                "side_rerun_worse": [],
                "found": [],
                "picked": [],
            },
        )
        prof = profiles[_key(rec)]
        named = _named(prof)
        if prof["asked"]:
            a = prof["asked"]
            acc["asked"] += _placed(rec["objects"], a["category"], a["receptacle"], True)
            mine = [o for o in rec["objects"] if o["moved"] and o["type"] == a["category"]]
            acc["found"] += [o["found"] for o in mine]
            acc["picked"] += [o["picked"] for o in mine]
        if prof["never"]:
            n = prof["never"]
            acc["never"] += _placed(rec["objects"], n["category"], n["receptacle"], False)
        if prof["group"]:
            g = prof["group"]
            for c in g["unnamed"]:
                acc["group"] += _placed(rec["objects"], c, g["receptacle"], True)
        first = base[(rec["variant"], _key(rec))]
        acc["side"] += _changed(rec, first, named)
        acc["side_worse"] += _changed(rec, first, named, worse=True)
        second = again.get((rec["variant"], _key(rec)))
        if second is not None:  # the reseeded run against the first, the same objects
            acc["side_rerun"] += _changed(second, first, named)
            acc["side_rerun_worse"] += _changed(second, first, named, worse=True)
    return {
        v: {k: {"n": len(xs), "share": float(np.mean(xs)) if xs else None} for k, xs in acc.items()}
        for v, acc in per.items()
    }


def run_preference_eval(cfg: PreferenceEvalConfig, command: str = "") -> dict[str, Any]:
    from tidee.agent.reasoning.preferences import group_members
    from tidee.protocol.episode_log import write_atomic

    out = Path(cfg.out)
    (out / "profiles").mkdir(parents=True, exist_ok=True)
    configs = select_configs(cfg.split, cfg.episodes)
    agent = cfg.agent
    spec = {"resolution": cfg.resolution, "max_steps": cfg.max_steps}

    def jobs(preferences: Mapping[Any, str | None], logs: str, seed_offset: int = 0) -> list[TidyJob]:
        log_dir = out / "logs" / logs if cfg.keep_logs else None
        return [
            TidyJob(
                agent=replace(
                    agent,
                    variant=v,
                    seed=c.index + seed_offset,
                    preferences=preferences.get((c.room_type, c.seed, c.mess_index)),
                ),
                spec=EpisodeSpec(room_type=c.room_type, seed=c.seed, mess_index=c.mess_index, **spec),
                split=cfg.split,
                renderer=cfg.renderer,
                log_dir=log_dir,
            )
            for c in configs
            for v in cfg.variants
        ]

    batch = cfg.batch
    if batch.backend == "ray":
        import_ray()  # not installed: say how, before any episode

    def run(todo: list[TidyJob], resume: bool) -> list[dict[str, Any]]:
        return run_jobs(
            todo,
            cfg.workers,
            cfg.renderer,
            cfg.progress,
            backend=batch.backend,
            ray_address=batch.ray_address,
            out_jsonl=out / EPISODES_FILE,
            resume=resume,
        )

    without = run(jobs({}, "without"), batch.resume)
    members = {p: group_members(p) for p in GROUP_PHRASES}
    profiles: dict[Any, Any] = {}
    files: dict[Any, str] = {}
    first = cfg.variants[0]
    with placement_check() as check:  # one profile per configuration, from the first agent's run
        for rec in without:
            if rec["variant"] == first:
                profiles[_key(rec)] = script_profile(rec, members, cfg.seed, check.room(*_key(rec)))
    for key, prof in profiles.items():
        path = out / "profiles" / "{}_{}_mess{}.json".format(*key)
        sentences = [prof[k]["text"] for k in SENTENCES if prof[k]]
        path.write_text(json.dumps({"household": path.stem, "preferences": sentences}, indent=1))
        files[key] = str(path)
    # the same records file: this run's episodes without preferences are in it (resumed or not)
    with_ = run(jobs(files, "with"), True)
    reseeded = run(jobs({}, "reseeded", RESEED_OFFSET), True) if cfg.reseeded else []
    result: dict[str, Any] = {
        "command": command,
        "machine": machine_note(),
        "config": {
            "split": cfg.split,
            "configurations": len(configs),
            "variants": list(cfg.variants),
            "perception": agent.perception,
            "oop": agent.oop,
            "seed": cfg.seed,
            "reseeded": cfg.reseeded,
        },
        "groups": {p: list(m) for p, m in members.items()},
        "metrics": score(without, with_, profiles, reseeded),
        "side_effects": side_effect_list(without, with_, profiles),
        "profiles": {"{}_{}_mess{}".format(*k): v for k, v in profiles.items()},
    }
    write_atomic(out / "preferences.json", json.dumps(result, indent=1).encode())
    write_atomic(out / "preferences.md", _markdown(result).encode())
    write_atomic(out / "preferences.png", _plot(result["metrics"]))
    return result


def _pct(m: Mapping[str, Any]) -> str:
    if m["share"] is None:
        return "–"
    return f"{100 * m['share']:.1f} % ({round(m['share'] * m['n'])} of {m['n']})"


def _markdown(r: Mapping[str, Any]) -> str:
    c = r["config"]
    lines = [
        "# Preferences: does the agent do what a household asks, and nothing else?",
        "",
        f"{c['configurations']} {c['split']} configurations, each run without and with a scripted "
        f"profile of three sentences (perception {c['perception']}, OOP detector {c['oop']}). "
        "Asked: a moved category goes on another receptacle the room has, one the catalog finds "
        "plausible for it and on which the simulator can put every object of the category at once. "
        "Never: a moved category may not go where the agent put it without "
        "preferences. Group: a phrase whose MiniLM members include a moved category it does not "
        "name, on a receptacle that holds all of the group's objects in the room at once. "
        "Side effects: other objects whose final receptacle changed; for the worse: of all "
        "the other objects, those that end where the catalog judge finds them implausible with the "
        "profile and plausible without it. Run to run: the same two shares between the run without "
        f"preferences and a second run without them under another agent seed (+{RESEED_OFFSET}): "
        "what any change of course does to the other objects.",
        "",
        "| Agent | Asked, placed as asked | Never, obeyed | Group, unnamed members placed as asked "
        "| Side effects | for the worse | Run to run, no profile | for the worse "
        "| Asked objects found | Asked objects picked |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    none = {"n": 0, "share": None}
    for v, m in r["metrics"].items():
        cells = [m.get(k, none) for k in ("side", "side_worse", "side_rerun", "side_rerun_worse")]
        lines.append(
            f"| {v} | {_pct(m['asked'])} | {_pct(m['never'])} | {_pct(m['group'])} | "
            + " | ".join(_pct(c) for c in cells)
            + f" | {_pct(m['found'])} | {_pct(m['picked'])} |"
        )
    effects = r.get("side_effects", [])
    if effects:
        lines += [
            "",
            "Side effects, object by object (the episode logs, kept with `--keep-logs`, say why):",
            "",
            "| Agent | Configuration | Object | Without the profile | With it "
            "| Moved by the mess | For the worse |",
            "|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {e['variant']} | {e['configuration']} | {e['object']} | {e['without'] or '–'} "
            f"| {e['with'] or '–'} | {'yes' if e['moved_by_mess'] else 'no'} "
            f"| {'yes' if e['worse'] else 'no'} |"
            for e in effects
        ]
    unfit = [(k, u) for k, p in r.get("profiles", {}).items() for u in p.get("unfit", [])]
    if unfit:
        asked = [
            f"{', '.join(u['categories'])} on the {u['receptacle']} ({k})"
            for k, u in unfit
            if u["kind"] == "asked"
        ]
        lines += [
            "",
            f"Not asked, because the objects do not fit there (the server's own placement, tried on "
            f"the configuration's scene: evaluation only): {len(asked)} plausible asks"
            + (f" ({'; '.join(asked)})" if asked else "")
            + f" and {len(unfit) - len(asked)} group receptacles.",
        ]
    lines += ["", "Group phrases and the categories MiniLM carried them to:", ""]
    lines += [f"- {p}: {', '.join(m)}" for p, m in r["groups"].items()]
    lines += ["", f"Command: `{r['command']}`", ""]
    if r.get("machine"):
        lines += [f"Ran on: {r['machine'].removeprefix('machine: ')}.", ""]
    return "\n".join(lines)


def _plot(metrics: Mapping[str, Any]) -> bytes:
    import io

    from matplotlib.figure import Figure

    keys = [
        ("asked", "asked"),
        ("never", "never"),
        ("group", "group (unnamed)"),
        ("side", "side effects"),
        ("side_rerun", "run to run"),
    ]
    names = list(metrics)
    fig = Figure(figsize=(max(6.0, 2.2 * len(names) + 2), 4.0))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(names))
    w = 0.8 / len(keys)
    for k, (key, label) in enumerate(keys):
        shares = [metrics[n].get(key, {"share": None})["share"] for n in names]
        vals = [np.nan if s is None else 100 * s for s in shares]
        ax.bar(x + (k - (len(keys) - 1) / 2) * w, vals, w, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels(names)
    ax.set_ylim(0, 100)
    ax.set_ylabel("%")
    ax.set_title("Preferences obeyed, and side effects")
    ax.legend(
        frameon=False, fontsize="small", ncol=len(keys), loc="upper center", bbox_to_anchor=(0.5, -0.08)
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    return buf.getvalue()
