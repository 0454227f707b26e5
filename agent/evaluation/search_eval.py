"""``tidee eval search``: object search on held-out rooms, the paper's Table 2.

Protocol (paper §4.4 and supplement "Exploration with visual search network evaluation"):
each test room in its tidy configuration, each category present (or a seeded sample of
``--categories-per-room`` of them); the agent starts at the episode's start pose and must
say Stop (``Done``) within ``--radius`` (1.5 m) of an instance of the category, with the
instance in view, within ``--max-steps`` (200) steps. A failed episode counts 200 steps.
Both methods share the mapping, the detector and the navigation (``policy/search.py``);
only the choice of where to search differs: (a) the visual search network's ranked search
points, re-predicted after each visit; (b) the nearest frontier (Yamauchi).

Ground truth is read only here, to score: the simulator's object poses (distance to the
instance's footprint rectangle) and the final frame's instance segmentation (in view:
at least ``MIN_VISIBLE_PIXELS`` pixels at 256^2). The agent's decisions never read it.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing as mp
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.perception import TRAINED_RENDERER
from tidee.agent.reasoning.search_commands import int_at_least

METHODS = ("network", "frontier")
PAPER = {
    "network": {"success_pct": 72.4, "mean_steps": 88.8},
    "frontier": {"success_pct": 64.8, "mean_steps": 100.9},
}
NETWORK_FALLBACKS = ("random", "frontier")
MIN_VISIBLE_PIXELS = 12  # at 256 x 256 (scaled with the resolution)


@dataclass
class SearchEvalConfig:
    out: str
    split: str = "test"
    methods: tuple[str, ...] = METHODS
    categories_per_room: int | None = 8  # None: every category present
    max_steps: int = 200
    radius: float = 1.5
    perception: str = "learned"
    resolution: int = 256
    workers: int = 2
    seed: int = 0
    weights: str | None = None
    rooms: int | None = None  # first N rooms of the split (smoke runs)
    examples: int = 4  # heatmap examples in the PNG
    explored_discount: float = 0.0  # VisualSearch.points: down-weight heat where the map is explored
    network_fallback: str = "random"  # network: where to go when no search point is left (random | frontier)

    def __post_init__(self) -> None:
        if self.split not in ("test", "val"):
            raise ValueError(
                f"tidee eval search scores held-out rooms: --split must be test or val, got {self.split!r}"
            )
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise ValueError(f"--methods must be a comma list of {METHODS}, got {list(self.methods)}")
        if self.categories_per_room is not None and self.categories_per_room < 1:
            raise ValueError(
                f"--categories-per-room must be >= 1 (or 0 for all), got {self.categories_per_room}"
            )
        if not 1 <= self.max_steps <= 1000:
            raise ValueError(f"--max-steps must be in [1, 1000], got {self.max_steps}")
        if not self.radius > 0:
            raise ValueError(f"--radius must be > 0 metres, got {self.radius}")
        if self.perception not in ("learned", "oracle"):
            raise ValueError(f"--perception must be learned or oracle, got {self.perception!r}")
        if not 0 <= self.explored_discount <= 1:
            raise ValueError(f"--explored-discount must be in [0, 1], got {self.explored_discount}")
        if self.network_fallback not in NETWORK_FALLBACKS:
            raise ValueError(
                f"--network-fallback must be one of {NETWORK_FALLBACKS}, got {self.network_fallback!r}"
            )
        if not 1 <= self.workers <= 2:
            raise ValueError(f"--workers must be 1 or 2, got {self.workers}")


def episodes(cfg: SearchEvalConfig) -> list[dict[str, Any]]:
    """One job per (room, category, method): categories present in each tidy room, sampled with the seed."""
    from tidee.agent.classes import CLASS_INDEX
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport
    from tidee.server.splits import ROOM_TYPES, rooms

    room_list = rooms(cfg.split)[: cfg.rooms]
    jobs = []
    with InProcessTransport(renderer=TRAINED_RENDERER) as t:
        for rt, seed in room_list:
            t.reset(EpisodeSpec(room_type=rt, seed=seed, resolution=32))
            present = sorted({o["type"] for o in t.state()["objects"] if o["type"] in CLASS_INDEX})
            rng = np.random.default_rng([cfg.seed, seed, ROOM_TYPES.index(rt)])
            n = (
                len(present)
                if cfg.categories_per_room is None
                else min(cfg.categories_per_room, len(present))
            )
            chosen = sorted(rng.choice(present, size=n, replace=False).tolist())
            for label in chosen:
                for method in cfg.methods:
                    jobs.append({"room_type": rt, "seed": seed, "label": label, "method": method})
    return jobs


def _one_episode(job: dict[str, Any], cfg: SearchEvalConfig) -> dict[str, Any]:
    from tidee.agent.classes import CLASS_INDEX
    from tidee.agent.navigation.explore import FrontierExplorer
    from tidee.agent.perception import make_perception
    from tidee.agent.policy.search import SkillDriver, frontier_proposer, search_object
    from tidee.agent.reasoning.search_net import (
        DEFAULT_WEIGHTS,
        VisualSearch,
        footprint_distance,
        room_instances,
    )
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport

    global _WORKER
    try:
        w = _WORKER
    except NameError:
        w = _WORKER = {
            "transport": InProcessTransport(renderer=TRAINED_RENDERER),
            "perception": make_perception(cfg.perception),
        }
    if job["method"] == "network" and "search" not in w:
        w["search"] = VisualSearch.load(
            cfg.weights or DEFAULT_WEIGHTS, explored_discount=cfg.explored_discount
        )
    transport = w["transport"]
    driver = SkillDriver(transport, w["perception"], ground_truth=True)  # ground truth: scoring only
    spec = EpisodeSpec(
        room_type=job["room_type"], seed=job["seed"], resolution=cfg.resolution, max_steps=cfg.max_steps
    )
    t0 = time.perf_counter()
    body = driver.reset(spec)
    fallback = None
    if job["method"] == "network":
        vs = w["search"]

        def propose(b: Any, label: str, visited: Any) -> list[tuple[float, float]]:
            return vs.points(b.mapper, label, tuple(b.xy), k=3, visited=visited)

        if cfg.network_fallback == "frontier":
            fallback = frontier_proposer(FrontierExplorer(body.mapper.grid))
    else:
        propose = frontier_proposer(FrontierExplorer(body.mapper.grid))
    rng = np.random.default_rng([cfg.seed, job["seed"], CLASS_INDEX[job["label"]]])
    goals: dict[str, int] = {}
    driver.run(search_object(body, job["label"], propose, rng, fallback=fallback, counts=goals))
    obs = body.obs
    # ---- scoring (privileged) ----
    inst = room_instances(transport.state())
    rows = inst[inst[:, 0] == CLASS_INDEX[job["label"]]]
    dist = float(footprint_distance(rows, body.xy[None])[:, 0].min()) if len(rows) else float("inf")
    gt = obs.ground_truth
    seg = gt.instance_seg
    min_px = max(4, int(MIN_VISIBLE_PIXELS * (seg.shape[0] / 256.0) ** 2))
    ids, counts = np.unique(seg[seg >= 0], return_counts=True)
    visible = any(
        gt.objects[k]["type"] == job["label"] and n >= min_px for k, n in zip(ids.tolist(), counts.tolist())
    )
    stopped = obs.last_action == "Done"
    success = bool(stopped and visible and dist <= cfg.radius)
    detected = bool(body.mapper.memory.of_label(job["label"]))  # the detector ever reported the category
    return {
        **job,
        "success": success,
        "stopped": bool(stopped),
        "visible": bool(visible),
        "detected": detected,
        "distance_m": round(dist, 3),
        "steps": int(obs.step),
        "steps_scored": int(obs.step) if success else cfg.max_steps,
        "goals": goals,
        "wall_s": round(time.perf_counter() - t0, 2),
    }


def _worker(args: tuple[dict[str, Any], SearchEvalConfig]) -> dict[str, Any]:
    return _one_episode(*args)


def summarize(records: list[dict[str, Any]], methods: tuple[str, ...]) -> dict[str, Any]:
    out = {}
    for m in methods:
        rs = [r for r in records if r["method"] == m]
        succ = [r for r in rs if r["success"]]
        out[m] = {
            "episodes": len(rs),
            "successes": len(succ),
            "success_pct": round(100.0 * len(succ) / len(rs), 1) if rs else None,
            "mean_steps_all": round(float(np.mean([r["steps_scored"] for r in rs])), 1) if rs else None,
            "mean_steps_successes": round(float(np.mean([r["steps"] for r in succ])), 1) if succ else None,
            "stopped_pct": round(100.0 * sum(r["stopped"] for r in rs) / len(rs), 1) if rs else None,
            "detected_pct": round(100.0 * sum(r.get("detected", False) for r in rs) / len(rs), 1)
            if rs
            else None,
            "goal_sources": _goal_sources(rs),
        }
    return out


def _goal_sources(records: list[dict[str, Any]]) -> dict[str, float]:
    """Share (%) of the search goals walked to that came from the method's proposer, its fallback,
    or a random reachable point (records without ``goals`` are skipped)."""
    total: dict[str, int] = {}
    for r in records:
        for k, n in (r.get("goals") or {}).items():
            total[k] = total.get(k, 0) + int(n)
    n = sum(total.values())
    return {k: round(100.0 * v / n, 1) for k, v in sorted(total.items())} if n else {}


def markdown(result: dict[str, Any]) -> str:
    s = result["summary"]
    lines = [
        f"# Object search ({result['config']['split']} rooms): visual search network vs frontier",
        "",
        f"command: `{result['command']}`",
        "",
        "| method | episodes | success % | mean steps (all, failures = max) | mean steps (successes) |",
        "|---|---|---|---|---|",
    ]
    names = {"network": "visual search network (ours, CPU)", "frontier": "frontier exploration (ours, CPU)"}
    for m, v in s.items():
        lines.append(
            f"| {names[m]} | {v['episodes']} | {v['success_pct']} | {v['mean_steps_all']} | "
            f"{v['mean_steps_successes']} |"
        )
    lines.append(
        f"| paper: TIDEE visual search network | 591 | {PAPER['network']['success_pct']} | "
        f"{PAPER['network']['mean_steps']} | - |"
    )
    lines.append(
        f"| paper: exploration baseline | 591 | {PAPER['frontier']['success_pct']} | "
        f"{PAPER['frontier']['mean_steps']} | - |"
    )
    pairs: dict[tuple, dict[str, bool]] = {}
    for e in result["episodes"]:
        pairs.setdefault((e["room_type"], e["seed"], e["label"]), {})[e["method"]] = e["success"]
    if all(len(v) == 2 for v in pairs.values()) and len(s) == 2:
        n = {
            k: sum(1 for v in pairs.values() if (v["network"], v["frontier"]) == k)
            for k in ((True, True), (True, False), (False, True), (False, False))
        }
        lines += [
            "",
            f"Paired outcomes over {len(pairs)} (room, category) searches: both succeed {n[(True, True)]}, "
            f"network only {n[(True, False)]}, frontier only {n[(False, True)]}, neither {n[(False, False)]}. "
            "Detector reported the category at some point: "
            + ", ".join(f"{m} {v['detected_pct']} %" for m, v in s.items())
            + ".",
        ]
    sources = {m: v.get("goal_sources") for m, v in s.items() if v.get("goal_sources")}
    if sources:
        lines += [
            "",
            "Where the search goals came from (% of goals walked to): "
            + "; ".join(
                f"{m}: " + ", ".join(f"{k} {pct}" for k, pct in src.items()) for m, src in sources.items()
            )
            + f". The network's fallback: {result['config'].get('network_fallback', 'random')}.",
        ]
    c = result["config"]
    lines += [
        "",
        f"Success: the agent says Stop within {c['radius']} m of an instance's footprint with an instance "
        f"of the category in the final frame (ground-truth segmentation, >= {MIN_VISIBLE_PIXELS} px at 256^2), "
        f"within {c['max_steps']} steps. Perception: {c['perception']}. "
        f"Categories per room: {c['categories_per_room'] or 'all'} (seed {c['seed']}). "
        f"Rooms: {result['rooms']} tidy {c['split']} rooms; the paper has 20 AI2-THOR test rooms, 591 episodes.",
        f"Wall time {result['wall_s']} s with {c['workers']} worker(s).",
        "",
        "![heatmaps](search_examples.png)",
        "",
    ]
    return "\n".join(lines)


def save_examples(cfg: SearchEvalConfig, jobs: list[dict[str, Any]], path: Path) -> None:
    """Map + heatmap + ground-truth positions + search points after the initial look-around, on test rooms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tidee.agent.classes import CLASS_INDEX
    from tidee.agent.perception import make_perception
    from tidee.agent.policy.search import SkillDriver
    from tidee.agent.policy.skills import look_around
    from tidee.agent.reasoning.search_net import DEFAULT_WEIGHTS, VisualSearch, room_instances, search_points
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport

    picks = [j for j in jobs if j["method"] == jobs[0]["method"]]
    rng = np.random.default_rng(cfg.seed)
    picks = [
        picks[i] for i in sorted(rng.choice(len(picks), size=min(cfg.examples, len(picks)), replace=False))
    ]
    if not picks:
        return
    vs = VisualSearch.load(cfg.weights or DEFAULT_WEIGHTS)
    fig, axes = plt.subplots(1, len(picks), figsize=(4 * len(picks), 4.2), dpi=90, squeeze=False)
    with InProcessTransport(renderer=TRAINED_RENDERER) as t:
        driver = SkillDriver(t, make_perception(cfg.perception))
        for ax, job in zip(axes[0], picks):
            body = driver.reset(
                EpisodeSpec(
                    room_type=job["room_type"],
                    seed=job["seed"],
                    resolution=cfg.resolution,
                    max_steps=cfg.max_steps,
                )
            )
            driver.run(look_around(body))
            heat = vs.heatmap(body.mapper, job["label"])
            g = body.mapper.voxel_grid
            pts, _ = search_points(heat, g, vs.threshold, 3)
            inst = room_instances(t.state())
            rows = inst[inst[:, 0] == CLASS_INDEX[job["label"]]]
            occ = body.mapper.occupancy.any(axis=2)
            x0, x1, y0, y1 = g.extent
            # image rows = +x (forward, up), columns = -y (left): the agent's view from above
            ext = (-y1, -y0, x0, x1)
            ax.imshow(occ[::-1, ::-1], cmap="gray_r", alpha=0.5, extent=ext)
            ax.imshow(heat[::-1, ::-1], cmap="Reds", alpha=0.6, extent=ext, vmin=0, vmax=1)
            ax.scatter(-rows[:, 2], rows[:, 1], marker="x", c="lime", s=60, label="ground truth")
            ax.scatter(-pts[:, 1], pts[:, 0], c="blue", s=40, label="search points")
            ax.scatter([0], [0], marker="^", c="k", s=40, label="start")
            ax.set_xlim(-4.5, 4.5)
            ax.set_ylim(-4.5, 4.5)
            ax.set_title(f"{job['label']} ({job['room_type']} {job['seed']})", fontsize=9)
            ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_search_eval(cfg: SearchEvalConfig, command: str = "", progress: bool = True) -> dict[str, Any]:
    from tqdm import tqdm

    from tidee.protocol.episode_log import write_json_atomic
    from tidee.threads import threads_per_process, use_threads

    t0 = time.time()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = episodes(cfg)
    records: list[dict[str, Any]] = []
    bar = tqdm(total=len(jobs), desc="search episodes", disable=not progress)
    if cfg.workers > 1 and len(jobs) > 1:
        with cf.ProcessPoolExecutor(
            cfg.workers,
            mp_context=mp.get_context("spawn"),
            initializer=use_threads,
            initargs=(threads_per_process(cfg.workers),),
        ) as pool:
            for rec in pool.map(_worker, [(j, cfg) for j in jobs]):
                records.append(rec)
                bar.update()
    else:
        use_threads(1)  # measured with one thread in process
        for j in jobs:
            records.append(_one_episode(j, cfg))
            bar.update()
    bar.close()
    result = {
        "command": command,
        "config": asdict(cfg),
        "rooms": len({(j["room_type"], j["seed"]) for j in jobs}),
        "summary": summarize(records, cfg.methods),
        "paper": PAPER,
        "episodes": records,
        "wall_s": round(time.time() - t0, 1),
    }
    if "network" in cfg.methods and cfg.examples > 0:
        save_examples(cfg, jobs, out / "search_examples.png")
    write_json_atomic(out / "search.json", result)
    (out / "search.md").write_text(markdown(result))
    return result


# --------------------------------------------------------------------------- CLI
def _methods(text: str) -> tuple[str, ...]:
    ms = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in ms if m not in METHODS]
    if bad or not ms:
        raise argparse.ArgumentTypeError(
            f"methods must be a comma list of {', '.join(METHODS)}; got {text!r}"
        )
    return ms


_count_from_0 = int_at_least(0)


def add_eval_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", default="test", choices=("test", "val"), help="held-out rooms only")
    p.add_argument("--out", required=True, help="directory for search.json, search.md, search_examples.png")
    p.add_argument("--methods", type=_methods, default=METHODS, help="comma list of network, frontier")
    p.add_argument(
        "--categories-per-room",
        type=_count_from_0,
        default=8,
        help="categories sampled per room (seeded); 0: every category present",
    )
    p.add_argument("--max-steps", type=_count_from_0, default=200)
    p.add_argument("--radius", type=float, default=1.5, help="success radius, metres")
    p.add_argument("--perception", default="learned", choices=("learned", "oracle"))
    p.add_argument("--workers", type=int, default=2, choices=(1, 2))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weights", default=None, help="default: agent/weights/search_net.pt")
    p.add_argument("--rooms", type=_count_from_0, default=0, help="first N rooms of the split (0: all)")
    p.add_argument(
        "--explored-discount",
        type=float,
        default=0.0,
        help="network: scale heat by (1 - d * explored) before choosing search points (0: paper)",
    )
    p.add_argument(
        "--network-fallback",
        default="random",
        choices=NETWORK_FALLBACKS,
        help="network: where to go once no search point is left: a random reachable point, or the "
        "nearest frontier",
    )
    p.set_defaults(func=_cmd_eval_search)


def config_from_args(args: argparse.Namespace) -> SearchEvalConfig:
    return SearchEvalConfig(
        out=args.out,
        split=args.split,
        methods=tuple(args.methods),
        categories_per_room=args.categories_per_room or None,
        max_steps=args.max_steps,
        radius=args.radius,
        perception=args.perception,
        workers=args.workers,
        seed=args.seed,
        weights=args.weights,
        rooms=args.rooms or None,
        explored_discount=args.explored_discount,
        network_fallback=args.network_fallback,
    )


def _cmd_eval_search(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    command = (
        f"tidee eval search --split {cfg.split} --methods {','.join(cfg.methods)} "
        f"--categories-per-room {args.categories_per_room} --max-steps {cfg.max_steps} --radius {cfg.radius} "
        f"--perception {cfg.perception} --workers {cfg.workers} --seed {cfg.seed} --out {cfg.out}"
        + (f" --weights {cfg.weights}" if cfg.weights else "")
        + (f" --rooms {cfg.rooms}" if cfg.rooms else "")
        + (f" --explored-discount {cfg.explored_discount}" if cfg.explored_discount else "")
        + (f" --network-fallback {cfg.network_fallback}" if cfg.network_fallback != "random" else "")
    )
    result = run_search_eval(cfg, command=command)
    print(markdown(result))
    return 0


def register(eval_sub: argparse._SubParsersAction) -> None:
    """``tidee eval search`` (Table 2)."""
    p = eval_sub.add_parser(
        "search", help="object search on held-out rooms: search network vs frontier (Table 2)"
    )
    add_eval_arguments(p)


__all__ = ["METHODS", "PAPER", "SearchEvalConfig", "episodes", "register", "run_search_eval", "summarize"]
