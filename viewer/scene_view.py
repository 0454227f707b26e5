"""The 3D scene: one viser node per layer, created once and updated in place.

Layers: the 3D map (the semantic voxel map coloured by class or by height, or the
camera-coloured point cloud fused from the agent's RGB-D frames), the object memory
(wireframe boxes and labels: out of place in orange, held in blue; in a rearrangement's
unshuffle, a line from each object believed moved to its walkthrough place), a
rearrangement's walkthrough memory (violet boxes: the goal room as the agent remembers it),
the agent (camera frustum, trajectory, planned path and goal), the search heatmap on the
floor with its ranked points, and the server's ground truth (oracle, off by default).

Nodes are never re-created per message: each update assigns to a node handle's props,
inside ``server.atomic()`` (the caller groups a whole batch). Labels come from a pool
that grows to the most objects seen at once (capped) and hides what it does not use. By
default only the objects that matter now are labelled (out of place, the current target,
the held object); labels are laid out for the viewer's camera so none covers another.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
import viser

from tidee.protocol.messages import (
    AgentFrame,
    AgentStatus,
    MapSnapshot,
    ObjectMemoryMsg,
    SearchHeatmap,
    WalkthroughMemoryMsg,
)
from tidee.viewer import geometry, images, palette
from tidee.viewer.colour_cloud import ColourCloud

LAYERS = ("voxels", "objects", "walkthrough", "agent", "search", "oracle")
COLOUR_MODES = ("semantic", "rgb", "height")  # how the 3D map is coloured (the "voxels" layer)
RGB_VOXEL = 0.05  # the camera-coloured cloud's voxel edge (m) and its point cap
RGB_MAX_POINTS = 150_000
RGB_PUSH_PERIOD_S = 1.0  # the coloured cloud goes to the browser at most this often
RGB_FUSE_PERIOD_S = 0.3  # live frames are fused at most this often (~15 ms each at 256 px)
LABEL_FONT_SCALE = 0.9  # viser screen-size labels: a 12 px em at scale 1
LABEL_CHAR_PX, LABEL_LINE_PX = 6.2, 17.0  # a label's box on screen: per character, and its height
LABEL_FALLBACK_FOV = 1.3  # rad, viser's default camera, until a browser reports its own
LABEL_FALLBACK_HEIGHT = 720  # px
MAX_LABELS = 96
MAX_ORACLE_LABELS = 48
FRUSTUM_IMAGE_SIZE = 64
STATUS_CAMERA_HEIGHT = 0.9015  # when only AgentStatus is known: the paper's camera height
STATUS_FOV = 1.5707963267948966  # and its 90 degree field of view
FLOOR_LAYER_TOP = 0.05  # unlabelled voxels below this are the floor: not drawn, so the
# grid, heatmap and paths on the floor stay visible


@dataclass
class OracleObject:
    """One ground-truth object in the start frame, from the server's privileged state."""

    label: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rotation: np.ndarray  # 3x3, object -> start frame
    moved: bool


def oracle_objects(scene: dict[str, Any]) -> list[OracleObject]:
    """Ground truth from a ``StateReply.scene``: every pickupable or moved object, in the start frame."""
    start = scene.get("start")
    if not isinstance(start, dict):
        raise ValueError(
            "the server's state has no 'start' entry: cannot place ground truth in the start frame"
        )
    t = geometry.start_from_world(float(start["x"]), float(start["y"]), float(start["yaw_deg"]))
    moved = {m.get("id") for m in scene.get("mess", [])}
    out = []
    for obj in scene.get("objects", []):
        if not (obj.get("pickupable") or obj.get("id") in moved):
            continue
        size = cast("tuple[float, float, float]", tuple(float(v) for v in obj["size"]))
        rot_world = geometry.quat_xyzw_to_matrix(obj["orientation"])
        bottom = np.append(np.asarray(obj["position"], np.float64), 1.0)  # bottom-centre, world
        center_world = bottom[:3] + rot_world @ np.array([0.0, 0.0, size[2] / 2.0])
        center = t[:3, :3] @ center_world + t[:3, 3]
        out.append(
            OracleObject(
                str(obj.get("type", "?")),
                (float(center[0]), float(center[1]), float(center[2])),
                size,
                t[:3, :3] @ rot_world,
                obj.get("id") in moved,
            )
        )
    return out


class _LabelPool:
    """Label nodes under ``prefix``, reused: ``show`` sets the first N, hides the rest."""

    def __init__(self, scene: viser.SceneApi, prefix: str, cap: int) -> None:
        self.scene, self.prefix, self.cap = scene, prefix, cap
        self.handles: list[viser.LabelHandle] = []
        self.shown = 0
        self.enabled = True

    def show(self, items: list[tuple[str, tuple[float, float, float]]]) -> None:
        items = items[: self.cap]
        while len(self.handles) < len(items):
            self.handles.append(
                self.scene.add_label(
                    f"{self.prefix}/{len(self.handles)}",
                    "",
                    visible=False,
                    anchor="bottom-center",
                    font_screen_scale=LABEL_FONT_SCALE,
                )
            )
        for handle, (text, position) in zip(self.handles, items):
            if handle.text != text:
                handle.text = text
            if not np.allclose(handle.position, position, atol=1e-4):  # a camera drag moves few labels
                handle.position = position
            if handle.visible != self.enabled:
                handle.visible = self.enabled
        for handle in self.handles[len(items) : self.shown]:
            handle.visible = False
        self.shown = len(items)

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        for handle in self.handles[: self.shown]:
            handle.visible = enabled


class SceneView:
    """Owns the viewer's 3D nodes. Not thread-safe: call from one thread (the update worker)."""

    def __init__(self, server: viser.ViserServer, max_points: int = 200_000) -> None:
        self.server = server
        self.max_points = max_points
        scene = server.scene
        scene.set_up_direction("+z")  # the start frame is z-up; say so rather than rely on a default
        self.colour_mode = "semantic"
        self.label_all = False  # label every tracked object, not only those that matter now
        self.label_view: geometry.ScreenView | None = None  # the browser's camera, for laying labels out
        self.layer_on = {layer: layer != "oracle" for layer in LAYERS}
        self._has = {
            name: False
            for name in (
                "voxels",
                "rgb_cloud",
                "boxes",
                "leaders",
                "goal_lines",
                "goal_points",
                "walkthrough",
                "frustum",
                "trajectory",
                "path",
                "goal",
                "heatmap",
                "search_points",
                "oracle",
            )
        }
        self._map: MapSnapshot | None = None
        self._memory: ObjectMemoryMsg | None = None
        self._walkthrough: WalkthroughMemoryMsg | None = None
        self._target_id: int | None = None
        self.colour_cloud = ColourCloud(voxel=RGB_VOXEL, cap=RGB_MAX_POINTS, floor_z=FLOOR_LAYER_TOP)
        self._cloud_step: int | None = None  # the step of the last frame fused
        self._cloud_fused = 0.0  # when the last live frame was fused (monotonic)
        self._cloud_pushed = 0.0  # when the cloud last went to the browser (monotonic)
        self._cloud_dirty = False
        self._has_frame = False  # frames place the frustum; else the status pose does
        self.plane: geometry.FloorPlane | None = None
        self.counts: dict[str, int] = {}  # what the scene holds now (tests and the status line)

        self.grid = scene.add_grid(
            "/floor/grid",
            width=8.0,
            height=8.0,
            plane="xy",
            cell_size=0.25,
            section_size=1.0,
            cell_color=(215, 215, 215),
            section_color=(165, 165, 165),
            position=(0.0, 0.0, -0.002),
        )
        self.start_axes = scene.add_frame("/floor/start", axes_length=0.25, axes_radius=0.012)
        empty_pts, empty_rgb = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        empty_seg = np.zeros((1, 2, 3), np.float32)
        self.voxels = scene.add_point_cloud(
            "/map/voxels",
            empty_pts,
            empty_rgb,
            point_size=0.05,
            point_shape="square",
            point_shading="flat",
            visible=False,
        )
        self.rgb_cloud = scene.add_point_cloud(
            "/map/rgb",
            empty_pts,
            empty_rgb,
            point_size=RGB_VOXEL,
            point_shape="square",
            point_shading="flat",
            visible=False,
        )
        self.boxes = scene.add_line_segments(
            "/objects/boxes", empty_seg, (0, 0, 0), thickness=0.012, visible=False
        )
        self.leaders = scene.add_line_segments(
            "/objects/leaders",
            empty_seg,
            (110, 110, 110),
            thickness=1.5,
            thickness_units="screen",
            visible=False,
        )
        self.labels = _LabelPool(scene, "/objects/labels", MAX_LABELS)
        # a rearrangement's unshuffle: object believed moved -> its walkthrough place
        self.goal_lines = scene.add_line_segments(
            "/objects/goals",
            empty_seg,
            palette.WARNING_RGB,
            thickness=3.0,
            thickness_units="screen",
            visible=False,
        )
        self.goal_points = scene.add_point_cloud(
            "/objects/goal_points", empty_pts, empty_rgb, point_size=0.07, point_shape="circle", visible=False
        )
        self.walkthrough_boxes = scene.add_line_segments(
            "/walkthrough/boxes",
            empty_seg,
            palette.WALKTHROUGH_RGB,
            thickness=2.0,
            thickness_units="screen",
            visible=False,
        )
        self.frustum = scene.add_camera_frustum(
            "/agent/camera",
            fov=STATUS_FOV,
            aspect=1.0,
            scale=0.35,
            thickness=0.02,
            color=palette.FRUSTUM_RGB,
            visible=False,
        )
        self.trajectory = scene.add_line_segments(
            "/agent/trajectory", empty_seg, palette.TRAJECTORY_RGB, thickness=0.025, visible=False
        )
        self.path = scene.add_line_segments(
            "/agent/path", empty_seg, palette.PATH_RGB, thickness=0.035, visible=False
        )
        self.goal = scene.add_icosphere("/agent/goal", radius=0.06, color=palette.PATH_RGB, visible=False)
        self.heatmap = scene.add_image(
            "/search/heatmap",
            np.zeros((2, 2, 4), np.uint8),
            1.0,
            1.0,
            cast_shadow=False,
            receive_shadow=False,
            visible=False,
        )
        self.search_points = scene.add_point_cloud(
            "/search/points", empty_pts, empty_rgb, point_size=0.09, point_shape="circle", visible=False
        )
        self.search_labels = _LabelPool(scene, "/search/labels", 5)
        self.oracle_boxes = scene.add_line_segments(
            "/oracle/boxes", empty_seg, (0, 0, 0), thickness=0.01, visible=False
        )
        self.oracle_labels = _LabelPool(scene, "/oracle/labels", MAX_ORACLE_LABELS)
        self.oracle_labels.set_enabled(False)

    # --- visibility ---------------------------------------------------------------------
    def _nodes(self) -> dict[str, tuple[str, Any]]:
        """node name -> (layer, handle) for the nodes whose visibility is data AND layer."""
        return {
            "voxels": ("voxels", self.voxels),
            "rgb_cloud": ("voxels", self.rgb_cloud),
            "boxes": ("objects", self.boxes),
            "leaders": ("objects", self.leaders),
            "goal_lines": ("objects", self.goal_lines),
            "goal_points": ("objects", self.goal_points),
            "walkthrough": ("walkthrough", self.walkthrough_boxes),
            "frustum": ("agent", self.frustum),
            "trajectory": ("agent", self.trajectory),
            "path": ("agent", self.path),
            "goal": ("agent", self.goal),
            "heatmap": ("search", self.heatmap),
            "search_points": ("search", self.search_points),
            "oracle": ("oracle", self.oracle_boxes),
        }

    def _refresh(self, name: str) -> None:
        layer, handle = self._nodes()[name]
        visible = self._has[name] and self.layer_on[layer]
        if name in ("voxels", "rgb_cloud"):  # one 3D map at a time: the colour mode picks which
            visible = visible and (name == "rgb_cloud") == (self.colour_mode == "rgb")
        if handle.visible != visible:
            handle.visible = visible

    def _set_has(self, name: str, has: bool) -> None:
        self._has[name] = has
        self._refresh(name)

    def set_layer(self, layer: str, on: bool) -> None:
        if layer not in LAYERS:
            raise ValueError(f"layer must be one of {LAYERS}, got {layer!r}")
        self.layer_on[layer] = on
        for name, (node_layer, _) in self._nodes().items():
            if node_layer == layer:
                self._refresh(name)
        pool = {"objects": self.labels, "search": self.search_labels, "oracle": self.oracle_labels}.get(layer)
        if pool is not None:
            pool.set_enabled(on)

    def set_colour_mode(self, mode: str) -> None:
        """Colour the 3D map by ``semantic`` class, by camera ``rgb`` (the fused frames) or by ``height``."""
        if mode not in COLOUR_MODES:
            raise ValueError(f"colour mode must be one of {COLOUR_MODES}, got {mode!r}")
        self.colour_mode = mode
        if self._map is not None and mode != "rgb":
            self.voxels.colors = self._voxel_colors(self._map)
        if mode == "rgb":
            self.push_cloud(force=True)
        self._refresh("voxels")
        self._refresh("rgb_cloud")

    def set_label_all(self, on: bool) -> None:
        self.label_all = on
        self._layout_labels()

    def set_label_view(self, view: geometry.ScreenView | None) -> None:
        """Lay labels out for this camera (a browser's; None: the overview camera)."""
        self.label_view = view
        self._layout_labels()

    def clear(self) -> None:
        """Hide every layer's data (another session was chosen)."""
        for name in self._has:
            self._set_has(name, False)
        for pool in (self.labels, self.search_labels, self.oracle_labels):
            pool.show([])
        self._map, self.counts, self._has_frame = None, {}, False
        self._memory, self._target_id, self._walkthrough = None, None, None
        self.colour_cloud.clear()
        self._cloud_step, self._cloud_dirty = None, False

    # --- updates (one per telemetry kind) ---------------------------------------------------
    def apply(self, kind: str, msg: Any) -> None:
        handler = {
            "maps": self.apply_maps,
            "memory": self.apply_memory,
            "walkthrough": self.apply_walkthrough,
            "status": self.apply_status,
            "frame": self.apply_frame,
            "search": self.apply_search,
        }.get(kind)
        if handler is not None:
            handler(msg)

    def _voxel_colors(self, msg: MapSnapshot) -> np.ndarray:
        points, labels = self._subsample(msg)
        if self.colour_mode == "height":
            return palette.height_colors(points[:, 2])
        return palette.class_colors(labels)

    def _subsample(self, msg: MapSnapshot) -> tuple[np.ndarray, np.ndarray]:
        points, labels = np.asarray(msg.points), np.asarray(msg.point_labels)
        if len(labels) != len(points):  # the codec checks each array, not that they agree
            labels = np.full(len(points), -1, np.int16)
        if len(points):
            above = (points[:, 2] >= FLOOR_LAYER_TOP) | (labels >= 0)
            points, labels = points[above], labels[above]
        if len(points) > self.max_points:  # a deterministic stride keeps the whole map's shape
            idx = np.linspace(0, len(points) - 1, self.max_points).astype(np.int64)
            points, labels = points[idx], labels[idx]
        return points, labels

    def apply_maps(self, msg: MapSnapshot) -> geometry.FloorPlane | None:
        self._map = msg
        points, _ = self._subsample(msg)
        if len(points):
            self.voxels.points = np.ascontiguousarray(points, np.float32)
            self.voxels.colors = self._voxel_colors(msg)
            if self.voxels.point_size != msg.voxel_size:
                self.voxels.point_size = float(msg.voxel_size)
        self._set_has("voxels", len(points) > 0)
        self.counts["voxels"] = int(len(points))
        if msg.occupancy.size == 0 or msg.cell <= 0:
            return self.plane
        plane = geometry.grid_plane(msg.origin, msg.cell, msg.occupancy.shape, z=-0.002)
        if plane != self.plane:
            self.grid.width, self.grid.height = plane.size_x, plane.size_y
            self.grid.position = plane.center
            self.plane = plane
        return plane

    def apply_memory(self, msg: ObjectMemoryMsg) -> None:
        objs = msg.objects
        if objs:
            mins = np.array([o.box_min for o in objs], np.float32)
            maxs = np.array([o.box_max for o in objs], np.float32)
            segments = geometry.boxes_segments(mins, maxs)
            colors = np.repeat(
                np.array([palette.object_color(o.held, o.out_of_place) for o in objs], np.uint8), 24, axis=0
            ).reshape(-1, 2, 3)
            self.boxes.points, self.boxes.colors = segments, colors
        self._set_has("boxes", bool(objs))
        goals = [o for o in objs if o.goal_centroid is not None and not o.held]
        if goals:
            ends = np.array([(o.centroid, o.goal_centroid) for o in goals], np.float32)
            self.goal_lines.points = ends
            self.goal_points.points = np.ascontiguousarray(ends[:, 1])
            self.goal_points.colors = np.tile(np.array(palette.WARNING_RGB, np.uint8), (len(goals), 1))
        self._set_has("goal_lines", bool(goals))
        self._set_has("goal_points", bool(goals))
        self._memory = msg
        self._layout_labels()
        self.counts["objects"] = len(objs)
        self.counts["goals"] = len(goals)

    def apply_walkthrough(self, msg: WalkthroughMemoryMsg) -> None:
        """A rearrangement's walkthrough memory: the goal room's objects as violet boxes."""
        objs = msg.objects
        if objs:
            mins = np.array([o.box_min for o in objs], np.float32)
            maxs = np.array([o.box_max for o in objs], np.float32)
            self.walkthrough_boxes.points = geometry.boxes_segments(mins, maxs)
        self._set_has("walkthrough", bool(objs))
        self._walkthrough = msg
        self.counts["walkthrough"] = len(objs)

    def _layout_labels(self) -> None:
        """Label the objects that matter now (or all of them), placed so that none covers
        another in ``label_view``; a leader line joins a lifted label to its object."""
        objs = self._memory.objects if self._memory is not None else []
        chosen = labelled_objects(objs, self._target_id, self.label_all)[:MAX_LABELS]
        texts = [_object_text(o, o.id == self._target_id) for o in chosen]
        anchors = np.array(
            [
                ((o.box_min[0] + o.box_max[0]) / 2, (o.box_min[1] + o.box_max[1]) / 2, o.box_max[2] + 0.03)
                for o in chosen
            ],
            np.float64,
        ).reshape(-1, 3)
        view = self.label_view or self._fallback_view()
        if view is not None and len(anchors):
            sizes = np.array([(len(t) * LABEL_CHAR_PX + 10, LABEL_LINE_PX) for t in texts])
            placed = geometry.place_labels(anchors, sizes, view)
        else:
            placed = anchors
        self.labels.show([(t, (float(p[0]), float(p[1]), float(p[2]))) for t, p in zip(texts, placed)])
        lifted = np.linalg.norm(placed - anchors, axis=1) > 0.02
        if lifted.any():
            self.leaders.points = np.stack([anchors[lifted], placed[lifted]], axis=1).astype(np.float32)
        self._set_has("leaders", bool(lifted.any()))
        self.counts["labels"] = len(chosen)

    def _fallback_view(self) -> geometry.ScreenView | None:
        if self.plane is None:
            return None
        return geometry.screen_view_looking_at(
            geometry.overview_camera(self.plane), LABEL_FALLBACK_FOV, LABEL_FALLBACK_HEIGHT
        )

    def apply_status(self, msg: AgentStatus) -> None:
        traj = geometry.polyline_segments(msg.trajectory, z=0.02)
        if len(traj):
            self.trajectory.points = traj
        self._set_has("trajectory", len(traj) > 0)
        path = geometry.polyline_segments(msg.path, z=0.04)
        if len(path):
            self.path.points = path
        self._set_has("path", len(path) > 0)
        if msg.goal is not None:
            self.goal.position = (float(msg.goal[0]), float(msg.goal[1]), 0.06)
        self._set_has("goal", msg.goal is not None)
        if msg.target_id != self._target_id:
            self._target_id = msg.target_id
            self._layout_labels()
        if not self._has_frame:
            x, y, yaw, pitch = (float(v) for v in msg.pose)
            pose = geometry.camera_pose_from_agent(x, y, yaw, pitch, STATUS_CAMERA_HEIGHT)
            self.frustum.wxyz = geometry.rotation_to_wxyz(pose[:3, :3])
            self.frustum.position = cast("tuple[float, float, float]", tuple(float(v) for v in pose[:3, 3]))
            self._set_has("frustum", True)
        self.counts["trajectory"] = int(len(traj))

    def apply_frame(self, msg: AgentFrame | Any) -> None:
        """An ``AgentFrame`` (or an ``Observation``: same camera fields)."""
        h, w = msg.rgb.shape[:2]
        f = geometry.frustum(msg.camera_pose, msg.intrinsics, w, h)
        if abs(self.frustum.fov - f.fov) > 1e-6 or abs(self.frustum.aspect - f.aspect) > 1e-6:
            self.frustum.fov, self.frustum.aspect = f.fov, f.aspect
        self.frustum.wxyz, self.frustum.position = f.wxyz, f.position
        small = cv2.resize(
            np.asarray(msg.rgb),
            (FRUSTUM_IMAGE_SIZE, max(1, FRUSTUM_IMAGE_SIZE * h // w)),
            interpolation=cv2.INTER_AREA,
        )
        self.frustum.image = small
        self._has_frame = True
        self._set_has("frustum", True)
        now = time.monotonic()
        # each frame once (a replay redraws the same one), a few a second (the agent moves slowly)
        if msg.step != self._cloud_step and now - self._cloud_fused >= RGB_FUSE_PERIOD_S:
            self._cloud_fused = now
            self.fuse_frame(msg)
            self.push_cloud()

    def fuse_frame(self, msg: AgentFrame | Any) -> None:
        """Add a frame to the camera-coloured cloud (``apply_frame`` does; a replay catching up
        on the frames it skipped calls it directly)."""
        self.colour_cloud.add(msg.rgb, msg.depth, msg.camera_pose, msg.intrinsics)
        self._cloud_step, self._cloud_dirty = msg.step, True

    def push_cloud(self, force: bool = False) -> None:
        """Send the coloured cloud to the browser if it changed and is shown, at most every
        ``RGB_PUSH_PERIOD_S`` unless ``force`` (it is large; the semantic map is what updates live)."""
        now = time.monotonic()
        if (
            self.colour_mode != "rgb"
            or not self._cloud_dirty
            or (not force and now - self._cloud_pushed < RGB_PUSH_PERIOD_S)
        ):
            return
        if len(self.colour_cloud):
            self.rgb_cloud.points = self.colour_cloud.points()
            self.rgb_cloud.colors = self.colour_cloud.colors()
        self.counts["rgb_points"] = len(self.colour_cloud)
        self._set_has("rgb_cloud", len(self.colour_cloud) > 0)
        self._cloud_pushed, self._cloud_dirty = now, False

    def apply_search(self, msg: SearchHeatmap) -> None:
        heat = np.asarray(msg.heatmap)
        if heat.size == 0 or msg.cell <= 0:
            self._set_has("heatmap", False)
            return
        plane = geometry.grid_plane(msg.origin, msg.cell, heat.shape, z=0.012)
        self.heatmap.image = images.heatmap_rgba(heat)
        self.heatmap.render_width, self.heatmap.render_height = plane.size_x, plane.size_y
        self.heatmap.position = plane.center
        self._set_has("heatmap", True)
        pts = np.asarray(msg.points, np.float32).reshape(-1, 2)[:5]
        if len(pts):
            xyz = np.concatenate([pts, np.full((len(pts), 1), 0.05, np.float32)], axis=1)
            self.search_points.points = xyz
            self.search_points.colors = np.tile(np.array(palette.SEARCH_POINT_RGB, np.uint8), (len(pts), 1))
        self._set_has("search_points", len(pts) > 0)
        self.search_labels.show(
            [
                (f"{rank}" if rank > 1 else f"1: search {msg.target}", (float(p[0]), float(p[1]), 0.1))
                for rank, p in enumerate(pts[:3], start=1)
            ]
        )

    def apply_oracle(self, objects: list[OracleObject]) -> None:
        if objects:
            segments = np.concatenate(
                [geometry.oriented_box_segments(o.center, o.size, o.rotation) for o in objects]
            )
            colors = np.repeat(
                np.array(
                    [palette.ORACLE_MOVED_RGB if o.moved else palette.ORACLE_RGB for o in objects], np.uint8
                ),
                24,
                axis=0,
            ).reshape(-1, 2, 3)
            self.oracle_boxes.points, self.oracle_boxes.colors = segments, colors
        self._set_has("oracle", bool(objects))
        self.oracle_labels.show(
            [
                (f"oracle: {o.label} (moved)", (o.center[0], o.center[1], o.center[2] + o.size[2] / 2))
                for o in objects
                if o.moved
            ]
        )
        self.counts["oracle"] = len(objects)

    def node_names(self) -> dict[str, bool]:
        """Each data node's name and whether it is shown now (for tests and diagnostics)."""
        return {handle.name: bool(handle.visible) for _, handle in self._nodes().values()}


def labelled_objects(objects: list[Any], target_id: int | None, label_all: bool) -> list[Any]:
    """The tracked objects to label, most important first: held, the current target, out of
    place (most likely first); then, with ``label_all``, the rest (best detected first)."""

    def rank(o: Any) -> tuple[int, float]:
        if o.held:
            return 0, 0.0
        if target_id is not None and o.id == target_id:
            return 1, 0.0
        if o.out_of_place:
            return 2, -(o.oop_prob or 0.0)
        return 3, -float(o.score)

    ranked = sorted(objects, key=rank)
    return ranked if label_all else [o for o in ranked if rank(o)[0] < 3]


def _object_text(o: Any, target: bool = False) -> str:
    if o.held:
        return f"{o.label} (held)"
    if getattr(o, "goal_centroid", None) is not None:
        text = f"{o.label}: moved"
    elif o.out_of_place:
        p = f" {o.oop_prob:.2f}" if o.oop_prob is not None else ""
        text = f"{o.label}: out of place{p}"
    else:
        text = o.label
    return f"{text} (target)" if target else text
