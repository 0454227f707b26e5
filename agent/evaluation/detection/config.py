"""The detector evaluations' options, each declared once: ``tidee eval detector``
(``EvalDetectorConfig``), ``tidee eval reclassifier`` (``EvalFusionConfig``) and ``tidee eval
oop`` (``EvalOopConfig``).

A light module (no torch, no numpy, no scipy): the command line builds its flags from these
fields (``tidee.options``).
"""

from __future__ import annotations

from dataclasses import dataclass

from tidee import argtypes
from tidee.agent.perception import TRAINED_RENDERER, PeakMode
from tidee.options import option
from tidee.protocol.vocab import HELD_OUT_SPLITS, HeldOutSplit, Renderer

EVAL_THRESHOLD = 0.05  # AP integrates over the whole precision/recall curve: keep low-score detections
SECOND_GUESSES = 3  # classes per heatmap peak in the report's second mAP (see run_detector_eval)
FUSION_ALPHAS: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0)
FUSION_BETAS: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0)
# A gate costs at most this much val mAP@0.5 (0.2 points) for the crops it saves.
GATE_TOLERANCE = 0.002

RECLASSIFIER_HELP = (
    "the crop classifier that renames detections: default (the shipped one when it is there), "
    "none (the detector's own classes), or a weights path"
)
WEIGHTS_HELP = "detector weights (default: the installed ones)"
OUT_HELP = "directory for the report (.json, .md and an example grid)"


def held_out_split(value: str) -> str:
    """--split: the detector is scored on held-out rooms only."""
    if value not in HELD_OUT_SPLITS:
        raise ValueError(
            f"{value!r}: the detector is evaluated on held-out rooms only; use --split test (or val)"
        )
    return value


@dataclass(kw_only=True)
class EvalDetectorConfig:
    """``tidee eval detector``: box AP of the learned detector on held-out rooms."""

    split: HeldOutSplit = option(
        "test", "test (default) or val", type=held_out_split, choices=HELD_OUT_SPLITS
    )
    out: str = option(help=OUT_HELP, type=argtypes.output_path)
    weights: str | None = option(None, WEIGHTS_HELP)
    rooms_per_type: int = option(5, "held-out rooms per type", type=argtypes.positive_int)
    messes: int = option(
        2, "messy configurations per room (plus the tidy one)", type=argtypes.non_negative_int
    )
    walks: int = option(1, "random walks per configuration", type=argtypes.positive_int)
    frames_per_walk: int = option(5, "frames kept per walk", type=argtypes.positive_int)
    seed: int = option(7, "seed of the walks", type=argtypes.non_negative_int)
    batch: int = option(16, "frames per detect_batch call", type=argtypes.positive_int)
    record: bool = option(False, "merge the metrics into the weights' manifest")
    classes_per_peak: int = option(
        SECOND_GUESSES,
        "also report mAP with this many best classes per heatmap peak (1: skip)",
        type=argtypes.positive_int,
    )
    renderer: Renderer = option(
        TRAINED_RENDERER,
        f"who draws the test frames (default {TRAINED_RENDERER}: what the detector was trained on)",
    )
    peaks: PeakMode = option(
        "class-max",
        "how heatmap peaks become detections (default class-max: the agent's; the others are "
        "an ablation, see detector.model.decode)",
    )
    reclassifier: str = option("default", RECLASSIFIER_HELP)


@dataclass(kw_only=True)
class EvalFusionConfig:
    """``tidee eval reclassifier``: box AP of the detector alone and fused with its crop
    reclassifier (alpha x beta), to choose the fusion on the validation rooms."""

    split: HeldOutSplit = option(
        "val",
        "val (default: where the fusion is chosen) or test",
        type=held_out_split,
        choices=HELD_OUT_SPLITS,
    )
    out: str = option(help=OUT_HELP, type=argtypes.output_path)
    weights: str | None = option(None, WEIGHTS_HELP)
    reclassifier: str = option("default", RECLASSIFIER_HELP)
    rooms_per_type: int = option(5, "held-out rooms per type", type=argtypes.positive_int)
    messes: int = option(
        2, "messy configurations per room (plus the tidy one)", type=argtypes.non_negative_int
    )
    walks: int = option(1, "random walks per configuration", type=argtypes.positive_int)
    frames_per_walk: int = option(5, "frames kept per walk", type=argtypes.positive_int)
    seed: int = option(7, "seed of the walks", type=argtypes.non_negative_int)
    batch: int = option(16, "frames per detect_batch call", type=argtypes.positive_int)
    alphas: tuple[float, ...] = option(
        FUSION_ALPHAS, "weights of the detector's class scores to try (comma-separated)"
    )
    betas: tuple[float, ...] = option(
        FUSION_BETAS, "exponents of the crop's class probability in the score to try (comma-separated)"
    )
    gates: tuple[float, ...] = option(
        (),
        "detector scores at and above which a detection skips the crop classifier, each tried "
        "at the best fusion (comma-separated; none: every detection is reclassified)",
    )
    gate_tolerance: float = option(
        GATE_TOLERANCE,
        "the chosen gate is the lowest whose mAP@0.5 is within this of the ungated best's",
        type=argtypes.non_negative_float,
    )
    record: bool = option(
        False, "write the best fusion (and the chosen gate) into the reclassifier's manifest"
    )


@dataclass(kw_only=True)
class EvalOopConfig:
    """``tidee eval oop``: in/out-of-place AP on messy held-out rooms (paper Table 3)."""

    split: HeldOutSplit = option(
        "test", "test (default) or val", type=held_out_split, choices=HELD_OUT_SPLITS
    )
    out: str = option(help=OUT_HELP, type=argtypes.output_path)
    weights: str | None = option(None, WEIGHTS_HELP)
    views: int = option(20, "views per messy configuration (paper: 20)", type=argtypes.positive_int)
    rooms_per_type: int = option(5, "held-out rooms per type", type=argtypes.positive_int)
    messes: int = option(5, "messy configurations per room (test has 5)", type=argtypes.non_negative_int)
    walks: int | None = option(
        None,
        "random walks per configuration to find the views (default: enough for 2 x --views)",
        type=argtypes.positive_int,
    )
    frames_per_walk: int = option(5, "frames kept per walk", cli=False)
    seed: int = option(11, "seed of the walks", type=argtypes.non_negative_int)
    batch: int = option(16, "frames per detect_batch call", type=argtypes.positive_int)
    record: bool = option(False, "merge the visual row into the weights' manifest")
    visual_only: bool = option(False, "skip the language, fused and oracle-language rows")
    reclassifier: str = option("default", RECLASSIFIER_HELP)


__all__ = [
    "EVAL_THRESHOLD",
    "FUSION_ALPHAS",
    "FUSION_BETAS",
    "SECOND_GUESSES",
    "EvalDetectorConfig",
    "EvalFusionConfig",
    "EvalOopConfig",
    "held_out_split",
]
