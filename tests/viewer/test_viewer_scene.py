"""Telemetry -> scene conversion (colours, boxes, frusta, heatmap and map images), the
scene's node handles, replay indexing, the live feed over Zenoh, and the no-torch rule."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.support import REPO as SUPPORT_REPO
from tests.support.net import wait_until
from tests.support.viewer_fakes import synthetic_source
from tidee.protocol.messages import AgentCommand, Detection2D, EpisodeSummary, TrackedObjectMsg
from tidee.viewer import geometry, images, palette
from tidee.viewer.synthetic import CLASSES, SyntheticEpisode, write_synthetic_log

REPO = SUPPORT_REPO


# --- colours ------------------------------------------------------------------------------


def test_class_colors_are_stable_distinct_and_vectorised():
    first = [palette.class_color(i) for i in range(40)]
    assert first == [palette.class_color(i) for i in range(40)]
    assert len(set(first)) == 40
    assert palette.class_color(-1) == palette.UNLABELLED_RGB
    labels = np.array([3, -1, 0, 25, 3], np.int16)
    colors = palette.class_colors(labels)
    assert colors.dtype == np.uint8 and colors.shape == (5, 3)
    assert [tuple(c) for c in colors] == [palette.class_color(int(i)) for i in labels]
    assert palette.class_colors(np.zeros(0, np.int16)).shape == (0, 3)


def test_height_colors_follow_height():
    c = palette.height_colors(np.array([0.0, 1.0, 2.0, 5.0]))
    assert c.shape == (4, 3) and c.dtype == np.uint8
    assert not np.array_equal(c[0], c[2])
    assert np.array_equal(c[2], c[3])  # clipped at z_max


def test_legend_lists_present_classes_most_points_first_and_escapes_names():
    html = palette.legend_html(["Mug", "<b>Desk</b>", "Sofa"], np.array([3, 10, 0]))
    assert html.index("&lt;b&gt;Desk&lt;/b&gt;") < html.index("Mug")
    assert "Sofa" not in html and "<b>Desk" not in html
    r, g, b = palette.class_color(0)
    assert f"rgb({r},{g},{b})" in html
    assert "no labelled voxels" in palette.legend_html([], np.zeros(0))


def test_object_color_priority():
    assert palette.object_color(held=True, out_of_place=True) == palette.HELD_RGB
    assert palette.object_color(held=False, out_of_place=True) == palette.WARNING_RGB
    assert palette.object_color(held=False, out_of_place=False) == palette.TRACKED_RGB


# --- geometry -------------------------------------------------------------------------------


def test_box_corners_and_segments():
    lo, hi = (0.0, 1.0, 2.0), (1.0, 3.0, 2.5)
    corners = geometry.box_corners(lo, hi)
    assert corners.shape == (8, 3) and len({tuple(c) for c in corners}) == 8
    assert np.allclose(corners.min(0), lo) and np.allclose(corners.max(0), hi)
    seg = geometry.boxes_segments(np.array([lo]), np.array([hi]))
    assert seg.shape == (12, 2, 3)
    d = np.abs(seg[:, 1] - seg[:, 0])
    assert np.all((d > 1e-9).sum(axis=1) == 1)  # every edge along one axis
    assert sorted(np.round(d.max(axis=1), 6)) == [0.5] * 4 + [1.0] * 4 + [2.0] * 4
    ends = [tuple(p) for p in seg.reshape(-1, 3)]
    assert all(ends.count(tuple(c)) == 3 for c in corners.astype(np.float32))  # 3 edges per corner
    two = geometry.boxes_segments(np.array([lo, lo]), np.array([hi, (5.0, 5.0, 5.0)]))
    assert two.shape == (24, 2, 3) and np.allclose(two[:12], seg)
    with pytest.raises(ValueError, match="3 numbers"):
        geometry.box_corners((0, 0), (1, 1))


def test_oriented_box_matches_axis_aligned_and_rotates():
    seg = geometry.oriented_box_segments((0.5, 2.0, 2.25), (1.0, 2.0, 0.5), np.eye(3))
    ref = geometry.boxes_segments(np.array([(0.0, 1.0, 2.0)]), np.array([(1.0, 3.0, 2.5)]))
    assert np.allclose(seg, ref)
    rz = geometry.quat_xyzw_to_matrix((0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)))  # 90 deg about z
    turned = geometry.oriented_box_segments((0, 0, 0), (1.0, 2.0, 0.5), rz).reshape(-1, 3)
    assert np.allclose(turned.max(0), (1.0, 0.5, 0.25), atol=1e-6)  # x and y extents swapped


def test_polyline_segments():
    seg = geometry.polyline_segments(np.array([[0, 0], [1, 0], [1, 2]], np.float32), z=0.1)
    assert seg.shape == (2, 2, 3)
    assert np.allclose(seg[1], [[1, 0, 0.1], [1, 2, 0.1]])
    assert geometry.polyline_segments(np.zeros((1, 2))).shape == (0, 2, 3)
    assert geometry.polyline_segments(None).shape == (0, 2, 3)
    with pytest.raises(ValueError, match="Nx2 or Nx3"):
        geometry.polyline_segments(np.zeros((3, 4)))


def test_rotation_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        m = geometry.quat_xyzw_to_matrix(q)
        w, x, y, z = geometry.rotation_to_wxyz(m)
        assert np.allclose(geometry.quat_xyzw_to_matrix((x, y, z, w)), m, atol=1e-9)
        assert w >= 0


def test_camera_pose_from_agent_axes():
    pose = geometry.camera_pose_from_agent(1.0, 2.0, 0.0, 0.0, 0.9)
    assert np.allclose(pose[:3, 2], [1, 0, 0])  # optical z: forward = +x
    assert np.allclose(pose[:3, 0], [0, -1, 0])  # optical x: right = -y
    assert np.allclose(pose[:3, 1], [0, 0, -1])  # optical y: down
    assert np.allclose(pose[:3, 3], [1, 2, 0.9])
    assert np.allclose(np.linalg.det(pose[:3, :3]), 1.0)
    looking_down = geometry.camera_pose_from_agent(0, 0, 90.0, 30.0, 0.9)
    assert np.allclose(looking_down[:3, 2], [0, math.cos(math.radians(30)), -0.5], atol=1e-9)


def test_frustum_from_intrinsics_and_pose():
    k = np.array([[64.0, 0, 64], [0, 64.0, 64], [0, 0, 1]])  # 90 degrees at 128 px
    pose = geometry.camera_pose_from_agent(1.0, 2.0, 90.0, 0.0, 0.9)
    f = geometry.frustum(pose, k, 128, 128)
    assert f.fov == pytest.approx(math.pi / 2) and f.aspect == pytest.approx(1.0)
    assert f.position == pytest.approx((1.0, 2.0, 0.9))
    w, x, y, z = f.wxyz
    assert np.allclose(geometry.quat_xyzw_to_matrix((x, y, z, w)), pose[:3, :3], atol=1e-9)
    with pytest.raises(ValueError, match="4x4"):
        geometry.frustum(np.eye(3), k, 128, 128)


def test_start_from_world_puts_the_start_pose_at_the_origin_facing_x():
    t = geometry.start_from_world(2.0, 3.0, 90.0)
    assert np.allclose(t @ [2.0, 3.0, 0.5, 1.0], [0, 0, 0.5, 1])
    assert np.allclose(t @ [2.0, 4.0, 0.0, 1.0], [1, 0, 0, 1])  # one metre along the start heading


def test_grid_plane_and_overview_camera():
    plane = geometry.grid_plane((-1.0, -2.0), 0.05, (40, 80))
    assert plane.size_x == pytest.approx(2.0) and plane.size_y == pytest.approx(4.0)
    assert plane.center == pytest.approx((0.0, 0.0, 0.01))
    view = geometry.overview_camera(plane)
    assert view.look_at == pytest.approx((0.0, 0.0, 0.0))
    assert view.position[2] > 2.0 and view.position[0] < 0  # above, behind the start heading
    with pytest.raises(ValueError, match="positive cell"):
        geometry.grid_plane((0, 0), 0.0, (4, 4))


def test_known_plane_frames_the_mapped_cells_only():
    occ = np.zeros((256, 256), np.uint8)
    assert geometry.known_plane((-6.4, -6.4), 0.05, occ) is None
    occ[100:140, 120:180] = 1  # 2 m x 3 m mapped
    plane = geometry.known_plane((-6.4, -6.4), 0.05, occ, margin=0.5)
    assert plane.size_x == pytest.approx(3.0) and plane.size_y == pytest.approx(4.0)
    assert plane.center[:2] == pytest.approx((-6.4 + 6.0, -6.4 + 7.5))


def _overlapping_pairs(boxes: np.ndarray, gap: float) -> list[tuple[int, int]]:
    pairs = []
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            if a[0] < b[2] + gap and b[0] < a[2] + gap and a[1] < b[3] + gap and b[1] < a[3] + gap:
                pairs.append((i, j))
    return pairs


@pytest.mark.parametrize("seed", range(4))
def test_placed_labels_never_overlap_on_screen(seed):
    rng = np.random.default_rng(seed)
    plane = geometry.FloorPlane((0.5, 0.5, 0.0), 5.0, 4.0)
    view = geometry.screen_view_looking_at(geometry.overview_camera(plane), 1.3, 720)
    n = 40
    anchors = np.c_[rng.normal(0.5, 0.4, (n, 2)), rng.uniform(0.2, 1.2, n)]  # a tight cluster
    sizes = np.c_[rng.uniform(40, 190, n), np.full(n, 17.0)]
    placed = geometry.place_labels(anchors, sizes, view, gap_px=3.0)
    before = geometry.label_boxes(view.project(anchors)[0], sizes)
    assert _overlapping_pairs(before, 3.0)  # crowded as given ...
    boxes = geometry.label_boxes(view.project(placed)[0], sizes)
    assert _overlapping_pairs(boxes, 3.0 - 1e-6) == []  # ... and apart once placed
    assert np.allclose(placed[0], anchors[0])  # the first keeps its spot
    lift = view.project(anchors)[0][:, 1] - view.project(placed)[0][:, 1]
    assert np.all(lift >= -1e-6)  # labels only move up on screen
    assert np.allclose(view.project(placed)[0][:, 0], view.project(anchors)[0][:, 0])  # never sideways
    assert np.array_equal(placed, geometry.place_labels(anchors, sizes, view, gap_px=3.0))  # deterministic


def test_labels_apart_stay_put_and_labels_behind_the_camera_too():
    view = geometry.screen_view(
        (0.0, 0.0, 5.0), geometry.rotation_to_wxyz(np.diag([1.0, -1.0, -1.0])), 1.0, 600
    )
    anchors = np.array([[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 9.0]])  # the last is behind the camera
    placed = geometry.place_labels(anchors, np.array([[60.0, 17.0]] * 3), view)
    assert np.allclose(placed, anchors)
    with pytest.raises(ValueError, match="one size per anchor"):
        geometry.place_labels(anchors, np.zeros((2, 2)), view)


def test_screen_view_projects_like_a_pinhole():
    # a camera 4 m above the origin looking straight down, image +x along world +x
    view = geometry.screen_view(
        (0.0, 0.0, 4.0), geometry.rotation_to_wxyz(np.diag([1.0, -1.0, -1.0])), 2 * math.atan(0.5), 400
    )  # focal length 400 px
    uv, depth = view.project(np.array([[1.0, 0.5, 0.0]]))
    assert depth[0] == pytest.approx(4.0)
    assert uv[0] == pytest.approx((100.0, -50.0))  # +y world is up on screen (-v)
    look = geometry.screen_view_looking_at(
        geometry.CameraView((0.0, 0.0, 4.0), (0.0, 0.0, 0.0)), 1.0, 400, up=(0.0, 1.0, 0.0)
    )
    assert look.project(np.array([[0.0, 1.0, 0.0]]))[0][0, 1] < 0  # up in the world is up on screen


def test_unproject_depth_follows_the_protocol_convention():
    k = np.array([[2.0, 0, 2.0], [0, 2.0, 2.0], [0, 0, 1.0]])
    pose = geometry.camera_pose_from_agent(1.0, 0.0, 0.0, 0.0, 1.0)  # at (1, 0, 1) looking along +x
    depth = np.full((4, 4), 2.0, np.float32)
    depth[0, 0], depth[3, 3] = 0.0, np.nan  # invalid: dropped
    pts, pix = geometry.unproject_depth(depth, k, pose)
    assert len(pts) == 14 and pts.dtype == np.float32
    centre = pts[(pix[:, 0] == 2) & (pix[:, 1] == 2)][0]  # pixel (u, v) = (cx, cy)
    assert centre == pytest.approx((3.0, 0.0, 1.0))  # 2 m straight ahead
    right = pts[(pix[:, 0] == 2) & (pix[:, 1] == 3)][0]  # one column right: -y, 1 m over
    assert right == pytest.approx((3.0, -1.0, 1.0))
    assert len(geometry.unproject_depth(depth, k, pose, stride=2)[0]) == 3


# --- images -----------------------------------------------------------------------------------


def test_heatmap_texture_is_the_transposed_grid_with_alpha():
    heat = np.zeros((6, 4), np.float32)  # X = 6 cells along x, Y = 4 along y
    heat[5, 1] = 1.0
    rgba = images.heatmap_rgba(heat)
    assert rgba.shape == (4, 6, 4) and rgba.dtype == np.uint8
    assert rgba[1, 5, 3] == 210 and rgba[0, 0, 3] == 0  # viser image: column = +x, row = +y
    assert rgba[1, 5, 0] > rgba[1, 5, 2]  # hot is red
    with pytest.raises(ValueError, match="2D grid"):
        images.heatmap_rgba(np.zeros(3))


def test_occupancy_image_is_drawn_x_up_y_left():
    occ = np.ones((10, 8), np.uint8)
    occ[9, 0] = 2  # the cell at max x, min y: top right of the image
    explored = np.ones_like(occ, bool)
    img = images.occupancy_image(occ, explored, (0.0, 0.0), 0.1, min_width=80)
    assert img.shape == (100, 80, 3)
    assert tuple(img[2, 77]) == images.OBSTACLE_RGB
    assert tuple(img[50, 40]) == images.FREE_RGB
    canvas = images.MapCanvas((0.0, 0.0), 0.1, (10, 8), 10)
    assert canvas.pixel(0.95, 0.05) == (75, 5)  # the obstacle cell's centre
    drawn = images.occupancy_image(
        occ,
        explored,
        (0.0, 0.0),
        0.1,
        pose=(0.5, 0.4, 90.0, 0.0),
        trajectory=np.array([[0.1, 0.1], [0.5, 0.4]]),
        path=np.array([[0.5, 0.4], [0.8, 0.4]]),
        goal=(0.8, 0.4),
        search_points=np.array([[0.3, 0.3]]),
        min_width=80,
    )
    assert np.any(np.all(drawn == images.AGENT_RGB, axis=2))
    assert not np.array_equal(drawn, img)


def test_occupancy_colors_mark_unknown_free_and_obstacles():
    occ = np.array([[0, 1, 2, 1]], np.uint8)
    c = images.occupancy_colors(occ, np.array([[False, True, True, False]]))
    assert [tuple(x) for x in c[0]] == [
        images.UNKNOWN_RGB,
        images.FREE_RGB,
        images.OBSTACLE_RGB,
        images.SEEN_FREE_RGB,
    ]
    with pytest.raises(ValueError, match="same shape"):
        images.occupancy_colors(occ, np.zeros((2, 2), bool))


def test_detections_drawn_with_warning_colour_for_out_of_place():
    rgb = np.full((64, 64, 3), 128, np.uint8)
    dets = [
        Detection2D("Mug", 0.9, (4, 4, 20, 20), oop_prob=0.95),
        Detection2D("Book", 0.8, (30, 30, 60, 60), oop_prob=0.1),
    ]
    img = images.draw_detections(rgb, dets, min_width=256)
    assert img.shape == (256, 256, 3)
    assert np.any(np.all(img == palette.WARNING_RGB, axis=2))
    assert np.any(np.all(img == palette.TRACKED_RGB, axis=2))


def test_progress_plot_has_a_fixed_size_for_any_history():
    empty = images.progress_plot(np.zeros((0, 3)))
    one = images.progress_plot(np.array([[0.0, 0.0, 1.0]]))
    many = images.progress_plot(np.array([(s, s // 40, min(1 + s // 25, 5)) for s in range(193)], float))
    for img in (empty, one, many):
        assert img.shape == (images.PLOT_SIZE[1], images.PLOT_SIZE[0], 3) and img.dtype == np.uint8
    put_away, found = (np.all(many == c, axis=2) for c in (palette.WARNING_RGB, palette.TRAJECTORY_RGB))
    assert put_away.sum() > 300 and found.sum() > 300  # both series drawn

    def has(img: np.ndarray, color: palette.RGB) -> bool:
        return bool(np.any(np.all(img == color, axis=2)))

    legend, plot_area = slice(0, 22), slice(22, None)
    assert has(empty[legend], palette.WARNING_RGB) and not has(empty[plot_area], palette.WARNING_RGB)
    assert has(one[plot_area], palette.WARNING_RGB) and has(
        one[plot_area], palette.TRAJECTORY_RGB
    )  # a dot each
    assert float(empty.std()) > 10  # axes and ticks, not a blank


def test_crop_to_known_keeps_the_mapped_part_square():
    occ = np.zeros((256, 256), np.uint8)
    occ[100:140, 120:180] = 1
    explored = occ > 0
    crop, exp, origin = images.crop_to_known(occ, explored, (-6.4, -6.4), 0.05, margin=0.5)
    assert crop.shape[0] == crop.shape[1] == 60 + 20  # the longer side plus margins
    assert exp.shape == crop.shape and crop.sum() == occ.sum()  # every known cell kept
    # rows 100-139 and columns 120-179, 10 cells of margin: an 80-cell square centred on (120, 150)
    assert origin == pytest.approx((-6.4 + 0.05 * 80, -6.4 + 0.05 * 110))
    whole = images.crop_to_known(np.zeros((8, 8), np.uint8), None, (0.0, 0.0), 0.1)
    assert whole[0].shape == (8, 8) and whole[2] == (0.0, 0.0)
    edge = np.zeros((50, 50), np.uint8)
    edge[0:3, 45:50] = 1  # at a corner: the crop stays inside
    c, _, _ = images.crop_to_known(edge, None, (0.0, 0.0), 0.1, margin=1.0)
    assert c.shape == (25, 25) and c.sum() == edge.sum()


# --- the camera-coloured cloud ------------------------------------------------------------------


def test_colour_cloud_fuses_frames_latest_colour_wins_and_stays_capped():
    from tidee.viewer.colour_cloud import ColourCloud

    k = np.array([[8.0, 0, 8.0], [0, 8.0, 8.0], [0, 0, 1.0]])
    pose = geometry.camera_pose_from_agent(0.0, 0.0, 0.0, 0.0, 1.0)  # looking along +x from 1 m up
    depth = np.full((16, 16), 2.0, np.float32)  # a wall 2 m ahead
    red, blue = np.zeros((16, 16, 3), np.uint8), np.zeros((16, 16, 3), np.uint8)
    red[..., 0], blue[..., 2] = 200, 200
    cloud = ColourCloud(voxel=0.1, cap=10_000, stride=1, floor_z=0.05, ceiling_z=2.4)
    n = cloud.add(red, depth, pose, k)
    pts = cloud.points()
    assert n == len(pts) > 20 and np.allclose(pts[:, 0], 2.05)  # voxel centres on the wall
    assert pts[:, 2].min() > 0.0 and pts[:, 2].max() < 2.4
    assert np.all(cloud.colors() == (200, 0, 0))
    assert cloud.add(blue, depth, pose, k) == n  # the same voxels, seen again ...
    assert np.all(cloud.colors() == (0, 0, 200))  # ... take the newest colour
    down = geometry.camera_pose_from_agent(0.0, 0.0, 0.0, 90.0, 1.0)  # looking straight down at the floor
    assert cloud.add(red, np.full((16, 16), 1.0, np.float32), down, k) == n  # floor points: dropped
    small = ColourCloud(voxel=0.1, cap=30, stride=1)
    small.add(red, depth, pose, k)
    shifted = pose.copy()
    shifted[1, 3] = 5.0  # another wall, elsewhere
    small.add(blue, depth, shifted, k)
    assert len(small) == 30 and np.all(small.colors() == (0, 0, 200))  # over the cap: the newest stay
    small.clear()
    assert len(small) == 0 and small.points().shape == (0, 3)


def test_depth_colormap_blacks_out_invalid_depth():
    depth = np.array([[0.0, 1.0], [np.nan, 4.0]], np.float32)
    img = images.colorize_depth(depth, min_width=2)
    assert img.shape == (2, 2, 3)
    assert tuple(img[0, 0]) == (0, 0, 0) and tuple(img[1, 0]) == (0, 0, 0)
    assert img[0, 1].sum() > img[1, 1].sum()  # near is brighter


# --- the scene's nodes (a real viser server, no browser) ---------------------------------------------


def test_scene_updates_assign_to_the_same_nodes(scene_view):
    ep = SyntheticEpisode(seed=1)
    handles = (scene_view.voxels, scene_view.boxes, scene_view.frustum, scene_view.heatmap)
    for step in (100, 400):
        for kind, msg in ep.messages(step).items():
            scene_view.apply(kind, msg)
    assert handles == (scene_view.voxels, scene_view.boxes, scene_view.frustum, scene_view.heatmap)
    maps, memory = ep.maps(400), ep.memory(400)
    assert scene_view.counts["voxels"] == len(maps.points) > 100
    assert scene_view.counts["objects"] == len(memory.objects) == 5
    assert scene_view.boxes.points.shape == (12 * 5, 2, 3)
    oop = [o for o in memory.objects if o.out_of_place]
    assert oop and any(tuple(c) == palette.WARNING_RGB for c in scene_view.boxes.colors[:, 0])
    texts = [h.text for h in scene_view.labels.handles[: scene_view.labels.shown]]
    assert any("out of place" in t for t in texts)
    shown = scene_view.node_names()
    assert (
        shown["/map/voxels"]
        and shown["/objects/boxes"]
        and shown["/agent/camera"]
        and shown["/search/heatmap"]
    )
    assert not shown["/oracle/boxes"]  # oracle: off by default
    assert scene_view.heatmap.render_width == pytest.approx(maps.occupancy.shape[0] * maps.cell)


def test_scene_layers_colour_modes_and_clear(scene_view):
    ep = SyntheticEpisode()
    for kind, msg in ep.messages(300).items():
        scene_view.apply(kind, msg)
    by_class = scene_view.voxels.colors.copy()
    scene_view.set_colour_mode("height")
    assert not np.array_equal(by_class, scene_view.voxels.colors)
    scene_view.set_colour_mode("rgb")  # the camera-coloured cloud replaces the voxel map
    assert scene_view.rgb_cloud.visible and not scene_view.voxels.visible
    scene_view.set_colour_mode("semantic")
    assert scene_view.voxels.visible and not scene_view.rgb_cloud.visible
    with pytest.raises(ValueError, match="colour mode must be one of"):
        scene_view.set_colour_mode("infrared")
    scene_view.set_layer("objects", False)
    assert not scene_view.boxes.visible
    assert not any(h.visible for h in scene_view.labels.handles)
    scene_view.set_layer("objects", True)
    assert scene_view.boxes.visible
    scene_view.clear()
    assert not any(scene_view.node_names().values())
    with pytest.raises(ValueError, match="layer must be one of"):
        scene_view.set_layer("walls", True)


def test_oracle_objects_are_placed_in_the_start_frame(scene_view):
    from tidee.viewer.scene_view import oracle_objects

    scene = {
        "start": {"x": 2.0, "y": 3.0, "yaw_deg": 90.0},
        "mess": [{"id": "Mug_0"}],
        "objects": [
            {
                "id": "Mug_0",
                "type": "Mug",
                "pickupable": True,
                "position": [2.0, 4.0, 0.7],
                "orientation": [0, 0, 0, 1],
                "size": [0.1, 0.1, 0.2],
            },
            {
                "id": "Wall_0",
                "type": "Wall",
                "pickupable": False,
                "position": [0, 0, 0],
                "orientation": [0, 0, 0, 1],
                "size": [1, 1, 1],
            },
        ],
    }
    objs = oracle_objects(scene)
    assert len(objs) == 1 and objs[0].moved and objs[0].label == "Mug"
    assert objs[0].center == pytest.approx((1.0, 0.0, 0.8))
    scene_view.set_layer("oracle", True)
    scene_view.apply_oracle(objs)
    assert scene_view.oracle_boxes.visible and scene_view.counts["oracle"] == 1
    with pytest.raises(ValueError, match="no 'start'"):
        oracle_objects({"objects": []})


# --- replay ------------------------------------------------------------------------------------


def test_replay_gives_the_latest_message_of_each_kind_at_a_step(tmp_path):
    from tidee.viewer.replay import ReplayLog

    write_synthetic_log(str(tmp_path), steps=23)
    log = ReplayLog(tmp_path)
    assert (log.first_step, log.last_step) == (0, 22) and log.session == "synthetic"
    at = log.at(13)
    assert at["status"].step == 13 and at["maps"].step == 10 and at["search"].step == 10
    assert at["frame"].step == 13 and at["frame"].rgb.shape == (128, 128, 3)
    assert log.index_at("maps", 14) == log.index_at("maps", 10) != log.index_at("maps", 15)
    hist = log.history(13)
    assert hist.shape == (14, 3) and hist[-1, 0] == 13
    assert len(log.history(22, max_points=5)) == 5
    # a crashed agent's log: the torn tail is skipped, the rest replays
    tlog = tmp_path / "telemetry.tlog"
    tlog.write_bytes(tlog.read_bytes()[:-100])
    cut = ReplayLog(tmp_path)
    assert cut.truncated and cut.last_step <= 22


def test_screenshot_steps_resolve_against_the_log(tmp_path):
    from tidee.viewer.replay import ReplayLog
    from tidee.viewer.screenshot import resolve_step

    write_synthetic_log(str(tmp_path), steps=23)
    log = ReplayLog(tmp_path)
    assert resolve_step(log, "end") == 22 and resolve_step(log, "7") == 7
    assert resolve_step(log, "search") == log.steps("search")[0]
    with pytest.raises(ValueError, match="outside the log's steps 0-22"):
        resolve_step(log, "40")
    with pytest.raises(ValueError, match="a step number, 'search' or 'end'"):
        resolve_step(log, "middle")


def test_replay_of_an_empty_log_says_so(tmp_path):
    from tidee.protocol.episode_log import LogWriter
    from tidee.viewer.replay import ReplayLog

    LogWriter(tmp_path).close()
    with pytest.raises(ValueError, match="no telemetry"):
        ReplayLog(tmp_path)


# --- the live feed over Zenoh --------------------------------------------------------------------


def test_live_feed_discovers_the_session_decodes_telemetry_and_commands_it():
    from tidee.viewer.feed import LiveFeed

    with synthetic_source() as src:
        feed = LiveFeed(endpoint=src.endpoint)
        try:
            seen: dict = {}
            assert wait_until(
                lambda: seen.update(feed.poll()) or {"status", "maps", "memory", "frame"} <= set(seen), 10.0
            )
            assert feed.selected == src.session
            assert wait_until(
                lambda: any(s.alive and s.server_id == src.server_id for s in feed.sessions()), 10.0
            )
            feed.send(AgentCommand(kind="pause", command_id="c1"))
            acks: list = []
            assert wait_until(
                lambda: acks.append(feed.poll().get("ack")) or any(a and a.command_id == "c1" for a in acks),
                10.0,
            )
            assert src.agent is not None and src.agent.paused
            with pytest.raises(LookupError, match="no server known"):
                feed.fetch_state("nobody")
        finally:
            feed.close()


# --- process hygiene and the command line --------------------------------------------------------------


def test_viewer_imports_neither_torch_nor_the_agent():
    code = (
        "import sys; import tidee.viewer.app, tidee.viewer.cli, tidee.viewer.bench, tidee.viewer.browser, "
        "tidee.viewer.synthetic; bad = [m for m in sys.modules if m == 'torch' or m.startswith('torch.') "
        "or m.startswith('tidee.agent')]; assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=60)


def test_cli_registers_the_viewer_without_importing_viser():
    code = (
        "import sys, argparse; from tidee.viewer.cli import register; p = argparse.ArgumentParser(); "
        "register(p.add_subparsers()); a = p.parse_args(['viewer', '--port', '0', '--session', 's1']); "
        "assert a.port == 0 and a.session == 's1' and a.host == '127.0.0.1'; "
        "assert 'viser' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=60)
    from tidee.viewer.app import ViewerConfig

    with pytest.raises(ValueError, match="port must be"):
        ViewerConfig(port=70000)
    with pytest.raises(FileNotFoundError, match="not a directory"):
        ViewerConfig(replay=os.path.join("no", "such", "log"))
    with pytest.raises(ValueError, match="session must be"):
        ViewerConfig(session="a/b")


def test_synthetic_episode_is_deterministic_and_realistic():
    a, b = SyntheticEpisode(seed=3), SyntheticEpisode(seed=3)
    ma, mb = a.messages(200), b.messages(200)
    assert np.array_equal(ma["frame"].rgb, mb["frame"].rgb)
    maps = ma["maps"]
    assert maps.classes == CLASSES and len(maps.points) > 300
    assert set(np.unique(maps.occupancy)) == {0, 1, 2}
    assert len(ma["memory"].objects) == 5 and ma["status"].trajectory.shape[1] == 2


def test_scene_survives_empty_and_inconsistent_maps(scene_view):
    import dataclasses

    maps = SyntheticEpisode().maps(100)
    scene_view.apply_maps(dataclasses.replace(maps, point_labels=maps.point_labels[:3]))  # labels too short
    assert scene_view.voxels.colors.shape == scene_view.voxels.points.shape
    empty = dataclasses.replace(
        maps,
        occupancy=np.zeros((0, 0), np.uint8),
        explored=np.zeros((0, 0), bool),
        points=np.zeros((0, 3), np.float32),
        point_labels=np.zeros(0, np.int16),
    )
    scene_view.apply_maps(empty)
    assert not scene_view.voxels.visible


# --- labels: only what matters, laid out apart ------------------------------------------------------


def _tracked(i: int, label: str, x: float, oop: bool = False, held: bool = False) -> TrackedObjectMsg:
    return TrackedObjectMsg(
        id=i,
        label=label,
        score=0.9 - 0.01 * i,
        centroid=(x, 0.0, 0.5),
        box_min=(x - 0.1, -0.1, 0.4),
        box_max=(x + 0.1, 0.1, 0.6),
        oop_prob=0.8 if oop else 0.1,
        out_of_place=oop,
        held=held,
    )


def test_labelled_objects_are_those_that_matter_unless_all_are_asked_for():
    from tidee.viewer.scene_view import labelled_objects

    objs = [
        _tracked(0, "Sofa", 0.0),
        _tracked(1, "Mug", 0.1, oop=True),
        _tracked(2, "Book", 0.2),
        _tracked(3, "Laptop", 0.3, held=True),
        _tracked(4, "Chair", 0.4),
    ]
    assert [o.label for o in labelled_objects(objs, target_id=2, label_all=False)] == [
        "Laptop",
        "Book",
        "Mug",
    ]
    assert [o.label for o in labelled_objects(objs, target_id=None, label_all=False)] == ["Laptop", "Mug"]
    every = [o.label for o in labelled_objects(objs, target_id=2, label_all=True)]
    assert every[:3] == ["Laptop", "Book", "Mug"] and sorted(every) == sorted(o.label for o in objs)


def test_scene_labels_a_crowd_without_overlap_and_all_on_request(scene_view):
    from tidee.protocol.messages import ObjectMemoryMsg
    from tidee.viewer.scene_view import LABEL_CHAR_PX, LABEL_LINE_PX

    crowd = [_tracked(i, f"Thing{i}", 0.05 * i, oop=i % 3 == 0) for i in range(12)]  # 12 objects in 60 cm
    scene_view.apply_maps(SyntheticEpisode().maps(300))  # a floor: the overview view
    scene_view.apply_memory(ObjectMemoryMsg("s", 1, crowd))
    shown = scene_view.labels.handles[: scene_view.labels.shown]
    assert len(shown) == 4 and all("out of place" in h.text for h in shown)  # 0, 3, 6, 9 only
    scene_view.set_label_all(True)
    shown = scene_view.labels.handles[: scene_view.labels.shown]
    assert len(shown) == 12 and scene_view.counts["labels"] == 12
    view = scene_view._fallback_view()
    uv = view.project(np.array([h.position for h in shown]))[0]
    sizes = np.array([(len(h.text) * LABEL_CHAR_PX + 10, LABEL_LINE_PX) for h in shown])
    assert _overlapping_pairs(geometry.label_boxes(uv, sizes), 2.9) == []
    assert scene_view.leaders.visible and len(scene_view.leaders.points) >= 6  # lifted labels: a line each
    scene_view.set_label_all(False)
    assert scene_view.labels.shown == 4


# --- the episode's end: feed, replay, panel --------------------------------------------------------


def test_summary_panel_says_how_the_episode_ended_and_escapes_text():
    from tidee.viewer.panels import SUMMARY_ID, summary_html

    s = EpisodeSummary(
        session="s",
        episode={
            "room_type": "Kitchen",
            "seed": 200,
            "mess_index": 0,
            "variant": "TIDEE",
            "perception": "learned",
        },
        steps=192,
        wall_s=142.6,
        end_reason="no <b>more</b> objects",
        put_away=4,
        moved=5,
        found=4,
        plausible=3,
        false_picks=0,
        replay="tidee viewer --replay runs/Kitchen_200_mess0",
    )
    page = summary_html(s)
    assert f"id='{SUMMARY_ID}'" in page and "Episode finished" in page and "Kitchen seed 200 mess 0" in page
    for text in (
        "moved <b>5</b>",
        "found <b>4</b>/5",
        "put away <b>4</b>",
        "plausible <b>3</b>/5",
        "false picks <b>0</b>",
        "<b>192</b> steps",
        "<b>143</b> s",
        "tidee viewer --replay runs/Kitchen_200_mess0",
    ):
        assert text in page, text
    assert "&lt;b&gt;more" in page and "<b>more" not in page
    unscored = summary_html(EpisodeSummary("s", {}, 10, 1.0, "step budget", 0))
    assert "not scored" in unscored and "moved –" in unscored


def test_replay_shows_the_summary_from_the_last_step_only(tmp_path):
    import json

    from tidee.protocol.episode_log import LogReader, LogWriter
    from tidee.viewer.replay import ReplayLog

    write_synthetic_log(str(tmp_path / "new"), steps=23)
    log = ReplayLog(tmp_path / "new")
    assert "summary" not in log.at(21)
    summary = log.at(22)["summary"]
    assert isinstance(summary, EpisodeSummary) and summary.steps == 23 and summary.moved == 3
    assert log.steps("summary") == [22]
    # a log whose telemetry lacks it (an older agent's): the summary comes from summary.json
    record = json.loads((tmp_path / "new" / "summary.json").read_text())
    with LogWriter(tmp_path / "old") as writer:
        for kind, msg in LogReader(tmp_path / "new").messages():
            if kind != "summary":
                writer.message(kind, msg)
        writer.finish(record)
    old = ReplayLog(tmp_path / "old")
    assert old.messages == log.messages - 1 and old.at(22)["summary"] == summary


def test_replay_viewer_shows_the_finished_panel_at_the_end_and_hides_it_before(tmp_path):
    from tidee.viewer.app import ViewerConfig, run_viewer

    write_synthetic_log(str(tmp_path), steps=40)
    with run_viewer(ViewerConfig(replay=str(tmp_path), port=0)) as viewer:
        app = viewer.app
        app.replay_seek(39)
        assert wait_until(
            lambda: app.panels.summary.visible and "episode finished" in app.panels.title.content, 10.0
        )
        assert "Episode finished" in app.panels.summary.content
        assert app.panels.plot.image.shape[:2] == (170, 360)
        app.set_colour_mode("rgb")  # the frames up to here, fused
        assert wait_until(lambda: app.scene.node_names()["/map/rgb"], 10.0)
        assert app.scene.counts["rgb_points"] > 500 and not app.scene.voxels.visible
        app.replay_seek(10)
        assert wait_until(lambda: not app.panels.summary.visible and app.stats.last_step == 10, 10.0)
        assert app.scene.colour_cloud.frames <= 11  # slid back: the cloud holds what was seen by step 10


def test_live_feed_delivers_the_episode_summary():
    from tidee.viewer.feed import LiveFeed

    with synthetic_source() as src:
        assert src.agent is not None
        feed = LiveFeed(endpoint=src.endpoint)
        try:
            seen: dict = {}
            assert wait_until(lambda: seen.update(feed.poll()) or "status" in seen, 10.0)
            src.agent.stop()  # the episode ends: the agent says how
            src.agent.publish_summary(wall_s=1.5)
            assert wait_until(lambda: seen.update(feed.poll()) or "summary" in seen, 10.0)
            assert isinstance(seen["summary"], EpisodeSummary) and seen["summary"].session == src.session
            assert seen["summary"].steps == src.agent.step and seen["summary"].wall_s == 1.5
            assert feed.decode_errors == 0
        finally:
            feed.close()


def test_annotated_screenshot_numbers_the_panels_found_and_names_them_below():
    from tidee.viewer.annotate import INK, PANELS, annotate

    shot = np.full((400, 640, 3), 255, np.uint8)
    boxes = {"camera": (10, 40, 200, 200), "canvas": (220, 0, 420, 400), "summary": (440, 60, 630, 160)}
    out = annotate(shot, boxes)
    assert out.shape[1] == 640 and out.shape[0] > 400  # the key goes below the picture
    ink = np.all(out == INK, axis=2)
    assert ink[40:200, 10:14].any() and ink[40:200, 197:201].any()  # the camera's box is drawn
    assert not ink[250:400, 0:200].any()  # nothing where no panel is
    assert ink[400:].sum() > 3 * 100  # three numbered badges in the key
    assert {k for k, _ in PANELS} >= set(boxes) | {"map", "plot", "predictions", "controls"}


def test_the_progress_plot_follows_steps_in_strides_and_counts_at_once() -> None:
    from types import SimpleNamespace

    from tidee.viewer.panels import PLOT_STEP_STRIDE, Panels

    panel = SimpleNamespace(_plot_key=None, plot=SimpleNamespace(image=None))
    drawn: list[float] = []

    def show(rows: list[tuple[float, float, float]], final: bool = False) -> None:
        before = panel.plot.image
        Panels.show_plot(panel, np.array(rows, np.float64), final=final)  # type: ignore[arg-type]
        if panel.plot.image is not before:
            drawn.append(rows[-1][0])

    rows = [(0.0, 0.0, 0.0)]
    show(rows)
    for step in range(1, 25):  # nothing found or put away: a redraw per stride
        rows.append((float(step), 0.0, 0.0))
        show(rows)
    assert drawn == [0.0, float(PLOT_STEP_STRIDE), float(2 * PLOT_STEP_STRIDE)]
    rows.append((25.0, 0.0, 1.0))  # an object found: drawn at once
    show(rows)
    rows.append((26.0, 0.0, 1.0))
    show(rows, final=True)  # the episode's last status: drawn at once
    assert drawn[-2:] == [25.0, 26.0]
    show(rows[:3])  # a new episode (fewer rows): drawn at once
    assert drawn[-1] == 2.0


def test_live_images_nobody_watches_are_drawn_when_a_browser_connects(tmp_path):
    # Live with no browser connected, the camera and 2D map images are kept, not encoded (a
    # core's time on a small machine); the newest ones are drawn once a browser connects.
    from tidee.viewer.app import ViewerApp, ViewerConfig
    from tidee.viewer.replay import ReplayLog

    write_synthetic_log(str(tmp_path), steps=12)
    msgs = ReplayLog(str(tmp_path)).at(11)
    app = ViewerApp(ViewerConfig(replay=str(tmp_path), port=0))  # the worker is not started
    try:
        app.replay, app._title = None, lambda: "live"  # drawn as live messages (no feed to name)
        clients: dict = {}
        app.server.get_clients = lambda: clients  # type: ignore[method-assign]
        camera, depth, plan = app.panels.rgb.image, app.panels.depth.image, app.panels.map.image
        app._draw({k: msgs[k] for k in ("maps", "frame", "status")})
        assert app.scene.counts["voxels"] > 0  # the 3D scene is kept up to date for a later browser
        assert app.panels.rgb.image is camera and app.panels.depth.image is depth
        assert app.panels.map.image is plan
        assert app._camera_pending is msgs["frame"] and app._map_pending
        clients[1] = object()  # a browser connects
        app._draw_images()
        assert app.panels.rgb.image is not camera and app.panels.depth.image is not depth
        assert app.panels.map.image is not plan
        assert app._camera_pending is None and not app._map_pending
    finally:
        app.server.stop()
