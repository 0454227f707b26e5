"""The visual search network's options, each declared once: ``tidee gen search``,
``tidee train search`` and ``tidee eval search`` (the paper's Table 2).

A light module (no torch, no scipy): the command line reads it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, TypeAlias, get_args

from tidee import argtypes
from tidee.agent.config import EXPLORERS, PERCEPTIONS, Explorer, PerceptionMode
from tidee.batch import BatchConfig
from tidee.options import option
from tidee.paths import PROJECT_DIR, RUNS_DIR
from tidee.protocol.vocab import HELD_OUT_SPLITS, ROOM_TYPES, SPLITS, HeldOutSplit, RoomType, Split

DEFAULT_DATA = PROJECT_DIR / "data" / "search"  # `tidee gen search` writes here, `train search` reads
# Where a search goes next: the network's ranked search points, or the nearest frontier (Yamauchi).
SearchMethod = Literal["network", "frontier"]
METHODS: tuple[SearchMethod, ...] = get_args(SearchMethod)
# The network's next goal once no search point is left: a random reachable point, or the nearest
# frontier: the agent's two explorers.
NetworkFallback: TypeAlias = Explorer
NETWORK_FALLBACKS: tuple[NetworkFallback, ...] = EXPLORERS


def count_or_all(text: str) -> int | None:
    """A count >= 0, where 0 means "all" (None)."""
    return argtypes.non_negative_int(text) or None


@dataclass
class SearchGenConfig:
    """``tidee gen search``: map snapshots of explored rooms + ground-truth object positions."""

    out: str = option(
        str(DEFAULT_DATA), "directory for the shards and manifest.json", type=argtypes.output_path
    )
    split: Split = option("train", "train for training data; val/test only for held-out evaluation sets")
    rooms_per_type: int = option(
        25, "train: seeds 0-19 first, then the training pool", type=argtypes.positive_int
    )
    messes_per_room: int = option(
        1,
        "messy configurations per room besides the tidy one",
        flag="--messes",
        type=argtypes.non_negative_int,
    )
    snapshots: int = option(6, "map snapshots per configuration", type=argtypes.positive_int)
    max_steps: int = option(200, "exploration steps per configuration", type=argtypes.positive_int)
    perception: PerceptionMode = option(
        "oracle", "detections that build the maps (oracle: the simulator's segmentation, cheaper)"
    )
    resolution: int = option(256, cli=False)
    seed: int = option(
        0, "seed of the explorations and of the snapshot steps", type=argtypes.non_negative_int
    )
    workers: int = option(2, "worker processes (local) or Ray actors", type=argtypes.positive_int)
    batch: BatchConfig = option(default_factory=BatchConfig)
    room_types: tuple[RoomType, ...] = option(ROOM_TYPES, cli=False)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {self.split!r}")
        if self.snapshots < 1 or self.max_steps <= 60:  # half the snapshots come after step 60
            raise ValueError(
                f"need snapshots >= 1 and max_steps > 60 (half the snapshots are taken after step 60), "
                f"got {self.snapshots}, {self.max_steps}"
            )


@dataclass
class SearchTrainConfig:
    """How the search network is trained (saved in its checkpoints and manifest)."""

    data: str = option(str(DEFAULT_DATA), "directory of `tidee gen search` shards")
    out: str | None = option(
        None,
        "weights to write, + .json manifest (default: the shipped agent/weights/search_net.pt)",
        type=argtypes.output_path,
    )
    work_dir: str = option(
        str(RUNS_DIR / "search" / "train"),
        "checkpoint and loss curve (resumable)",
        type=argtypes.output_path,
    )
    steps: int = option(1200, "training steps", type=argtypes.positive_int)
    batch_size: int = option(8, "maps per step", type=argtypes.positive_int)
    classes_per_map: int = option(8, cli=False)
    lr: float = option(2e-3, "peak learning rate (cosine decay to 0)")
    weight_decay: float = option(1e-4, cli=False)
    pos_weight: float = option(10.0, "BCE weight of positive cells")
    width: int = option(32, cli=False)
    embed: int = option(48, cli=False)
    val_fraction: float = option(0.1, cli=False)  # of training *rooms*, held out to report
    seed: int = option(
        0, "seed of the weights, the batches and the validation rooms", type=argtypes.non_negative_int
    )
    threads: int = option(2, "CPU threads (0: torch's default)", type=argtypes.non_negative_int)
    log_every: int = option(20, cli=False)
    ckpt_every: int = option(100, cli=False)
    extra: dict[str, Any] = option(default_factory=dict, cli=False)


@dataclass
class SearchTrainCommand:
    """``tidee train search``: the training config and whether to resume."""

    train: SearchTrainConfig = option(default_factory=SearchTrainConfig)
    resume: bool = option(True, "continue from a checkpoint in --work-dir made with the same config")


@dataclass
class SearchEvalConfig:
    """``tidee eval search``: object search on held-out rooms, network vs frontier (Table 2)."""

    out: str = option(
        help="directory for search.json, search.md, search_examples.png", type=argtypes.output_path
    )
    split: HeldOutSplit = option("test", "held-out rooms only")
    methods: tuple[SearchMethod, ...] = option(METHODS, "comma list of network, frontier")
    categories_per_room: int | None = option(
        8, "categories sampled per room (seeded); 0: every category present", type=count_or_all
    )  # None: every category present
    max_steps: int = option(200, "steps per search", type=argtypes.non_negative_int)
    radius: float = option(1.5, "success radius, metres")
    perception: PerceptionMode = option("learned", "detections that build the maps")
    resolution: int = option(256, cli=False)
    workers: int = option(2, "worker processes (local) or Ray actors", type=argtypes.positive_int)
    batch: BatchConfig = option(default_factory=BatchConfig)
    seed: int = option(
        0, "seed of the sampled categories and of the random goals", type=argtypes.non_negative_int
    )
    weights: str | None = option(None, "search network weights (default: agent/weights/search_net.pt)")
    rooms: int | None = option(None, "first N rooms of the split (0: all)", type=count_or_all)
    examples: int = option(4, cli=False)  # heatmap examples in the PNG
    explored_discount: float = option(
        0.0, "network: scale heat by (1 - d * explored) before choosing search points (0: paper)"
    )
    network_fallback: NetworkFallback = option(
        "random",
        "network: where to go once no search point is left: a random reachable point, or the "
        "nearest frontier",
    )

    def __post_init__(self) -> None:
        if self.split not in HELD_OUT_SPLITS:
            raise ValueError(
                "tidee eval search scores held-out rooms: --split must be "
                f"{' or '.join(HELD_OUT_SPLITS)}, got {self.split!r}"
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
        if self.perception not in PERCEPTIONS:
            raise ValueError(f"--perception must be one of {', '.join(PERCEPTIONS)}, got {self.perception!r}")
        if not 0 <= self.explored_discount <= 1:
            raise ValueError(f"--explored-discount must be in [0, 1], got {self.explored_discount}")
        if self.network_fallback not in NETWORK_FALLBACKS:
            raise ValueError(
                f"--network-fallback must be one of {NETWORK_FALLBACKS}, got {self.network_fallback!r}"
            )


__all__ = [
    "DEFAULT_DATA",
    "METHODS",
    "NETWORK_FALLBACKS",
    "NetworkFallback",
    "SearchEvalConfig",
    "SearchGenConfig",
    "SearchMethod",
    "SearchTrainCommand",
    "SearchTrainConfig",
    "count_or_all",
]
