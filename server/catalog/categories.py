"""Every object category: its shape recipe, sizes, palettes, flags and variants.

Recipes are written in the normalised local frame of ``schema.py`` (x, y in [-0.5, 0.5],
z in [0, 1], +y is the object's front). Conventions used throughout:

* Sizes are sampled with ONE shared fraction ``t`` for all three axes (see
  ``sample_size``), so an instance's proportions move together between ``size_min``
  and ``size_max``. Round parts (cylinders, spheres, lathes) have their radius tied to
  sx, so the recipes rely on this to keep e.g. a mug's body inside its box.
* Lathe parts are stored with max(r) == 1 and extent[0] = the diameter as a fraction of
  sx, so the radius at a profile point is r * extent[0] * sx / 2 (what server/meshes.py
  draws; it agrees with the schema's "r as a fraction of sx / 2" for full-width lathes).
  The ``lathe`` helper below takes profiles authored in fractions of sx / 2 and rescales.
* Only a part with ``door`` set moves when opened; knobs and handles would be left
  floating, so openable objects draw their doors as plain panels in a contrasting colour.
* The Box lid is a ``door="slide"`` part: it slides forward off the box when opened (a
  hinged "top" door is a front flap that swings out, which suits vertical panels only).
* Pickupable vessels (Bowl, Plate, Pot, Pan, Mug, Cup) are *not* receptacles here, to keep
  stacking out of the simulation; Box is the one pickupable receptacle (openable).
* Drawer is a small standalone chest of drawers whose top drawer slides open; Dresser is a
  wide, non-openable chest with a top surface (as in AI2THOR, where a Dresser itself does
  not open).
* StoveBurner is the whole stove unit (AI2THOR's receptacle type for pans sits on it).
* Floor is a thin slab (sz 0.02 m) the generator stretches to the room; its one surface is
  its top face (z=1), so place the body at world z=-sz to put the walkable level at 0.
* Furniture with placement "none" (Microwave, CoffeeMachine, Toaster, Television,
  DeskLamp) stands on another piece: rooms.json says which ("on").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Literal, TypedDict, Unpack

from .schema import Category, ColorRole, Hinge, Part, Placement, Surface, Variant

V3 = tuple[float, float, float]
Profile = Sequence[tuple[float, float]]
Kind = Literal["small", "furniture", "structure"]


class PartOptions(TypedDict, total=False):
    """The optional ``Part`` fields the part helpers pass through (``lathe`` sets ``profile``)."""

    door: Hinge | None
    collide: bool


class Aspect(TypedDict):
    """A round part's nominal sx / sy and sx / sz (``sph``'s ``ay`` and ``az``)."""

    ay: float
    az: float


class _CommonOptions(TypedDict, total=False):
    """Optional ``Category`` fields every helper below passes through unchanged."""

    receptacle: bool
    openable: bool
    surfaces: tuple[Surface, ...]
    variants: tuple[Variant, ...]
    mount_height: float
    tags: frozenset[str]


class SmallOptions(_CommonOptions, total=False):
    """What ``small`` passes on: it sets ``pickupable`` and ``mass`` itself."""

    placement: Placement


class FurnitureOptions(_CommonOptions, total=False):
    """What ``furn`` passes on: it takes ``placement`` by name."""

    pickupable: bool
    mass: float


class CategoryOptions(SmallOptions, FurnitureOptions, total=False):
    """Every optional ``Category`` field, as ``cat`` passes them to ``Category``."""


# Roles every palette has unless it overrides them; recipes use these for fittings.
DEFAULT_ROLES: dict[str, str] = {
    "metal": "#a7abaf",
    "dark": "#242424",
    "light": "#efece6",
}


# --------------------------------------------------------------------------- helpers


def box(c: V3, e: V3, color: ColorRole = "primary", **kw: Unpack[PartOptions]) -> Part:
    return Part("box", c, e, color, **kw)


def cyl(
    c: V3, d: float, h: float, color: ColorRole = "primary", ay: float = 1.0, **kw: Unpack[PartOptions]
) -> Part:
    """Vertical cylinder of diameter ``d`` (fraction of sx) and height ``h``.

    ``ay`` is the object's nominal sx / sy, so extent[1] documents the y footprint.
    """
    return Part("cylinder", c, (d, d * ay, h), color, **kw)


def sph(
    c: V3,
    d: float,
    color: ColorRole = "primary",
    ay: float = 1.0,
    az: float = 1.0,
    **kw: Unpack[PartOptions],
) -> Part:
    """Sphere of diameter ``d`` (fraction of sx); ay, az are nominal sx/sy and sx/sz."""
    return Part("sphere", c, (d, d * ay, d * az), color, **kw)


def lathe(
    c: V3,
    h: float,
    profile: Profile,
    color: ColorRole = "primary",
    ay: float = 1.0,
    **kw: Unpack[PartOptions],
) -> Part:
    """Surface of revolution; ``profile`` is (r, z) bottom to top, r a fraction of sx/2.

    Stored normalised: max r becomes 1 and the part's diameter fraction goes to extent[0].
    """
    d = max(p[0] for p in profile)
    norm = tuple((round(float(a) / d, 6), float(b)) for a, b in profile)
    return Part("lathe", c, (d, d * ay, h), color, profile=norm, **kw)


def surf(c: tuple[float, float], e: tuple[float, float], z: float, inside: bool = False) -> Surface:
    return Surface(c, e, z, inside)


def pal(**roles: str) -> dict[str, str]:
    return {**DEFAULT_ROLES, **roles}


def pals(*palettes: dict[str, str]) -> tuple[dict[str, str], ...]:
    return tuple(pal(**p) for p in palettes)


def legs4(
    top: float, wx: float, wy: float, color: ColorRole = "primary", inset: float = 0.0, bottom: float = 0.0
) -> list[Part]:
    """Four square legs in the corners, from z=bottom to z=top."""
    x, y = 0.5 - inset - wx / 2, 0.5 - inset - wy / 2
    h = top - bottom
    return [box((sx * x, sy * y, bottom + h / 2), (wx, wy, h), color) for sx in (-1, 1) for sy in (-1, 1)]


def cat(
    name: str,
    kind: Kind,
    smin: V3,
    smax: V3,
    parts: Iterable[Part],
    palettes: Iterable[dict[str, str]],
    **kw: Unpack[CategoryOptions],
) -> Category:
    return Category(
        name=name,
        kind=kind,
        size_min=smin,
        size_max=smax,
        parts=tuple(parts),
        palettes=tuple(palettes),
        **kw,
    )


def small(
    name: str,
    smin: V3,
    smax: V3,
    parts: Iterable[Part],
    palettes: Iterable[dict[str, str]],
    mass: float,
    **kw: Unpack[SmallOptions],
) -> Category:
    return cat(name, "small", smin, smax, parts, palettes, pickupable=True, mass=mass, **kw)


def furn(
    name: str,
    smin: V3,
    smax: V3,
    parts: Iterable[Part],
    palettes: Iterable[dict[str, str]],
    placement: Placement,
    **kw: Unpack[FurnitureOptions],
) -> Category:
    return cat(name, "furniture", smin, smax, parts, palettes, placement=placement, **kw)


# Common palettes.
WOODS = pals(
    dict(primary="#8b5a2b", secondary="#6e4423", accent="#c9a27a"),  # walnut
    dict(primary="#c49a6c", secondary="#a67c52", accent="#e6d2b5"),  # oak
    dict(primary="#e9e4dc", secondary="#d6d0c6", accent="#9c8f80"),  # white-painted
    dict(primary="#3b2f2a", secondary="#2a211d", accent="#8a7a6a"),  # espresso
    dict(primary="#a0522d", secondary="#7f3f22", accent="#deb887"),  # cherry
)
FABRICS = pals(
    dict(primary="#6b6f76", secondary="#7d828a", accent="#3a3d42"),  # grey
    dict(primary="#2f4a6d", secondary="#3c5a82", accent="#1d2f47"),  # navy
    dict(primary="#b9a88f", secondary="#cbbba3", accent="#7d6c55"),  # beige
    dict(primary="#5b7553", secondary="#6c8863", accent="#384a33"),  # olive
    dict(primary="#8c3b3b", secondary="#a04848", accent="#5a2222"),  # burgundy
    dict(primary="#d9d4c7", secondary="#e6e1d6", accent="#9d968a"),  # cream
)
CERAMICS = pals(
    dict(primary="#f4f2ee", secondary="#dcd8d0"),  # white
    dict(primary="#3d5a80", secondary="#2c4360"),  # blue glaze
    dict(primary="#c9744a", secondary="#a65a35"),  # terracotta
    dict(primary="#8fae9a", secondary="#6f8f7b"),  # sage
    dict(primary="#2b2b2b", secondary="#1a1a1a"),  # black
    dict(primary="#e8d9b5", secondary="#cdbb92"),  # cream
)
STEELS = pals(
    dict(primary="#b5b9bd", secondary="#8e9397"),  # stainless
    dict(primary="#2a2a2a", secondary="#444444"),  # black
    dict(primary="#f2f2f0", secondary="#d6d6d4"),  # white enamel
)
PLASTICS = pals(
    dict(primary="#d23c3c", secondary="#f2f2f2"),
    dict(primary="#2f6db5", secondary="#f2f2f2"),
    dict(primary="#f2c12e", secondary="#333333"),
    dict(primary="#3c9a5f", secondary="#f2f2f2"),
    dict(primary="#222222", secondary="#888888"),
    dict(primary="#f4f4f4", secondary="#9aa3ab"),
)


# ------------------------------------------------------------------- small objects


def _small_objects() -> list[Category]:
    out: list[Category] = []
    add = out.append

    add(
        small(
            "AlarmClock",
            (0.10, 0.06, 0.08),
            (0.15, 0.08, 0.12),
            [
                box((0, -0.05, 0.5), (1, 0.9, 1)),
                box((0, 0.45, 0.55), (0.72, 0.1, 0.72), "light", collide=False),  # dial face
                box((0.05, 0.5 - 0.01, 0.6), (0.3, 0.02, 0.05), "dark", collide=False),  # hands
                box((0, 0.5 - 0.01, 0.7), (0.04, 0.02, 0.25), "dark", collide=False),
            ],
            pals(
                dict(primary="#1f1f1f"),
                dict(primary="#f3f1ec", light="#ffffff"),
                dict(primary="#b8312f"),
                dict(primary="#2e5e8c"),
            ),
            mass=0.3,
            tags=frozenset({"electronics"}),
        )
    )

    apple_profile = [(0, 0), (0.55, 0.02), (0.9, 0.2), (1, 0.5), (0.92, 0.8), (0.55, 0.95), (0.2, 1), (0, 1)]
    add(
        small(
            "Apple",
            (0.07, 0.07, 0.07),
            (0.09, 0.09, 0.09),
            [
                lathe((0, 0, 0.45), 0.9, apple_profile),
                cyl((0, 0, 0.93), 0.08, 0.14, "#4a3220"),
            ],
            pals(
                dict(primary="#b3161b"),
                dict(primary="#8cbf3f"),
                dict(primary="#c8412b"),
                dict(primary="#9e1b1f"),
            ),
            mass=0.18,
            tags=frozenset({"food", "fruit"}),
        )
    )

    book_parts = [
        box((0, 0, 0.07), (1, 1, 0.14)),  # back cover
        box((0, 0, 0.93), (1, 1, 0.14)),  # front cover
        box((-0.47, 0, 0.5), (0.06, 1, 0.72)),  # spine
        box((0.02, 0, 0.5), (0.94, 0.96, 0.72), "pages"),  # page block
    ]
    add(
        small(
            "Book",
            (0.15, 0.21, 0.025),
            (0.19, 0.25, 0.05),
            book_parts,
            pals(
                dict(primary="#7a1f1f", pages="#f2ead3"),
                dict(primary="#1f3a5f", pages="#f0e6cc"),
                dict(primary="#2f5130", pages="#efe8d4"),
                dict(primary="#3a3a3a", pages="#f4eedd"),
                dict(primary="#6b4b2a", pages="#ede2c6"),
            ),
            mass=0.6,
            variants=(
                Variant("hardcover"),
                # Cookbooks: bigger, flatter, glossy bright covers, white pages.
                Variant(
                    "cookbook",
                    size_min=(0.20, 0.25, 0.015),
                    size_max=(0.24, 0.29, 0.028),
                    palettes=pals(
                        dict(primary="#e2582b", pages="#ffffff"),
                        dict(primary="#f0c419", pages="#ffffff"),
                        dict(primary="#d93b5c", pages="#fbfbfb"),
                        dict(primary="#4fa35a", pages="#ffffff"),
                    ),
                    mass=0.8,
                ),
            ),
        )
    )

    bowl_profile = [(0, 0), (0.5, 0), (0.62, 0.12), (0.86, 0.5), (0.97, 0.86), (1, 1)]
    serving_profile = [(0, 0), (0.55, 0), (0.6, 0.08), (0.9, 0.45), (1, 0.8), (1, 1)]
    add(
        small(
            "Bowl",
            (0.13, 0.13, 0.06),
            (0.17, 0.17, 0.08),
            [
                lathe((0, 0, 0.5), 1.0, bowl_profile),
                cyl((0, 0, 0.93), 0.86, 0.06, "secondary", collide=False),  # the inside, seen from above
            ],
            CERAMICS,
            mass=0.3,
            tags=frozenset({"kitchenware", "round"}),
            variants=(
                Variant("cereal"),
                Variant(
                    "serving",
                    size_min=(0.24, 0.24, 0.09),
                    size_max=(0.32, 0.32, 0.13),
                    parts=(
                        lathe((0, 0, 0.5), 1.0, serving_profile),
                        cyl((0, 0, 0.95), 0.9, 0.05, "secondary", collide=False),
                    ),
                    palettes=pals(
                        dict(primary="#9c6b3e", secondary="#b5824f"),  # wood
                        dict(primary="#cfe2e6", secondary="#e6f1f3"),  # glass
                        dict(primary="#f4f2ee", secondary="#3d5a80"),  # white, blue inside
                        dict(primary="#6d8f6f", secondary="#e8e2d0"),
                    ),
                    mass=0.9,
                ),
            ),
        )
    )

    add(
        small(
            "Bread",
            (0.12, 0.25, 0.10),
            (0.15, 0.31, 0.13),
            [
                box((0, 0, 0.32), (1, 1, 0.64)),
                box((0, 0, 0.8), (0.82, 0.96, 0.36), "secondary"),  # domed crust
                box((0, 0, 0.985), (0.5, 0.9, 0.03), "accent", collide=False),  # score
            ],
            pals(
                dict(primary="#d6a566", secondary="#b0743a", accent="#e8c58d"),
                dict(primary="#a8733f", secondary="#7c4f25", accent="#c79a62"),
                dict(primary="#e3b777", secondary="#c48a45", accent="#f1d39f"),
            ),
            mass=0.45,
            tags=frozenset({"food"}),
        )
    )

    add(
        small(
            "ButterKnife",
            (0.02, 0.20, 0.01),
            (0.024, 0.23, 0.014),
            [
                box((0, 0.2, 0.4), (1, 0.6, 0.6), "metal"),
                box((0, -0.3, 0.5), (0.9, 0.4, 1)),
            ],
            pals(dict(primary="#b5b9bd"), dict(primary="#2b2b2b"), dict(primary="#e9e4d8")),
            mass=0.05,
            tags=frozenset({"utensil"}),
        )
    )

    add(
        small(
            "CellPhone",
            (0.07, 0.14, 0.008),
            (0.078, 0.16, 0.01),
            [
                box((0, 0, 0.45), (1, 1, 0.9)),
                box((0, 0, 0.95), (0.9, 0.92, 0.1), "screen", collide=False),
            ],
            pals(
                dict(primary="#1c1c1e", screen="#0e1620"),
                dict(primary="#d9d9de", screen="#111a24"),
                dict(primary="#2c4a6e", screen="#0e1620"),
                dict(primary="#b8a18a", screen="#0c121a"),
            ),
            mass=0.18,
            tags=frozenset({"electronics"}),
        )
    )

    add(
        small(
            "Candle",
            (0.07, 0.07, 0.10),
            (0.09, 0.09, 0.18),
            [
                cyl((0, 0, 0.47), 1.0, 0.94),
                cyl((0, 0, 0.97), 0.08, 0.06, "dark", collide=False),  # wick
            ],
            pals(
                dict(primary="#f3ecd9"),
                dict(primary="#e9d6a8"),
                dict(primary="#b33a3a"),
                dict(primary="#f6f4ef"),
            ),
            mass=0.35,
            tags=frozenset({"decor", "round"}),
            variants=(
                Variant("pillar"),
                # Tealight: a short metal cup with a white wax disc.
                Variant(
                    "tealight",
                    size_min=(0.038, 0.038, 0.016),
                    size_max=(0.042, 0.042, 0.02),
                    parts=(
                        cyl((0, 0, 0.45), 1.0, 0.9, "metal"),
                        cyl((0, 0, 0.93), 0.86, 0.06, "primary", collide=False),
                        cyl((0, 0, 0.97), 0.1, 0.06, "dark", collide=False),
                    ),
                    palettes=pals(dict(primary="#fbfaf5"), dict(primary="#f4efe0")),
                    mass=0.015,
                ),
            ),
        )
    )

    add(
        small(
            "Cloth",
            (0.20, 0.20, 0.01),
            (0.25, 0.25, 0.02),
            [
                box((0, 0, 0.5), (1, 1, 1)),
                box((0, 0, 0.97), (1, 0.18, 0.06), "accent", collide=False),  # woven stripe
                box((0, 0.3, 0.97), (1, 0.06, 0.06), "accent", collide=False),
                box((0, -0.3, 0.97), (1, 0.06, 0.06), "accent", collide=False),
            ],
            pals(
                dict(primary="#f2f0e8", accent="#c0392b"),
                dict(primary="#f2f0e8", accent="#2e6db0"),
                dict(primary="#e9e2cf", accent="#4f8a4b"),
            ),
            mass=0.05,
            tags=frozenset({"textile"}),
            variants=(
                Variant("dishcloth"),
                # Washcloth: smaller, thicker (folded terry), plain pastel, no stripes.
                Variant(
                    "washcloth",
                    size_min=(0.13, 0.13, 0.025),
                    size_max=(0.16, 0.16, 0.035),
                    parts=(
                        box((0, 0, 0.5), (1, 1, 1)),
                        box((0, 0.45, 0.5), (1, 0.1, 0.9), "accent", collide=False),  # folded edge hem
                    ),
                    palettes=pals(
                        dict(primary="#bcd8e8", accent="#a6c6d8"),
                        dict(primary="#f4c7c3", accent="#e8b0ab"),
                        dict(primary="#ffffff", accent="#e6e6e6"),
                        dict(primary="#c8e0c0", accent="#b3cfaa"),
                    ),
                    mass=0.06,
                ),
            ),
        )
    )

    add(
        small(
            "CreditCard",
            (0.054, 0.086, 0.002),
            (0.054, 0.086, 0.003),
            [
                box((0, 0, 0.5), (1, 1, 1)),
                box((0, 0.25, 0.9), (1, 0.14, 0.2), "accent", collide=False),
                box((-0.2, -0.05, 0.9), (0.25, 0.14, 0.2), "#d4af37", collide=False),  # chip
            ],
            pals(
                dict(primary="#1f4e9c", accent="#0f2a57"),
                dict(primary="#b0b3b8", accent="#6c6f74"),
                dict(primary="#111111", accent="#444444"),
                dict(primary="#c0392b", accent="#7b241c"),
            ),
            mass=0.005,
        )
    )

    cup_profile = [(0, 0), (0.78, 0), (0.84, 0.5), (1, 1)]
    add(
        small(
            "Cup",
            (0.07, 0.07, 0.10),
            (0.085, 0.085, 0.13),
            [
                lathe((0, 0, 0.5), 1.0, cup_profile),
                cyl((0, 0, 0.95), 0.9, 0.06, "secondary", collide=False),
            ],
            pals(
                dict(primary="#cfe3ea", secondary="#e9f3f6"),
                dict(primary="#b9d6c5", secondary="#dcebe2"),
                dict(primary="#e8e8e8", secondary="#ffffff"),
                dict(primary="#d9c9a8", secondary="#efe5cf"),
            ),
            mass=0.2,
            tags=frozenset({"kitchenware", "round"}),
        )
    )

    add(
        small(
            "DishSponge",
            (0.09, 0.06, 0.03),
            (0.11, 0.07, 0.04),
            [
                box((0, 0, 0.35), (1, 1, 0.7)),
                box((0, 0, 0.85), (1, 1, 0.3), "secondary"),  # scouring layer
            ],
            pals(
                dict(primary="#f3d34a", secondary="#2f8f3a"),
                dict(primary="#f0a04b", secondary="#2a6e3a"),
                dict(primary="#7fc3e8", secondary="#1f5f8b"),
            ),
            mass=0.02,
        )
    )

    egg_profile = [(0, 0), (0.55, 0.04), (0.92, 0.26), (1, 0.42), (0.88, 0.7), (0.52, 0.93), (0, 1)]
    add(
        small(
            "Egg",
            (0.043, 0.043, 0.057),
            (0.047, 0.047, 0.062),
            [
                lathe((0, 0, 0.5), 1.0, egg_profile),
            ],
            pals(dict(primary="#f3e6c8"), dict(primary="#d8a878"), dict(primary="#f7f3ea")),
            mass=0.06,
            tags=frozenset({"food", "round"}),
        )
    )

    add(
        small(
            "Fork",
            (0.025, 0.18, 0.012),
            (0.028, 0.21, 0.014),
            [
                box((0, -0.18, 0.5), (0.35, 0.64, 0.7)),
                box((0, 0.2, 0.5), (0.9, 0.14, 0.7)),
                *[box((x, 0.38, 0.5), (0.16, 0.24, 0.7)) for x in (-0.37, -0.12, 0.12, 0.37)],
            ],
            pals(dict(primary="#b5b9bd"), dict(primary="#c9a65a"), dict(primary="#2b2b2b")),
            mass=0.04,
            tags=frozenset({"utensil"}),
        )
    )

    # Kettle: body is sy wide; the spout pokes out along +x (sx = 1.35 sy).
    k_ay = 1.35
    add(
        small(
            "Kettle",
            (0.22, 0.163, 0.2),
            (0.26, 0.193, 0.24),
            [
                lathe((-0.13, 0, 0.4), 0.8, [(0, 0), (0.7, 0), (0.74, 0.5), (0.6, 0.92), (0.3, 1)], ay=k_ay),
                box((0.32, 0, 0.45), (0.36, 0.12, 0.1)),  # spout
                box((-0.13, 0, 0.95), (0.36, 0.12, 0.1), "dark"),  # handle bar
                box((-0.3, 0, 0.86), (0.05, 0.1, 0.18), "dark"),
                box((0.04, 0, 0.86), (0.05, 0.1, 0.18), "dark"),
            ],
            STEELS
            + pals(
                dict(primary="#c0392b", secondary="#7f2620"), dict(primary="#e8d9b5", secondary="#b59f6f")
            ),
            mass=1.0,
            tags=frozenset({"kitchenware"}),
        )
    )

    add(
        small(
            "KeyChain",
            (0.06, 0.03, 0.008),
            (0.08, 0.04, 0.012),
            [
                cyl((-0.32, 0, 0.5), 0.36, 1.0, "metal", ay=2.0),  # ring
                box((0.15, 0, 0.5), (0.6, 0.5, 0.8), "metal"),  # key
                box((-0.05, 0.2, 0.5), (0.2, 0.5, 0.8), "primary"),  # fob
            ],
            pals(
                dict(primary="#c0392b"),
                dict(primary="#2e5e8c"),
                dict(primary="#3a3a3a"),
                dict(primary="#8b5a2b"),
            ),
            mass=0.03,
        )
    )

    add(
        small(
            "Knife",
            (0.026, 0.26, 0.016),
            (0.03, 0.32, 0.02),
            [
                box((0, 0.18, 0.4), (0.9, 0.64, 0.5), "metal"),
                box((0, -0.32, 0.5), (1, 0.36, 1)),
            ],
            pals(dict(primary="#1f1f1f"), dict(primary="#6e4423"), dict(primary="#b5b9bd")),
            mass=0.12,
            tags=frozenset({"utensil"}),
        )
    )

    l_ay = 0.3  # sx / sy of a ladle
    add(
        small(
            "Ladle",
            (0.084, 0.28, 0.08),
            (0.1, 0.333, 0.095),
            [
                lathe((0, 0.33, 0.3), 0.6, [(0, 0), (0.7, 0.1), (1, 0.6), (1, 1)], ay=l_ay),
                cyl((0, 0.33, 0.58), 0.9, 0.02, "dark", ay=l_ay, collide=False),
                box((0, -0.1, 0.75), (0.16, 0.8, 0.08)),
            ],
            STEELS + pals(dict(primary="#222222", secondary="#111111")),
            mass=0.15,
            tags=frozenset({"utensil"}),
        )
    )

    add(
        small(
            "Laptop",
            (0.30, 0.21, 0.2),
            (0.36, 0.25, 0.24),
            [
                box((0, 0.02, 0.045), (1, 0.96, 0.09)),  # base
                box((0, 0.12, 0.095), (0.88, 0.46, 0.01), "dark", collide=False),  # keyboard
                box((0, -0.46, 0.55), (1, 0.08, 0.9)),  # lid, upright
                box((0, -0.415, 0.56), (0.9, 0.01, 0.76), "screen", collide=False),
            ],
            pals(
                dict(primary="#b8bcc2", screen="#1b2a3a"),
                dict(primary="#2b2b2e", screen="#14202d"),
                dict(primary="#d8d2c8", screen="#1b2a3a"),
            ),
            mass=1.6,
            tags=frozenset({"electronics"}),
        )
    )

    add(
        small(
            "Lettuce",
            (0.14, 0.14, 0.13),
            (0.18, 0.18, 0.16),
            [
                lathe(
                    (0, 0, 0.5),
                    1.0,
                    [(0, 0), (0.6, 0), (0.95, 0.25), (1, 0.5), (0.85, 0.8), (0.4, 1), (0, 1)],
                ),
                lathe((0, 0, 0.88), 0.2, [(0.55, 0), (0.3, 1)], "secondary", collide=False),
            ],
            pals(dict(primary="#6fae3f", secondary="#a7d36b"), dict(primary="#5c9a34", secondary="#c4e08a")),
            mass=0.5,
            tags=frozenset({"food", "vegetable"}),
        )
    )

    m_ay = 1.4  # mug: sx includes the handle, sy is the body diameter
    add(
        small(
            "Mug",
            (0.119, 0.085, 0.09),
            (0.133, 0.095, 0.105),
            [
                cyl((-0.15, 0, 0.5), 0.7, 1.0, ay=m_ay),
                box((0.34, 0, 0.5), (0.32, 0.16, 0.6)),  # handle
                cyl((-0.15, 0, 0.99), 0.6, 0.03, "secondary", ay=m_ay, collide=False),  # dark inside
            ],
            pals(
                dict(primary="#f4f2ee", secondary="#4a3326"),
                dict(primary="#2f5e8c", secondary="#1f2f3f"),
                dict(primary="#c0392b", secondary="#3b1a17"),
                dict(primary="#e3c16f", secondary="#4a3326"),
                dict(primary="#2b2b2b", secondary="#111111"),
            ),
            mass=0.33,
            tags=frozenset({"kitchenware"}),
        )
    )

    add(
        small(
            "Newspaper",
            (0.28, 0.36, 0.01),
            (0.32, 0.42, 0.02),
            [
                box((0, 0, 0.5), (1, 1, 1)),
                box((0, 0.36, 0.97), (0.86, 0.1, 0.06), "dark", collide=False),  # headline
                *[
                    box((x, -0.1, 0.97), (0.26, 0.6, 0.06), "secondary", collide=False)
                    for x in (-0.3, 0, 0.3)
                ],
            ],
            pals(dict(primary="#e6e3d9", secondary="#a9a69e"), dict(primary="#efe4c8", secondary="#b2a98f")),
            mass=0.2,
        )
    )

    p_ay = 0.575  # pan: sx is the pan diameter, sy includes the handle
    add(
        small(
            "Pan",
            (0.24, 0.42, 0.05),
            (0.3, 0.52, 0.06),
            [
                lathe((0, 0.21, 0.5), 1.0, [(0, 0), (0.84, 0), (1, 1)], ay=p_ay),
                cyl((0, 0.21, 0.96), 0.88, 0.06, "secondary", ay=p_ay, collide=False),
                box((0, -0.29, 0.8), (0.12, 0.42, 0.3), "dark"),
            ],
            pals(
                dict(primary="#2b2b2b", secondary="#1a1a1a"),
                dict(primary="#b5b9bd", secondary="#8e9397"),
                dict(primary="#b5652d", secondary="#6b3a1c"),
                dict(primary="#3a3f45", secondary="#2a2e33"),
            ),
            mass=1.2,
            tags=frozenset({"kitchenware"}),
        )
    )

    add(
        small(
            "Pen",
            (0.01, 0.135, 0.01),
            (0.012, 0.15, 0.012),
            [
                box((0, -0.08, 0.5), (1, 0.84, 1)),
                box((0, 0.38, 0.5), (0.8, 0.24, 0.8), "accent"),  # cap
                box((0.5 - 0.1, 0.3, 0.5), (0.2, 0.3, 0.5), "metal"),  # clip
            ],
            pals(
                dict(primary="#1f3f8c", accent="#1f3f8c"),
                dict(primary="#e8e8e8", accent="#111111"),
                dict(primary="#111111", accent="#c9a65a"),
                dict(primary="#c0392b", accent="#c0392b"),
            ),
            mass=0.015,
        )
    )

    add(
        small(
            "Pencil",
            (0.008, 0.175, 0.008),
            (0.008, 0.19, 0.008),
            [
                box((0, -0.04, 0.5), (1, 0.84, 1)),
                box((0, 0.43, 0.5), (0.6, 0.1, 0.6), "#e2c290"),  # sharpened wood
                box((0, 0.49, 0.5), (0.25, 0.02, 0.25), "dark"),
                box((0, -0.47, 0.5), (1, 0.06, 1), "#e58c9a"),  # eraser
            ],
            pals(dict(primary="#f2c12e"), dict(primary="#2f6e3a"), dict(primary="#c0392b")),
            mass=0.007,
        )
    )

    shaker_profile = [(0, 0), (0.9, 0), (1, 0.3), (0.85, 0.75), (0.7, 1)]
    add(
        small(
            "PepperShaker",
            (0.04, 0.04, 0.08),
            (0.05, 0.05, 0.1),
            [
                lathe((0, 0, 0.4), 0.8, shaker_profile),
                cyl((0, 0, 0.9), 0.72, 0.2, "secondary"),
            ],
            pals(
                dict(primary="#2a2a2a", secondary="#a7abaf"),
                dict(primary="#5a3e2b", secondary="#b5b9bd"),
                dict(primary="#3b3b3b", secondary="#1a1a1a"),
            ),
            mass=0.09,
            tags=frozenset({"kitchenware"}),
        )
    )
    add(
        small(
            "SaltShaker",
            (0.04, 0.04, 0.08),
            (0.05, 0.05, 0.1),
            [
                lathe((0, 0, 0.4), 0.8, shaker_profile),
                cyl((0, 0, 0.9), 0.72, 0.2, "secondary"),
            ],
            pals(
                dict(primary="#f4f4f2", secondary="#a7abaf"),
                dict(primary="#e2eef2", secondary="#c9cdd1"),
                dict(primary="#fbfbfb", secondary="#c0392b"),
            ),
            mass=0.09,
            tags=frozenset({"kitchenware"}),
        )
    )

    pillow_parts = [
        box((0, 0, 0.5), (0.92, 0.9, 1)),  # puffed middle
        box((0, 0, 0.5), (1, 1, 0.45)),  # seamed edge
    ]
    add(
        small(
            "Pillow",
            (0.5, 0.35, 0.12),
            (0.7, 0.5, 0.17),
            pillow_parts,
            pals(
                dict(primary="#f5f3ee"),
                dict(primary="#e9e4d8"),
                dict(primary="#d7dde3"),
                dict(primary="#efe6d2"),
            ),
            mass=0.6,
            tags=frozenset({"textile"}),
            variants=(
                Variant("bed"),
                # Throw pillows: square, smaller, coloured, with a piped edge and a button.
                Variant(
                    "throw",
                    size_min=(0.4, 0.4, 0.12),
                    size_max=(0.5, 0.5, 0.15),
                    parts=(
                        box((0, 0, 0.5), (0.9, 0.9, 1)),
                        box((0, 0, 0.5), (1, 1, 0.35), "accent"),
                        cyl((0, 0, 0.98), 0.06, 0.04, "accent", collide=False),
                    ),
                    palettes=pals(
                        dict(primary="#c0392b", accent="#7b241c"),
                        dict(primary="#e3a63a", accent="#9c6d1c"),
                        dict(primary="#2f6d7a", accent="#1c434b"),
                        dict(primary="#7d5a9c", accent="#4d3563"),
                        dict(primary="#6b8f4e", accent="#3f5a2c"),
                    ),
                    mass=0.4,
                ),
            ),
        )
    )

    add(
        small(
            "Plate",
            (0.22, 0.22, 0.02),
            (0.28, 0.28, 0.028),
            [
                lathe((0, 0, 0.5), 1.0, [(0, 0), (0.6, 0), (0.66, 0.35), (1, 1)]),
                cyl((0, 0, 0.82), 0.6, 0.1, "secondary", collide=False),  # well of the plate
            ],
            pals(
                dict(primary="#f6f5f1", secondary="#ebe8e1"),
                dict(primary="#e8dcc3", secondary="#d9caa8"),
                dict(primary="#3d5a80", secondary="#35506f"),
                dict(primary="#f6f5f1", secondary="#8fae9a"),
            ),
            mass=0.45,
            tags=frozenset({"kitchenware", "round"}),
        )
    )

    pot_ay = 1.25  # pot: sx includes the side handles
    add(
        small(
            "Pot",
            (0.25, 0.2, 0.14),
            (0.33, 0.264, 0.19),
            [
                cyl((0, 0, 0.5), 0.8, 1.0, ay=pot_ay),
                cyl((0, 0, 0.99), 0.72, 0.03, "secondary", ay=pot_ay, collide=False),
                box((-0.45, 0, 0.82), (0.1, 0.24, 0.1), "dark"),
                box((0.45, 0, 0.82), (0.1, 0.24, 0.1), "dark"),
            ],
            pals(
                dict(primary="#b5b9bd", secondary="#6d7175"),
                dict(primary="#c0392b", secondary="#2b2b2b"),
                dict(primary="#2b2b2b", secondary="#151515"),
                dict(primary="#e8e4d8", secondary="#6d7175"),
            ),
            mass=1.6,
            tags=frozenset({"kitchenware"}),
        )
    )

    add(
        small(
            "Potato",
            (0.06, 0.09, 0.052),
            (0.07, 0.105, 0.06),
            [
                sph((0, -0.2, 0.5), 0.84, ay=0.667, az=1.15),
                sph((0, 0.0, 0.5), 0.86, ay=0.667, az=1.15),
                sph((0, 0.2, 0.48), 0.8, ay=0.667, az=1.15),
            ],
            pals(dict(primary="#a67b4f"), dict(primary="#b98a57"), dict(primary="#8c5a3c")),
            mass=0.2,
            tags=frozenset({"food", "vegetable"}),
        )
    )

    add(
        small(
            "RemoteControl",
            (0.045, 0.16, 0.018),
            (0.055, 0.2, 0.024),
            [
                box((0, 0, 0.5), (1, 1, 1)),
                box((0, 0.38, 0.98), (0.3, 0.08, 0.04), "#c0392b", collide=False),  # power
                *[
                    box((0, y, 0.98), (0.7, 0.06, 0.04), "secondary", collide=False)
                    for y in (0.15, 0.0, -0.15, -0.3)
                ],
            ],
            pals(
                dict(primary="#1c1c1c", secondary="#555555"),
                dict(primary="#3a3a3d", secondary="#8a8a8a"),
                dict(primary="#d8d8d8", secondary="#5a5a5a"),
            ),
            mass=0.12,
            tags=frozenset({"electronics"}),
        )
    )

    add(
        small(
            "SoapBar",
            (0.085, 0.055, 0.025),
            (0.095, 0.062, 0.03),
            [
                box((0, 0, 0.35), (1, 1, 0.7)),
                box((0, 0, 0.8), (0.86, 0.82, 0.4)),
            ],
            pals(
                dict(primary="#f3e9d2"),
                dict(primary="#f2c6d0"),
                dict(primary="#cde6c8"),
                dict(primary="#cfe0f0"),
            ),
            mass=0.11,
            tags=frozenset({"toiletry"}),
        )
    )

    add(
        small(
            "SoapBottle",
            (0.07, 0.07, 0.17),
            (0.085, 0.085, 0.21),
            [
                lathe((0, 0, 0.37), 0.74, [(0, 0), (0.95, 0), (1, 0.15), (1, 0.8), (0.5, 1)]),
                cyl((0, 0, 0.8), 0.3, 0.12, "secondary"),
                cyl((0, 0, 0.9), 0.4, 0.08, "secondary"),
                box((0, 0.15, 0.95), (0.14, 0.3, 0.06), "secondary"),  # pump nozzle
            ],
            pals(
                dict(primary="#e3c16f", secondary="#f4f4f4"),
                dict(primary="#8fc1d9", secondary="#2b2b2b"),
                dict(primary="#c7e0b5", secondary="#ffffff"),
                dict(primary="#f2a2b2", secondary="#ffffff"),
                dict(primary="#f5f5f0", secondary="#b5b9bd"),
            ),
            mass=0.35,
            tags=frozenset({"toiletry"}),
        )
    )

    s_ay = 0.8  # spray bottle: the trigger head sticks out to the front
    add(
        small(
            "SprayBottle",
            (0.08, 0.1, 0.24),
            (0.09, 0.1125, 0.28),
            [
                lathe((0, -0.1, 0.36), 0.72, [(0, 0), (0.95, 0), (1, 0.1), (1, 0.75), (0.45, 1)], ay=s_ay),
                box((0, 0.0, 0.86), (0.44, 0.5, 0.2), "secondary"),  # trigger head
                box((0, 0.38, 0.9), (0.2, 0.24, 0.08), "secondary"),  # nozzle
                box((0, 0.22, 0.76), (0.14, 0.08, 0.12), "secondary"),  # trigger
            ],
            pals(
                dict(primary="#4fb3d9", secondary="#f4f4f4"),
                dict(primary="#f2f2f2", secondary="#2f6db5"),
                dict(primary="#9bd16b", secondary="#2b2b2b"),
                dict(primary="#f7d154", secondary="#c0392b"),
            ),
            mass=0.55,
            tags=frozenset({"cleaning"}),
        )
    )

    add(
        small(
            "Spatula",
            (0.06, 0.28, 0.02),
            (0.075, 0.33, 0.03),
            [
                box((0, 0.3, 0.2), (1, 0.4, 0.4)),
                box((0, -0.2, 0.6), (0.28, 0.6, 0.6), "secondary"),
            ],
            pals(
                dict(primary="#1c1c1c", secondary="#1c1c1c"),
                dict(primary="#b5b9bd", secondary="#6e4423"),
                dict(primary="#c0392b", secondary="#2b2b2b"),
                dict(primary="#c49a6c", secondary="#c49a6c"),
            ),
            mass=0.08,
            tags=frozenset({"utensil"}),
        )
    )

    sp_ay = 0.25  # spoon: bowl width vs length
    add(
        small(
            "Spoon",
            (0.04, 0.16, 0.012),
            (0.045, 0.18, 0.014),
            [
                box((0, -0.16, 0.6), (0.32, 0.68, 0.6)),
                cyl((0, 0.32, 0.4), 1.0, 0.8, ay=sp_ay),
            ],
            pals(dict(primary="#b5b9bd"), dict(primary="#c9a65a"), dict(primary="#8b5a2b")),
            mass=0.04,
            tags=frozenset({"utensil"}),
        )
    )

    stone = pals(
        dict(primary="#8c6a3f", secondary="#3a3a3a"),
        dict(primary="#f0eee8", secondary="#b8b4aa"),
        dict(primary="#2b2b2b", secondary="#6b6b6b"),
        dict(primary="#c9744a", secondary="#6b4b2a"),
    )
    add(
        small(
            "Statue",
            (0.06, 0.06, 0.12),
            (0.09, 0.09, 0.2),
            [
                box((0, 0, 0.06), (1, 1, 0.12), "secondary"),  # base
                lathe((0, 0, 0.45), 0.66, [(0.6, 0), (0.7, 0.3), (0.45, 0.8), (0.3, 1)]),
                sph((0, 0, 0.88), 0.4, az=0.5),  # head
            ],
            stone,
            mass=0.4,
            tags=frozenset({"decor"}),
            variants=(
                Variant("figurine"),
                # Sculpture: a tall abstract piece on a plinth, knee-height or more.
                Variant(
                    "sculpture",
                    size_min=(0.24, 0.24, 0.5),
                    size_max=(0.34, 0.34, 0.8),
                    parts=(
                        box((0, 0, 0.05), (1, 1, 0.1), "secondary"),
                        box((0, 0, 0.3), (0.35, 0.35, 0.4)),
                        lathe((0, 0, 0.72), 0.56, [(0.5, 0), (0.95, 0.35), (0.6, 0.7), (0.85, 1)]),
                    ),
                    mass=8.0,
                ),
            ),
        )
    )

    tb = Aspect(ay=1.25, az=0.833)  # teddy bear sx/sy and sx/sz
    add(
        small(
            "TeddyBear",
            (0.22, 0.176, 0.264),
            (0.3, 0.24, 0.36),
            [
                sph((0, 0, 0.3), 0.6, **tb),  # body
                sph((0, 0.02, 0.77), 0.45, **tb),  # head
                sph((-0.17, 0, 0.92), 0.16, **tb),
                sph((0.17, 0, 0.92), 0.16, **tb),  # ears
                sph((0, 0.3, 0.74), 0.16, "secondary", **tb),  # snout
                sph((-0.2, 0.24, 0.1), 0.22, **tb),
                sph((0.2, 0.24, 0.1), 0.22, **tb),  # legs
                sph((-0.33, 0.06, 0.4), 0.18, **tb),
                sph((0.33, 0.06, 0.4), 0.18, **tb),  # arms
                sph((-0.08, 0.27, 0.83), 0.05, "dark", collide=False, **tb),
                sph((0.08, 0.27, 0.83), 0.05, "dark", collide=False, **tb),
            ],
            pals(
                dict(primary="#a0703c", secondary="#d9b98f"),
                dict(primary="#d9c2a0", secondary="#f1e6d2"),
                dict(primary="#6b4a2e", secondary="#b08a62"),
                dict(primary="#e8e2d6", secondary="#c9b8a0"),
            ),
            mass=0.4,
            tags=frozenset({"toy"}),
        )
    )

    add(
        small(
            "TissueBox",
            (0.22, 0.11, 0.08),
            (0.25, 0.125, 0.1),
            [
                box((0, 0, 0.42), (1, 1, 0.84)),
                box((0, 0, 0.9), (0.3, 0.4, 0.2), "light"),  # tissue puff
            ],
            pals(
                dict(primary="#7fb3d5"),
                dict(primary="#f2f2f2"),
                dict(primary="#c9b6e4"),
                dict(primary="#a3c4a0"),
                dict(primary="#e6b89c"),
            ),
            mass=0.2,
        )
    )

    add(
        small(
            "ToiletPaper",
            (0.11, 0.11, 0.1),
            (0.12, 0.12, 0.11),
            [
                cyl((0, 0, 0.5), 1.0, 1.0),
                cyl((0, 0, 0.99), 0.36, 0.02, "#9c7a54", collide=False),  # cardboard core
            ],
            pals(dict(primary="#fbfbf8"), dict(primary="#f4efe6")),
            mass=0.1,
            tags=frozenset({"toiletry", "round"}),
        )
    )

    add(
        small(
            "Tomato",
            (0.065, 0.065, 0.05),
            (0.085, 0.085, 0.065),
            [
                lathe(
                    (0, 0, 0.47),
                    0.94,
                    [(0, 0), (0.5, 0), (0.9, 0.15), (1, 0.45), (0.9, 0.8), (0.5, 0.98), (0, 1)],
                ),
                cyl((0, 0, 0.96), 0.3, 0.08, "secondary", collide=False),  # green calyx
            ],
            pals(
                dict(primary="#d62d20", secondary="#3f7a2a"),
                dict(primary="#e2401c", secondary="#4f8a34"),
                dict(primary="#b8231b", secondary="#3f7a2a"),
            ),
            mass=0.12,
            tags=frozenset({"food", "vegetable", "round"}),
        )
    )

    add(
        small(
            "Towel",
            (0.35, 0.25, 0.06),
            (0.44, 0.3, 0.09),
            [
                box((0, 0, 0.5), (0.98, 1, 1)),
                box((0, 0.45, 0.5), (1, 0.1, 0.92), "secondary"),  # folded edge
                box((0, 0, 0.985), (1, 0.08, 0.03), "accent", collide=False),  # woven band
            ],
            pals(
                dict(primary="#f7f7f4", secondary="#ecebe6", accent="#c9c6bd"),
                dict(primary="#3f6e9e", secondary="#355f89", accent="#f7f7f4"),
                dict(primary="#9a9a9a", secondary="#8a8a8a", accent="#f7f7f4"),
                dict(primary="#a7c4a0", secondary="#96b38f", accent="#f7f7f4"),
                dict(primary="#e9dcc3", secondary="#dccdb1", accent="#b8a88a"),
            ),
            mass=0.6,
            tags=frozenset({"textile"}),
            variants=(
                Variant("bath"),
                # Hand towels: half the size, and striped so they look different from bath ones.
                Variant(
                    "hand",
                    size_min=(0.2, 0.14, 0.03),
                    size_max=(0.25, 0.18, 0.045),
                    parts=(
                        box((0, 0, 0.5), (0.98, 1, 1)),
                        box((0, 0.45, 0.5), (1, 0.1, 0.92), "secondary"),
                        box((0, -0.25, 0.985), (1, 0.12, 0.03), "accent", collide=False),
                        box((0, 0.2, 0.985), (1, 0.12, 0.03), "accent", collide=False),
                    ),
                    palettes=pals(
                        dict(primary="#f7f7f4", secondary="#ecebe6", accent="#3f6e9e"),
                        dict(primary="#f2d7d5", secondary="#e8c6c3", accent="#b03a2e"),
                        dict(primary="#d6eaf8", secondary="#c5dcec", accent="#1f4e79"),
                    ),
                    mass=0.15,
                ),
            ),
        )
    )

    add(
        small(
            "Vase",
            (0.1, 0.1, 0.18),
            (0.14, 0.14, 0.28),
            [
                lathe((0, 0, 0.5), 1.0, [(0, 0), (0.7, 0), (1, 0.35), (0.85, 0.65), (0.4, 0.85), (0.5, 1)]),
            ],
            CERAMICS + pals(dict(primary="#7fa99b", secondary="#5e8a7b")),
            mass=0.6,
            tags=frozenset({"decor", "round"}),
            variants=(
                Variant("small"),
                # Floor vases: tall amphora shape with dry branches sticking out.
                Variant(
                    "large",
                    size_min=(0.3, 0.3, 0.75),
                    size_max=(0.4, 0.4, 1.0),
                    parts=(
                        lathe(
                            (0, 0, 0.4),
                            0.8,
                            [(0, 0), (0.55, 0), (0.95, 0.25), (1, 0.45), (0.6, 0.8), (0.4, 0.95), (0.5, 1)],
                        ),
                        box((0.04, 0, 0.88), (0.03, 0.03, 0.24), "#6b4b2a", collide=False),
                        box((-0.06, 0.03, 0.9), (0.03, 0.03, 0.2), "#6b4b2a", collide=False),
                    ),
                    palettes=pals(
                        dict(primary="#c9744a", secondary="#a65a35"),
                        dict(primary="#2b2b2b", secondary="#1a1a1a"),
                        dict(primary="#d8cfc0", secondary="#b8ab97"),
                        dict(primary="#3d5a80", secondary="#2c4360"),
                    ),
                    mass=7.0,
                ),
            ),
        )
    )

    add(
        small(
            "Watch",
            (0.04, 0.2, 0.012),
            (0.045, 0.23, 0.014),
            [
                box((0, 0, 0.2), (0.7, 1, 0.4), "secondary"),  # strap laid flat
                cyl((0, 0, 0.6), 1.0, 0.8, "metal", ay=0.2),  # case
                cyl((0, 0, 0.98), 0.8, 0.04, "light", ay=0.2, collide=False),  # dial
            ],
            pals(
                dict(primary="#222222", secondary="#3b2a1f"),
                dict(primary="#222222", secondary="#1c1c1c"),
                dict(primary="#222222", secondary="#b5b9bd", metal="#d4af37"),
            ),
            mass=0.08,
        )
    )

    wine_profile = [(0, 0), (1, 0), (1, 0.62), (0.8, 0.7), (0.34, 0.78), (0.32, 1)]
    add(
        small(
            "WineBottle",
            (0.075, 0.075, 0.29),
            (0.085, 0.085, 0.33),
            [
                lathe((0, 0, 0.5), 1.0, wine_profile),
                cyl((0, 0, 0.35), 1.02, 0.22, "light", collide=False),  # label
                cyl((0, 0, 0.95), 0.36, 0.1, "accent", collide=False),  # capsule
            ],
            pals(
                dict(primary="#1f3d24", accent="#7b1f2b"),
                dict(primary="#3b1418", accent="#c9a65a"),
                dict(primary="#5b6b3b", accent="#2b2b2b"),
                dict(primary="#d9e8c4", accent="#c9a65a"),
            ),
            mass=1.3,
            tags=frozenset({"drink"}),
        )
    )

    # A few more objects AI2THOR has, so rooms are not all kitchenware.
    box_parts = (
        box((0, 0, 0.02), (1, 1, 0.04)),
        box((0, 0.485, 0.47), (1, 0.03, 0.86)),
        box((0, -0.485, 0.47), (1, 0.03, 0.86)),
        box((-0.485, 0, 0.47), (0.03, 0.94, 0.86)),
        box((0.485, 0, 0.47), (0.03, 0.94, 0.86)),
        box((0, 0, 0.95), (1, 1, 0.1), "secondary", door="slide"),  # lid
    )
    box_surfaces = (surf((0, 0), (0.9, 0.9), 0.04, inside=True), surf((0, 0), (0.92, 0.92), 1.0))
    add(
        small(
            "Box",
            (0.4, 0.3, 0.25),
            (0.5, 0.375, 0.31),
            box_parts,
            pals(
                dict(primary="#b48a5a", secondary="#a47c4f"),
                dict(primary="#c29a6b", secondary="#b08a5c"),
                dict(primary="#f0f0f0", secondary="#dcdcdc"),
            ),
            mass=0.6,
            receptacle=True,
            openable=True,
            surfaces=box_surfaces,
            variants=(
                Variant("storage"),
                # Shoeboxes: small, flat, brand-coloured with a contrasting lid.
                Variant(
                    "shoebox",
                    size_min=(0.3, 0.18, 0.1),
                    size_max=(0.35, 0.21, 0.125),
                    palettes=pals(
                        dict(primary="#e67e22", secondary="#d35400"),
                        dict(primary="#1c1c1c", secondary="#c0392b"),
                        dict(primary="#f4f4f4", secondary="#2e5e8c"),
                        dict(primary="#7f8c8d", secondary="#2b2b2b"),
                    ),
                    mass=0.3,
                ),
            ),
        )
    )

    add(
        small(
            "BaseballBat",
            (0.07, 0.8, 0.07),
            (0.07, 0.86, 0.07),
            [
                box((0, -0.46, 0.5), (0.55, 0.04, 0.55), "accent"),  # knob
                box((0, -0.25, 0.5), (0.36, 0.4, 0.36), "accent"),  # grip
                box((0, 0.03, 0.5), (0.6, 0.2, 0.6)),  # taper
                box((0, 0.3, 0.5), (0.95, 0.38, 0.95)),  # barrel
            ],
            pals(
                dict(primary="#c8a06a", accent="#2b2b2b"),
                dict(primary="#1c1c1c", accent="#c0392b"),
                dict(primary="#b5b9bd", accent="#1f3f8c"),
            ),
            mass=0.9,
            tags=frozenset({"sport"}),
        )
    )

    add(
        small(
            "BasketBall",
            (0.24, 0.24, 0.24),
            (0.245, 0.245, 0.245),
            [
                sph((0, 0, 0.5), 1.0),
                cyl((0, 0, 0.5), 1.01, 0.03, "dark", collide=False),
            ],
            pals(dict(primary="#d35a1e"), dict(primary="#c4501a")),
            mass=0.6,
            tags=frozenset({"sport", "round"}),
        )
    )

    add(
        small(
            "Plunger",
            (0.12, 0.12, 0.44),
            (0.14, 0.14, 0.5),
            [
                lathe((0, 0, 0.1), 0.2, [(1, 0), (0.95, 0.5), (0.5, 0.9), (0.15, 1)]),
                cyl((0, 0, 0.6), 0.22, 0.8, "secondary"),
            ],
            pals(dict(primary="#b22222", secondary="#8b5a2b"), dict(primary="#1c1c1c", secondary="#f2f2f2")),
            mass=0.4,
            tags=frozenset({"cleaning"}),
        )
    )

    add(
        small(
            "ScrubBrush",
            (0.1, 0.1, 0.36),
            (0.12, 0.12, 0.42),
            [
                lathe((0, 0, 0.25), 0.5, [(0, 0), (0.95, 0), (1, 0.9), (0.9, 1)]),  # holder
                cyl((0, 0, 0.75), 0.2, 0.5, "secondary"),  # handle
            ],
            pals(
                dict(primary="#f4f4f4", secondary="#b5b9bd"),
                dict(primary="#2b2b2b", secondary="#2b2b2b"),
                dict(primary="#9ac7d6", secondary="#f4f4f4"),
            ),
            mass=0.3,
            tags=frozenset({"cleaning"}),
        )
    )

    add(
        small(
            "PaperTowelRoll",
            (0.11, 0.11, 0.25),
            (0.125, 0.125, 0.28),
            [
                cyl((0, 0, 0.5), 1.0, 0.98),
                cyl((0, 0, 0.995), 0.36, 0.01, "#9c7a54", collide=False),
                cyl((0, 0, 0.5), 1.01, 0.02, "accent", collide=False),  # printed band
            ],
            pals(dict(primary="#fbfbf8", accent="#a9cce3"), dict(primary="#f4efe6", accent="#d5dbdb")),
            mass=0.2,
            tags=frozenset({"round"}),
        )
    )

    r_ay = 0.4  # racket head width vs total length
    add(
        small(
            "TennisRacket",
            (0.26, 0.65, 0.03),
            (0.28, 0.7, 0.035),
            [
                cyl((0, 0.2, 0.45), 1.0, 0.9, ay=r_ay),
                cyl((0, 0.2, 0.5), 0.86, 1.0, "light", ay=r_ay, collide=False),  # strings
                box((0, -0.25, 0.5), (0.12, 0.5, 0.9), "secondary"),  # handle
            ],
            pals(
                dict(primary="#1c1c1c", secondary="#f2f2f2"),
                dict(primary="#c0392b", secondary="#1c1c1c"),
                dict(primary="#2e5e8c", secondary="#f2f2f2"),
            ),
            mass=0.3,
            tags=frozenset({"sport"}),
        )
    )

    add(
        small(
            "Dumbbell",
            (0.1, 0.28, 0.1),
            (0.12, 0.34, 0.12),
            [
                box((0, -0.38, 0.5), (1, 0.24, 1)),
                box((0, 0.38, 0.5), (1, 0.24, 1)),
                box((0, 0, 0.5), (0.3, 0.6, 0.3), "metal"),
            ],
            pals(dict(primary="#1c1c1c"), dict(primary="#2f6db5"), dict(primary="#c0392b")),
            mass=5.0,
            tags=frozenset({"sport"}),
        )
    )

    add(
        small(
            "Bottle",
            (0.07, 0.07, 0.22),
            (0.08, 0.08, 0.26),
            [
                lathe((0, 0, 0.5), 1.0, [(0, 0), (1, 0), (1, 0.7), (0.5, 0.85), (0.4, 1)]),
                cyl((0, 0, 0.97), 0.42, 0.06, "secondary"),  # cap
                cyl((0, 0, 0.4), 1.02, 0.25, "accent", collide=False),  # label
            ],
            pals(
                dict(primary="#cfe3ea", secondary="#2f6db5", accent="#ffffff"),
                dict(primary="#b7d7a8", secondary="#2b2b2b", accent="#f4e4c1"),
                dict(primary="#e8e8e8", secondary="#c0392b", accent="#2b2b2b"),
            ),
            mass=0.5,
            tags=frozenset({"drink"}),
        )
    )

    return out


# ------------------------------------------------------------------------ furniture


def _sink_parts(f: float, b: float) -> tuple[Part, ...]:
    """A vanity/sink cabinet: counter top at z=f, basin bottom at z=b (< f), faucet above."""
    mid, band = (b + f) / 2, f - b
    return (
        box((0, -0.03, 0.03), (0.96, 0.9, 0.06), "dark"),  # plinth
        box((0, -0.03, (0.06 + b) / 2), (1, 0.94, b - 0.06), "secondary"),  # cabinet
        box((0, 0.445, (0.06 + b) / 2), (0.008, 0.01, b - 0.14), "dark", collide=False),  # door gap
        box((-0.05, 0.46, b - 0.08), (0.02, 0.02, 0.08), "metal", collide=False),
        box((0.05, 0.46, b - 0.08), (0.02, 0.02, 0.08), "metal", collide=False),
        box((0, 0.03, b + 0.01), (0.72, 0.54, 0.02), "basin"),  # basin floor
        box((0, 0.4, mid), (1, 0.2, band)),  # front rim
        box((0, -0.37, mid), (1, 0.26, band)),  # back ledge
        box((-0.43, 0.03, mid), (0.14, 0.54, band)),
        box((0.43, 0.03, mid), (0.14, 0.54, band)),
        box((0, 0.03, b + 0.035), (0.72, 0.54, 0.03), "basin", collide=False),  # basin glint
        cyl((0, -0.4, (f + 0.97) / 2), 0.06, 0.97 - f, "metal", ay=1.5),  # faucet neck
        box((0, -0.28, 0.955), (0.05, 0.24, 0.03), "metal"),  # spout over basin
        box((-0.1, -0.42, f + 0.025), (0.05, 0.06, 0.05), "metal"),
        box((0.1, -0.42, f + 0.025), (0.05, 0.06, 0.05), "metal"),
    )


def _sink_surfaces(f: float, b: float) -> tuple[Surface, ...]:
    return (
        surf((0, 0.03), (0.68, 0.5), b + 0.02),  # in the basin
        surf((-0.3, -0.37), (0.34, 0.2), f),  # ledge left of the faucet
        surf((0.3, -0.37), (0.34, 0.2), f),  # ledge right of the faucet
    )


def _furniture() -> list[Category]:
    out: list[Category] = []
    add = out.append

    # ---- kitchen
    add(
        furn(
            "CounterTop",
            (1.0, 0.6, 0.9),
            (2.2, 0.65, 0.92),
            [
                box((0, -0.04, 0.05), (0.98, 0.86, 0.1), "dark"),  # recessed toe kick
                box((0, -0.03, 0.5), (1, 0.92, 0.8), "secondary"),  # base cabinets
                box((0, 0, 0.955), (1, 1, 0.09)),  # worktop
                box((0, 0.435, 0.5), (0.006, 0.01, 0.66), "dark", collide=False),  # door gap
                box((0, 0.435, 0.8), (0.98, 0.01, 0.006), "dark", collide=False),  # drawer line
                box((-0.25, 0.445, 0.85), (0.12, 0.02, 0.02), "metal", collide=False),
                box((0.25, 0.445, 0.85), (0.12, 0.02, 0.02), "metal", collide=False),
                box((-0.04, 0.445, 0.65), (0.01, 0.02, 0.1), "metal", collide=False),
                box((0.04, 0.445, 0.65), (0.01, 0.02, 0.1), "metal", collide=False),
            ],
            pals(
                dict(primary="#5f5f5f", secondary="#f2f0eb"),
                dict(primary="#e9e6df", secondary="#2f3e50"),
                dict(primary="#b98a57", secondary="#f2f0eb"),
                dict(primary="#1f1f1f", secondary="#8fa39a"),
                dict(primary="#d6d2ca", secondary="#8b5a2b"),
            ),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0.01), (0.96, 0.9), 1.0),),
            tags=frozenset({"kitchen"}),
        )
    )

    sink_k, sink_v = (0.8, 0.63), (0.83, 0.68)
    add(
        furn(
            "Sink",
            (0.8, 0.6, 1.12),
            (1.0, 0.65, 1.14),
            _sink_parts(*sink_k),
            pals(
                dict(primary="#5f5f5f", secondary="#f2f0eb", basin="#b8bcc0"),
                dict(primary="#e9e6df", secondary="#2f3e50", basin="#c4c8cc"),
                dict(primary="#1f1f1f", secondary="#8fa39a", basin="#a9adb1"),
            ),
            placement="wall",
            receptacle=True,
            surfaces=_sink_surfaces(*sink_k),
            variants=(
                Variant("kitchen"),
                # Bathroom vanity: narrower, white ceramic basin.
                Variant(
                    "vanity",
                    size_min=(0.6, 0.46, 1.0),
                    size_max=(0.9, 0.55, 1.05),
                    parts=_sink_parts(*sink_v),
                    surfaces=_sink_surfaces(*sink_v),
                    palettes=pals(
                        dict(primary="#f4f4f2", secondary="#8b5a2b", basin="#ffffff"),
                        dict(primary="#e8e4dc", secondary="#f2f2f0", basin="#ffffff"),
                        dict(primary="#d9d9d9", secondary="#4a5a6a", basin="#fbfbfb"),
                    ),
                ),
            ),
        )
    )

    add(
        furn(
            "StoveBurner",
            (0.6, 0.6, 0.9),
            (0.76, 0.65, 0.92),
            [
                box((0, -0.02, 0.47), (1, 0.96, 0.94)),  # body
                box((0, -0.02, 0.96), (1, 0.96, 0.04), "dark"),  # cooktop
                *[
                    cyl((x, -0.02 + y, 0.985), 0.32, 0.012, "burner", ay=1.08)
                    for x in (-0.24, 0.24)
                    for y in (-0.21, 0.21)
                ],
                box((0, 0.47, 0.42), (0.86, 0.02, 0.5), "dark", collide=False),  # oven window
                box((0, 0.49, 0.72), (0.7, 0.02, 0.03), "metal", collide=False),  # oven handle
                *[
                    box((x, 0.48, 0.86), (0.06, 0.04, 0.04), "dark", collide=False)
                    for x in (-0.3, -0.1, 0.1, 0.3)
                ],
            ],
            pals(
                dict(primary="#b5b9bd", burner="#3a3a3a"),
                dict(primary="#f2f2f0", burner="#2b2b2b"),
                dict(primary="#2b2b2b", burner="#555555"),
            ),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, -0.02), (0.94, 0.9), 0.99),),
            tags=frozenset({"kitchen", "appliance"}),
        )
    )

    fridge_inside = (0, -0.06)
    add(
        furn(
            "Fridge",
            (0.7, 0.7, 1.7),
            (0.85, 0.8, 1.9),
            [
                box((0, -0.04, 0.03), (1, 0.92, 0.06)),  # base
                box((0, 0.46, 0.03), (1, 0.08, 0.06), "dark"),  # kick grille
                box((0, -0.04, 0.98), (1, 0.92, 0.04)),  # top
                box((0, -0.475, 0.51), (1, 0.05, 0.9)),  # back
                box((-0.475, -0.04, 0.51), (0.05, 0.92, 0.9)),
                box((0.475, -0.04, 0.51), (0.05, 0.92, 0.9)),
                box((0, -0.06, 0.33), (0.9, 0.8, 0.012), "light"),  # glass shelves
                box((0, -0.06, 0.58), (0.9, 0.8, 0.012), "light"),
                box((0, -0.04, 0.72), (0.9, 0.88, 0.02)),  # freezer floor
                box((0, 0.46, 0.53), (1, 0.08, 0.94), "door", door="right"),
            ],
            pals(
                dict(primary="#f4f4f2", door="#f7f7f5", light="#dfe9ee"),
                dict(primary="#b5b9bd", door="#c3c7cb", light="#dfe9ee"),
                dict(primary="#2b2b2b", door="#333333", light="#cfd8dc"),
                dict(primary="#efe6cf", door="#a9c6b8", light="#dfe9ee"),
            ),
            placement="wall",
            receptacle=True,
            openable=True,
            surfaces=(
                surf(fridge_inside, (0.88, 0.8), 0.06, inside=True),
                surf(fridge_inside, (0.88, 0.8), 0.336, inside=True),
                surf(fridge_inside, (0.88, 0.8), 0.586, inside=True),
                surf(fridge_inside, (0.88, 0.8), 0.73, inside=True),
            ),
            tags=frozenset({"kitchen", "appliance"}),
        )
    )

    add(
        furn(
            "Cabinet",
            (0.5, 0.42, 0.8),
            (0.9, 0.6, 0.9),
            [
                box((0, -0.03, 0.04), (0.96, 0.9, 0.08), "dark"),  # plinth
                box((0, -0.03, 0.1), (1, 0.94, 0.04)),  # bottom
                box((0, -0.03, 0.98), (1, 0.94, 0.04)),  # top
                box((0, -0.475, 0.54), (1, 0.05, 0.84)),  # back
                box((-0.475, -0.03, 0.54), (0.05, 0.94, 0.84)),
                box((0.475, -0.03, 0.54), (0.05, 0.94, 0.84)),
                box((0, -0.03, 0.54), (0.9, 0.84, 0.03)),  # inner shelf
                box((0, 0.47, 0.55), (1, 0.06, 0.9), "secondary", door="left"),
            ],
            WOODS
            + pals(
                dict(primary="#f2f0eb", secondary="#2f3e50"), dict(primary="#f2f0eb", secondary="#8fa39a")
            ),
            placement="wall",
            receptacle=True,
            openable=True,
            surfaces=(
                surf((0, -0.03), (0.88, 0.82), 0.12, inside=True),
                surf((0, -0.03), (0.88, 0.82), 0.555, inside=True),
                surf((0, 0), (0.96, 0.96), 1.0),
            ),
        )
    )

    add(
        furn(
            "Microwave",
            (0.45, 0.34, 0.26),
            (0.55, 0.4, 0.31),
            [
                box((0, -0.03, 0.04), (1, 0.94, 0.08)),  # bottom
                box((0, -0.03, 0.96), (1, 0.94, 0.08)),  # top
                box((0, -0.47, 0.5), (1, 0.06, 0.84)),  # back
                box((-0.475, -0.03, 0.5), (0.05, 0.94, 0.84)),
                box((0.37, -0.03, 0.5), (0.26, 0.94, 0.84)),  # electronics column
                box((0.37, 0.47, 0.5), (0.26, 0.06, 1.0), "secondary"),  # control panel
                box((0.37, 0.5 - 0.005, 0.8), (0.16, 0.01, 0.1), "#3ddc84", collide=False),  # display
                box((-0.13, 0.47, 0.5), (0.74, 0.06, 1.0), "dark", door="left"),
            ],
            pals(
                dict(primary="#2b2b2b", secondary="#8e9397"),
                dict(primary="#f2f2f0", secondary="#d9d9d7"),
                dict(primary="#b5b9bd", secondary="#2b2b2b"),
            ),
            placement="none",
            receptacle=True,
            openable=True,
            surfaces=(surf((-0.12, -0.03), (0.62, 0.82), 0.08, inside=True),),
            tags=frozenset({"kitchen", "appliance"}),
        )
    )

    add(
        furn(
            "CoffeeMachine",
            (0.2, 0.3, 0.35),
            (0.26, 0.36, 0.4),
            [
                box((0, 0, 0.04), (1, 1, 0.08), "secondary"),  # drip tray base
                box((0, -0.3, 0.5), (1, 0.4, 1)),  # water tank tower
                box((0, 0.15, 0.88), (1, 0.5, 0.24)),  # brew head
                cyl((0, 0.2, 0.73), 0.2, 0.06, "metal", ay=0.72, collide=False),  # spout
            ],
            pals(
                dict(primary="#2b2b2b", secondary="#555555"),
                dict(primary="#b5b9bd", secondary="#2b2b2b"),
                dict(primary="#c0392b", secondary="#2b2b2b"),
                dict(primary="#f2f2f0", secondary="#9a9a9a"),
            ),
            placement="none",
            receptacle=True,
            surfaces=(surf((0, 0.25), (0.6, 0.4), 0.08),),
            tags=frozenset({"kitchen", "appliance"}),
        )
    )

    add(
        furn(
            "Toaster",
            (0.26, 0.16, 0.18),
            (0.3, 0.19, 0.21),
            [
                box((0, 0, 0.48), (1, 1, 0.96)),
                box((0, -0.18, 0.97), (0.7, 0.14, 0.02), "dark", collide=False),  # bread slots
                box((0, 0.18, 0.97), (0.7, 0.14, 0.02), "dark", collide=False),
                box((0.35, 0.49, 0.6), (0.1, 0.02, 0.08), "dark", collide=False),  # lever
            ],
            pals(
                dict(primary="#b5b9bd"),
                dict(primary="#c0392b"),
                dict(primary="#f2efe6"),
                dict(primary="#2b2b2b"),
            ),
            placement="none",
            tags=frozenset({"kitchen", "appliance"}),
        )
    )

    # ---- tables and seating
    add(
        furn(
            "DiningTable",
            (1.2, 0.8, 0.74),
            (1.8, 1.0, 0.76),
            [
                box((0, 0, 0.97), (1, 1, 0.06)),
                box((0, 0, 0.885), (0.9, 0.86, 0.11), "secondary"),  # apron
                *legs4(0.94, 0.05, 0.075, "secondary", inset=0.04),
            ],
            WOODS + pals(dict(primary="#f2f2f0", secondary="#2b2b2b")),
            placement="open",
            receptacle=True,
            surfaces=(surf((0, 0), (0.96, 0.94), 1.0),),
        )
    )

    add(
        furn(
            "CoffeeTable",
            (0.9, 0.5, 0.38),
            (1.3, 0.7, 0.45),
            [
                box((0, 0, 0.95), (1, 1, 0.1)),
                *legs4(0.9, 0.06, 0.1, "secondary", inset=0.02),
                box((0, 0, 0.2), (0.9, 0.84, 0.04), "secondary"),  # magazine shelf
            ],
            WOODS + pals(dict(primary="#cfe0e6", secondary="#2b2b2b")),
            placement="open",
            receptacle=True,
            surfaces=(surf((0, 0), (0.96, 0.94), 1.0), surf((0, 0), (0.8, 0.74), 0.22)),
        )
    )

    add(
        furn(
            "SideTable",
            (0.4, 0.35, 0.5),
            (0.55, 0.45, 0.65),
            [
                box((0, 0, 0.96), (1, 1, 0.08)),
                box((0, 0, 0.83), (0.92, 0.92, 0.18)),  # drawer box
                box((0, 0.465, 0.83), (0.7, 0.01, 0.13), "secondary", collide=False),  # drawer front
                box((0, 0.48, 0.83), (0.06, 0.02, 0.03), "metal", collide=False),
                *legs4(0.92, 0.08, 0.09, inset=0.02),
                box((0, 0, 0.22), (0.88, 0.86, 0.03)),  # lower shelf
            ],
            WOODS,
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0), (0.94, 0.94), 1.0), surf((0, 0), (0.76, 0.76), 0.235)),
        )
    )

    add(
        furn(
            "Desk",
            (1.0, 0.55, 0.74),
            (1.4, 0.7, 0.76),
            [
                box((0, 0, 0.97), (1, 1, 0.06)),
                box((0.33, -0.02, 0.47), (0.32, 0.92, 0.94)),  # drawer pedestal
                *[
                    box((0.33, 0.445, z), (0.28, 0.01, 0.26), "secondary", collide=False)
                    for z in (0.16, 0.46, 0.76)
                ],
                *[box((0.33, 0.46, z), (0.06, 0.02, 0.03), "metal", collide=False) for z in (0.2, 0.5, 0.8)],
                box((-0.47, -0.02, 0.47), (0.05, 0.92, 0.94)),  # leg panel
                box((-0.08, -0.46, 0.65), (0.74, 0.03, 0.5)),  # modesty panel
            ],
            WOODS + pals(dict(primary="#f2f2f0", secondary="#d9d9d7")),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0), (0.96, 0.94), 1.0),),
        )
    )

    add(
        furn(
            "Chair",
            (0.42, 0.45, 0.85),
            (0.48, 0.52, 0.95),
            [
                box((0, 0.04, 0.49), (1, 0.92, 0.06)),  # seat
                box((0, 0.05, 0.535), (0.9, 0.82, 0.03), "secondary"),  # seat pad
                box((-0.45, 0.45, 0.23), (0.08, 0.08, 0.46)),  # front legs
                box((0.45, 0.45, 0.23), (0.08, 0.08, 0.46)),
                box((-0.45, -0.45, 0.5), (0.08, 0.08, 1.0)),  # back legs, posts
                box((0.45, -0.45, 0.5), (0.08, 0.08, 1.0)),
                box((0, -0.45, 0.8), (0.82, 0.06, 0.3)),  # backrest
                box((0, -0.45, 0.62), (0.82, 0.05, 0.04)),  # rail
            ],
            pals(*[dict(primary=w["primary"], secondary=f["primary"]) for w, f in zip(WOODS, FABRICS)]),
            placement="open",
            receptacle=True,
            surfaces=(surf((0, 0.05), (0.82, 0.78), 0.55),),
        )
    )

    add(
        furn(
            "Stool",
            (0.34, 0.34, 0.62),
            (0.4, 0.4, 0.76),
            [
                cyl((0, 0, 0.96), 1.0, 0.08),  # round seat
                *[
                    box((x, y, 0.46), (0.08, 0.08, 0.92), "secondary")
                    for x in (-0.3, 0.3)
                    for y in (-0.3, 0.3)
                ],
                *[box((0, y, 0.3), (0.6, 0.04, 0.03), "secondary") for y in (-0.3, 0.3)],  # foot rests
                *[box((x, 0, 0.3), (0.04, 0.6, 0.03), "secondary") for x in (-0.3, 0.3)],
            ],
            pals(
                dict(primary="#c49a6c", secondary="#a67c52"),
                dict(primary="#2b2b2b", secondary="#b5b9bd"),
                dict(primary="#8c3b3b", secondary="#2b2b2b"),
                dict(primary="#f2f2f0", secondary="#c49a6c"),
            ),
            placement="open",
            receptacle=True,
            surfaces=(surf((0, 0), (0.66, 0.66), 1.0),),
            tags=frozenset({"round"}),
        )
    )

    def upholstered(n_cushions: int, arm: float) -> list[Part]:
        """Sofa / armchair: low base, cushions, back, two arms, short dark legs."""
        inner = 1 - 2 * arm
        w = inner / n_cushions
        xs = [-inner / 2 + w * (i + 0.5) for i in range(n_cushions)]
        return [
            *legs4(0.08, 0.06, 0.06, "dark", inset=0.03),
            box((0, 0.02, 0.24), (1, 0.96, 0.32)),  # base
            box((0, -0.4, 0.66), (1, 0.2, 0.68)),  # back
            box((-0.5 + arm / 2, 0.06, 0.56), (arm, 0.88, 0.32)),  # arms
            box((0.5 - arm / 2, 0.06, 0.56), (arm, 0.88, 0.32)),
            *[box((x, 0.1, 0.46), (w * 0.98, 0.78, 0.12), "secondary") for x in xs],  # seat cushions
            *[box((x, -0.255, 0.7), (w * 0.98, 0.09, 0.4), "secondary") for x in xs],  # back cushions
        ]

    add(
        furn(
            "Sofa",
            (1.6, 0.85, 0.8),
            (2.3, 0.98, 0.9),
            upholstered(2, 0.08),
            FABRICS,
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0.12), (0.8, 0.64), 0.52),),
        )
    )
    add(
        furn(
            "ArmChair",
            (0.75, 0.75, 0.8),
            (0.92, 0.9, 0.95),
            upholstered(1, 0.16),
            FABRICS,
            placement="corner",
            receptacle=True,
            surfaces=(surf((0, 0.12), (0.64, 0.64), 0.52),),
        )
    )

    add(
        furn(
            "Ottoman",
            (0.5, 0.45, 0.38),
            (0.7, 0.6, 0.45),
            [
                *legs4(0.15, 0.07, 0.08, "dark", inset=0.04),
                box((0, 0, 0.55), (1, 1, 0.8)),
                box((0, 0, 0.975), (0.96, 0.96, 0.05), "secondary"),  # top cushion
                box((0, 0, 0.15 + 0.01), (1.0, 1.0, 0.02), "accent", collide=False),  # piping
            ],
            FABRICS,
            placement="open",
            receptacle=True,
            surfaces=(surf((0, 0), (0.9, 0.9), 1.0),),
        )
    )

    add(
        furn(
            "Bed",
            (1.4, 2.0, 1.0),
            (2.0, 2.15, 1.2),
            [
                *legs4(0.08, 0.05, 0.04, "primary", inset=0.01),
                box((0, 0.02, 0.2), (1, 0.96, 0.24)),  # frame
                box((0, 0.02, 0.42), (0.96, 0.94, 0.2), "light"),  # mattress
                box((0, 0.12, 0.535), (0.99, 0.74, 0.03), "secondary"),  # duvet top
                box((0, 0.485, 0.43), (0.99, 0.03, 0.2), "secondary"),  # duvet overhang, foot
                box((-0.4925, 0.12, 0.43), (0.015, 0.74, 0.2), "secondary", collide=False),  # ... and sides
                box((0.4925, 0.12, 0.43), (0.015, 0.74, 0.2), "secondary", collide=False),
                box((-0.22, -0.36, 0.57), (0.4, 0.14, 0.08), "light"),  # pillows
                box((0.22, -0.36, 0.57), (0.4, 0.14, 0.08), "light"),
                box((0, -0.48, 0.5), (1, 0.04, 1.0)),  # headboard
            ],
            pals(
                *[
                    dict(primary=w["primary"], secondary=f["primary"], light="#f6f4ef")
                    for w, f in zip(WOODS, FABRICS)
                ]
            ),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0.1), (0.9, 0.76), 0.55),),
        )
    )  # clear of pillows

    add(
        furn(
            "Dresser",
            (0.9, 0.45, 0.75),
            (1.4, 0.55, 0.95),
            [
                *legs4(0.08, 0.05, 0.06, "primary", inset=0.02),
                box((0, -0.03, 0.52), (1, 0.94, 0.88)),  # carcass
                box((0, 0, 0.98), (1, 1, 0.04)),  # top
                *[
                    box((x, 0.465, z), (0.46, 0.03, 0.26), "secondary")
                    for x in (-0.245, 0.245)
                    for z in (0.22, 0.5, 0.78)
                ],
                *[
                    box((x, 0.49, z), (0.06, 0.02, 0.03), "metal", collide=False)
                    for x in (-0.245, 0.245)
                    for z in (0.22, 0.5, 0.78)
                ],
            ],
            WOODS,
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0), (0.96, 0.94), 1.0),),
        )
    )

    add(
        furn(
            "Drawer",
            (0.4, 0.38, 0.55),
            (0.5, 0.45, 0.7),
            [
                box((0, -0.03, 0.025), (0.94, 0.9, 0.05), "dark"),  # plinth
                box((0, -0.03, 0.3), (1, 0.94, 0.5)),  # lower body
                box((0, 0.47, 0.18), (0.96, 0.06, 0.24), "secondary"),  # fixed fronts
                box((0, 0.47, 0.44), (0.96, 0.06, 0.24), "secondary"),
                box((0, 0.49, 0.2), (0.1, 0.02, 0.03), "metal", collide=False),
                box((0, 0.49, 0.46), (0.1, 0.02, 0.03), "metal", collide=False),
                box((-0.475, -0.03, 0.755), (0.05, 0.94, 0.41)),  # top compartment
                box((0.475, -0.03, 0.755), (0.05, 0.94, 0.41)),
                box((0, -0.475, 0.755), (1, 0.05, 0.41)),
                box((0, 0, 0.98), (1, 1, 0.04)),  # top
                box((0, 0.47, 0.755), (0.96, 0.06, 0.38), "secondary", door="slide"),  # the drawer
            ],
            WOODS,
            placement="wall",
            receptacle=True,
            openable=True,
            surfaces=(
                surf((0, -0.03), (0.86, 0.82), 0.55, inside=True),
                surf((0, 0), (0.94, 0.94), 1.0),
            ),
        )
    )

    add(
        furn(
            "Shelf",
            (0.6, 0.28, 1.2),
            (1.0, 0.38, 1.9),
            [
                box((-0.475, 0, 0.5), (0.05, 1, 1)),
                box((0.475, 0, 0.5), (0.05, 1, 1)),
                box((0, -0.48, 0.5), (0.9, 0.04, 1)),  # back
                box((0, 0, 0.985), (0.9, 1, 0.03)),  # top
                box((0, 0.02, 0.025), (0.9, 0.96, 0.05), "secondary"),  # plinth
                box((0, 0, 0.06), (0.9, 0.96, 0.02)),  # bottom board
                *[box((0, 0.02, z), (0.9, 0.92, 0.02)) for z in (0.3, 0.53, 0.76)],
            ],
            WOODS
            + pals(
                dict(primary="#f2f2f0", secondary="#d9d9d7"), dict(primary="#2b2b2b", secondary="#1c1c1c")
            ),
            placement="wall",
            receptacle=True,
            surfaces=(
                surf((0, 0.02), (0.86, 0.86), 0.07),
                surf((0, 0.02), (0.86, 0.86), 0.31),
                surf((0, 0.02), (0.86, 0.86), 0.54),
                surf((0, 0.02), (0.86, 0.86), 0.77),
                surf((0, 0), (0.9, 0.9), 1.0),
            ),
        )
    )

    add(
        furn(
            "TVStand",
            (1.2, 0.4, 0.45),
            (1.8, 0.5, 0.6),
            [
                box((0, 0, 0.04), (0.96, 0.9, 0.08), "dark"),
                box((0, 0, 0.11), (1, 1, 0.06)),  # bottom
                box((0, 0, 0.96), (1, 1, 0.08)),  # top
                box((-0.48, 0, 0.53), (0.04, 1, 0.78)),
                box((0.48, 0, 0.53), (0.04, 1, 0.78)),
                box((0, -0.48, 0.53), (0.92, 0.04, 0.78)),  # back
                box((0, 0, 0.53), (0.92, 0.96, 0.04)),  # middle shelf
                box((-0.31, 0.48, 0.53), (0.3, 0.04, 0.78), "secondary"),  # closed side bays
                box((0.31, 0.48, 0.53), (0.3, 0.04, 0.78), "secondary"),
            ],
            WOODS + pals(dict(primary="#2b2b2b", secondary="#3a3a3a")),
            placement="wall",
            receptacle=True,
            surfaces=(
                surf((0, 0), (0.96, 0.92), 1.0),
                surf((0, 0), (0.3, 0.88), 0.55),
                surf((0, 0), (0.3, 0.88), 0.14),
            ),
        )
    )

    # ---- bathroom
    add(
        furn(
            "Bathtub",
            (1.5, 0.7, 0.5),
            (1.7, 0.8, 0.6),
            [
                box((0, 0, 0.1), (1, 1, 0.2)),  # bottom
                box((0, 0.45, 0.6), (1, 0.1, 0.8)),  # front wall
                box((0, -0.43, 0.6), (1, 0.14, 0.8)),  # back wall, wide rim
                box((-0.46, 0.02, 0.6), (0.08, 0.76, 0.8)),
                box((0.46, 0.02, 0.6), (0.08, 0.76, 0.8)),
                box((0, 0.02, 0.21), (0.84, 0.76, 0.02), "secondary"),  # lighter basin
                box((-0.4, 0.02, 0.85), (0.04, 0.06, 0.05), "metal", collide=False),  # spout
                box((-0.41, 0.02, 0.225), (0.02, 0.04, 0.01), "dark", collide=False),  # drain
            ],
            pals(
                dict(primary="#eeeeea", secondary="#fbfbfa"),
                dict(primary="#e6e0d2", secondary="#f6f2e8"),
                dict(primary="#e9edf0", secondary="#f8fbfc"),
            ),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, 0.02), (0.8, 0.72), 0.22), surf((0, -0.43), (0.9, 0.12), 1.0)),
        )
    )

    t_ay = 0.576  # toilet sx / sy
    add(
        furn(
            "Toilet",
            (0.37, 0.65, 0.75),
            (0.41, 0.71, 0.8),
            [
                box((0, 0.05, 0.2), (0.5, 0.5, 0.4)),  # pedestal
                cyl((0, 0.1, 0.47), 0.92, 0.14, ay=t_ay),  # bowl
                cyl((0, 0.1, 0.56), 0.96, 0.04, "secondary", ay=t_ay),  # seat lid
                box((0, -0.23, 0.47), (0.5, 0.14, 0.12)),  # neck to tank
                box((0, -0.39, 0.72), (0.94, 0.22, 0.5)),  # tank
                box((0, -0.39, 0.985), (0.98, 0.22, 0.03)),  # tank lid
                box((0, -0.39, 1.0 - 0.005), (0.2, 0.06, 0.01), "metal", collide=False),  # flush button
            ],
            pals(
                dict(primary="#f6f6f4", secondary="#ffffff"),
                dict(primary="#f2efe8", secondary="#2b2b2b"),
                dict(primary="#f6f6f4", secondary="#c49a6c"),
            ),
            placement="wall",
            receptacle=True,
            surfaces=(surf((0, -0.39), (0.9, 0.2), 1.0), surf((0, 0.1), (0.6, 0.34), 0.58)),
        )
    )

    add(
        furn(
            "TowelHolder",
            (0.45, 0.08, 0.06),
            (0.6, 0.1, 0.08),
            [
                box((-0.46, -0.1, 0.5), (0.06, 0.8, 0.8), "metal"),
                box((0.46, -0.1, 0.5), (0.06, 0.8, 0.8), "metal"),
                box((0, 0.25, 0.75), (0.98, 0.3, 0.3), "metal"),  # bar
            ],
            pals(dict(metal="#b5b9bd"), dict(metal="#c9a65a"), dict(metal="#2b2b2b")),
            placement="wall_mounted",
            mount_height=1.0,
            receptacle=True,
            surfaces=(surf((0, 0.25), (0.9, 0.3), 0.9),),
        )
    )

    add(
        furn(
            "ToiletPaperHanger",
            (0.14, 0.1, 0.06),
            (0.16, 0.12, 0.08),
            [
                box((0, -0.45, 0.5), (1, 0.1, 1), "metal"),  # wall plate
                box((-0.45, -0.05, 0.5), (0.1, 0.8, 0.4), "metal"),
                box((0.45, -0.05, 0.5), (0.1, 0.8, 0.4), "metal"),
                box((0, 0.2, 0.5), (0.9, 0.14, 0.18), "metal"),  # spindle
            ],
            pals(dict(metal="#b5b9bd"), dict(metal="#c9a65a"), dict(metal="#2b2b2b")),
            placement="wall_mounted",
            mount_height=0.7,
            receptacle=True,
            surfaces=(surf((0, 0.2), (0.8, 0.3), 0.6),),
        )
    )

    add(
        furn(
            "GarbageCan",
            (0.26, 0.26, 0.34),
            (0.34, 0.34, 0.45),
            [
                box((0, 0, 0.03), (1, 1, 0.06), "dark"),
                box((0, 0.47, 0.505), (1, 0.06, 0.89)),
                box((0, -0.47, 0.505), (1, 0.06, 0.89)),
                box((-0.47, 0, 0.505), (0.06, 0.88, 0.89)),
                box((0.47, 0, 0.505), (0.06, 0.88, 0.89)),
                box((0, 0.47, 0.975), (1, 0.06, 0.05), "secondary"),  # rim
                box((0, -0.47, 0.975), (1, 0.06, 0.05), "secondary"),
                box((-0.47, 0, 0.975), (0.06, 0.88, 0.05), "secondary"),
                box((0.47, 0, 0.975), (0.06, 0.88, 0.05), "secondary"),
            ],
            pals(
                dict(primary="#b5b9bd", secondary="#2b2b2b"),
                dict(primary="#f2f2f0", secondary="#9a9a9a"),
                dict(primary="#2b2b2b", secondary="#555555"),
                dict(primary="#6fa36f", secondary="#3f6b3f"),
            ),
            placement="corner",
            receptacle=True,
            surfaces=(surf((0, 0), (0.84, 0.84), 0.06),),
        )
    )

    # ---- decor furniture (not receptacles)
    add(
        furn(
            "Television",
            (0.8, 0.2, 0.52),
            (1.2, 0.24, 0.76),
            [  # 32"-55", narrower than a TVStand
                box((0, 0, 0.015), (0.45, 1, 0.03), "dark"),  # foot
                box((0, -0.1, 0.075), (0.08, 0.2, 0.09), "metal"),  # neck
                box((0, -0.1, 0.56), (1, 0.18, 0.88)),  # panel
                box((0, 0.0, 0.565), (0.96, 0.02, 0.82), "screen", collide=False),
            ],
            pals(
                dict(primary="#1c1c1c", screen="#0d1b2a"),
                dict(primary="#8a8d90", screen="#101820"),
                dict(primary="#2b2b2b", screen="#0a1522"),
            ),
            placement="none",
            tags=frozenset({"electronics"}),
        )
    )

    add(
        furn(
            "FloorLamp",
            (0.32, 0.32, 1.5),
            (0.45, 0.45, 1.8),
            [
                cyl((0, 0, 0.01), 0.7, 0.02, "dark"),
                cyl((0, 0, 0.44), 0.06, 0.84, "metal"),
                lathe((0, 0, 0.89), 0.22, [(1, 0), (0.64, 1)], "shade"),
            ],
            pals(
                dict(shade="#f1e6cf"),
                dict(shade="#ffffff", metal="#c9a65a"),
                dict(shade="#d9cbb0", metal="#2b2b2b"),
            ),
            placement="corner",
            tags=frozenset({"light", "round"}),
        )
    )

    add(
        furn(
            "DeskLamp",
            (0.18, 0.18, 0.38),
            (0.25, 0.25, 0.52),
            [
                cyl((0, 0, 0.03), 0.7, 0.06, "secondary"),
                cyl((0, 0, 0.35), 0.08, 0.6, "metal"),
                lathe((0, 0, 0.8), 0.4, [(1, 0), (0.56, 1)], "shade"),
            ],
            pals(
                dict(shade="#f1e6cf", secondary="#2b2b2b"),
                dict(shade="#ffffff", secondary="#c9a65a"),
                dict(shade="#2f6d7a", secondary="#b5b9bd"),
                dict(shade="#e8d9b5", secondary="#8b5a2b"),
            ),
            placement="none",
            tags=frozenset({"light", "round"}),
        )
    )

    add(
        furn(
            "HousePlant",
            (0.35, 0.35, 0.6),
            (0.5, 0.5, 1.1),
            [
                lathe((0, 0, 0.15), 0.3, [(0, 0), (0.4, 0), (0.5, 1)], "pot"),
                cyl((0, 0, 0.35), 0.08, 0.2, "#5a4128"),  # stem
                sph((0, 0, 0.55), 0.8, "leaf", az=0.583),
                sph((0.15, 0.1, 0.75), 0.6, "leaf2", az=0.583),
                sph((-0.15, -0.1, 0.8), 0.55, "leaf", az=0.583),
            ],
            pals(
                dict(pot="#c9744a", leaf="#3f7a3a", leaf2="#4f8f45"),
                dict(pot="#f2f2f0", leaf="#2f6b3a", leaf2="#3d7d48"),
                dict(pot="#2b2b2b", leaf="#5a8f3c", leaf2="#6ba04a"),
            ),
            placement="corner",
            tags=frozenset({"decor", "round"}),
        )
    )

    add(
        furn(
            "Painting",
            (0.5, 0.03, 0.4),
            (1.0, 0.04, 0.8),
            [
                box((0, -0.1, 0.5), (0.86, 0.6, 0.86), "light"),  # canvas
                box((0, 0, 0.96), (1, 1, 0.08)),
                box((0, 0, 0.04), (1, 1, 0.08)),  # frame
                box((-0.47, 0, 0.5), (0.06, 1, 0.84)),
                box((0.47, 0, 0.5), (0.06, 1, 0.84)),
                box((-0.15, 0.22, 0.55), (0.4, 0.04, 0.45), "secondary", collide=False),  # picture
                box((0.18, 0.22, 0.35), (0.35, 0.04, 0.3), "accent", collide=False),
                box((0, 0.22, 0.78), (0.8, 0.04, 0.12), "#7fb3d5", collide=False),
            ],
            pals(
                dict(primary="#c9a65a", light="#efe6d2", secondary="#3d5a80", accent="#c0392b"),
                dict(primary="#2b2b2b", light="#f4f4f2", secondary="#e3a63a", accent="#2f6d7a"),
                dict(primary="#8b5a2b", light="#e9dcc3", secondary="#5b7553", accent="#a0522d"),
            ),
            placement="wall_mounted",
            mount_height=1.3,
            tags=frozenset({"decor"}),
        )
    )

    add(
        furn(
            "Mirror",
            (0.5, 0.03, 0.6),
            (0.8, 0.04, 0.9),
            [
                box((0, -0.1, 0.5), (0.9, 0.8, 0.9), "glass"),
                box((0, 0, 0.975), (1, 1, 0.05)),
                box((0, 0, 0.025), (1, 1, 0.05)),
                box((-0.475, 0, 0.5), (0.05, 1, 0.9)),
                box((0.475, 0, 0.5), (0.05, 1, 0.9)),
            ],
            pals(
                dict(primary="#c9a65a", glass="#d5e1e6"),
                dict(primary="#2b2b2b", glass="#d5e1e6"),
                dict(primary="#f2f2f0", glass="#cfdde3"),
            ),
            placement="wall_mounted",
            mount_height=1.05,
            tags=frozenset({"decor"}),
        )
    )

    return out


# ------------------------------------------------------------------------ structure


def _structure() -> list[Category]:
    white = pals(dict(primary="#f6f6f4"), dict(primary="#e9e6df"))
    return [
        # The floor is sized to the room by the generator; its surface is its top face.
        cat(
            "Floor",
            "structure",
            (1.0, 1.0, 0.02),
            (1.0, 1.0, 0.02),
            [box((0, 0, 0.5), (1, 1, 1))],
            pals(
                dict(primary="#b08a5c"),
                dict(primary="#8b6a48"),
                dict(primary="#d8d4cc"),
                dict(primary="#9a9a96"),
            ),
            receptacle=True,
            surfaces=(surf((0, 0), (1, 1), 1.0),),
            tags=frozenset({"structure"}),
        ),
        cat(
            "Wall",
            "structure",
            (1.0, 0.1, 2.5),
            (6.0, 0.12, 2.7),
            [box((0, 0, 0.5), (1, 1, 1))],
            pals(
                dict(primary="#f2efe8"),
                dict(primary="#e3e8ea"),
                dict(primary="#e9e1d3"),
                dict(primary="#dfe6dc"),
            ),
            tags=frozenset({"structure"}),
        ),
        cat(
            "Window",
            "structure",
            (0.8, 0.1, 1.0),
            (1.4, 0.1, 1.4),
            [
                box((0, 0, 0.5), (0.9, 0.2, 0.9), "glass", collide=False),
                box((0, 0, 0.97), (1, 1, 0.06)),
                box((0, 0, 0.03), (1, 1, 0.06)),
                box((-0.47, 0, 0.5), (0.06, 1, 0.88)),
                box((0.47, 0, 0.5), (0.06, 1, 0.88)),
                box((0, 0, 0.5), (0.03, 0.6, 0.88)),
                box((0, 0, 0.5), (0.9, 0.6, 0.03)),  # mullions
            ],
            pals(
                dict(primary="#f6f6f4", glass="#bcd7e6"),
                dict(primary="#6e4423", glass="#b5d0e0"),
                dict(primary="#2b2b2b", glass="#c2dbe8"),
            ),
            placement="wall_mounted",
            mount_height=1.0,
            tags=frozenset({"structure"}),
        ),
        cat(
            "LightSwitch",
            "structure",
            (0.08, 0.015, 0.12),
            (0.08, 0.015, 0.12),
            [
                box((0, -0.2, 0.5), (1, 0.6, 1)),
                box((0, 0.3, 0.5), (0.3, 0.4, 0.35), "secondary"),
            ],
            pals(dict(primary="#f6f6f4", secondary="#e6e6e2"), dict(primary="#e9e6df", secondary="#d9d4c7")),
            placement="wall_mounted",
            mount_height=1.15,
            tags=frozenset({"structure"}),
        ),
        cat(
            "Faucet",
            "structure",
            (0.06, 0.18, 0.1),
            (0.08, 0.22, 0.12),
            [
                box((0, -0.45, 0.5), (1, 0.1, 1), "metal"),
                box((0, 0.0, 0.6), (0.6, 0.8, 0.35), "metal"),
                box((0, 0.35, 0.35), (0.5, 0.15, 0.3), "metal"),
            ],
            white,
            placement="wall_mounted",
            mount_height=0.65,
            tags=frozenset({"structure"}),
        ),
        cat(
            "ShowerHead",
            "structure",
            (0.12, 0.3, 0.12),
            (0.16, 0.35, 0.16),
            [
                box((0, -0.2, 0.75), (0.15, 0.6, 0.14), "metal"),  # arm from the wall
                cyl((0, 0.28, 0.55), 1.0, 0.3, "metal", ay=0.44),  # head
                cyl((0, 0.28, 0.38), 0.8, 0.04, "dark", ay=0.44, collide=False),  # nozzle face
            ],
            white,
            placement="wall_mounted",
            mount_height=1.85,
            tags=frozenset({"structure"}),
        ),
    ]


def _build() -> dict[str, Category]:
    cats = [*_small_objects(), *_furniture(), *_structure()]
    out: dict[str, Category] = {}
    for c in cats:
        if c.name in out:
            raise ValueError(f"duplicate category {c.name}")
        out[c.name] = c
    return out


CATEGORIES: dict[str, Category] = _build()
