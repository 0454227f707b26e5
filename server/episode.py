"""One episode: a room, an agent body, its camera and the actions of the paper.

``Episode.reset`` builds the (tidy or messy) room for an ``EpisodeSpec`` and spawns the
agent near the room centre; ``Episode.step`` executes one action and returns the next
``Observation``. World failures never raise: ``obs.success`` / ``obs.error`` say why.
Ground truth is attached only when the caller asks for it.

A rearrangement (``spec.rearrange_index``) has two phases: ``reset`` starts the
*walkthrough* in the goal state (moving and looking only; ``spec.walkthrough_steps``), and
``begin_unshuffle`` switches to the shuffled state with the agent back at its start pose
(``spec.max_steps``). States come from ``tidee.server.shuffle``.
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numpy as np

from tidee.protocol.messages import (
    INTERACT_M,
    PIXEL_ACTIONS,
    Action,
    ActionError,
    ActionName,
    EpisodeSpec,
    GroundTruth,
    Observation,
)
from tidee.server.messup import mess_up
from tidee.server.rooms import AGENT_RADIUS, NAV_CELL, generate_scene, nav_grid, rooms_version, spawn_point
from tidee.server.scene import Scene, quat_yaw
from tidee.server.scene_cache import SceneCache
from tidee.server.shuffle import Rearrangement, make_rearrangement
from tidee.server.splits import check_mess_index
from tidee.server.world import FOV_DEG, World

MOVE_M = 0.25
TURN_DEG = 90.0
LOOK_DEG = 30.0
PITCH_LIMITS = (-30.0, 60.0)  # AI2THOR's horizon limits, positive looking down
REACH_DROP_M = 0.15  # a put at a point: the surface must lie this close under it
REACH_SLACK_M = 0.05  # ... and nothing nearer along the ray than the point less this
POSE_NOISE_M = 0.005
POSE_NOISE_DEG = 0.5
DEPTH_NOISE_REL = 0.02
MOVES = {
    ActionName.MoveAhead: (1, 0),
    ActionName.MoveBack: (-1, 0),
    ActionName.MoveLeft: (0, 1),
    ActionName.MoveRight: (0, -1),
}


class SceneLibrary:
    """Tidy and messy scenes by key: a small in-memory LRU over the on-disk :class:`SceneCache`,
    generated (physics and all) only when neither has them.

    ``disk``: a SceneCache, or None for no disk cache; default: the user's cache directory.
    ``version``: the room generator's (``rooms.rooms_version``; default 1).
    """

    def __init__(
        self,
        capacity: int = 32,
        disk: SceneCache | None | Literal["default"] = "default",
        version: int | None = None,
    ) -> None:
        self.capacity = capacity
        self.version = rooms_version(version)
        self._cache: OrderedDict[tuple, dict] = OrderedDict()
        self._disk = SceneCache(version=self.version) if disk == "default" else disk

    def disk(self) -> SceneCache | None:
        """The disk cache (None: disabled)."""
        return self._disk

    def _get(self, key: tuple) -> dict | None:
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        disk = self._disk
        stored = disk.load(*key) if disk is not None else None
        if stored is not None:
            self._remember(key, stored)
        return stored

    def _remember(self, key: tuple, scene: dict) -> None:
        self._cache[key] = scene
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)

    def _put(self, key: tuple, scene: Scene) -> None:
        # Through JSON, so a fresh scene is built from exactly what a later load from disk gives.
        d = json.loads(json.dumps(scene.to_dict()))
        disk = self._disk
        if disk is not None:
            disk.store(*key, d)
        self._remember(key, d)

    def scene(self, world: World, room_type: str, seed: int, mess_index: int | None) -> Scene:
        """The scene, built into ``world`` as a side effect; refuses a mess index outside the room's split."""
        check_mess_index(int(seed), mess_index)
        key = (room_type, int(seed), mess_index)
        cached = self._get(key)
        if cached is not None:
            scene = Scene.from_dict(cached)
            world.build(scene)
            return scene
        tidy = self.tidy_scene(world, room_type, seed)
        if mess_index is None:
            scene = Scene.from_dict(self._cache[(room_type, int(seed), None)])
            world.build(scene)
            return scene
        world.build(tidy)
        records = mess_up(world, tidy, mess_index)
        messy = world.export()
        messy.mess_index = mess_index
        messy.mess = records
        self._put(key, messy)
        scene = Scene.from_dict(self._cache[key])
        world.build(scene)
        return scene

    def tidy_scene(self, world: World, room_type: str, seed: int) -> Scene:
        """The tidy room: from the caches (``world`` untouched), else generated in ``world``
        (physics and all) and stored."""
        key = (room_type, int(seed), None)
        cached = self._get(key)
        if cached is not None:
            return Scene.from_dict(cached)
        tidy = generate_scene(room_type, seed, world=world, version=self.version)
        self._put(key, tidy)
        return tidy

    def rearrangement(self, world: World, room_type: str, seed: int, index: int) -> Rearrangement:
        """Rearrangement configuration ``index`` of a room (``tidee.server.shuffle``): its goal
        and shuffled scenes, generated from the tidy room when not cached. ``world`` is left
        holding some state of the room: build the one you need."""
        check_mess_index(int(seed), index)
        keys = [(room_type, int(seed), f"{state}{int(index)}") for state in ("goal", "shuffle")]
        cached = [self._get(key) for key in keys]
        if cached[0] is None or cached[1] is None:
            self.scene(world, room_type, seed, None)
            made = make_rearrangement(world, world.export(), index)
            for key, scene in zip(keys, (made.goal, made.shuffled)):
                self._put(key, scene)
            cached = [self._cache[key] for key in keys]
        return Rearrangement(Scene.from_dict(cached[0]), Scene.from_dict(cached[1]))


@dataclass
class Body:
    """The agent: true pose (world) and what its odometry believes (world)."""

    x: float
    y: float
    yaw: float  # radians
    pitch: float  # degrees, positive down
    odo_x: float
    odo_y: float
    odo_yaw: float
    held: str | None = None
    held_turn: float = 0.0  # radians: the held object's yaw at pick-up less the agent's then


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def camera_axes(yaw: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, down, forward) unit vectors in the world for a yaw and a downward pitch."""
    th = math.radians(pitch_deg)
    fwd = np.array([math.cos(yaw) * math.cos(th), math.sin(yaw) * math.cos(th), -math.sin(th)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    return right, down, fwd


class Episode:
    def __init__(self, renderer: str = "auto", library: SceneLibrary | None = None) -> None:
        self.world = World(renderer=renderer)
        self.library = library or SceneLibrary()
        self.spec = EpisodeSpec()
        self.session = ""
        self.scene: Scene | None = None
        self.body = Body(0, 0, 0, 0, 0, 0, 0)
        self.start = (0.0, 0.0, 0.0)
        self.steps = 0
        self.done = False
        self.free = np.zeros((1, 1), bool)
        self.rng = np.random.default_rng(0)
        self._present: list[str] = []
        self.phase: str | None = None  # a rearrangement's phase; None in a tidying episode
        self._shuffled: Scene | None = None  # the unshuffle phase's scene, during the walkthrough

    @property
    def renderer(self) -> str:
        return self.world.renderer

    def close(self) -> None:
        self.world.close()

    # ----------------------------------------------------------------- reset
    def reset(self, spec: EpisodeSpec, session: str = "local", ground_truth: bool = False) -> Observation:
        """A tidying episode (``spec.mess_index``; None: the tidy room), or the walkthrough phase
        of a rearrangement (``spec.rearrange_index``): the goal state, interaction refused."""
        self.spec, self.session = spec, session
        self.phase, self._shuffled = None, None
        if spec.rearrange_index is None:
            self.scene = self.library.scene(self.world, spec.room_type, spec.seed, spec.mess_index)
        else:
            pair = self.library.rearrangement(self.world, spec.room_type, spec.seed, spec.rearrange_index)
            self.scene, self._shuffled, self.phase = pair.goal, pair.shuffled, "walkthrough"
            self.world.build(pair.goal)
        self.steps, self.done = 0, False
        mess = 0 if spec.mess_index is None else spec.mess_index + 1
        if spec.rearrange_index is not None:
            mess = 1000 + spec.rearrange_index
        self.rng = np.random.default_rng(
            np.random.SeedSequence([spec.seed, mess, spec.start_seed or 0, 5150])
        )
        self._update_free()
        x, y = self._spawn_point(spec.start_seed)
        yaw = float(self.rng.integers(4)) * math.pi / 2
        self.body = Body(x, y, yaw, 0.0, x, y, yaw)
        self.start = (x, y, yaw)
        self._last = (None, True, None, "")
        return self.observe(ground_truth)

    def load(
        self,
        scene: Scene,
        spec: EpisodeSpec,
        agent_xy: tuple[float, float],
        yaw_deg: float,
        session: str = "local",
        ground_truth: bool = False,
    ) -> Observation:
        """Start an episode in a given scene with the agent at a given pose (tests, tools)."""
        self.spec, self.session, self.scene = spec, session, scene
        self.phase, self._shuffled = None, None
        self.world.build(scene)
        self.steps, self.done = 0, False
        self.rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 5150]))
        self._update_free()
        yaw = math.radians(yaw_deg)
        self.body = Body(agent_xy[0], agent_xy[1], yaw, 0.0, agent_xy[0], agent_xy[1], yaw)
        self.start = (agent_xy[0], agent_xy[1], yaw)
        self._last = (None, True, None, "")
        return self.observe(ground_truth)

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation:
        """End a rearrangement's walkthrough: the shuffled room, the step count back to 0, the
        agent at its start pose (the same start frame as the walkthrough's) with empty hands."""
        if self.scene is None:
            raise RuntimeError("begin_unshuffle() before reset()")
        if self.phase is None:
            raise ValueError("this is not a rearrangement episode: reset with spec.rearrange_index first")
        if self.phase != "walkthrough" or self._shuffled is None:
            raise ValueError("the unshuffle phase has already begun; reset to start a new rearrangement")
        self.scene, self._shuffled, self.phase = self._shuffled, None, "unshuffle"
        self.world.build(self.scene)
        self._update_free()
        self.steps, self.done = 0, False
        x, y, yaw = self.start
        self.body = Body(x, y, yaw, 0.0, x, y, yaw)
        self._last = (None, True, None, "")
        return self.observe(ground_truth)

    @property
    def step_cap(self) -> int:
        """This phase's step budget: the walkthrough's, else ``spec.max_steps``."""
        return self.spec.walkthrough_steps if self.phase == "walkthrough" else self.spec.max_steps

    def _update_free(self) -> None:
        assert self.scene is not None
        aabbs = [self.world.aabb(o.id) for o in self.scene.objects if not o.pickupable and o.type != "Floor"]
        self.free = nav_grid(aabbs, self.scene.width, self.scene.depth)

    def _spawn_point(self, start_seed: int | None) -> tuple[float, float]:
        assert self.scene is not None
        return spawn_point(self.free, self.scene.width, self.scene.depth, start_seed)

    # ----------------------------------------------------------------- step
    def step(self, action: Action, ground_truth: bool = False) -> Observation:
        self.act(action)
        return self.observe(ground_truth)

    def act(self, action: Action) -> tuple[bool, ActionError | None, str]:
        """``step`` without the render: (success, error, message). For walks that keep only some
        frames (data generation): ``observe`` renders the state when a frame is wanted. The
        episode's state is what ``step`` leaves; with depth noise the random stream differs,
        since that noise is drawn at the render."""
        if self.scene is None:
            raise RuntimeError("step() before reset()")
        name = ActionName(action.name)
        if self.done:
            self._last = (
                name.value,
                False,
                ActionError.episode_over,
                "the episode is over (Done was called or the step cap reached)",
            )
            return self._last[1:]
        self.steps += 1
        if self.phase == "walkthrough" and name in PIXEL_ACTIONS:
            ok, err, msg = (
                False,
                ActionError.walkthrough,
                f"{name.value} is not allowed in the walkthrough phase (only moving and looking); "
                "switch to the unshuffle phase first",
            )
        else:
            ok, err, msg = self._execute(action)
        if name == ActionName.Done or self.steps >= self.step_cap:
            self.done = True
        self._last = (name.value, ok, err, msg)
        return ok, err, msg

    def observe(self, ground_truth: bool = False) -> Observation:
        """Render the current state, reporting the outcome of the last action (``step`` = ``act`` + this)."""
        if self.scene is None:
            raise RuntimeError("observe() before reset()")
        return self._observe(*self._last, ground_truth)

    @property
    def pitch(self) -> float:
        """The camera's pitch in degrees (positive looks down), as ``Observation.agent_pose[3]``."""
        return float(self.body.pitch)

    def _execute(self, a: Action) -> tuple[bool, ActionError | None, str]:
        n = a.name
        if n in MOVES:
            return self._move(*MOVES[n])
        if n in (ActionName.RotateLeft, ActionName.RotateRight):
            sign = 1.0 if n == ActionName.RotateLeft else -1.0
            noise = math.radians(self.rng.normal(0, POSE_NOISE_DEG)) if self.spec.pose_noise else 0.0
            self.body.yaw += sign * math.radians(TURN_DEG) + noise
            self.body.odo_yaw += sign * math.radians(TURN_DEG)
            return True, None, ""
        if n in (ActionName.LookUp, ActionName.LookDown):
            new = self.body.pitch + (LOOK_DEG if n == ActionName.LookDown else -LOOK_DEG)
            if not PITCH_LIMITS[0] - 1e-6 <= new <= PITCH_LIMITS[1] + 1e-6:
                return False, ActionError.look_limit, f"pitch would be {new:.0f} deg, outside {PITCH_LIMITS}"
            self.body.pitch = new
            return True, None, ""
        if n == ActionName.Done:
            return True, None, ""
        assert a.x is not None and a.y is not None
        if n == ActionName.PickupObject:
            return self._pickup(a.x, a.y)
        if n == ActionName.PutObject:
            return self._put(a.x, a.y, a.yaw, a.reach)
        return self._open_close(a.x, a.y, open_=(n == ActionName.OpenObject))

    def _walkable(self, x: float, y: float) -> bool:
        i, j = int(x / NAV_CELL), int(y / NAV_CELL)
        return 0 <= i < self.free.shape[0] and 0 <= j < self.free.shape[1] and bool(self.free[i, j])

    def _move(self, fwd: int, left: int) -> tuple[bool, ActionError | None, str]:
        b = self.body
        dx = MOVE_M * (fwd * math.cos(b.yaw) - left * math.sin(b.yaw))
        dy = MOVE_M * (fwd * math.sin(b.yaw) + left * math.cos(b.yaw))
        if self.spec.pose_noise:
            dx += self.rng.normal(0, POSE_NOISE_M)
            dy += self.rng.normal(0, POSE_NOISE_M)
        tx, ty = b.x + dx, b.y + dy
        if not all(self._walkable(b.x + f * dx, b.y + f * dy) for f in (0.5, 1.0)):
            return False, ActionError.blocked, "the move would collide with furniture or a wall"
        b.x, b.y = tx, ty
        ox = MOVE_M * (fwd * math.cos(b.odo_yaw) - left * math.sin(b.odo_yaw))
        oy = MOVE_M * (fwd * math.sin(b.odo_yaw) + left * math.cos(b.odo_yaw))
        b.odo_x, b.odo_y = b.odo_x + ox, b.odo_y + oy
        return True, None, ""

    # -- interaction --------------------------------------------------------------
    def _eye(self) -> np.ndarray:
        return np.array([self.body.x, self.body.y, self.spec.camera_height])

    def _pixel_ray(self, u: float, v: float) -> tuple[str | None, int, np.ndarray, float]:
        """Cast through a normalised image point (0..1 across the image: a pixel's centre is
        ((u + 0.5) / w, (v + 0.5) / h)) along the ray the render shows there; returns (object
        id, link, hit point, distance). Thin things on the floor (a knife, a pencil) are two
        or three pixels wide: half a pixel off and a pick aimed at them hits the floor."""
        eye = self._eye()
        oid, link, point, _ = self.world.ray(eye, eye + 20.0 * self._pixel_dir(u, v))
        return oid, link, point, float(np.linalg.norm(point - eye))

    def _pixel_dir(self, u: float, v: float) -> np.ndarray:
        """The unit world direction of the ray the render shows at a normalised image point."""
        right, down, fwd = camera_axes(self.body.yaw, self.body.pitch)
        t = math.tan(math.radians(FOV_DEG / 2))
        du, dv = self.world.pixel_offset
        r = self.spec.resolution
        u, v = u + du / r, v + dv / r
        d = fwd + (2 * u - 1) * t * right + (2 * v - 1) * t * down
        return d / np.linalg.norm(d)

    def _target(self, u: float, v: float) -> tuple[str, np.ndarray] | tuple[bool, ActionError, str]:
        """The object at a pixel within reach: (id, hit point), or a failure triple."""
        oid, _, point, dist = self._pixel_ray(u, v)
        if oid is None:
            return False, ActionError.nothing_there, "nothing at that pixel"
        if dist > INTERACT_M:
            return False, ActionError.too_far, f"{oid} is {dist:.2f} m away (limit {INTERACT_M} m)"
        return oid, point

    def _pickup(self, u: float, v: float) -> tuple[bool, ActionError | None, str]:
        if self.body.held is not None:
            return False, ActionError.hands_full, f"already holding {self.body.held}"
        hit = self._target(u, v)
        if len(hit) == 3:
            return hit  # type: ignore[return-value]
        oid = hit[0]
        obj = self.world.bodies[oid].obj
        if not obj.pickupable:
            return False, ActionError.not_pickupable, f"{obj.type} cannot be picked up"
        _, orn = self.world.pose(oid)
        self.body.held_turn = quat_yaw(orn) - self.body.yaw  # a held object turns with the agent
        self.world.set_static(oid, True)
        self.world.set_pose(oid, [self.body.x, self.body.y, -5.0], [0, 0, 0, 1])
        obj.parent, obj.parent_type = "agent", "agent"
        self.body.held = oid
        return True, None, ""

    def _reach(
        self, u: float, v: float, reach: float
    ) -> tuple[str, np.ndarray] | tuple[bool, ActionError, str]:
        """The surface under the point ``reach`` metres along the pixel's ray (as AI2THOR's
        PlaceObjectAtPoint puts at a point): (id, surface point), or a failure triple. The way
        there must be clear (an arm reaches over a counter's edge, not through a vase), and
        something must lie within ``REACH_DROP_M`` under the point."""
        if reach > INTERACT_M:
            return False, ActionError.too_far, f"a reach of {reach:.2f} m is beyond {INTERACT_M} m"
        oid, _, _, dist = self._pixel_ray(u, v)
        if oid is not None and dist < reach - REACH_SLACK_M:
            return False, ActionError.blocked, f"{oid} is in the way, {dist:.2f} m along the ray"
        point = self._eye() + reach * self._pixel_dir(u, v)
        under, _, hit, _ = self.world.ray(point + [0.0, 0.0, 0.01], point - [0.0, 0.0, REACH_DROP_M])
        if under is None:
            return False, ActionError.nothing_there, f"nothing within {REACH_DROP_M} m under that point"
        return under, hit

    def _put(
        self, u: float, v: float, turn_deg: float | None = None, reach: float | None = None
    ) -> tuple[bool, ActionError | None, str]:
        """Put the held object down where the pixel's ray meets a receptacle, or (``reach``
        given) on the receptacle under the point that far along the ray: with its x axis along
        the agent's heading, or (``turn_deg`` given) turned that much from how it lay when
        picked up, as the agent has turned since. A put at a point (``reach``) that would touch
        a neighbour there is shifted 1-3 cm before it goes to the 6 cm lattice (``World.place``).
        A closed openable takes nothing at a pixel (``receptacle_closed``: open it first); a put
        at a point on its outer top (a toilet roll on a closed bathroom cabinet) lands there."""
        held = self.body.held
        if held is None:
            return False, ActionError.hands_empty, "not holding anything"
        hit = self._target(u, v) if reach is None else self._reach(u, v, reach)
        if len(hit) == 3:
            return hit  # type: ignore[return-value]
        oid, point = hit  # type: ignore[misc]
        target = self.world.bodies[oid].obj
        if target.pickupable and not target.receptacle and target.parent not in (None, "agent"):
            target = self.world.bodies[target.parent].obj  # aiming at a thing on a table: the table
        if not target.receptacle:
            return False, ActionError.not_receptacle, f"{target.type} is not a receptacle"
        if (
            target.openable
            and not target.is_open
            and not (reach is not None and self.world.on_outer_surface(target.id, point))
        ):
            return False, ActionError.receptacle_closed, f"{target.type} is closed; open it first"
        yaw = (
            self.body.yaw
            if turn_deg is None
            else self.body.yaw + self.body.held_turn + math.radians(turn_deg)
        )
        if self.world.place(held, target.id, point, yaw=yaw, nudge=reach is not None):
            self.body.held = None
            return True, None, ""
        return False, ActionError.no_free_space, f"no stable free spot for {held} on {target.id} there"

    def _open_close(self, u: float, v: float, open_: bool) -> tuple[bool, ActionError | None, str]:
        hit = self._target(u, v)
        if len(hit) == 3:
            return hit  # type: ignore[return-value]
        oid = hit[0]
        obj = self.world.bodies[oid].obj
        parent = self.world.bodies.get(obj.parent or "")
        if not obj.openable and obj.pickupable and parent is not None and parent.obj.openable:
            obj, oid = parent.obj, parent.obj.id  # aiming at a thing inside: its container
        if not obj.openable:
            return False, ActionError.not_openable, f"{obj.type} cannot be opened or closed"
        if obj.is_open == open_:
            return (
                False,
                (ActionError.already_open if open_ else ActionError.already_closed),
                f"{obj.type} is already {'open' if open_ else 'closed'}",
            )
        self.world.set_open(oid, open_)
        if open_ and not obj.pickupable and self._door_hits_agent(oid):
            self.world.set_open(oid, False)
            return False, ActionError.blocked, f"the {obj.type} door would hit the agent; step back"
        if not obj.pickupable:
            self._update_free()
        return True, None, ""

    def _door_hits_agent(self, oid: str) -> bool:
        lo, hi = self.world.aabb(oid)
        dx = max(lo[0] - self.body.x, 0.0, self.body.x - hi[0])
        dy = max(lo[1] - self.body.y, 0.0, self.body.y - hi[1])
        return math.hypot(dx, dy) < AGENT_RADIUS

    # ----------------------------------------------------------------- observe
    def _start_from_world(self) -> np.ndarray:
        x0, y0, yaw0 = self.start
        t = np.eye(4)
        t[:3, :3] = _rot_z(yaw0).T
        t[:3, 3] = -_rot_z(yaw0).T @ np.array([x0, y0, 0.0])
        return t

    def camera_pose_world(self, believed: bool) -> np.ndarray:
        b = self.body
        x, y, yaw = (b.odo_x, b.odo_y, b.odo_yaw) if believed else (b.x, b.y, b.yaw)
        right, down, fwd = camera_axes(yaw, b.pitch)
        t = np.eye(4)
        t[:3, 0], t[:3, 1], t[:3, 2] = right, down, fwd
        t[:3, 3] = [x, y, self.spec.camera_height]
        return t

    def intrinsics(self) -> np.ndarray:
        r = self.spec.resolution
        f = (r / 2) / math.tan(math.radians(FOV_DEG / 2))
        return np.array([[f, 0, (r - 1) / 2], [0, f, (r - 1) / 2], [0, 0, 1.0]])

    def _observe(
        self, last: str | None, ok: bool, err: ActionError | None, msg: str, ground_truth: bool
    ) -> Observation:
        b = self.body
        right, down, fwd = camera_axes(b.yaw, b.pitch)
        rgb, depth, seg = self.world.render(
            self._eye(), fwd, -down, self.spec.resolution, segmentation=ground_truth
        )
        if self.spec.depth_noise:
            depth = (depth * (1.0 + self.rng.normal(0, DEPTH_NOISE_REL, depth.shape))).astype(np.float32)
        s2w = self._start_from_world()
        cam = s2w @ self.camera_pose_world(believed=True)
        ox, oy, _ = s2w[:3, :3] @ np.array([b.odo_x, b.odo_y, 0]) + s2w[:3, 3]
        yaw_deg = math.degrees(b.odo_yaw - self.start[2])
        gt = self._ground_truth(seg) if ground_truth else None
        held_type = self.world.bodies[b.held].obj.type if b.held else None
        return Observation(
            session=self.session,
            step=self.steps,
            rgb=rgb,
            depth=depth,
            camera_pose=cam,
            agent_pose=(float(ox), float(oy), float((yaw_deg + 180) % 360 - 180), float(b.pitch)),
            intrinsics=self.intrinsics(),
            held=held_type,
            held_id=b.held,
            last_action=last,
            success=ok,
            error=err.value if err else None,
            message=msg,
            done=self.done,
            steps_left=max(self.step_cap - self.steps, 0),
            ground_truth=gt,
            phase=self.phase,
        )

    def _ground_truth(self, seg: np.ndarray | None) -> GroundTruth:
        objects = self.object_states()
        index = {o["id"]: k for k, o in enumerate(objects)}
        lut = {uid: index[oid] for uid, oid in self.world.uid_to_id.items()}
        inst = np.full(seg.shape if seg is not None else (0, 0), -1, np.int32)
        if seg is not None:
            uids = seg & ((1 << 24) - 1)
            for uid, k in lut.items():
                inst[uids == uid] = k
        return GroundTruth(instance_seg=inst, objects=objects)

    def object_states(self) -> list[dict]:
        """Scene-export entries at the current physics state, with ``moved`` flags."""
        assert self.scene is not None
        moved = {m.id for m in self.scene.mess}
        out = []
        for o in self.world.export().objects:
            d = {
                k: getattr(o, k)
                for k in (
                    "id",
                    "type",
                    "variant",
                    "pickupable",
                    "receptacle",
                    "openable",
                    "is_open",
                    "parent",
                    "parent_type",
                    "position",
                    "orientation",
                    "size",
                )
            }
            d["moved"] = o.id in moved
            out.append(d)
        return out

    def state(self) -> dict:
        """Privileged: the full scene (evaluation), with the agent's true pose."""
        assert self.scene is not None
        self.world.refresh_parents()
        scene = self.world.export().to_dict()
        scene["agent"] = {
            "x": self.body.x,
            "y": self.body.y,
            "yaw_deg": math.degrees(self.body.yaw),
            "pitch_deg": self.body.pitch,
            "held": self.body.held,
            "steps": self.steps,
            "done": self.done,
        }
        x0, y0, yaw0 = self.start
        scene["start"] = {"x": x0, "y": y0, "yaw_deg": math.degrees(yaw0)}  # the start frame in the world
        scene["phase"] = self.phase
        return scene
