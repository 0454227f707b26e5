"""The scene record: what a room holds, as JSON, independent of PyBullet.

A ``Scene`` is what ``tidee scene export`` writes and what the world is built from, so
export -> load -> export is the identity. Positions are world metres (z up, floor at
z = 0, room spanning [0, width] x [0, depth]); orientations are quaternions (x, y, z, w).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from typing import Any

SCENE_FORMAT_VERSION = 1


def quat_yaw(q: list[float] | tuple[float, ...]) -> float:
    """Yaw (rotation about z, radians) of a quaternion (x, y, z, w)."""
    return math.atan2(2 * (q[3] * q[2] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))


FLOOR_ID = "Floor"


@dataclass
class SceneObject:
    id: str
    type: str
    variant: str | None
    pickupable: bool
    receptacle: bool
    openable: bool
    is_open: bool
    parent: str | None  # id of the supporting/containing object, or "Floor"
    parent_type: str | None
    position: list[float]  # bottom-centre of the bounding box, world frame
    orientation: list[float]  # quaternion x, y, z, w
    size: list[float]  # bounding-box size (sx, sy, sz) in the object frame
    palette: dict[str, str] = field(default_factory=dict)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> SceneObject:
        known = {f for f in SceneObject.__dataclass_fields__}
        missing = known - set(d) - {"palette"}
        if missing:
            raise ValueError(f"scene object {d.get('id', '?')!r} lacks fields {sorted(missing)}")
        return SceneObject(**{k: d[k] for k in known if k in d})


@dataclass
class MessRecord:
    """One object the mess-up moved: where it was and where it came to rest."""

    id: str
    type: str
    how: str  # "drop" | "throw"
    original_parent: str | None
    original_parent_type: str | None
    original_position: list[float]
    original_orientation: list[float]
    messy_parent: str | None
    messy_parent_type: str | None
    messy_position: list[float]
    messy_orientation: list[float]
    tries: int


@dataclass
class Scene:
    room_type: str
    seed: int
    width: float  # room extent along x (metres)
    depth: float  # room extent along y
    wall_height: float
    objects: list[SceneObject]
    mess_index: int | None = None
    mess: list[MessRecord] = field(default_factory=list)
    format_version: int = SCENE_FORMAT_VERSION

    def by_id(self) -> dict[str, SceneObject]:
        return {o.id: o for o in self.objects}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Scene:
        if d.get("format_version") != SCENE_FORMAT_VERSION:
            raise ValueError(
                f"scene format_version must be {SCENE_FORMAT_VERSION}, got {d.get('format_version')!r}"
            )
        return Scene(
            room_type=d["room_type"],
            seed=int(d["seed"]),
            width=float(d["width"]),
            depth=float(d["depth"]),
            wall_height=float(d["wall_height"]),
            objects=[SceneObject.from_dict(o) for o in d["objects"]],
            mess_index=d.get("mess_index"),
            mess=[MessRecord(**m) for m in d.get("mess", [])],
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    def save(self, path: str) -> None:
        """Write atomically: a crash mid-write never leaves a half file behind."""
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w") as f:
            f.write(self.to_json())
        os.replace(tmp, path)

    @staticmethod
    def load(path: str) -> Scene:
        with open(path) as f:
            return Scene.from_dict(json.load(f))
