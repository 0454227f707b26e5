"""The 3D scene: one viser node per layer, created once and updated in place.

Layers: the voxel map (coloured by class, or by height with "occupancy only"), the
object memory (wireframe boxes and labels: out of place in orange, held in blue), the
agent (camera frustum, trajectory, planned path and goal), the search heatmap on the
floor with its ranked points, and the server's ground truth (oracle, off by default).

Nodes are never re-created per message: each update assigns to a node handle's props,
inside ``server.atomic()`` (the caller groups a whole batch). Labels come from a pool
that grows to the most objects seen at once (capped) and hides what it does not use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import viser
from tidee.protocol.messages import AgentFrame, AgentStatus, MapSnapshot, ObjectMemoryMsg, SearchHeatmap
from tidee.viewer import geometry, images, palette

LAYERS = ("voxels", "objects", "agent", "search", "oracle")
MAX_LABELS = 96
MAX_ORACLE_LABELS = 48
FRUSTUM_IMAGE_SIZE = 64
STATUS_CAMERA_HEIGHT = 0.9015        # when only AgentStatus is known: the paper's camera height
STATUS_FOV = 1.5707963267948966      # and its 90 degree field of view
FLOOR_LAYER_TOP = 0.05               # unlabelled voxels below this are the floor: not drawn, so the
                                     # grid, heatmap and paths on the floor stay visible


@dataclass
class OracleObject:
    """One ground-truth object in the start frame, from the server's privileged state."""

    label: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rotation: np.ndarray                 # 3x3, object -> start frame
    moved: bool


def oracle_objects(scene: dict[str, Any]) -> list[OracleObject]:
    """Ground truth from a ``StateReply.scene``: every pickupable or moved object, in the start frame."""
    start = scene.get("start")
    if not isinstance(start, dict):
        raise ValueError("the server's state has no 'start' entry: cannot place ground truth in the start frame")
    t = geometry.start_from_world(float(start["x"]), float(start["y"]), float(start["yaw_deg"]))
    moved = {m.get("id") for m in scene.get("mess", [])}
    out = []
    for obj in scene.get("objects", []):
        if not (obj.get("pickupable") or obj.get("id") in moved):
            continue
        size = tuple(float(v) for v in obj["size"])
        rot_world = geometry.quat_xyzw_to_matrix(obj["orientation"])
        bottom = np.append(np.asarray(obj["position"], np.float64), 1.0)   # bottom-centre, world
        center_world = bottom[:3] + rot_world @ np.array([0.0, 0.0, size[2] / 2.0])
        center = t[:3, :3] @ center_world + t[:3, 3]
        out.append(OracleObject(str(obj.get("type", "?")), (float(center[0]), float(center[1]), float(center[2])),
                                size, t[:3, :3] @ rot_world, obj.get("id") in moved))  # type: ignore[arg-type]
    return out


class _LabelPool:
    """Label nodes under ``prefix``, reused: ``show`` sets the first N, hides the rest."""

    def __init__(self, scene: viser.SceneApi, prefix: str, cap: int) -> None:
        self.scene, self.prefix, self.cap = scene, prefix, cap
        self.handles: list[viser.LabelHandle] = []
        self.shown = 0
        self.enabled = True

    def show(self, items: list[tuple[str, tuple[float, float, float]]]) -> None:
        items = items[:self.cap]
        while len(self.handles) < len(items):
            self.handles.append(self.scene.add_label(f"{self.prefix}/{len(self.handles)}", "", visible=False,
                                                     anchor="bottom-center", font_screen_scale=0.8))
        for handle, (text, position) in zip(self.handles, items):
            if handle.text != text:
                handle.text = text
            handle.position = position
            handle.visible = self.enabled
        for handle in self.handles[len(items):self.shown]:
            handle.visible = False
        self.shown = len(items)

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        for handle in self.handles[:self.shown]:
            handle.visible = enabled


class SceneView:
    """Owns the viewer's 3D nodes. Not thread-safe: call from one thread (the update worker)."""

    def __init__(self, server: viser.ViserServer, max_points: int = 200_000) -> None:
        self.server = server
        self.max_points = max_points
        scene = server.scene
        scene.set_up_direction("+z")  # the start frame is z-up; say so rather than rely on a default
        self.occupancy_only = False
        self.layer_on = {layer: layer != "oracle" for layer in LAYERS}
        self._has = {name: False for name in ("voxels", "boxes", "frustum", "trajectory", "path", "goal",
                                              "heatmap", "search_points", "oracle")}
        self._map: MapSnapshot | None = None
        self._has_frame = False                   # frames place the frustum; else the status pose does
        self.plane: geometry.FloorPlane | None = None
        self.counts: dict[str, int] = {}          # what the scene holds now (tests and the status line)

        self.grid = scene.add_grid("/floor/grid", width=8.0, height=8.0, plane="xy", cell_size=0.25,
                                   section_size=1.0, cell_color=(215, 215, 215), section_color=(165, 165, 165),
                                   position=(0.0, 0.0, -0.002))
        self.start_axes = scene.add_frame("/floor/start", axes_length=0.25, axes_radius=0.012)
        empty_pts, empty_rgb = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
        empty_seg = np.zeros((1, 2, 3), np.float32)
        self.voxels = scene.add_point_cloud("/map/voxels", empty_pts, empty_rgb, point_size=0.05,
                                            point_shape="square", point_shading="flat", visible=False)
        self.boxes = scene.add_line_segments("/objects/boxes", empty_seg, (0, 0, 0), thickness=0.012,
                                             visible=False)
        self.labels = _LabelPool(scene, "/objects/labels", MAX_LABELS)
        self.frustum = scene.add_camera_frustum("/agent/camera", fov=STATUS_FOV, aspect=1.0, scale=0.35,
                                                thickness=0.02, color=palette.FRUSTUM_RGB, visible=False)
        self.trajectory = scene.add_line_segments("/agent/trajectory", empty_seg, palette.TRAJECTORY_RGB,
                                                  thickness=0.025, visible=False)
        self.path = scene.add_line_segments("/agent/path", empty_seg, palette.PATH_RGB, thickness=0.035,
                                            visible=False)
        self.goal = scene.add_icosphere("/agent/goal", radius=0.06, color=palette.PATH_RGB, visible=False)
        self.heatmap = scene.add_image("/search/heatmap", np.zeros((2, 2, 4), np.uint8), 1.0, 1.0,
                                       cast_shadow=False, receive_shadow=False, visible=False)
        self.search_points = scene.add_point_cloud("/search/points", empty_pts, empty_rgb, point_size=0.09,
                                                   point_shape="circle", visible=False)
        self.search_labels = _LabelPool(scene, "/search/labels", 5)
        self.oracle_boxes = scene.add_line_segments("/oracle/boxes", empty_seg, (0, 0, 0), thickness=0.01,
                                                    visible=False)
        self.oracle_labels = _LabelPool(scene, "/oracle/labels", MAX_ORACLE_LABELS)
        self.oracle_labels.set_enabled(False)

    # --- visibility ---------------------------------------------------------------------
    def _nodes(self) -> dict[str, tuple[str, Any]]:
        """node name -> (layer, handle) for the nodes whose visibility is data AND layer."""
        return {"voxels": ("voxels", self.voxels), "boxes": ("objects", self.boxes),
                "frustum": ("agent", self.frustum), "trajectory": ("agent", self.trajectory),
                "path": ("agent", self.path), "goal": ("agent", self.goal), "heatmap": ("search", self.heatmap),
                "search_points": ("search", self.search_points), "oracle": ("oracle", self.oracle_boxes)}

    def _refresh(self, name: str) -> None:
        layer, handle = self._nodes()[name]
        visible = self._has[name] and self.layer_on[layer]
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

    def set_occupancy_only(self, on: bool) -> None:
        self.occupancy_only = on
        if self._map is not None:
            self.voxels.colors = self._voxel_colors(self._map)

    def clear(self) -> None:
        """Hide every layer's data (another session was chosen)."""
        for name in self._has:
            self._set_has(name, False)
        for pool in (self.labels, self.search_labels, self.oracle_labels):
            pool.show([])
        self._map, self.counts, self._has_frame = None, {}, False

    # --- updates (one per telemetry kind) ---------------------------------------------------
    def apply(self, kind: str, msg: Any) -> None:
        handler = {"maps": self.apply_maps, "memory": self.apply_memory, "status": self.apply_status,
                   "frame": self.apply_frame, "search": self.apply_search}.get(kind)
        if handler is not None:
            handler(msg)

    def _voxel_colors(self, msg: MapSnapshot) -> np.ndarray:
        points, labels = self._subsample(msg)
        if self.occupancy_only:
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
            colors = np.repeat(np.array([palette.object_color(o.held, o.out_of_place) for o in objs], np.uint8),
                               24, axis=0).reshape(-1, 2, 3)
            self.boxes.points, self.boxes.colors = segments, colors
        self._set_has("boxes", bool(objs))
        self.labels.show([(_object_text(o), (float((o.box_min[0] + o.box_max[0]) / 2),
                                             float((o.box_min[1] + o.box_max[1]) / 2), float(o.box_max[2]) + 0.03))
                          for o in objs])
        self.counts["objects"] = len(objs)

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
        if not self._has_frame:
            x, y, yaw, pitch = (float(v) for v in msg.pose)
            pose = geometry.camera_pose_from_agent(x, y, yaw, pitch, STATUS_CAMERA_HEIGHT)
            self.frustum.wxyz = geometry.rotation_to_wxyz(pose[:3, :3])
            self.frustum.position = tuple(float(v) for v in pose[:3, 3])
            self._set_has("frustum", True)
        self.counts["trajectory"] = int(len(traj))

    def apply_frame(self, msg: AgentFrame | Any) -> None:
        """An ``AgentFrame`` (or an ``Observation``: same camera fields)."""
        h, w = msg.rgb.shape[:2]
        f = geometry.frustum(msg.camera_pose, msg.intrinsics, w, h)
        if abs(self.frustum.fov - f.fov) > 1e-6 or abs(self.frustum.aspect - f.aspect) > 1e-6:
            self.frustum.fov, self.frustum.aspect = f.fov, f.aspect
        self.frustum.wxyz, self.frustum.position = f.wxyz, f.position
        small = cv2.resize(np.asarray(msg.rgb), (FRUSTUM_IMAGE_SIZE, max(1, FRUSTUM_IMAGE_SIZE * h // w)),
                           interpolation=cv2.INTER_AREA)
        self.frustum.image = small
        self._has_frame = True
        self._set_has("frustum", True)

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
        self.search_labels.show([(f"{rank}" if rank > 1 else f"1: search {msg.target}",
                                  (float(p[0]), float(p[1]), 0.1)) for rank, p in enumerate(pts[:3], start=1)])

    def apply_oracle(self, objects: list[OracleObject]) -> None:
        if objects:
            segments = np.concatenate([geometry.oriented_box_segments(o.center, o.size, o.rotation) for o in objects])
            colors = np.repeat(np.array([palette.ORACLE_MOVED_RGB if o.moved else palette.ORACLE_RGB
                                         for o in objects], np.uint8), 24, axis=0).reshape(-1, 2, 3)
            self.oracle_boxes.points, self.oracle_boxes.colors = segments, colors
        self._set_has("oracle", bool(objects))
        self.oracle_labels.show([(f"oracle: {o.label} (moved)", (o.center[0], o.center[1], o.center[2] + o.size[2] / 2))
                                 for o in objects if o.moved])
        self.counts["oracle"] = len(objects)

    def node_names(self) -> dict[str, bool]:
        """Each data node's name and whether it is shown now (for tests and diagnostics)."""
        return {handle.name: bool(handle.visible) for _, handle in self._nodes().values()}


def _object_text(o: Any) -> str:
    if o.held:
        return f"{o.label} (held)"
    if o.out_of_place:
        p = f" {o.oop_prob:.2f}" if o.oop_prob is not None else ""
        return f"{o.label}: out of place{p}"
    return o.label
