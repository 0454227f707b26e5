"""The crop reclassifier's options, each declared once: the network's shape
(``ReclassifierConfig``) and its training (``tidee train reclassifier``:
``ReclassifierTrainConfig``, ``TrainReclassifierConfig``).

A light module (no torch): the command line builds its flags from these fields
(``tidee.options``). Path options default to None: a location in the checkout, never the
working directory.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, get_args

from tidee import argtypes
from tidee.agent.perception import DETECTOR_SETS, DETECTORS
from tidee.agent.perception.detector.config import DATA_DIR, WEIGHTS_DIR, Precision
from tidee.options import option
from tidee.paths import RUNS_DIR

DEFAULT_RECLASSIFIER = WEIGHTS_DIR / DETECTORS[DETECTOR_SETS[0]][1]
DEFAULT_DATA = DATA_DIR / "detection_d"

# Where the training boxes come from: jittered ground-truth boxes, or the detector's own detections.
BoxSource = Literal["jitter", "detector"]
BOX_SOURCES: tuple[BoxSource, ...] = get_args(BoxSource)


@dataclass
class ReclassifierConfig:
    """The network's shape (kept in its weights file)."""

    num_classes: int = 92  # + 1 output: background
    crop: int = 40  # crop side in pixels
    context: float = 1.2  # the crop covers the box grown by this factor
    widths: tuple[int, int, int] = (32, 64, 128)
    hidden: int = 128
    det_inputs: bool = False  # also read the detector's class logits and score (det_features)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> ReclassifierConfig:
        d = dict(d)
        d["widths"] = tuple(d["widths"])
        return ReclassifierConfig(**d)


@dataclass
class ReclassifierTrainConfig:
    """How the reclassifier trains (recorded in its manifest's ``train_config``)."""

    data: str | None = option(
        None,
        "comma-separated `tidee gen detection` directories (default: data/detection_d in the checkout)",
    )
    out: str | None = option(
        None,
        "shipped weights (+ .json manifest); default: agent/weights/reclassifier.pt",
        type=argtypes.output_path,
    )
    work_dir: str | None = option(
        None,
        "checkpoints and the loss curve (resumable); default: runs/reclassifier in the checkout",
        type=argtypes.output_path,
    )
    steps: int = option(3000, "training steps", type=argtypes.positive_int)
    batch_size: int = option(256, "crops per step", type=argtypes.positive_int)
    frames_per_batch: int = option(32, cli=False)
    background: float = option(
        0.2, "share of each batch drawn as background boxes", type=argtypes.non_negative_float
    )
    lr: float = option(2e-3, "peak learning rate")
    weight_decay: float = option(1e-4, cli=False)
    warmup: int = option(100, cli=False)
    seed: int = option(
        0, "seed of the initial weights, the batches and the augmentation", type=argtypes.non_negative_int
    )
    device: str = option("auto", "auto | cpu | cuda")
    threads: int = option(0, "CPU threads (0: torch's default)", type=argtypes.non_negative_int)
    ckpt_every: int = option(200, cli=False)
    log_every: int = option(20, cli=False)
    limit_frames: int | None = option(
        None, "train on the first N frames only (smoke runs)", type=argtypes.positive_int
    )
    precision: Precision = option("auto", "auto: bf16 autocast where the CPU or GPU has it")
    boxes: BoxSource = option(
        "jitter",
        "jitter: jittered ground-truth boxes; detector: the detector's own detections on the "
        "frames, and the network also reads the detector's class logits (a learned fusion)",
    )
    detector: str | None = option(
        None, "--boxes detector: the detector's weights (default: the shipped ones)"
    )
    init: str | None = option(None, "start from these reclassifier weights (same crop network)")

    @property
    def data_spec(self) -> str:
        return self.data if self.data is not None else str(DEFAULT_DATA)

    @property
    def out_path(self) -> str:
        return self.out if self.out is not None else str(DEFAULT_RECLASSIFIER)

    @property
    def work_path(self) -> Path:
        return Path(self.work_dir) if self.work_dir is not None else RUNS_DIR / "reclassifier"

    def resolved(self) -> ReclassifierTrainConfig:
        """A copy with the default paths filled in (data/detection_d, agent/weights/reclassifier.pt,
        runs/reclassifier in the checkout), as the manifest records them."""
        return dataclasses.replace(self, data=self.data_spec, out=self.out_path, work_dir=str(self.work_path))


@dataclass
class TrainReclassifierConfig:
    """``tidee train reclassifier``: the crop classifier that renames the detector's detections,
    on `tidee gen detection` data."""

    train: ReclassifierTrainConfig = option(default_factory=ReclassifierTrainConfig)
    crop: int = option(40, "crop side in pixels", type=argtypes.positive_int)
    no_resume: bool = option(False, "ignore a checkpoint in --work-dir")

    def model_config(self) -> ReclassifierConfig:
        return ReclassifierConfig(crop=self.crop)


__all__ = [
    "BOX_SOURCES",
    "BoxSource",
    "DEFAULT_DATA",
    "DEFAULT_RECLASSIFIER",
    "ReclassifierConfig",
    "ReclassifierTrainConfig",
    "TrainReclassifierConfig",
]
