"""The detector's options, each declared once: the network's shape (``DetectorConfig``), its
training data (``tidee gen detection``: ``GenConfig``, ``GenDetectionConfig``) and its training
(``tidee train detector``: ``TrainConfig``, ``TrainDetectorConfig``).

A light module (no torch, no PyBullet): the command line builds its flags from these fields
(``tidee.options``). Path options default to None: a location in the checkout
(``tidee.paths``), never the working directory.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from tidee import argtypes
from tidee.agent.learning import WEIGHTS_DIR
from tidee.agent.perception import DETECTOR_SETS, DETECTORS, TRAINED_RENDERER
from tidee.batch import BatchConfig
from tidee.options import option
from tidee.paths import PROJECT_DIR, RUNS_DIR
from tidee.protocol.vocab import ROOM_TYPES, Renderer, RoomType, Split
from tidee.server.splits import SPLIT_SEEDS, TRAIN_POOL

DEFAULT_WEIGHTS = WEIGHTS_DIR / DETECTORS[DETECTOR_SETS[0]][0]
DATA_DIR = PROJECT_DIR / "data"  # `tidee gen detection` output folders: data/detection, data/detection_d, ...
DEFAULT_DATA = DATA_DIR / "detection"

# Training precision: bf16 autocast + channels-last where the CPU or GPU has it, fp32 otherwise.
Precision = Literal["auto", "fp32", "bf16"]


@dataclass
class DetectorConfig:
    """The network's shape (kept in its weights file)."""

    num_classes: int = 92
    widths: tuple[int, ...] = (16, 32, 64, 96, 128)  # stride 2, 4, 8, 16, 32
    neck: int = 64
    stride: int = 4
    input_size: int = 256
    use_depth: bool = True
    # grown capacity (``tidee train detector --init``): extra residual blocks at stride 8, 16,
    # 32 (``extra_blocks``) and 4 (``extra_s4``), and a depthwise-separable conv before the
    # heads. Each starts as the identity, so a grown model computes exactly what the weights it
    # was initialised from computed.
    extra_blocks: tuple[int, int, int] = (0, 0, 0)
    head_conv: bool = False
    extra_s4: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> DetectorConfig:
        d = dict(d)
        d["widths"] = tuple(d["widths"])
        d["extra_blocks"] = tuple(d.get("extra_blocks", (0, 0, 0)))
        return DetectorConfig(**d)


def room_seeds(split: str, rooms_per_type: int, skip: int = 0) -> list[int]:
    """The room seeds of ``split`` in the order the generators visit them (train: seeds 0-19,
    then the pool 10000...), ``rooms_per_type`` of them after skipping ``skip``."""
    if split == "train":
        seeds = list(SPLIT_SEEDS["train"]) + list(TRAIN_POOL)
    elif split in SPLIT_SEEDS:
        seeds = list(SPLIT_SEEDS[split])
    else:
        raise ValueError(f"split must be train, val or test, got {split!r}")
    if skip < 0 or not 1 <= rooms_per_type <= len(seeds) - skip:
        raise ValueError(
            f"{split} has {len(seeds)} rooms per type; asked for {rooms_per_type} after skipping {skip}"
        )
    return seeds[skip : skip + rooms_per_type]


@dataclass
class GenConfig:
    """Which frames the generator renders: ``tidee gen detection`` (training rooms) and the
    evaluations' held-out frames (``split`` val or test, never written next to training data)."""

    split: Split = option("train", "train (train seeds + pool) or test (evaluation only)", cli=False)
    rooms_per_type: int = option(
        60, "training rooms per type: seeds 0-19, then the pool", type=argtypes.positive_int
    )
    skip_rooms: int = option(
        0,
        "start after this many rooms per type (e.g. 60: rooms the shipped detector never saw)",
        type=argtypes.non_negative_int,
    )
    messes_per_room: int = option(
        2,
        "messy configurations per room (plus the tidy one)",
        flag="--messes",
        type=argtypes.non_negative_int,
    )
    walks_per_config: int = option(
        2, "random walks per configuration", flag="--walks", type=argtypes.positive_int
    )
    frames_per_walk: int = option(6, "frames kept per walk", type=argtypes.positive_int)
    stride: int = option(3, "keep every stride-th step of a walk", cli=False)
    resolution: int = option(256, "frame side in pixels", type=argtypes.resolution)
    seed: int = option(0, "seed of the walks", type=argtypes.non_negative_int)
    shard_size: int = option(
        256, "at most this many frames per shard file (whole configurations)", type=argtypes.positive_int
    )
    room_types: tuple[RoomType, ...] = option(ROOM_TYPES, cli=False)
    oop_views_only: bool = option(
        False, "keep only messy frames with an out-of-place object in view", cli=False
    )
    per_config: int | None = option(None, "stop a configuration once it has this many frames", cli=False)
    tidy: bool = option(True, "include the tidy configuration of each room", cli=False)
    renderer: Renderer = option(
        TRAINED_RENDERER,
        f"who draws the frames ({TRAINED_RENDERER}: what the shipped detector was trained on; egl, to "
        "train one for both renderers)",
    )
    extra: dict[str, Any] = option(default_factory=dict, cli=False)


@dataclass(kw_only=True)
class GenDetectionConfig:
    """``tidee gen detection``: RGB-D frames + instance targets from random walks in training rooms."""

    out: str | None = option(
        None, "directory of shards (default: data/detection in the checkout)", type=argtypes.output_path
    )
    gen: GenConfig = option(default_factory=GenConfig)
    workers: int = option(
        2, "worker processes (local) or Ray actors that render frames", type=argtypes.positive_int
    )
    batch: BatchConfig = option(default_factory=BatchConfig)

    @property
    def out_dir(self) -> Path:
        return Path(self.out) if self.out is not None else DEFAULT_DATA


@dataclass
class TrainConfig:
    """How the detector trains (recorded in its manifest's ``train_config``)."""

    data: str | None = option(
        None,
        "directory of `tidee gen detection` shards, or several, comma-separated (different rooms); "
        "default: data/detection in the checkout",
    )
    out: str | None = option(
        None,
        "shipped weights (+ .json manifest); default: agent/weights/detector.pt",
        type=argtypes.output_path,
    )
    work_dir: str | None = option(
        None,
        "checkpoints and the loss curve (resumable); default: runs/detector in the checkout",
        type=argtypes.output_path,
    )
    steps: int = option(5500, "training steps", type=argtypes.positive_int)
    batch_size: int = option(16, "frames per step", type=argtypes.positive_int)
    lr: float = option(2e-3, "peak learning rate")
    weight_decay: float = option(1e-4, cli=False)
    warmup: int = option(200, "steps of linear learning-rate warm-up", type=argtypes.non_negative_int)
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
    init: str | None = option(
        None,
        "start from these detector weights; with --extra-blocks / --head-conv the model grows "
        "around them, starting as exactly the same function",
    )
    precision: Precision = option(
        "auto",
        "bf16 autocast + channels-last (about 2x faster on a CPU with AVX512-BF16); "
        "auto: bf16 where the CPU or GPU supports it, fp32 otherwise",
    )
    loader_workers: int = option(
        0,
        "build batches in this many processes (a GPU outruns one); a run is reproducible "
        "for a given count. 0: in the training process",
        type=argtypes.non_negative_int,
    )

    @property
    def data_spec(self) -> str:
        return self.data if self.data is not None else str(DEFAULT_DATA)

    @property
    def out_path(self) -> str:
        return self.out if self.out is not None else str(DEFAULT_WEIGHTS)

    @property
    def work_path(self) -> Path:
        return Path(self.work_dir) if self.work_dir is not None else RUNS_DIR / "detector"

    def resolved(self) -> TrainConfig:
        """A copy with the default paths filled in (data/detection, agent/weights/detector.pt,
        runs/detector in the checkout), as the manifest records them."""
        return dataclasses.replace(self, data=self.data_spec, out=self.out_path, work_dir=str(self.work_path))


@dataclass
class TrainDetectorConfig:
    """``tidee train detector``: the RGB-D detector with its OOP head, on `tidee gen detection` data."""

    train: TrainConfig = option(default_factory=TrainConfig)
    extra_blocks: tuple[int, ...] = option(
        (0, 0, 0),
        "extra residual blocks at stride 8,16,32, or 4,8,16,32 (identity at start)",
        type=argtypes.non_negative_int,
    )
    head_conv: bool = option(False, "a depthwise-separable conv before the heads (identity at start)")
    no_resume: bool = option(False, "ignore a checkpoint in --work-dir")

    def __post_init__(self) -> None:
        self.extra_blocks = tuple(self.extra_blocks)
        if len(self.extra_blocks) not in (3, 4) or min(self.extra_blocks) < 0:
            raise ValueError(
                "--extra-blocks wants three non-negative integers (stride 8, 16, 32) or four "
                f"(stride 4, 8, 16, 32), not {','.join(map(str, self.extra_blocks))!r}"
            )

    def model_config(self) -> DetectorConfig:
        """The network these options build (the first of four --extra-blocks is at stride 4)."""
        e = self.extra_blocks
        extra_s4, extra = (e[0], e[1:]) if len(e) == 4 else (0, e)
        return DetectorConfig(
            extra_blocks=(extra[0], extra[1], extra[2]), head_conv=self.head_conv, extra_s4=extra_s4
        )


__all__ = [
    "WEIGHTS_DIR",
    "DATA_DIR",
    "DEFAULT_DATA",
    "DEFAULT_WEIGHTS",
    "DetectorConfig",
    "GenConfig",
    "GenDetectionConfig",
    "Precision",
    "TrainConfig",
    "TrainDetectorConfig",
    "room_seeds",
]
