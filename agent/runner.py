"""The agent's episode loop: observation -> perception -> mapping -> policy -> action.

``EpisodeRunner.run(spec)`` plays one episode against any ``SimTransport`` (Zenoh
client or in-process), publishes telemetry when a publisher is attached, writes an
episode log when a log directory is given, and returns an ``EpisodeResult`` with
per-step timings and, when ``evaluate=True``, the evaluation record (the only place that
reads the server's privileged state: after the episode, for scoring).

A tidying episode runs ``TidyPolicy``; a rearrangement (``spec.rearrange_index``) runs
``RearrangePolicy`` over both phases: when it calls Done in the walkthrough (or the
walkthrough's budget runs out, which the runner tells it by throwing ``WalkthroughOver``),
the runner asks the server for the unshuffle phase and starts a fresh map in the same
start frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import CLASSES, PICKUPABLE
from tidee.agent.config import AgentConfig
from tidee.agent.mapping.config import wants_carving
from tidee.agent.mapping.geometry import start_to_world_xy
from tidee.agent.mapping.localise import ScanLocaliser, wants_localiser
from tidee.agent.mapping.maps import SemanticMapper
from tidee.agent.perception import make_perception
from tidee.agent.policy.rearrange import RearrangePolicy, WalkthroughOver
from tidee.agent.policy.skills import Body
from tidee.agent.policy.tidy import TidyPolicy
from tidee.agent.reasoning.oop import make_oop
from tidee.agent.reasoning.placement import make_placement
from tidee.agent.telemetry import TelemetryPublisher
from tidee.protocol.episode_log import LogWriter
from tidee.protocol.messages import (
    Action,
    ActionName,
    AgentCommand,
    AgentFrame,
    AgentStatus,
    Detection2D,
    EpisodeSpec,
    EpisodeSummary,
    ObjectMemoryMsg,
    Observation,
    ReceptaclePrediction,
    SearchHeatmap,
    TrackedObjectMsg,
    WalkthroughMemoryMsg,
)
from tidee.protocol.transport import SimTransport, send_step

log = logging.getLogger("tidee.agent")


@dataclass
class EpisodeResult:
    spec: EpisodeSpec
    steps: int
    wall_s: float
    end_reason: str
    objects_fixed: int
    timings: dict[str, list[float]] = field(default_factory=dict)  # ms per step
    record: dict[str, Any] | None = None  # evaluation record
    aborted_by: AgentCommand | None = None  # a new_episode command
    summary: EpisodeSummary | None = None  # what a person reads at the end


def episode_summary(
    session: str,
    info: dict[str, Any],
    steps: int,
    wall: float,
    end_reason: str,
    put_away: int,
    record: dict[str, Any] | None,
    replay: str = "",
) -> EpisodeSummary:
    """How the episode ended; the moved / found / plausible / false-pick counts come from the
    evaluation ``record`` (scored against the server's privileged state), None without one."""
    counts: dict[str, Any] = {}
    if record is not None and "rearrange" in record:
        counts = {"rearrange": {k: record["rearrange"][k] for k in REARRANGE_SUMMARY}}
    elif record is not None:
        from tidee.agent.evaluation.report import variant_metrics

        m = variant_metrics([record])[record["variant"]]
        counts = {k: int(m[k]) for k in ("moved", "found", "plausible", "false_picks")}
    return EpisodeSummary(
        session=session,
        episode=dict(info),
        steps=int(steps),
        wall_s=round(float(wall), 2),
        end_reason=end_reason,
        put_away=int(put_away),
        replay=replay,
        **counts,
    )


LOG_EVERY = 10  # an episode log keeps frames, maps and memory of every 10th step (and the last)

REARRANGE_SUMMARY = (
    "success",
    "fixed_strict",
    "misplaced",
    "energy",
    "start_misplaced",
    "fixed",
    "newly_misplaced",
)


def format_summary(s: EpisodeSummary) -> str:
    """One line for a terminal: what was moved, found, put away, judged plausible, and how to replay it."""
    e = s.episode
    mess = "tidy" if e.get("mess_index") is None else f"mess {e['mess_index']}"
    if e.get("rearrange_index") is not None:
        mess = f"rearrangement {e['rearrange_index']}"
    where = f"{e.get('room_type')} seed {e.get('seed')} {mess}"
    if s.rearrange is not None:
        r = s.rearrange
        scored = (
            f"restored {r['fixed']} of {r['start_misplaced']} changed, "
            f"newly misplaced {r['newly_misplaced']}, success {int(r['success'])}, "
            f"FixedStrict {r['fixed_strict']:.2f} (RoomR metrics)"
        )
    elif s.moved is None:
        scored = f"put away {s.put_away}"
    else:
        scored = (
            f"moved {s.moved}, found {s.found}, put away {s.put_away}, plausible {s.plausible}/{s.moved} "
            f"(catalog judge), false picks {s.false_picks}"
        )
    line = f"{where}: {scored}; {s.steps} steps, {s.wall_s:.1f} s ({s.end_reason})"
    return line + (f". Replay: {s.replay}" if s.replay else "")


@dataclass
class AgentModels:
    """The loaded models an agent configuration needs. Loading them takes seconds, so a batch
    worker keeps one set per ``key`` and reuses it across episodes (none keeps state between
    calls; a typed preference retrains the language OOP head, so a live agent owns its set)."""

    key: tuple[Any, ...]
    perception: Any
    depth_net: Any
    oop: Any
    placement: Any
    searcher: Any
    preferences: Any = None  # a PreferenceProfile (--preferences) or None

    @staticmethod
    def key_of(config: AgentConfig) -> tuple[Any, ...]:
        return (
            config.perception,
            config.detection_threshold,
            config.detector,
            config.depth,
            config.oop,
            config.variant,
            config.preferences,
        )

    @staticmethod
    def load(config: AgentConfig) -> AgentModels:
        perception = make_perception(config.perception, config.detection_threshold, config.detector)
        depth_net = None
        if config.depth == "estimated":
            from tidee.agent.perception.depth.model import DepthEstimator

            depth_net = DepthEstimator.load()
        oop = make_oop(config.oop)
        placement, searcher = make_placement(config.variant)
        preferences = None
        if config.preferences is not None:
            from tidee.agent.reasoning.preferences import PreferenceProfile

            preferences = PreferenceProfile.load(config.preferences)
        return AgentModels(
            AgentModels.key_of(config), perception, depth_net, oop, placement, searcher, preferences
        )


def worker_models(config: AgentConfig) -> AgentModels:
    """The ``AgentModels`` for an ``AgentConfig``, loaded once per batch worker and key (kept in
    ``tidee.batch.worker_state``)."""
    from tidee.batch import worker_state

    models: dict[Any, AgentModels] = worker_state().setdefault("models", {})
    key = AgentModels.key_of(config)
    if key not in models:
        models[key] = AgentModels.load(config)
    return models[key]


class EpisodeRunner:
    def __init__(
        self,
        config: AgentConfig,
        transport: SimTransport,
        session: str = "agent",
        publisher: TelemetryPublisher | None = None,
        log_dir: str | Path | None = None,
        on_step: Callable[[int], None] | None = None,
        models: AgentModels | None = None,
    ) -> None:
        self.cfg = config
        self.transport = transport
        self.session = session
        self.publisher = publisher
        self.log_dir = Path(log_dir) if log_dir else None
        self.on_step = on_step
        m = models if models is not None else AgentModels.load(config)
        if m.key != AgentModels.key_of(config):
            raise ValueError(
                f"models loaded for {m.key} cannot serve an agent configured as {AgentModels.key_of(config)}"
            )
        self.models = m
        self.perception, self.depth_net, self.oop = m.perception, m.depth_net, m.oop
        self.placement, self.searcher = m.placement, m.searcher
        self._search_sent: tuple[str, int] | None = None
        self._policy: Any = None  # the episode under way's TidyPolicy
        self.paused = False
        self._single_steps = 0

    def _apply_preference(self, text: str) -> tuple[bool, str]:
        """A placement preference in plain language: it joins the household's profile, which
        decides OOP and placement for what it names (every OOP mode and placement model); the
        language / fused OOP head also learns it (seconds)."""
        from tidee.agent.reasoning.preferences import PreferenceProfile

        if self.models.preferences is None:
            self.models.preferences = PreferenceProfile()
        try:
            pref = self.models.preferences.add(text)
        except ValueError as e:
            return False, f"could not use {text!r}: {e}"
        if self._policy is not None:  # the episode under way follows it from its next decision
            self._policy.preferences = self.models.preferences
        classifier = getattr(self.oop, "classifier", None)
        if classifier is None or pref.group is not None:
            return True, f"will follow {text!r}: {pref.describe()}"
        from tidee.agent.reasoning.language_oop.instructions import apply_instruction

        try:
            report = apply_instruction(classifier, text)
        except ValueError as e:
            return False, f"could not use {text!r}: {e}"
        return True, f"learned {text!r}: " + ", ".join(
            f"{k}={v}" for k, v in report.items() if isinstance(v, (int, float, str))
        )[:300]

    # ------------------------------------------------------------------ the loop
    def run(
        self, spec: EpisodeSpec, evaluate: bool = False, episode_name: str | None = None
    ) -> EpisodeResult:
        gt = self.perception.needs_ground_truth
        t_start = time.perf_counter()
        obs = self.transport.reset(spec, ground_truth=gt)
        initial = self.transport.state() if evaluate else None
        rearrange = spec.rearrange_index is not None
        policy_class = RearrangePolicy if rearrange else TidyPolicy
        # the tidy agent's commonsense: placement and search (a rearrangement's unmatched objects, when asked)
        common = not rearrange or self.cfg.policy.unmatched == "commonsense"
        map_config = dataclasses.replace(
            policy_class.map_config(self.cfg.map), carve=wants_carving(self.cfg.carve, self.cfg.depth)
        )
        mapper = SemanticMapper(map_config, CLASSES, passable=PICKUPABLE)
        body = Body(mapper)
        localiser = (
            ScanLocaliser(mapper.grid, mapper.config.obstacle_z, mapper.config.max_depth)
            if wants_localiser(self.cfg.localise, spec.pose_noise)
            else None
        )
        writer = LogWriter(self.log_dir / (episode_name or self._name(spec))) if self.log_dir else None
        events: list[dict[str, Any]] = []

        def on_event(**kw: Any) -> None:
            kw["step"] = body.obs.step if body.obs is not None else 0
            events.append(kw)
            if writer:
                writer.event(**kw)

        policy = policy_class(
            self.cfg,
            body,
            self.oop,
            self.placement if common else None,
            spec.room_type,
            on_event=on_event,
            searcher=self.searcher if common else None,
            preferences=None if rearrange else self.models.preferences,
        )
        unshuffle_start: dict | None = None  # a rearrangement's state when its unshuffle began (evaluation)
        self._policy = policy
        gen = policy.run()
        info = {
            "room_type": spec.room_type,
            "seed": spec.seed,
            "mess_index": spec.mess_index,
            "rearrange_index": spec.rearrange_index,
            "variant": "Rearrange" if rearrange else self.cfg.variant,
            "perception": self.cfg.perception,
            "oop": self.cfg.oop,
            "depth": self.cfg.depth,
            "explorer": self.cfg.explorer,
            "resolution": spec.resolution,
        }
        timings: dict[str, list[float]] = {
            "perception_ms": [],
            "mapping_ms": [],
            "planning_ms": [],
            "step_ms": [],
            "sim_ms": [],
        }
        trajectory: list[tuple[float, float]] = []
        picked: set[str] = set()
        put: set[str] = set()  # ids put down (a rearrangement's evaluation)
        held_before: str | None = None
        aborted: AgentCommand | None = None
        action: Action | None = None
        try:
            while True:
                t0 = time.perf_counter()
                if self.depth_net is not None:  # the "+est. depth" agent never reads the depth sensor
                    obs = dataclasses.replace(obs, depth=self.depth_net.predict(obs.rgb))
                if localiser is not None:  # the poses the agent believes: odometry, corrected
                    obs = localiser.correct(obs)
                dets = self.perception.detect(obs)
                t1 = time.perf_counter()
                touched = mapper.update(obs, dets)
                t2 = time.perf_counter()
                body.obs, body.detections = obs, dets
                policy.score_objects(touched)
                if obs.last_action == ActionName.PickupObject.value and obs.success and obs.held_id:
                    picked.add(obs.held_id)
                if obs.last_action == ActionName.PutObject.value and obs.success and held_before:
                    put.add(held_before)
                held_before = obs.held_id
                trajectory.append((float(obs.agent_pose[0]), float(obs.agent_pose[1])))
                walkthrough = obs.phase == "walkthrough"
                if obs.done and not walkthrough:
                    action = None
                else:
                    try:  # the walkthrough's budget spent: the policy wraps up its walkthrough
                        action = gen.throw(WalkthroughOver()) if obs.done else next(gen)
                    except StopIteration:
                        action = Action(ActionName.Done)
                t3 = time.perf_counter()
                timings["perception_ms"].append((t1 - t0) * 1e3)
                timings["mapping_ms"].append((t2 - t1) * 1e3)
                timings["planning_ms"].append((t3 - t2) * 1e3)
                emitted = False

                # This step's telemetry and log records, once: before a pause's wait, or while
                # the server acts on the step (send_step below).
                def emit(obs: Observation = obs, dets: list = dets) -> None:
                    nonlocal emitted
                    if not emitted:
                        emitted = True
                        self._emit(obs, dets, body, policy, info, trajectory, writer)

                aborted = self._handle_commands(body, policy, info, trajectory, writer, before_wait=emit)
                if aborted is not None or action is None:
                    emit()
                    break
                if writer:
                    writer.event(
                        kind="action",
                        step=obs.step,
                        action=action.name.value,
                        x=action.x,
                        y=action.y,
                        pose=list(obs.agent_pose),
                    )
                t4 = time.perf_counter()
                if walkthrough and action.name == ActionName.Done:
                    emit()
                    t4 = time.perf_counter()
                    self._emit_walkthrough(body.obs, policy, writer)
                    obs = self.transport.begin_unshuffle(ground_truth=gt)
                    mapper.reset()  # a fresh map of the shuffled room, in the same start frame
                    if localiser is not None:  # the agent is back at its start pose
                        localiser.new_phase()
                    body.path, body.goal = None, None
                    if evaluate:
                        unshuffle_start = self.transport.state()
                    on_event(kind="unshuffle_started", walkthrough_steps=int(body.obs.step))
                else:
                    # Over Zenoh the server acts while this step's telemetry is built and logged.
                    observe = send_step(self.transport, action, ground_truth=gt)
                    te = time.perf_counter()
                    emit()
                    t4 += time.perf_counter() - te  # sim_ms: the wait for the server, not the telemetry
                    obs = observe()
                t5 = time.perf_counter()
                timings["sim_ms"].append((t5 - t4) * 1e3)
                timings["step_ms"].append((t3 - t0) * 1e3)
                if self.on_step:
                    self.on_step(obs.step)
                if writer and not obs.success:
                    writer.event(
                        kind="action_failed",
                        step=obs.step,
                        action=obs.last_action,
                        error=obs.error,
                        message=obs.message,
                    )
        except Exception:
            if writer:
                writer.event(kind="crash", step=obs.step)
                writer.close()  # the log stays readable: every record so far is complete
            raise
        wall = time.perf_counter() - t_start
        end_reason = policy.state.end_reason or ("aborted" if aborted else "step cap")
        record = None
        if evaluate and rearrange:
            assert isinstance(policy, RearrangePolicy)
            record = self.rearrange_record(
                spec,
                initial,
                unshuffle_start,
                self.transport.state(),
                events,
                obs,
                wall,
                end_reason,
                policy,
                (picked, put),
            )
        elif evaluate:
            record = self.evaluation_record(
                spec, initial, self.transport.state(), events, picked, obs, wall, end_reason
            )
        replay = f"tidee viewer --replay {writer.dir}" if writer else ""
        summary = episode_summary(
            self.session, info, int(obs.step), wall, end_reason, policy.state.objects_fixed, record, replay
        )
        result = EpisodeResult(
            spec,
            int(obs.step),
            wall,
            end_reason,
            policy.state.objects_fixed,
            timings,
            record,
            aborted,
            summary,
        )
        if self.publisher:
            self.publisher.offer("summary", lambda: summary, force=True)
        if writer:
            writer.message("summary", summary)
            writer.finish(
                {
                    "episode": info,
                    "steps": result.steps,
                    "wall_s": round(wall, 2),
                    "end_reason": end_reason,
                    "objects_fixed": result.objects_fixed,
                    "events": len(events),
                    "summary": dataclasses.asdict(summary),
                    "record": record,
                }
            )
        log.info(
            "episode %s: %d steps, %.1f s, fixed %d (%s)",
            self._name(spec),
            result.steps,
            wall,
            result.objects_fixed,
            end_reason,
        )
        return result

    @staticmethod
    def _name(spec: EpisodeSpec) -> str:
        mess = "tidy" if spec.mess_index is None else f"mess{spec.mess_index}"
        if spec.rearrange_index is not None:
            mess = f"rearrange{spec.rearrange_index}"
        return f"{spec.room_type}_{spec.seed}_{mess}"

    # ------------------------------------------------------------------ telemetry
    def _status(
        self,
        obs: Observation,
        body: Body,
        policy: TidyPolicy,
        info: dict,
        trajectory: list[tuple[float, float]],
    ) -> AgentStatus:
        st = policy.state
        traj = np.asarray(trajectory[-2000:], np.float32).reshape(-1, 2)
        return AgentStatus(
            session=self.session,
            step=int(obs.step),
            phase=st.phase,
            episode=info,
            pose=tuple(float(v) for v in obs.agent_pose),
            paused=self.paused,
            target_object=st.target.label if st.target else None,
            target_id=st.target.id if st.target else None,
            target_receptacle=st.target_receptacle,
            predictions=[ReceptaclePrediction(r, float(p)) for r, p in st.predictions[:5]],
            held=obs.held,
            objects_fixed=st.objects_fixed,
            oop_found=st.oop_found,
            done=bool(obs.done),
            message=st.message,
            trajectory=traj,
            path=body.path if body.path is not None and len(body.path) else None,
            goal=body.goal,
        )

    def _emit(
        self,
        obs: Observation,
        dets: list,
        body: Body,
        policy: TidyPolicy,
        info: dict,
        trajectory: list[tuple[float, float]],
        writer: LogWriter | None,
    ) -> None:
        if self.publisher is None and writer is None:
            return
        mapper = body.mapper
        ids = mapper.last_track_ids

        def frame() -> AgentFrame:
            d2 = []
            for k, d in enumerate(dets):
                tid = ids[k] if k < len(ids) else None
                tracked = mapper.memory.get(tid) if tid is not None else None
                d2.append(
                    Detection2D(
                        d.label,
                        float(d.score),
                        tuple(float(v) for v in d.box),
                        oop_prob=tracked.oop_prob if tracked else d.oop_prob,
                        track_id=tid,
                    )
                )
            return AgentFrame(
                self.session,
                int(obs.step),
                np.asarray(obs.rgb),
                np.asarray(obs.depth, np.float32),
                np.asarray(obs.camera_pose),
                np.asarray(obs.intrinsics),
                d2,
                self.perception.name,
            )

        def memory() -> ObjectMemoryMsg:
            # a rearrangement's unshuffle: each object believed moved goes back to its walkthrough box
            goals = {
                m.now.id: tuple(float(v) for v in (m.then.box_min + m.then.box_max) / 2)
                for m in getattr(policy, "moves", [])
            }
            return ObjectMemoryMsg(
                self.session,
                int(obs.step),
                [
                    TrackedObjectMsg(
                        o.id,
                        o.label,
                        float(o.score),
                        tuple(map(float, o.centroid)),
                        tuple(map(float, o.box_min)),
                        tuple(map(float, o.box_max)),
                        o.oop_prob,
                        bool(o.out_of_place),
                        False,
                        goals.get(o.id),
                    )
                    for o in mapper.memory
                ],
            )

        def search() -> SearchHeatmap:
            view = policy.search_view
            assert view is not None
            grid = mapper.voxel_grid if view.heatmap.shape == mapper.voxel_grid.shape else mapper.grid
            return SearchHeatmap(
                self.session,
                int(obs.step),
                view.label,
                tuple(grid.origin),
                float(grid.cell),
                np.clip(view.heatmap, 0, 1).astype(np.float32),
                np.asarray(view.points, np.float32).reshape(-1, 2),
            )

        builders = {
            "status": lambda: self._status(obs, body, policy, info, trajectory),
            "frame": frame,
            "maps": lambda: mapper.snapshot(self.session, int(obs.step)),
            "memory": memory,
        }
        view = policy.search_view
        new_search = view is not None and (view.label, view.step) != self._search_sent
        if new_search:
            builders["search"] = search
            self._search_sent = (view.label, view.step)
        walk: WalkthroughMemoryMsg | None = getattr(self, "_walkthrough_msg", None)
        if self.publisher is not None and walk is not None and obs.phase == "unshuffle":
            # sent (and logged) once at the phase switch; again now and then for viewers that joined late
            self.publisher.offer("walkthrough", lambda: walk)
        final = bool(obs.done)
        for kind, build in builders.items():
            msg = None
            if self.publisher is not None:
                msg = self.publisher.offer(kind, build, force=final or kind == "search")
            # The log keeps every status and every new search heatmap, and the other kinds every
            # LOG_EVERY-th step only (viewers get more, rate-limited: a log of each would be 8x larger).
            if writer is not None and (kind in ("status", "search") or obs.step % LOG_EVERY == 0 or final):
                writer.message(kind, msg if msg is not None else build())

    def _emit_walkthrough(self, obs: Observation, policy: Any, writer: LogWriter | None) -> None:
        """The walkthrough's memory, once, as the walkthrough ends (telemetry kind ``walkthrough``)."""
        msg = WalkthroughMemoryMsg(
            self.session,
            int(obs.step),
            [
                TrackedObjectMsg(
                    i,
                    s.label,
                    1.0,
                    tuple(map(float, s.centroid)),
                    tuple(map(float, s.box_min)),
                    tuple(map(float, s.box_max)),
                )
                for i, s in enumerate(getattr(policy, "walkthrough", []))
            ],
        )
        self._walkthrough_msg = msg
        if self.publisher is not None:
            self.publisher.offer("walkthrough", lambda: msg, force=True)
        if writer is not None:
            writer.message("walkthrough", msg)

    # ------------------------------------------------------------------ commands
    def _handle_commands(
        self,
        body: Body,
        policy: TidyPolicy,
        info: dict,
        trajectory: list,
        writer: LogWriter | None,
        before_wait: Callable[[], None] = lambda: None,
    ) -> AgentCommand | None:
        """The viewer's commands since the last step; while paused, waits here (``before_wait``
        first: the viewer shows the step the agent waits at)."""
        if self.publisher is None:
            return None
        while True:
            for cmd in self.publisher.commands():
                if isinstance(cmd, str):
                    log.warning(cmd)
                    self.publisher.ack("", "malformed", False, cmd)
                    continue
                if cmd.kind == "pause":
                    self.paused = True
                    self.publisher.ack(cmd.command_id, cmd.kind, True, "paused")
                elif cmd.kind == "resume":
                    self.paused, self._single_steps = False, 0
                    self.publisher.ack(cmd.command_id, cmd.kind, True, "resumed")
                elif cmd.kind == "step":
                    self.paused, self._single_steps = True, self._single_steps + 1
                    self.publisher.ack(cmd.command_id, cmd.kind, True, "one step")
                elif cmd.kind == "new_episode":
                    self.publisher.ack(
                        cmd.command_id,
                        cmd.kind,
                        True,
                        f"starting {cmd.room_type} seed {cmd.seed} mess {cmd.mess_index}",
                    )
                    return cmd
                elif cmd.kind == "preference":
                    if writer:
                        writer.event(kind="preference", text=cmd.text)
                    ok, msg = self._apply_preference(cmd.text)
                    self.publisher.ack(cmd.command_id, cmd.kind, ok, msg)
            if not self.paused:
                return None
            if self._single_steps > 0:
                self._single_steps -= 1
                return None
            before_wait()
            self.publisher.offer(
                "status", lambda: self._status(body.obs, body, policy, info, trajectory), force=True
            )
            time.sleep(0.05)

    # ------------------------------------------------------------------ evaluation
    def rearrange_record(
        self,
        spec: EpisodeSpec,
        goal: dict | None,
        start: dict | None,
        end: dict,
        events: list[dict[str, Any]],
        obs: Observation,
        wall: float,
        end_reason: str,
        policy: RearrangePolicy,
        handled: tuple[set[str], set[str]],
    ) -> dict[str, Any]:
        """Score a rearrangement with RoomR's metrics (goal, unshuffle start and end states;
        evaluation only) and say where each change's score went (``fates``). An episode
        that never reached the unshuffle phase scores its walkthrough's end as the start
        (nothing was restored). ``handled``: the ids the agent picked up and put down."""
        from tidee.agent.evaluation.rearrange_fates import change_fates
        from tidee.agent.evaluation.rearrange_metrics import episode_metrics
        from tidee.agent.policy.rearrange import MIN_OBS

        assert goal is not None
        start = start if start is not None else end
        metrics = episode_metrics(goal["objects"], start["objects"], end["objects"])
        walk = next((e["walkthrough_steps"] for e in events if e["kind"] == "unshuffle_started"), None)
        # Which objects the agent's "moved" beliefs were about (the nearest of that type, within
        # 0.5 m of where it believed the object was at the start of the unshuffle phase).
        changed = {o["id"] for o in metrics["objects"] if o["misplaced_start"]}
        believed: set[str] = set()
        for e in events:
            if e["kind"] not in ("moved", "openness_changed") or "centroid" not in e:
                continue
            xy = np.asarray(start_to_world_xy(end["start"], e["centroid"]))
            near = [
                (float(np.linalg.norm(np.asarray(o["position"][:2]) - xy)), o["id"])
                for o in start["objects"]
                if o["type"] == e["label"]
            ]
            d, oid = min(near, default=(float("inf"), ""))
            believed.add(
                oid if d < 0.5 + (0.5 if e["kind"] == "openness_changed" else 0.0) else f"?{len(believed)}"
            )
        found = len(believed & changed)
        aims: dict[str, np.ndarray] = {}  # object id: the world (x, y) its put aimed at
        held: str | None = None
        for e in events:
            if e["kind"] == "picked":
                held = e.get("held_id")
            elif e["kind"] in ("put_back", "put_mended") and held is not None and "target" in e:
                aims[held] = start_to_world_xy(end["start"], e["target"])
        fates = change_fates(
            metrics,
            goal["objects"],
            start["objects"],
            end["objects"],
            end["start"],
            [(t.label, t.centroid, t.n_obs) for t in policy.walkthrough],
            [(t.label, t.centroid, t.n_obs) for t in policy.unshuffle],
            believed,
            *handled,
            min_obs=MIN_OBS,
            aims=aims,
        )
        return {
            "variant": "Rearrange",
            "perception": self.cfg.perception,
            "depth": self.cfg.depth,
            "pose_noise": spec.pose_noise,
            "depth_noise": spec.depth_noise,
            "split": None,
            "room_type": spec.room_type,
            "seed": spec.seed,
            "rearrange_index": spec.rearrange_index,
            "walkthrough_steps": walk,
            "steps": int(obs.step),
            "wall_s": round(wall, 2),
            "end_reason": end_reason,
            "believed_moved": sum(e["kind"] == "moved" for e in events),
            "believed_toggled": sum(e["kind"] == "openness_changed" for e in events),
            "changed_found": found,  # changed objects the agent believed changed
            "false_beliefs": len(believed) - found,  # beliefs about objects that had not changed
            "rearrange": metrics,
            "fates": fates,
        }

    def evaluation_record(
        self,
        spec: EpisodeSpec,
        initial: dict | None,
        final: dict,
        events: list[dict[str, Any]],
        picked: set[str],
        obs: Observation,
        wall: float,
        end_reason: str,
    ) -> dict[str, Any]:
        """Score the episode against the server's privileged state (evaluation only)."""
        assert initial is not None
        mess = {m["id"]: m for m in initial.get("mess", [])}
        start = final["start"]
        flagged = [
            (e["label"], start_to_world_xy(start, e["centroid"])) for e in events if e["kind"] == "oop_found"
        ]
        init_objs = {o["id"]: o for o in initial["objects"]}
        objects = []
        for o in final["objects"]:
            if not o["pickupable"] or o["id"] not in init_objs:
                continue
            first = init_objs[o["id"]]
            moved = o["id"] in mess
            pos0 = np.asarray(first["position"][:2])
            found = o["id"] in picked or (
                moved
                and any(lbl == o["type"] and float(np.linalg.norm(xy - pos0)) < 0.75 for lbl, xy in flagged)
            )
            objects.append(
                {
                    "id": o["id"],
                    "type": o["type"],
                    "variant": o.get("variant"),
                    "moved": moved,
                    "found": bool(found),
                    "picked": o["id"] in picked,
                    "original_parent_type": mess[o["id"]]["original_parent_type"]
                    if moved
                    else first["parent_type"],
                    "messy_parent_type": first["parent_type"],
                    "final_parent_type": o["parent_type"],
                }
            )
        receptacles = sorted(
            {o["type"] for o in final["objects"] if o.get("receptacle") and not o.get("pickupable")}
        )
        return {
            "variant": self.cfg.variant,
            "perception": self.cfg.perception,
            "oop": self.cfg.oop,
            "split": None,
            "room_type": spec.room_type,
            "seed": spec.seed,
            "mess_index": spec.mess_index,
            "steps": int(obs.step),
            "wall_s": round(wall, 2),
            "end_reason": end_reason,
            "present_receptacles": receptacles,
            "objects": objects,
        }
