"""The names every part of tidee shares, each declared once: room types, renderers, splits.

Each is a ``Literal`` type (for annotations, and so ``tidee.options`` makes it a CLI choice)
and the tuple of its values (for validation and loops). Nothing else in the tree spells these
lists out; ``tests/test_layout.py`` checks that.
"""

from __future__ import annotations

from typing import Literal, get_args

RoomType = Literal["Kitchen", "LivingRoom", "Bedroom", "Bathroom"]
ROOM_TYPES: tuple[RoomType, ...] = get_args(RoomType)

# Who draws the frames: PyBullet's EGL (OpenGL via Mesa/GPU), its TinyRenderer (CPU), or EGL
# when it loads and tiny otherwise.
Renderer = Literal["auto", "egl", "tiny"]
RENDERERS: tuple[Renderer, ...] = get_args(Renderer)

# Room seed splits (server/splits.py holds their seeds); evaluations use the held-out ones.
Split = Literal["train", "val", "test"]
SPLITS: tuple[Split, ...] = get_args(Split)
HeldOutSplit = Literal["test", "val"]
HELD_OUT_SPLITS: tuple[HeldOutSplit, ...] = get_args(HeldOutSplit)


def check_choice(what: str, value: object, choices: tuple) -> None:
    """A ValueError naming ``what``, the bad value and the choices, unless value is one of them."""
    if value not in choices:
        raise ValueError(f"{what} must be one of {', '.join(map(str, choices))}; got {value!r}")
