"""The shape of catalog data: what a category, a part, a surface and a variant are.

A category's geometry is a *recipe*: a list of primitive parts laid out inside the
object's bounding box in normalised coordinates, so one recipe draws every size the
category's size range allows. The builder in ``server/world/bodies.py`` turns a recipe
plus a sampled size and palette into PyBullet bodies.

Local frame of every object (before its yaw in the room):
  * origin at the centre of the bottom face of the bounding box;
  * +x to the object's right, +y towards its *front* (the side a person uses: a sofa's
    seat, a fridge's door, a TV's screen), +z up;
  * a part's ``center`` is (x, y, z) with x, y in [-0.5, 0.5] and z in [0, 1], in units
    of the bounding-box size (sx, sy, sz); its ``extent`` is its full size along x, y, z
    in the same units.  So ``Part("box", (0, 0, 0.95), (1, 1, 0.1))`` is a slab 10 % of
    the height thick at the top of the box: a table top.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

ShapeKind = Literal["box", "cylinder", "sphere", "lathe"]
# Where a part's colour comes from: a role in the instance's palette, or a fixed "#rrggbb".
ColorRole = str
Hinge = Literal["left", "right", "top", "bottom", "slide"]


@dataclass(frozen=True)
class Part:
    """One primitive of a recipe.

    shape:
      * ``box``: a cuboid of the given extent;
      * ``cylinder``: axis along z; radius = extent[0] * sx / 2 (extent[1] is ignored
        for the radius but documents intent: keep it equal to extent[0] * sx / sy);
      * ``sphere``: radius = extent[0] * sx / 2;
      * ``lathe``: a surface of revolution about z; ``profile`` lists (r, z) pairs with r
        as a fraction of sx / 2 and z in [0, 1] of the part's own height
        extent[2] * sz, bottom to top.  Bowls, vases, bottles, lamp shades, plates.
    color: a palette role ("primary", "secondary", "accent", "metal", "dark", "light")
      or a literal "#rrggbb".
    door: ``None`` for a rigid part; otherwise the part moves when the object is
      opened: a hinge side ("left", "right", "top", "bottom": rotates 90° about that
      edge) or "slide" (drawer: moves out along +y by its own depth).
    collide: False for purely visual details (handles, knobs, screen faces) that
      should not take part in physics.
    """

    shape: ShapeKind
    center: tuple[float, float, float]
    extent: tuple[float, float, float]
    color: ColorRole = "primary"
    profile: tuple[tuple[float, float], ...] = ()
    door: Hinge | None = None
    collide: bool = True


@dataclass(frozen=True)
class Surface:
    """A horizontal area objects can rest on, in the same normalised frame.

    ``z`` is the height of the surface as a fraction of sz; ``center``/``extent`` are the
    (x, y) centre and full (x, y) size. ``inside`` marks a surface behind a door or in a
    drawer: reachable only when the object is open.
    """

    center: tuple[float, float]
    extent: tuple[float, float]
    z: float
    inside: bool = False


@dataclass(frozen=True)
class Variant:
    """A sub-category whose look (size, palette, shape) changes where it belongs.

    Fields left ``None`` inherit the category's. ``name`` is unique within a category
    and is what placement priors key on.
    """

    name: str
    size_min: tuple[float, float, float] | None = None
    size_max: tuple[float, float, float] | None = None
    palettes: tuple[dict[str, str], ...] | None = None
    parts: tuple[Part, ...] | None = None
    surfaces: tuple[Surface, ...] | None = None
    mass: float | None = None


Placement = Literal["wall", "corner", "open", "floor", "wall_mounted", "none"]


@dataclass(frozen=True)
class Category:
    """One object type, named as AI2THOR names it.

    size_min / size_max: (sx, sy, sz) in metres, sampled uniformly per instance.
    palettes: each a dict role -> "#rrggbb"; one is chosen per instance.
    mass: kg, for pickupable objects (throw distance depends on it, as in AI2THOR).
    kind: "small" objects are placed on receptacles; "furniture" is placed in the room
      layout; "structure" is walls, floor, windows and the like.
    placement: for furniture, how the layout places it (against a wall, in a corner,
      in the open, or mounted on a wall at some height).
    """

    name: str
    kind: Literal["small", "furniture", "structure"]
    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]
    parts: tuple[Part, ...]
    palettes: tuple[dict[str, str], ...]
    pickupable: bool = False
    receptacle: bool = False
    openable: bool = False
    mass: float = 1.0
    surfaces: tuple[Surface, ...] = ()
    variants: tuple[Variant, ...] = ()
    placement: Placement = "none"
    # Height above the floor of a wall-mounted object's bottom (metres).
    mount_height: float = 0.0
    tags: frozenset[str] = field(default_factory=frozenset)

    def variant(self, name: str | None) -> Variant | None:
        if name is None:
            return None
        for v in self.variants:
            if v.name == name:
                return v
        raise KeyError(
            f"category {self.name} has no variant {name!r}; known: {[v.name for v in self.variants]}"
        )
