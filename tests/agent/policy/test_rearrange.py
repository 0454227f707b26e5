"""The rearrangement agent's decisions: which objects moved, which openables changed."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from tidee.agent.mapping.geometry import GridSpec
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.policy.rearrange import (
    STEP_UP_M,
    Occupancy,
    Seen,
    _pairs,
    box_change,
    door_evidence,
    find_moves,
    find_toggles,
    match_phases,
    neighbour_at,
    put_turn,
)
from tidee.agent.policy.tidy import Gen


def _track(
    i: int, label: str, xyz: tuple[float, float, float], half: float = 0.05, n_obs: int = 3
) -> TrackedObject:
    c = np.array(xyz, float)
    return TrackedObject(i, label, 0.9, c, c - half, c + half, n_obs=n_obs)


def _seen(
    label: str,
    xyz: tuple[float, float, float],
    half: float = 0.05,
    n_obs: int = 3,
    colour: tuple[float, float, float] | None = None,
) -> Seen:
    s = Seen.of(_track(0, label, xyz, half, n_obs))
    return s if colour is None else dataclasses.replace(s, colour=np.array(colour))


def test_a_moved_object_is_found_and_a_still_one_is_not() -> None:
    then = [_seen("Mug", (1.0, 1.0, 0.9)), _seen("Book", (2.0, 0.0, 0.5))]
    now = [_track(1, "Mug", (3.0, -1.0, 0.0)), _track(2, "Book", (2.1, 0.05, 0.5))]
    moves = find_moves(then, now)
    assert [(m.now.id, m.then.label) for m in moves] == [(1, "Mug")]
    assert np.isclose(moves[0].distance, np.linalg.norm([2.0, -2.0, -0.9]))


def test_two_instances_one_moved_pairs_the_still_one_with_its_old_place() -> None:
    then = [_seen("Pen", (0.0, 0.0, 0.8)), _seen("Pen", (1.0, 0.0, 0.8))]
    now = [_track(1, "Pen", (0.02, 0.0, 0.8)), _track(2, "Pen", (3.0, 2.0, 0.0))]
    moves = find_moves(then, now)
    assert len(moves) == 1 and moves[0].now.id == 2 and np.allclose(moves[0].then.centroid, [1.0, 0.0, 0.8])


def test_tracks_seen_once_and_new_places_held_before_are_not_moves() -> None:
    # seen once in the unshuffle: not trusted
    assert find_moves([_seen("Mug", (0, 0, 0.9))], [_track(1, "Mug", (2, 2, 0.9), n_obs=1)]) == []
    # its new place held a mug in the walkthrough too (a second mug the walkthrough saw there)
    then = [_seen("Mug", (0, 0, 0.9)), _seen("Mug", (2, 2, 0.9), n_obs=1)]
    assert find_moves(then, [_track(1, "Mug", (2, 2, 0.9))]) == []


def test_an_openable_whose_box_grew_was_opened_and_one_that_shrank_was_closed() -> None:
    closed = _seen("Fridge", (1.0, 1.0, 0.9), half=0.4)
    opened = _track(1, "Fridge", (1.2, 1.0, 0.9), half=0.4)
    opened.box_max = opened.box_max + np.array([0.5, 0.0, 0.0])  # the door swung out along +x
    grown, shrunk = box_change(closed, opened)
    assert np.isclose(grown, 0.7) and np.isclose(shrunk, 0.2)
    (t,) = find_toggles([closed], [opened])
    assert t.opened and np.isclose(t.change_m, 0.7)
    (back,) = find_toggles([Seen.of(opened)], [_track(2, "Fridge", (1.0, 1.0, 0.9), half=0.4)])
    assert not back.opened


def test_an_unchanged_openable_and_a_second_track_of_a_toggled_one_are_left_alone() -> None:
    same = find_toggles(
        [_seen("Cabinet", (0, 0, 0.4), half=0.3)], [_track(1, "Cabinet", (0.05, 0, 0.4), half=0.3)]
    )
    assert same == []
    then = [_seen("Fridge", (1.0, 1.0, 0.9), half=0.4), _seen("Fridge", (1.6, 1.0, 0.9), half=0.1)]
    a = _track(1, "Fridge", (1.0, 1.0, 0.9), half=0.4)
    a.box_max = a.box_max + np.array([0.6, 0.0, 0.0])
    b = _track(2, "Fridge", (1.7, 1.0, 0.9), half=0.4)  # the open door, tracked apart
    toggles = find_toggles(then, [a, b])
    assert len(toggles) == 1  # one fridge: toggled once, never back


def test_a_put_turns_the_held_object_onto_its_walkthrough_axis() -> None:
    # picked lying at 10 degrees while the agent faced 90; the agent now faces 180, so the object
    # (turned with it) lies at 100: 70 degrees clockwise takes it to the walkthrough's 30
    assert put_turn(30.0, (10.0, 90.0), 180.0) == -70.0
    assert put_turn(170.0, (10.0, 0.0), 0.0) == -20.0  # the short way round an axis
    assert put_turn(None, (10.0, 0.0), 0.0) is None  # the walkthrough saw no axis
    assert put_turn(30.0, None, 0.0) is None  # nor did the unshuffle


def test_two_moved_instances_go_back_to_the_places_their_colours_say() -> None:
    red, green = (0.8, 0.1, 0.1), (0.2, 0.7, 0.2)
    then = [_seen("Apple", (0.0, 0.0, 0.9), colour=red), _seen("Apple", (2.0, 0.0, 0.9), colour=green)]
    # the red apple now lies nearer the green one's old place, and the other way round
    now = [_track(1, "Apple", (1.6, 1.0, 0.5)), _track(2, "Apple", (0.4, 1.0, 0.5))]
    by_distance = {m.now.id: tuple(m.then.centroid) for m in find_moves(then, now)}
    assert by_distance == {1: (2.0, 0.0, 0.9), 2: (0.0, 0.0, 0.9)}  # a swap
    colours = {1: np.array(red) + 0.05, 2: np.array(green) - 0.05}  # seen a little differently now
    by_look = {m.now.id: tuple(m.then.centroid) for m in find_moves(then, now, colours=colours)}
    assert by_look == {1: (0.0, 0.0, 0.9), 2: (2.0, 0.0, 0.9)}


def test_a_short_move_counts_but_not_one_the_metric_would_call_in_place() -> None:
    # a knife slid 25 cm along the counter (the shuffle moves things at least 30 cm on one receptacle)
    (m,) = find_moves([_seen("Knife", (1.0, 0.0, 0.93))], [_track(1, "Knife", (1.0, 0.25, 0.93))])
    assert np.isclose(m.distance, 0.25)
    # a 90 cm box 20 cm off still overlaps its old box by IoU 0.64: in place, left alone
    big = [_seen("Box", (0.0, 0.0, 0.45), half=0.45)]
    assert find_moves(big, [_track(1, "Box", (0.2, 0.0, 0.45), half=0.45)]) == []
    assert len(find_moves(big, [_track(1, "Box", (0.35, 0.0, 0.45), half=0.45)])) == 1


def test_a_fridge_is_toggled_only_when_its_door_cells_appear_or_vanish() -> None:
    grid = GridSpec((-2.0, -2.0), 0.05, (80, 80))  # 4 x 4 m around the start
    then = [_seen("Fridge", (1.0, 0.0, 0.45), half=0.4)]  # standing on the floor
    now = _track(1, "Fridge", (1.0, 0.0, 0.45), half=0.4)
    now.box_min = now.box_min - np.array([0.0, 0.3, 0.0])  # its box grew 30 cm towards -y
    free = np.zeros(grid.shape, bool)
    seen = np.ones(grid.shape, bool)
    door = np.zeros(grid.shape, bool)
    door[50:66, 29] = True  # 16 cells in front of it (x 0.5-1.3 m, y -0.55 m)

    def toggles(before: np.ndarray, after: np.ndarray):
        return find_toggles(then, [now], maps=(grid, Occupancy(before, seen), Occupancy(after, seen)))

    assert toggles(free, free) == []  # a box that grew, a map that did not change: not toggled
    (t,) = toggles(free, door)
    assert t.opened and t.cells == (16, 0)
    (t,) = toggles(door, free)  # the door's cells vanished: it was closed
    assert not t.opened and t.cells == (0, 16)


def test_the_rearrangement_agent_keeps_nearby_small_objects_apart_in_its_memory() -> None:
    from tidee.agent.classes import CLASSES, PICKUPABLE
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy.rearrange import RearrangePolicy
    from tidee.agent.policy.tidy import TidyPolicy

    base = MapConfig()
    assert TidyPolicy.map_config(base) is base  # the tidy agent maps as configured
    cfg = RearrangePolicy.map_config(base)
    assert cfg.small_merge_distance == 0.25 and base.small_merge_distance is None
    memory = SemanticMapper(cfg, CLASSES, passable=PICKUPABLE).memory
    c = np.array([1.0, 2.0, 0.9])
    first = memory.add_or_merge("Apple", 0.9, c, c - 0.04, c + 0.04, step=0)
    other = memory.add_or_merge("Apple", 0.9, c + [0.4, 0, 0], c - 0.04, c + 0.04, step=0)
    assert other is not first
    shelf = memory.add_or_merge("Shelf", 0.9, c, c - 0.3, c + 0.3, step=0)
    assert memory.add_or_merge("Shelf", 0.9, c + [0.6, 0, 0], c - 0.3, c + 0.3, step=0) is shelf


def test_a_glimpse_nearer_than_a_sure_tracks_match_does_not_take_it() -> None:
    # a mug seen three times at the origin in the walkthrough, a glimpse of a mug at x = 3; now one
    # sure mug at x = 2: nearer the glimpse, but the sure tracks pair first, and that is a move
    then = [_seen("Mug", (0.0, 0.0, 0.9)), _seen("Mug", (3.0, 0.0, 0.9), n_obs=1)]
    now = [_track(1, "Mug", (2.0, 0.0, 0.9))]
    ((s, o, d),) = _pairs(then, now, min_obs=1)  # without the preference: the glimpse takes it
    assert s.n_obs == 1 and np.isclose(d, 1.0)
    ((s, o, d),) = _pairs(then, now, min_obs=2)
    assert s.n_obs == 3 and np.isclose(d, 2.0)
    (m,) = find_moves(then, now)
    assert m.now.id == 1 and np.allclose(m.then.centroid, [0.0, 0.0, 0.9]) and np.isclose(m.distance, 2.0)


def test_glimpses_take_part_in_the_matching_but_never_count_as_moves() -> None:
    # two sure mugs then; now one sure mug at the first's place and a glimpse far from both: the
    # glimpse pairs with the second (the only one left), but a pair with a glimpse is no move
    then = [_seen("Mug", (0.0, 0.0, 0.9)), _seen("Mug", (1.0, 0.0, 0.9))]
    now = [_track(1, "Mug", (0.0, 0.02, 0.9)), _track(2, "Mug", (3.0, 2.0, 0.9), n_obs=1)]
    pairs = {o.id: tuple(s.centroid) for s, o, _ in _pairs(then, now, min_obs=2)}
    assert pairs == {1: (0.0, 0.0, 0.9), 2: (1.0, 0.0, 0.9)}
    assert find_moves(then, now) == []


def test_door_cells_between_two_openables_count_for_the_nearest() -> None:
    grid = GridSpec((0.0, 0.0), 0.05, (60, 40))  # 3 x 2 m
    a = (np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0]))  # footprints 1 m apart along x
    b = (np.array([2.0, 0.0, 0.0]), np.array([3.0, 1.0, 1.0]))
    seen = np.ones(grid.shape, bool)
    free = np.zeros(grid.shape, bool)
    cells = free.copy()
    cells[20:40, 10] = True  # 20 cells at y 0.525, x 1.025 .. 1.975: 10 nearer each footprint
    before, after = Occupancy(free, seen), Occupancy(cells, seen)
    assert door_evidence(grid, before, after, *a) == (18, 0)  # alone: the 18 within 0.9 m of it
    assert door_evidence(grid, before, after, *a, others=[b]) == (10, 0)
    assert door_evidence(grid, before, after, *b, others=[a]) == (10, 0)
    assert door_evidence(grid, after, before, *b, others=[a]) == (0, 10)  # vanished, the same way


def test_a_fridge_door_opening_beside_a_cabinet_toggles_the_fridge_only() -> None:
    grid = GridSpec((-2.0, -2.0), 0.05, (100, 80))
    then = [_seen("Fridge", (1.0, 0.0, 0.45), half=0.4), _seen("Cabinet", (1.75, 0.0, 0.3), half=0.25)]
    fridge = _track(1, "Fridge", (1.0, 0.0, 0.45), half=0.4)
    fridge.box_min = fridge.box_min - np.array([0.0, 0.3, 0.0])  # the door swung out towards -y
    cabinet = _track(2, "Cabinet", (1.75, 0.0, 0.3), half=0.25)
    cabinet.box_min = cabinet.box_min - np.array([0.0, 0.2, 0.0])  # the door's points stretched it too
    seen = np.ones(grid.shape, bool)
    free = np.zeros(grid.shape, bool)
    door = free.copy()
    door[52:68, 29] = True  # 16 cells at y -0.525, x 0.625 .. 1.375: in the fridge's box now
    # all of them lie within 0.9 m of the cabinet too: enough to toggle it were they counted for it
    lo, hi = np.array([1.5, -0.45, 0.05]), np.array([2.0, 0.25, 0.55])
    assert door_evidence(grid, Occupancy(free, seen), Occupancy(door, seen), lo, hi) == (16, 0)
    (t,) = find_toggles(then, [fridge, cabinet], maps=(grid, Occupancy(free, seen), Occupancy(door, seen)))
    assert t.now.label == "Fridge" and t.opened and t.cells == (16, 0)


def test_a_pixel_nearer_another_openable_is_that_ones() -> None:
    cabinet = _track(1, "Cabinet", (0.0, 0.0, 0.4), half=0.3)  # x -0.3 .. 0.3
    fridge = _track(2, "Fridge", (0.75, 0.0, 0.9), half=0.4)  # x 0.35 .. 1.15
    door = _track(3, "Cabinet", (0.2, -0.5, 0.4), half=0.1)  # the cabinet's own door, tracked apart
    mug = _track(4, "Mug", (0.4, 0.0, 0.9))  # not an openable
    tracks = [cabinet, fridge, door, mug]
    assert neighbour_at(np.array([0.6, 0.0, 0.9]), cabinet, tracks) is fridge  # on the fridge
    assert neighbour_at(np.array([0.1, 0.0, 0.6]), cabinet, tracks) is None  # on the cabinet
    assert (
        neighbour_at(np.array([0.32, 0.0, 0.5]), cabinet, tracks) is None
    )  # 2 cm from it, 3 cm from the fridge
    assert neighbour_at(np.array([0.2, -0.5, 0.4]), cabinet, tracks) is None  # its door: the same piece
    assert neighbour_at(np.array([0.1, 0.0, 0.6]), fridge, tracks) is cabinet


def _restore(
    monkeypatch: pytest.MonkeyPatch,
    points: list[np.ndarray],
    replies: list[str | None],
    distances: list[float] | None = None,
    walks: list[dict[str, object]] | None = None,
) -> tuple[list[str], list[str], bool]:
    """Run ``restore_openness`` for a fridge that was opened (its box grew), beside a cabinet,
    with the walk and the turn stubbed out: each look's sighting is at the next of ``points``,
    the next of ``distances`` from the eye (0.8 m when None), and the server answers the
    agent's actions with the next of ``replies`` (None: done). Each walk's keyword arguments
    go to ``walks``. Returns the actions, the events and the skill's result."""
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body, Sighting

    mapper = SemanticMapper(MapConfig(), CLASSES)
    c = np.array([1.0, 0.0, 0.9])
    fridge = mapper.memory.add_or_merge("Fridge", 0.9, c, c - 0.4, c + 0.4, step=0)
    c = np.array([1.7, 0.0, 0.4])
    mapper.memory.add_or_merge("Cabinet", 0.9, c, c - 0.25, c + 0.25, step=0)
    body = Body(mapper)
    body.obs = SimpleNamespace(depth=np.zeros((8, 8)), success=True, error=None)
    events: list[str] = []
    policy = rearrange.RearrangePolicy(
        AgentConfig(), body, None, None, "Kitchen", lambda **kw: events.append(kw["kind"])
    )
    views = iter(points)
    far = iter(distances or [0.8] * len(points))

    def stay(*args: object, **kwargs: object) -> Gen:
        return True
        yield

    def walk(*args: object, **kwargs: object) -> Gen:
        if walks is not None:
            walks.append(kwargs)
        return True
        yield

    monkeypatch.setattr(rearrange, "navigate", walk)
    monkeypatch.setattr(rearrange, "face_point", stay)
    monkeypatch.setattr(
        rearrange, "find_in_view", lambda *a, **k: Sighting(None, 4, 4, next(far), next(views))
    )
    toggle = rearrange.Toggle(fridge, Seen.of(fridge), opened=True, change_m=0.5)
    run, answers, actions = policy.restore_openness(toggle), iter(replies), []
    try:
        action = next(run)
        while True:
            actions.append(action.name.value)
            error = next(answers)
            body.obs = SimpleNamespace(depth=np.zeros((8, 8)), success=error is None, error=error)
            action = run.send(None)
    except StopIteration as stop:
        return actions, events, stop.value


def test_an_openable_already_as_wanted_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    on_fridge = np.array([0.7, -0.4, 0.9])
    actions, events, done = _restore(monkeypatch, [on_fridge], ["already_closed"])
    assert actions == ["CloseObject"] and not done  # no Open to make up for it
    assert events == ["openness_unchanged"]


def test_a_pixel_on_the_neighbour_is_skipped_and_a_blocked_door_retried(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    on_cabinet, on_fridge = np.array([1.6, -0.2, 0.5]), np.array([0.8, -0.4, 1.0])
    actions, events, done = _restore(monkeypatch, [on_cabinet, on_fridge], ["blocked", None, None])
    assert events == ["openness_neighbour", "openness_restored"] and done
    assert actions == ["CloseObject", "MoveBack", "CloseObject"]
    actions, events, done = _restore(monkeypatch, [on_cabinet, on_cabinet], [])
    assert (
        actions == []
        and events == ["openness_neighbour", "openness_neighbour", "openness_failed"]
        and not done
    )


def test_an_openable_in_view_beyond_reach_is_walked_up_to(monkeypatch: pytest.MonkeyPatch) -> None:
    # the walk to the fridge's box ends by its open door's end; the part in view is 1.45 m off
    on_fridge, nearer = np.array([0.8, -0.4, 1.0]), np.array([0.75, -0.35, 1.0])
    walks: list[dict[str, object]] = []
    actions, events, done = _restore(
        monkeypatch, [on_fridge, nearer], [None], distances=[1.45, 0.9], walks=walks
    )
    assert actions == ["CloseObject"] and events == ["openness_restored"] and done
    assert walks[0]["goal_mask"] is not None  # the walk to the box, then one up to the point seen
    assert walks[1]["goal_xy"] == (0.8, -0.4) and walks[1]["radius"] == STEP_UP_M
    # still beyond reach from there: the next standpoint (a wider ring round the box), then give up
    walks.clear()
    actions, events, done = _restore(
        monkeypatch, [on_fridge] * 4, [], distances=[1.45, 1.45, 1.6, 1.5], walks=walks
    )
    assert actions == [] and events == ["openness_failed"] and not done
    assert [("goal_mask" in w, "goal_xy" in w) for w in walks] == [(True, False), (False, True)] * 2


def test_a_second_instance_that_stayed_near_the_old_place_does_not_hide_a_move() -> None:
    # two apples 34 cm apart on a coffee table; one was carried to the dining table
    then = [_seen("Apple", (1.2, 2.15, 0.45), half=0.04), _seen("Apple", (1.53, 2.12, 0.45), half=0.04)]
    now = [
        _track(1, "Apple", (0.05, 0.43, 0.8), half=0.04),
        _track(2, "Apple", (1.54, 2.11, 0.45), half=0.04),
    ]
    (m,) = find_moves(then, now)
    assert m.now.id == 1 and np.allclose(m.then.centroid, [1.2, 2.15, 0.45])
    # an unshuffle track by the old place that matches nothing still counts against the move
    stray = now + [_track(3, "Apple", (1.3, 2.3, 0.45), half=0.04, n_obs=1)]
    assert find_moves(then, stray) == []


def test_one_object_tracked_twice_in_the_walkthrough_is_not_a_move() -> None:
    # one basketball left two walkthrough tracks 10 cm apart; one of them pairs with a second
    # basketball elsewhere in the unshuffle, the other with the first one, still in its place
    then = [
        _seen("BasketBall", (-0.55, -1.45, 0.18), half=0.12),
        _seen("BasketBall", (-0.66, -1.45, 0.11), half=0.12),
    ]
    now = [
        _track(1, "BasketBall", (1.5, 1.7, 0.65), half=0.12),
        _track(2, "BasketBall", (-0.6, -1.45, 0.18), half=0.12),
    ]
    assert find_moves(then, now) == []
    # two basketballs 60 cm apart: the one whose place is empty now moved
    apart = [
        _seen("BasketBall", (0.0, -1.45, 0.12), half=0.12),
        _seen("BasketBall", (-0.6, -1.45, 0.12), half=0.12),
    ]
    (m,) = find_moves(apart, now)
    assert m.now.id == 1 and np.allclose(m.then.centroid, [0.0, -1.45, 0.12])


def test_a_glimpse_that_takes_the_moved_track_is_matched_again_without_it() -> None:
    # four scrub brushes by a toilet; the walkthrough saw one of them (B) twice, once in a
    # glimpse 1.4 cm off; A was carried 1.2 m away. Nearest first, the glimpse and then B itself
    # pair with A's new track, each ruled out (B still stands there), leaving A's own track
    # paired with nothing: matched again without them, A moved
    a = _seen("ScrubBrush", (2.11, 0.33, 0.12), n_obs=26)
    b = _seen("ScrubBrush", (2.61, 0.68, 0.12), n_obs=23)
    glimpse = _seen("ScrubBrush", (2.62, 0.67, 0.12), n_obs=2)
    now = [_track(1, "ScrubBrush", (2.6, 0.67, 0.12), n_obs=23), _track(2, "ScrubBrush", (2.45, 1.52, 0.12))]
    moves, pairs = match_phases([glimpse, b, a], now)
    assert [(m.now.id, tuple(m.then.centroid)) for m in moves] == [(2, (2.11, 0.33, 0.12))]
    assert any(s is a and o.id == 2 for s, o, _ in pairs)  # the matching the log shows
    # with every track paired (no brush left over) a ruled-out pair is not matched again
    assert find_moves([glimpse, b], now) == []


def test_a_walkthrough_track_by_the_new_place_counts_even_when_its_match_stayed() -> None:
    # the walkthrough merged two remotes 28 cm apart into one track; in the unshuffle both are
    # tracked, one pairs with the merged track, the other with a third remote's old place: that
    # third remote was moved where it was not seen, and the second remote did not move
    # (the memory's box of a merged track is the union of its views: it spans both remotes)
    merged = dataclasses.replace(
        _seen("RemoteControl", (1.0, 2.25, 0.41)),
        box_min=np.array([0.85, 2.08, 0.4]),
        box_max=np.array([1.1, 2.43, 0.44]),
    )
    then = [_seen("RemoteControl", (-0.84, 2.4, 0.5)), merged]
    now = [_track(1, "RemoteControl", (1.02, 2.38, 0.42)), _track(2, "RemoteControl", (0.93, 2.13, 0.42))]
    assert find_moves(then, now) == []


def test_a_second_instance_that_stayed_near_the_new_place_does_not_hide_a_move() -> None:
    # two soap bottles 50 cm apart on a counter; the first was put 22 cm from the second, which
    # stayed where it stood (its own track, whose box does not reach the new place)
    then = [
        _seen("SoapBottle", (0.75, 0.87, 0.9), half=0.04),
        _seen("SoapBottle", (0.24, 1.02, 0.9), half=0.04),
    ]
    now = [
        _track(1, "SoapBottle", (0.39, 1.18, 0.9), half=0.04),
        _track(2, "SoapBottle", (0.24, 1.02, 0.9), half=0.04),
    ]
    (m,) = find_moves(then, now)
    assert m.now.id == 1 and np.allclose(m.then.centroid, [0.75, 0.87, 0.9])
    # the second bottle's walkthrough track reaching the new place: one track of both, no move
    wide = dataclasses.replace(then[1], box_max=np.array([0.45, 1.25, 0.94]))
    assert find_moves([then[0], wide], now) == []
    # the second bottle not seen in the unshuffle: nothing says it still stands there, no move
    assert find_moves(then, now[:1]) == []


def _view_of_a_bed(
    bed_end_x: float, top_z: float = 0.6, bed_start_x: float = 0.3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 64x64 depth frame from an eye at 0.9 m looking along +x, 30 degrees down, at a bed
    top (a thin slab) at ``top_z`` from x = ``bed_start_x`` to ``bed_end_x`` with the floor
    beyond and under it: (depth, K, pose)."""
    k = np.array([[32.0, 0.0, 32.0], [0.0, 32.0, 32.0], [0.0, 0.0, 1.0]])
    th = np.radians(30.0)
    rot = np.stack(
        [[0.0, -1.0, 0.0], [-np.sin(th), 0.0, -np.cos(th)], [np.cos(th), 0.0, -np.sin(th)]], axis=1
    )
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, [0.0, 0.0, 0.9]
    v, u = np.mgrid[0:64, 0:64] + 0.5
    rays = np.stack([(u - 32.0) / 32.0, (v - 32.0) / 32.0, np.ones_like(u)], axis=-1) @ rot.T
    down = np.where(rays[..., 2] < 0, rays[..., 2], -1e-9)
    on_bed = (top_z - 0.9) / down  # depth (along the optical axis) where the ray meets the top
    x_bed = rays[..., 0] * on_bed
    depth = np.where((x_bed >= bed_start_x) & (x_bed <= bed_end_x), on_bed, (0.0 - 0.9) / down)
    return depth, k, pose


def test_a_put_beyond_reach_is_pulled_in_onto_the_same_surface() -> None:
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body

    body = Body(SemanticMapper(MapConfig(), CLASSES))
    policy = rearrange.RearrangePolicy(AgentConfig(), body, None, None, "Bedroom", lambda **kw: None)
    pillow = np.array([2.0, 0.0, 0.6 + rearrange.REACH_LIFT_M])  # the middle of a long bed, 2 m away
    depth, k, pose = _view_of_a_bed(2.4)
    body.obs = SimpleNamespace(depth=depth, intrinsics=k, camera_pose=pose)
    near = policy.pulled_in(pillow)
    assert near is not None
    assert np.isclose(np.linalg.norm(near - pose[:3, 3]), rearrange.PULL_REACH_M)
    assert np.isclose(near[2], pillow[2]) and np.isclose(near[1], 0.0) and 1.3 < near[0] < 1.5
    # the bed ends before the pulled-in point: the floor is there, no put
    depth, k, pose = _view_of_a_bed(1.2)
    body.obs = SimpleNamespace(depth=depth, intrinsics=k, camera_pose=pose)
    assert policy.pulled_in(pillow) is None
    # within reach already: nothing to pull in
    assert policy.pulled_in(np.array([1.0, 0.0, 0.7])) is None


def test_a_point_hidden_under_a_table_top_is_seen_as_overhead() -> None:
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body

    body = Body(SemanticMapper(MapConfig(), CLASSES))
    policy = rearrange.RearrangePolicy(AgentConfig(), body, None, None, "LivingRoom", lambda **kw: None)
    depth, k, pose = _view_of_a_bed(1.0, top_z=0.45)  # a coffee table's top from x = 0.3 to 1.0
    body.obs = SimpleNamespace(depth=depth, intrinsics=k, camera_pose=pose)
    shelf = np.array([0.8, 0.0, 0.2])  # on the shelf under the top: the ray meets the top at x = 0.51
    assert isinstance(policy.reach_action(shelf, None), str) and policy.overhead(shelf)
    on_top = np.array([0.7, 0.0, 0.55])  # above the top: in plain view
    assert not isinstance(policy.reach_action(on_top, None), str) and not policy.overhead(on_top)
    # a wall 0.5 m in front of the eye hides the point too, but nothing is seen over it
    body.obs = SimpleNamespace(depth=np.minimum(depth, 0.5), intrinsics=k, camera_pose=pose)
    assert isinstance(policy.reach_action(shelf, None), str) and not policy.overhead(shelf)


def _put_at(
    monkeypatch: pytest.MonkeyPatch,
    room: str,
    seen: Seen,
    toward: tuple[float, float],
    hidden: Callable[[list[np.ndarray], Any], bool],
    overhead: Callable[[list[np.ndarray]], bool],
) -> tuple[bool, list[str], list[str], list[np.ndarray]]:
    """Run ``put_at(seen)`` with its walks standing on the goal region's cell nearest
    ``toward`` and its reach failing ("something ... in front of it") while ``hidden(spots,
    body)``: (its result, the actions it sent, its events, the spots it stood on)."""
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body

    mapper = SemanticMapper(MapConfig(), CLASSES)
    body = Body(mapper)
    events: list[str] = []
    policy = rearrange.RearrangePolicy(
        AgentConfig(), body, None, None, room, lambda **kw: events.append(kw["kind"])
    )
    spots: list[np.ndarray] = []
    pose = np.eye(4)
    pose[2, 3] = 0.9  # the eye

    def walk(body_: Body, goal_mask: np.ndarray, **kwargs: object) -> Gen:
        x, y = np.broadcast_arrays(*mapper.grid.centres())
        d = np.where(goal_mask, np.hypot(x - toward[0], y - toward[1]), np.inf)
        i = np.unravel_index(int(np.argmin(d)), d.shape)
        spots.append(np.array([x[i], y[i]]))
        body.obs = SimpleNamespace(
            agent_pose=(x[i], y[i], 0.0, 0.0), success=True, error=None, camera_pose=pose
        )
        return True
        yield

    def aim(point: np.ndarray, yaw: float | None) -> rearrange.Action | str:
        if hidden(spots, body):
            return "something 0.40 m away in front of it"
        return rearrange.Action(rearrange.ActionName.PutObject, x=0.5, y=0.5, reach=0.9)

    def face(*args: object, **kwargs: object) -> Gen:
        return True
        yield

    monkeypatch.setattr(rearrange, "navigate", walk)
    monkeypatch.setattr(rearrange, "face_point", face)
    monkeypatch.setattr(policy, "reach_action", aim)
    monkeypatch.setattr(policy, "overhead", lambda point: overhead(spots))
    body.obs = SimpleNamespace(agent_pose=(0.0, 0.0, 0.0, 0.0), success=True, error=None, camera_pose=pose)
    run, actions = policy.put_at(seen), []
    try:
        action = next(run)
        while True:
            actions.append(action.name.value)
            action = run.send(None)
    except StopIteration as stop:
        return bool(stop.value), actions, events, spots


def test_a_put_hidden_under_a_table_top_is_tried_from_farther_off(monkeypatch: pytest.MonkeyPatch) -> None:
    """From the first spot the table's top hides the shelf under it; the next spot stands at
    least ``FARTHER_M`` farther from the point, within reach of it."""
    from tidee.agent.policy import rearrange

    shelf = np.array([1.5, 0.0, 0.2])
    done, _, _, spots = _put_at(
        monkeypatch,
        "LivingRoom",
        _seen("Book", (1.5, 0.0, 0.15), half=0.04),
        toward=(shelf[0], shelf[1]),
        hidden=lambda spots, body: len(spots) == 1,
        overhead=lambda spots: len(spots) == 1,
    )
    first, second = (float(np.linalg.norm(p - shelf[:2])) for p in spots)
    assert done and len(spots) == 2 and second >= first + rearrange.FARTHER_M - 0.05
    # the outermost band within reach: the lowest rays
    target = np.array([1.5, 0.0, 0.15 - 0.04 + rearrange.REACH_LIFT_M])
    farthest = np.sqrt(rearrange.PULL_REACH_M**2 - (0.9 - target[2]) ** 2)
    assert farthest - rearrange.BAND_M - 0.05 <= second <= farthest


def test_a_put_blocked_from_one_spot_is_tried_from_another(monkeypatch: pytest.MonkeyPatch) -> None:
    """A toaster in the way of the reach from the first spot beside a counter: the next walk
    keeps ``RETRY_PUT_M`` from it, and the put goes from there."""
    from tidee.agent.policy import rearrange

    done, actions, events, spots = _put_at(
        monkeypatch,
        "Kitchen",
        _seen("Mug", (1.5, 0.0, 0.95), half=0.04),
        toward=(1.0, 0.0),
        hidden=lambda spots, body: bool(np.linalg.norm(body.xy - spots[0]) < 1e-6),
        overhead=lambda spots: False,  # the toaster stands beside the point
    )
    assert done and actions == ["PutObject"] and events == ["aim_failed", "put_back"]
    assert len(spots) == 2 and np.linalg.norm(spots[1] - spots[0]) >= rearrange.RETRY_PUT_M


def _box(label: str, lo: tuple[float, float, float], hi: tuple[float, float, float], n_obs: int = 10) -> Seen:
    a, b = np.array(lo, float), np.array(hi, float)
    return Seen(label, (a + b) / 2, a, b, n_obs)


def _box_track(
    i: int, label: str, lo: tuple[float, float, float], hi: tuple[float, float, float], n_obs: int
) -> TrackedObject:
    a, b = np.array(lo, float), np.array(hi, float)
    return TrackedObject(i, label, 0.9, (a + b) / 2, a, b, n_obs=n_obs)


def test_a_walkthrough_track_of_two_objects_is_split_when_one_of_them_moved() -> None:
    # the walkthrough tracked two remotes side by side (x 0.9-1.1 and 1.1-1.3) as one track
    # centred between them; one stayed, the other went to the sofa: the split puts it back at
    # 2 x merged - stayer, beside the one that stayed
    merged = _box("RemoteControl", (0.9, 1.96, 0.40), (1.3, 2.04, 0.44))
    stayer = _box_track(1, "RemoteControl", (0.9, 1.96, 0.40), (1.1, 2.04, 0.44), n_obs=8)
    moved = _box_track(2, "RemoteControl", (3.9, 0.16, 0.43), (4.1, 0.24, 0.47), n_obs=6)
    (m,) = find_moves([merged], [stayer, moved])
    assert m.now is moved
    assert np.allclose(m.then.centroid[:2], [1.2, 2.0]) and m.then.middle == pytest.approx((1.2, 2.0))
    assert np.allclose(m.then.box_min, [1.1, 1.96, 0.40]) and np.allclose(m.then.box_max, [1.3, 2.04, 0.44])
    # nothing to split: the walkthrough track was as small as its match
    assert find_moves([_box("RemoteControl", (0.9, 1.96, 0.40), (1.1, 2.04, 0.44))], [stayer, moved]) == []
    # two tracks that could be the merge: which one is not known
    other = _box("RemoteControl", (-2.2, 0.0, 0.40), (-1.8, 0.08, 0.44))
    other_now = _box_track(3, "RemoteControl", (-2.2, 0.0, 0.40), (-2.0, 0.08, 0.44), n_obs=8)
    assert find_moves([merged, other], [stayer, other_now, moved]) == []


def test_a_big_track_matched_with_a_smaller_view_of_itself_is_not_split() -> None:
    # a box seen whole in the walkthrough and only in part now: the "split" would stand it
    # inside the box that stayed
    whole = _box("Box", (0.0, 0.0, 0.0), (0.75, 0.5, 0.4))
    part = _box_track(1, "Box", (0.09, 0.01, 0.0), (0.57, 0.49, 0.4), n_obs=7)
    other = _box_track(2, "Box", (2.7, 2.75, 0.0), (3.3, 3.25, 0.4), n_obs=20)
    assert find_moves([whole], [part, other]) == []


def test_a_move_to_beside_a_still_object_gives_way_to_a_sure_track_paired_with_nothing() -> None:
    # two salt shakers 15 cm apart; the walkthrough saw one of them (A) and a third (B) on
    # another counter. B was moved to the table; in the unshuffle both of the pair are seen:
    # the one the walkthrough missed (X) is nearer B's old place than B is, but it stands
    # beside A, which stayed, and B's track is paired with nothing: B moved, X did not
    a, b = (
        _seen("SaltShaker", (0.41, 1.33, 0.9), half=0.025),
        _seen("SaltShaker", (1.31, 0.43, 0.9), half=0.025),
    )
    now = [
        _track(1, "SaltShaker", (0.41, 1.33, 0.9), half=0.025),
        _track(2, "SaltShaker", (0.27, 1.37, 0.9), half=0.025),  # X
        _track(3, "SaltShaker", (1.78, 2.03, 0.75), half=0.025),  # B now
    ]
    (m,) = find_moves([a, b], now)
    assert m.now.id == 3 and m.then is b
    # without a track paired with nothing, a move to beside a still object stands
    (m,) = find_moves([a, b], now[:2])
    assert m.now.id == 2 and m.then is b


def test_one_object_under_two_labels_is_put_back_as_the_one_seen_more_often() -> None:
    # the unshuffle tracked a moved vase twice, as a vase (its walkthrough track far away) and
    # as a soap bottle; a soap bottle the walkthrough merged with a second one stayed
    merged = _box("SoapBottle", (0.70, -1.10, 0.15), (0.86, -1.02, 0.25))
    stayer = _track(1, "SoapBottle", (0.74, -1.06, 0.2), half=0.04, n_obs=8)
    bottle = _track(2, "SoapBottle", (0.52, 0.32, 0.13), half=0.04, n_obs=5)
    vase_then = _seen("Vase", (0.05, 1.58, 0.86), half=0.06)
    vase = _track(3, "Vase", (0.53, 0.32, 0.12), half=0.06, n_obs=13)
    (alone,) = find_moves([merged], [stayer, bottle])
    assert alone.now is bottle  # without the vase: the second soap bottle moved
    (m,) = find_moves([merged, vase_then], [stayer, bottle, vase])
    assert m.now is vase and m.then is vase_then  # the vase, seen more often, says what it is
    # seen more often as a soap bottle: the split's move, and not the vase's
    (m,) = find_moves([merged, vase_then], [stayer, dataclasses.replace(bottle, n_obs=20), vase])
    assert m.now.label == "SoapBottle" and np.allclose(m.then.centroid[:2], [0.82, -1.06])


def _check_put(
    monkeypatch: pytest.MonkeyPatch,
    matches: list[tuple[float, float, float, float]],
    views: int = 1,
    x: float = 1.0,
    pending: int = 0,
) -> tuple[bool, list[str], list[float]]:
    """Run ``check_put`` on a mug put down at (1.5, 0, 1.0), with the walk to a view's pose
    stubbed out and ``match_view`` answering the next of ``matches`` (shift x in metres, turn,
    misfit, misfit standing still); a mend records its turn and lands where it aimed. Returns
    the skill's result, the events and the mends' turns."""
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.mapping.view_match import ObjectView, ViewMatch
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body

    body = Body(SemanticMapper(MapConfig(), CLASSES))
    body.obs = SimpleNamespace(
        rgb=None,
        depth=None,
        intrinsics=None,
        camera_pose=None,
        steps_left=300,
        agent_pose=(x, 0.0, 0.0, 30.0),
    )
    events: list[str] = []
    policy = rearrange.RearrangePolicy(
        AgentConfig(), body, None, None, "Kitchen", lambda **kw: events.append(kw["kind"])
    )
    seen = dataclasses.replace(_seen("Mug", (1.5, 0.0, 0.95), half=0.05), track_id=7)
    pts = np.array([[1.5 + 0.01 * (i % 5), 0.01 * (i // 5), 0.96] for i in range(20)])
    made = [ObjectView((1.0, 0.25 * k, 0.0, 30.0), pts, np.zeros((20, 3))) for k in range(views)]
    policy.views[7] = [SimpleNamespace(view=lambda v=v: v) for v in made]  # type: ignore[misc]
    answers = iter(matches)
    turns: list[float] = []

    def stand(self: Any, view: Any) -> Gen:
        return True
        yield

    def mend(self: Any, view: Any, match: Any, target: np.ndarray, yaw: float, held: Any, label: str) -> Gen:
        turns.append(yaw)
        return target
        yield

    def match_view(*args: Any) -> ViewMatch:
        dx, turn, misfit, still = next(answers)
        return ViewMatch(np.array([dx, 0.0]), turn, misfit, still, 1.0)

    monkeypatch.setattr(rearrange.RearrangePolicy, "_stand_at", stand)
    monkeypatch.setattr(rearrange.RearrangePolicy, "_mend_put", mend)
    monkeypatch.setattr(rearrange, "match_view", match_view)
    policy.pending = pending
    run = policy.check_put(seen, np.array([1.5, 0.0, 1.0]), "Mug")
    try:
        next(run)
        raise AssertionError("the stubs take no action")
    except StopIteration as stop:
        return bool(stop.value), events, turns


def test_a_put_seen_off_its_place_from_a_walkthrough_pose_is_mended_once_in_place(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """3 cm off and turned 170 degrees (a box turned 10 degrees less than half round): mended
    with a turn of 10 degrees, then seen in place."""
    done, events, turns = _check_put(monkeypatch, [(0.03, 170.0, 0.1, 0.5), (0.002, 1.0, 0.05, 0.06)])
    assert done and events == ["put_checked", "put_checked"]
    assert turns == [pytest.approx(10.0)]


def test_a_mend_that_leaves_the_frame_fitting_worse_is_undone(monkeypatch: pytest.MonkeyPatch) -> None:
    """After the mend the view's place fits the frame worse (0.8) than before it (0.7): the
    object goes back, turned the other way."""
    done, events, turns = _check_put(monkeypatch, [(0.1, 30.0, 0.1, 0.7), (0.1, 150.0, 0.75, 0.8)])
    assert done and events == ["put_checked", "put_checked", "mend_undone"]
    assert turns == [pytest.approx(-30.0), pytest.approx(30.0)]


def test_a_walk_to_a_view_pose_keeps_to_lattice_points_stood_on() -> None:
    from tidee.agent.policy.rearrange import lattice_key, lattice_move, lattice_path
    from tidee.protocol.messages import ActionName

    stood = {(0, 0), (1, 0), (2, 0), (2, 1), (0, 2), (1, 2), (2, 2)}
    assert lattice_key((0.49, -0.01, 90.0, 30.0)) == (2, 0)
    assert lattice_path(stood, (0, 0), (2, 2), 10) == [(1, 0), (2, 0), (2, 1), (2, 2)]
    assert lattice_path(stood, (0, 0), (1, 1), 10) is None  # never stood on
    assert lattice_path(stood, (0, 0), (2, 2), 3) is None  # farther than allowed
    assert lattice_path(stood, (1, 0), (1, 0), 3) == []
    # heading +y (90 degrees): +x is to the right, -y behind
    assert lattice_move(90.0, (0, 0), (1, 0)) == ActionName.MoveRight
    assert lattice_move(90.0, (0, 0), (0, -1)) == ActionName.MoveBack
    assert lattice_move(180.0, (0, 0), (-1, 0)) == ActionName.MoveAhead
    assert lattice_move(0.0, (0, 0), (0, 1)) == ActionName.MoveLeft
    assert lattice_move(0.0, (0, 0), (2, 0)) is None


def test_a_put_is_left_alone_when_in_place_or_when_the_match_is_not_believed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 5 mm and 3 degrees off: in place for IoU 0.5
    assert _check_put(monkeypatch, [(0.005, 3.0, 0.05, 0.2)])[2] == []
    # 4 cm off, but no better a fit than standing still (a frame where the mug is hidden)
    assert _check_put(monkeypatch, [(0.04, 0.0, 0.5, 0.52)])[2] == []
    # a fit not much better than standing still's (an alarm clock on a shelf above the eye)
    assert _check_put(monkeypatch, [(0.06, 0.0, 0.2, 0.3)])[2] == []
    # a better fit than standing still, but a poor one
    from tidee.agent.policy import rearrange

    assert _check_put(monkeypatch, [(0.04, 0.0, rearrange.FIT_MAX + 0.05, 0.9)])[2] == []


def test_a_put_still_off_is_mended_at_most_twice(monkeypatch: pytest.MonkeyPatch) -> None:
    from tidee.agent.policy import rearrange

    done, events, turns = _check_put(monkeypatch, [(0.03, 20.0, 0.1, 0.5)] * 5)
    assert done and len(turns) == rearrange.MENDS and events == ["put_checked"] * (rearrange.MENDS + 1)


def test_a_put_without_a_walkthrough_view_of_its_place_is_not_checked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    done, events, turns = _check_put(monkeypatch, [], views=0)
    assert not done and events == ["put_unchecked"] and turns == []


def test_a_put_is_not_checked_when_the_pose_is_off_the_lattice(monkeypatch: pytest.MonkeyPatch) -> None:
    """With noisy odometry the corrected pose is off the lattice: no pose recurs exactly."""
    done, events, turns = _check_put(monkeypatch, [(0.03, 20.0, 0.1, 0.5)], x=1.03)
    assert not done and events == ["put_unchecked"] and turns == []


def test_a_lattice_walk_goes_round_a_move_found_blocked() -> None:
    from tidee.agent.policy.rearrange import lattice_path

    stood = {(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)}
    assert lattice_path(stood, (0, 0), (2, 0), 10) == [(1, 0), (2, 0)]
    blocked = {frozenset(((1, 0), (2, 0)))}
    assert lattice_path(stood, (0, 0), (2, 0), 10, blocked) in (
        [(1, 0), (1, 1), (2, 1), (2, 0)],
        [(0, 1), (1, 1), (2, 1), (2, 0)],
    )


def test_a_put_is_not_checked_when_the_objects_still_to_put_back_need_the_steps(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """300 steps left, 10 objects still to put back: they come first."""
    assert _check_put(monkeypatch, [(0.03, 20.0, 0.1, 0.5)], pending=10) == (False, [], [])
    assert _check_put(monkeypatch, [(0.03, 20.0, 0.1, 0.5)] * 3, pending=2)[2] != []


_K = np.array([[4.0, 0.0, 4.0], [0.0, 4.0, 4.0], [0.0, 0.0, 1.0]])  # an 8x8 camera


def _frame(depth: np.ndarray, pose: np.ndarray | None = None, **kw: Any) -> Any:
    from types import SimpleNamespace

    pose = np.eye(4) if pose is None else pose
    return SimpleNamespace(
        depth=depth, intrinsics=_K, camera_pose=pose, success=True, error=None, agent_pose=(0, 0, 0, 30), **kw
    )


def _lying() -> tuple[np.ndarray, np.ndarray]:
    """Depth before and after a pick took a thing 1 m from the eye (pixels in rows 4-6,
    columns 1-3) off a surface 2 m away."""
    after = np.full((8, 8), 2.0)
    before = after.copy()
    before[4:7, 1:4] = 1.0
    return before, after


def test_where_a_picked_thing_lay_is_the_middle_of_the_pixels_it_left() -> None:
    from tidee.agent.mapping.geometry import unproject
    from tidee.agent.policy.rearrange import where_it_lay
    from tidee.protocol.messages import Action, ActionName

    before, after = _lying()
    before[0:2, 6:8] = 1.5  # something else gone too, not touching it: not the picked thing
    pick = Action(ActionName.PickupObject, x=2.5 / 8, y=5.5 / 8)
    mask = np.zeros((8, 8), bool)
    mask[4:7, 1:4] = True
    expected = unproject(before, _K, np.eye(4), mask=mask)[0].mean(axis=0)
    assert where_it_lay(_frame(before), _frame(after), pick) == pytest.approx(expected, abs=1e-6)
    # the pick's pixel did not change, or the frames are of two poses: nothing to go by
    assert where_it_lay(_frame(before), _frame(after), Action(ActionName.PickupObject, x=0.9, y=0.9)) is None
    moved = np.eye(4)
    moved[0, 3] = 0.25
    assert where_it_lay(_frame(before), _frame(after, moved), pick) is None


def _put_back(monkeypatch: pytest.MonkeyPatch, held: str) -> tuple[list[Any], list[Any], bool]:
    """Run ``put_back`` on a spoon believed moved, the walk stubbed out and the put at its
    walkthrough place recorded as an event; the pick (at pixel (2, 5)) succeeds with ``held``
    in the hand, the thing gone from the frame, and every other action succeeds. Returns the
    actions, the events (kind and fields) and the skill's result."""
    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body, Sighting

    mapper = SemanticMapper(MapConfig(), CLASSES)
    c = np.array([1.0, 0.0, 0.8])
    spoon = mapper.memory.add_or_merge("Spoon", 0.9, c, c - 0.05, c + 0.05, step=0)
    body = Body(mapper)
    before, after = _lying()
    body.obs = _frame(before, held=None, held_id=None)
    events: list[Any] = []
    policy = rearrange.RearrangePolicy(
        AgentConfig(), body, None, None, "Kitchen", lambda **kw: events.append(kw)
    )

    def approach(self: Any, *args: Any) -> Gen:
        return Sighting(None, 2, 5, 0.8, c)
        yield

    def put_at(self: Any, *args: Any, **kwargs: Any) -> Gen:
        events.append({"kind": "put_at"})
        return True
        yield

    monkeypatch.setattr(rearrange.RearrangePolicy, "approach", approach)
    monkeypatch.setattr(rearrange.RearrangePolicy, "put_at", put_at)
    move = rearrange.Move(spoon, _seen("Spoon", (2.0, 0.0, 0.8)), 1.0)
    run, actions = policy.put_back(move), []
    try:
        action = next(run)
        while True:
            actions.append(action)
            if action.name.value == "PickupObject":
                body.obs = _frame(after, held=held, held_id=f"{held}_0")
            else:
                body.obs = _frame(
                    before if action.name.value == "PutObject" else after, held=None, held_id=None
                )
            action = run.send(None)
    except StopIteration as stop:
        return actions, events, bool(stop.value)


def test_a_pick_that_took_another_kind_of_thing_puts_it_back_where_it_lay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A spatula in the hand where a spoon was believed moved: it was lying there and did not
    move, so it goes back down, turned as it lay, at the middle of the pixels it left in the
    frame (reached for at its distance along that pixel's ray), and nothing is carried off."""
    actions, events, done = _put_back(monkeypatch, "Spatula")
    assert [a.name.value for a in actions] == ["PickupObject", "PutObject"]
    pick, put = actions
    assert (pick.x, pick.y) == (2.5 / 8, 5.5 / 8)
    # the 3x3 pixels it left (rows 4-6, columns 1-3) have their middle at pixel (2, 5), 1 m away
    assert (put.x, put.y, put.yaw) == (2.5 / 8, 5.5 / 8, 0.0)
    assert put.reach == pytest.approx(np.linalg.norm([-2 / 4, 1 / 4, 1.0]), rel=1e-6)
    assert [e["kind"] for e in events] == ["picked", "picked_another"] and not done
    assert events[1]["held"] == "Spatula"


def test_a_pick_that_took_the_believed_thing_carries_it_back(monkeypatch: pytest.MonkeyPatch) -> None:
    actions, events, done = _put_back(monkeypatch, "Spoon")
    assert [a.name.value for a in actions] == ["PickupObject"]
    assert [e["kind"] for e in events] == ["picked", "put_at"] and done


def test_the_commonsense_row_tidies_only_sure_unmatched_objects_found_out_of_place(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``--unmatched commonsense``: after the moves, an unshuffle track seen at least twice
    that paired with nothing of the walkthrough and that the OOP detector finds out of place
    is tidied as the tidy agent tidies, nearest first; one in place, one seen once, one paired
    and one believed moved (``put_back``'s) are left alone."""
    from types import SimpleNamespace

    from tidee.agent.classes import CLASSES
    from tidee.agent.config import AgentConfig, PolicyConfig
    from tidee.agent.mapping.config import MapConfig
    from tidee.agent.mapping.maps import SemanticMapper
    from tidee.agent.policy import rearrange
    from tidee.agent.policy.skills import Body

    mapper = SemanticMapper(MapConfig(), CLASSES)

    def add(label: str, x: float, n_obs: int = 3) -> TrackedObject:
        c = np.array([x, 0.0, 0.8])
        t = mapper.memory.add_or_merge(label, 0.9, c, c - 0.05, c + 0.05, step=0)
        t.n_obs = n_obs
        return t

    far_knife, near_apple, still_spoon, glimpse = (
        add("Knife", 3.0),
        add("Apple", 1.0),
        add("Spoon", 2.0),
        add("Fork", 1.5, 1),
    )
    paired_cup, moved_bowl = add("Cup", 2.5), add("Bowl", 0.5)
    oop = {"Knife": 0.9, "Apple": 0.7, "Spoon": 0.1, "Fork": 0.99, "Cup": 0.99, "Bowl": 0.99}

    class FakeOOP:
        name = "fake"

        def score_all(self, targets: list, objects: list, room_type: str) -> dict[int, float]:
            assert {t.label for t in targets} == {"Knife", "Apple", "Spoon"}  # sure, unmatched, unmoved
            return {t.id: oop[t.label] for t in targets}

    body = Body(mapper)
    body.obs = SimpleNamespace(steps_left=100, agent_pose=(0.0, 0.0, 0.0, 30.0))
    events: list[Any] = []
    cfg = AgentConfig(policy=PolicyConfig(unmatched="commonsense"))
    policy = rearrange.RearrangePolicy(
        cfg, body, FakeOOP(), object(), "Kitchen", lambda **kw: events.append(kw)
    )
    policy.moves = [rearrange.Move(moved_bowl, _seen("Bowl", (0.0, 1.0, 0.8)), 1.0)]
    tidied: list[str] = []

    def tidy_object(self: Any, obj: TrackedObject) -> Gen:
        tidied.append(obj.label)
        return None
        yield

    monkeypatch.setattr(rearrange.RearrangePolicy, "tidy_object", tidy_object)
    now = list(mapper.memory)
    pairs = [(_seen("Cup", (2.5, 0.0, 0.8)), paired_cup, 0.0)]
    assert list(policy.tidy_unmatched(now, pairs)) == []
    assert tidied == ["Apple", "Knife"]  # nearest first
    assert [e["label"] for e in events if e["kind"] == "unmatched_oop"] == ["Knife", "Apple"]
    assert near_apple.out_of_place and far_knife.out_of_place and not still_spoon.out_of_place
    assert not glimpse.out_of_place

    tidied.clear()
    body.obs = SimpleNamespace(steps_left=cfg.policy.reserve_steps, agent_pose=(0.0, 0.0, 0.0, 30.0))
    assert list(policy.tidy_unmatched(now, pairs)) == [] and tidied == []  # no steps to spare
