"""Algorithm 1 of the paper: map the room, find out-of-place objects, put them away.

``TidyPolicy.run()`` is one generator for the whole episode; it reads like the paper's
pseudo code::

    map the scene                     (look around, then unexplored goals until < A unexplored)
    while an OOP object is found within k search goals:
        navigate to it, PickupObject
        receptacle classes <- placement model (CommonMemory, rGCN, ...) for the kind the hand
            holds (the observation's ``held``; a track's class can be wrong)
        if one is in the object memory: navigate there, PutObject (open it first if closed)
        else: search for it (exploration / visual search network), PutObject
              (missing_top="search": the top-ranked class is searched for before the others,
               as in the paper's Algorithm S1; "skip": only after the classes in memory; a
               class a household's preference asks for: always first, and every mapped
               instance of it is tried before the next class)
        after m failed tries per class: drop the object where the agent stands
    with a household's preferences, when no OOP object is left: each object a category
        preference names and the agent has not handled: walk up to it (mapped) or search
        for it (not mapped, and none of it put away yet) and put it where asked if it is not
        there (OOP objects met on the way are tidied; they start no new round of search goals)
    an object this agent put away is never picked again, unless a preference names it and
        finds it out of place where it came to rest, on another receptacle than the one the put
        aimed at: picked again, twice per category at most
    Done

Approaching an object or a receptacle that is not in view or not within reach from the spot
reached: the neighbouring pitch, then another spot at least ``RETRY_AWAY_M`` from those tried.

Every decision reads the agent's own maps, detections and observations; events go to
``on_event``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from tidee.agent.classes import OPENABLE, PICKUPABLE, PLACEABLE_RECEPTACLES
from tidee.agent.config import AgentConfig
from tidee.agent.mapping.config import MapConfig
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.navigation.explore import (
    FrontierExplorer,
    sample_reachable_goal,
    sample_unexplored_goal,
    unexplored_fraction,
)
from tidee.agent.policy.skills import (
    EDGE_MARGIN,
    MOVE_M,
    PITCHES,
    Body,
    Sighting,
    face_point,
    find_in_view,
    footprint_gap,
    frontier_goal,
    goal_mask_near_box,
    look_around,
    mask_away_from,
    navigate,
    other_receptacles,
    pitch_to,
    planner_and_reach,
    projected_sighting,
    raised_sighting,
    reachable_mask,
    receptacle_in_view,
    sighting_of,
)
from tidee.agent.reasoning.oop import OOPDetector, supports
from tidee.agent.reasoning.placement import PlacementModel
from tidee.protocol.messages import Action, ActionName

if TYPE_CHECKING:  # the profile module loads the text encoder; the policy only calls it
    from tidee.agent.reasoning.preferences import PreferenceProfile

Gen = Generator[Action, None, Any]
FLOOR = "Floor"
REAIM_AFTER_OPENING = (
    "too_far",
    "nothing_there",
    "not_receptacle",
    "not_openable",
)  # errors of an aim gone stale
APPROACH_TRIES = 4  # walks to get an object or a receptacle in view and within reach
ASKED_SEARCH_FACTOR = 2  # a receptacle a preference asks for gets this many times the search goals
PUT_AGAIN = 2  # a category's puts that missed what a preference asks are tried again this many times
SURE_SUPPORT_OBS = 5  # ... when they rest on a receptacle tracked at least this often (or the floor)
AIMED_MARGIN_M = 0.1  # ... and lie farther than this (x, y) from every track of the one aimed at


class Searcher(Protocol):
    """Where to look for a class not in the object memory (the visual search network)."""

    def heatmap(self, mapper: Any, label: str) -> np.ndarray: ...

    def points(
        self,
        mapper: Any,
        label: str,
        agent_xy: tuple[float, float],
        k: int,
        visited: list[tuple[float, float]] = ...,
        heat: np.ndarray | None = ...,
    ) -> list[tuple[float, float]]: ...


@dataclass
class SearchView:
    """One search prediction: the heatmap (on the voxel grid) and the ranked points."""

    label: str
    step: int
    heatmap: np.ndarray
    points: list[tuple[float, float]]


@dataclass
class PolicyState:
    """What the policy is doing, for telemetry and logs."""

    phase: str = "idle"
    target: TrackedObject | None = None
    target_receptacle: str | None = None
    predictions: list[tuple[str, float]] = field(default_factory=list)
    objects_fixed: int = 0
    oop_found: int = 0
    message: str = ""
    end_reason: str = ""


class TidyPolicy:
    def __init__(
        self,
        config: AgentConfig,
        body: Body,
        oop: OOPDetector,
        placement: PlacementModel | None,
        room_type: str,
        on_event: Callable[..., None] = lambda **kw: None,
        searcher: Searcher | None = None,
        preferences: PreferenceProfile | None = None,
    ) -> None:
        self.cfg, self.p = config, config.policy
        self.preferences = preferences  # a household's: they decide OOP and placement for what they name
        self.body, self.oop, self.placement = body, oop, placement
        self.searcher = searcher
        self.search_view: SearchView | None = None  # the latest heatmap, for telemetry
        self._visited: dict[str, list[tuple[float, float]]] = {}
        self.room_type = room_type
        self.rng = np.random.default_rng(config.seed)
        self.state = PolicyState()
        self.on_event = on_event
        # (label, xy, receptacle the put aimed at) of the objects this agent put away
        self.placed: list[tuple[str, np.ndarray, str]] = []
        self.dropped: list[tuple[str, np.ndarray]] = []  # (label, agent xy) of objects it gave up on
        self.flagged: set[int] = set()
        self.frontier = FrontierExplorer(body.mapper.grid)
        self._rescore = True
        self._last_put_xy = np.zeros(2)
        self._asked_searched: set[str] = set()  # named categories searched for after the tidying
        self._put_again: dict[int, str] = {}  # track id -> label: puts that missed (``_note_misputs``)
        self.picked_at: Action | None = None  # the last pick action (``pick``)

    @staticmethod
    def map_config(config: MapConfig) -> MapConfig:
        """The mapping this policy needs, from the agent's (the tidy agent: as configured)."""
        return config

    # ------------------------------------------------------------------ bookkeeping
    def event(self, kind: str, **fields: Any) -> None:
        self.state.message = f"{kind}: " + ", ".join(f"{k}={v}" for k, v in fields.items() if k != "centroid")
        self.on_event(kind=kind, **fields)

    def score_objects(self, touched: list[TrackedObject] | None = None) -> None:
        """Run the OOP detector over the pickupable objects in memory.

        Not while mapping (Algorithm 1 detects OOP objects after the map is built, when the
        receptacles under them are known); afterwards whenever the memory changed.
        """
        if self.state.phase in ("idle", "mapping") or (
            touched is not None and not touched and not self._rescore
        ):
            return
        self._rescore = False
        objs = list(self.body.mapper.memory)
        targets = [o for o in objs if o.label in PICKUPABLE]
        probs = self.oop.score_all(targets, objs, self.room_type)
        if self.preferences is not None:
            verdicts = self.preferences.verdicts(targets, objs)
            probs = {**probs, **verdicts}
            self._note_misputs([o for o in targets if verdicts.get(o.id) == 1.0], objs)
        for o in targets:
            o.oop_prob = float(probs[o.id])
            o.out_of_place = o.oop_prob >= self.p.oop_threshold and not self._held_back(o)
            if o.out_of_place and o.id not in self.flagged:
                self.flagged.add(o.id)
                self.state.oop_found += 1
                self.event(
                    "oop_found",
                    label=o.label,
                    track_id=o.id,
                    oop_prob=round(o.oop_prob, 3),
                    support=o.meta.get("support"),
                    paragraph=o.meta.get("paragraph"),
                    centroid=[round(float(v), 3) for v in o.centroid],
                )

    def _held_back(self, o: TrackedObject) -> bool:
        """Not to be picked: put away (or dropped) by this agent, unless the put missed what a
        household asked (``_note_misputs``)."""
        return self._is_placed(o) and o.id not in self._put_again

    def _note_misputs(self, misplaced: list[TrackedObject], objects: list[TrackedObject]) -> None:
        """Tracks the preferences find out of place where this agent put them, resting on
        something else than the receptacle the put aimed at: on the floor (a plate put at a
        pixel of a cabinet whose ray met the floor in front of it), or on a receptacle tracked
        at least ``SURE_SUPPORT_OBS`` times, more than ``AIMED_MARGIN_M`` from every track of the
        one aimed at. Over the receptacle aimed at, the support rules' answer is not believed
        (lettuce on the counter above a stool the map knows well). Each is picked again, up to
        ``PUT_AGAIN`` times per category."""
        misplaced = [o for o in misplaced if o.id not in self._put_again and self._put_target(o) is not None]
        if not misplaced:
            return
        rests_on = supports(misplaced, objects)
        for o in misplaced:
            aimed, sup = self._put_target(o), rests_on[o.id]
            if isinstance(sup, str):
                on, sure = sup, True
            else:
                on = sup.label
                sure = any(r.id == sup.id and r.n_obs >= SURE_SUPPORT_OBS for r in objects) and not any(
                    r.label == aimed
                    and footprint_gap(r.box_min, r.box_max, *o.centroid[:2]) <= AIMED_MARGIN_M
                    for r in objects
                )
            if on == aimed or not sure:
                continue
            tries = sum(1 for label in self._put_again.values() if label == o.label)
            if tries < PUT_AGAIN:
                self._put_again[o.id] = o.label
                self.event("put_missed", label=o.label, track_id=o.id, aimed=aimed, rests_on=on)

    def _put_target(self, o: TrackedObject) -> str | None:
        """The receptacle this agent aimed at when it put ``o`` where it lies (None: not put by it)."""
        for label, xy, target in self.placed:
            if label == o.label and np.linalg.norm(o.centroid[:2] - xy) < 0.6:
                return target
        return None

    def _is_placed(self, o: TrackedObject) -> bool:
        """Put there by this agent: never picked again (a dropped object, whose receptacle was
        not found or was full, would otherwise be picked, carried and dropped in a loop)."""
        return self._put_target(o) is not None or any(
            lbl == o.label and np.linalg.norm(o.centroid[:2] - xy) < 1.2 for lbl, xy in self.dropped
        )

    def _candidates(self) -> list[TrackedObject]:
        xy = self.body.xy
        objs = [
            o
            for o in self.body.mapper.memory
            if o.out_of_place and not o.meta.get("give_up") and not self._held_back(o)
        ]
        return sorted(objs, key=lambda o: float(np.linalg.norm(o.centroid[:2] - xy)))

    # ------------------------------------------------------------------ Algorithm 1
    def run(self) -> Gen:
        self.state.phase = "mapping"
        yield from look_around(self.body)
        yield from self.map_room()
        self.event("mapped", steps=self.body.obs.step, objects=len(self.body.mapper.memory))
        self.state.phase = "searching"
        self._rescore = True
        self.score_objects()
        empty_goals = 0
        asking = False  # the usual tidying has ended; what is left is for the preferences
        while self.body.steps_left() > self.p.reserve_steps:
            candidates = self._candidates()
            if candidates:
                # objects met on the way to an asked one are tidied, but they do not start
                # another round of search goals: that would move what the household never asked
                # about, on walks the agent without preferences never takes
                empty_goals = empty_goals if asking else 0
                yield from self.tidy_object(candidates[0])
                self.state.phase = "searching"
                continue
            if empty_goals >= self.p.k_empty_goals:
                asked = self.asked_object_goal()
                if asked is not None:  # an object a preference names, not handled yet
                    asking = True
                    yield from self.tidy_asked(*asked)
                    self.state.phase = "searching"
                    continue
                self.state.end_reason = f"no out-of-place object found after {empty_goals} search goals"
                break
            goal = sample_reachable_goal(
                reachable_mask(self.body), self.body.mapper.grid, self.rng, tuple(self.body.xy)
            )
            empty_goals += 1
            if goal is None:
                continue
            yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)
            yield from look_around(self.body, pitches=(30.0,))
        else:
            self.state.end_reason = "step budget"
        self.state.phase = "done"
        self.event("done", reason=self.state.end_reason, fixed=self.state.objects_fixed)
        yield Action(ActionName.Done)

    def asked_object_goal(self) -> tuple[str, TrackedObject | None] | None:
        """After the usual tidying, the next object a category preference names that the agent
        has not handled: (category, track) for a mapped one not visited for it yet (its OOP
        score left it alone, or an approach gave up on it: from up close the agent judges it
        again; also after one of its category was put away: the preference names every one),
        (category, None) for a category it has not mapped and has put none of away, to search
        for like a receptacle; None when every named category is handled (its mapped ones
        visited, and one put away or searched for in vain)."""
        if self.preferences is None:
            return None
        memory, xy = self.body.mapper.memory, self.body.xy
        for cat in self.preferences.named_categories():
            if cat not in PICKUPABLE:
                continue
            tracks = [
                o
                for o in memory.of_label(cat)
                if not o.meta.get("asked_visit")
                and not self._held_back(o)
                and (not o.meta.get("give_up") or o.n_obs >= 2)
            ]
            if tracks:
                return cat, min(tracks, key=lambda o: float(np.linalg.norm(o.centroid[:2] - xy)))
            put_away = any(lbl == cat for lbl, _, _ in self.placed)
            if cat not in self._asked_searched and not memory.of_label(cat) and not put_away:
                return cat, None
        return None

    def tidy_asked(self, category: str, obj: TrackedObject | None) -> Gen:
        """Handle what ``asked_object_goal`` chose: walk up to the mapped object and tidy it if
        it is not where the preferences want it; or search for the category (the search
        network's points for it, else unexplored space) until one is mapped."""
        if obj is not None:
            obj.meta["asked_visit"] = True
            obj.meta.pop("give_up", None)
            self.event("asked_object", label=category, track_id=obj.id)
            yield from self.tidy_object(obj)
            return
        self._asked_searched.add(category)
        self.state.phase = "searching"
        self.event("asked_object", label=category, track_id=None)
        for _ in range(self.p.search_goals):
            if self.body.mapper.memory.of_label(category) or self.body.steps_left() <= self.p.reserve_steps:
                break
            goal = self.search_goal(category)
            if goal is None:
                break
            yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)
            yield from look_around(self.body, pitches=(30.0,))

    def explore_randomly(self, planner: Any, reachable: np.ndarray) -> tuple[float, float] | None:
        """--explorer random: a random reachable cell not yet explored."""
        mapper = self.body.mapper
        return sample_unexplored_goal(mapper.explored, reachable, mapper.grid, self.rng, tuple(self.body.xy))

    def explore_frontiers(self, planner: Any, reachable: np.ndarray) -> tuple[float, float] | None:
        """--explorer frontier: the nearest frontier between explored and unknown space."""
        return frontier_goal(self.body, self.frontier, planner)

    def map_room(self) -> Gen:
        start = self.body.obs.step
        while self.body.obs.step - start < self.p.mapping_step_budget and self.body.steps_left() > 1:
            planner, reachable = planner_and_reach(self.body)
            mapper = self.body.mapper
            if unexplored_fraction(mapper.explored, reachable) < self.p.explore_unexplored_stop:
                break
            goal = EXPLORER_GOALS[self.cfg.explorer](self, planner, reachable)
            if goal is None:
                break
            yield from pitch_to(self.body, 30.0)
            yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)

    # ------------------------------------------------------------------ one object
    def tidy_object(self, obj: TrackedObject) -> Gen:
        st = self.state
        st.target, st.target_receptacle, st.predictions = obj, None, []
        st.phase = "approaching"
        sighting = yield from self.approach(obj, self.p.approach_m)
        if sighting is None:
            obj.meta["give_up"] = "could not get it in view within reach"
            self.event("unreachable", label=obj.label, track_id=obj.id)
            return
        if not self._still_out_of_place(obj):
            return
        if not (yield from self.pick(obj, sighting)):
            return
        tracked_as = obj.label
        held = self.body.obs.held
        if held is not None and held != obj.label and held in PICKUPABLE:
            # the hand holds another kind of thing (a spoon tracked as a knife, or the pick took
            # a neighbour): it goes where that kind goes
            self.event("held_another", label=obj.label, held=held, track_id=obj.id)
            obj.label = held
        st.phase = "inferring"
        placed = yield from self.put_away(obj)
        if placed and tracked_as != obj.label:  # the detector may name it as before: held back so too
            _, xy, receptacle = self.placed[-1]
            self.placed.append((tracked_as, xy, receptacle))
        if not placed:
            st.phase = "dropping"
            placed = yield from self.drop()
            if placed:
                self.dropped.append((obj.label, self.body.xy.copy()))
                if tracked_as != obj.label:
                    self.dropped.append((tracked_as, self.body.xy.copy()))
                self._rescore = True
                self.event("dropped", label=obj.label)
        st.target = None

    def pick(self, obj: TrackedObject, sighting: Sighting) -> Gen:
        """Pick ``obj`` up at the pixel of its sighting (again at the highest point over its
        footprint when that pixel hit its support; ``picked_at``: the last pick action); a
        picked object leaves the memory."""
        self.state.phase = "picking"
        self.picked_at = sighting.action(ActionName.PickupObject, self.body.obs.depth.shape)
        yield self.picked_at
        obs = self.body.obs
        if not obs.success and obs.error == "not_pickupable":
            # the pixel hit what the object stands on: try the highest point over its footprint
            again = raised_sighting(self.body, obj, reach=self.p.interact_m, skip=(sighting.u, sighting.v))
            if again is not None:
                self.event("pick_retry", label=obj.label, first=obs.message)
                self.picked_at = again.action(ActionName.PickupObject, self.body.obs.depth.shape)
                yield self.picked_at
                obs = self.body.obs
        if not obs.success:
            obj.meta["pick_fails"] = obj.meta.get("pick_fails", 0) + 1
            if obj.meta["pick_fails"] >= 2:
                obj.meta["give_up"] = f"pickup failed: {obs.error}"
            self.event("pick_failed", label=obj.label, error=obs.error, message=obs.message)
            return False
        self.body.mapper.memory.remove(obj.id)
        self.event(
            "picked",
            label=obj.label,
            track_id=obj.id,
            held_id=obs.held_id,
            oop_prob=round(obj.oop_prob or 0.0, 3),
        )
        return True

    def _still_out_of_place(self, obj: TrackedObject) -> bool:
        """Re-score a target seen from up close before picking it: the walk there refined its
        box and the receptacles around it, and a paragraph that now reads "in place" spares
        an object the mess-up never moved. Cleared twice: never flagged again."""
        objs = list(self.body.mapper.memory)
        probs = self.oop.score_all([obj], objs, self.room_type)
        if self.preferences is not None:
            probs = self.preferences.adjust_oop(probs, [obj], objs)
        prob = float(probs[obj.id])
        obj.oop_prob = prob
        if prob >= self.p.oop_threshold:
            return True
        obj.out_of_place = False
        obj.meta["cleared"] = obj.meta.get("cleared", 0) + 1
        if obj.meta["cleared"] >= 2:
            obj.meta["give_up"] = "in place when seen up close, twice"
        self.event(
            "oop_cleared",
            label=obj.label,
            track_id=obj.id,
            oop_prob=round(prob, 3),
            paragraph=obj.meta.get("paragraph"),
        )
        return False

    def approach(self, obj: TrackedObject, radius: float) -> Gen:
        """Walk next to a tracked object and get it in view within reach; its Sighting or None.

        The first stop is within ``radius`` of the object's footprint, and near enough that
        the eye-to-object distance can be within ``interact_m`` (a floor object is ~0.9 m
        below the camera, so it must be nearer in (x, y) than a table top). Seen but too far:
        the next try walks 0.25 m closer; not seen or no way there: the next try widens the
        ring and stands at least ``RETRY_AWAY_M`` from every spot already tried (another side
        of the object), up to ``APPROACH_TRIES`` walks.
        """
        radius = min(radius, self._reach_xy(obj))
        tried: list[np.ndarray] = []  # spots stood on without the object within reach
        closer = False
        for _attempt in range(APPROACH_TRIES):
            mask = goal_mask_near_box(self.body.mapper, obj.box_min, obj.box_max, radius)
            if tried and not closer:  # not seen or no way there: from another side
                away = mask_away_from(mask, self.body.mapper.grid, tried)
                mask = away if away.any() else mask
            arrived = yield from navigate(
                self.body, goal_mask=mask, stop_radius=0.05, budget=self.p.goal_step_budget
            )
            seen_far = False
            for pitch_try in range(2):
                yield from face_point(self.body, obj.centroid)
                sighting = find_in_view(self.body, obj)
                if sighting is None and self._pick_unseen(obj):
                    sighting = projected_sighting(self.body, obj, reach=self.p.interact_m)
                if sighting is not None and sighting.distance <= self.p.interact_m:
                    return sighting
                if sighting is not None:
                    seen_far = True
                    break  # seen but too far: walk closer
                if pitch_try == 0:  # not seen: try the neighbouring pitch
                    yield from pitch_to(
                        self.body, self.body.pose[3] + (30.0 if self.body.pose[3] < 60 else -30.0)
                    )
            if self.body.steps_left() <= 2:
                break
            tried.append(self.body.xy.copy())
            closer = seen_far and arrived
            radius = max(radius - MOVE_M, 0.25) if closer else radius + 0.15
        return None

    def _pick_unseen(self, obj: TrackedObject) -> bool:
        """Whether a track the detector does not see from up close may be picked at its projected
        centroid (when the depth there agrees): one seen twice, or once as surely out of place
        (``sure_oop``; a preference never makes a track seen once sure, see
        ``PreferenceProfile.adjust_oop``). Small objects on the floor are often detected once from
        afar and missed from above; one stray detection with a middling P(OOP) is not worth a pick."""
        return obj.n_obs >= 2 or (obj.oop_prob or 0.0) >= self.p.sure_oop

    def _reach_xy(self, obj: TrackedObject) -> float:
        """How far from the object's footprint, in (x, y), the agent can stand and still have
        its centroid within ``interact_m`` of the eye (less one move step of slack: poses are
        on a 0.25 m lattice and the footprint's edge is nearer than the centroid)."""
        assert self.body.obs is not None
        dz = float(self.body.obs.camera_pose[2, 3]) - float(obj.centroid[2])
        reach = math.sqrt(max(self.p.interact_m**2 - dz**2, 0.0))
        half = 0.5 * float(np.hypot(*(obj.box_max[:2] - obj.box_min[:2])))
        return max(reach - half - MOVE_M / 2, 0.25)

    # ------------------------------------------------------------------ placing
    def put_away(self, obj: TrackedObject) -> Gen:
        st = self.state
        preferred = self.preferences is not None and bool(self.preferences.about(obj.label))
        if self.cfg.variant == "3DSmntMap2Place" and not preferred:
            st.predictions = []
            return (yield from self.put_near_proposals(obj.label))
        if self.placement is None and not preferred:  # RandomReceptacle
            st.predictions = []
            return (yield from self.put_on_first_found(obj.label))
        ranked = (
            self.placement.predict(obj, self.body.mapper.memory, self.room_type) if self.placement else []
        )
        asked: list[str] = []  # receptacles a household asked for: searched for and tried to the end
        if self.preferences is not None:
            ranked = self.preferences.rank(obj.label, ranked)
            asked = self.preferences.asked(obj.label)
        st.predictions = ranked[:5]
        self.event("predicted", label=obj.label, top=[[r, round(p, 3)] for r, p in ranked[:5]])
        searched = None  # the class already searched for (Algorithm S1), not tried again
        top = ranked[0][0] if ranked else FLOOR
        if (self.p.missing_top == "search" or top in asked) and top != FLOOR and not self._instances(top):
            # Algorithm S1 (and always for an asked receptacle): the best receptacle is not in
            # memory: search for it first
            searched = top
            if (yield from self.search_and_put(obj.label, top, asked=top in asked)):
                return True
        st.phase = "placing"
        tried = 0
        missing: list[str] = []
        for label, _ in ranked:
            if tried >= self.p.max_receptacle_classes or self.body.steps_left() <= 2:
                break
            if label == searched:
                continue
            if label == FLOOR:
                st.target_receptacle = FLOOR
                tried += 1
                if (yield from self.drop()):
                    return self._placed(obj.label, FLOOR)
                continue
            instances = self._instances(label)
            if not instances:
                missing.append(label)
                continue
            tried += 1
            st.target_receptacle = label
            done: set[int] = set()
            for rec in instances if label in asked else instances[:2]:
                done.add(rec.id)
                if (yield from self.put_on(rec)):
                    return self._placed(obj.label, label)
            if label in asked:  # every mapped one failed (a stray track, full): look for another
                if (yield from self.search_and_put(obj.label, label, asked=True, skip=done)):
                    return True
        # Receptacles the model wants but the memory lacks: search for them.
        for label in missing[: self.p.max_receptacle_classes]:
            if (yield from self.search_and_put(obj.label, label, asked=label in asked)):
                return True
        return False

    def search_and_put(self, held: str, label: str, asked: bool = False, skip: set[int] | None = None) -> Gen:
        """Walk to search goals for receptacle class ``label`` (the visual search network's
        points, else unexplored space) until one is mapped; put the held object on it.

        ``asked``: a household's preference asks for ``label``: ``ASKED_SEARCH_FACTOR`` times
        the goals, and every instance mapped is tried (the search goes on after they all
        failed) before it gives up. ``skip``: ids of instances already tried in vain."""
        st = self.state
        st.phase, st.target_receptacle = "searching_receptacle", label
        goals = self.p.search_goals * (ASKED_SEARCH_FACTOR if asked else 1)
        tried = set() if skip is None else set(skip)
        while True:
            fresh = [r for r in self._instances(label) if r.id not in tried]
            for rec in fresh if asked else fresh[:1]:
                tried.add(rec.id)
                st.phase = "placing"
                if (yield from self.put_on(rec)):
                    return self._placed(held, label)
            if (fresh and not asked) or goals <= 0 or self.body.steps_left() <= self.p.reserve_steps:
                return False
            goal = self.search_goal(label)
            if goal is None:
                return False
            goals -= 1
            st.phase = "searching_receptacle"
            yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)
            yield from look_around(self.body, pitches=(30.0,))

    def search_goal(self, label: str) -> tuple[float, float] | None:
        """Where to look for a class not in memory: the visual search network's best point not
        visited yet for this label; without a network, unexplored space, else a random place."""
        if self.searcher is not None:
            goal = self.searched_point(label)
            if goal is not None:
                return goal
        mapper, reachable = self.body.mapper, reachable_mask(self.body)
        goal = sample_unexplored_goal(mapper.explored, reachable, mapper.grid, self.rng, tuple(self.body.xy))
        return goal or sample_reachable_goal(reachable, mapper.grid, self.rng, tuple(self.body.xy))

    def searched_point(self, label: str) -> tuple[float, float] | None:
        """The search network's best point for ``label`` at least 1 m from the points already
        visited for it (re-predicted each time: the map grows as the agent walks)."""
        assert self.searcher is not None
        mapper = self.body.mapper
        visited = self._visited.setdefault(label, [])
        heat = self.searcher.heatmap(mapper, label)
        points = self.searcher.points(mapper, label, tuple(self.body.xy), 3, visited=list(visited), heat=heat)
        self.search_view = SearchView(label, self.body.obs.step, heat, points)
        for p in points:
            if all(math.hypot(p[0] - v[0], p[1] - v[1]) >= 1.0 for v in visited):
                visited.append(p)
                self.event("search_point", label=label, x=round(p[0], 2), y=round(p[1], 2))
                return p
        return None

    def put_near_proposals(self, label: str) -> Gen:
        """3DSmntMap2Place: the search network conditioned on the object's own class proposes
        where such objects are; put it on the first receptacle mapped near a proposal."""
        self.state.phase = "searching_receptacle"
        for _ in range(self.p.search_goals):
            if self.body.steps_left() <= self.p.reserve_steps:
                break
            goal = self.searched_point(label) if self.searcher is not None else None
            if goal is None:
                break
            for rec in self._receptacles_near(goal, 1.5)[:2]:
                self.state.phase, self.state.target_receptacle = "placing", rec.label
                if (yield from self.put_on(rec)):
                    return self._placed(label, rec.label)
            yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)
            yield from look_around(self.body, pitches=(30.0,))
            for rec in self._receptacles_near(goal, 1.5)[:1]:
                self.state.phase, self.state.target_receptacle = "placing", rec.label
                if (yield from self.put_on(rec)):
                    return self._placed(label, rec.label)
        return False

    def _receptacles_near(self, xy: tuple[float, float], radius: float) -> list[TrackedObject]:
        p = np.asarray(xy)
        near = []
        for o in self.body.mapper.memory:
            if o.label not in PLACEABLE_RECEPTACLES or o.meta.get("full"):
                continue
            gap = np.maximum(0.0, np.maximum(o.box_min[:2] - p, p - o.box_max[:2]))
            d = float(np.hypot(*gap))
            if d <= radius:
                near.append((d, o))
        return [o for _, o in sorted(near, key=lambda t: t[0])]

    def _instances(self, label: str) -> list[TrackedObject]:
        """Tracks of a receptacle class to put things on: not full, not visited in vain
        (``unseen``: the detector saw no such receptacle from beside the track, a stray
        detection), those detected at least twice first, then the nearest."""
        xy = self.body.xy
        return sorted(
            (
                o
                for o in self.body.mapper.memory.of_label(label)
                if not o.meta.get("full") and not o.meta.get("unseen")
            ),
            key=lambda o: (o.n_obs < 2, float(np.linalg.norm(o.centroid[:2] - xy))),
        )

    def _placed(self, label: str, receptacle: str) -> bool:
        self.state.objects_fixed += 1
        self.placed.append(
            (label, self.body.xy.copy() if receptacle == FLOOR else self._last_put_xy, receptacle)
        )
        self._rescore = True
        self.event("placed", label=label, receptacle=receptacle)
        return True

    def put_on(self, rec: TrackedObject) -> Gen:
        """Go to a receptacle and put the held object on/in it (opening it first if needed).

        Up to ``APPROACH_TRIES`` walks and ``m_place_tries`` puts. From each spot reached the
        agent faces the receptacle's top; not detected there, it tries the neighbouring
        pitches before walking on. A spot from which it was not seen or not within reach is
        not stood on again: the next goal region keeps ``RETRY_AWAY_M`` from it; a put that
        found no free space sends the next walk to another side. The aim pixel keeps off the
        frame's border and off other receptacles' pixels (``aim_region``). A door that would
        hit the agent when opened ("blocked"): one step back and one more try; still blocked,
        the next spot is another one, at least 0.25 m farther from the box than this one.
        """
        shape = self.body.obs.depth.shape
        no_room: list[np.ndarray] = []  # points where a put found no free space or no receptacle
        tried: list[np.ndarray] = []  # spots from which it was not seen, or not within reach
        door_gap = 0.0  # a door hit the agent this far from the box: stand farther off
        seen = False
        puts = 0
        for attempt in range(max(APPROACH_TRIES, self.p.m_place_tries)):
            if self.body.steps_left() <= 2 or puts >= self.p.m_place_tries:
                break
            grid = self.body.mapper.grid
            radius = max((0.5, 0.35, 0.75)[attempt % 3], door_gap + 0.35)
            mask = goal_mask_near_box(self.body.mapper, rec.box_min, rec.box_max, radius)
            if door_gap:
                farther = mask & ~goal_mask_near_box(self.body.mapper, rec.box_min, rec.box_max, door_gap)
                mask = farther if farther.any() else mask
            if no_room:  # no free space where it aimed: go round to another side of the receptacle
                near = np.logical_or.reduce(
                    [goal_mask_near_box(self.body.mapper, q, q, 0.9) for q in no_room]
                )
                other = mask & ~near
                mask = other if other.any() else mask
            if tried:
                away = mask_away_from(mask, grid, tried)
                mask = away if away.any() else mask
            yield from navigate(self.body, goal_mask=mask, stop_radius=0.05, budget=self.p.goal_step_budget)
            top = rec.centroid.copy()
            top[2] = rec.box_max[2]
            yield from face_point(self.body, top)
            det = self._detection_of(rec)
            if det is None:  # the neighbouring pitches before another spot
                pitch = self.body.pose[3]
                for q in sorted(PITCHES, key=lambda q: abs(q - pitch)):
                    if abs(abs(q - pitch) - 30.0) > 1.0 or self.body.steps_left() <= 2:
                        continue
                    yield from pitch_to(self.body, q)
                    det = self._detection_of(rec)
                    if det is not None:
                        break
            sighting = self._aim(rec, det, no_room) if det is not None else None
            seen = seen or det is not None
            if sighting is None or sighting.distance > self.p.interact_m + 0.1:
                tried.append(self.body.xy.copy())
                continue  # not seen, or not within reach from here: walk again, elsewhere
            puts += 1
            yield sighting.action(ActionName.PutObject, shape)
            obs = self.body.obs
            if obs.success:
                self._last_put_xy = sighting.point[:2].copy()
                return True
            if obs.error == "receptacle_closed":
                opened = yield from self._open_and_put(rec, sighting, top, no_room)
                if opened is True:
                    return True
                if opened == "blocked":  # from another spot, farther from the door's swing
                    tried.append(self.body.xy.copy())
                    gap = float(footprint_gap(rec.box_min, rec.box_max, *self.body.xy))
                    door_gap = max(door_gap, gap) + 0.25
            elif obs.error in ("no_free_space", "not_receptacle"):  # aim elsewhere next time (not_receptacle:
                no_room.append(sighting.point)  # a wall or window above a shelf)
                if obs.error == "no_free_space" and self._count_full(rec):
                    return False
            self.event("put_failed", receptacle=rec.label, error=obs.error, message=obs.message)
        if not seen:
            rec.meta["unseen"] = True
            self.event(
                "put_failed",
                receptacle=rec.label,
                error="not_in_view",
                message=f"no {rec.label} detected from beside track {rec.id} in {attempt + 1} walks",
            )
        return False

    def _aim(self, rec: TrackedObject, det: Any, no_room: list[np.ndarray]) -> Sighting | None:
        """Where on ``det`` (a detection of ``rec``) to put: its top within the mapped box (the
        middle of its front for a cabinet, drawer, fridge or microwave: things go in, and the
        top of a base cabinet is the counter over it), away from points already tried, the
        frame's border and other receptacles' pixels."""
        return sighting_of(
            self.body,
            det,
            prefer_top=rec.label not in OPENABLE,
            reach=self.p.interact_m,
            avoid=no_room,
            within=(rec.box_min, rec.box_max),
            others=other_receptacles(self.body, det, PLACEABLE_RECEPTACLES),
            edge=EDGE_MARGIN,
        )

    def _open_and_put(
        self, rec: TrackedObject, sighting: Sighting, top: np.ndarray, no_room: list[np.ndarray]
    ) -> Gen:
        """Open a closed receptacle, put the held object in and close it again (also when the
        put fails: the room is left as it was). An opening refused as "blocked" (the door would
        hit the agent): step back, aim again, retry once; once it is open, step forward again if
        the step back left the put out of reach. True when put; "blocked" when the door still
        hit the agent; else False."""
        shape = self.body.obs.depth.shape
        for retry in range(2):
            yield sighting.action(ActionName.OpenObject, shape)
            if self.body.obs.success:
                put_at = sighting
                if retry:
                    put_at = (
                        yield from self._closer_after_step_back(rec, sighting, top, no_room)
                    ) or sighting
                yield put_at.action(ActionName.PutObject, shape)
                put, error = self.body.obs.success, self.body.obs.error
                if not put and error in REAIM_AFTER_OPENING:
                    # the pixel was aimed at the closed door: the open box's inside can lie
                    # beyond reach along it. Aim again at what this frame shows, closer if need be
                    again = yield from self._reaim_within_reach(rec, top, no_room)
                    if again is not None:
                        put_at = again
                        yield put_at.action(ActionName.PutObject, shape)
                        put, error = self.body.obs.success, self.body.obs.error
                if put:
                    self._last_put_xy = put_at.point[:2].copy()
                    yield from self._close(rec, put_at, top, no_room)
                    return True
                if error == "no_free_space":  # counted as a put on an open one is
                    self._count_full(rec)
                self.event("put_failed_closing", receptacle=rec.label)
                yield from self._close(rec, put_at, top, no_room)
                return False
            if self.body.obs.error != "blocked" or retry or self.body.steps_left() <= 4:
                return "blocked" if self.body.obs.error == "blocked" else False
            self.event("open_blocked", receptacle=rec.label)
            yield Action(ActionName.MoveBack)
            yield from face_point(self.body, top)
            det = self._detection_of(rec)
            again = self._aim(rec, det, no_room) if det is not None else None
            if again is None or again.distance > self.p.interact_m + 0.1:
                return False
            sighting = again
        return False

    def _reaim_within_reach(
        self, rec: TrackedObject, top: np.ndarray, no_room: list[np.ndarray]
    ) -> Generator[Action, None, Sighting | None]:
        """An aim at ``rec`` from the current frame within reach: as it is, else after one step
        towards it; None when there is none."""
        det = self._detection_of(rec)
        aim = self._aim(rec, det, no_room) if det is not None else None
        if aim is None or aim.distance > self.p.interact_m:
            aim = yield from self._step_in_and_aim(rec, top, no_room)
        return aim if aim is not None and aim.distance <= self.p.interact_m else None

    def _step_in_and_aim(
        self, rec: TrackedObject, top: np.ndarray, no_room: list[np.ndarray], event: str | None = None
    ) -> Generator[Action, None, Sighting | None]:
        """One step towards ``rec`` (``event`` said once it is taken), face its top and aim again;
        None when the step is refused (an open door, anything else in the way), steps are short
        or it is not detected from there."""
        if self.body.steps_left() <= 4:
            return None
        yield Action(ActionName.MoveAhead)
        if not self.body.obs.success:
            return None
        if event:
            self.event(event, receptacle=rec.label)
        yield from face_point(self.body, top)
        det = self._detection_of(rec)
        return self._aim(rec, det, no_room) if det is not None else None

    def _count_full(self, rec: TrackedObject) -> bool:
        """One more put on ``rec`` found no free space; True (and marked full) at the third."""
        rec.meta["full_tries"] = rec.meta.get("full_tries", 0) + 1
        rec.meta["full"] = rec.meta["full_tries"] >= 3
        return rec.meta["full"]

    def _close(self, rec: TrackedObject, at: Sighting, top: np.ndarray, no_room: list[np.ndarray]) -> Gen:
        """Close ``rec`` again, at ``at``; when that pixel is out of reach (the open door swung
        away from it), at a fresh aim within reach: a receptacle the agent opened is never left
        open because its first aim missed."""
        shape = self.body.obs.depth.shape
        yield at.action(ActionName.CloseObject, shape)
        if self.body.obs.success or self.body.obs.error not in REAIM_AFTER_OPENING:
            return
        error = self.body.obs.error
        again = yield from self._reaim_within_reach(rec, top, no_room)
        if again is not None:
            yield again.action(ActionName.CloseObject, shape)
            if self.body.obs.success:
                return
            error = self.body.obs.error
        self.event("close_failed", receptacle=rec.label, error=error)

    def _closer_after_step_back(
        self, rec: TrackedObject, sighting: Sighting, top: np.ndarray, no_room: list[np.ndarray]
    ) -> Generator[Action, None, Sighting | None]:
        """After a step back and an opening: step forward again when the put point is beyond
        reach; the new aim, or None to put from here."""
        if sighting.distance <= self.p.interact_m:
            return None
        return (yield from self._step_in_and_aim(rec, top, no_room, event="put_step_forward"))

    def _detection_of(self, rec: TrackedObject):
        """The detection of ``rec`` in the current frame; else the largest detection of its
        class (any instance will take the object; a track's box can be off where the detector
        still sees the receptacle)."""
        s = find_in_view(self.body, rec, max_pixel_gap=0.3)
        if s is not None:
            return s.detection
        return receptacle_in_view(self.body, frozenset({rec.label}))

    def put_on_first_found(self, label: str) -> Gen:
        """RandomReceptacle: walk to random places; put on the first receptacle in view."""
        shape = self.body.obs.depth.shape
        self.state.phase = "searching_receptacle"
        for _ in range(self.p.search_goals + 2):
            goal = sample_reachable_goal(
                reachable_mask(self.body), self.body.mapper.grid, self.rng, tuple(self.body.xy)
            )
            if goal is not None:
                yield from navigate(self.body, goal_xy=goal, budget=self.p.goal_step_budget)
            yield from pitch_to(self.body, 30.0)
            for _ in range(4):
                det = receptacle_in_view(self.body, PLACEABLE_RECEPTACLES)
                if det is not None:
                    sighting = sighting_of(self.body, det, prefer_top=True, reach=self.p.interact_m)
                    if sighting is not None and sighting.distance <= self.p.interact_m + 0.1:
                        self.state.phase, self.state.target_receptacle = "placing", det.label
                        yield sighting.action(ActionName.PutObject, shape)
                        if self.body.obs.success:
                            self._last_put_xy = sighting.point[:2].copy()
                            return self._placed(label, det.label)
                if self.body.steps_left() <= 2:
                    return False
                yield Action(ActionName.RotateLeft)
        return False

    def drop(self) -> Gen:
        """Put the held object on the floor in front of the agent (or beside it)."""
        yield from pitch_to(self.body, 60.0)
        for _ in range(4):
            if self.body.steps_left() <= 1:
                return False
            for u, v in ((0.5, 0.85), (0.3, 0.9), (0.7, 0.9)):
                yield Action(ActionName.PutObject, x=u, y=v)
                if self.body.obs.success:
                    return True
                if self.body.obs.error in ("hands_empty", "episode_over"):
                    return False
            yield Action(ActionName.RotateLeft)
        return False


# Explorers by name (the keys are agent.config.EXPLORERS): the next mapping goal, or None.
EXPLORER_GOALS: dict[str, Callable[[TidyPolicy, Any, np.ndarray], tuple[float, float] | None]] = {
    "random": TidyPolicy.explore_randomly,
    "frontier": TidyPolicy.explore_frontiers,
}
