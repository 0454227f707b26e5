"""Telemetry -> scene conversion (colours, boxes, frusta, heatmap and map images), the
scene's node handles, replay indexing, the live feed over Zenoh, and the no-torch rule."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tidee.protocol.messages import AgentCommand, Detection2D
from tidee.viewer import geometry, images, palette
from tidee.viewer.synthetic import CLASSES, SyntheticEpisode, write_synthetic_log

from tests.test_service import wait_until
from tests.viewer_fakes import synthetic_source

REPO = Path(__file__).resolve().parents[1]


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
    assert np.all((d > 1e-9).sum(axis=1) == 1)                       # every edge along one axis
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
    assert np.allclose(turned.max(0), (1.0, 0.5, 0.25), atol=1e-6)     # x and y extents swapped


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
    assert np.allclose(pose[:3, 2], [1, 0, 0])     # optical z: forward = +x
    assert np.allclose(pose[:3, 0], [0, -1, 0])    # optical x: right = -y
    assert np.allclose(pose[:3, 1], [0, 0, -1])    # optical y: down
    assert np.allclose(pose[:3, 3], [1, 2, 0.9])
    assert np.allclose(np.linalg.det(pose[:3, :3]), 1.0)
    looking_down = geometry.camera_pose_from_agent(0, 0, 90.0, 30.0, 0.9)
    assert np.allclose(looking_down[:3, 2], [0, math.cos(math.radians(30)), -0.5], atol=1e-9)


def test_frustum_from_intrinsics_and_pose():
    k = np.array([[64.0, 0, 64], [0, 64.0, 64], [0, 0, 1]])        # 90 degrees at 128 px
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
    assert np.allclose(t @ [2.0, 4.0, 0.0, 1.0], [1, 0, 0, 1])     # one metre along the start heading


def test_grid_plane_and_overview_camera():
    plane = geometry.grid_plane((-1.0, -2.0), 0.05, (40, 80))
    assert plane.size_x == pytest.approx(2.0) and plane.size_y == pytest.approx(4.0)
    assert plane.center == pytest.approx((0.0, 0.0, 0.01))
    view = geometry.overview_camera(plane)
    assert view.look_at == pytest.approx((0.0, 0.0, 0.0))
    assert view.position[2] > 2.0 and view.position[0] < 0          # above, behind the start heading
    with pytest.raises(ValueError, match="positive cell"):
        geometry.grid_plane((0, 0), 0.0, (4, 4))


def test_known_plane_frames_the_mapped_cells_only():
    occ = np.zeros((256, 256), np.uint8)
    assert geometry.known_plane((-6.4, -6.4), 0.05, occ) is None
    occ[100:140, 120:180] = 1                                          # 2 m x 3 m mapped
    plane = geometry.known_plane((-6.4, -6.4), 0.05, occ, margin=0.5)
    assert plane.size_x == pytest.approx(3.0) and plane.size_y == pytest.approx(4.0)
    assert plane.center[:2] == pytest.approx((-6.4 + 6.0, -6.4 + 7.5))


# --- images -----------------------------------------------------------------------------------

def test_heatmap_texture_is_the_transposed_grid_with_alpha():
    heat = np.zeros((6, 4), np.float32)          # X = 6 cells along x, Y = 4 along y
    heat[5, 1] = 1.0
    rgba = images.heatmap_rgba(heat)
    assert rgba.shape == (4, 6, 4) and rgba.dtype == np.uint8
    assert rgba[1, 5, 3] == 210 and rgba[0, 0, 3] == 0   # viser image: column = +x, row = +y
    assert rgba[1, 5, 0] > rgba[1, 5, 2]                  # hot is red
    with pytest.raises(ValueError, match="2D grid"):
        images.heatmap_rgba(np.zeros(3))


def test_occupancy_image_is_drawn_x_up_y_left():
    occ = np.ones((10, 8), np.uint8)
    occ[9, 0] = 2                                 # the cell at max x, min y: top right of the image
    explored = np.ones_like(occ, bool)
    img = images.occupancy_image(occ, explored, (0.0, 0.0), 0.1, min_width=80)
    assert img.shape == (100, 80, 3)
    assert tuple(img[2, 77]) == images.OBSTACLE_RGB
    assert tuple(img[50, 40]) == images.FREE_RGB
    canvas = images.MapCanvas((0.0, 0.0), 0.1, (10, 8), 10)
    assert canvas.pixel(0.95, 0.05) == (75, 5)   # the obstacle cell's centre
    drawn = images.occupancy_image(occ, explored, (0.0, 0.0), 0.1, pose=(0.5, 0.4, 90.0, 0.0),
                                   trajectory=np.array([[0.1, 0.1], [0.5, 0.4]]),
                                   path=np.array([[0.5, 0.4], [0.8, 0.4]]),
                                   goal=(0.8, 0.4), search_points=np.array([[0.3, 0.3]]), min_width=80)
    assert np.any(np.all(drawn == images.AGENT_RGB, axis=2))
    assert not np.array_equal(drawn, img)


def test_occupancy_colors_mark_unknown_free_and_obstacles():
    occ = np.array([[0, 1, 2, 1]], np.uint8)
    c = images.occupancy_colors(occ, np.array([[False, True, True, False]]))
    assert [tuple(x) for x in c[0]] == [images.UNKNOWN_RGB, images.FREE_RGB, images.OBSTACLE_RGB,
                                        images.SEEN_FREE_RGB]
    with pytest.raises(ValueError, match="same shape"):
        images.occupancy_colors(occ, np.zeros((2, 2), bool))


def test_detections_drawn_with_warning_colour_for_out_of_place():
    rgb = np.full((64, 64, 3), 128, np.uint8)
    dets = [Detection2D("Mug", 0.9, (4, 4, 20, 20), oop_prob=0.95),
            Detection2D("Book", 0.8, (30, 30, 60, 60), oop_prob=0.1)]
    img = images.draw_detections(rgb, dets, min_width=256)
    assert img.shape == (256, 256, 3)
    assert np.any(np.all(img == palette.WARNING_RGB, axis=2))
    assert np.any(np.all(img == palette.TRACKED_RGB, axis=2))


def test_depth_colormap_blacks_out_invalid_depth():
    depth = np.array([[0.0, 1.0], [np.nan, 4.0]], np.float32)
    img = images.colorize_depth(depth, min_width=2)
    assert img.shape == (2, 2, 3)
    assert tuple(img[0, 0]) == (0, 0, 0) and tuple(img[1, 0]) == (0, 0, 0)
    assert img[0, 1].sum() > img[1, 1].sum()        # near is brighter


# --- the scene's nodes (a real viser server, no browser) ---------------------------------------------

@pytest.fixture
def scene_view():
    import viser
    from tidee.viewer.scene_view import SceneView

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        yield SceneView(server)
    finally:
        server.stop()


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
    texts = [h.text for h in scene_view.labels.handles[:scene_view.labels.shown]]
    assert any("out of place" in t for t in texts)
    shown = scene_view.node_names()
    assert shown["/map/voxels"] and shown["/objects/boxes"] and shown["/agent/camera"] and shown["/search/heatmap"]
    assert not shown["/oracle/boxes"]                                # oracle: off by default
    assert scene_view.heatmap.render_width == pytest.approx(maps.occupancy.shape[0] * maps.cell)


def test_scene_layers_occupancy_only_and_clear(scene_view):
    ep = SyntheticEpisode()
    for kind, msg in ep.messages(300).items():
        scene_view.apply(kind, msg)
    by_class = scene_view.voxels.colors.copy()
    scene_view.set_occupancy_only(True)
    assert not np.array_equal(by_class, scene_view.voxels.colors)
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

    scene = {"start": {"x": 2.0, "y": 3.0, "yaw_deg": 90.0}, "mess": [{"id": "Mug_0"}],
             "objects": [{"id": "Mug_0", "type": "Mug", "pickupable": True, "position": [2.0, 4.0, 0.7],
                          "orientation": [0, 0, 0, 1], "size": [0.1, 0.1, 0.2]},
                         {"id": "Wall_0", "type": "Wall", "pickupable": False, "position": [0, 0, 0],
                          "orientation": [0, 0, 0, 1], "size": [1, 1, 1]}]}
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
            assert wait_until(lambda: seen.update(feed.poll()) or {"status", "maps", "memory", "frame"} <= set(seen), 10.0)
            assert feed.selected == src.session
            assert wait_until(lambda: any(s.alive and s.server_id == src.server_id for s in feed.sessions()), 10.0)
            feed.send(AgentCommand(kind="pause", command_id="c1"))
            acks: list = []
            assert wait_until(lambda: acks.append(feed.poll().get("ack"))
                              or any(a and a.command_id == "c1" for a in acks), 10.0)
            assert src.agent is not None and src.agent.paused
            with pytest.raises(LookupError, match="no server known"):
                feed.fetch_state("nobody")
        finally:
            feed.close()


# --- process hygiene and the command line --------------------------------------------------------------

def test_viewer_imports_neither_torch_nor_the_agent():
    code = ("import sys; import tidee.viewer.app, tidee.viewer.cli, tidee.viewer.bench, tidee.viewer.browser, "
            "tidee.viewer.synthetic; bad = [m for m in sys.modules if m == 'torch' or m.startswith('torch.') "
            "or m.startswith('tidee.agent')]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=60)


def test_cli_registers_the_viewer_without_importing_viser():
    code = ("import sys, argparse; from tidee.viewer.cli import register; p = argparse.ArgumentParser(); "
            "register(p.add_subparsers()); a = p.parse_args(['viewer', '--port', '0', '--session', 's1']); "
            "assert a.port == 0 and a.session == 's1' and a.host == '127.0.0.1'; assert 'viser' not in sys.modules")
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
    scene_view.apply_maps(dataclasses.replace(maps, point_labels=maps.point_labels[:3]))   # labels too short
    assert scene_view.voxels.colors.shape == scene_view.voxels.points.shape
    empty = dataclasses.replace(maps, occupancy=np.zeros((0, 0), np.uint8), explored=np.zeros((0, 0), bool),
                                points=np.zeros((0, 3), np.float32), point_labels=np.zeros(0, np.int16))
    scene_view.apply_maps(empty)
    assert not scene_view.voxels.visible
