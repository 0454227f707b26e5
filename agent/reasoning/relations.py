"""Spatial relations between tracked objects (TIDEE supplement: centroid relations, Memex graph).

Two families, both in the start frame (x forward, y left, z up, metres, floor at z = 0):

* **Centroid relations** for the out-of-place language classifier: each object is an
  :class:`ObjectRef` (centroid, optional axis-aligned box, receptacle flag). The relations
  ``next_to``, ``supported_by`` and ``closest_to`` are turned into the paper's paragraph,
  e.g. "The pillow is next to the side table. The pillow is supported by the side table.
  The pillow is closest to the mug."
* **Box relations** for the Memex scene graph, from oriented boxes :class:`Box3D`:
  ``above``, ``below``, ``supported_by``, ``next_to``, ``aligned_with`` and ``facing``.

Everything here is pure and deterministic; ties keep the input order.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FLOOR",
    "FACING_CLASSES",
    "ObjectRef",
    "words",
    "supported_by",
    "next_to",
    "closest_to",
    "centroid_relations",
    "relation_paragraph",
    "Box3D",
    "BoxRelationParams",
    "box_relations",
]

FLOOR = "Floor"
Vec3 = tuple[float, float, float]


def _vec3(v: Sequence[float], name: str) -> Vec3:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers (metres), got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


# ---------------------------------------------------------------------------- centroid relations
@dataclass(frozen=True)
class ObjectRef:
    """A tracked object as the relation rules see it.

    id: tracker id (any hashable; the target is excluded from ``others`` by id).
    label: catalog category (AI2THOR type name, e.g. "SideTable").
    centroid: (x, y, z) metres, start frame.
    box_min, box_max: optional axis-aligned 3D box corners (metres, start frame); both or
        neither.
    receptacle: whether things can be put on/in it.
    """

    id: object
    label: str
    centroid: Vec3
    box_min: Vec3 | None = None
    box_max: Vec3 | None = None
    receptacle: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "centroid", _vec3(self.centroid, "centroid"))
        if (self.box_min is None) != (self.box_max is None):
            raise ValueError(f"object {self.id!r}: give both box_min and box_max or neither")
        if self.box_min is not None and self.box_max is not None:
            lo, hi = _vec3(self.box_min, "box_min"), _vec3(self.box_max, "box_max")
            if any(a > b for a, b in zip(lo, hi)):
                raise ValueError(f"object {self.id!r}: box_min {lo} exceeds box_max {hi}")
            object.__setattr__(self, "box_min", lo)
            object.__setattr__(self, "box_max", hi)

    @property
    def has_box(self) -> bool:
        return self.box_min is not None


Support = ObjectRef | str


def words(label: str) -> str:
    """AI2THOR CamelCase label to lower-case words.

    "SideTable" -> "side table", "TVStand" -> "tv stand", "CD" -> "cd",
    "AlarmClock" -> "alarm clock", "Floor" -> "floor". Underscores, dashes and spaces
    also separate words.
    """
    parts = re.findall(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+", label)
    if not parts:
        raise ValueError(f"label {label!r} has no words")
    return " ".join(p.lower() for p in parts)


def _dist(a: ObjectRef, b: ObjectRef) -> float:
    return math.dist(a.centroid, b.centroid)


def _others(target: ObjectRef, others: Sequence[ObjectRef]) -> list[ObjectRef]:
    return [o for o in others if o.id != target.id]


def _by_distance(target: ObjectRef, objs: Sequence[ObjectRef]) -> list[ObjectRef]:
    return sorted(objs, key=lambda o: _dist(target, o))  # stable: ties keep input order


WALLED_CONTAINERS = frozenset({"Box", "GarbageCan"})
"""Receptacles with walls down to the floor: what lies within their footprint is in them,
however low it lies (nothing on the floor can be under them)."""


def supported_by(
    target: ObjectRef,
    others: Sequence[ObjectRef],
    floor_z: float = 0.0,
    xy_margin_m: float = 0.1,
    top_tol_m: float = 0.05,
    floor_band_m: float = 0.2,
    height_weight: float = 4.0,
    off_floor_m: float = 0.05,
) -> Support:
    """The receptacle the target rests on, or ``"Floor"``. Only receptacles are candidates.

    Rules, first match wins (metres, start frame):
      1. Surface: receptacles with a box whose (x, y) extent, grown by ``xy_margin_m``,
         contains the target centroid's (x, y) and whose top (box_max z) is at most the
         target's bottom + ``top_tol_m`` (bottom: its box_min z when it has a box, else its
         centroid z): the one that best explains the target resting on it, i.e. the least
         ``height_weight`` x (bottom - top) + (how far the centroid lies outside its
         unexpanded footprint): a surface at the right height beats one merely under it;
         nearest on ties. Using the bottom keeps a tall bottle off the microwave beside it.
      2. Low shelf: a target with a box whose bottom is at least ``off_floor_m`` above the
         floor and whose centroid lies inside a receptacle's box (x, y within its footprint,
         not grown): the smallest such box. A coffee table's magazine shelf (9 cm), a TV
         stand's or side table's bottom shelf and a bathtub's floor are this low; something
         lying on the floor has its bottom on it. A walled container
         (``WALLED_CONTAINERS``: a box, a garbage can) holds what lies in its footprint
         at any height.
      3. Floor band: target centroid z - ``floor_z`` <= ``floor_band_m``, or its box bottom
         within half that of the floor (a tall box standing there) -> "Floor"
         (under a table is on the floor).
      4. Inside: receptacles whose box contains the target centroid in 3D (x, y grown by
         ``xy_margin_m``): the smallest box volume (a shelf or cabinet, not the room-sized
         thing around it).
      5. Paper rule: receptacles whose centroid z is below the target's: the nearest
         (euclidean centroid distance).
      6. "Floor".
    """
    recs = [o for o in _others(target, others) if o.receptacle]
    tx, ty, tz = target.centroid

    def xy_in(o: ObjectRef, margin: float = xy_margin_m) -> bool:
        assert o.box_min is not None and o.box_max is not None
        return (
            o.box_min[0] - margin <= tx <= o.box_max[0] + margin
            and o.box_min[1] - margin <= ty <= o.box_max[1] + margin
        )

    boxed = [o for o in recs if o.has_box and xy_in(o)]
    bottom = float(target.box_min[2]) if target.has_box else tz  # type: ignore[index]
    surfaces = [o for o in boxed if o.box_max[2] <= bottom + top_tol_m]  # type: ignore[index]
    if surfaces:

        def misfit(o: ObjectRef) -> float:
            ox = max(o.box_min[0] - tx, 0.0, tx - o.box_max[0])  # type: ignore[index]
            oy = max(o.box_min[1] - ty, 0.0, ty - o.box_max[1])  # type: ignore[index]
            return height_weight * (bottom - float(o.box_max[2])) + math.hypot(ox, oy)  # type: ignore[index]

        # min keeps the first of equal misfits: the nearest, as candidates are sorted by distance
        return min(_by_distance(target, surfaces), key=misfit)

    def volume(o: ObjectRef) -> float:
        return float(np.prod(np.subtract(o.box_max, o.box_min)))  # type: ignore[arg-type]

    off_floor = target.has_box and bottom - floor_z >= off_floor_m
    shelves = [
        o
        for o in recs
        if o.has_box
        and xy_in(o, 0.0)
        and o.box_min[2] <= tz <= o.box_max[2]  # type: ignore[index]
        and (off_floor or o.label in WALLED_CONTAINERS)
    ]
    if shelves:
        return min(shelves, key=volume)
    if tz - floor_z <= floor_band_m or (target.has_box and bottom - floor_z <= 0.5 * floor_band_m):
        return FLOOR
    inside = [o for o in boxed if o.box_min[2] <= tz <= o.box_max[2]]  # type: ignore[index]
    if inside:
        return min(inside, key=volume)
    below = [o for o in recs if o.centroid[2] < tz]
    if below:
        return _by_distance(target, below)[0]
    return FLOOR


def next_to(
    target: ObjectRef, others: Sequence[ObjectRef], d: float = 1.0, receptacles_only: bool = True
) -> list[ObjectRef]:
    """Objects whose centroid is within ``d`` metres (euclidean, 3D) of the target's, nearest first.

    By default only receptacles count (the paper's example: "next to the side table",
    while small objects appear through ``closest_to``).
    """
    if not d > 0:
        raise ValueError(f"next_to distance threshold must be > 0 metres, got {d!r}")
    cands = [o for o in _others(target, others) if o.receptacle or not receptacles_only]
    return [o for o in _by_distance(target, cands) if _dist(target, o) < d]


def closest_to(
    target: ObjectRef, others: Sequence[ObjectRef], include_receptacles: bool = False
) -> ObjectRef | None:
    """The object with the nearest centroid (euclidean, 3D), or None if there is none.

    By default only non-receptacles count (receptacles are covered by ``next_to`` and
    ``supported_by``).
    """
    cands = [o for o in _others(target, others) if include_receptacles or not o.receptacle]
    ranked = _by_distance(target, cands)
    return ranked[0] if ranked else None


def centroid_relations(
    target: ObjectRef, others: Sequence[ObjectRef], d: float = 1.0
) -> list[tuple[str, str]]:
    """The target's relations as (relation, label) pairs, in paragraph order.

    Relations: "next_to" for each ``next_to`` receptacle (nearest first), then one
    "supported_by" (a label or "Floor"), then "closest_to" when any non-receptacle exists.
    """
    rels: list[tuple[str, str]] = [("next_to", o.label) for o in next_to(target, others, d)]
    sup = supported_by(target, others)
    rels.append(("supported_by", sup if isinstance(sup, str) else sup.label))
    near = closest_to(target, others)
    if near is not None:
        rels.append(("closest_to", near.label))
    return rels


_PHRASES = {"next_to": "is next to", "supported_by": "is supported by", "closest_to": "is closest to"}


def relation_paragraph(target: ObjectRef, others: Sequence[ObjectRef], d: float = 1.0) -> str:
    """The paper's text form, one sentence per relation of ``centroid_relations``.

    E.g. "The pillow is next to the side table. The pillow is supported by the side table.
    The pillow is closest to the mug."
    """
    name = words(target.label)
    return " ".join(
        f"The {name} {_PHRASES[rel]} the {words(label)}."
        for rel, label in centroid_relations(target, others, d)
    )


# ---------------------------------------------------------------------------- box relations
# Classes with a meaningful front (local +y) for the "facing" relation.
FACING_CLASSES = frozenset(
    {
        "Toilet",
        "Laptop",
        "Chair",
        "Desk",
        "Television",
        "ArmChair",
        "Sofa",
        "Microwave",
        "CoffeeMachine",
        "Fridge",
        "Toaster",
    }
)


@dataclass(frozen=True)
class Box3D:
    """An upright oriented box in the start frame.

    center: (x, y, z) of the box's geometric centre, metres (not the catalog's
        bottom-centre origin: that is center - (0, 0, size z / 2)).
    size: full extents (sx, sy, sz) in metres along the object's local x (right),
        y (front) and z (up) axes.
    yaw: rotation about z in radians, counter-clockwise: local +x points along
        (cos yaw, sin yaw), the front (local +y) along (-sin yaw, cos yaw).
    """

    center: Vec3
    size: Vec3
    yaw: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        size = _vec3(self.size, "size")
        if min(size) <= 0:
            raise ValueError(f"Box3D size must be positive (metres), got {size}")
        object.__setattr__(self, "size", size)
        if not math.isfinite(self.yaw):
            raise ValueError(f"Box3D yaw must be finite radians, got {self.yaw!r}")
        object.__setattr__(self, "yaw", float(self.yaw))

    @property
    def z_min(self) -> float:
        return self.center[2] - self.size[2] / 2.0

    @property
    def z_max(self) -> float:
        return self.center[2] + self.size[2] / 2.0

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) unit vectors of the local x (right) and y (front) axes."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([c, s]), np.array([-s, c])

    def footprint(self) -> np.ndarray:
        """float64 (4, 2): the top-down rectangle's corners (metres), counter-clockwise."""
        ux, uy = self.axes()
        hx, hy = self.size[0] / 2.0, self.size[1] / 2.0
        c = np.array(self.center[:2])
        return np.array(
            [c - hx * ux - hy * uy, c + hx * ux - hy * uy, c + hx * ux + hy * uy, c - hx * ux + hy * uy]
        )

    def contains_xy(self, xy: Sequence[float], margin: float = 0.0) -> bool:
        """True if the point (metres) lies in the footprint grown by ``margin`` metres."""
        ux, uy = self.axes()
        v = np.asarray(xy, dtype=np.float64)[:2] - np.array(self.center[:2])
        return (
            abs(float(v @ ux)) <= self.size[0] / 2.0 + margin
            and abs(float(v @ uy)) <= self.size[1] / 2.0 + margin
        )

    def front_prism(self, depth: float, z_pad: float) -> Box3D:
        """The box extruded ``depth`` metres from the front face, z grown by ``z_pad`` each side."""
        _, uy = self.axes()
        off = (self.size[1] + depth) / 2.0
        return Box3D(
            center=(self.center[0] + off * uy[0], self.center[1] + off * uy[1], self.center[2]),
            size=(self.size[0], depth, self.size[2] + 2.0 * z_pad),
            yaw=self.yaw,
        )

    def side_faces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(outward unit normal, face centre) in world (x, y) for the 4 vertical faces."""
        ux, uy = self.axes()
        c = np.array(self.center[:2])
        hx, hy = self.size[0] / 2.0, self.size[1] / 2.0
        return [(ux, c + hx * ux), (-ux, c - hx * ux), (uy, c + hy * uy), (-uy, c - hy * uy)]


@dataclass(frozen=True)
class BoxRelationParams:
    """Thresholds of :func:`box_relations` (metres, degrees)."""

    vertical_tol_m: float = 0.05  # slack on "bottom above top" and on z-interval overlap
    contact_tol_m: float = 0.05  # |bottom of i - top of j| for supported_by
    support_margin_m: float = 0.02  # i's centre must be inside j's footprint grown by this
    next_to_m: float = 0.5  # max horizontal gap between footprints for next_to
    align_angle_deg: float = 10.0  # yaw difference from a multiple of 90 degrees
    align_plane_m: float = 0.1  # max distance between parallel face planes
    align_max_gap_m: float = 1.0  # aligned objects must also be this close (footprints)
    facing_depth_m: float = 2.0  # length of the prism extruded from the front face
    facing_z_pad_m: float = 0.1  # the prism's z extent grows by this on each side


def _project(poly: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
    p = poly @ axis
    return float(p.min()), float(p.max())


def _polys_overlap(a: np.ndarray, b: np.ndarray, eps: float = 1e-6) -> bool:
    """Separating-axis test for two convex polygons: True if they share area (> eps deep)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for e in edges:
            n = np.array([-e[1], e[0]])
            norm = float(np.hypot(*n))
            if norm == 0.0:
                continue
            n /= norm
            a0, a1 = _project(a, n)
            b0, b1 = _project(b, n)
            if min(a1, b1) - max(a0, b0) <= eps:
                return False
    return True


def _point_segment(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> float:
    d = s1 - s0
    L2 = float(d @ d)
    t = 0.0 if L2 == 0.0 else min(1.0, max(0.0, float((p - s0) @ d) / L2))
    return float(np.hypot(*(p - (s0 + t * d))))


def _polys_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Minimum distance (metres) between two convex polygons; 0 if they overlap or touch."""
    if _polys_overlap(a, b, eps=-1e-9):
        return 0.0
    best = math.inf
    for p, q in ((a, b), (b, a)):
        for k in range(len(q)):
            s0, s1 = q[k], q[(k + 1) % len(q)]
            for pt in p:
                best = min(best, _point_segment(pt, s0, s1))
    return best


def _z_overlap(a: Box3D, b: Box3D, tol: float) -> bool:
    return max(a.z_min, b.z_min) <= min(a.z_max, b.z_max) + tol


def _above(a: Box3D, b: Box3D, p: BoxRelationParams) -> bool:
    return a.z_min >= b.z_max - p.vertical_tol_m and _polys_overlap(a.footprint(), b.footprint())


def _supported_by(a: Box3D, b: Box3D, p: BoxRelationParams) -> bool:
    return (
        _above(a, b, p)
        and abs(a.z_min - b.z_max) <= p.contact_tol_m
        and b.contains_xy(a.center[:2], p.support_margin_m)
    )


def _next_to(a: Box3D, b: Box3D, p: BoxRelationParams) -> bool:
    if _above(a, b, p) or _above(b, a, p) or not _z_overlap(a, b, p.vertical_tol_m):
        return False
    return _polys_distance(a.footprint(), b.footprint()) <= p.next_to_m


def _aligned(a: Box3D, b: Box3D, p: BoxRelationParams) -> bool:
    diff = math.degrees(a.yaw - b.yaw) % 90.0
    if min(diff, 90.0 - diff) > p.align_angle_deg:
        return False
    if _polys_distance(a.footprint(), b.footprint()) > p.align_max_gap_m:
        return False
    cos_tol = math.cos(math.radians(p.align_angle_deg))
    for na, ca in a.side_faces():
        for nb, cb in b.side_faces():
            if abs(float(na @ nb)) >= cos_tol and abs(float(na @ (cb - ca))) <= p.align_plane_m:
                return True
    return False


def _facing(label: str, a: Box3D, b: Box3D, p: BoxRelationParams) -> bool:
    if label not in FACING_CLASSES or _above(a, b, p) or _above(b, a, p):
        return False
    prism = a.front_prism(p.facing_depth_m, p.facing_z_pad_m)
    return _z_overlap(prism, b, 0.0) and _polys_overlap(prism.footprint(), b.footprint())


def box_relations(
    boxes: Sequence[tuple[str, Box3D]], params: BoxRelationParams = BoxRelationParams()
) -> list[tuple[int, str, int]]:
    """All pairwise relations as (i, relation, j) triples: "box i <relation> box j".

    Pairs are visited i ascending, then j ascending (i != j); per pair the relations come
    in the order below. Rules (defaults from :class:`BoxRelationParams`, metres):
      * ``above``: bottom of i >= top of j - 0.05 and the top-down footprints share area.
      * ``below``: j is above i.
      * ``supported_by``: i is above j, |bottom of i - top of j| <= 0.05 (contact) and
        i's centre lies in j's footprint grown by 0.02.
      * ``next_to`` (symmetric): neither is above the other, their z ranges overlap
        (0.05 slack) and the horizontal gap between footprints is <= 0.5.
      * ``aligned_with`` (symmetric): yaws parallel or perpendicular within 10 degrees, a
        vertical face of i and a parallel vertical face of j lie in planes <= 0.1 apart
        (coplanar fronts, or faces side by side), and the footprints are <= 1.0 apart.
      * ``facing``: only if i's label is in ``FACING_CLASSES``; neither is above the other
        and j's box intersects the prism extruded 2.0 from i's front face (local +y), as
        wide and tall as i (z grown by 0.1 each side).
    """
    out: list[tuple[int, str, int]] = []
    for i, (label_i, a) in enumerate(boxes):
        for j, (_, b) in enumerate(boxes):
            if i == j:
                continue
            if _above(a, b, params):
                out.append((i, "above", j))
            if _above(b, a, params):
                out.append((i, "below", j))
            if _supported_by(a, b, params):
                out.append((i, "supported_by", j))
            if _next_to(a, b, params):
                out.append((i, "next_to", j))
            if _aligned(a, b, params):
                out.append((i, "aligned_with", j))
            if _facing(label_i, a, b, params):
                out.append((i, "facing", j))
    return out
