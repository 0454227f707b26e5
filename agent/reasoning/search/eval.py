"""``tidee eval search``: object search on held-out rooms, the paper's Table 2; and the network's
held-out map metrics (cell AP, hit@k), which training reports on its validation rooms.

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

import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from tidee.agent.classes import CLASSES, PICKUPABLE
from tidee.agent.perception import TRAINED_RENDERER
from tidee.agent.reasoning.search.config import SearchEvalConfig
from tidee.agent.reasoning.search.data import footprint_distance, room_instances, target_heat
from tidee.agent.reasoning.search.model import (
    DEFAULT_WEIGHTS,
    OUT_SIZE,
    Z_BINS,
    VisualSearch,
    out_grid,
    search_points,
)

PAPER = {
    "network": {"success_pct": 72.4, "mean_steps": 88.8},
    "frontier": {"success_pct": 64.8, "mean_steps": 100.9},
}
MIN_VISIBLE_PIXELS = 12  # at 256 x 256 (scaled with the resolution)
EPISODES_FILE = "episodes.jsonl"  # in OUT: each episode's record as it ends (--resume reads it)


def episodes(cfg: SearchEvalConfig) -> list[dict[str, Any]]:
    """One job per (room, category, method): categories present in each tidy room, sampled with the seed."""
    from tidee.agent.classes import CLASS_INDEX
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport
    from tidee.protocol.vocab import ROOM_TYPES
    from tidee.server.splits import rooms

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


def _worker_search(cfg: SearchEvalConfig) -> Any:
    """This batch worker's search network for ``cfg`` (weights and discount), loaded once."""
    from tidee.batch import worker_state

    made: dict[Any, Any] = worker_state().setdefault("search", {})
    key = (cfg.weights, cfg.explored_discount)
    if key not in made:
        made[key] = VisualSearch.load(cfg.weights or DEFAULT_WEIGHTS, explored_discount=cfg.explored_discount)
    return made[key]


def _run_one(args: tuple[dict[str, Any], SearchEvalConfig]) -> dict[str, Any]:
    """One search episode (a batch job) in this worker's simulator with its perception and, for
    the network, its search network."""
    from tidee.agent.reasoning.search.data import worker_perception
    from tidee.batch import worker_transport

    job, cfg = args
    state = {"transport": worker_transport(TRAINED_RENDERER), "perception": worker_perception(cfg.perception)}
    if job["method"] == "network":
        state["search"] = _worker_search(cfg)
    return _one_episode(job, cfg, state)


# What picks the episodes or where they run, not how one plays: left out of an episode's key.
_SELECTION = ("out", "methods", "categories_per_room", "rooms", "examples", "workers", "batch")


def _job_key(args: tuple[dict[str, Any], SearchEvalConfig]) -> str:
    from tidee.batch import config_digest

    job, cfg = args
    return f"{job['method']}/{job['room_type']}/{job['seed']}/{job['label']}/{config_digest(cfg, _SELECTION)}"


def _one_episode(job: dict[str, Any], cfg: SearchEvalConfig, w: dict[str, Any]) -> dict[str, Any]:
    from tidee.agent.classes import CLASS_INDEX
    from tidee.agent.navigation.explore import FrontierExplorer
    from tidee.agent.policy.search import SkillDriver, frontier_proposer, search_object
    from tidee.protocol.messages import EpisodeSpec

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
            f"Paired outcomes over {len(pairs)} (room, category) searches: "
            f"both succeed {n[(True, True)]}, network only {n[(True, False)]}, "
            f"frontier only {n[(False, True)]}, neither {n[(False, False)]}. "
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
        f"of the category in the final frame (ground-truth segmentation, >= {MIN_VISIBLE_PIXELS} px "
        f"at 256^2), within {c['max_steps']} steps. Perception: {c['perception']}. "
        f"Categories per room: {c['categories_per_room'] or 'all'} (seed {c['seed']}). "
        f"Rooms: {result['rooms']} tidy {c['split']} rooms; the paper has 20 AI2-THOR test rooms, "
        "591 episodes.",
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
    from tidee.batch import import_ray, init_worker, run_jobs, worker_state
    from tidee.protocol.episode_log import write_json_atomic

    if cfg.batch.backend == "ray":
        import_ray()  # not installed: say how, before any episode
    t0 = time.time()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = episodes(cfg)
    if cfg.workers == 1 and cfg.batch.backend == "local" and "ready" not in worker_state():
        init_worker(None, 1)  # in this process: one thread, as each of 2 workers on 2 cores
    records = run_jobs(
        [(j, cfg) for j in jobs],
        _run_one,
        workers=cfg.workers,
        renderer=TRAINED_RENDERER,
        backend=cfg.batch.backend,
        ray_address=cfg.batch.ray_address,
        progress=progress,
        out_jsonl=out / EPISODES_FILE,
        resume=cfg.batch.resume,
        key=_job_key,
        desc="search episodes",
    )
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


# --------------------------------------------------------------------------- held-out metrics
def _as_eval_set(data: dict[str, Any], idx: Sequence[int]) -> list[dict[str, Any]]:
    return [{"x": data["x"][i], "inst": data["inst"][data["owner"][i]], "seen": data["seen"][i]} for i in idx]


def occupancy_heat(x: np.ndarray) -> np.ndarray:
    """The trivial baseline's [64, 64] heat: class-agnostic clutter (occupancy above the floor band,
    Gaussian-blurred): "objects are where stuff is"."""
    n = len(CLASSES)
    occ = np.asarray(x[n : n + Z_BINS], np.float32)
    if occ.max() > 1:
        occ = occ / 255.0
    clutter = occ.max(axis=0)
    small = clutter.reshape(OUT_SIZE, 2, OUT_SIZE, 2).mean(axis=(1, 3))
    return ndimage.gaussian_filter(small, 1.5)


def _average_precision(score: np.ndarray, positive: np.ndarray) -> float:
    order = np.argsort(-score, kind="stable")
    pos = positive[order]
    if not pos.any():
        return float("nan")
    hits = np.cumsum(pos)
    precision = hits / np.arange(1, len(pos) + 1)
    return float(precision[pos].mean())


def heldout_metrics(
    search: VisualSearch | None, samples: list[dict[str, Any]], k: int = 3, hit_radius: float = 1.0
) -> dict[str, Any]:
    """Per (map, present category): cell AP (targets >= 0.5 positive) and hit@k (one of the top-k
    search points within ``hit_radius`` of an instance footprint), for the network and the
    occupancy baseline; also over the categories not yet in the agent's memory ("unseen")."""
    import torch

    grid = out_grid()
    res: dict[str, dict[str, list[float]]] = {
        m: {"ap": [], "hit": [], "ap_unseen": [], "hit_unseen": []} for m in ("network", "occupancy")
    }
    for s in samples:
        x = np.asarray(s["x"], np.float32)
        if x.max() > 1.0:
            x = x / 255.0
        inst = s["inst"]
        present = np.unique(inst[:, 0]).astype(np.int64)
        targets = target_heat(inst, present)
        heats = {"occupancy": np.repeat(occupancy_heat(x)[None], len(present), 0)}
        if search is not None:
            logits = search.logits_for(x, [CLASSES[c] for c in present])
            heats["network"] = torch.sigmoid(torch.from_numpy(logits)).numpy()
        for j, c in enumerate(present):
            unseen = int(c) not in set(s["seen"])
            rows = inst[inst[:, 0] == c]
            for name, h in heats.items():
                ap = _average_precision(h[j].ravel(), targets[j].ravel() >= 0.5)
                pts, _ = search_points(h[j], grid, threshold=0.5 if name == "network" else np.inf, k=k)
                hit = float(len(pts) > 0 and footprint_distance(rows, pts).min() <= hit_radius)
                res[name]["ap"].append(ap)
                res[name]["hit"].append(hit)
                if unseen:
                    res[name]["ap_unseen"].append(ap)
                    res[name]["hit_unseen"].append(hit)
    out: dict[str, Any] = {"maps": len(samples)}
    for name, r in res.items():
        if search is None and name == "network":
            continue
        out[name] = {f"{m}": round(float(np.nanmean(v)), 4) if v else None for m, v in r.items()}
        out[name]["n"] = len(r["ap"])
        out[name]["n_unseen"] = len(r["ap_unseen"])
    return out


def time_inference(search: VisualSearch, repeats: int = 20) -> dict[str, float]:
    """Median ms of ``heatmap`` on one thread for a fresh (empty) map, input building included."""
    import torch

    from tidee.agent.mapping.maps import SemanticMapper

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mapper = SemanticMapper(classes=CLASSES, passable=PICKUPABLE)
        search.heatmap(mapper, CLASSES[0])
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            search.heatmap(mapper, CLASSES[0])
            ts.append((time.perf_counter() - t0) * 1e3)
    finally:
        torch.set_num_threads(threads)
    return {"heatmap_ms_median": round(float(np.median(ts)), 1), "threads": 1}


__all__ = [
    "MIN_VISIBLE_PIXELS",
    "PAPER",
    "episodes",
    "heldout_metrics",
    "markdown",
    "occupancy_heat",
    "run_search_eval",
    "summarize",
    "time_inference",
]
