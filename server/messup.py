"""Mess-up, as in the paper's supplement ("Tidying task").

N = 5 random pickupable objects per configuration. For each: stand the agent at a random
navigable spot facing a random multiple of 90 deg; with p = 0.5 drop the object there,
else throw it along the view (AI2THOR's ThrowObject with 150 N; here an impulse of
150 N over one 1/60 s frame, capped at 6 m/s); let physics settle. Nothing breaks. An
object that comes to rest somewhere its placement priors call plausible, or that knocks
another object off its receptacle, is tried again (up to 10 tries, then left out), so
every moved object is really out of place and nothing else moved.
"""

from __future__ import annotations

import math

import numpy as np

from tidee.server.bullet import pb
from tidee.server.catalog import is_plausible
from tidee.server.rooms import NAV_CELL, ROOM_TYPE_INDEX, main_component, nav_grid
from tidee.server.scene import MessRecord, Scene
from tidee.server.world import World

N_MOVED = 5
P_DROP = 0.5
THROW_FORCE_N = 150.0
THROW_DT = 1.0 / 60.0
MAX_THROW_SPEED = 6.0
MAX_TRIES = 10
HAND_HEIGHT = 0.9
HAND_REACH = 0.35


def mess_rng(room_type: str, seed: int, mess_index: int) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence([ROOM_TYPE_INDEX[room_type], int(seed), int(mess_index), 90210])
    )


def walkable_cells(world: World, scene: Scene) -> np.ndarray:
    free = nav_grid(
        [world.aabb(o.id) for o in scene.objects if not o.pickupable and o.type != "Floor"],
        scene.width,
        scene.depth,
    )
    return np.argwhere(main_component(free))


def snapshot(world: World) -> dict[str, tuple[list[float], list[float], str | None, str | None]]:
    out = {}
    for oid in world.dynamic_ids():
        pos, orn = world.pose(oid)
        o = world.bodies[oid].obj
        out[oid] = (pos, orn, o.parent, o.parent_type)
    return out


def restore(world: World, snap: dict[str, tuple[list[float], list[float], str | None, str | None]]) -> None:
    for oid, (pos, orn, parent, ptype) in snap.items():
        world.set_pose(oid, pos, orn)
        o = world.bodies[oid].obj
        o.parent, o.parent_type = parent, ptype


def mess_up(world: World, scene: Scene, mess_index: int, n_objects: int = N_MOVED) -> list[MessRecord]:
    """Move ``n_objects`` objects out of place in the built, settled tidy world."""
    rng = mess_rng(scene.room_type, scene.seed, mess_index)
    present = sorted({o.type for o in scene.objects if o.receptacle and not o.pickupable})
    cells = walkable_cells(world, scene)
    candidates = [o for o in scene.objects if o.pickupable and reachable(world, o.id)]
    order = [candidates[int(i)] for i in rng.permutation(len(candidates))]
    records: list[MessRecord] = []
    for obj in order:
        if len(records) >= n_objects:
            break
        rec = _move_one(world, scene, obj.id, rng, cells, present)
        if rec is not None:
            records.append(rec)
    return records


def reachable(world: World, obj_id: str) -> bool:
    """Not shut inside a closed openable (the agent could not see it either)."""
    container = world.container_of(obj_id)
    return container is None or world.bodies[container].obj.is_open


def toss(world: World, obj_id: str, rng: np.random.Generator, cells: np.ndarray) -> bool | None:
    """Drop or throw ``obj_id`` from a hand at a random walkable cell, let physics settle and
    refresh every object's parent. True: thrown, False: dropped, None: the start pose collided
    (nothing was simulated; the caller restores its snapshot)."""
    i, j = cells[int(rng.integers(len(cells)))]
    ax, ay = (i + 0.5) * NAV_CELL, (j + 0.5) * NAV_CELL
    yaw = float(rng.integers(4)) * math.pi / 2
    throw = rng.random() >= P_DROP
    fx, fy = math.cos(yaw), math.sin(yaw)
    start = [ax + fx * HAND_REACH, ay + fy * HAND_REACH, HAND_HEIGHT]
    spin = float(rng.uniform(-math.pi, math.pi))
    world.set_pose(obj_id, start, [0, 0, math.sin(spin / 2), math.cos(spin / 2)])
    if world.collides(obj_id, ignore=set()):
        return None
    if throw:
        speed = min(THROW_FORCE_N * THROW_DT / max(world.bodies[obj_id].mass, 1e-3), MAX_THROW_SPEED)
        pb.resetBaseVelocity(
            world.bodies[obj_id].uid,
            [fx * speed, fy * speed, 0.0],
            [0, 0, 0],
            physicsClientId=world.client,
        )
    world.settle(max_seconds=4.0, min_seconds=0.5)
    world.refresh_parents()
    return throw


def _move_one(
    world: World, scene: Scene, obj_id: str, rng: np.random.Generator, cells: np.ndarray, present: list[str]
) -> MessRecord | None:
    obj = world.bodies[obj_id].obj
    orig_pos, orig_orn = world.pose(obj_id)
    orig_parent, orig_ptype = obj.parent, obj.parent_type
    for attempt in range(1, MAX_TRIES + 1):
        snap = snapshot(world)
        throw = toss(world, obj_id, rng, cells)
        if throw is None:
            restore(world, snap)
            continue
        disturbed = [
            o for o, (_, _, parent, _) in snap.items() if o != obj_id and world.bodies[o].obj.parent != parent
        ]
        new_parent, new_ptype = obj.parent, obj.parent_type
        lo, _ = world.aabb(obj_id)
        escaped = lo[2] < -0.2 or not (0 < lo[0] < scene.width and 0 < lo[1] < scene.depth)
        plausible = new_ptype is not None and is_plausible(
            obj.type, obj.variant, scene.room_type, new_ptype, present
        )
        if disturbed or escaped or plausible or new_parent == orig_parent:
            restore(world, snap)
            continue
        pos, orn = world.pose(obj_id)
        return MessRecord(
            id=obj_id,
            type=obj.type,
            how="throw" if throw else "drop",
            original_parent=orig_parent,
            original_parent_type=orig_ptype,
            original_position=list(orig_pos),
            original_orientation=list(orig_orn),
            messy_parent=new_parent,
            messy_parent_type=new_ptype,
            messy_position=list(pos),
            messy_orientation=list(orn),
            tries=attempt,
        )
    return None
