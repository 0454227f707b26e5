"""The depth network's options, each declared once: ``tidee train depth`` (``DepthTrainConfig``)
and ``tidee eval depth`` (``DepthEvalConfig``), with the held-out frames both score
(``EvalSet``).

A light module (no torch): the command line builds its flags from these fields
(``tidee.options``). Path options default to None: a location in the checkout, never the
working directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tidee import argtypes
from tidee.agent.perception.detector.config import DEFAULT_DATA, WEIGHTS_DIR, Precision
from tidee.options import option
from tidee.paths import PROJECT_DIR, RUNS_DIR
from tidee.protocol.vocab import HeldOutSplit

DEFAULT_WEIGHTS = WEIGHTS_DIR / "depth.pt"
DOCS_LOSS_PNG = PROJECT_DIR / "docs" / "models" / "depth_loss.png"


@dataclass(frozen=True)
class EvalSet:
    """The held-out frames a depth model is scored on (training's final eval and ``tidee eval depth``)."""

    rooms_per_type: int = option(5, "held-out rooms per type", type=argtypes.positive_int)
    messes: int = option(
        1, "messy configurations per room (plus the tidy one)", type=argtypes.non_negative_int
    )
    frames_per_walk: int = option(5, "frames kept per walk", type=argtypes.positive_int)
    seed: int = option(7, cli=False)


@dataclass
class DepthTrainConfig:
    """``tidee train depth``: the depth-from-RGB network (the '+est. depth' setting)."""

    data: str | None = option(
        None,
        "frames from `tidee gen detection`: one directory or several, comma-separated, holding "
        "different rooms (default: data/detection in the checkout)",
    )
    out: str | None = option(
        None,
        "weights file, default agent/weights/depth.pt (its manifest .json goes beside it)",
        type=argtypes.output_path,
    )
    # the shipped weights' options (agent/weights/depth.json, which also names their data)
    steps: int = option(8000, "training steps", type=argtypes.positive_int)
    batch_size: int = option(16, "frames per step", type=argtypes.positive_int)
    lr: float = option(2e-3, "peak learning rate")
    seed: int = option(
        0, "seed of the initial weights, the batches and the augmentation", type=argtypes.non_negative_int
    )
    device: str = option("auto", "auto | cpu | cuda")
    precision: Precision = option(
        "auto",
        "bf16 autocast (faster on a CPU with AVX512-BF16); auto: bf16 where the CPU or GPU "
        "supports it, fp32 otherwise",
    )
    work_dir: str | None = option(
        None, "checkpoint and loss curve (default: runs/depth in the checkout)", type=argtypes.output_path
    )
    resume: bool = option(False, "continue from the checkpoint in --work-dir")
    checkpoint_every: int = option(100, "steps between checkpoints", type=argtypes.positive_int)
    log_every: int = option(10, cli=False)
    widths: tuple[int, ...] = option(
        (16, 24, 48, 96), "channels of the four encoder stages (1/2 to 1/16), comma-separated"
    )
    context: bool = option(True, "a global context vector at 1/16 (DepthNet's context branch)")
    # scored at the end of training (held-out test rooms); None skips it
    eval_set: EvalSet | None = option(default_factory=EvalSet, cli=False)

    @property
    def data_spec(self) -> str:
        return self.data if self.data is not None else str(DEFAULT_DATA)

    @property
    def out_path(self) -> Path:
        return Path(self.out) if self.out is not None else DEFAULT_WEIGHTS

    @property
    def work_path(self) -> Path:
        return Path(self.work_dir) if self.work_dir is not None else RUNS_DIR / "depth"


@dataclass(kw_only=True)
class DepthEvalConfig:
    """``tidee eval depth``: the depth network on held-out rooms: abs rel, RMSE, delta<1.25."""

    split: HeldOutSplit = option("test", "test or val (held-out rooms only)")
    weights: str | None = option(None, "default: agent/weights/depth.pt")
    eval_set: EvalSet = option(default_factory=EvalSet)
    out: str = option(
        help="directory for depth.json, depth.md, depth_examples.png", type=argtypes.output_path
    )

    @property
    def weights_path(self) -> Path:
        return Path(self.weights) if self.weights else DEFAULT_WEIGHTS


__all__ = ["DEFAULT_WEIGHTS", "DOCS_LOSS_PNG", "DepthEvalConfig", "DepthTrainConfig", "EvalSet"]
