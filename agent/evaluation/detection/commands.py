"""The detector evaluations' commands: ``tidee eval detector``, ``tidee eval reclassifier`` and
``tidee eval oop``. Their options are the fields of :mod:`.config`; nothing heavy is imported
until a command runs, so building the command line loads neither torch nor the simulator."""

from __future__ import annotations

import argparse
from pathlib import Path

from tidee.agent.evaluation.detection.config import EvalDetectorConfig, EvalFusionConfig, EvalOopConfig
from tidee.agent.perception import TRAINED_RENDERER
from tidee.options import add_command


def run_eval_detector(cfg: EvalDetectorConfig) -> int:
    from tidee.agent.evaluation.detection import eval as ev

    if cfg.record and cfg.renderer != TRAINED_RENDERER:
        raise SystemExit(
            f"tidee eval detector: --record keeps the manifest's figures on {TRAINED_RENDERER} frames, "
            f"the detector's own; drop --record with --renderer {cfg.renderer}"
        )
    if cfg.record and cfg.peaks != "class-max":
        raise SystemExit(
            f"tidee eval detector: --record keeps the manifest's figures for the agent's decoding "
            f"(class-max); drop --record with --peaks {cfg.peaks}"
        )
    det = ev._load_detector(cfg.weights, cfg.reclassifier)
    r = ev.run_detector_eval(det, cfg)
    if cfg.record:
        mc = r.get("multiclass")
        ev._record_in_manifest(
            det,
            {
                "box_map50": r["map50"],
                "box_map50_95": r["map"],
                **(
                    {"box_map50_multiclass": mc["map50"], "classes_per_peak": mc["classes_per_peak"]}
                    if mc
                    else {}
                ),
                "box_eval": {
                    "command": r["command"],
                    "frames": r["data"]["frames"],
                    "single_frame_ms_median": r["timing"]["single_frame_ms_median"],
                },
            },
        )
    print((Path(cfg.out) / "detector.md").read_text())
    return 0


def _gated_map(report: dict) -> float:
    return next(row["map50"] for row in report["gates"] if row["gate"] == report["gate"])


def run_eval_reclassifier(cfg: EvalFusionConfig) -> int:
    from tidee.agent.evaluation.detection import eval as ev
    from tidee.agent.evaluation.detection.fusion import run_fusion_sweep

    if cfg.record and cfg.split != "val":
        raise SystemExit(
            "tidee eval reclassifier: --record chooses the fusion weights on the validation rooms; "
            "use --split val (the test rooms stay for the final figures)"
        )
    det = ev._load_detector(cfg.weights, cfg.reclassifier)
    r = run_fusion_sweep(det, cfg)
    if cfg.record:
        b = r["best"]
        ev._record_in_manifest(
            det,
            {
                "fusion": {
                    "alpha": b["alpha"],
                    "beta": b["beta"],
                    "val_map50": b["map50"],
                    "val_map50_detector_alone": r["rows"][0]["map50"],
                    **(
                        {"gate": r["gate"], "val_map50_gated": _gated_map(r)} if r["gate"] is not None else {}
                    ),
                    "command": r["command"],
                }
            },
        )
    print((Path(cfg.out) / "fusion.md").read_text())
    return 0


def run_eval_oop(cfg: EvalOopConfig) -> int:
    from tidee.agent.evaluation.detection import eval as ev
    from tidee.agent.evaluation.detection.metrics import VISUAL_ROW

    det = ev._load_detector(cfg.weights, cfg.reclassifier)
    r = ev.run_oop_eval(det, cfg, extra_rows=None if cfg.visual_only else ev._language_rows())
    if cfg.record:
        ev._record_in_manifest(det, {"oop_visual": r["rows"][VISUAL_ROW], "oop_eval_command": r["command"]})
    print((Path(cfg.out) / "oop.md").read_text())
    return 0


def register(eval_sub: argparse._SubParsersAction) -> None:
    """Add ``detector``, ``reclassifier`` and ``oop`` to the ``tidee eval`` subcommands."""
    add_command(
        eval_sub,
        "detector",
        EvalDetectorConfig,
        run_eval_detector,
        "box AP of the learned detector on held-out rooms",
    )
    add_command(
        eval_sub,
        "reclassifier",
        EvalFusionConfig,
        run_eval_reclassifier,
        "box AP of the detector alone and fused with its crop reclassifier "
        "(alpha x beta), to choose the fusion on the validation rooms",
    )
    add_command(
        eval_sub,
        "oop",
        EvalOopConfig,
        run_eval_oop,
        "in/out-of-place AP on messy held-out rooms (paper Table 3)",
    )


__all__ = ["register", "run_eval_detector", "run_eval_oop", "run_eval_reclassifier"]
