"""Procedural rooms: (room type, seed) -> a settled, tidy Scene.

1. Lay out the shell (floor, four walls) and the furniture of the room template in 2D:
   pieces against walls, in corners, in the open, around a table, on another piece, or
   mounted on a wall; reject layouts whose walkable floor is not one connected area
   that reaches every receptacle.
2. Build the furniture in PyBullet and put 15-40 small objects on receptacle surfaces,
   drawn from the placement priors (rays check each spot has a surface and headroom).
   :func:`populate` has two versions (:func:`rooms_version`; 1 is the default).
3. Let physics settle them, drop any that did not end where the priors put them, and
   record each object's parent.
Everything random comes from one numpy Generator seeded by (room type, seed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from tidee.server.catalog import CATEGORIES, ROOM_TEMPLATES, receptacle_weights, sample_size
from tidee.server.catalog.schema import Category
from tidee.server.scene import FLOOR_ID, Scene, SceneObject, quat_yaw
from tidee.server.world import World, resolve_category

WALL_HEIGHT = 2.6
WALL_THICKNESS = 0.1
AGENT_RADIUS = 0.2
NAV_CELL = 0.05
REACH = 1.0  # a receptacle must have walkable floor within this distance
ROOM_TYPE_INDEX = {"Kitchen": 0, "LivingRoom": 1, "Bedroom": 2, "Bathroom": 3}
ROOMS_VERSIONS = (1, 2)
SEATS = ("Chair", "Stool")
TABLES_FOR_SEATS = ("DiningTable", "Desk", "CounterTop")


def room_rng(room_type: str, seed: int, stream: int = 0) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence([ROOM_TYPE_INDEX[room_type], int(seed), stream, 7411])
    )


def yaw_quat(yaw: float) -> list[float]:
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]


@dataclass
class Footprint:
    """An axis-aligned rectangle on the floor (furniture yaws are multiples of 90 deg)."""

    x0: float
    y0: float
    x1: float
    y1: float

    def overlaps(self, o: Footprint, gap: float = 0.0) -> bool:
        return not (
            self.x1 + gap <= o.x0 or o.x1 + gap <= self.x0 or self.y1 + gap <= o.y0 or o.y1 + gap <= self.y0
        )

    @staticmethod
    def of(cx: float, cy: float, sx: float, sy: float, yaw: float) -> Footprint:
        if abs(math.sin(yaw)) > 0.5:
            sx, sy = sy, sx
        return Footprint(cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2)


# Wall k: (yaw that turns the object's front into the room, inward normal)
WALLS = {0: (0.0, (0, 1)), 1: (math.pi / 2, (-1, 0)), 2: (math.pi, (0, -1)), 3: (-math.pi / 2, (1, 0))}


class LayoutError(RuntimeError):
    pass


def _sample_size(cat: Category, variant: str | None, rng: np.random.Generator) -> list[float]:
    return [round(float(v), 4) for v in sample_size(cat.name, variant, rng)]


def _sample_palette(cat: Category, variant: str | None, rng: np.random.Generator) -> dict[str, str]:
    var = cat.variant(variant)
    palettes = (var.palettes if var and var.palettes else None) or cat.palettes
    return dict(palettes[int(rng.integers(len(palettes)))])


def _sample_variant(
    cat: Category, rng: np.random.Generator, weights: dict[str, float] | None = None
) -> str | None:
    """A variant of the category: by the room template's weights when it gives some."""
    if not cat.variants:
        return None
    names = [v.name for v in cat.variants]
    w = np.array([(weights or {}).get(n, 0.0) for n in names], float) if weights else np.ones(len(names))
    if w.sum() <= 0:
        w = np.ones(len(names))
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _new_object(
    oid: str,
    cat: Category,
    variant: str | None,
    size: list[float],
    palette: dict[str, str],
    position: list[float],
    yaw: float,
    parent: str | None = FLOOR_ID,
) -> SceneObject:
    return SceneObject(
        id=oid,
        type=cat.name,
        variant=variant,
        pickupable=cat.pickupable,
        receptacle=cat.receptacle,
        openable=cat.openable,
        is_open=False,
        parent=parent,
        parent_type=None if parent is None else (parent.split("_")[0] if parent != FLOOR_ID else "Floor"),
        position=[round(v, 5) for v in position],
        orientation=yaw_quat(yaw),
        size=size,
        palette=palette,
    )


class _Ids:
    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def __call__(self, type_name: str) -> str:
        k = self.counts.get(type_name, 0)
        self.counts[type_name] = k + 1
        return f"{type_name}_{k}"


def _shell(width: float, depth: float, ids: _Ids) -> list[SceneObject]:
    floor_cat, wall_cat = CATEGORIES["Floor"], CATEGORIES["Wall"]
    t, h = WALL_THICKNESS, WALL_HEIGHT
    floor = _new_object(
        FLOOR_ID,
        floor_cat,
        None,
        [width + 2 * t, depth + 2 * t, 0.05],
        _first_palette(floor_cat),
        [width / 2, depth / 2, -0.05],
        0.0,
        parent=None,
    )
    walls = []
    wall_palette = _first_palette(wall_cat)
    specs = [
        ((width / 2, -t / 2), width + 2 * t, 0.0),
        ((width + t / 2, depth / 2), depth + 2 * t, math.pi / 2),
        ((width / 2, depth + t / 2), width + 2 * t, math.pi),
        ((-t / 2, depth / 2), depth + 2 * t, -math.pi / 2),
    ]
    for (cx, cy), length, yaw in specs:
        walls.append(
            _new_object(
                ids("Wall"), wall_cat, None, [length, t, h], wall_palette, [cx, cy, 0.0], yaw, parent=None
            )
        )
    return [floor, *walls]


def _first_palette(cat: Category) -> dict[str, str]:
    return dict(cat.palettes[0])


class _Layout:
    """Mutable state of one layout attempt."""

    def __init__(self, room_type: str, width: float, depth: float, rng: np.random.Generator) -> None:
        self.room_type, self.width, self.depth, self.rng = room_type, width, depth, rng
        self.ids = _Ids()
        self.objects: list[SceneObject] = _shell(width, depth, self.ids)
        self.floor_prints: dict[str, Footprint] = {}
        self.mounted: dict[int, list[tuple[float, float]]] = {k: [] for k in WALLS}
        self.on_top: dict[str, list[SceneObject]] = {}

    def of_type(self, type_name: str) -> list[SceneObject]:
        return [o for o in self.objects if o.type == type_name]

    def free(self, fp: Footprint, gap: float, ignore: str | None = None) -> bool:
        if fp.x0 < -1e-6 or fp.y0 < -1e-6 or fp.x1 > self.width + 1e-6 or fp.y1 > self.depth + 1e-6:
            return False
        return not any(fp.overlaps(o, gap) for k, o in self.floor_prints.items() if k != ignore)

    def add(
        self,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
        cx: float,
        cy: float,
        z: float,
        yaw: float,
        parent: str | None = FLOOR_ID,
    ) -> SceneObject:
        obj = _new_object(self.ids(cat.name), cat, variant, size, palette, [cx, cy, z], yaw, parent)
        self.objects.append(obj)
        if cat.placement not in ("wall_mounted",) and parent == FLOOR_ID:
            self.floor_prints[obj.id] = Footprint.of(cx, cy, size[0], size[1], yaw)
        return obj

    # -- placement strategies -------------------------------------------------------
    def place_wall(
        self,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
        corner: bool = False,
        tries: int = 40,
    ) -> SceneObject | None:
        sx, sy = size[0], size[1]
        for _ in range(tries):
            wall = int(self.rng.integers(4))
            yaw, (nx, ny) = WALLS[wall]
            length = self.width if wall in (0, 2) else self.depth
            if length < sx + 0.05:
                continue
            if corner:
                t = sx / 2 + 0.01 if self.rng.random() < 0.5 else length - sx / 2 - 0.01
            else:
                t = float(self.rng.uniform(sx / 2 + 0.01, length - sx / 2 - 0.01))
            off = sy / 2 + 0.01
            cx, cy = {
                0: (t, off),
                1: (self.width - off, t),
                2: (self.width - t, self.depth - off),
                3: (off, self.depth - t),
            }[wall]
            if self.free(Footprint.of(cx, cy, sx, sy, yaw), gap=0.08):
                return self.add(cat, variant, size, palette, cx, cy, 0.0, yaw)
        return None

    def place_open(
        self, cat: Category, variant: str | None, size: list[float], palette: dict[str, str], tries: int = 60
    ) -> SceneObject | None:
        margin = 0.75
        for _ in range(tries):
            yaw = float(self.rng.integers(4)) * math.pi / 2
            fp0 = Footprint.of(0, 0, size[0], size[1], yaw)
            hx, hy = fp0.x1, fp0.y1
            if self.width - 2 * (margin + hx) <= 0 or self.depth - 2 * (margin + hy) <= 0:
                return None
            cx = float(self.rng.uniform(margin + hx, self.width - margin - hx))
            cy = float(self.rng.uniform(margin + hy, self.depth - margin - hy))
            if self.free(Footprint.of(cx, cy, size[0], size[1], yaw), gap=0.6):
                return self.add(cat, variant, size, palette, cx, cy, 0.0, yaw)
        return None

    def place_in_front(
        self,
        host: SceneObject,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
        distance: float,
        facing_host: bool,
    ) -> SceneObject | None:
        """In front of ``host`` (a coffee table before a sofa, a chair at a desk)."""
        hyaw = _yaw(host)
        fx, fy = -math.sin(hyaw), math.cos(hyaw)  # host's front direction (+y local)
        d = host.size[1] / 2 + distance + size[1] / 2
        hx, hy = _center_xy(host)
        for lateral in (0.0, -0.25, 0.25, -0.5, 0.5):
            cx = hx + fx * d + fy * lateral
            cy = hy + fy * d - fx * lateral
            yaw = hyaw + math.pi if facing_host else hyaw
            if self.free(Footprint.of(cx, cy, size[0], size[1], yaw), gap=0.05):
                return self.add(cat, variant, size, palette, cx, cy, 0.0, yaw)
        return None

    def place_at_table(
        self,
        table: SceneObject,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
    ) -> SceneObject | None:
        """A seat along one of the table's sides, facing it."""
        tyaw = _yaw(table)
        tx, ty = _center_xy(table)
        sides = []
        for k in range(4):
            ang = tyaw + k * math.pi / 2  # k=0: front (+y local)
            half = table.size[1] / 2 if k % 2 == 0 else table.size[0] / 2
            along = table.size[0] if k % 2 == 0 else table.size[1]
            sides.append((ang, half, along))
        order = self.rng.permutation(4)
        for k in order:
            ang, half, along = sides[int(k)]
            nx, ny = -math.sin(ang), math.cos(ang)
            for lateral in self.rng.uniform(-along / 3, along / 3, size=3):
                d = half + size[1] / 2 - 0.12  # seats tuck slightly under the top
                cx, cy = tx + nx * d + ny * lateral, ty + ny * d - nx * lateral
                yaw = ang + math.pi  # the seat's front faces the table
                fp = Footprint.of(cx, cy, size[0], size[1], yaw)
                if self.free(fp, gap=0.04, ignore=table.id) and not fp.overlaps(
                    self.floor_prints[table.id], gap=-0.13
                ):
                    return self.add(cat, variant, size, palette, cx, cy, 0.0, yaw)
        return None

    def place_on(
        self,
        host: SceneObject,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
    ) -> SceneObject | None:
        """On the host's top surface, back towards the host's back (a TV on its stand)."""
        _, _, surfaces, _ = resolve_category(host)
        tops = [s for s in surfaces if not s.inside]
        if not tops:
            return None
        top = max(tops, key=lambda s: s.z)
        span_x = top.extent[0] * host.size[0]
        if size[0] > span_x or size[1] > top.extent[1] * host.size[1]:
            return None
        taken = self.on_top.setdefault(host.id, [])
        hyaw = _yaw(host)
        for _ in range(20):
            lx = top.center[0] * host.size[0] + float(
                self.rng.uniform(-(span_x - size[0]) / 2, (span_x - size[0]) / 2)
            )
            ly = (top.center[1] - top.extent[1] / 2) * host.size[1] + size[1] / 2 + 0.01
            if any(
                abs(lx - t_lx) < (size[0] + t.size[0]) / 2 + 0.03
                for t, t_lx in ((t, _local_x(host, t)) for t in taken)
            ):
                continue
            hx, hy = _center_xy(host)
            c, s = math.cos(hyaw), math.sin(hyaw)
            cx, cy = hx + c * lx - s * ly, hy + s * lx + c * ly
            z = host.position[2] + top.z * host.size[2] + 0.002
            obj = self.add(cat, variant, size, palette, cx, cy, z, hyaw, parent=host.id)
            obj.parent_type = host.type
            taken.append(obj)
            return obj
        return None

    def place_mounted(
        self,
        cat: Category,
        variant: str | None,
        size: list[float],
        palette: dict[str, str],
        near: SceneObject | None = None,
        tries: int = 30,
    ) -> SceneObject | None:
        """On a wall at the category's mount height; beside ``near`` when given (a mirror
        above the sink, a paper hanger by the toilet)."""
        for k in range(tries):
            if near is not None and k < tries // 2:
                wall, t_near = _wall_of(near, self.width, self.depth)
                lateral = float(self.rng.uniform(-0.6, 0.6)) * (near.size[0] / 2 + size[0] / 2 + 0.1)
                t = t_near + lateral if k else t_near
            else:
                wall, t = int(self.rng.integers(4)), None
            yaw, (nx, ny) = WALLS[wall]
            length = self.width if wall in (0, 2) else self.depth
            if length < size[0] + 0.4:
                continue
            if t is None:
                t = float(self.rng.uniform(size[0] / 2 + 0.2, length - size[0] / 2 - 0.2))
            if not size[0] / 2 + 0.05 <= t <= length - size[0] / 2 - 0.05:
                continue
            if any(abs(t - t2) < (size[0] + w2) / 2 + 0.15 for t2, w2 in self.mounted[wall]):
                continue
            off = size[1] / 2 + 0.002
            cx, cy = {
                0: (t, off),
                1: (self.width - off, t),
                2: (self.width - t, self.depth - off),
                3: (off, self.depth - t),
            }[wall]
            z = cat.mount_height
            # Low mounted things (a paper hanger) need the wall in front of them free.
            fp = Footprint.of(cx + nx * 0.05, cy + ny * 0.05, size[0], size[1] + 0.1, yaw)
            if z < 1.0 and near is None and not self.free(fp, gap=0.02):
                continue
            self.mounted[wall].append((t, size[0]))
            return self.add(cat, variant, size, palette, cx, cy, z, yaw, parent=None)
        return None


def _wall_of(obj: SceneObject, width: float, depth: float) -> tuple[int, float]:
    """The wall nearest to an object, and the object's position along that wall."""
    x, y = obj.position[0], obj.position[1]
    dists = {0: y, 1: width - x, 2: depth - y, 3: x}
    wall = min(dists, key=lambda w: dists[w])
    t = {0: x, 1: y, 2: width - x, 3: depth - y}[wall]
    return wall, t


def _yaw(obj: SceneObject) -> float:
    return quat_yaw(obj.orientation)


def _center_xy(obj: SceneObject) -> tuple[float, float]:
    return obj.position[0], obj.position[1]


def _local_x(host: SceneObject, obj: SceneObject) -> float:
    hyaw = _yaw(host)
    dx, dy = obj.position[0] - host.position[0], obj.position[1] - host.position[1]
    return math.cos(hyaw) * dx + math.sin(hyaw) * dy


def nav_grid(
    aabbs: list[tuple[np.ndarray, np.ndarray]],
    width: float,
    depth: float,
    radius: float = AGENT_RADIUS,
    cell: float = NAV_CELL,
) -> np.ndarray:
    """Boolean grid [ix, iy] of cells where the agent's centre may stand."""
    nx, ny = int(math.ceil(width / cell)), int(math.ceil(depth / cell))
    occ = np.zeros((nx, ny), bool)
    for lo, hi in aabbs:
        if lo[2] > 1.7 or hi[2] < 0.05:  # above the agent's head or flat on the floor
            continue
        i0, j0 = int(math.floor(lo[0] / cell)), int(math.floor(lo[1] / cell))
        i1, j1 = int(math.ceil(hi[0] / cell)), int(math.ceil(hi[1] / cell))
        occ[max(i0, 0) : max(min(i1, nx), 0), max(j0, 0) : max(min(j1, ny), 0)] = True
    r = int(math.ceil(radius / cell))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (xx**2 + yy**2) <= r * r
    blocked = ndimage.binary_dilation(occ, structure=disk)
    blocked[:r, :] = blocked[-r:, :] = True
    blocked[:, :r] = blocked[:, -r:] = True
    return ~blocked


def main_component(free: np.ndarray) -> np.ndarray:
    labels, n = ndimage.label(free)
    if n == 0:
        return np.zeros_like(free)
    sizes = ndimage.sum(free, labels, index=range(1, n + 1))
    return labels == (int(np.argmax(sizes)) + 1)


def spawn_point(free: np.ndarray, width: float, depth: float, start_seed: int | None) -> tuple[float, float]:
    """Where an episode starts the agent: the walkable cell (of the main component of the nav
    grid ``free``) nearest the room centre, or a random one drawn from ``start_seed``."""
    cells = np.argwhere(main_component(free))
    pts = (cells + 0.5) * NAV_CELL
    if start_seed is None:
        k = int(np.argmin(np.linalg.norm(pts - np.array([width / 2, depth / 2]), axis=1)))
    else:
        k = int(np.random.default_rng(start_seed).integers(len(pts)))
    return float(pts[k][0]), float(pts[k][1])


def check_layout(layout: _Layout) -> str | None:
    """Why the layout is not walkable, or None when it is."""
    aabbs = []
    for obj in layout.objects:
        if obj.type in ("Floor",) or obj.parent not in (FLOOR_ID, None):
            continue
        fp = Footprint.of(obj.position[0], obj.position[1], obj.size[0], obj.size[1], _yaw(obj))
        aabbs.append(
            (
                np.array([fp.x0, fp.y0, obj.position[2]]),
                np.array([fp.x1, fp.y1, obj.position[2] + obj.size[2]]),
            )
        )
    free = nav_grid(aabbs, layout.width, layout.depth)
    main = main_component(free)
    if free.sum() == 0 or main.sum() < 0.9 * free.sum():
        return "walkable floor is split into disconnected areas"
    if main.sum() * NAV_CELL**2 < 0.25 * layout.width * layout.depth:
        return "too little walkable floor"
    reach = int(round(REACH / NAV_CELL))
    for obj in layout.objects:
        if not obj.receptacle or obj.type == "Floor" or obj.parent not in (FLOOR_ID, None):
            continue
        fp = Footprint.of(obj.position[0], obj.position[1], obj.size[0], obj.size[1], _yaw(obj))
        i0, j0 = max(int(fp.x0 / NAV_CELL) - reach, 0), max(int(fp.y0 / NAV_CELL) - reach, 0)
        i1, j1 = int(fp.x1 / NAV_CELL) + reach, int(fp.y1 / NAV_CELL) + reach
        if not main[i0:i1, j0:j1].any():
            return f"{obj.id} cannot be reached from the walkable floor"
    return None


def layout_furniture(room_type: str, seed: int, max_attempts: int = 60) -> _Layout:
    template = ROOM_TEMPLATES[room_type]
    last_reason = ""
    for attempt in range(max_attempts):
        rng = room_rng(room_type, seed, stream=attempt)
        (wx0, wx1), (dy0, dy1) = template["size"]
        width = round(float(rng.uniform(wx0, wx1)), 2)
        depth = round(float(rng.uniform(dy0, dy1)), 2)
        layout = _Layout(room_type, width, depth, rng)
        ok = True
        entries = sorted(template["furniture"], key=lambda e: _placement_order(e))
        for entry in entries:
            cat = CATEGORIES[entry["type"]]
            lo, hi = entry.get("count", [1, 1])
            n = int(rng.integers(lo, hi + 1))
            for _ in range(n):
                placed = _place_one(layout, cat, entry)
                if placed is None and entry.get("required", False):
                    ok, last_reason = False, f"could not place required {cat.name}"
                    break
            if not ok:
                break
        if ok:
            reason = check_layout(layout)
            if reason is None:
                return layout
            last_reason = reason
    raise LayoutError(
        f"no valid {room_type} layout for seed {seed} after {max_attempts} attempts: {last_reason}"
    )


def _placement_order(entry: dict) -> int:
    cat = CATEGORIES[entry["type"]]
    if entry.get("on"):
        return 4
    if cat.name in SEATS:
        return 3
    if cat.placement == "wall_mounted":
        return 5
    if cat.placement == "open":
        return 2 if entry.get("near") or cat.name == "CoffeeTable" else 1
    return 0 if entry.get("required", False) else 1


def _place_one(layout: _Layout, cat: Category, entry: dict) -> SceneObject | None:
    rng = layout.rng
    variant = entry.get("variant") or _sample_variant(cat, rng)
    size = _sample_size(cat, variant, rng)
    palette = _sample_palette(cat, variant, rng)
    host_type = entry.get("on")
    if host_type:
        hosts = layout.of_type(host_type)
        for i in rng.permutation(len(hosts)):
            obj = layout.place_on(hosts[int(i)], cat, variant, size, palette)
            if obj is not None:
                return obj
        return None
    if cat.name in SEATS:
        near = (entry["near"],) if entry.get("near") else TABLES_FOR_SEATS
        tables = [o for t in near for o in layout.of_type(t)]
        for i in rng.permutation(len(tables)):
            obj = layout.place_at_table(tables[int(i)], cat, variant, size, palette)
            if obj is not None:
                return obj
        return layout.place_wall(cat, variant, size, palette)
    if cat.name == "CoffeeTable" and layout.of_type("Sofa"):
        obj = layout.place_in_front(
            layout.of_type("Sofa")[0], cat, variant, size, palette, 0.4, facing_host=False
        )
        if obj is not None:
            return obj
    if cat.name == "Ottoman" and layout.of_type("ArmChair"):
        obj = layout.place_in_front(
            layout.of_type("ArmChair")[0], cat, variant, size, palette, 0.3, facing_host=False
        )
        if obj is not None:
            return obj
    placement = cat.placement
    if placement == "wall_mounted":
        hosts = layout.of_type(entry["near"]) if entry.get("near") else []
        host = hosts[int(rng.integers(len(hosts)))] if hosts else None
        return layout.place_mounted(cat, variant, size, palette, near=host)
    if placement == "open":
        return layout.place_open(cat, variant, size, palette) or layout.place_wall(
            cat, variant, size, palette
        )
    return layout.place_wall(cat, variant, size, palette, corner=(placement == "corner"))


# ---------------------------------------------------------------------- small objects
def _spot_on(
    world: World,
    host: SceneObject,
    size: list[float],
    rng: np.random.Generator,
    taken: list[tuple[float, float, float]],
    inside_ok: bool,
    tries: int = 12,
) -> tuple[float, float, float] | None:
    """A free (x, y, z) on one of the host's surfaces with headroom for the object."""
    surfaces = world.surfaces_world(host.id, include_inside=inside_ok)
    if not surfaces:
        return None
    areas = np.array([4 * h[0] * h[1] for _, h, _, _, _ in surfaces])
    radius = 0.5 * math.hypot(size[0], size[1])
    for _ in range(tries):
        k = int(rng.choice(len(surfaces), p=areas / areas.sum()))
        cxy, half, z, yaw, _inside = surfaces[k]
        mx, my = half[0] - radius * 0.8, half[1] - radius * 0.8
        if mx <= 0 or my <= 0:
            continue
        lx, ly = rng.uniform(-mx, mx), rng.uniform(-my, my)
        c, s = math.cos(yaw), math.sin(yaw)
        x, y = cxy[0] + c * lx - s * ly, cxy[1] + s * lx + c * ly
        if any(math.hypot(x - tx, y - ty) < radius + tr + 0.02 for tx, ty, tr in taken):
            continue
        hit_id, _, hit, _ = world.ray(np.array([x, y, z + 0.03]), np.array([x, y, z - 0.08]))
        if hit_id != host.id or abs(hit[2] - z) > 0.04:
            continue
        up_id, _, up, _ = world.ray(np.array([x, y, hit[2] + 0.005]), np.array([x, y, hit[2] + 3.0]))
        if up_id is not None and up[2] - hit[2] < size[2] + 0.03:
            continue
        return x, y, float(hit[2])
    return None


def _floor_spot(
    free: np.ndarray, size: list[float], rng: np.random.Generator, taken: list[tuple[float, float, float]]
) -> tuple[float, float, float] | None:
    # Keep floor objects off the walkway: cells next to blocked ones.
    edge = free & ~ndimage.binary_erosion(free, iterations=3)
    cells = np.argwhere(edge)
    if len(cells) == 0:
        return None
    radius = 0.5 * math.hypot(size[0], size[1])
    for _ in range(20):
        i, j = cells[int(rng.integers(len(cells)))]
        x, y = (i + 0.5) * NAV_CELL, (j + 0.5) * NAV_CELL
        if any(math.hypot(x - tx, y - ty) < radius + tr + 0.05 for tx, ty, tr in taken):
            continue
        return x, y, 0.0
    return None


def rooms_version(version: int | None = None) -> int:
    """The room generator's version: ``version``, else 1.

    1 is the generator every shipped model and report so far used. 2 keeps the rooms' small objects
    closer to the placement prior (:func:`populate`); its rooms differ from 1's in every small object."""
    if version is None:
        version = 1
    if version not in ROOMS_VERSIONS:
        raise ValueError(f"the room generator version must be one of {ROOMS_VERSIONS}, got {version!r}")
    return int(version)


def populate(world: World, scene: Scene, rng: np.random.Generator, version: int = 1) -> list[SceneObject]:
    """Choose and place the small objects of a room on its receptacles (not yet settled).

    Version 1 draws (category, receptacle type) pairs from the priors until the room's target count
    is placed; a draw whose receptacle has no free spot is replaced by a new draw, so roomy
    receptacles end up with more than their share and small ones with less. Version 2 draws the
    target count once, tries every instance of the drawn receptacle type with more spots, and drops
    what still does not fit without replacing it: the placed objects follow the prior, thinned only
    by each receptacle's failure rate."""
    template = ROOM_TEMPLATES[scene.room_type]
    ids = _Ids()
    for o in scene.objects:
        ids.counts[o.type] = ids.counts.get(o.type, 0) + 1
    receptacles: dict[str, list[SceneObject]] = {}
    for o in scene.objects:
        if o.receptacle and not o.pickupable:
            receptacles.setdefault(o.type, []).append(o)
    present = list(receptacles)
    names = list(template["small"])
    freq = np.array([template["small"][n] for n in names], float)
    lo, hi = template.get("n_small", [15, 40])
    target = int(rng.integers(lo, hi + 1))
    draws = target * 6 if version == 1 else target
    taken: dict[str, list[tuple[float, float, float]]] = {}
    free = nav_grid([world.aabb(o.id) for o in scene.objects if o.type != "Floor"], scene.width, scene.depth)
    placed: list[SceneObject] = []
    attempts = 0
    while len(placed) < target and attempts < draws:
        attempts += 1
        cat = CATEGORIES[names[int(rng.choice(len(names), p=freq / freq.sum()))]]
        variant = _sample_variant(cat, rng, template.get("variant_weights", {}).get(cat.name))
        weights = receptacle_weights(cat.name, variant, scene.room_type, present)
        if not weights:
            continue
        rtypes = list(weights)
        rtype = rtypes[int(rng.choice(len(rtypes), p=np.array([weights[r] for r in rtypes])))]
        size = _sample_size(cat, variant, rng)
        palette = _sample_palette(cat, variant, rng)
        spot = None
        if rtype == "Floor":
            host_id = FLOOR_ID
            spot = _floor_spot(free, size, rng, taken.setdefault(host_id, []))
        else:
            hosts = receptacles[rtype]
            # version 1: one instance at random, 12 spots; version 2: every instance, 30 spots each
            order = (
                [int(rng.integers(len(hosts)))]
                if version == 1
                else [int(k) for k in rng.permutation(len(hosts))]
            )
            for k in order:
                host_id = hosts[k].id
                spot = _spot_on(
                    world,
                    hosts[k],
                    size,
                    rng,
                    taken.setdefault(host_id, []),
                    inside_ok=True,
                    tries=12 if version == 1 else 30,
                )
                if spot is not None:
                    break
        if spot is None:
            continue
        x, y, z = spot
        taken[host_id].append((x, y, 0.5 * math.hypot(size[0], size[1])))
        obj = _new_object(
            ids(cat.name),
            cat,
            variant,
            size,
            palette,
            [x, y, z + 0.003],
            float(rng.uniform(-math.pi, math.pi)),
            parent=host_id,
        )
        obj.parent_type = "Floor" if host_id == FLOOR_ID else rtype
        placed.append(obj)
    return placed


def generate_scene(
    room_type: str, seed: int, world: World | None = None, version: int | None = None
) -> Scene:
    """The tidy room for (room_type, seed), settled by physics. Deterministic.

    ``version``: the generator's version (:func:`rooms_version`; None: 1)."""
    version = rooms_version(version)
    if room_type not in ROOM_TEMPLATES:
        raise ValueError(f"room_type must be one of {sorted(ROOM_TEMPLATES)}, got {room_type!r}")
    layout = layout_furniture(room_type, seed)
    scene = Scene(
        room_type=room_type,
        seed=int(seed),
        width=layout.width,
        depth=layout.depth,
        wall_height=WALL_HEIGHT,
        objects=list(layout.objects),
    )
    own = world is None
    world = world or World(renderer="tiny")
    try:
        world.build(scene)
        rng = room_rng(room_type, seed, stream=1000)
        small = populate(world, scene, rng, version)
        intended = {o.id: o.parent for o in small}
        scene.objects.extend(small)
        world.build(scene)
        world.settle(max_seconds=3.0)
        world.refresh_parents()
        # Keep only objects that came to rest where the priors put them.
        keep = [o for o in scene.objects if not o.pickupable or o.parent == intended.get(o.id)]
        if len(keep) != len(scene.objects):
            scene.objects = keep
            world.build(scene)
        world.export()
        return scene
    finally:
        if own:
            world.close()
