"""A simulated judge for final object placements.

The TIDEE paper (ECCV 2022, Table 1) compares tidying agents by asking human raters
which of two final placements of an object they prefer. We have no raters, so the
judge here scores a placement by the catalog's placement priors for the room
(:func:`tidee.server.catalog.receptacle_weights`): the prior weight of the receptacle
the object ended on, divided by the weight of the object's most likely receptacle in
that room. A score of 1 is the most likely place, 0 a place with no prior weight (or
no receptacle at all). Between two placements the judge prefers the higher score
(:func:`prefer`).

This module also builds the two reference "agents" of the paper's table from a real
episode record (:func:`reference_records`):

* ``AI2THORPlacement``: every object back at its original (pre-mess) receptacle;
* ``MessyPlacement``: every object left where the mess-up put it.

Both "pick" exactly the objects the mess-up moved (``found = picked = moved``), took
0 steps and 0 s.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping
from typing import Any

from tidee.server.catalog import DEFAULT_PLAUSIBILITY, is_plausible, receptacle_weights

__all__ = [
    "AI2THOR_PLACEMENT",
    "MESSY_PLACEMENT",
    "REFERENCE_VARIANTS",
    "DEFAULT_PLAUSIBILITY",
    "judge_score",
    "plausible",
    "prefer",
    "reference_records",
]

AI2THOR_PLACEMENT = "AI2THORPlacement"
MESSY_PLACEMENT = "MessyPlacement"
REFERENCE_VARIANTS: tuple[str, str] = (AI2THOR_PLACEMENT, MESSY_PLACEMENT)


def judge_score(
    category: str, variant: str | None, room_type: str, parent_type: str | None, present: Iterable[str] | None
) -> float:
    """How good a placement looks to the simulated judge, in [0, 1].

    ``category``/``variant``: the object's catalog type and variant (None: none);
    ``room_type``: the room's type; ``parent_type``: the receptacle type the object rests
    on or in (None: no receptacle, e.g. still held, scores 0); ``present``: the
    receptacle types in the actual room (Floor is always considered present; None: any
    receptacle the room type can contain).

    Returns the receptacle's prior weight divided by the largest weight (1.0 for the most
    likely receptacle, 0.0 for one without weight). Because it is relative to the
    maximum, ``judge_score >= threshold`` (and > 0) is exactly
    :func:`tidee.server.catalog.is_plausible`. Raises KeyError (from the catalog) for
    categories without placement priors, unknown variants and unknown room types.
    """
    if parent_type is None:
        return 0.0
    present_list = None if present is None else list(present)
    weights = receptacle_weights(category, variant, room_type, present_list)
    top = max(weights.values())
    if top <= 0:
        return 0.0
    return float(min(1.0, max(0.0, weights.get(parent_type, 0.0) / top)))


def plausible(
    category: str,
    variant: str | None,
    room_type: str,
    parent_type: str | None,
    present: Iterable[str] | None,
    threshold: float = DEFAULT_PLAUSIBILITY,
) -> bool:
    """Whether the simulated judge accepts the placement at all.

    Wraps :func:`tidee.server.catalog.is_plausible`: the receptacle's prior weight is > 0
    and at least ``threshold`` times the largest weight. ``parent_type`` None is never
    plausible.
    """
    if parent_type is None:
        return False
    present_list = None if present is None else list(present)
    return bool(is_plausible(category, variant, room_type, parent_type, present_list, threshold))


def prefer(a_score: float, b_score: float, eps: float = 1e-6) -> float:
    """The judge's preference for placement A over B: 1.0 (A), 0.0 (B) or 0.5 (tie).

    Scores within ``eps`` of each other tie.
    """
    if eps < 0:
        raise ValueError(f"prefer: eps must be >= 0, got {eps}")
    if a_score > b_score + eps:
        return 1.0
    if b_score > a_score + eps:
        return 0.0
    return 0.5


_REF_OBJECT_KEYS = ("moved", "original_parent_type", "messy_parent_type")


def reference_records(record: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The AI2THORPlacement and MessyPlacement records for the configuration of ``record``.

    Each is a deep copy of ``record`` with ``variant`` set to the reference's name,
    ``steps`` and ``wall_s`` 0, ``end_reason`` ``"reference"``, ``reference`` True, and per
    object ``final_parent_type`` = ``original_parent_type`` (AI2THORPlacement) or
    ``messy_parent_type`` (MessyPlacement) and ``found = picked = moved``. Everything
    else (room, seed, mess index, present receptacles, perception, split) is kept, so
    the references line up with the real records of the same configuration.

    Raises ValueError when ``record`` has no ``objects`` list or an object lacks
    ``moved``, ``original_parent_type`` or ``messy_parent_type``.
    """
    if not isinstance(record, Mapping):
        raise ValueError(f"reference_records: expected a record dict, got {type(record).__name__}")
    objects = record.get("objects")
    if not isinstance(objects, (list, tuple)):
        raise ValueError(
            f"reference_records: the record (variant {record.get('variant')!r}, "
            f"room {record.get('room_type')!r}, seed {record.get('seed')!r}, "
            f"mess {record.get('mess_index')!r}) has no 'objects' list"
        )
    for i, obj in enumerate(objects):
        for key in _REF_OBJECT_KEYS:
            if key not in obj:
                raise ValueError(
                    f"reference_records: object {i} ({obj.get('id', '?')!r}) of the record "
                    f"(variant {record.get('variant')!r}, room {record.get('room_type')!r}, "
                    f"seed {record.get('seed')!r}, mess {record.get('mess_index')!r}) "
                    f"is missing key {key!r}"
                )
    out: dict[str, dict[str, Any]] = {}
    for name, source in ((AI2THOR_PLACEMENT, "original_parent_type"), (MESSY_PLACEMENT, "messy_parent_type")):
        rec = copy.deepcopy(dict(record))
        rec["variant"] = name
        rec["steps"] = 0
        rec["wall_s"] = 0.0
        rec["end_reason"] = "reference"
        rec["reference"] = True
        for obj in rec["objects"]:
            moved = bool(obj["moved"])
            obj["final_parent_type"] = obj[source]
            obj["found"] = moved
            obj["picked"] = moved
        out[name] = rec
    return out
