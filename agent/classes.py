"""The categories the agent perceives and reasons about, with their flags.

Taken from the catalog (data only, no simulator): every category except the structure
the agent never acts on (walls; the floor is handled geometrically, at z = 0).
"""

from __future__ import annotations

from tidee.server.catalog import CATEGORIES

_STRUCTURE = frozenset({"Floor", "Wall"})

CLASSES: tuple[str, ...] = tuple(sorted(n for n in CATEGORIES if n not in _STRUCTURE))
CLASS_INDEX: dict[str, int] = {n: i for i, n in enumerate(CLASSES)}
RECEPTACLES: frozenset[str] = frozenset(n for n in CLASSES if CATEGORIES[n].receptacle)
PICKUPABLE: frozenset[str] = frozenset(n for n in CLASSES if CATEGORIES[n].pickupable)
# Openable furniture (doors, drawers): what a rearrangement's openness changes are about.
OPENABLE: frozenset[str] = frozenset(
    n for n in CLASSES if CATEGORIES[n].openable and not CATEGORIES[n].pickupable
)
# Receptacles an object is put *on or in*, in the order the agent prefers to try them.
PLACEABLE_RECEPTACLES: frozenset[str] = RECEPTACLES - PICKUPABLE

# Categories with sub-category variants (a small vs a large vase): the look, and the size
# that tells them apart, changes where they belong.
WITH_VARIANTS: frozenset[str] = frozenset(n for n in CLASSES if CATEGORIES[n].variants)
