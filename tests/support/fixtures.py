"""Hand-built scenes with known geometry, for tests of actions and sensing."""

from __future__ import annotations

import math

import numpy as np

from tidee.protocol.messages import EpisodeSpec
from tidee.server.catalog import CATEGORIES
from tidee.server.rooms import WALL_HEIGHT, _Ids, _shell, yaw_quat
from tidee.server.scene import FLOOR_ID, Scene, SceneObject


def make_object(
    oid: str,
    type_name: str,
    xy: tuple[float, float],
    z: float = 0.0,
    yaw_deg: float = 0.0,
    parent: str | None = FLOOR_ID,
    size: list[float] | None = None,
) -> SceneObject:
    cat = CATEGORIES[type_name]
    size = size or [round((a + b) / 2, 3) for a, b in zip(cat.size_min, cat.size_max)]
    return SceneObject(
        id=oid,
        type=type_name,
        variant=cat.variants[0].name if cat.variants else None,
        pickupable=cat.pickupable,
        receptacle=cat.receptacle,
        openable=cat.openable,
        is_open=False,
        parent=parent,
        parent_type=None if parent is None else ("Floor" if parent == FLOOR_ID else parent.split("_")[0]),
        position=[xy[0], xy[1], z],
        orientation=yaw_quat(math.radians(yaw_deg)),
        size=size,
        palette=dict(cat.palettes[0]),
    )


def table_room() -> Scene:
    """A 4 x 4 m room: a dining table with a mug in the middle, a fridge on the north wall.

    The table (1.2 x 0.8 m) stands at (2, 2); the mug sits on it at (2, 2); the fridge's
    back is against the wall at y = 4, its door facing -y.
    """
    width = depth = 4.0
    objects = _shell(width, depth, _Ids())
    table = make_object("DiningTable_0", "DiningTable", (2.0, 2.0), size=[1.2, 0.8, 0.75])
    fridge_size = [0.8, 0.75, 1.8]
    fridge = make_object(
        "Fridge_0", "Fridge", (3.0, depth - fridge_size[1] / 2 - 0.01), yaw_deg=180, size=fridge_size
    )
    mug = make_object("Mug_0", "Mug", (2.0, 2.0), z=table_top(table), parent="DiningTable_0")
    objects += [table, fridge, mug]
    return Scene(
        room_type="Kitchen", seed=0, width=width, depth=depth, wall_height=WALL_HEIGHT, objects=objects
    )


def counter_room() -> Scene:
    """A 4 x 4 m kitchen: a 0.92 m high counter (1.6 x 0.6 m) against the north wall, its
    front at y = 3.39, a mug on it at (1.5, 3.7): the counter top is at the camera's height,
    seen edge-on."""
    width = depth = 4.0
    objects = _shell(width, depth, _Ids())
    counter = make_object("CounterTop_0", "CounterTop", (2.0, 3.69), yaw_deg=180, size=[1.6, 0.6, 0.92])
    mug = make_object("Mug_0", "Mug", (1.5, 3.7), z=table_top(counter), parent="CounterTop_0")
    objects += [counter, mug]
    return Scene(
        room_type="Kitchen", seed=0, width=width, depth=depth, wall_height=WALL_HEIGHT, objects=objects
    )


def table_top(table: SceneObject) -> float:
    cat = CATEGORIES[table.type]
    return max(s.z for s in cat.surfaces if not s.inside) * table.size[2] + 0.002


def spec(resolution: int = 128) -> EpisodeSpec:
    return EpisodeSpec(room_type="Kitchen", seed=0, resolution=resolution, max_steps=50)


def project(ep, obs, world_point) -> tuple[float, float]:
    """Normalised pixel (x, y) where a world point appears in an observation of ``ep``."""
    p_start = ep._start_from_world() @ np.append(np.asarray(world_point, float), 1.0)
    p_cam = np.linalg.inv(obs.camera_pose) @ p_start
    k = obs.intrinsics
    u = k[0, 0] * p_cam[0] / p_cam[2] + k[0, 2]
    v = k[1, 1] * p_cam[1] / p_cam[2] + k[1, 2]
    r = obs.rgb.shape[1]
    return float((u + 0.5) / r), float((v + 0.5) / r)
