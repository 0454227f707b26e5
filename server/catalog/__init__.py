"""The object catalog: categories, placement priors and room templates.

Everything is loaded and validated once, at import; the module-level objects are
read-only (``PRIORS`` and ``ROOM_TEMPLATES`` are frozen: mappings are
``MappingProxyType`` and lists are tuples).

* ``CATEGORIES``: name -> :class:`Category` (see ``categories.py`` for the recipes).
* ``PRIORS``: ``{category: {variant | "*": {room_type: {receptacle_type: weight}}}}``.
  A variant's entry for a room replaces the ``"*"`` entry for that room as a whole.
* ``ROOM_TEMPLATES``: per room type, ``size`` ([[xmin, xmax], [ymin, ymax]] m),
  ``furniture`` (list of ``{"type", "count": [min, max], "required"}`` plus optional
  ``"on"``: the furniture type it stands on (placed on that host's top surface, facing the
  same way), ``"near"``: a furniture type it should be placed next to, ``"variant"``: the
  variant to build), ``small`` (category -> frequency weight), ``variant_weights``
  (category -> {variant: weight}; a category with variants but no entry samples them
  uniformly) and ``n_small`` ([min, max] number of small objects).

Plausibility rule used by the judge (``is_plausible``): a receptacle is plausible for an
object when its prior weight is positive and at least ``threshold`` times the weight of
the object's most likely receptacle in that room. Being relative to the maximum, the
rule does not change when the distribution is renormalised over the receptacles present.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

from tidee.protocol.vocab import ROOM_TYPES

from .categories import CATEGORIES
from .schema import Category, Part, Surface, Variant

__all__ = [
    "CATEGORIES",
    "PRIORS",
    "ROOM_TEMPLATES",
    "ROOM_TYPES",
    "Look",
    "look",
    "sample_size",
    "receptacle_types",
    "receptacle_weights",
    "is_plausible",
    "variant_weights",
    "validate_catalog",
    "load_priors",
    "load_room_templates",
]

_DIR = Path(__file__).parent
_HEX = re.compile(r"^#[0-9a-fA-F]{6}$")
_TOL = 0.02  # parts may poke out of the box by 2 % of a side (rounding in recipes)
DEFAULT_PLAUSIBILITY = 0.1


def load_priors() -> dict[str, Any]:
    """A fresh, mutable copy of priors.json (for tools and tests; the module uses PRIORS)."""
    return json.loads((_DIR / "priors.json").read_text())


def load_room_templates() -> dict[str, Any]:
    """A fresh, mutable copy of rooms.json."""
    return json.loads((_DIR / "rooms.json").read_text())


def _freeze(x: Any) -> Any:
    if isinstance(x, dict):
        return MappingProxyType({k: _freeze(v) for k, v in x.items()})
    if isinstance(x, list):
        return tuple(_freeze(v) for v in x)
    return x


# ----------------------------------------------------------------- resolved looks


@dataclass(frozen=True)
class Look:
    """A category's geometry and appearance with a variant's overrides applied."""

    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]
    parts: tuple[Part, ...]
    palettes: tuple[dict[str, str], ...]
    surfaces: tuple[Surface, ...]
    mass: float


def _look(cat: Category, var: Variant | None) -> Look:
    def pick(name: str) -> Any:
        v = getattr(var, name) if var is not None else None
        return getattr(cat, name) if v is None else v

    return Look(
        pick("size_min"), pick("size_max"), pick("parts"), pick("palettes"), pick("surfaces"), pick("mass")
    )


def look(category: str, variant: str | None = None, categories: Mapping[str, Category] | None = None) -> Look:
    cat = (categories or CATEGORIES)[category]
    return _look(cat, cat.variant(variant))


class _Rng(Protocol):
    def random(self) -> float: ...


def sample_size(category: str, variant: str | None, rng: _Rng) -> tuple[float, float, float]:
    """Sample an instance size: ONE fraction t for all axes, so proportions stay coherent.

    Recipes rely on this (round parts have radii tied to sx), see categories.py.
    ``rng`` is anything with ``.random()`` (``random.Random``, ``numpy.random.Generator``).
    """
    lk = look(category, variant)
    t = float(rng.random())
    return tuple(a + t * (b - a) for a, b in zip(lk.size_min, lk.size_max))  # type: ignore[return-value]


# ------------------------------------------------------------------------- priors


def receptacle_types(
    room_type: str, rooms: Mapping[str, Any] | None = None, categories: Mapping[str, Category] | None = None
) -> frozenset[str]:
    """Receptacle types a room of this type can contain: its furniture receptacles, the
    receptacle small objects it lists (Box) and the Floor."""
    rooms = ROOM_TEMPLATES if rooms is None else rooms
    cats = CATEGORIES if categories is None else categories
    tpl = rooms[room_type]
    names = {f["type"] for f in tpl["furniture"]} | set(tpl["small"]) | {"Floor"}
    return frozenset(n for n in names if n in cats and cats[n].receptacle)


def _table(
    priors: Mapping[str, Any], category: str, variant: str | None, room_type: str
) -> Mapping[str, float] | None:
    entry = priors[category]
    if variant is not None and room_type in entry.get(variant, {}):
        return entry[variant][room_type]
    return entry.get("*", {}).get(room_type)


def _normalised(w: Mapping[str, float]) -> dict[str, float]:
    total = sum(w.values())
    return {k: v / total for k, v in sorted(w.items(), key=lambda kv: -kv[1])} if total > 0 else {}


def receptacle_weights(
    category: str, variant: str | None, room_type: str, present: Iterable[str] | None = None
) -> dict[str, float]:
    """Prior distribution over receptacle types for an object in a room, summing to 1.

    1. The table for (category, variant, room) from PRIORS (variant entry, else "*").
       If the category has no table for this room (an object carried elsewhere), the
       mean of its normalised tables in the other rooms is used instead, restricted to
       the receptacle types this room type can contain.
    2. If ``present`` is given (receptacle types in the actual room; Floor is always
       considered present), the distribution is restricted to them and renormalised.
    3. If nothing is left after restricting, the result is uniform over the candidate
       receptacles (``present``, else the room type's receptacle types): the object has
       no preferred place there, so no place is wrong.

    Sorted by decreasing weight. Raises KeyError for categories without priors (not
    pickupable) and unknown variants.
    """
    if category not in PRIORS:
        raise KeyError(f"no placement prior for {category!r} (only pickupable categories have one)")
    CATEGORIES[category].variant(variant)  # validates the variant name
    if room_type not in ROOM_TEMPLATES:
        raise KeyError(f"unknown room type {room_type!r}; known: {list(ROOM_TEMPLATES)}")
    room_recs = receptacle_types(room_type)
    table = _table(PRIORS, category, variant, room_type)
    if table is not None:
        weights = dict(table)
    else:
        weights = {}
        others = [
            t for r in ROOM_TYPES if r != room_type if (t := _table(PRIORS, category, variant, r)) is not None
        ]
        for t in others:
            for rec, w in _normalised(t).items():
                if rec in room_recs:
                    weights[rec] = weights.get(rec, 0.0) + w / len(others)
    candidates = room_recs
    if present is not None:
        candidates = frozenset(p for p in present if p in CATEGORIES and CATEGORIES[p].receptacle) | {"Floor"}
        weights = {k: v for k, v in weights.items() if k in candidates}
    out = _normalised(weights)
    if not out:
        out = {k: 1.0 / len(candidates) for k in sorted(candidates)}
    return out


def is_plausible(
    category: str,
    variant: str | None,
    room_type: str,
    receptacle_type: str,
    present: Iterable[str] | None = None,
    threshold: float = DEFAULT_PLAUSIBILITY,
) -> bool:
    """True when the receptacle's prior weight is > 0 and >= threshold × the largest weight.

    With the default 0.1: a Mug in a Kitchen is plausible on a CounterTop, DiningTable,
    Shelf, in a Cabinet, Sink or CoffeeMachine, but not in the Microwave or on the Floor.
    """
    w = receptacle_weights(category, variant, room_type, present)
    x = w.get(receptacle_type, 0.0)
    return x > 0 and x >= threshold * max(w.values())


def variant_weights(category: str, room_type: str) -> dict[str | None, float]:
    """Normalised sampling weights of a category's variants in a room type.

    {None: 1.0} for categories without variants; uniform when the template gives none.
    """
    cat = CATEGORIES[category]
    if not cat.variants:
        return {None: 1.0}
    given = ROOM_TEMPLATES[room_type].get("variant_weights", {}).get(category)
    w = dict(given) if given else {v.name: 1.0 for v in cat.variants}
    return _normalised(w)  # type: ignore[return-value]


# --------------------------------------------------------------------- validation


def _round_half_extents(p: Part, s: tuple[float, float, float]) -> tuple[float, float, float]:
    """Half extents in normalised units of a part at size s (round parts tie radii to sx)."""
    sx, sy, sz = s
    e = p.extent
    if p.shape == "box":
        return e[0] / 2, e[1] / 2, e[2] / 2
    r = e[0] / 2  # radius / sx (lathe: at r == 1)
    hz = r * sx / sz if p.shape == "sphere" else e[2] / 2
    return r, r * sx / sy, hz


def _check_parts(
    where: str,
    parts: tuple[Part, ...],
    sizes: Iterable[tuple[float, float, float]],
    palettes: tuple[dict[str, str], ...],
) -> None:
    if not parts:
        raise ValueError(f"{where}: no parts")
    if not palettes:
        raise ValueError(f"{where}: no palettes")
    for pal in palettes:
        for role, col in pal.items():
            if not _HEX.match(col):
                raise ValueError(f"{where}: palette role {role!r} has bad colour {col!r}")
    sizes = list(sizes)
    for i, p in enumerate(parts):
        tag = f"{where} part {i} ({p.shape} at {p.center})"
        if p.shape not in ("box", "cylinder", "sphere", "lathe"):
            raise ValueError(f"{tag}: unknown shape")
        if min(p.extent) <= 0:
            raise ValueError(f"{tag}: extent must be positive, got {p.extent}")
        if p.color.startswith("#"):
            if not _HEX.match(p.color):
                raise ValueError(f"{tag}: bad colour {p.color!r}")
        else:
            for pal in palettes:
                if p.color not in pal:
                    raise ValueError(f"{tag}: colour role {p.color!r} missing from palette {pal}")
        if p.shape == "lathe":
            prof = p.profile
            if len(prof) < 2 or any(not (0 <= r <= 1 and 0 <= z <= 1) for r, z in prof):
                raise ValueError(f"{tag}: lathe profile must have >= 2 (r, z) points in [0, 1]: {prof}")
            if any(b[1] < a[1] for a, b in zip(prof, prof[1:])):
                raise ValueError(f"{tag}: lathe profile z must not decrease: {prof}")
            if abs(max(r for r, _ in prof) - 1) > 1e-6:
                raise ValueError(f"{tag}: lathe profile must reach r = 1 (extent[0] sets the diameter)")
        elif p.profile:
            raise ValueError(f"{tag}: only lathe parts take a profile")
        for s in sizes:
            h = _round_half_extents(p, s)
            lo = [p.center[k] - h[k] for k in range(3)]
            hi = [p.center[k] + h[k] for k in range(3)]
            if (
                min(lo[0], lo[1]) < -0.5 - _TOL
                or max(hi[0], hi[1]) > 0.5 + _TOL
                or lo[2] < -_TOL
                or hi[2] > 1 + _TOL
            ):
                raise ValueError(
                    f"{tag}: outside the bounding box at size {s}: "
                    f"spans x {lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f}, "
                    f"z {lo[2]:.3f}..{hi[2]:.3f}"
                )


def _check_surfaces(where: str, surfaces: tuple[Surface, ...], openable: bool) -> None:
    for s in surfaces:
        if not (0 <= s.z <= 1) or min(s.extent) <= 0:
            raise ValueError(f"{where}: bad surface {s}")
        for k in range(2):
            if s.center[k] - s.extent[k] / 2 < -0.5 - 1e-9 or s.center[k] + s.extent[k] / 2 > 0.5 + 1e-9:
                raise ValueError(f"{where}: surface {s} outside the bounding box")
        if s.inside and not openable:
            raise ValueError(f"{where}: inside surface on a category that does not open")


def _check_category(c: Category) -> None:
    w = f"category {c.name}"
    if c.kind not in ("small", "furniture", "structure"):
        raise ValueError(f"{w}: unknown kind {c.kind!r}")
    if c.pickupable and c.kind != "small":
        raise ValueError(f"{w}: pickupable objects must be kind 'small'")
    if c.kind == "small" and not c.pickupable:
        raise ValueError(f"{w}: small objects must be pickupable")
    if c.pickupable and c.mass <= 0:
        raise ValueError(f"{w}: pickupable objects need a positive mass")
    if c.placement == "wall_mounted" and c.mount_height <= 0:
        raise ValueError(f"{w}: wall_mounted needs mount_height > 0")
    names = [v.name for v in c.variants]
    if len(set(names)) != len(names) or "*" in names:
        raise ValueError(f"{w}: variant names must be unique and not '*': {names}")
    for var in (None, *c.variants):
        lk = _look(c, var)
        wv = w if var is None else f"{w} variant {var.name}"
        if any(a <= 0 or b < a for a, b in zip(lk.size_min, lk.size_max)):
            raise ValueError(f"{wv}: bad size range {lk.size_min}..{lk.size_max}")
        _check_parts(wv, lk.parts, (lk.size_min, lk.size_max), lk.palettes)
        doors = [p for p in lk.parts if p.door is not None]
        if c.openable and not doors:
            raise ValueError(f"{wv}: openable but no door part")
        if doors and not c.openable:
            raise ValueError(f"{wv}: has a door part but is not openable")
        if c.receptacle and not lk.surfaces:
            raise ValueError(f"{wv}: receptacle without surfaces")
        if lk.surfaces and not c.receptacle:
            raise ValueError(f"{wv}: surfaces on a non-receptacle")
        if c.openable and not any(s.inside for s in lk.surfaces):
            raise ValueError(f"{wv}: openable but no inside surface")
        _check_surfaces(wv, lk.surfaces, c.openable)


def _check_priors(priors: Mapping[str, Any], rooms: Mapping[str, Any], cats: Mapping[str, Category]) -> None:
    recs = {r: receptacle_types(r, rooms, cats) for r in rooms}
    for name, entry in priors.items():
        w = f"priors[{name!r}]"
        if name not in cats:
            raise ValueError(f"{w}: unknown category")
        if not cats[name].pickupable:
            raise ValueError(f"{w}: {name} is not pickupable, so it needs no placement prior")
        known = {v.name for v in cats[name].variants}
        for var, by_room in entry.items():
            if var != "*" and var not in known:
                raise ValueError(f"{w}: unknown variant {var!r}; known: {sorted(known)}")
            for room, table in by_room.items():
                wr = f"{w}[{var!r}][{room!r}]"
                if room not in rooms:
                    raise ValueError(f"{wr}: unknown room type")
                if not table:
                    raise ValueError(f"{wr}: empty table")
                for rec, x in table.items():
                    if rec not in cats:
                        raise ValueError(f"{wr}: unknown receptacle {rec!r}")
                    if not cats[rec].receptacle:
                        raise ValueError(f"{wr}: {rec!r} is not a receptacle")
                    if rec not in recs[room]:
                        raise ValueError(
                            f"{wr}: receptacle {rec!r} never appears in a {room} "
                            f"(its template has {sorted(recs[room])})"
                        )
                    if not isinstance(x, (int, float)) or x <= 0:
                        raise ValueError(f"{wr}: weight for {rec!r} must be a positive number, got {x!r}")
    for name, c in cats.items():
        if c.pickupable and name not in priors:
            raise ValueError(f"category {name}: pickupable but has no placement prior")


def _check_rooms(rooms: Mapping[str, Any], priors: Mapping[str, Any], cats: Mapping[str, Category]) -> None:
    if set(rooms) != set(ROOM_TYPES):
        raise ValueError(f"room templates must be exactly {ROOM_TYPES}, got {sorted(rooms)}")
    used: set[str] = set()
    for room, tpl in rooms.items():
        w = f"room {room}"
        (x0, x1), (y0, y1) = tpl["size"]
        if not (0 < x0 <= x1 and 0 < y0 <= y1):
            raise ValueError(f"{w}: bad size {tpl['size']}")
        types = [f["type"] for f in tpl["furniture"]]
        for f in tpl["furniture"]:
            t = f["type"]
            wf = f"{w} furniture {t}"
            if t not in cats or cats[t].kind == "small":
                raise ValueError(f"{wf}: not a furniture or structure category")
            lo, hi = f["count"]
            if not (0 <= lo <= hi):
                raise ValueError(f"{wf}: bad count {f['count']}")
            if bool(f["required"]) != (lo >= 1):
                raise ValueError(f"{wf}: required must be true exactly when count[0] >= 1")
            for key in ("on", "near"):
                host = f.get(key)
                if host is not None and host not in types:
                    raise ValueError(f"{wf}: {key!r} names {host!r}, which is not in the room's furniture")
            if f.get("on") is not None and not cats[f["on"]].receptacle:
                raise ValueError(f"{wf}: stands on {f['on']!r}, which has no surface")
            if f.get("variant") is not None and f["variant"] not in {v.name for v in cats[t].variants}:
                raise ValueError(f"{wf}: unknown variant {f['variant']!r}")
        n0, n1 = tpl["n_small"]
        if not (0 < n0 <= n1):
            raise ValueError(f"{w}: bad n_small {tpl['n_small']}")
        for name, x in tpl["small"].items():
            if name not in cats or not cats[name].pickupable:
                raise ValueError(f"{w}: small object {name!r} is not a pickupable category")
            if x <= 0:
                raise ValueError(f"{w}: small weight for {name!r} must be positive")
            used.add(name)
            vw = tpl.get("variant_weights", {}).get(name)
            known = {v.name for v in cats[name].variants}
            if vw is not None:
                bad = set(vw) - known
                if bad or not vw or min(vw.values()) <= 0:
                    raise ValueError(f"{w}: bad variant_weights for {name}: {vw} (known {sorted(known)})")
            for var in vw or known or [None]:
                if name in priors and _table(priors, name, var, room) is None:
                    raise ValueError(f"{w}: {name} (variant {var}) appears here but has no prior for {room}")
        for name in tpl.get("variant_weights", {}):
            if name not in tpl["small"]:
                raise ValueError(f"{w}: variant_weights for {name!r}, which is not in its small objects")
    for name, c in cats.items():
        if c.pickupable and name not in used:
            raise ValueError(f"category {name}: pickupable but in no room's small objects")


def validate_catalog(
    categories: Mapping[str, Category] | None = None,
    priors: Mapping[str, Any] | None = None,
    rooms: Mapping[str, Any] | None = None,
) -> None:
    """Check the catalog is self-consistent; raise ValueError naming the first problem.

    Defaults to the loaded catalog; pass modified copies to check those instead.
    """
    cats = CATEGORIES if categories is None else categories
    priors = PRIORS if priors is None else priors
    rooms = ROOM_TEMPLATES if rooms is None else rooms
    for key, c in cats.items():
        if key != c.name:
            raise ValueError(f"category keyed {key!r} is named {c.name!r}")
        _check_category(c)
    _check_rooms(rooms, priors, cats)
    _check_priors(priors, rooms, cats)


PRIORS: Mapping[str, Any] = _freeze(load_priors())
ROOM_TEMPLATES: Mapping[str, Any] = _freeze(load_room_templates())
validate_catalog()
