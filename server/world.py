"""The PyBullet world of one episode: bodies built from a Scene, physics, rendering, rays.

One ``World`` owns one PyBullet DIRECT client. Furniture is static (mass 0) with doors
and drawer fronts as jointed links; small objects are dynamic rigid bodies. Every object
is one multibody whose unique id maps back to its scene id, so the segmentation buffer
is an instance mask for free.

Rendering goes through PyBullet's eglRenderer plugin (OpenGL; Mesa's llvmpipe without a
GPU) when it loads, else through TinyRenderer; both draw the same palette-textured
meshes (``tidee.server.meshes``). An EGL World must be used from the thread that made it.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
import pkgutil
from dataclasses import dataclass

import numpy as np

from tidee.protocol.vocab import RENDERERS
from tidee.server.bullet import pb, quiet_stdio
from tidee.server.catalog import CATEGORIES
from tidee.server.catalog.schema import Category, Part, Surface
from tidee.server.meshes import Mesh, add_part, hex_to_rgb, part_geometry
from tidee.server.scene import FLOOR_ID, Scene, SceneObject, quat_yaw

log = logging.getLogger(__name__)

PHYSICS_HZ = 240
NEAR, FAR = 0.05, 20.0
FOV_DEG = 90.0
DEFAULT_ROLES = {
    "metal": "#b8bcc2",
    "dark": "#2a2a2e",
    "light": "#ecebe6",
    "white": "#f4f4f2",
    "black": "#141416",
    "glass": "#9fc6d8",
}
DOOR_OPEN_RAD = math.radians(95)
PLACE_CANDIDATES = 160  # spots tried per PutObject, nearest the aimed point first (6 cm lattice)
# A put at a point (``place(nudge=True)``) whose aimed spot touches a neighbour tries these
# shifts (metres, 8 directions each) before the lattice.
NUDGES_M = (0.01, 0.02, 0.03)


def resolve_category(obj: SceneObject) -> tuple[Category, tuple[Part, ...], tuple[Surface, ...], float]:
    cat = CATEGORIES[obj.type]
    var = cat.variant(obj.variant)
    parts = (var.parts if var and var.parts else None) or cat.parts
    surfaces = (var.surfaces if var and var.surfaces else None) or cat.surfaces
    mass = (var.mass if var and var.mass is not None else None) or cat.mass
    return cat, parts, surfaces, mass


def part_color(part: Part, palette: dict[str, str]) -> tuple[int, int, int]:
    if part.color.startswith("#"):
        return hex_to_rgb(part.color)
    hexc = palette.get(part.color) or DEFAULT_ROLES.get(part.color)
    if hexc is None:
        hexc = next(iter(palette.values()), "#808080")
    return hex_to_rgb(hexc)


@dataclass
class Door:
    joint: int
    kind: str  # hinge side or "slide"
    open_value: float  # joint value when open


@dataclass
class BodyInfo:
    obj: SceneObject
    uid: int
    surfaces: tuple[Surface, ...]
    doors: list[Door]
    mass: float


class RendererUnavailable(RuntimeError):
    pass


@functools.cache
def _libegl() -> ctypes.CDLL:
    """libEGL, the library the eglRenderer plugin itself loads (so its handles are ours)."""
    egl = ctypes.CDLL("libEGL.so.1")
    egl.eglGetCurrentDisplay.restype = ctypes.c_void_p
    egl.eglGetCurrentSurface.restype = ctypes.c_void_p
    egl.eglGetCurrentSurface.argtypes = [ctypes.c_int]
    egl.eglGetCurrentContext.restype = ctypes.c_void_p
    egl.eglMakeCurrent.restype = ctypes.c_uint
    egl.eglMakeCurrent.argtypes = [ctypes.c_void_p] * 4
    return egl


class EGLContext:
    """The OpenGL context of one World's eglRenderer plugin.

    The plugin makes its EGL context current once, when it loads, and never again. A
    second EGL World on the same thread (a server holding several sessions on one worker)
    takes over the current context, so the first one's shapes and frames would go to the
    wrong context (wrong pictures, then a crash when that context is destroyed). A World
    therefore captures its context right after loading the plugin and makes it current
    again before every call that reaches OpenGL. A context can be current on one thread
    only: the thread that created the World.
    """

    EGL_DRAW = 0x3059

    def __init__(self) -> None:
        egl = _libegl()
        self.display = egl.eglGetCurrentDisplay()
        self.surface = egl.eglGetCurrentSurface(self.EGL_DRAW)
        self.context = egl.eglGetCurrentContext()
        if not (self.display and self.surface and self.context):
            raise RendererUnavailable("the eglRenderer plugin loaded but left no EGL context current")

    def make_current(self) -> None:
        egl = _libegl()
        if egl.eglGetCurrentContext() != self.context and not egl.eglMakeCurrent(
            self.display, self.surface, self.surface, self.context
        ):
            raise RuntimeError(
                "cannot make this World's EGL context current: an EGL World must be "
                "used from the thread that created it"
            )


def surface_local(centre: np.ndarray, yaw: float, point: np.ndarray) -> tuple[float, float]:
    """A world point's (x, y) in a surface's own frame: from its centre, along its axes."""
    c, s = math.cos(yaw), math.sin(yaw)
    return (
        c * (point[0] - centre[0]) + s * (point[1] - centre[1]),
        -s * (point[0] - centre[0]) + c * (point[1] - centre[1]),
    )


class World:
    """A PyBullet client holding one room."""

    def __init__(self, renderer: str = "auto") -> None:
        if renderer not in RENDERERS:
            raise ValueError(f"renderer must be auto, egl or tiny; got {renderer!r}")
        self.client = pb.connect(pb.DIRECT)
        self.renderer = "tiny"
        self._egl_plugin = -1
        self._gl: EGLContext | None = None
        # "auto" takes EGL (faster than TinyRenderer, even on llvmpipe) when the plugin
        # loads, and falls back to TinyRenderer otherwise.
        if renderer != "tiny":
            self._load_egl()
            if self._gl is not None:
                self.renderer = "egl"
            elif renderer == "egl":
                pb.disconnect(self.client)
                raise RendererUnavailable(
                    "EGL renderer requested but PyBullet's eglRenderer plugin did not load; "
                    "install Debian's libegl1 libegl-mesa0 libgl1-mesa-dri or use --renderer tiny"
                )
            else:
                log.info("EGL renderer unavailable; using TinyRenderer")
        self.bodies: dict[str, BodyInfo] = {}
        self.uid_to_id: dict[int, str] = {}
        self.scene: Scene | None = None

    # ------------------------------------------------------------------ set-up
    def _load_egl(self) -> None:
        """Load the eglRenderer plugin and capture its context; on failure leave ``_gl`` None."""
        loader = pkgutil.get_loader("eglRenderer")
        if loader is None:
            return
        path = loader.get_filename()  # type: ignore[attr-defined]
        try:
            with quiet_stdio():
                self._egl_plugin = pb.loadPlugin(path, "_eglRendererPlugin", physicsClientId=self.client)
            if self._egl_plugin >= 0:
                self._gl = EGLContext()
        except Exception:  # pragma: no cover - depends on the machine's GL stack
            if self._egl_plugin >= 0:
                pb.unloadPlugin(self._egl_plugin, physicsClientId=self.client)
            self._egl_plugin = -1

    def _use_gl(self) -> None:
        """Before a call that reaches OpenGL: make this World's EGL context current."""
        if self._gl is not None:
            self._gl.make_current()

    def close(self) -> None:
        if self.client is not None and self.client >= 0:
            try:
                if self._egl_plugin >= 0:
                    self._use_gl()
                    with quiet_stdio():
                        pb.unloadPlugin(self._egl_plugin, physicsClientId=self.client)
                with quiet_stdio():
                    pb.disconnect(self.client)
            except (pb.error, RuntimeError):  # a wrong thread: leak the client rather than crash
                pass
            self.client = -1

    def __del__(self) -> None:  # a dropped World must not leak its PyBullet client
        try:
            self.close()
        except Exception:
            pass

    def build(self, scene: Scene) -> None:
        """(Re)create every body of the scene exactly as recorded."""
        c = self.client
        self._use_gl()
        pb.resetSimulation(physicsClientId=c)
        # PyBullet keeps every OBJ file it has parsed, process-wide, keyed by path, and neither
        # resetSimulation nor disconnect frees it; meshes are files named by a digest, so each new
        # room would add about 2.4 MB for the life of the process. Switching file caching off and
        # on empties that cache (shapes repeated within this scene are still parsed once).
        pb.setPhysicsEngineParameter(enableFileCaching=0, physicsClientId=c)
        pb.setPhysicsEngineParameter(enableFileCaching=1, physicsClientId=c)
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=1.0 / PHYSICS_HZ,
            numSolverIterations=30,
            deterministicOverlappingPairs=1,
            physicsClientId=c,
        )
        self.bodies.clear()
        self.uid_to_id.clear()
        self.scene = scene
        for obj in scene.objects:
            info = self._create_body(obj)
            self.bodies[obj.id] = info
            self.uid_to_id[info.uid] = obj.id
            for d in info.doors:
                pb.resetJointState(info.uid, d.joint, d.open_value if obj.is_open else 0.0, physicsClientId=c)

    def _create_body(self, obj: SceneObject) -> BodyInfo:
        c = self.client
        cat, parts, surfaces, mass = resolve_category(obj)
        size = np.array(obj.size, float)
        palette = obj.palette
        rigid = [p for p in parts if p.door is None]
        doors = [p for p in parts if p.door is not None]
        dynamic = cat.pickupable

        base_mesh = Mesh()
        for p in rigid:
            add_part(base_mesh, p, size, part_color(p, palette))
        base_vis = self._visual(base_mesh)
        base_col = self._collision([p for p in rigid if p.collide], size)

        link_args: dict[str, list] = {
            k: []
            for k in (
                "linkMasses",
                "linkCollisionShapeIndices",
                "linkVisualShapeIndices",
                "linkPositions",
                "linkOrientations",
                "linkInertialFramePositions",
                "linkInertialFrameOrientations",
                "linkParentIndices",
                "linkJointTypes",
                "linkJointAxis",
            )
        }
        door_infos: list[Door] = []
        for i, p in enumerate(doors):
            center = np.array(p.center) * size
            ext = np.array(p.extent) * size
            pivot, axis, joint, open_value = self._door_joint(p, center, ext, size)
            mesh = Mesh()
            add_part(mesh, p, size, part_color(p, palette), offset=pivot)
            link_args["linkMasses"].append(0.0)
            link_args["linkCollisionShapeIndices"].append(
                self._collision([p], size, offset=pivot) if p.collide else -1
            )
            link_args["linkVisualShapeIndices"].append(self._visual(mesh))
            link_args["linkPositions"].append(pivot.tolist())
            link_args["linkOrientations"].append([0, 0, 0, 1])
            link_args["linkInertialFramePositions"].append([0, 0, 0])
            link_args["linkInertialFrameOrientations"].append([0, 0, 0, 1])
            link_args["linkParentIndices"].append(0)
            link_args["linkJointTypes"].append(joint)
            link_args["linkJointAxis"].append(axis)
            door_infos.append(Door(joint=i, kind=str(p.door), open_value=open_value))

        uid = pb.createMultiBody(
            baseMass=mass if dynamic else 0.0,
            baseCollisionShapeIndex=base_col,
            baseVisualShapeIndex=base_vis,
            basePosition=obj.position,
            baseOrientation=obj.orientation,
            physicsClientId=c,
            **link_args,
        )
        if uid < 0:
            raise RuntimeError(f"PyBullet could not create body for {obj.id}")
        if dynamic:
            pb.changeDynamics(
                uid,
                -1,
                lateralFriction=0.8,
                rollingFriction=0.002,
                spinningFriction=0.002,
                linearDamping=0.05,
                angularDamping=0.2,
                physicsClientId=c,
            )
        return BodyInfo(obj=obj, uid=uid, surfaces=surfaces, doors=door_infos, mass=mass)

    @staticmethod
    def _door_joint(
        p: Part, center: np.ndarray, ext: np.ndarray, size: np.ndarray
    ) -> tuple[np.ndarray, list[float], int, float]:
        front_y = center[1] + ext[1] / 2
        if p.door == "left":
            return (
                np.array([center[0] - ext[0] / 2, front_y, center[2]]),
                [0, 0, 1],
                pb.JOINT_REVOLUTE,
                DOOR_OPEN_RAD,
            )
        if p.door == "right":
            return (
                np.array([center[0] + ext[0] / 2, front_y, center[2]]),
                [0, 0, 1],
                pb.JOINT_REVOLUTE,
                -DOOR_OPEN_RAD,
            )
        if p.door == "top":
            return (
                np.array([center[0], front_y, center[2] + ext[2] / 2]),
                [1, 0, 0],
                pb.JOINT_REVOLUTE,
                DOOR_OPEN_RAD,
            )
        if p.door == "bottom":
            return (
                np.array([center[0], front_y, center[2] - ext[2] / 2]),
                [1, 0, 0],
                pb.JOINT_REVOLUTE,
                -DOOR_OPEN_RAD,
            )
        if p.door == "slide":
            return center.copy(), [0, 1, 0], pb.JOINT_PRISMATIC, float(0.6 * size[1])
        raise ValueError(f"unknown door kind {p.door!r}")

    def _visual(self, mesh: Mesh) -> int:
        """A visual shape for the mesh; its OBJ file brings the palette texture along."""
        if mesh.empty:
            return -1
        return pb.createVisualShape(
            pb.GEOM_MESH, fileName=mesh.obj_file(), meshScale=[1, 1, 1], physicsClientId=self.client
        )

    def _collision(self, parts: list[Part], size: np.ndarray, offset: np.ndarray | None = None) -> int:
        if not parts:
            return -1
        c = self.client
        off = np.zeros(3) if offset is None else offset
        if len(parts) == 1 and parts[0].shape == "lathe":
            v, _, _ = part_geometry(parts[0], size)
            return pb.createCollisionShape(pb.GEOM_MESH, vertices=(v - off).tolist(), physicsClientId=c)
        types, half, radii, lengths, frames = [], [], [], [], []
        for p in parts:
            center = np.array(p.center) * size - off
            ext = np.array(p.extent) * size
            if p.shape == "box":
                types.append(pb.GEOM_BOX)
                half.append((ext / 2).tolist())
                radii.append(0.0)
                lengths.append(0.0)
                frames.append(center.tolist())
            elif p.shape == "sphere":
                types.append(pb.GEOM_SPHERE)
                half.append([0, 0, 0])
                radii.append(ext[0] / 2)
                lengths.append(0.0)
                frames.append(center.tolist())
            else:  # cylinder, and lathes inside a compound, approximated by their bounding cylinder
                r = ext[0] / 2
                if p.shape == "lathe":
                    r = max(r0 for r0, _ in p.profile) * ext[0] / 2
                types.append(pb.GEOM_CYLINDER)
                half.append([0, 0, 0])
                radii.append(r)
                lengths.append(ext[2])
                frames.append(center.tolist())
        return pb.createCollisionShapeArray(
            types,
            radii=radii,
            halfExtents=half,
            lengths=lengths,
            collisionFramePositions=frames,
            physicsClientId=c,
        )

    # ------------------------------------------------------------------ state
    def pose(self, obj_id: str) -> tuple[list[float], list[float]]:
        pos, orn = pb.getBasePositionAndOrientation(self.bodies[obj_id].uid, physicsClientId=self.client)
        return list(pos), list(orn)

    def set_pose(self, obj_id: str, position, orientation) -> None:
        info = self.bodies[obj_id]
        pb.resetBasePositionAndOrientation(info.uid, position, orientation, physicsClientId=self.client)
        pb.resetBaseVelocity(info.uid, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    def set_open(self, obj_id: str, is_open: bool) -> None:
        info = self.bodies[obj_id]
        for d in info.doors:
            pb.resetJointState(
                info.uid, d.joint, d.open_value if is_open else 0.0, physicsClientId=self.client
            )
        info.obj.is_open = is_open

    def set_static(self, obj_id: str, static: bool) -> None:
        """Freeze a dynamic object (mass 0) or give it back its mass."""
        info = self.bodies[obj_id]
        pb.changeDynamics(info.uid, -1, mass=0.0 if static else info.mass, physicsClientId=self.client)

    def dynamic_ids(self) -> list[str]:
        return [i for i, b in self.bodies.items() if CATEGORIES[b.obj.type].pickupable]

    def step_physics(self, steps: int) -> None:
        for _ in range(steps):
            pb.stepSimulation(physicsClientId=self.client)

    def settle(
        self, max_seconds: float = 3.0, min_seconds: float = 0.5, ids: list[str] | None = None
    ) -> float:
        """Simulate until every dynamic body is at rest (or the time runs out)."""
        watch = [self.bodies[i].uid for i in (ids if ids is not None else self.dynamic_ids())]
        steps, chunk = 0, PHYSICS_HZ // 10
        while steps < max_seconds * PHYSICS_HZ:
            self.step_physics(chunk)
            steps += chunk
            if steps < min_seconds * PHYSICS_HZ:
                continue
            if all(
                np.linalg.norm(pb.getBaseVelocity(u, physicsClientId=self.client)[0]) < 0.01 for u in watch
            ):
                break
        return steps / PHYSICS_HZ

    def aabb(self, obj_id: str) -> tuple[np.ndarray, np.ndarray]:
        info = self.bodies[obj_id]
        lo, hi = pb.getAABB(info.uid, -1, physicsClientId=self.client)
        lo, hi = np.array(lo), np.array(hi)
        for d in info.doors:
            l2, h2 = pb.getAABB(info.uid, d.joint, physicsClientId=self.client)
            lo, hi = np.minimum(lo, l2), np.maximum(hi, h2)
        return lo, hi

    # ------------------------------------------------------------------ support
    def surfaces_world(
        self, obj_id: str, include_inside: bool = True
    ) -> list[tuple[np.ndarray, np.ndarray, float, float, bool]]:
        """Each surface as (centre xy, half extents, height z, yaw, inside) in world terms."""
        info = self.bodies[obj_id]
        pos, orn = self.pose(obj_id)
        yaw = quat_yaw(orn)
        cy, sy = math.cos(yaw), math.sin(yaw)
        size = np.array(info.obj.size)
        out = []
        for s in info.surfaces:
            if s.inside and not include_inside:
                continue
            lx, ly = s.center[0] * size[0], s.center[1] * size[1]
            cxy = np.array([pos[0] + cy * lx - sy * ly, pos[1] + sy * lx + cy * ly])
            half = np.array([s.extent[0] * size[0] / 2, s.extent[1] * size[1] / 2])
            out.append((cxy, half, pos[2] + s.z * size[2], yaw, s.inside))
        return out

    def on_outer_surface(self, obj_id: str, point: np.ndarray, tol: float = 0.01) -> bool:
        """Whether a point lies on one of the object's outer surfaces (its top, not a shelf
        inside): within the surface's extent and ``tol`` of its height."""
        for cxy, half, z, yaw, _inside in self.surfaces_world(obj_id, include_inside=False):
            lx, ly = surface_local(cxy, yaw, point)
            if abs(lx) <= half[0] and abs(ly) <= half[1] and abs(float(point[2]) - z) <= tol:
                return True
        return False

    def support_of(self, obj_id: str) -> str:
        """The object that holds ``obj_id`` up: a receptacle, or the floor.

        Contacts below the object decide; an object resting on a small non-receptacle
        object (a book on a book) belongs to that object's support. Falls back to a ray
        straight down when there is no contact (e.g. right after a teleport).
        """
        info = self.bodies[obj_id]
        below: dict[int, int] = {}
        for cp in pb.getContactPoints(bodyA=info.uid, physicsClientId=self.client):
            other, normal_on_b = cp[2], cp[7]
            if other != info.uid and normal_on_b[2] > 0.5:
                below[other] = below.get(other, 0) + 1
        support_uid = max(below, key=lambda u: below[u]) if below else None
        if support_uid is None:
            lo, hi = self.aabb(obj_id)
            center = (lo + hi) / 2
            hits = pb.rayTest(
                [center[0], center[1], lo[2] + 0.01],
                [center[0], center[1], -1.0],
                physicsClientId=self.client,
            )
            support_uid = hits[0][0] if hits and hits[0][0] not in (-1, info.uid) else None
            if support_uid is None:
                hits = pb.rayTestBatch(
                    [[center[0], center[1], lo[2] - 0.005]],
                    [[center[0], center[1], -1.0]],
                    physicsClientId=self.client,
                )
                support_uid = hits[0][0] if hits[0][0] >= 0 else None
        sid = self.uid_to_id.get(support_uid) if support_uid is not None else None
        if sid is None:
            return FLOOR_ID
        sobj = self.bodies[sid].obj
        if sobj.receptacle or sid == FLOOR_ID:
            return sid
        if sobj.pickupable:  # stacked on a small object: take that object's support
            return sobj.parent if sobj.parent else FLOOR_ID
        return FLOOR_ID

    def container_of(self, obj_id: str) -> str | None:
        """The openable receptacle whose box contains the object's centre, if any."""
        lo, hi = self.aabb(obj_id)
        c = (lo + hi) / 2
        for oid, info in self.bodies.items():
            if not info.obj.openable or oid == obj_id or info.obj.pickupable:
                continue
            blo, bhi = pb.getAABB(info.uid, -1, physicsClientId=self.client)
            if np.all(c > np.array(blo)) and np.all(c < np.array(bhi)):
                return oid
        return None

    def refresh_parents(self, ids: list[str] | None = None) -> None:
        """Recompute parent/parent_type and pose of small objects from the physics state."""
        ids = ids if ids is not None else self.dynamic_ids()
        pb.performCollisionDetection(physicsClientId=self.client)
        # Supports first (furniture never changes), then stacked objects see fresh parents.
        ordered = sorted(ids, key=lambda i: self.pose(i)[0][2])
        for oid in ordered:
            obj = self.bodies[oid].obj
            if obj.parent == "agent":
                continue
            pos, orn = self.pose(oid)
            obj.position, obj.orientation = pos, orn
            parent = self.container_of(oid) or self.support_of(oid)
            obj.parent = parent
            obj.parent_type = self.bodies[parent].obj.type if parent in self.bodies else "Floor"

    def export(self) -> Scene:
        """The scene at the current physics state (poses rounded to 1 um / 1e-7)."""
        assert self.scene is not None
        for oid in self.dynamic_ids():
            obj = self.bodies[oid].obj
            if obj.parent != "agent":
                pos, orn = self.pose(oid)
                obj.position = [round(v, 6) for v in pos]
                obj.orientation = [round(v, 7) for v in orn]
        return self.scene

    # ------------------------------------------------------------------ sensing
    def render(
        self,
        eye: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        resolution: int,
        segmentation: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """RGB (uint8), metric z-depth (float32) and, if asked, the body-uid mask."""
        self._use_gl()
        view = pb.computeViewMatrix(
            eye.tolist(), (eye + forward).tolist(), up.tolist(), physicsClientId=self.client
        )
        proj = pb.computeProjectionMatrixFOV(FOV_DEG, 1.0, NEAR, FAR, physicsClientId=self.client)
        flags = 0 if segmentation else pb.ER_NO_SEGMENTATION_MASK
        renderer = pb.ER_BULLET_HARDWARE_OPENGL if self.renderer == "egl" else pb.ER_TINY_RENDERER
        _, _, rgba, zbuf, seg = pb.getCameraImage(
            resolution,
            resolution,
            view,
            proj,
            renderer=renderer,
            flags=flags,
            shadow=0,
            lightDirection=[0.4, -0.3, 1.0],
            lightAmbientCoeff=0.55,
            lightDiffuseCoeff=0.5,
            lightSpecularCoeff=0.05,
            physicsClientId=self.client,
        )
        rgba = np.asarray(rgba, dtype=np.uint8).reshape(resolution, resolution, 4)
        zbuf = np.asarray(zbuf, dtype=np.float32).reshape(resolution, resolution)
        depth = (FAR * NEAR / (FAR - (FAR - NEAR) * zbuf)).astype(np.float32)
        mask = np.asarray(seg, dtype=np.int32).reshape(resolution, resolution) if segmentation else None
        return np.ascontiguousarray(rgba[:, :, :3]), depth, mask

    @property
    def pixel_offset(self) -> tuple[float, float]:
        """(du, dv) pixels from a pixel's centre to where the ray that the render shows there
        passes. Pixel (u, v) spans [u, u + 1) x [v, v + 1) of the image; pybullet's tiny
        renderer draws there what the ray through image point (u, v + 1) meets, half a pixel
        left of and below the centre (u + 1/2, v + 1/2); the EGL renderer draws the centre.
        Measured on a knife on the floor seen from 1 m at eight headings
        (``tests/server/test_actions.py``): rays through the centres hit the knife on 79 % of its
        tiny-renderer pixels, through these points on 100 %."""
        return (-0.5, 0.5) if self.renderer == "tiny" else (0.0, 0.0)

    def ray(self, start: np.ndarray, end: np.ndarray) -> tuple[str | None, int, np.ndarray, np.ndarray]:
        """First hit along a segment: (object id or None, link, point, normal)."""
        hit = pb.rayTest(start.tolist(), end.tolist(), physicsClientId=self.client)[0]
        uid, link, pos, normal = hit[0], hit[1], hit[3], hit[4]
        if uid < 0:
            return None, -1, np.asarray(end, float), np.zeros(3)
        return self.uid_to_id.get(uid), link, np.array(pos), np.array(normal)

    def collides(self, obj_id: str, margin: float = 0.0, ignore: set[str] = frozenset()) -> list[str]:  # type: ignore[assignment]
        """Ids of bodies within ``margin`` of the object (penetration when margin is 0)."""
        info = self.bodies[obj_id]
        lo, hi = self.aabb(obj_id)
        near = (
            pb.getOverlappingObjects(
                (lo - margin - 0.01).tolist(), (hi + margin + 0.01).tolist(), physicsClientId=self.client
            )
            or []
        )
        hits = []
        for uid, _link in near:
            oid = self.uid_to_id.get(uid)
            if oid is None or oid == obj_id or oid in ignore or oid in hits:
                continue
            if pb.getClosestPoints(info.uid, uid, margin, physicsClientId=self.client):
                hits.append(oid)
        return hits

    # ------------------------------------------------------------------ placing
    def place(
        self,
        obj_id: str,
        receptacle_id: str,
        near: np.ndarray,
        yaw: float,
        max_settles: int = 3,
        nudge: bool = False,
    ) -> bool:
        """Put a held (frozen, hidden) object stably on a surface of the receptacle.

        Candidate spots on the receptacle's surfaces (inside ones only when it is open)
        are tried nearest to ``near`` first (``near`` itself before all, when on a surface;
        then the nearest ``PLACE_CANDIDATES``, on a 6 cm
        lattice: a spot up to ~0.4 m from the aimed one, as a person would shift a pillow
        along a crowded bed; with ``nudge``, the spots ``NUDGES_M`` round the aimed one come
        between the two): the object must fit in the surface, touch
        nothing and have headroom; then physics runs and the object must come to rest
        on the receptacle. On failure the object is hidden again and False returned.
        Without ``nudge`` the object stays at a spot that touched a neighbour while the next
        spot's rays are cast, so a spot within its footprint meets the object itself and is
        skipped (the shuffle's and pixel puts' placements are made so; a put at a point
        clears the object away before each spot).
        """
        info, target = self.bodies[obj_id], self.bodies[receptacle_id]
        size = np.array(info.obj.size)
        radius = 0.5 * float(np.hypot(size[0], size[1]))
        include_inside = target.obj.is_open or not target.obj.openable
        hidden_pos, hidden_orn = self.pose(obj_id)
        quat = [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]
        candidates: list[tuple[float, np.ndarray]] = []
        for cxy, half, z, syaw, _inside in self.surfaces_world(receptacle_id, include_inside=include_inside):
            mx, my = half[0] - 0.6 * radius, half[1] - 0.6 * radius
            if mx < 0 or my < 0:
                continue
            c, s = math.cos(syaw), math.sin(syaw)
            # The aimed spot itself first, when the object fits there (a put that aims well
            # lands where it aimed, not on the nearest lattice point, up to 4 cm away).
            lx, ly = surface_local(cxy, syaw, near)
            if abs(lx) <= mx and abs(ly) <= my and abs(float(near[2]) - z) < 0.1:
                candidates.append((-1.0, np.array([float(near[0]), float(near[1]), z])))
                for r in NUDGES_M if nudge else ():
                    for a in np.arange(8) * math.pi / 4:
                        nx, ny = lx + r * math.cos(a), ly + r * math.sin(a)
                        if abs(nx) <= mx and abs(ny) <= my:
                            p = np.array([cxy[0] + c * nx - s * ny, cxy[1] + s * nx + c * ny, z])
                            candidates.append((r - 1.0, p))
            for lx in np.linspace(-mx, mx, max(2, int(2 * mx / 0.06) + 1)):
                for ly in np.linspace(-my, my, max(2, int(2 * my / 0.06) + 1)):
                    p = np.array([cxy[0] + c * lx - s * ly, cxy[1] + s * lx + c * ly, z])
                    candidates.append((float(np.linalg.norm(p - near)), p))
        candidates.sort(key=lambda t: t[0])
        settles = 0
        for _, p in candidates[:PLACE_CANDIDATES]:
            if nudge:  # the spot tried before would stand in this one's rays
                self.set_pose(obj_id, hidden_pos, hidden_orn)
            hit_id, _, hit, _ = self.ray(p + [0, 0, 0.03], p - [0, 0, 0.08])
            if hit_id != receptacle_id:
                continue
            up_id, _, up, _ = self.ray(hit + [0, 0, 0.005], hit + [0, 0, 3.0])
            if up_id is not None and up[2] - hit[2] < size[2] + 0.02:
                continue
            self.set_pose(obj_id, [float(hit[0]), float(hit[1]), float(hit[2]) + 0.004], quat)
            pb.performCollisionDetection(physicsClientId=self.client)
            if self.collides(obj_id):
                continue
            self.set_static(obj_id, False)
            self.settle(max_seconds=1.5, min_seconds=0.3, ids=[obj_id])
            pb.performCollisionDetection(physicsClientId=self.client)
            info.obj.parent = None
            support = self.container_of(obj_id) or self.support_of(obj_id)
            pos, _ = self.pose(obj_id)
            if support == receptacle_id and np.linalg.norm(np.array(pos[:2]) - hit[:2]) < 0.15:
                info.obj.parent, info.obj.parent_type = receptacle_id, target.obj.type
                info.obj.position, info.obj.orientation = self.pose(obj_id)
                return True
            self.set_static(obj_id, True)
            self.set_pose(obj_id, hidden_pos, hidden_orn)
            info.obj.parent, info.obj.parent_type = "agent", "agent"
            settles += 1
            if settles >= max_settles:
                break
        self.set_pose(obj_id, hidden_pos, hidden_orn)
        info.obj.parent, info.obj.parent_type = "agent", "agent"
        return False
