"""Which seeds are train, val and test rooms, and how messy configurations are numbered.

Like iTHOR: per room type 20 train, 5 val and 5 test rooms (120 rooms in all), plus a
large pool of further training seeds for data generation. Messy configurations are
addressed by index within a split and generated on demand, never stored:
  train: 80 rooms x 100 messes = 8000;  val: 20 rooms x 10 = 200;  test: 20 rooms x 5 = 100.
"""

from __future__ import annotations

from dataclasses import dataclass

from tidee.protocol.vocab import ROOM_TYPES

SPLIT_SEEDS: dict[str, range] = {
    "train": range(0, 20),
    "val": range(100, 105),
    "test": range(200, 205),
}
# Further training seeds for data generation (detector images, relation statistics...).
TRAIN_POOL = range(10_000, 20_000)
MESSES_PER_ROOM = {"train": 100, "val": 10, "test": 5}


@dataclass(frozen=True)
class MessConfig:
    split: str
    index: int
    room_type: str
    seed: int
    mess_index: int


def split_of(seed: int) -> str:
    for name, seeds in SPLIT_SEEDS.items():
        if seed in seeds:
            return name
    if seed in TRAIN_POOL:
        return "train_pool"
    return "unassigned"


def messes_per_room(seed: int) -> int | None:
    """How many messy configurations a room of ``seed`` has (None: a seed outside every split)."""
    split = split_of(seed)
    if split == "unassigned":
        return None
    return MESSES_PER_ROOM["train" if split == "train_pool" else split]


def check_mess_index(seed: int, mess_index: int | None) -> None:
    """Refuse a messy configuration index outside the room's split, naming the valid range."""
    limit = messes_per_room(seed)
    if mess_index is None or limit is None:
        return
    if not 0 <= mess_index < limit:
        raise ValueError(
            f"mess_index {mess_index} is out of range: {split_of(seed)} room seed {seed} has messy "
            f"configurations 0-{limit - 1}"
        )


def rooms(split: str) -> list[tuple[str, int]]:
    if split not in SPLIT_SEEDS:
        raise ValueError(f"split must be one of {sorted(SPLIT_SEEDS)}, got {split!r}")
    return [(rt, s) for rt in ROOM_TYPES for s in SPLIT_SEEDS[split]]


def num_configs(split: str) -> int:
    return len(rooms(split)) * MESSES_PER_ROOM[split]


def mess_config(split: str, index: int) -> MessConfig:
    """Configuration #index of a split: rooms in order, each with its messes in order."""
    n = num_configs(split)
    if not 0 <= index < n:
        raise ValueError(f"{split} has {n} messy configurations; index {index} is out of range")
    per = MESSES_PER_ROOM[split]
    room_type, seed = rooms(split)[index // per]
    return MessConfig(split, index, room_type, seed, index % per)
