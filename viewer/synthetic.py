"""Synthetic agent telemetry: a plausible tidy episode in a living room, with no agent.

Used by the viewer's tests and benchmark (and handy to try the viewer alone):
``SyntheticEpisode(seed).messages(step)`` gives the telemetry an agent would publish at
``step`` (status, frame, maps, memory, search), ``summary(steps)`` the episode's end;
``SyntheticAgent`` publishes them over Zenoh, declares the session's liveliness as a server
would, and answers viewer commands (pause, resume, step, new_episode, preference) with
``CommandAck``. Deterministic in (seed, step). No torch, no agent code.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.messages import (
    PHASES,
    AgentCommand,
    AgentFrame,
    AgentStatus,
    CommandAck,
    Detection2D,
    EpisodeSummary,
    MapSnapshot,
    ObjectMemoryMsg,
    ReceptaclePrediction,
    SearchHeatmap,
    TrackedObjectMsg,
)
from tidee.protocol.zenoh_config import make_config
from tidee.viewer.geometry import camera_pose_from_agent

log = logging.getLogger("tidee.viewer.synthetic")

CLASSES = [
    "Sofa",
    "CoffeeTable",
    "TVStand",
    "Television",
    "ArmChair",
    "Shelf",
    "DiningTable",
    "RemoteControl",
    "Book",
    "Pillow",
    "AlarmClock",
    "Laptop",
]
CELL = 0.05
VOXEL = 0.1
ROOM_MIN, ROOM_MAX = (-2.5, -2.0), (3.5, 3.0)  # start-frame extent of the room (x, y)
CAMERA_HEIGHT = 0.9
EXPLORE_RADIUS = 2.2  # metres the agent "sees" around each past pose


@dataclass(frozen=True)
class _Box:
    label: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


FURNITURE = [
    _Box("Sofa", (2.5, -1.6, 0.0), (3.3, 0.6, 0.85)),
    _Box("CoffeeTable", (1.0, -0.9, 0.0), (1.8, 0.1, 0.45)),
    _Box("TVStand", (-2.4, -1.0, 0.0), (-1.95, 1.0, 0.55)),
    _Box("Television", (-2.35, -0.6, 0.55), (-2.25, 0.6, 1.25)),
    _Box("ArmChair", (-1.4, 2.2, 0.0), (-0.6, 2.9, 0.9)),
    _Box("Shelf", (1.2, 2.6, 0.0), (2.4, 2.95, 1.8)),
    _Box("DiningTable", (-1.6, -1.9, 0.0), (-0.4, -1.1, 0.75)),
]
# Small objects: (label, centre, size, out of place?)
SMALL = [
    ("RemoteControl", (0.4, 1.2, 0.02), (0.18, 0.06, 0.03), True),
    ("Book", (-1.0, 2.55, 0.93), (0.22, 0.16, 0.04), False),
    ("Pillow", (2.9, 0.1, 0.95), (0.4, 0.4, 0.15), False),
    ("AlarmClock", (1.4, -0.4, 0.51), (0.12, 0.08, 0.12), True),
    ("Laptop", (-0.2, -0.8, 0.02), (0.34, 0.24, 0.03), True),
]
RECEPTACLES = ["CoffeeTable", "TVStand", "Shelf", "DiningTable", "Sofa", "ArmChair"]


def _loop_pose(step: int) -> tuple[float, float, float]:
    """(x, y, yaw_deg) along an elliptic tour of the room, ~0.05 m per step, starting at the
    origin facing +x (the start frame is the agent's pose at reset)."""
    a, b, cx, cy = 1.5, 1.1, 0.0, 1.1
    theta = 2 * math.pi * step * 0.05 / (math.pi * (a + b)) - math.pi / 2
    x, y = cx + a * math.cos(theta), cy + b * math.sin(theta)
    dx, dy = -a * math.sin(theta), b * math.cos(theta)
    return x, y, math.degrees(math.atan2(dy, dx))


def intrinsics(resolution: int, fov_deg: float = 90.0) -> np.ndarray:
    f = resolution / 2.0 / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0, resolution / 2.0], [0, f, resolution / 2.0], [0, 0, 1.0]])


@dataclass
class SyntheticEpisode:
    """Telemetry of a made-up episode; ``messages(step)`` is a pure function of (seed, step)."""

    seed: int = 0
    session: str = "synthetic"
    resolution: int = 128
    room_type: str = "LivingRoom"
    mess_index: int | None = 0
    _points: np.ndarray = field(init=False, repr=False)
    _labels: np.ndarray = field(init=False, repr=False)
    _occupancy: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        shape = (round((ROOM_MAX[0] - ROOM_MIN[0]) / CELL) + 2, round((ROOM_MAX[1] - ROOM_MIN[1]) / CELL) + 2)
        self.origin = (ROOM_MIN[0] - CELL, ROOM_MIN[1] - CELL)
        occ = np.ones(shape, np.uint8)
        occ[:2, :] = occ[-2:, :] = occ[:, :2] = occ[:, -2:] = 2  # walls
        for box in FURNITURE:
            occ[self._cells(box.lo[0], box.hi[0], 0), self._cells(box.lo[1], box.hi[1], 1)] = 2
        self._occupancy = occ
        self._points, self._labels = self._voxels()

    def _cells(self, lo: float, hi: float, axis: int) -> slice:
        return slice(int((lo - self.origin[axis]) / CELL), int(math.ceil((hi - self.origin[axis]) / CELL)))

    def _voxels(self) -> tuple[np.ndarray, np.ndarray]:
        pts, labels = [], []
        for box in FURNITURE + [
            _Box(n, tuple(np.subtract(c, np.divide(s, 2))), tuple(np.add(c, np.divide(s, 2))))
            for n, c, s, _ in SMALL
        ]:
            axes = [
                np.arange(lo + VOXEL / 2, max(hi, lo + VOXEL / 2 + 1e-6), VOXEL)
                for lo, hi in zip(box.lo, box.hi)
            ]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            # keep the shell: voxels on the box's surface, as a depth sensor sees them
            lo_idx = np.array([a[0] for a in axes])
            hi_idx = np.array([a[-1] for a in axes])
            shell = np.any(np.isclose(grid, lo_idx) | np.isclose(grid, hi_idx), axis=1)
            pts.append(grid[shell])
            labels.append(np.full(int(shell.sum()), CLASSES.index(box.label), np.int16))
        # walls: unlabelled voxels, coarser, up to 1.8 m
        zs = np.arange(VOXEL / 2, 1.8, 2 * VOXEL)
        xs = np.arange(ROOM_MIN[0], ROOM_MAX[0] + 1e-6, 2 * VOXEL)
        ys = np.arange(ROOM_MIN[1], ROOM_MAX[1] + 1e-6, 2 * VOXEL)
        walls = [
            np.array([(x, y, z) for x in xs for z in zs for y in (ROOM_MIN[1], ROOM_MAX[1])]),
            np.array([(x, y, z) for y in ys for z in zs for x in (ROOM_MIN[0], ROOM_MAX[0])]),
        ]
        for w in walls:
            pts.append(w)
            labels.append(np.full(len(w), -1, np.int16))
        return np.concatenate(pts).astype(np.float32), np.concatenate(labels)

    # --- what the agent believes at a step ---------------------------------------------
    def pose(self, step: int) -> tuple[float, float, float, float]:
        x, y, yaw = _loop_pose(step)
        return x, y, yaw, 30.0 if step % 40 < 20 else 0.0

    def _explored(self, step: int) -> np.ndarray:
        xs = self.origin[0] + (np.arange(self._occupancy.shape[0]) + 0.5) * CELL
        ys = self.origin[1] + (np.arange(self._occupancy.shape[1]) + 0.5) * CELL
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        seen = np.zeros(self._occupancy.shape, bool)
        for s in range(0, step + 1, 10):
            x, y, _ = _loop_pose(s)
            seen |= (gx - x) ** 2 + (gy - y) ** 2 < EXPLORE_RADIUS**2
        return seen

    def _seen(self, xy: np.ndarray, explored: np.ndarray) -> np.ndarray:
        i = np.clip(((xy[:, 0] - self.origin[0]) / CELL).astype(int), 0, explored.shape[0] - 1)
        j = np.clip(((xy[:, 1] - self.origin[1]) / CELL).astype(int), 0, explored.shape[1] - 1)
        return explored[i, j]

    def status(self, step: int, paused: bool = False) -> AgentStatus:
        phase = PHASES[1 + (step // 25) % (len(PHASES) - 2)]
        target = SMALL[(step // 150) % len(SMALL)]
        logits = np.array([math.sin(0.05 * step + k) * 2 for k in range(len(RECEPTACLES))])
        probs = np.exp(logits) / np.exp(logits).sum()
        order = np.argsort(-probs)[:5]
        traj = np.array([_loop_pose(s)[:2] for s in range(0, step + 1, max(1, step // 200 + 1))], np.float32)
        path = np.array([_loop_pose(s)[:2] for s in range(step, step + 30, 2)], np.float32)
        return AgentStatus(
            session=self.session,
            step=step,
            phase=phase,
            episode={
                "room_type": self.room_type,
                "seed": self.seed,
                "mess_index": self.mess_index,
                "variant": "tidee",
                "perception": "synthetic",
            },
            pose=self.pose(step),
            paused=paused,
            target_object=target[0],
            target_id=SMALL.index(target),
            target_receptacle=RECEPTACLES[int(order[0])],
            predictions=[ReceptaclePrediction(RECEPTACLES[int(k)], round(float(probs[k]), 4)) for k in order],
            held="Laptop" if 300 <= step % 600 < 360 else None,
            objects_fixed=min(step // 150, 3),
            oop_found=min(1 + step // 60, 3),
            done=False,
            message=f"{phase}: {target[0]} -> {RECEPTACLES[int(order[0])]}",
            trajectory=traj,
            path=path,
            goal=(float(path[-1, 0]), float(path[-1, 1])),
        )

    def frame(self, step: int) -> AgentFrame:
        r = self.resolution
        x, y, yaw, pitch = self.pose(step)
        rng = np.random.default_rng(self.seed * 100_003 + step)
        rows = np.linspace(0, 1, r, dtype=np.float32)[:, None]
        horizon = 0.5 - 0.5 * math.tan(math.radians(pitch)) / 1.0
        wall = np.array([205, 200, 185], np.float32)
        floor = np.array([150, 115, 80], np.float32)
        img = np.where((rows < horizon)[..., None], wall, floor) * (0.85 + 0.15 * rows[..., None])
        img = np.broadcast_to(img, (r, r, 3)).copy()
        floor_depth = CAMERA_HEIGHT / np.maximum(rows - horizon + 0.25, 0.05)
        depth = np.where(rows < horizon, 3.5, floor_depth).astype(np.float32)
        depth = np.broadcast_to(depth, (r, r)).copy()
        detections = []
        for k, (label, _, _, oop) in enumerate(SMALL[:3]):
            cx = (0.2 + 0.3 * k + 0.05 * math.sin(step * 0.1 + k)) * r
            cy = (0.55 + 0.1 * k) * r
            w, h = 0.14 * r, 0.1 * r
            box = (cx - w, cy - h, cx + w, cy + h)
            color = np.array([(60, 60, 200), (200, 60, 60), (60, 160, 60)][k], np.float32)
            img[int(box[1]) : int(box[3]), int(box[0]) : int(box[2])] = color
            depth[int(box[1]) : int(box[3]), int(box[0]) : int(box[2])] = 1.2 + 0.5 * k
            detections.append(
                Detection2D(
                    label,
                    round(0.8 + 0.05 * k, 3),
                    tuple(float(v) for v in box),
                    oop_prob=0.9 if oop else 0.1,
                    track_id=k,
                )
            )
        img += rng.normal(0, 4, img.shape)
        return AgentFrame(
            session=self.session,
            step=step,
            rgb=np.clip(img, 0, 255).astype(np.uint8),
            depth=depth,
            camera_pose=camera_pose_from_agent(x, y, yaw, pitch, CAMERA_HEIGHT),
            intrinsics=intrinsics(r),
            detections=detections,
            perception="synthetic",
        )

    def maps(self, step: int) -> MapSnapshot:
        explored = self._explored(step)
        occ = np.where(explored, self._occupancy, 0).astype(np.uint8)
        keep = self._seen(self._points[:, :2], explored)
        return MapSnapshot(
            session=self.session,
            step=step,
            origin=self.origin,
            cell=CELL,
            occupancy=occ,
            explored=explored,
            voxel_size=VOXEL,
            points=self._points[keep],
            point_labels=self._labels[keep],
            classes=list(CLASSES),
        )

    def memory(self, step: int) -> ObjectMemoryMsg:
        explored = self._explored(step)
        held_now = self.status(step).held
        objects = []
        for k, (label, c, s, oop) in enumerate(SMALL):
            if not self._seen(np.array([c[:2]]), explored)[0]:
                continue
            held = held_now == label
            centre = c if not held else (*self.pose(step)[:2], 0.6)
            lo = tuple(float(a - b / 2) for a, b in zip(centre, s))
            hi = tuple(float(a + b / 2) for a, b in zip(centre, s))
            objects.append(
                TrackedObjectMsg(
                    id=k,
                    label=label,
                    score=0.9,
                    centroid=tuple(float(v) for v in centre),
                    box_min=lo,
                    box_max=hi,
                    oop_prob=0.9 if oop else 0.1,
                    out_of_place=oop and k >= step // 150 % len(SMALL),
                    held=held,
                )
            )
        return ObjectMemoryMsg(session=self.session, step=step, objects=objects)

    def search(self, step: int) -> SearchHeatmap:
        box = FURNITURE[(step // 150) % len(FURNITURE)]
        shape = self._occupancy.shape
        xs = self.origin[0] + (np.arange(shape[0]) + 0.5) * CELL
        ys = self.origin[1] + (np.arange(shape[1]) + 0.5) * CELL
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        cx, cy = (box.lo[0] + box.hi[0]) / 2, (box.lo[1] + box.hi[1]) / 2
        heat = np.exp(-((gx - cx) ** 2 + (gy - cy) ** 2) / (2 * 0.6**2))
        heat += 0.5 * np.exp(-((gx - 0.3) ** 2 + (gy - 2.2) ** 2) / (2 * 0.4**2))
        heat = (heat / heat.max()).astype(np.float32)
        # ranked viewpoints: in front of the receptacle (towards the room's middle), then around it
        toward = np.array([0.5 - cx, 0.5 - cy]) / max(math.hypot(0.5 - cx, 0.5 - cy), 1e-6)
        side = np.array([-toward[1], toward[0]])
        c = np.array([cx, cy])
        points = np.array(
            [
                c + 1.0 * toward,
                c + 0.9 * toward + 0.7 * side,
                (0.3, 2.2),
                c + 0.9 * toward - 0.7 * side,
                c + 1.6 * toward,
            ],
            np.float32,
        )
        return SearchHeatmap(
            session=self.session,
            step=step,
            target=box.label,
            origin=self.origin,
            cell=CELL,
            heatmap=heat,
            points=points,
            source="synthetic",
        )

    def summary(self, steps: int, wall_s: float = 0.0, replay: str = "") -> EpisodeSummary:
        """How an episode of ``steps`` steps ended (kind ``summary``, sent once at the end)."""
        last = self.status(max(steps - 1, 0))
        moved = sum(oop for *_, oop in SMALL)
        return EpisodeSummary(
            session=self.session,
            episode=dict(last.episode),
            steps=steps,
            wall_s=round(wall_s, 2),
            end_reason="step budget",
            put_away=last.objects_fixed,
            moved=moved,
            found=min(last.oop_found, moved),
            plausible=min(last.objects_fixed, moved),
            false_picks=0,
            replay=replay,
        )

    def messages(
        self, step: int, paused: bool = False, kinds: tuple[str, ...] | None = None
    ) -> dict[str, Any]:
        """The telemetry of ``step`` (``kinds``: a subset of status, frame, maps, memory, search)."""
        makers = {
            "status": lambda: self.status(step, paused),
            "frame": lambda: self.frame(step),
            "maps": lambda: self.maps(step),
            "memory": lambda: self.memory(step),
            "search": lambda: self.search(step),
        }
        return {kind: make() for kind, make in makers.items() if kinds is None or kind in kinds}


# How often each kind goes out (every n-th step), as an agent would rate-limit them.
PUBLISH_EVERY = {"status": 1, "frame": 1, "memory": 2, "maps": 5, "search": 10}


class SyntheticAgent:
    """Publishes a ``SyntheticEpisode`` over Zenoh and answers viewer commands.

    ``listen=True`` makes this process the peer-mode rendezvous (as a server would be).
    ``work_ms``: CPU time burnt per step, to stand in for an agent's own computation
    (the benchmark measures how much a viewer slows that down).
    """

    def __init__(
        self,
        session: str = "synthetic",
        server_id: str = "sim0",
        endpoint: str | None = None,
        router: str | None = None,
        listen: bool = True,
        seed: int = 0,
        resolution: int = 128,
        rate_hz: float = 20.0,
        work_ms: float = 0.0,
    ) -> None:
        self.session = keys.check_id("session", session)
        self.server_id = keys.check_id("server_id", server_id)
        self.episode = SyntheticEpisode(seed=seed, session=session, resolution=resolution)
        self.rate_hz, self.work_ms = rate_hz, work_ms
        self.step = 0
        self.steps_published = 0
        self.paused = False
        self.acks: list[CommandAck] = []  # the last few, for tests
        self._single_steps = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._z = zenoh.open(make_config(listen=listen, endpoint=endpoint, router=router))
        self._token = self._z.liveliness().declare_token(keys.alive_session(server_id, session))
        self._pubs = {
            kind: self._z.declare_publisher(
                keys.agent_telemetry(session, kind), congestion_control=zenoh.CongestionControl.DROP
            )
            for kind in (*PUBLISH_EVERY, "ack", "summary")
        }
        self._commands = self._z.declare_subscriber(keys.agent_cmd(session), zenoh.handlers.FifoChannel(64))
        self._thread: threading.Thread | None = None

    def start(self, steps: int | None = None) -> SyntheticAgent:
        self._thread = threading.Thread(
            target=self.run, args=(steps,), daemon=True, name="tidee-synthetic-agent"
        )
        self._thread.start()
        return self

    def run(self, steps: int | None = None) -> float:
        """Publish until ``steps`` steps are out (None: until ``stop``); returns steps/s."""
        period = 1.0 / self.rate_hz if self.rate_hz > 0 else 0.0
        t0, published = time.perf_counter(), 0
        next_t = t0
        while not self._stop.is_set() and (steps is None or published < steps):
            self._handle_commands()
            with self._lock:
                advance = not self.paused or self._single_steps > 0
                if self.paused and self._single_steps > 0:
                    self._single_steps -= 1
            if advance:
                self.publish_step(self.step)
                self.step += 1
                published += 1
            else:  # paused: keep saying so
                self._pubs["status"].put(encode(self.episode.status(self.step, paused=True)))
            if period:
                next_t += period
                self._stop.wait(max(0.0, next_t - time.perf_counter()))
        elapsed = time.perf_counter() - t0
        if steps is not None and published >= steps:  # the episode's end, as an agent reports it
            self.publish_summary(elapsed)
        return published / elapsed if elapsed > 0 else 0.0

    def publish_summary(self, wall_s: float = 0.0) -> None:
        """Report the episode's end (``EpisodeSummary``) at the current step."""
        self._pubs["summary"].put(encode(self.episode.summary(self.step, wall_s)))

    def publish_step(self, step: int) -> None:
        if self.work_ms > 0:
            _burn(self.work_ms / 1000.0)
        kinds = tuple(k for k, every in PUBLISH_EVERY.items() if step % every == 0)
        for kind, msg in self.episode.messages(step, self.paused, kinds).items():
            self._pubs[kind].put(encode(msg))
        self.steps_published += 1

    def _handle_commands(self) -> None:
        while (sample := self._commands.try_recv()) is not None:
            try:
                cmd = decode(sample.payload.to_bytes(), expected=AgentCommand)
            except ProtocolError as e:
                log.warning("bad command: %s", e)
                continue
            ok, message = True, ""
            with self._lock:
                if cmd.kind == "pause":
                    self.paused, message = True, "paused"
                elif cmd.kind == "resume":
                    self.paused, message = False, "resumed"
                elif cmd.kind == "step":
                    self._single_steps += 1
                    message = "one step" if self.paused else "stepping (not paused)"
                elif cmd.kind == "new_episode":
                    self.episode = SyntheticEpisode(
                        seed=cmd.seed or 0,
                        session=self.session,
                        resolution=self.episode.resolution,
                        room_type=cmd.room_type or "LivingRoom",
                        mess_index=cmd.mess_index,
                    )
                    self.step, message = (
                        0,
                        f"new episode {cmd.room_type} seed {cmd.seed} mess {cmd.mess_index}",
                    )
                elif cmd.kind == "preference":
                    message = f"noted: {cmd.text!r} (synthetic agent: no learned response)"
            ack = CommandAck(self.session, cmd.command_id, cmd.kind, ok, message)
            self.acks = (self.acks + [ack])[-16:]
            self._pubs["ack"].put(encode(ack))

    def wait_for_subscriber(self, timeout: float) -> bool:
        """Wait until someone (a viewer) subscribes to this session's status; False on timeout."""
        deadline = time.monotonic() + timeout
        # zenoh's stubs type matching_status as bool; it is a MatchingStatus with .matching
        while not self._pubs["status"].matching_status.matching:  # type: ignore[attr-defined]
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None

    def close(self) -> None:
        self.stop()
        if self._z is None:
            return
        self._commands.undeclare()
        for pub in self._pubs.values():
            pub.undeclare()
        self._token.undeclare()
        self._z.close()
        self._z = None  # type: ignore[assignment]

    def __enter__(self) -> SyntheticAgent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _burn(seconds: float) -> None:
    """Busy CPU work for ``seconds`` (an agent's step is compute, not sleep)."""
    end = time.perf_counter() + seconds
    a = np.ones((64, 64), np.float32)
    while time.perf_counter() < end:
        a = a @ a * 1e-3 + 1.0


def write_synthetic_log(directory: str, steps: int, seed: int = 0, session: str = "synthetic") -> None:
    """An episode log (``protocol/episode_log.py`` format) of ``steps`` synthetic steps, for
    replay, ending with the episode's summary (in the log and in ``summary.json``), as an agent's."""
    import dataclasses

    from tidee.protocol.episode_log import LogWriter

    episode = SyntheticEpisode(seed=seed, session=session)
    with LogWriter(directory) as writer:
        for step in range(steps):
            kinds = tuple(k for k, every in PUBLISH_EVERY.items() if step % every == 0)
            for kind, msg in episode.messages(step, kinds=kinds).items():
                writer.message(kind, msg)
            writer.event(step=step, kind="step")
        summary = episode.summary(steps, replay=f"tidee viewer --replay {directory}")
        writer.message("summary", summary)
        writer.finish(
            {"steps": steps, "session": session, "synthetic": True, "summary": dataclasses.asdict(summary)}
        )


def main(argv: list[str] | None = None) -> int:
    """``python -m tidee.viewer.synthetic``: publish a synthetic episode (try the viewer without an agent)."""
    import argparse
    import json
    import signal

    from tidee.options import add_options, from_args
    from tidee.viewer.config import SyntheticConfig

    p = argparse.ArgumentParser(prog="python -m tidee.viewer.synthetic", description=main.__doc__)
    add_options(p, SyntheticConfig)
    cfg = from_args(SyntheticConfig, p.parse_args(argv))
    with SyntheticAgent(
        session=cfg.session,
        server_id=cfg.server_id,
        endpoint=cfg.endpoint,
        router=cfg.router,
        listen=not cfg.connect,
        resolution=cfg.resolution,
        rate_hz=cfg.rate_hz,
        work_ms=cfg.work_ms,
    ) as agent:
        for sig in (
            signal.SIGINT,
            signal.SIGTERM,
        ):  # explicit: a background job may start with SIGINT ignored
            signal.signal(sig, lambda *_: agent.stop())
        matched = agent.wait_for_subscriber(cfg.wait_viewer) if cfg.wait_viewer > 0 else False
        rate = agent.run(cfg.steps or None)
        print(
            json.dumps(
                {"steps": agent.steps_published, "steps_per_s": round(rate, 3), "viewer_matched": matched}
            ),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
