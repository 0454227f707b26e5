"""Can the simulator carry out a placement at all? The preference evaluation's check that a
scripted preference asks for something possible: a box 48 cm long does not fit on a side table
40 cm wide, and a laptop does not go into a drawer, however well an agent obeys.

The check reads the simulator's scene of the configuration (as the mess-up left it), so it is
evaluation only: no agent ever sees it. An object *fits* a receptacle class when the server's
own ``World.place`` (the code a ``PutObject`` runs) puts it stably on some instance of that class:
aimed at the middle of each of its surfaces and every 0.6 m over it (inside ones too, the
instance opened), lying along
the surface's axes either way. A preference about a category (or a group) moves every object of
it that is elsewhere, so all of them must fit at once: they are put down one after another,
the biggest first, each beside those already there.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tidee.agent.reasoning.relations import FLOOR  # room enough for anything a person carries

HIDDEN = [0.0, 0.0, -5.0]  # where a held object waits, out of the world
AIM_SPACING_M = 0.6  # between the points aimed at on a long surface


class RoomFit:
    """``fits(categories, receptacle)`` for one configuration; answers are remembered."""

    def __init__(self, check: PlacementCheck, key: tuple[str, int, int | None]) -> None:
        self.check = check
        self.key = key
        self._memo: dict[tuple[tuple[str, ...], str], bool] = {}

    def __call__(self, categories: str | tuple[str, ...], receptacle: str) -> bool:
        cats = (categories,) if isinstance(categories, str) else tuple(sorted(categories))
        if (cats, receptacle) not in self._memo:
            self._memo[(cats, receptacle)] = receptacle == FLOOR or self._check(cats, receptacle)
        return self._memo[(cats, receptacle)]

    def _check(self, categories: tuple[str, ...], receptacle: str) -> bool:
        w, scene = self.check.world, self.check.scene(*self.key)  # the room as the mess-up left it
        hosts = [o.id for o in scene.objects if o.type == receptacle]
        objs = [o for o in scene.objects if o.type in categories and o.parent_type != receptacle]
        if not hosts:
            return False
        for o in objs:  # all of them in hand at once, then put down one after another
            w.set_static(o.id, True)
            w.set_pose(o.id, HIDDEN, [0, 0, 0, 1])
        for h in hosts:
            if w.bodies[h].obj.openable:
                w.set_open(h, True)
        biggest_first = sorted(objs, key=lambda o: -float(np.prod(o.size[:2])))
        return all(self._put(o.id, hosts) for o in biggest_first)

    def _put(self, obj_id: str, hosts: list[str]) -> bool:
        w = self.check.world
        for host in hosts:
            for cxy, half, z, syaw, _inside in w.surfaces_world(host, include_inside=True):
                for aim in _aims(cxy, half, syaw):
                    for yaw in (syaw, syaw + math.pi / 2):
                        if w.place(obj_id, host, np.array([aim[0], aim[1], z]), yaw=yaw):
                            return True
        return False


def _aims(cxy: np.ndarray, half: np.ndarray, yaw: float) -> list[np.ndarray]:
    """Where to aim on a surface: its middle, then a lattice every ``AIM_SPACING_M`` over it
    (``World.place`` tries spots up to about 0.4 m from the aimed one)."""
    c, s = math.cos(yaw), math.sin(yaw)
    xs = np.arange(-half[0], half[0] + 1e-9, AIM_SPACING_M) if half[0] > AIM_SPACING_M / 2 else [0.0]
    ys = np.arange(-half[1], half[1] + 1e-9, AIM_SPACING_M) if half[1] > AIM_SPACING_M / 2 else [0.0]
    lattice = [np.array([cxy[0] + c * x - s * y, cxy[1] + s * x + c * y]) for x in xs for y in ys]
    return [np.asarray(cxy, dtype=float)] + lattice


class PlacementCheck:
    """One simulator world, rebuilt per configuration: ``room(...)`` gives its :class:`RoomFit`."""

    def __init__(self, renderer: str = "tiny") -> None:
        from tidee.server.episode import SceneLibrary
        from tidee.server.world import World

        self.world = World(renderer=renderer)
        self.library = SceneLibrary(capacity=1)

    def scene(self, room_type: str, seed: int, mess_index: int | None) -> Any:
        """The configuration's scene, built afresh into the world (a check moves things)."""
        return self.library.scene(self.world, room_type, seed, mess_index)

    def room(self, room_type: str, seed: int, mess_index: int | None) -> RoomFit:
        return RoomFit(self, (room_type, seed, mess_index))

    def close(self) -> None:
        self.world.close()

    def __enter__(self) -> PlacementCheck:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
