"""``tidee eval search`` (Table 2): arguments, validation, scoring summary and one short episode."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from tidee.agent.reasoning.search import eval as se
from tidee.agent.reasoning.search.commands import register
from tidee.agent.reasoning.search.config import SearchEvalConfig
from tidee.options import from_args


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tidee")
    sub = p.add_subparsers(dest="group", required=True)
    register(
        *(sub.add_parser(g).add_subparsers(dest="what", required=True) for g in ("gen", "train", "eval"))
    )
    return p


def config_from_args(args: argparse.Namespace) -> SearchEvalConfig:
    return from_args(SearchEvalConfig, args)


def test_cli_parses_the_table_2_run():
    args = _parser().parse_args(
        [
            "eval",
            "search",
            "--split",
            "test",
            "--out",
            "x",
            "--categories-per-room",
            "3",
            "--methods",
            "frontier,network",
            "--workers",
            "2",
        ]
    )
    cfg = config_from_args(args)
    assert cfg.split == "test" and cfg.methods == ("frontier", "network") and cfg.categories_per_room == 3
    assert cfg.max_steps == 200 and cfg.radius == 1.5 and cfg.perception == "learned"
    assert (
        config_from_args(
            _parser().parse_args(["eval", "search", "--out", "x", "--categories-per-room", "0"])
        ).categories_per_room
        is None
    )


def test_gen_and_train_commands_build_their_configs_from_the_flags():
    from tidee.agent.reasoning.search.config import SearchGenConfig, SearchTrainCommand, SearchTrainConfig
    from tidee.options import to_argv

    argv = ["--perception", "learned", "--rooms-per-type", "13", "--messes", "1", "--out", "d"]
    cfg = from_args(SearchGenConfig, _parser().parse_args(["gen", "search", *argv]))
    assert cfg == SearchGenConfig(out="d", rooms_per_type=13, messes_per_room=1, perception="learned")
    assert (cfg.snapshots, cfg.workers, cfg.split) == (6, 2, "train")
    assert from_args(SearchGenConfig, _parser().parse_args(["gen", "search", *to_argv(cfg)])) == cfg
    args = _parser().parse_args(["train", "search", "--data", "d", "--steps", "3", "--no-resume"])
    cmd = from_args(SearchTrainCommand, args)
    assert cmd == SearchTrainCommand(SearchTrainConfig(data="d", steps=3), resume=False)
    assert to_argv(cmd) == ["--data", "d", "--steps", "3", "--no-resume"]


@pytest.mark.parametrize(
    "argv",
    [
        ["--split", "train"],  # training rooms would measure memorisation
        ["--methods", "network,random"],
        ["--categories-per-room", "-1"],
        ["--categories-per-room", "two"],
        ["--workers", "0"],
        [],  # --out is required
    ],
)
def test_cli_refuses_bad_input(argv, capsys):
    base = [] if argv == [] else ["--out", "x"]
    with pytest.raises(SystemExit):
        _parser().parse_args(["eval", "search", *base, *argv])
    assert "error" in capsys.readouterr().err


def test_config_validation_says_what_is_wrong():
    with pytest.raises(ValueError, match="held-out"):
        SearchEvalConfig(out="x", split="train")
    with pytest.raises(ValueError, match="radius"):
        SearchEvalConfig(out="x", radius=0)
    with pytest.raises(ValueError, match="methods"):
        SearchEvalConfig(out="x", methods=("bogus",))


def test_summary_counts_failures_as_max_steps():
    recs = [
        {"method": "network", "success": True, "stopped": True, "steps": 40, "steps_scored": 40},
        {"method": "network", "success": False, "stopped": False, "steps": 199, "steps_scored": 200},
        {"method": "frontier", "success": False, "stopped": True, "steps": 80, "steps_scored": 200},
    ]
    s = se.summarize(recs, ("network", "frontier"))
    assert s["network"] == {
        "episodes": 2,
        "successes": 1,
        "success_pct": 50.0,
        "mean_steps_all": 120.0,
        "mean_steps_successes": 40.0,
        "stopped_pct": 50.0,
        "detected_pct": 0.0,
        "goal_sources": {},
    }
    assert s["frontier"]["success_pct"] == 0.0 and s["frontier"]["mean_steps_successes"] is None


def test_jobs_sample_categories_present_in_test_rooms():
    cfg = SearchEvalConfig(out="x", rooms=2, categories_per_room=2, methods=("frontier",))
    jobs = se.episodes(cfg)
    assert len(jobs) == 4 and {(j["room_type"], j["seed"]) for j in jobs} == {
        ("Kitchen", 200),
        ("Kitchen", 201),
    }
    assert jobs == se.episodes(cfg)  # seeded


@pytest.mark.slow
def test_one_short_search_episode(tmp_path):
    cfg = SearchEvalConfig(
        out=str(tmp_path),
        rooms=1,
        categories_per_room=1,
        methods=("frontier",),
        perception="oracle",
        max_steps=40,
        workers=1,
        examples=0,
    )
    res = se.run_search_eval(cfg, command="test", progress=False)
    assert res["summary"]["frontier"]["episodes"] == 1
    assert (tmp_path / "search.md").exists() and (tmp_path / "search.json").exists()


def test_a_tracked_object_placed_in_the_frame_from_the_map():
    from types import SimpleNamespace

    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.policy.search import _in_frame_unoccluded

    # camera 1.5 m up looking along +x (optical axes: x right = -y, y down = -z, z forward = +x)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = (0.0, 0.0, 1.5)
    k = np.array([[128.0, 0.0, 128.0], [0.0, 128.0, 128.0], [0.0, 0.0, 1.0]])

    def body(depth: float, detections=()):
        obs = SimpleNamespace(depth=np.full((256, 256), depth, np.float32), intrinsics=k, camera_pose=pose)
        return SimpleNamespace(obs=obs, detections=list(detections))

    def obj(x, y, z=1.5):
        c = np.array([x, y, z])
        return TrackedObject(0, "Candle", 0.5, c, c - 0.05, c + 0.05)

    assert _in_frame_unoccluded(body(3.0), obj(1.0, 0.0))  # ahead, 1 m, nothing in front
    assert not _in_frame_unoccluded(body(0.5), obj(1.0, 0.0))  # something 0.5 m in front of it
    assert not _in_frame_unoccluded(body(3.0), obj(2.0, 0.0))  # out of reach
    assert not _in_frame_unoccluded(body(3.0), obj(1.0, 1.0))  # at the image edge (45 degrees left)
    assert not _in_frame_unoccluded(body(3.0), obj(-1.0, 0.0))  # behind the camera

    # Picking at the projected centroid (the tidy policy) also needs the ray to meet the object:
    # the wall 3 m behind it is not the object; a surface at the centroid's depth is.
    from tidee.agent.policy.skills import projected_sighting

    assert projected_sighting(body(3.0), obj(1.0, 0.0)) is None
    s = projected_sighting(body(1.05), obj(1.0, 0.0))
    assert s is not None and s.detection is None and (s.u, s.v) == (128, 128)
    assert abs(s.distance - 1.05) < 1e-3 and abs(s.point[0] - 1.05) < 1e-3
    # up close the detector sees another small thing there: the track was a confusion, no pick;
    # a receptacle under it (the table the candle stands on) or a candle detection is no objection
    from tidee.agent.perception.base import Detection

    other = Detection("TennisRacket", 0.6, (100, 100, 160, 160))
    table = Detection("DiningTable", 0.9, (0, 100, 256, 256))
    candle = Detection("Candle", 0.4, (120, 120, 140, 140))
    assert projected_sighting(body(1.05, [other]), obj(1.0, 0.0)) is None
    assert projected_sighting(body(1.05, [table, candle]), obj(1.0, 0.0)) is not None
    off = Detection("TennisRacket", 0.6, (0, 0, 40, 40))  # elsewhere in the frame
    assert projected_sighting(body(1.05, [off]), obj(1.0, 0.0)) is not None


def _still_body(x: float = 0.0, y: float = 0.0, detections=()):
    """A body whose pose never changes (what a move that cannot happen looks like)."""
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.mapping.maps import MapConfig, SemanticMapper
    from tidee.agent.policy.skills import Body

    obs = SimpleNamespace(step=4, agent_pose=(x, y, 0.0, 0.0), steps_left=500, success=True, error="")
    return Body(SemanticMapper(MapConfig(), CLASSES), obs=obs, detections=list(detections))


def _drain(skill):
    """Run a skill whose body never changes to its end: (the actions it yielded, its result)."""
    actions = []
    try:
        while True:
            actions.append(next(skill))
    except StopIteration as done:
        return actions, done.value


def test_a_start_hemmed_in_by_the_map_still_plans():
    """The agent between a bed and a dresser: their cells 0.2 m away, dilated by the 0.2 m agent
    radius, cover every cell around it. The planner steps down to half the radius there."""
    from tidee.agent.navigation.fmm import FMMPlanner
    from tidee.agent.policy.skills import AGENT_RADIUS, TRAPPED_CELLS, planner_from

    body = _still_body()
    m = body.mapper
    for y in np.arange(-1.0, 1.0, 0.02):  # a bed edge 0.2 m ahead and a dresser 0.2 m behind
        m.stamp_obstacle((0.2, y), radius=0.03)
        m.stamp_obstacle((-0.2, y), radius=0.03)
    m.stood[m.grid.to_cell((0.0, 0.0))] = True
    plain = FMMPlanner(m.traversible(AGENT_RADIUS), m.grid).reachable_from((0.0, 0.0))
    assert plain.sum() < TRAPPED_CELLS
    reach = planner_from(body).reachable_from((0.0, 0.0))
    assert reach.sum() > 100 and reach[m.grid.to_cell((0.0, 0.8))]  # along the corridor between them
    # with room around it the agent keeps the full radius
    free = _still_body()
    assert np.array_equal(planner_from(free).traversible, free.mapper.traversible(AGENT_RADIUS))


def test_a_start_with_no_lattice_move_steps_down_to_half_the_radius():
    """Four things 0.42 m from the agent along +-x and +-y (an object it just dropped in front
    of it, a sofa, a wall): dilated by the agent radius, each blocks the 0.25 m move towards
    it, while the room stays reachable diagonally, which no move can follow. On the full-radius
    map the walk turned on the spot and gave up; on half the radius it moves."""
    from tidee.agent.navigation.fmm import FMMPlanner
    from tidee.agent.policy.skills import AGENT_RADIUS, TRAPPED_CELLS, can_step, navigate, planner_from
    from tidee.protocol.messages import ActionName

    body = _still_body()
    m = body.mapper
    for q in ((0.42, 0.0), (-0.42, 0.0), (0.0, 0.42), (0.0, -0.42)):
        m.stamp_obstacle(q, radius=0.03)
    m.stood[m.grid.to_cell((0.0, 0.0))] = True
    full = FMMPlanner(m.traversible(AGENT_RADIUS), m.grid)
    assert full.reachable_from((0.0, 0.0)).sum() >= TRAPPED_CELLS and not can_step(full, (0.0, 0.0))
    planner = planner_from(body)
    assert can_step(planner, (0.0, 0.0))
    assert np.array_equal(planner.traversible, m.traversible(AGENT_RADIUS / 2))
    actions, _ = _drain(navigate(body, goal_xy=(1.5, 0.0), budget=6))
    assert actions and actions[0].name == ActionName.MoveAhead
    # a free start keeps the full radius
    free = _still_body()
    assert can_step(planner_from(free), (0.0, 0.0))


def test_a_second_pick_aims_at_what_stands_over_the_track():
    """A pick that hit the floor beside a mug retries at the mug, what rises over the track's
    footprint; a track with nothing standing there (bare floor) gets no second pixel, nor does
    one whose chosen point a detection of another pickupable class covers."""
    from types import SimpleNamespace

    from tidee.agent.mapping.geometry import unproject
    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.perception.base import Detection
    from tidee.agent.policy.skills import raised_sighting

    pose = np.eye(4)  # camera 1 m up looking straight down (image right = -y, image down = -x)
    pose[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    pose[:3, 3] = (0.0, 0.0, 1.0)
    k = np.array([[128.0, 0.0, 128.0], [0.0, 128.0, 128.0], [0.0, 0.0, 1.0]])
    floor = np.full((256, 256), 1.0, np.float32)
    mug = floor.copy()
    mug[150:160, 150:160] = 0.9  # 10 cm tall, a few centimetres off the centroid
    pts, _ = unproject(mug, k, pose, mask=np.pad(np.ones((10, 10), bool), ((150, 96), (150, 96))))
    c = pts.mean(0)
    track = TrackedObject(
        0,
        "Mug",
        0.5,
        np.array([c[0] + 0.04, c[1] - 0.03, 0.05]),
        np.array([c[0] - 0.01, c[1] - 0.08, 0.0]),
        np.array([c[0] + 0.09, c[1] + 0.02, 0.1]),
    )

    def body(depth, detections=()):
        obs = SimpleNamespace(depth=depth, intrinsics=k, camera_pose=pose)
        return SimpleNamespace(obs=obs, detections=list(detections))

    s = raised_sighting(body(mug), track)
    assert s is not None and 150 <= s.u < 160 and 150 <= s.v < 160
    assert abs(s.point[2] - 0.1) < 1e-3 and s.detection is None
    assert raised_sighting(body(floor), track) is None
    bowl = Detection("Bowl", 0.7, (145, 145, 165, 165))
    assert raised_sighting(body(mug, [bowl]), track) is None
    assert raised_sighting(body(mug, [Detection("Mug", 0.7, (145, 145, 165, 165))]), track) is not None


def test_a_second_pick_aims_at_a_flat_thing_not_at_the_stool_beside_it():
    """A spoon lying flat (6 mm high) with a stool's leg 40 cm tall inside the track's grown
    footprint: the retry aims at the spoon, not at the highest point there (the stool), and a
    spoon too flat to rise 4 mm above the floor gets no second pixel."""
    from types import SimpleNamespace

    from tidee.agent.mapping.geometry import unproject
    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.policy.skills import raised_sighting

    pose = np.eye(4)  # camera 1 m up looking straight down
    pose[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    pose[:3, 3] = (0.0, 0.0, 1.0)
    k = np.array([[128.0, 0.0, 128.0], [0.0, 128.0, 128.0], [0.0, 0.0, 1.0]])
    floor = np.full((256, 256), 1.0, np.float32)
    spoon = floor.copy()
    spoon[150:153, 140:160] = 0.994  # 6 mm high, 15 cm long
    pts, _ = unproject(spoon, k, pose, mask=np.pad(np.ones((3, 20), bool), ((150, 103), (140, 96))))
    lo, hi = pts.min(0), pts.max(0)
    track = TrackedObject(0, "Spoon", 0.5, pts.mean(0), lo, hi)
    stool = spoon.copy()
    stool[156:160, 150:154] = 0.6  # a leg 3 cm from the spoon

    def body(depth):
        return SimpleNamespace(
            obs=SimpleNamespace(depth=depth, intrinsics=k, camera_pose=pose), detections=[]
        )

    s = raised_sighting(body(stool), track)
    assert s is not None and 150 <= s.v < 153 and 140 <= s.u < 160
    assert abs(s.point[2] - 0.006) < 1e-3
    flat = floor.copy()
    flat[150:153, 140:160] = 0.998  # a card 2 mm thick: nothing rises enough to aim at
    assert raised_sighting(body(flat), track) is None


def test_a_detection_of_the_category_counts_only_within_the_stop_radius():
    """Stop needs an instance near the agent: a detection of the label whose near side is 2.5 m
    away (the real TV stand across the room while the track that brought the agent here was
    mislocated) does not verify; the same detection 1 m away does."""
    from types import SimpleNamespace

    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.perception.base import Detection
    from tidee.agent.policy.search import _in_view

    pose = np.eye(4)  # camera 1.5 m up at the origin looking along +x, as above
    pose[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = (0.0, 0.0, 1.5)
    k = np.array([[128.0, 0.0, 128.0], [0.0, 128.0, 128.0], [0.0, 0.0, 1.0]])
    stand = TrackedObject(
        0, "TVStand", 0.5, np.array([1.0, 0.0, 0.4]), np.array([0.8, -0.3, 0.0]), np.array([1.2, 0.3, 0.8])
    )

    def body(depth: float, detections):
        obs = SimpleNamespace(depth=np.full((256, 256), depth, np.float32), intrinsics=k, camera_pose=pose)
        return SimpleNamespace(obs=obs, detections=list(detections), xy=np.zeros(2))

    seen = Detection("TVStand", 0.5, (100, 100, 156, 156))
    assert _in_view(body(1.0, [seen]), stand)
    assert not _in_view(body(2.5, [seen]), stand)
    assert not _in_view(body(1.0, [Detection("Television", 0.9, (100, 100, 156, 156))]), stand)
    assert not _in_view(body(1.0, []), stand)


def test_a_detection_from_across_the_room_is_not_stopping_near_it():
    """If the walk to the object cannot happen (the agent stays 1.6 m away), seeing its class
    in the frame must not count as found: the attempt verifies nothing and the approach fails."""
    from tidee.agent.mapping.memory import TrackedObject
    from tidee.agent.perception.base import Detection
    from tidee.agent.policy.search import approach_and_verify
    from tidee.agent.policy.skills import footprint_gap

    bell = TrackedObject(
        0,
        "Dumbbell",
        0.5,
        np.array([0.9, -1.45, 0.06]),
        np.array([0.77, -1.59, 0.01]),
        np.array([1.04, -1.34, 0.11]),
    )
    assert footprint_gap(bell.box_min, bell.box_max, 0.0, 0.0) == pytest.approx(np.hypot(0.77, 1.34))
    assert footprint_gap(bell.box_min, bell.box_max, 0.9, -1.4) == 0.0
    body = _still_body(detections=[Detection("Dumbbell", 0.49, (10, 200, 30, 220))])
    actions, found = _drain(approach_and_verify(body, bell, radius=1.0, budget=5))
    assert found is False
    assert actions and all(a.name.value in ("MoveAhead", "RotateLeft", "RotateRight") for a in actions)


def test_a_walk_whose_plans_alternate_gives_up_on_the_spot(monkeypatch):
    """Plans that make "progress" but disagree from one step to the next (turn right, turn
    left, ...: a committed plan is lost when the map is rebuilt) used to spend the whole
    budget on the spot; a walk now gives up after ``ON_THE_SPOT`` actions without a move."""
    from tidee.agent.navigation.fmm import NavStatus
    from tidee.agent.policy import skills
    from tidee.protocol.messages import ActionName

    class Alternating:
        status = NavStatus.progress
        calls = 0

        def set_goal(self, *a, **k):
            return True

        def next_action(self, *a, **k):
            Alternating.calls += 1
            return ActionName.RotateLeft if Alternating.calls % 2 else ActionName.RotateRight

        def path(self, *a, **k):
            return np.zeros((1, 2))

    monkeypatch.setattr(skills, "planner_from", lambda body: Alternating())
    actions, arrived = _drain(skills.navigate(_still_body(), goal_xy=(2.0, 0.0), budget=60))
    assert arrived is False and len(actions) == skills.ON_THE_SPOT


def test_a_stuck_walk_gives_up_after_a_full_turn(monkeypatch):
    """A planner that finds no move lowering the distance, at the agent radius and at half of
    it, turns towards downhill; turning on the spot for longer than a full turn is a walk that
    cannot happen (it used to burn the step budget turning left, right, left ... until the
    episode's cap)."""
    from tidee.agent.navigation.fmm import NavStatus
    from tidee.agent.policy import skills
    from tidee.protocol.messages import ActionName

    class Stuck:
        status = NavStatus.stuck

        def set_goal(self, *a, **k):
            return True

        def next_action(self, *a, **k):
            return ActionName.RotateLeft

        def path(self, *a, **k):
            return np.zeros((1, 2))

    monkeypatch.setattr(skills, "planner_from", lambda body: Stuck())
    monkeypatch.setattr(skills, "FMMPlanner", lambda *a, **k: Stuck())
    actions, arrived = _drain(skills.navigate(_still_body(), goal_xy=(2.0, 0.0), budget=60))
    assert arrived is False and len(actions) == skills.STUCK_TURNS


def test_goal_sources_are_shares_of_the_goals_walked_to():
    recs = [
        {
            "method": "network",
            "success": True,
            "stopped": True,
            "steps": 40,
            "steps_scored": 40,
            "goals": {"proposed": 3, "fallback": 1},
        },
        {
            "method": "network",
            "success": False,
            "stopped": False,
            "steps": 199,
            "steps_scored": 200,
            "goals": {"proposed": 2, "random": 2, "fallback": 2},
        },
    ]
    assert se.summarize(recs, ("network",))["network"]["goal_sources"] == {
        "fallback": 30.0,
        "proposed": 50.0,
        "random": 20.0,
    }
    with pytest.raises(ValueError, match="network-fallback"):
        SearchEvalConfig(out="x", network_fallback="nearest")
    args = _parser().parse_args(["eval", "search", "--out", "x", "--network-fallback", "frontier"])
    assert config_from_args(args).network_fallback == "frontier"


def test_search_walks_to_the_fallback_once_the_proposer_has_nothing(monkeypatch):
    """The network's search points first; when none is left unvisited, the fallback proposer's
    (e.g. the nearest frontier), and only when that has none either a random reachable point."""
    from tidee.agent.policy import search
    from tidee.protocol.messages import Action, ActionName

    walked: list[tuple[float, float]] = []

    def fake_navigate(body, goal_xy=None, **kw):
        walked.append(tuple(goal_xy))
        yield Action(ActionName.MoveAhead)

    def no_look(body, **kw):
        return
        yield

    monkeypatch.setattr(search, "navigate", fake_navigate)
    monkeypatch.setattr(search, "look_around", no_look)
    network_points = [
        [(2.0, 0.0)],
        [(2.0, 0.0)],
        [(2.0, 0.0), (0.0, 2.0)],
    ]  # the second call: only a visited point

    def propose(body, label, visited):
        return network_points.pop(0) if network_points else []

    def frontier(body, label, visited):
        return [(-2.0 - 1.5 * len(visited), 0.0)]

    counts: dict[str, int] = {}
    skill = search.search_object(
        _still_body(), "Mug", propose, np.random.default_rng(0), fallback=frontier, counts=counts
    )
    for _ in range(5):
        next(skill)
    skill.close()
    assert walked == [(2.0, 0.0), (-3.5, 0.0), (0.0, 2.0), (-6.5, 0.0), (-8.0, 0.0)]
    assert counts == {"proposed": 2, "fallback": 3}
