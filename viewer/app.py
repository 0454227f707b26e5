"""The viewer process: a viser server fed by live Zenoh telemetry or by a saved log.

One update worker thread does all decoding and drawing, at most ``rate_hz`` times a
second, applying only the newest message of each kind (latest wins), every batch inside
``server.atomic()``. GUI callbacks (viser's thread pool) only record what was asked or
put a command on Zenoh. Memory stays flat: no list grows with the episode (the live plot
is a bounded deque; the trajectory arrives whole in each status message; the camera-coloured
cloud keeps at most ``scene_view.RGB_MAX_POINTS`` voxels).

A rearrangement's two phases are one episode: its walkthrough memory (sent once, when the
walkthrough ends) stays drawn through the unshuffle phase, whose step count starts again at 0
(``phases.py``); a replay lays the unshuffle after the walkthrough on one step axis.

When the agent reports the episode's end (an ``EpisodeSummary``), the page shows it in an
"Episode finished" panel and stays live; when the viewer itself stops, it first tells the
open pages so (they freeze, dimmed, once the connection closes).

Who may send commands: ``access.AccessGate`` (``read_only``, and a token when the page
is served beyond loopback).

``run_viewer(config)`` starts it in-process and returns a handle (``.url``, ``.stop()``);
``serve(config)`` runs it until SIGINT/SIGTERM (``tidee viewer``).
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from tidee.launch import check_bindable, free_port, wait_for_signal
from tidee.protocol.messages import (
    AgentCommand,
    AgentFrame,
    AgentStatus,
    EpisodeSummary,
    MapSnapshot,
    SearchHeatmap,
)
from tidee.viewer import access, geometry, images, palette
from tidee.viewer.config import ViewerConfig
from tidee.viewer.feed import OBSERVATION, LiveFeed
from tidee.viewer.panels import Panels
from tidee.viewer.phases import rearrangement_phase, unshuffle_began
from tidee.viewer.replay import REPLAYED_KINDS, ReplayLog
from tidee.viewer.scene_view import LABEL_FALLBACK_HEIGHT, SceneView, oracle_objects

log = logging.getLogger("tidee.viewer")

HISTORY_POINTS = 600  # live plot: (step, fixed, OOP found) rows kept
SESSION_REFRESH_S = 1.0
DRAW_ORDER = ("maps", "memory", "walkthrough", "search", "frame", OBSERVATION, "status", "ack", "summary")
REPLAY_FUSE_MAX = 150  # replay: frames fused into the coloured cloud when jumping ahead, at most
MAP_POSE_PERIOD_S = 0.25  # live: a status alone (the agent moved) redraws the 2D map at most this often
STOP_NOTE_S = 0.3  # on stop: time for the "viewer stopped" note to reach the browsers


@dataclass
class ViewerStats:
    """What the update worker has done (read by tests and the benchmark)."""

    updates: int = 0  # worker cycles that drew something
    applied: dict[str, int] = field(default_factory=lambda: collections.defaultdict(int))
    last_step: int = -1
    started: float = field(default_factory=time.monotonic)


class ViewerApp:
    def __init__(self, config: ViewerConfig) -> None:
        self.config = config
        self.replay = ReplayLog(config.replay) if config.replay else None
        self.feed: LiveFeed | None = None
        self.stats = ViewerStats()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._lock = threading.Lock()  # guards the requests below (GUI threads -> worker)
        self._requests: dict[str, Any] = {}
        self._history: collections.deque[tuple[float, float, float]] = collections.deque(
            maxlen=HISTORY_POINTS
        )
        self._session_shown: str | None = None
        self._camera_aimed = False  # at the first map of each session
        self._map_drawn = 0.0  # when the 2D map was last drawn (monotonic s)
        self._latest: dict[str, Any] = {}  # the newest message of each kind on screen
        self._agent_frames = False  # this session sends AgentFrames (else observations fill in)
        # Live, with no browser connected: the newest camera frame and whether the 2D map is due,
        # drawn once one connects (nobody would see the images; encoding them costs a core's time).
        self._camera_pending: Any = None
        self._map_pending = False
        self._oracle_on = False
        self._oracle_thread: threading.Thread | None = None
        self._replay_step = self.replay.first_step if self.replay else 0
        self._replay_playing, self._replay_rate = False, 10.0
        self._replay_shown: dict[str, int | None] = {}
        self._cloud_upto = -1  # replay: the last frame index fused into the coloured cloud
        self.access = access.AccessGate(access.required_token(config.host, config.token), config.read_only)

        # viser moves to the next free port when one is taken (and retries forever on a host it cannot
        # bind): check first, and refuse a moved port, so the printed URL is the one asked for.
        check_bindable(
            config.host,
            config.port,
            f"viewer --host {config.host} --port {config.port}",
            " (choose another --port, or --port 0 for any free port)",
        )
        port = config.port or free_port(config.host)
        self.server = viser.ViserServer(host=config.host, port=port, label="tidee", verbose=False)
        if self.server.get_port() != port:
            self.server.stop()
            raise OSError(
                f"viewer --port {port}: port {port} on {config.host} was taken while the viewer "
                f"started (choose another --port, or --port 0 for any free port)"
            )
        self.url = f"http://{_display_host(config.host)}:{self.server.get_port()}"
        self.server.on_client_connect(self._on_client_connect)
        self.server.on_client_disconnect(lambda client: self.access.forget(client.client_id))
        try:
            self.scene = SceneView(self.server, max_points=config.max_points)
            steps = (self.replay.first_step, self.replay.last_step) if self.replay else None
            self.panels = Panels(
                self.server, self, steps, initial_session=config.session, read_only=config.read_only
            )
            if self.replay is None:
                self.feed = LiveFeed(config.endpoint, config.router, config.session, config.zenoh_config)
        except BaseException:
            self.server.stop()
            raise
        self._worker = threading.Thread(target=self._run, daemon=True, name="tidee-viewer-update")

    # --- lifecycle ------------------------------------------------------------------------
    def start(self) -> ViewerApp:
        self._worker.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10)
        if self._oracle_thread is not None:
            self._oracle_thread.join(timeout=5)
        if self.feed is not None:
            self.feed.close()
        if self.server.get_clients():  # a page left open freezes (dimmed) once we go: say why
            summary: EpisodeSummary | None = self._latest.get("summary")
            again = (
                f"Replay the episode: `{summary.replay}`" if summary is not None and summary.replay else ""
            )
            self.panels.show_stopped(again)
            time.sleep(STOP_NOTE_S)
        self.server.stop()

    # --- the update worker -----------------------------------------------------------------------
    def _run(self) -> None:
        """Requests from the GUI are handled as soon as they come (a wake-up); telemetry is
        drawn at most ``rate_hz`` times a second, however often the worker wakes."""
        period = 1.0 / self.config.rate_hz
        next_draw = next_sessions = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                self._handle_requests()
                if now >= next_draw:
                    next_draw = now + period
                    if self.replay is not None:
                        self._replay_tick(period)
                    else:
                        self._live_tick()
                if self.feed is not None and now >= next_sessions:
                    self._refresh_sessions()
                    next_sessions = now + SESSION_REFRESH_S
            except Exception:  # a bad message must not end the viewer
                log.exception("viewer update failed")
            self._wake.wait(max(0.0, next_draw - time.monotonic()))
            self._wake.clear()

    def _live_tick(self) -> None:
        assert self.feed is not None
        msgs = self.feed.poll()
        selected = self.feed.selected
        if selected != self._session_shown:
            self._switch_session(selected)
            # a choice made during the poll: keep only the new session's messages
            msgs = {k: m for k, m in msgs.items() if getattr(m, "session", selected) == selected}
        if msgs:
            self._draw(msgs)
        with self.server.atomic():
            self.scene.push_cloud()  # the last frames' colours, once due (frames may have stopped)
            if not msgs and (self._camera_pending is not None or self._map_pending):
                self._draw_images()  # a browser connected since: the images kept for it

    def _switch_session(self, session: str | None) -> None:
        with self.server.atomic():
            self.scene.clear()
            self.panels.show_summary(None)
            self.panels.show_phase(None)
        self._session_shown, self._latest, self._agent_frames = session, {}, False
        self._camera_pending, self._map_pending = None, False
        self._camera_aimed = False
        self._history.clear()
        self.panels.show_title(self._title())
        log.info("viewer: showing session %s", session)

    def _draw(self, msgs: dict[str, Any]) -> None:
        """Apply one batch (at most one message per kind) to the scene and panels."""
        status, shown = msgs.get("status"), self._latest.get("status")
        if (
            status is not None
            and shown is not None
            and status.step < shown.step
            and not unshuffle_began(shown, status)  # a rearrangement's second phase: the same episode
        ):
            self._switch_session(self._session_shown)  # a new episode: drop the old one's layers
        with self.server.atomic():
            for kind in DRAW_ORDER:
                msg = msgs.get(kind)
                if msg is None:
                    continue
                self._apply(kind, msg)
                self.stats.applied[kind] += 1
            status_due = "status" in msgs and (
                self.replay is not None
                or msgs["status"].done
                or time.monotonic() - self._map_drawn >= MAP_POSE_PERIOD_S
            )
            if "maps" in msgs or "search" in msgs or status_due:
                self._map_pending = True
                self._map_drawn = time.monotonic()
            self._draw_images()
        self.stats.updates += 1
        self.panels.show_title(self._title())

    def _apply(self, kind: str, msg: Any) -> None:
        if kind == "ack":
            self.panels.show_ack(msg)
            return
        if kind == "summary":
            self._latest[kind] = msg
            self.panels.show_summary(msg)
            return
        if kind == OBSERVATION:
            if self._agent_frames:
                return  # the agent's own frames (with detections) take precedence
            self.scene.apply_frame(msg)
            self._camera_pending = msg
            return
        self._latest[kind] = msg
        self.scene.apply(kind, msg)
        if isinstance(msg, MapSnapshot):
            self._show_legend(msg)
            known = geometry.known_plane(msg.origin, msg.cell, msg.occupancy, margin=1.5)
            if not self._camera_aimed and known is not None:
                self._aim_camera(known)  # at what has been mapped, not the whole (12.8 m) grid
                self._camera_aimed = True
        elif isinstance(msg, AgentFrame):
            self._agent_frames = True
            self._camera_pending = msg
        elif isinstance(msg, AgentStatus):
            if self.replay is None:  # a replay counts steps on its own axis (_replay_tick)
                self.stats.last_step = msg.step
            self.panels.show_status(msg)
            if self._history and msg.step < self._history[-1][0]:
                self._history.clear()  # a new episode started
            if not self._history or msg.step > self._history[-1][0]:
                self._history.append((float(msg.step), float(msg.objects_fixed), float(msg.oop_found)))
            if self.replay is None:
                self.panels.show_plot(np.array(self._history), final=bool(msg.done))

    def _watched(self) -> bool:
        """Whether the camera and map images are drawn now: always in a replay, live only while
        a browser is connected (the newest ones are drawn when one connects)."""
        return self.replay is not None or bool(self.server.get_clients())

    def _draw_images(self) -> None:
        """The camera panel (the newest frame) and the 2D map, when due and watched."""
        if not self._watched():
            return
        msg, self._camera_pending = self._camera_pending, None
        if isinstance(msg, AgentFrame):
            self.panels.show_camera(
                images.draw_detections(msg.rgb, msg.detections), images.colorize_depth(msg.depth)
            )
        elif msg is not None:
            self.panels.show_camera(
                images.upscale(np.asarray(msg.rgb), 512)[0], images.colorize_depth(msg.depth)
            )
        if self._map_pending:
            self._map_pending = False
            self._draw_map()

    def _show_legend(self, msg: MapSnapshot) -> None:
        labels = np.asarray(msg.point_labels)
        valid = labels[(labels >= 0) & (labels < len(msg.classes))].astype(np.int64)
        counts = np.bincount(valid, minlength=len(msg.classes))
        self.panels.show_legend(palette.legend_html(msg.classes, counts))

    def _draw_map(self) -> None:
        maps: MapSnapshot | None = self._latest.get("maps")
        if maps is None or maps.occupancy.size == 0 or maps.cell <= 0:
            return
        status: AgentStatus | None = self._latest.get("status")
        search: SearchHeatmap | None = self._latest.get("search")
        # the mapped part only (a 12.8 m grid is mostly unknown): the room fills the panel
        occupancy, explored, origin = images.crop_to_known(
            maps.occupancy, maps.explored, maps.origin, maps.cell
        )
        img = images.occupancy_image(
            occupancy,
            explored,
            origin,
            maps.cell,
            pose=status.pose if status else None,
            trajectory=status.trajectory if status else None,
            path=status.path if status else None,
            goal=status.goal if status else None,
            search_points=search.points if search is not None else None,
        )
        self.panels.show_map(img)

    def _title(self) -> str:
        finished = " · **episode finished**" if "summary" in self._latest else ""
        if self.replay is not None:
            return (
                f"**tidee viewer** · replay of `{os.path.basename(os.path.abspath(self.replay.directory))}` "
                f"· session {self.replay.session or '?'}{finished}"
            )
        assert self.feed is not None
        session = self._session_shown or "none yet"
        mode = "pinned" if self.feed.pinned else "newest"
        err = f" · **{self.feed.decode_errors} undecodable**" if self.feed.decode_errors else ""
        step = f" · step {self.stats.last_step}" if self.stats.last_step >= 0 else ""
        return f"**tidee viewer** · session `{session}` ({mode}){step}{finished} · via {self.feed.where}{err}"

    def _refresh_sessions(self) -> None:
        assert self.feed is not None
        self.panels.show_sessions(self.feed.sessions(), self.feed.selected if self.feed.pinned else None)

    def _aim_camera(self, plane: geometry.FloorPlane) -> None:
        view = geometry.overview_camera(plane)
        self.server.initial_camera.position = view.position
        self.server.initial_camera.look_at = view.look_at
        # labels laid out for this view until a browser reports its own camera
        self.scene.set_label_view(
            geometry.screen_view_looking_at(view, self.server.initial_camera.fov, LABEL_FALLBACK_HEIGHT)
        )
        for client in self.server.get_clients().values():
            try:
                with client.atomic():
                    client.camera.position = view.position
                    client.camera.look_at = view.look_at
            except (AssertionError, ValueError):
                pass  # the client has not reported its camera yet; it gets the initial camera

    def _on_client_connect(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(self._camera_moved)
        self._wake.set()  # draw the images kept while nobody watched
        if self.access.needs_token and self.replay is None:
            self.panels.add_token_input(client)

    def _camera_moved(self, camera: viser.CameraHandle) -> None:
        """A browser's camera moved: lay the 3D labels out again for what it sees."""
        try:
            view = geometry.screen_view(camera.position, camera.wxyz, camera.fov, camera.image_height)
        except (AssertionError, ValueError):
            return  # not reported yet, or a degenerate canvas
        with self._lock:
            self._requests["label_view"] = view
        self._wake.set()

    # --- replay ----------------------------------------------------------------------------------
    def _replay_tick(self, period: float) -> None:
        assert self.replay is not None
        with self._lock:
            if self._replay_playing:
                advance = max(1, round(self._replay_rate * period))
                self._replay_step = min(self.replay.last_step, self._replay_step + advance)
                if self._replay_step >= self.replay.last_step:
                    self._replay_playing = False
            step = self._replay_step
        current = {kind: self.replay.index_at(kind, step) for kind in REPLAYED_KINDS}
        shown = self._replay_shown
        changed = [k for k, i in current.items() if i != shown.get(k, -1)]
        if not changed:
            return
        msgs = {k: v for k, v in self.replay.at(step).items() if k in changed}
        if any(shown.get(k) is not None and (current[k] is None or current[k] < shown[k]) for k in changed):
            # slid back: start clean and draw everything current at this step
            with self.server.atomic():
                self.scene.clear()
                self.panels.show_summary(None)
                self.panels.show_phase(None)
            self._latest, self._agent_frames, self._cloud_upto = {}, False, -1
            msgs = self.replay.at(step)
        self._replay_shown = current
        self._catch_up_cloud(current["frame"])
        if msgs:
            self._draw(msgs)
        if current["status"] is not None:
            self.stats.last_step = self.replay.step_of("status", current["status"])
        with self.server.atomic():
            self.scene.push_cloud(force=True)
        self.panels.show_plot(self.replay.history(step), final=True)  # exact at every slider position
        trunc = f" · **log truncated** ({self.replay.corrupt_message})" if self.replay.truncated else ""
        status: AgentStatus | None = self._latest.get("status")
        local = ""
        if status is not None and rearrangement_phase(status) is not None and status.step != step:
            local = f" ({rearrangement_phase(status)} step {status.step})"
        self.panels.show_replay_step(
            step,
            f"step {step}{local} of {self.replay.first_step}–{self.replay.last_step} · "
            f"{self.replay.messages} messages{trunc}",
        )

    def _catch_up_cloud(self, frame: int | None) -> None:
        """Replay: fuse the frames up to ``frame`` (its index in the log) not fused yet, so the
        coloured cloud holds what the camera saw up to this step, however the slider moved."""
        assert self.replay is not None
        if frame is None or frame <= self._cloud_upto:
            return
        for logged in self.replay.frames(self._cloud_upto + 1, frame, max_frames=REPLAY_FUSE_MAX):
            self.scene.fuse_frame(logged)
        self._cloud_upto = frame

    # --- PanelActions (viser's thread pool) -------------------------------------------------------
    def select_session(self, session: str | None) -> None:
        if self.feed is not None:
            self.feed.select(session)
            self._wake.set()

    def command(self, kind: str, client_id: int | None = None, **fields: object) -> None:
        """Send ``kind`` to the shown session's agent, if the access gate lets ``client_id``
        (None: this process, not a browser) do so; a refused client is told why."""
        refused = self.access.refusal(client_id)
        if refused is not None:
            log.warning("viewer: %s from client %s refused: %s", kind, client_id, refused)
            self._notify(client_id, f"{kind} not sent", refused)
            return
        if self.feed is None:
            return
        try:
            cmd = AgentCommand(kind=kind, command_id=uuid.uuid4().hex[:12], **fields)  # type: ignore[arg-type]
            target = self.feed.send(cmd)
        except (ValueError, RuntimeError) as e:
            self.panels.show_sent(f"**not sent**: {e}")
            return
        self.panels.show_sent(
            f"**{kind}** sent to `{target}` (id {cmd.command_id}); waiting for the agent's ack…"
        )

    def present_token(self, client_id: int | None, token: str) -> None:
        if client_id is None or not token.strip():
            return
        if self.access.unlock(client_id, token):
            self._notify(client_id, "Agent controls unlocked", "this page may now send commands to the agent")
        else:
            self._notify(client_id, "Wrong access token", "the agent controls stay locked on this page")

    def _notify(self, client_id: int | None, title: str, body: str) -> None:
        client = self.server.get_clients().get(client_id) if client_id is not None else None
        if client is not None:
            client.add_notification(
                title, body, auto_close_seconds=6.0, color="green" if title.endswith("unlocked") else "red"
            )

    def set_layer(self, layer: str, on: bool) -> None:
        with self._lock:
            self._requests[f"layer:{layer}"] = on
        self._wake.set()

    def set_colour_mode(self, mode: str) -> None:
        with self._lock:
            self._requests["colour_mode"] = mode
        self._wake.set()

    def set_label_all(self, on: bool) -> None:
        with self._lock:
            self._requests["label_all"] = on
        self._wake.set()

    def reset_view(self) -> None:
        with self._lock:
            self._requests["reset_view"] = True
        self._wake.set()

    def replay_seek(self, step: int) -> None:
        with self._lock:
            self._replay_step = int(step)  # drawn at the next tick (the slider also moves while playing)

    def replay_play(self, playing: bool, steps_per_s: float) -> None:
        with self._lock:
            if playing and self.replay is not None and self._replay_step >= self.replay.last_step:
                self._replay_step = self.replay.first_step  # play again from the start
            self._replay_playing, self._replay_rate = playing, max(0.1, float(steps_per_s))
        self._wake.set()

    def _handle_requests(self) -> None:
        with self._lock:
            requests, self._requests = self._requests, {}
        if not requests:
            return
        with self.server.atomic():
            for name, value in requests.items():
                if name.startswith("layer:"):
                    layer = name.split(":", 1)[1]
                    self.scene.set_layer(layer, bool(value))
                    if layer == "oracle":
                        self._set_oracle(bool(value))
                elif name == "colour_mode":
                    self.scene.set_colour_mode(str(value))
                elif name == "label_all":
                    self.scene.set_label_all(bool(value))
                elif name == "label_view":
                    self.scene.set_label_view(value)
                elif name == "reset_view" and self.scene.plane is not None:
                    self._aim_camera(self.scene.plane)
                elif name == "oracle_objects" and self._oracle_on:
                    self.scene.apply_oracle(value)

    # --- oracle ------------------------------------------------------------------------------------
    def _set_oracle(self, on: bool) -> None:
        self._oracle_on = on
        if (
            on
            and self.feed is not None
            and (self._oracle_thread is None or not self._oracle_thread.is_alive())
        ):
            self._oracle_thread = threading.Thread(
                target=self._oracle_loop, daemon=True, name="tidee-viewer-oracle"
            )
            self._oracle_thread.start()

    def _oracle_loop(self) -> None:
        """While the oracle layer is on: ask the session's server for its true state now and then."""
        assert self.feed is not None
        last_error = ""
        while self._oracle_on and not self._stop.is_set():
            session = self._session_shown
            if session is not None:
                try:
                    objects = oracle_objects(self.feed.fetch_state(session))
                    with self._lock:
                        self._requests["oracle_objects"] = objects
                    last_error = ""
                except (LookupError, TimeoutError, RuntimeError, ValueError, KeyError) as e:
                    if str(e) != last_error:
                        log.warning("oracle layer: %s", e)
                        last_error = str(e)
            self._stop.wait(self.config.oracle_period_s)


def _display_host(host: str) -> str:
    return "127.0.0.1" if host in ("0.0.0.0", "") else host


class ViewerHandle:
    """A running viewer: ``url``, ``app`` (its scene and stats), ``stop()``."""

    def __init__(self, app: ViewerApp) -> None:
        self.app = app
        self.url = app.url

    def stop(self) -> None:
        self.app.stop()

    def __enter__(self) -> ViewerHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def run_viewer(config: ViewerConfig | None = None) -> ViewerHandle:
    """Start a viewer in this process (threads only); returns at once with its handle."""
    return ViewerHandle(ViewerApp(config or ViewerConfig()).start())


def serve(config: ViewerConfig) -> None:
    """``tidee viewer``: run until SIGINT or SIGTERM, printing the URL first."""
    handle = run_viewer(config)
    print(access.announce(handle.url, handle.app.access.token, config.read_only), flush=True)
    try:
        wait_for_signal()
    finally:
        handle.stop()
