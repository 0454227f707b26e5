"""Object search (paper §3.4, Table 2): find an instance of a category and stop next to it.

``search_object`` is a skill like those in ``skills.py``: look around, then repeatedly ask a
*proposer* where to go (the visual search network's ranked points, or a frontier), walk
there and look around, re-asking as the map grows. As soon as the detector has put an
instance of the target in the object memory the agent walks to it, faces it and, when the
detector sees it again, says ``Done`` (the benchmark's Stop). Decisions read only the
agent's own maps and detections.

``SkillDriver`` plays a skill against a transport outside the full ``EpisodeRunner`` (data
generation and the search evaluation): perception -> mapping -> skill -> step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from tidee.agent.classes import CLASSES, PICKUPABLE
from tidee.agent.mapping.geometry import unproject
from tidee.agent.mapping.maps import MapConfig, SemanticMapper
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.navigation.explore import FrontierExplorer, sample_reachable_goal
from tidee.agent.perception.base import Detection
from tidee.agent.policy.skills import (
    Body,
    Skill,
    face_point,
    footprint_gap,
    frontier_goal,
    goal_mask_near_box,
    look_around,
    navigate,
    pitch_to,
    projected_sighting,
    reachable_mask,
)
from tidee.protocol.messages import Action, ActionName, EpisodeSpec

# A detection of the target counts as "stopped near it" when its near side is this close (x, y);
# the benchmark's success radius is 1.5 m from the instance's footprint.
STOP_REACH_M = 1.5

# Where to search next: (body, target label, search points already visited) -> ranked goals (x, y).
Proposer = Callable[[Body, str, Sequence[tuple[float, float]]], list[tuple[float, float]]]


class SkillDriver:
    """Runs skills against a transport: each step detects, maps, then asks the skill for an action."""

    def __init__(
        self, transport: Any, perception: Any, map_config: MapConfig | None = None, ground_truth: bool = False
    ) -> None:
        self.transport, self.perception = transport, perception
        self.map_config = map_config
        # Ground truth travels in the observations for oracle perception or for scoring only.
        self.ground_truth = bool(ground_truth or perception.needs_ground_truth)
        self.body: Body | None = None

    def reset(self, spec: EpisodeSpec) -> Body:
        obs = self.transport.reset(spec, ground_truth=self.ground_truth)
        self.body = Body(SemanticMapper(self.map_config, CLASSES, passable=PICKUPABLE))
        self._observe(obs)
        return self.body

    def _observe(self, obs: Any) -> None:
        assert self.body is not None
        dets = self.perception.detect(obs)
        self.body.mapper.update(obs, dets)
        self.body.obs, self.body.detections = obs, dets

    def run(self, skill: Skill, on_step: Callable[[Body], None] | None = None) -> Any:
        """Play ``skill`` until it returns or the episode ends; its return value (None if cut off)."""
        body = self.body
        assert body is not None, "reset() first"
        while not body.obs.done:
            try:
                action = next(skill)
            except StopIteration as stop:
                return stop.value
            self._observe(self.transport.step(action, ground_truth=self.ground_truth))
            if on_step is not None:
                on_step(body)
        skill.close()
        return None


def frontier_proposer(explorer: FrontierExplorer | None = None) -> Proposer:
    """The Yamauchi baseline: the geodesically nearest frontier (Table 2's exploration agent)."""

    def propose(body: Body, label: str, visited: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
        goal = frontier_goal(body, explorer or FrontierExplorer(body.mapper.grid))
        return [] if goal is None else [goal]

    return propose


def _interruptible(body: Body, skill: Skill, stop: Callable[[], bool]) -> Skill:
    """Play ``skill`` but end it (returning False) as soon as ``stop()`` holds."""
    try:
        while True:
            if stop():
                return False
            try:
                action = next(skill)
            except StopIteration as done:
                return bool(done.value)
            yield action
    finally:
        skill.close()


def _known(body: Body, label: str, rejected: set[int]) -> TrackedObject | None:
    objs = [o for o in body.mapper.memory.of_label(label) if o.id not in rejected]
    if not objs:
        return None
    xy = body.xy
    return min(objs, key=lambda o: float(np.linalg.norm(o.centroid[:2] - xy)))


def _in_view(body: Body, obj: TrackedObject, reach_xy: float = STOP_REACH_M) -> bool:
    """The detector sees the category now, within ``reach_xy`` of the agent: a detection of the
    label whose nearest tenth of pixels (valid depth) lies within ``reach_xy`` in (x, y). Any
    instance will do (the benchmark asks for the category), but not one across the room: a
    mislocated track can bring the agent near nothing while the real instance is in the frame
    2.5 m away."""
    return any(d.label == obj.label and _detection_within(body, d, reach_xy) for d in body.detections)


def _detection_within(body: Body, det: Detection, reach_xy: float) -> bool:
    """The 10th percentile of the (x, y) distance from the agent to the 3D points of the
    detection's region is at most ``reach_xy`` (a box region also holds some floor or wall
    around the object: a low percentile stands for the object's near side)."""
    obs = body.obs
    assert obs is not None
    pts, _ = unproject(obs.depth, obs.intrinsics, obs.camera_pose, mask=det.region(obs.depth.shape))
    if len(pts) == 0:
        return False
    d = np.hypot(pts[:, 0] - body.xy[0], pts[:, 1] - body.xy[1])
    return float(np.percentile(d, 10)) <= reach_xy


def _in_frame_unoccluded(body: Body, obj: TrackedObject) -> bool:
    """In the frame within reach (1.4 m) with nothing more than 0.25 m in front of it; what lies
    behind does not matter here (Stop needs the object in view, not a pixel on it)."""
    return projected_sighting(body, obj, reach=1.4, nearer_tol=0.25, farther_tol=math.inf) is not None


def approach_and_verify(body: Body, obj: TrackedObject, radius: float = 1.0, budget: int = 40) -> Skill:
    """Walk within ``radius`` of a tracked object's footprint, face it; True when the detector
    sees it in view, or when an object the detector has seen at least twice lies in the frame,
    within reach and unoccluded (small objects are often missed from up close). An attempt
    that ends farther than ``radius`` + 0.25 m from the footprint (the goal cells were not
    reachable yet) verifies nothing: a detection from across the room is not "stopped near it"."""
    for attempt in range(2):
        r = radius + 0.25 * attempt
        mask = goal_mask_near_box(body.mapper, obj.box_min, obj.box_max, r)
        yield from navigate(body, goal_mask=mask, stop_radius=0.05, budget=budget)
        if footprint_gap(obj.box_min, obj.box_max, *body.xy) > r + 0.25:
            continue
        for pitch_try in range(2):
            if body.steps_left() <= 1:
                return False
            yield from face_point(body, obj.centroid)
            if _in_view(body, obj) or (obj.n_obs >= 2 and _in_frame_unoccluded(body, obj)):
                return True
            if pitch_try == 0:
                p = body.pose[3]
                yield from pitch_to(body, p + (30.0 if p < 60 else -30.0))
    return False


def _unvisited(
    goals: Sequence[tuple[float, float]], visited: Sequence[tuple[float, float]], radius: float
) -> list[tuple[float, float]]:
    return [g for g in goals if all(math.dist(g, v) > radius for v in visited)]


def search_object(
    body: Body,
    label: str,
    propose: Proposer,
    rng: np.random.Generator,
    goal_budget: int = 40,
    approach_radius: float = 1.0,
    visit_radius: float = 1.0,
    fallback: Proposer | None = None,
    counts: dict[str, int] | None = None,
) -> Skill:
    """Find an instance of ``label`` and stop near it with it in view (yields ``Done``); True on Stop.

    The loop (paper: search points visited in rank order, re-predicted as the map grows):
    look around; while steps remain: if the memory holds an instance not set aside, approach
    it and stop when it is verified in view (else set it aside: after a first failed approach
    until the next search point has been visited, for good after a second); otherwise walk to
    the best proposed point not yet visited (when ``propose`` has none: ``fallback``'s point,
    e.g. a frontier, and a random reachable point when that has none either), interrupting
    the walk the moment the target is detected, and look around there. ``counts``, when
    given, tallies where the goals came from: ``proposed``, ``fallback``, ``random``.
    """
    rejected: set[int] = set()  # failed twice, or deferred until the next search point
    tries: dict[int, int] = {}
    visited: list[tuple[float, float]] = []

    def seen() -> bool:
        return _known(body, label, rejected) is not None

    yield from _interruptible(body, look_around(body), seen)
    while body.steps_left() > 1:
        target = _known(body, label, rejected)
        if target is not None:
            if (yield from approach_and_verify(body, target, approach_radius, goal_budget)):
                yield Action(ActionName.Done)
                return True
            tries[target.id] = tries.get(target.id, 0) + 1
            rejected.add(target.id)
            continue
        source = "proposed"
        goals = _unvisited(propose(body, label, visited), visited, visit_radius)
        if not goals and fallback is not None:
            source, goals = "fallback", _unvisited(fallback(body, label, visited), visited, visit_radius)
        if not goals:
            g = sample_reachable_goal(reachable_mask(body), body.mapper.grid, rng, tuple(body.xy))
            if g is None:
                break
            source, goals = "random", [g]
        if counts is not None:
            counts[source] = counts.get(source, 0) + 1
        goal = goals[0]
        visited.append((float(goal[0]), float(goal[1])))
        yield from _interruptible(body, navigate(body, goal_xy=goal, budget=goal_budget), seen)
        if not seen():
            yield from _interruptible(body, look_around(body, pitches=(30.0,)), seen)
        rejected = {i for i in rejected if tries.get(i, 0) >= 2}  # deferred ones: try again from here
    return False


__all__ = ["Proposer", "SkillDriver", "approach_and_verify", "frontier_proposer", "search_object"]
