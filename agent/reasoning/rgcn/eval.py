"""``tidee eval placement``: rGCN (TIDEE), WithoutMemex and CommonMemory on the tidy rooms of a
held-out split; the simulated judge scores the receptacle each would choose."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tidee.agent.classes import CLASSES
from tidee.agent.reasoning.rgcn.config import PlacementEvalConfig
from tidee.agent.reasoning.rgcn.data import RoomSamples, heldout_rooms
from tidee.agent.reasoning.rgcn.memex import PLACE_CLASSES
from tidee.agent.reasoning.rgcn.model import (
    DEFAULT_WEIGHTS,
    DEFAULT_WITHOUT_MEMEX,
    PlacementRGCN,
    collate,
    load_rgcn,
)
from tidee.protocol.vocab import ROOM_TYPES


def rank_rooms(model: PlacementRGCN, rooms: Sequence[RoomSamples], batch: int = 256) -> list[np.ndarray]:
    """Probabilities (S x K) for every sample of every room (the object taken out, no augmentation)."""
    model.eval()
    out = []
    with torch.no_grad():
        for room in rooms:
            items = [(room.graph, int(t), None, ROOM_TYPES.index(room.room_type)) for t in room.targets]
            probs = [
                torch.softmax(model(collate(items[i : i + batch])), dim=1).numpy()
                for i in range(0, len(items), batch)
            ]
            out.append(np.concatenate(probs) if probs else np.zeros((0, len(PLACE_CLASSES)), np.float32))
    return out


def _choice(ranked: Sequence[str], present: Sequence[str]) -> str | None:
    """The receptacle the policy would go to with a complete map: the first ranked one in the room."""
    have = set(present) | {"Floor"}
    return next((r for r in ranked if r in have), None)


def evaluate_placement(rooms: Sequence[RoomSamples], rankers: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Per ranker: top-1 / top-3 accuracy against the receptacle each object had in the tidy
    held-out room, and the simulated judge's score (and plausible rate) of the receptacle the
    policy would choose. ``rankers``: name -> PlacementRGCN or a function
    (room, sample index) -> ranked receptacle names."""
    from tidee.agent.evaluation.judge import judge_score, plausible

    out: dict[str, dict[str, float]] = {}
    for name, ranker in rankers.items():
        if isinstance(ranker, PlacementRGCN):
            probs = rank_rooms(ranker, rooms)
            ranked_of = lambda r, k, probs=probs: [
                PLACE_CLASSES[i] for i in np.argsort(-probs[r][k], kind="stable")
            ]
        else:
            ranked_of = ranker
        top1 = top3 = judge = ok = n = 0.0
        for r, room in enumerate(rooms):
            for k in range(len(room.targets)):
                ranked = ranked_of(r, k)
                truth = PLACE_CLASSES[int(room.labels[k])]
                top1 += ranked[:1] == [truth]
                top3 += truth in ranked[:3]
                cat = CLASSES[int(room.graph.labels[int(room.targets[k])])]
                choice = _choice(ranked, room.present)
                judge += judge_score(cat, room.variants[k], room.room_type, choice, room.present)
                ok += plausible(cat, room.variants[k], room.room_type, choice, room.present)
                n += 1
        out[name] = {
            "top1": top1 / max(n, 1),
            "top3": top3 / max(n, 1),
            "judge_score": judge / max(n, 1),
            "plausible": ok / max(n, 1),
            "samples": int(n),
        }
    return out


def run_placement_eval(
    cfg: PlacementEvalConfig, command: str = "tidee eval placement", progress: bool = True
) -> dict[str, Any]:
    """``tidee eval placement``: rGCN (TIDEE), WithoutMemex and CommonMemory on the tidy rooms of
    a held-out split; JSON + Markdown in ``cfg.out``. Weights left None are the shipped ones."""
    from tidee.agent.learning import update_manifest_metrics
    from tidee.agent.reasoning.stats import PlacementStats
    from tidee.protocol.episode_log import write_json_atomic

    split = cfg.split
    weights = cfg.weights or DEFAULT_WEIGHTS
    without_memex = cfg.without_memex_weights or DEFAULT_WITHOUT_MEMEX
    rooms = heldout_rooms(split, cfg.cache_dir, progress)
    stats = PlacementStats.load()
    names = {r: i for i, r in enumerate(PLACE_CLASSES)}

    def common(r: int, k: int) -> list[str]:
        cat = CLASSES[int(rooms[r].graph.labels[int(rooms[r].targets[k])])]
        return [c for c, _ in stats.ranked(cat) if c in names]

    rankers: dict[str, Any] = {"TIDEE (Memex + rGCN)": load_rgcn(weights)[0]}
    if Path(without_memex).exists():
        rankers["WithoutMemex (scene rGCN)"] = load_rgcn(without_memex)[0]
    rankers["CommonMemory"] = common
    result = evaluate_placement(rooms, rankers)
    report = {
        "command": command,
        "split": split,
        "rooms": len(rooms),
        "samples": next(iter(result.values()))["samples"],
        "rows": result,
        "note": "Scene graphs from the simulator's boxes made axis-aligned (a complete map); one sample "
        "per pickupable object of each tidy room, taken out of its graph. top-1/top-3: the "
        "receptacle type it had; judge: the simulated judge's score of the first ranked "
        "receptacle present in the room (what the policy would choose).",
    }
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "report.json", report)
    lines = [
        f"# Placement: where does an object belong? ({split} rooms)",
        "",
        f"`{command}` — {len(rooms)} tidy rooms, {report['samples']} objects.",
        "",
        "| ranker | top-1 | top-3 | judge score | plausible |",
        "|---|---|---|---|---|",
    ]
    for name, m in result.items():
        lines.append(
            f"| {name} | {100 * m['top1']:.1f} | {100 * m['top3']:.1f} | {m['judge_score']:.3f} | "
            f"{100 * m['plausible']:.1f} |"
        )
    lines += ["", report["note"], ""]
    (out / "report.md").write_text("\n".join(lines))
    if cfg.record:
        for name, path in (("TIDEE (Memex + rGCN)", weights), ("WithoutMemex (scene rGCN)", without_memex)):
            if name in result:
                update_manifest_metrics(
                    path,
                    {
                        f"{split}_{k}": round(v, 4) if isinstance(v, float) else v
                        for k, v in result[name].items()
                    },
                )
    return report


__all__ = ["evaluate_placement", "rank_rooms", "run_placement_eval"]
