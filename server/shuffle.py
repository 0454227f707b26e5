"""Rearrangement configurations: a room's goal state and a shuffled state of it.

The 2-phase room-rearrangement task (RoomR, Weihs et al. 2021): the agent walks through
the room in its *goal* state, then the room is *shuffled* and the agent must put it back.
A configuration is addressed by (room type, seed, index) and is deterministic:

* **goal**: the tidy room with 0-2 of its openable furniture pieces (cabinets, drawers,
  fridges, ...) open, so neither phase's openness is "all closed";
* **shuffled**, from the goal: 0-3 openables toggled (open <-> closed), then 1-5
  pickupable objects moved, each either *placed* on another receptacle at a random spot of
  its surfaces (p = 0.5; inside ones only when open), or dropped / thrown from a random
  walkable spot with the mess-up's physics (``messup.toss``). Unlike the tidying mess-up, a
  new place need not be implausible: a mug moved from the counter to the table counts.

Nothing else may move: a toggle or a move that disturbs another object, ends outside the
room, inside a closed container, or within ``MIN_MOVE_M`` of where it was on the same
receptacle is undone and drawn again (up to ``MAX_TRIES`` per object, then the next
object). Openables whose open door would reach within ``KEEP_CLEAR_M`` of the agent's
start are left alone, so the agent starts both phases at the same free spot. Closing an
openable may hide what it holds; objects are only moved to places visible in the shuffled
state. Only kitchens, bathrooms and some bedrooms have openable furniture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tidee.server.messup import reachable, restore, snapshot, toss, walkable_cells
from tidee.server.rooms import ROOM_TYPE_INDEX, nav_grid, spawn_point
from tidee.server.scene import FLOOR_ID, MessRecord, Scene
from tidee.server.world import World

GOAL_OPEN = (0, 2)  # openables open in the goal state: min, max
TOGGLED = (0, 3)  # openables toggled by the shuffle
MOVED = (1, 5)  # pickupable objects moved by the shuffle
P_PLACE = 0.5  # a move places the object on another receptacle (else the mess-up's physics)
MIN_MOVE_M = 0.3
MAX_TRIES = 10
KEEP_CLEAR_M = 0.6
HIDDEN_Z = -5.0


@dataclass
class Rearrangement:
    """A configuration: the goal scene and the shuffled scene (its ``mess`` lists the moves)."""

    goal: Scene
    shuffled: Scene

    def toggled(self) -> list[str]:
        """Ids of the openables whose openness differs between the two states."""
        goal = {o.id: o.is_open for o in self.goal.objects if o.openable and not o.pickupable}
        return sorted(o.id for o in self.shuffled.objects if o.id in goal and goal[o.id] != o.is_open)


def shuffle_rng(room_type: str, seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence([ROOM_TYPE_INDEX[room_type], int(seed), int(index), 31337])
    )


def start_point(world: World, scene: Scene) -> tuple[float, float]:
    """The agent's default start in the world as built (``Episode.reset`` with no start seed)."""
    aabbs = [world.aabb(o.id) for o in scene.objects if not o.pickupable and o.type != "Floor"]
    return spawn_point(nav_grid(aabbs, scene.width, scene.depth), scene.width, scene.depth, None)


def make_rearrangement(world: World, tidy: Scene, index: int) -> Rearrangement:
    """Both states of configuration ``index`` of the tidy room built (and settled) in ``world``.
    Leaves the shuffled state built in the world."""
    rng = shuffle_rng(tidy.room_type, tidy.seed, index)
    scene = world.scene
    assert scene is not None
    start = start_point(world, scene)
    n_goal = int(rng.integers(GOAL_OPEN[0], GOAL_OPEN[1] + 1))
    _toggle_some(world, scene, rng, n_goal, start)
    goal = Scene.from_dict(world.export().to_dict())
    goal.mess_index, goal.mess = None, []
    start = start_point(world, scene)  # an open door may have moved the nearest free cell
    n_toggle = int(rng.integers(TOGGLED[0], TOGGLED[1] + 1))
    _toggle_some(world, scene, rng, n_toggle, start)
    n_move = int(rng.integers(MOVED[0], MOVED[1] + 1))
    records = _move_some(world, scene, rng, n_move)
    shuffled = Scene.from_dict(world.export().to_dict())
    shuffled.mess_index, shuffled.mess = None, records
    return Rearrangement(goal, shuffled)


def _openables(scene: Scene) -> list[str]:
    """Openable furniture (a toggle that would move what it holds is undone by ``_toggle``)."""
    return [o.id for o in scene.objects if o.openable and not o.pickupable]


def _toggle_some(
    world: World, scene: Scene, rng: np.random.Generator, n: int, start: tuple[float, float]
) -> list[str]:
    toggled: list[str] = []
    candidates = _openables(scene)
    for k in rng.permutation(len(candidates)):
        if len(toggled) >= n:
            break
        oid = candidates[int(k)]
        if _toggle(world, oid, start):
            toggled.append(oid)
    return toggled


def _toggle(world: World, oid: str, start: tuple[float, float]) -> bool:
    """Toggle one openable unless its door reaches the start or it disturbs anything."""
    obj = world.bodies[oid].obj
    snap = snapshot(world)
    world.set_open(oid, not obj.is_open)
    lo, hi = world.aabb(oid)
    gap = math.hypot(
        max(lo[0] - start[0], 0.0, start[0] - hi[0]), max(lo[1] - start[1], 0.0, start[1] - hi[1])
    )
    ok = gap >= KEEP_CLEAR_M
    if ok:
        world.settle(max_seconds=1.0, min_seconds=0.2)
        world.refresh_parents()
        ok = not _disturbed(world, snap, exclude=None)
    if not ok:
        world.set_open(oid, not obj.is_open)
        restore(world, snap)
    return ok


def _disturbed(world: World, snap: dict, exclude: str | None) -> bool:
    for oid, (pos, _, parent, _) in snap.items():
        if oid == exclude:
            continue
        if world.bodies[oid].obj.parent != parent:
            return True
        now, _ = world.pose(oid)
        if float(np.linalg.norm(np.subtract(now, pos))) > 0.02:
            return True
    return False


def _move_some(world: World, scene: Scene, rng: np.random.Generator, n: int) -> list[MessRecord]:
    cells = walkable_cells(world, scene)
    candidates = [o.id for o in scene.objects if o.pickupable and reachable(world, o.id)]
    records: list[MessRecord] = []
    for k in rng.permutation(len(candidates)):
        if len(records) >= n:
            break
        rec = _move_one(world, scene, candidates[int(k)], rng, cells)
        if rec is not None:
            records.append(rec)
    return records


def _targets(world: World, scene: Scene, exclude: str | None) -> list[str]:
    return [
        o.id
        for o in scene.objects
        if o.receptacle
        and not o.pickupable
        and o.id not in (exclude, FLOOR_ID)
        and (o.is_open or not o.openable)
        and world.surfaces_world(o.id, include_inside=o.is_open or not o.openable)
    ]


def _place(world: World, scene: Scene, oid: str, rng: np.random.Generator, exclude: str | None) -> bool:
    """Put ``oid`` on a random spot of a random other receptacle (as a held object is put)."""
    targets = _targets(world, scene, exclude)
    if not targets:
        return False
    target = targets[int(rng.integers(len(targets)))]
    t = world.bodies[target].obj
    surfaces = world.surfaces_world(target, include_inside=t.is_open or not t.openable)
    cxy, half, z, syaw, _ = surfaces[int(rng.integers(len(surfaces)))]
    lx, ly = (rng.uniform(-1.0, 1.0, 2) * half).tolist()
    c, s = math.cos(syaw), math.sin(syaw)
    near = np.array([cxy[0] + c * lx - s * ly, cxy[1] + s * lx + c * ly, z])
    yaw = float(rng.uniform(-math.pi, math.pi))
    pos, orn = world.pose(oid)
    world.set_static(oid, True)
    world.set_pose(oid, [pos[0], pos[1], HIDDEN_Z], orn)
    if world.place(oid, target, near, yaw=yaw):
        world.refresh_parents()
        return True
    world.set_static(oid, False)
    return False


def _move_one(
    world: World, scene: Scene, oid: str, rng: np.random.Generator, cells: np.ndarray
) -> MessRecord | None:
    obj = world.bodies[oid].obj
    orig_pos, orig_orn = world.pose(oid)
    orig_parent, orig_ptype = obj.parent, obj.parent_type
    for attempt in range(1, MAX_TRIES + 1):
        snap = snapshot(world)
        how = "place" if rng.random() < P_PLACE else "toss"
        if how == "place":
            moved = _place(world, scene, oid, rng, exclude=orig_parent)
        else:
            thrown = toss(world, oid, rng, cells)
            moved = thrown is not None
            how = "throw" if thrown else "drop"
        if not moved:
            restore(world, snap)
            continue
        pos, orn = world.pose(oid)
        lo, _ = world.aabb(oid)
        escaped = lo[2] < -0.2 or not (0 < lo[0] < scene.width and 0 < lo[1] < scene.depth)
        shift = float(np.linalg.norm(np.subtract(pos, orig_pos)))
        same_place = obj.parent == orig_parent and shift < MIN_MOVE_M
        if escaped or same_place or not reachable(world, oid) or _disturbed(world, snap, exclude=oid):
            restore(world, snap)
            continue
        return MessRecord(
            id=oid,
            type=obj.type,
            how=how,
            original_parent=orig_parent,
            original_parent_type=orig_ptype,
            original_position=list(orig_pos),
            original_orientation=list(orig_orn),
            messy_parent=obj.parent,
            messy_parent_type=obj.parent_type,
            messy_position=list(pos),
            messy_orientation=list(orn),
            tries=attempt,
        )
    return None
