"""The placement models' options, each declared once: the rGCN's shape, ``tidee train rgcn``,
``tidee eval placement`` and ``tidee eval ceiling``.

A light module (no torch, no numpy): the command line and the checkpoints read it.
"""

from __future__ import annotations

from dataclasses import dataclass

from tidee import argtypes
from tidee.options import option
from tidee.paths import RUNS_DIR
from tidee.protocol.vocab import HeldOutSplit

DEFAULT_CACHE = RUNS_DIR / "cache" / "rgcn"  # generated rooms (pickles keyed by their seeds)
SURVEY_FIRST_SEED = 10185  # the shipped rGCN trains on training-pool seeds 10000-10184


@dataclass
class RGCNConfig:
    """The network's shape (saved in every checkpoint)."""

    hidden: int = 64
    use_memex: bool = True
    dropout: float = 0.1


@dataclass
class RGCNTrainConfig:
    """How the rGCN is trained (saved in the manifest as ``train_config``)."""

    steps: int = option(3000, "training steps", type=argtypes.positive_int)
    batch_size: int = option(128, "samples per step", type=argtypes.positive_int)
    lr: float = option(2e-3, "peak learning rate (cosine decay to 0)")
    weight_decay: float = option(1e-4, cli=False)
    node_drop: float = option(0.25, cli=False)  # scene nodes left out per sample (augmentation)
    seed: int = option(0, "seed of the weights and of every sampled batch", type=argtypes.non_negative_int)
    train_rooms_per_type: int = option(
        200,
        "training rooms per type (training seeds after the 5 Memex memory rooms)",
        flag="--rooms-per-type",
        type=argtypes.positive_int,
    )
    use_memex: bool = option(True, cli=False)  # the command line sets it with --without-memex
    hidden: int = option(64, cli=False)
    threads: int = option(2, "torch CPU threads (0: torch's default)", type=argtypes.non_negative_int)


@dataclass
class RGCNTrainCommand:
    """``tidee train rgcn``: the training config and where its outputs go."""

    train: RGCNTrainConfig = option(default_factory=RGCNTrainConfig)
    without_memex: bool = option(False, "the WithoutMemex ablation (scene graph only)")
    out: str | None = option(
        None,
        "weights to write (default: agent/weights/rgcn.pt, or rgcn_without_memex.pt)",
        type=argtypes.output_path,
    )
    loss_png: str | None = option(
        None,
        "loss curve (default: docs/models/ for the shipped weights, beside --out otherwise)",
        type=argtypes.output_path,
    )
    cache_dir: str = option(
        str(DEFAULT_CACHE), "generated rooms, reused across runs", type=argtypes.output_path
    )


@dataclass
class PlacementEvalConfig:
    """``tidee eval placement``: rGCN vs WithoutMemex vs CommonMemory on held-out tidy rooms."""

    out: str = option(help="directory for report.json and report.md", type=argtypes.output_path)
    split: HeldOutSplit = option("test", "held-out rooms to score")
    weights: str | None = option(None, "rGCN weights (default: the shipped agent/weights/rgcn.pt)")
    without_memex_weights: str | None = option(
        None,
        "WithoutMemex weights (default: the shipped agent/weights/rgcn_without_memex.pt; "
        "a path that does not exist leaves its row out)",
    )
    cache_dir: str = option(
        str(DEFAULT_CACHE), "generated rooms, reused across runs", type=argtypes.output_path
    )
    record: bool = option(False, "write the metrics into the weights' manifests")


@dataclass
class CeilingConfig:
    """``tidee eval ceiling``: the judge preference a perfect learner of the tidy rooms could reach."""

    report: tuple[str, ...] = option(
        help="a tidy report with TIDEE and CommonMemory episodes (report.json[.gz] or its folder); "
        "repeat for several",
        metavar="REPORT",
        repeat=True,
    )
    out: str = option(help="directory for ceiling.json and ceiling.md", type=argtypes.output_path)
    rooms_per_type: int = option(200, "survey rooms per room type", type=argtypes.positive_int)
    rooms_version: int = option(1, "room generator version of the survey")
    first_seed: int = option(
        SURVEY_FIRST_SEED,
        "first training-pool seed of the survey (another seed gives an independent survey)",
        type=argtypes.non_negative_int,
    )


__all__ = [
    "DEFAULT_CACHE",
    "SURVEY_FIRST_SEED",
    "CeilingConfig",
    "PlacementEvalConfig",
    "RGCNConfig",
    "RGCNTrainCommand",
    "RGCNTrainConfig",
]
