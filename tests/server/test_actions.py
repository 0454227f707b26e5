"""Each action's semantics and failure reasons, in a hand-built room with known geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.support.fixtures import counter_room, make_object, project, spec, table_room, table_top
from tidee.protocol.messages import Action
from tidee.protocol.messages import ActionName as A
from tidee.server.episode import Episode


@pytest.fixture()
def ep():
    e = Episode(renderer="tiny")
    yield e
    e.close()


def at_table(ep: Episode):
    """Agent 1.0 m south of the table centre, facing north (+y), looking down 30 deg."""
    ep.load(table_room(), spec(), (2.0, 0.6), yaw_deg=90)
    return ep.step(Action(A.LookDown))


def test_observation_shapes_and_intrinsics(ep):
    obs = ep.load(table_room(), spec(96), (2.0, 1.0), yaw_deg=90)
    assert obs.rgb.shape == (96, 96, 3) and obs.rgb.dtype == np.uint8
    assert obs.depth.shape == (96, 96) and obs.depth.dtype == np.float32
    assert obs.intrinsics[0, 0] == pytest.approx(48.0)  # 90 deg FOV: f = W / 2
    assert obs.ground_truth is None  # privileged data only on request
    np.testing.assert_allclose(obs.agent_pose, (0, 0, 0, 0), atol=1e-9)


def test_depth_matches_known_geometry(ep):
    # Facing the south wall (inner face at y = 0) from y = 1.0: centre pixel depth 1.0 m.
    obs = ep.load(table_room(), spec(64), (1.0, 1.0), yaw_deg=-90)
    assert obs.depth[31:33, 31:33].mean() == pytest.approx(1.0, abs=0.02)


def test_moves_turns_and_looks(ep):
    ep.load(table_room(), spec(), (1.0, 1.0), yaw_deg=0)
    obs = ep.step(Action(A.MoveAhead))
    assert obs.success and obs.agent_pose[0] == pytest.approx(0.25)
    obs = ep.step(Action(A.MoveLeft))
    assert obs.success and obs.agent_pose[1] == pytest.approx(0.25)
    obs = ep.step(Action(A.RotateLeft))
    assert obs.agent_pose[2] == pytest.approx(90)
    obs = ep.step(Action(A.LookUp))
    assert obs.success and obs.agent_pose[3] == pytest.approx(-30)
    obs = ep.step(Action(A.LookUp))
    assert not obs.success and obs.error == "look_limit"
    for _ in range(3):
        obs = ep.step(Action(A.LookDown))
    assert obs.success and obs.agent_pose[3] == pytest.approx(60)
    assert ep.step(Action(A.LookDown)).error == "look_limit"


def test_acting_without_a_render_leaves_the_state_a_step_leaves(ep):
    # data generation walks with Episode.act and renders only the frames it keeps (Episode.observe)
    walk = [
        A.MoveAhead,
        A.RotateLeft,
        A.LookDown,
        A.MoveAhead,
        A.MoveAhead,
        A.LookUp,
        A.LookUp,
        A.LookUp,
        A.MoveRight,
    ]
    ep.load(table_room(), spec(64), (1.0, 1.0), yaw_deg=0)
    stepped = [ep.step(Action(a)) for a in walk]
    other = Episode(renderer="tiny")
    try:
        other.load(table_room(), spec(64), (1.0, 1.0), yaw_deg=0)
        outcomes = [other.act(Action(a)) for a in walk]
        seen = other.observe()
        assert [(o.success, o.error, o.message) for o in stepped] == [
            (ok, err.value if err else None, msg) for ok, err, msg in outcomes
        ]
        assert not outcomes[-2][0]  # the third LookUp is refused at the limit
        assert other.pitch == stepped[-1].agent_pose[3] == pytest.approx(-30.0)
        np.testing.assert_array_equal(seen.rgb, stepped[-1].rgb)
        np.testing.assert_array_equal(seen.depth, stepped[-1].depth)
        assert seen.agent_pose == stepped[-1].agent_pose and seen.last_action == "MoveRight" and seen.success
    finally:
        other.close()


def test_move_into_wall_is_blocked(ep):
    ep.load(table_room(), spec(), (0.3, 1.0), yaw_deg=180)  # facing the west wall, 0.3 m away
    obs = ep.step(Action(A.MoveAhead))
    assert not obs.success and obs.error == "blocked"
    assert obs.agent_pose[0] == pytest.approx(0.0)


def test_pickup_and_put_on_table(ep):
    obs = at_table(ep)
    mug = ep.world.bodies["Mug_0"].obj
    x, y = project(ep, obs, np.array(mug.position) + [0, 0, mug.size[2] / 2])
    assert ep.step(Action(A.PutObject, x, y)).error == "hands_empty"
    obs = ep.step(Action(A.PickupObject, x, y))
    assert obs.success, obs.message
    assert obs.held == "Mug" and obs.held_id == "Mug_0"
    obs = ep.step(Action(A.PickupObject, x, y))
    assert obs.error == "hands_full"
    table = ep.world.bodies["DiningTable_0"].obj
    tx, ty = project(ep, obs, np.array([2.3, 1.9, table_top(table)]))
    obs = ep.step(Action(A.PutObject, tx, ty))
    assert obs.success, obs.message
    assert obs.held is None
    state = {o["id"]: o for o in ep.object_states()}
    assert state["Mug_0"]["parent"] == "DiningTable_0"
    assert abs(state["Mug_0"]["position"][0] - 2.3) < 0.2


@pytest.mark.parametrize("held", ["Mug", "Laptop"])
@pytest.mark.parametrize("nudge", [False, True])
def test_a_put_aimed_a_centimetre_into_a_neighbour_is_nudged_not_sent_down_the_lattice(ep, nudge, held):
    """A flat, wide thing (a laptop's 2 cm base) as well as a tall, narrow one: the spot
    tried before stands in the next spot's rays unless it is cleared away first."""
    scene = table_room()
    table = next(o for o in scene.objects if o.id == "DiningTable_0")
    book = make_object("Book_0", "Book", (2.3, 2.0), z=table_top(table), parent="DiningTable_0")
    thing = make_object(f"{held}_0", held, (1.9, 1.9), z=table_top(table), parent="DiningTable_0")
    objects = [o for o in scene.objects if o.id != "Mug_0"] + [book, thing]
    obs = ep.load(dataclasses.replace(scene, objects=objects), spec(), (2.0, 0.6), yaw_deg=90)
    obs = ep.step(Action(A.LookDown))
    obj = ep.world.bodies[thing.id].obj
    assert ep.step(Action(A.PickupObject, *project(ep, obs, np.array(obj.position) + [0, 0, 0.015]))).success
    # Its box would overlap the book's by 1 cm along x.
    aim = np.array([2.3 - (obj.size[0] + book.size[0]) / 2 + 0.01, 2.0, table_top(table)])
    assert ep.world.place(thing.id, "DiningTable_0", aim, yaw=0.0, nudge=nudge)
    off = float(np.linalg.norm(np.array(ep.world.pose(thing.id)[0][:2]) - aim[:2]))
    if nudge:  # the first free shift: 1 cm, or 2 where a box's edge touching the book's counts
        assert off == pytest.approx(0.01, abs=0.005) or off == pytest.approx(0.02, abs=0.005)
    else:  # the nearest free point of the 6 cm lattice
        assert off > 0.04
    assert "Book_0" not in ep.world.collides(thing.id)
    assert ep.world.bodies[thing.id].obj.parent == "DiningTable_0"


def _yaw_deg(ep: Episode, oid: str) -> float:
    _, q = ep.world.pose(oid)
    return float(np.degrees(np.arctan2(2 * (q[3] * q[2] + q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))))


def _turn(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("turn", [None, 0.0, 35.0, -120.0])
def test_put_turns_the_held_object_by_the_yaw_asked_from_how_it_lay(ep, turn):
    obs = at_table(ep)
    mug = ep.world.bodies["Mug_0"].obj
    x, y = project(ep, obs, np.array(mug.position) + [0, 0, mug.size[2] / 2])
    lay = _yaw_deg(ep, "Mug_0")
    assert ep.step(Action(A.PickupObject, x, y)).success
    ep.step(Action(A.RotateLeft))  # the held mug turns with the agent: +90
    ep.step(Action(A.RotateRight))
    ep.step(Action(A.RotateRight))  # and back, then -90: the agent faces east (0 deg)
    obs = ep.step(Action(A.RotateLeft))  # north again, as at pick-up
    table = ep.world.bodies["DiningTable_0"].obj
    tx, ty = project(ep, obs, np.array([2.3, 1.9, table_top(table)]))
    obs = ep.step(Action(A.PutObject, tx, ty, yaw=turn))
    assert obs.success, obs.message
    want = 90.0 if turn is None else lay + turn  # None: along the agent's heading (north)
    assert abs(_turn(_yaw_deg(ep, "Mug_0"), want)) < 2.0


def test_a_turned_agent_turns_what_it_holds(ep):
    obs = at_table(ep)  # facing north, south of the table
    mug = ep.world.bodies["Mug_0"].obj
    x, y = project(ep, obs, np.array(mug.position) + [0, 0, mug.size[2] / 2])
    lay = _yaw_deg(ep, "Mug_0")
    assert ep.step(Action(A.PickupObject, x, y)).success
    walk = [A.RotateLeft] + [A.MoveAhead] * 6 + [A.RotateRight] + [A.MoveAhead] * 6 + [A.RotateRight]
    for a in walk:  # west of the table, facing east: turned -90 since the pick
        obs = ep.step(Action(a))
        assert obs.success, (a, obs.message)
    table = ep.world.bodies["DiningTable_0"].obj
    tx, ty = project(ep, obs, np.array([1.8, 2.0, table_top(table)]))
    obs = ep.step(Action(A.PutObject, tx, ty, yaw=10.0))
    assert obs.success, obs.message
    assert abs(_turn(_yaw_deg(ep, "Mug_0"), lay - 90.0 + 10.0)) < 2.0


def holding_mug_at_counter(ep: Episode):
    """In front of the counter (1.0 m south of its back half), facing it, looking down 30 deg,
    holding the mug; the counter top is at the camera's height."""
    ep.load(counter_room(), spec(), (2.0, 2.7), yaw_deg=90)
    obs = ep.step(Action(A.LookDown))
    mug = ep.world.bodies["Mug_0"].obj
    assert ep.step(Action(A.PickupObject, *project(ep, obs, np.array(mug.position) + [0, 0, 0.05]))).success
    return obs, table_top(ep.world.bodies["CounterTop_0"].obj)


def test_a_put_with_a_reach_lands_where_a_counter_seen_edge_on_hides_the_spot(ep):
    obs, top = holding_mug_at_counter(ep)
    goal = np.array([2.2, 3.75, top])  # near the back of the counter
    obs = ep.step(Action(A.PutObject, *project(ep, obs, goal)))
    assert obs.success, obs.message  # the ray meets the counter's front: the mug lands at its edge
    plain = np.array(ep.world.pose("Mug_0")[0])
    assert goal[1] - plain[1] > 0.2
    x, y = project(ep, obs, plain + [0, 0, 0.05])
    assert ep.step(Action(A.PickupObject, x, y)).success
    point = goal + [0, 0, 0.03]
    eye = np.array([2.0, 2.7, ep.spec.camera_height])
    obs = ep.step(Action(A.PutObject, *project(ep, obs, point), reach=float(np.linalg.norm(point - eye))))
    assert obs.success, obs.message
    assert np.linalg.norm(np.array(ep.world.pose("Mug_0")[0])[:2] - goal[:2]) < 0.02


def test_a_reach_needs_a_clear_way_a_surface_under_it_and_arms_length(ep):
    obs, top = holding_mug_at_counter(ep)
    eye = np.array([2.0, 2.7, ep.spec.camera_height])
    # the counter's front face stands between the eye and a point 10 cm below its top
    low = np.array([2.0, 3.6, top - 0.1])
    obs = ep.step(Action(A.PutObject, *project(ep, obs, low), reach=float(np.linalg.norm(low - eye))))
    assert obs.error == "blocked" and "CounterTop_0 is in the way" in obs.message
    air = np.array([2.0, 3.2, 0.5])  # over the floor in front of the counter, 0.5 m up
    obs = ep.step(Action(A.PutObject, *project(ep, obs, air), reach=float(np.linalg.norm(air - eye))))
    assert obs.error == "nothing_there" and "under that point" in obs.message
    far = np.array([2.0, 3.7, top + 0.03])
    obs = ep.step(Action(A.PutObject, *project(ep, obs, far), reach=1.6))
    assert obs.error == "too_far" and obs.held == "Mug"


def test_a_put_at_a_point_on_a_closed_cabinets_top_lands_there(ep):
    """A closed openable's top is a surface like any other for a put at a point (the goal
    state of a rearrangement holds things there); at a pixel it still asks to be opened."""
    obs, _ = holding_mug_at_counter(ep)
    scene = counter_room()
    counter = next(o for o in scene.objects if o.id == "CounterTop_0")
    scene.objects.remove(counter)
    scene.objects.append(make_object("Cabinet_0", "Cabinet", (2.0, 3.69), yaw_deg=180, size=[0.8, 0.5, 0.9]))
    mug = next(o for o in scene.objects if o.id == "Mug_0")
    mug.position, mug.parent, mug.parent_type = (
        [2.2, 3.69, table_top(scene.objects[-1])],
        "Cabinet_0",
        "Cabinet",
    )
    ep.load(scene, spec(), (2.0, 2.9), yaw_deg=90)
    obs = ep.step(Action(A.LookDown))
    cabinet = ep.world.bodies["Cabinet_0"].obj
    assert cabinet.openable and not cabinet.is_open
    start = np.array(ep.world.pose("Mug_0")[0])
    assert ep.step(Action(A.PickupObject, *project(ep, obs, start + [0, 0, 0.05]))).success
    goal = np.array([1.85, 3.6, table_top(cabinet)])
    obs = ep.step(Action(A.PutObject, *project(ep, obs, goal)))
    assert obs.error == "receptacle_closed", obs.message
    point = goal + [0, 0, 0.05]
    eye = np.array([2.0, 2.9, ep.spec.camera_height])
    obs = ep.step(Action(A.PutObject, *project(ep, obs, point), reach=float(np.linalg.norm(point - eye))))
    assert obs.success, obs.message
    assert np.linalg.norm(np.array(ep.world.pose("Mug_0")[0])[:2] - goal[:2]) < 0.02
    assert not cabinet.is_open and {o["id"]: o for o in ep.object_states()}["Mug_0"]["parent"] == "Cabinet_0"


def test_failure_reasons(ep):
    obs = at_table(ep)
    table = ep.world.bodies["DiningTable_0"].obj
    tx, ty = project(ep, obs, np.array([2.3, 1.75, table_top(table)]))
    assert ep.step(Action(A.PickupObject, tx, ty)).error == "not_pickupable"
    assert ep.step(Action(A.OpenObject, tx, ty)).error == "not_openable"
    # Looking level at the far wall: 3.4 m away.
    ep.step(Action(A.LookUp))
    obs = ep.step(Action(A.PickupObject, 0.5, 0.5))
    assert obs.error == "too_far", obs.message


def test_fridge_open_put_inside_close(ep):
    scene = table_room()
    ep.load(scene, spec(), (2.0, 0.6), yaw_deg=90)
    obs = ep.step(Action(A.LookDown))
    mug = ep.world.bodies["Mug_0"].obj
    mx, my = project(ep, obs, np.array(mug.position) + [0, 0, mug.size[2] / 2])
    assert ep.step(Action(A.PickupObject, mx, my)).success
    # Stand 1 m in front of the fridge (just clear of its swinging door), facing it.
    ep.body.x = ep.body.odo_x = 3.0
    ep.body.y = ep.body.odo_y = 2.1
    ep.body.pitch = 0.0
    obs = ep.step(Action(A.RotateLeft))
    obs = ep.step(Action(A.RotateRight))
    fridge = ep.world.bodies["Fridge_0"].obj
    door = np.array([fridge.position[0], fridge.position[1] - fridge.size[1] / 2, 1.0])
    x, y = project(ep, obs, door)
    obs = ep.step(Action(A.PutObject, x, y))
    assert obs.error == "receptacle_closed", obs.message
    assert ep.step(Action(A.CloseObject, x, y)).error == "already_closed"
    obs = ep.step(Action(A.OpenObject, x, y))
    assert obs.success, obs.message
    # Aim at the front of the lowest-but-one inside shelf.
    shelves = sorted((s for s in ep.world.surfaces_world("Fridge_0") if s[4]), key=lambda s: s[2])
    cxy, half, z, _, _ = shelves[min(1, len(shelves) - 1)]
    inside = np.array([cxy[0], fridge.position[1] - fridge.size[1] / 2 + 0.12, z])
    px, py = project(ep, obs, inside)
    assert ep.step(Action(A.OpenObject, px, py)).error == "already_open"
    obs = ep.step(Action(A.PutObject, px, py))
    assert obs.success, obs.message
    state = {o["id"]: o for o in ep.object_states()}
    assert state["Mug_0"]["parent"] == "Fridge_0"
    obs = ep.step(Action(A.CloseObject, px, py))
    assert obs.success, obs.message
    assert not ep.world.bodies["Fridge_0"].obj.is_open


def test_done_and_step_cap(ep):
    ep.load(table_room(), spec(), (1.0, 1.0), yaw_deg=0)
    obs = ep.step(Action(A.Done))
    assert obs.done and obs.success
    obs = ep.step(Action(A.RotateLeft))
    assert not obs.success and obs.error == "episode_over"
    s = spec()
    s.max_steps = 3
    ep.load(table_room(), s, (1.0, 1.0), yaw_deg=0)
    for _ in range(3):
        obs = ep.step(Action(A.RotateLeft))
    assert obs.done and obs.steps_left == 0


def test_ground_truth_only_on_request(ep):
    obs = at_table(ep)
    assert obs.ground_truth is None
    obs = ep.step(Action(A.RotateLeft), ground_truth=True)
    obs = ep.step(Action(A.RotateRight), ground_truth=True)
    gt = obs.ground_truth
    assert gt is not None and gt.instance_seg.shape == obs.depth.shape
    ids = [gt.objects[k]["id"] for k in np.unique(gt.instance_seg) if k >= 0]
    assert "DiningTable_0" in ids and "Mug_0" in ids


def test_pose_noise_drifts_true_pose_not_odometry():
    e = Episode(renderer="tiny")
    try:
        s = spec()
        s.pose_noise = True
        e.load(table_room(), s, (1.0, 0.6), yaw_deg=0)
        for a in (A.MoveAhead, A.MoveAhead, A.RotateLeft, A.MoveAhead):
            obs = e.step(Action(a))
        assert obs.agent_pose[0] == pytest.approx(0.5) and obs.agent_pose[1] == pytest.approx(0.25)
        true_offset = np.hypot(e.body.x - 1.5, e.body.y - 0.85)
        assert 0 < true_offset < 0.1
    finally:
        e.close()


@pytest.mark.parametrize("renderer", ["tiny"])
def test_a_pixel_acts_on_what_the_render_shows_there(renderer):
    """A knife on the floor, seen from 1 m at eight headings: two or three pixels wide, so a
    ray half a pixel off hits the floor beside it. Every pixel the render shows the knife at
    picks it (the tiny renderer draws half a pixel off the pixel centre; the ray follows)."""
    import math

    from tidee.protocol.messages import EpisodeSpec
    from tidee.server.episode import camera_axes

    e = Episode(renderer=renderer)
    try:
        e.reset(EpisodeSpec(room_type="Kitchen", seed=103, mess_index=0), ground_truth=True)
        knife = e.world.bodies["Knife_0"]
        pos = np.array(e.world.pose("Knife_0")[0])
        assert pos[2] < 0.05  # the mess-up left it on the floor
        hits = total = 0
        for ang in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            b = e.body
            b.x, b.y, b.yaw, b.pitch = pos[0] - math.cos(ang), pos[1] - math.sin(ang), ang, 45.0
            right, down, fwd = camera_axes(b.yaw, b.pitch)
            r = e.spec.resolution
            _, _, seg = e.world.render(e._eye(), fwd, -down, r, segmentation=True)
            pixels = np.argwhere(seg == knife.uid)
            total += len(pixels)
            hits += sum(e._pixel_ray((u + 0.5) / r, (v + 0.5) / r)[0] == "Knife_0" for v, u in pixels)
        assert total > 100 and hits / total >= 0.97, (hits, total)
    finally:
        e.close()


def test_only_a_put_with_a_reach_is_nudged(ep, monkeypatch):
    """A put at a point (``reach``) aims at that point; one at a pixel only at a receptacle."""
    calls = []
    place = type(ep.world).place
    monkeypatch.setattr(
        type(ep.world), "place", lambda self, *a, **k: calls.append(k.get("nudge")) or place(self, *a, **k)
    )
    test_a_put_with_a_reach_lands_where_a_counter_seen_edge_on_hides_the_spot(ep)
    assert calls == [False, True]
