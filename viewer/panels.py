"""The GUI around the 3D scene: camera and map panels, episode status (with a
rearrangement's phase), plot, controls, and the "Episode finished" summary.

``Panels`` builds every widget once and exposes ``show_*`` methods that assign to the
widgets' handles. What a person does (pick a session, pause, type a preference, move the
replay slider) goes to a ``PanelActions`` implementation (the app), called on viser's
thread pool.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import viser

from tidee.protocol.messages import ROOM_TYPES, AgentStatus, CommandAck, EpisodeSummary
from tidee.viewer import images, palette
from tidee.viewer.feed import SessionInfo
from tidee.viewer.phases import WALKTHROUGH, rearrangement_phase
from tidee.viewer.scene_view import COLOUR_MODES, LAYERS

AUTO_SESSION = "(follow newest)"
PLOT_STEP_STRIDE = 10  # the progress plot follows the steps in strides; a count that changes shows at once
LAYER_LABELS = {
    "voxels": "3D map",
    "objects": "Object memory",
    "walkthrough": "Walkthrough memory",
    "agent": "Agent (camera, paths)",
    "search": "Search heatmap",
    "oracle": "Ground truth (oracle)",
}
LAYER_HINTS = {
    "walkthrough": "A rearrangement: the objects the agent remembered of the goal room in its "
    "walkthrough (violet boxes), beside what it tracks now.",
    "oracle": "Privileged: the server's true object boxes (moved objects in red), fetched "
    "about once a second from the server's state. Not what the agent knows.",
}
COLOUR_LABELS = {"semantic": "semantic classes", "rgb": "camera RGB", "height": "height"}
COLOUR_HINT = (
    "semantic classes: the agent's voxel map, one colour per class (the legend below); camera RGB: "
    "the agent's RGB-D frames fused into coloured points; height: the voxel map coloured by height"
)
SUMMARY_ID = "tidee-summary"  # DOM ids: the screenshot tools find these panels by them
PREDICTIONS_ID = "tidee-predictions"
PHASE_ID = "tidee-phase"


class PanelActions(Protocol):
    def select_session(self, session: str | None) -> None: ...
    def command(self, kind: str, client_id: int | None, **fields: object) -> None: ...
    def present_token(self, client_id: int | None, token: str) -> None: ...
    def set_layer(self, layer: str, on: bool) -> None: ...
    def set_colour_mode(self, mode: str) -> None: ...
    def set_label_all(self, on: bool) -> None: ...
    def reset_view(self) -> None: ...
    def replay_seek(self, step: int) -> None: ...
    def replay_play(self, playing: bool, steps_per_s: float) -> None: ...


class Panels:
    def __init__(
        self,
        server: viser.ViserServer,
        actions: PanelActions,
        replay_steps: tuple[int, int] | None,
        initial_session: str | None = None,
        read_only: bool = False,
    ) -> None:
        gui = server.gui
        self.server, self.actions = server, actions
        self.replay = replay_steps is not None
        self.read_only = read_only
        self.command_controls: list[object] = []  # the widgets that send commands (none when read-only)
        gui.configure_theme(control_width="medium", show_share_button=False, brand_color=(40, 90, 220))

        # --- left: what the agent sees, and its 2D map -----------------------------------------
        self.view_panel = gui.add_panel()
        with self.view_panel.add_tab("Camera", viser.Icon.CAMERA):
            self.rgb = gui.add_image(
                images.placeholder("waiting for the agent's camera", 512, 512),
                label="RGB + detections (orange: out of place)",
                format="jpeg",
                jpeg_quality=85,
            )
        with self.view_panel.add_tab("Depth", viser.Icon.RULER_MEASURE):
            self.depth = gui.add_image(
                images.placeholder("waiting for depth", 512, 512),
                label="Depth",
                format="jpeg",
                jpeg_quality=85,
            )
        self.view_panel.dock_left()
        self.view_panel.set_width(330)
        self.map_panel = gui.add_panel()
        with self.map_panel.add_tab("2D map", viser.Icon.MAP_2):
            self.map = gui.add_image(
                images.placeholder("waiting for the map", 360, 300), label=None, format="png"
            )
            gui.add_html(_map_key_html())
        self.map_panel.dock_below(self.view_panel)

        # --- right: status, controls, layers (docked, so the 3D view is not under it) -----------
        gui.main_panel.dock_right()
        gui.main_panel.set_width(330)
        self.title = gui.add_markdown("**tidee viewer** · connecting…")
        # a rearrangement's phase (walkthrough / unshuffle), in large type; hidden for tidying
        self.phase = gui.add_html("", visible=False)
        # shown when the agent reports the episode's end (EpisodeSummary); above everything else
        self.summary = gui.add_html("", visible=False)
        self._summary_shown: EpisodeSummary | None = None
        with gui.add_folder("Episode"):
            self.status = gui.add_markdown("_no status yet_")
            self.predictions = gui.add_html("")
            # drawn here as an image of a fixed size: it cannot collapse, whatever the panel's
            # layout when it first appears, and it shows the same in every browser and screenshot
            self._plot_key: tuple[int, tuple[float, ...]] | None = None
            self.plot = gui.add_image(
                images.progress_plot(np.zeros((0, 3))), label="Progress (by step)", format="png"
            )
        if self.replay:
            assert replay_steps is not None
            self._build_replay(gui, *replay_steps)
        else:
            self._build_controls(gui, initial_session)
        with gui.add_folder("Layers", expand_by_default=not self.replay):
            self.layer_boxes = {}
            for layer in LAYERS:
                box = gui.add_checkbox(
                    LAYER_LABELS[layer], initial_value=layer != "oracle", hint=LAYER_HINTS.get(layer)
                )

                def _toggle_layer(e: viser.GuiEvent[viser.GuiCheckboxHandle], layer: str = layer) -> None:
                    actions.set_layer(layer, bool(e.target.value))

                box.on_update(_toggle_layer)
                self.layer_boxes[layer] = box
            self.colour_mode = gui.add_dropdown(
                "3D map colours",
                tuple(COLOUR_LABELS[m] for m in COLOUR_MODES),
                initial_value=COLOUR_LABELS["semantic"],
                hint=COLOUR_HINT,
            )
            by_label = {label: mode for mode, label in COLOUR_LABELS.items()}
            self.colour_mode.on_update(lambda e: actions.set_colour_mode(by_label[str(e.target.value)]))
            self.label_all = gui.add_checkbox(
                "Label all objects",
                initial_value=False,
                hint="Off: only objects out of place, the current target and the held object are labelled",
            )
            self.label_all.on_update(lambda e: actions.set_label_all(bool(e.target.value)))
            gui.add_button("Reset view", icon=viser.Icon.FOCUS_CENTERED).on_click(
                lambda _: actions.reset_view()
            )
            gui.add_markdown("**Classes** (voxel colours)")
            self.legend = gui.add_html(palette.legend_html([], np.zeros(0)))
            gui.add_html(_object_key_html())

    def _build_controls(self, gui: viser.GuiApi, initial_session: str | None) -> None:
        actions = self.actions
        self.agent_folder = gui.add_folder("Agent")
        with self.agent_folder:
            options = (AUTO_SESSION,) if initial_session is None else (AUTO_SESSION, initial_session)
            self.session = gui.add_dropdown(
                "Session",
                options,
                initial_value=initial_session or AUTO_SESSION,
                hint="Live sessions (liveliness) and sessions publishing telemetry",
            )
            self.session.on_update(
                lambda e: actions.select_session(
                    None if e.target.value == AUTO_SESSION else str(e.target.value)
                )
            )
            self.sessions_info = gui.add_html("")
            if self.read_only:
                self.ack = gui.add_markdown("_read-only viewer: no agent controls_")
                return
            run = gui.add_button_group("Run", ("Pause", "Resume", "Step"))
            kinds = {"Pause": "pause", "Resume": "resume", "Step": "step"}
            run.on_click(lambda e: actions.command(kinds[e.target.value], e.client_id))
            self.ack = gui.add_markdown("_no command sent yet_")
        with gui.add_folder("New episode", expand_by_default=False):
            room = gui.add_dropdown("Room type", ROOM_TYPES, initial_value="LivingRoom")
            seed = gui.add_number("Seed", 0, min=0, step=1)
            mess = gui.add_number("Mess index", 0, min=0, step=1)
            new_episode = gui.add_button("Start new episode", icon=viser.Icon.PLAYER_PLAY)
            new_episode.on_click(
                lambda e: actions.command(
                    "new_episode",
                    e.client_id,
                    room_type=room.value,
                    seed=int(seed.value),
                    mess_index=int(mess.value),
                )
            )
        with gui.add_folder("Placement preference", expand_by_default=False):
            text = gui.add_text(
                "Preference", "", hint='In plain language, e.g. "I want my alarm clock on the desk"'
            )
            send = gui.add_button("Send to the agent", icon=viser.Icon.SEND)
            send.on_click(lambda e: actions.command("preference", e.client_id, text=text.value))
        self.command_controls = [run, new_episode, send]

    def add_token_input(self, client: viser.ClientHandle) -> None:
        """One client's own "Access token" field (client-scoped: what it types reaches no other
        browser), at the top of the Agent folder."""
        with self.agent_folder:
            field = client.gui.add_text(
                "Access token",
                "",
                order=-1.0,
                hint="The token printed where the viewer started: it unlocks this page's agent controls",
            )
        field.on_update(lambda e: self.actions.present_token(e.client_id, str(e.target.value)))

    def _build_replay(self, gui: viser.GuiApi, first: int, last: int) -> None:
        actions = self.actions
        with gui.add_folder("Replay"):
            self.slider = gui.add_slider(
                "Step", min=first, max=max(last, first + 1), step=1, initial_value=first
            )
            # a person's move only: the viewer moving the slider to the step it drew (a callback on
            # the update worker, with no client) must not undo a seek asked for meanwhile
            self.slider.on_update(
                lambda e: actions.replay_seek(int(e.target.value)) if e.client_id is not None else None
            )
            self.speed = gui.add_slider("Steps / s", min=1, max=100, step=1, initial_value=10)
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self._playing = False

            def toggle(_: object) -> None:
                self._playing = not self._playing
                self.play.label = "Pause" if self._playing else "Play"
                self.play.icon = viser.Icon.PLAYER_PAUSE if self._playing else viser.Icon.PLAYER_PLAY
                actions.replay_play(self._playing, float(self.speed.value))

            self.play.on_click(toggle)
            self.speed.on_update(lambda e: actions.replay_play(self._playing, float(e.target.value)))
            self.replay_info = gui.add_markdown("")

    # --- updates (from the update worker) -------------------------------------------------------
    def show_title(self, text: str) -> None:
        if self.title.content != text:
            self.title.content = text

    def show_status(self, s: AgentStatus) -> None:
        ep = s.episode or {}
        room = f"{ep.get('room_type', '?')} seed {ep.get('seed', '?')} {_episode_kind(ep)}"
        found = "changes found" if rearrangement_phase(s) is not None else "OOP found"
        lines = [
            f"**{html.escape(s.phase)}** · step **{s.step}**"
            + (" · **PAUSED**" if s.paused else "")
            + (" · **DONE**" if s.done else ""),
            f"{html.escape(room)} · {html.escape(str(ep.get('variant', '')))} "
            f"{html.escape(str(ep.get('perception', '')))}",
            f"target: **{html.escape(s.target_object or '–')}** → {html.escape(s.target_receptacle or '–')}",
            f"holding: {html.escape(s.held or '–')} · fixed **{s.objects_fixed}** · {found} {s.oop_found}",
        ]
        if s.message:
            lines.append(f"_{html.escape(s.message)}_")
        self.status.content = "  \n".join(lines)
        predictions = predictions_html([(p.label, p.prob) for p in s.predictions[:5]])
        if self.predictions.content != predictions:
            self.predictions.content = predictions
        self.show_phase(s)

    def show_phase(self, s: AgentStatus | None) -> None:
        """The rearrangement phase banner (hidden for a tidying episode, or with None)."""
        content = phase_html(s) if s is not None else ""
        if self.phase.content != content:
            self.phase.content = content
        if self.phase.visible != bool(content):
            self.phase.visible = bool(content)

    def show_plot(self, history: np.ndarray, final: bool = False) -> None:
        """Redraw the progress plot when its data changed (``K x 3``: step, put away, found):
        at once for new counts or a ``final`` row, every PLOT_STEP_STRIDE steps otherwise."""
        rows = np.asarray(history, np.float64).reshape(-1, 3)
        key = (len(rows), tuple(rows[-1]) if len(rows) else ())
        last = self._plot_key
        if key == last:
            return
        if (
            not final
            and last is not None
            and len(rows) > last[0]
            and last[1]
            and key[1][1:] == last[1][1:]  # the same counts: only the steps moved on
            and key[1][0] - last[1][0] < PLOT_STEP_STRIDE
        ):
            return  # redrawn (and re-encoded) every PLOT_STEP_STRIDE steps, not every step
        self._plot_key = key
        self.plot.image = images.progress_plot(rows)

    def show_summary(self, summary: EpisodeSummary | None) -> None:
        """The "Episode finished" panel (None hides it: a new episode began, or a replay slid back)."""
        if summary == self._summary_shown:
            return
        self._summary_shown = summary
        if summary is None:
            self.summary.visible = False
            return
        self.summary.content = summary_html(summary)
        self.summary.visible = True

    def show_stopped(self, note: str) -> None:
        """The viewer is shutting down: say so on the page (which freezes, dimmed, once the
        connection closes) so the last thing a person sees explains it."""
        self.title.content = f"**tidee viewer stopped** · this page no longer updates. {note}"

    def show_camera(self, rgb: np.ndarray, depth: np.ndarray | None) -> None:
        self.rgb.image = rgb
        if depth is not None:
            self.depth.image = depth

    def show_map(self, img: np.ndarray) -> None:
        self.map.image = img

    def show_legend(self, content: str) -> None:
        if self.legend.content != content:
            self.legend.content = content

    def show_ack(self, ack: CommandAck) -> None:
        if self.replay:
            return
        mark = "agent: ok" if ack.ok else "agent: **refused**"
        self.ack.content = f"{mark} · **{html.escape(ack.kind)}**: {html.escape(ack.message or 'done')}"

    def show_sent(self, text: str) -> None:
        if not self.replay:
            self.ack.content = text

    def show_sessions(self, sessions: Sequence[SessionInfo], pinned: str | None) -> None:
        """Session ids as the dropdown's options (stable strings, so a choice stays valid
        while its state changes); each one's state in the line below."""
        if self.replay:
            return
        ids = [s.session for s in sessions]
        if pinned is not None and pinned not in ids:
            ids.append(pinned)
        opts = (AUTO_SESSION, *ids)
        if tuple(self.session.options) != opts:
            self.session.options = opts
        text = ", ".join(html.escape(s.describe()) for s in sessions[:8]) or "none seen yet"
        more = f" and {len(sessions) - 8} more" if len(sessions) > 8 else ""
        content = f"<div style='font-size:0.8em;color:#666'>sessions: {text}{more}</div>"
        if self.sessions_info.content != content:
            self.sessions_info.content = content

    def show_replay_step(self, step: int, info: str) -> None:
        if int(self.slider.value) != step:
            # viser declares value's setter apart from its getter (another method between), so
            # mypy drops the setter and sees the property read-only
            self.slider.value = step  # type: ignore[misc]
        if self.replay_info.content != info:
            self.replay_info.content = info


def predictions_html(preds: Sequence[tuple[str, float]]) -> str:
    """Top receptacle predictions as labelled probability bars."""
    if not preds:
        return ""
    rows = []
    for label, prob in preds:
        pct = max(0.0, min(1.0, float(prob))) * 100
        rows.append(
            "<div style='display:flex;align-items:center;font-size:0.8em;margin:1px 0'>"
            "<span style='width:38%;overflow:hidden;text-overflow:ellipsis;white-space:nowrap'>"
            f"{html.escape(label)}</span>"
            "<span style='flex:1;background:#e6e6e6;border-radius:3px;height:10px;margin:0 6px'>"
            f"<span style='display:block;width:{pct:.0f}%;height:10px;border-radius:3px;"
            f"background:{palette.css(palette.PATH_RGB)}'></span></span>"
            f"<span style='width:3.2em;text-align:right'>{prob:.2f}</span></div>"
        )
    return (
        f"<div id='{PREDICTIONS_ID}'><div style='font-size:0.8em;color:#666'>where it belongs (top 5)</div>"
        + "".join(rows)
        + "</div>"
    )


def _episode_kind(ep: dict[str, Any]) -> str:
    """``mess 3``, ``rearrangement 1`` or ``(tidy)``."""
    if ep.get("rearrange_index") is not None:
        return f"rearrangement {ep['rearrange_index']}"
    return f"mess {ep['mess_index']}" if ep.get("mess_index") is not None else "(tidy)"


def phase_html(s: AgentStatus) -> str:
    """A rearrangement's phase in large type: the walkthrough (mapping the goal room) or the
    unshuffle (putting the shuffled room back); empty for a tidying episode."""
    phase = rearrangement_phase(s)
    if phase is None:
        return ""
    if phase == WALKTHROUGH:
        colour, head, what = palette.WALKTHROUGH_RGB, "WALKTHROUGH · phase 1 of 2", "mapping the goal room"
    else:
        colour, head, what = palette.WARNING_RGB, "UNSHUFFLE · phase 2 of 2", "putting the shuffled room back"
        what += f" · {s.oop_found} changes believed · {s.objects_fixed} put back or reset"
    ep = s.episode or {}
    return (
        f"<div id='{PHASE_ID}' style='border-left:6px solid {palette.css(colour)};background:#f7f5fb;"
        f"border-radius:4px;padding:3px 8px;margin:2px 8px 6px;line-height:1.35'>"
        f"<div style='font-size:1.25em;font-weight:800;color:{palette.css(colour)}'>{head}</div>"
        f"<div style='font-size:0.8em'>{html.escape(_episode_kind(ep))} · {html.escape(what)} · "
        f"step {s.step}</div></div>"
    )


def _count(v: Any, of: Any = None) -> str:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return "–"
    return f"<b>{int(v)}</b>" + (f"/{int(of)}" if isinstance(of, (int, float)) else "")


def _fraction(v: Any) -> str:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        return "–"
    return f"<b>{float(v):.2f}</b>"


def _score_cells(s: EpisodeSummary) -> tuple[list[tuple[str, str]], str, str]:
    """The summary's chips, a note under them and their tooltip: RoomR's metrics for a
    rearrangement, the tidying counts otherwise."""
    if s.rearrange is not None:
        r = s.rearrange
        success = r.get("success")
        cells = [
            ("success", "–" if success is None else f"<b>{'yes' if success else 'no'}</b>"),
            ("FixedStrict", _fraction(r.get("fixed_strict"))),
            ("misplaced", _fraction(r.get("misplaced"))),
            ("energy", _fraction(r.get("energy"))),
            ("fixed", _count(r.get("fixed"), r.get("start_misplaced"))),
            ("newly misplaced", _count(r.get("newly_misplaced"))),
        ]
        tip = (
            "RoomR's metrics against the goal room: fixed is out of the objects the shuffle changed; "
            "misplaced and energy are fractions of the start's (lower is better)"
        )
        return cells, f"<div style='color:#555'>put back or reset by the agent: {s.put_away}</div>", tip
    cells = [
        ("moved", _count(s.moved)),
        ("found", _count(s.found, s.moved)),
        ("put away", _count(s.put_away)),
        ("plausible", _count(s.plausible, s.moved)),
        ("false picks", _count(s.false_picks)),
    ]
    unscored = (
        "<div style='color:#777'>moved, found, plausible, false picks: not scored (the server gave no "
        "state)</div>"
        if s.moved is None
        else ""
    )
    tip = "found and plausible are out of the objects the mess-up moved; plausible by the simulated judge"
    return cells, unscored, tip


def summary_html(s: EpisodeSummary) -> str:
    """The "Episode finished" box: how the episode ended, its scores (RoomR's metrics for a
    rearrangement) and the replay command. Every string is escaped (it comes from the network)."""
    ep = s.episode or {}
    kind = _episode_kind(ep)
    room = f"{ep.get('room_type', '?')} seed {ep.get('seed', '?')}" + (f" {kind}" if kind != "(tidy)" else "")
    who = " ".join(str(ep[k]) for k in ("variant", "perception") if ep.get(k))
    cells, unscored, tip = _score_cells(s)
    chips = "".join(
        f"<span style='display:inline-block;white-space:nowrap;background:#fff;border-radius:4px;"
        f"padding:0 5px;margin:2px 4px 0 0'>{html.escape(k)} {v}</span>"
        for k, v in cells
    )
    replay = (
        f"<div style='margin-top:3px'>replay: <code style='font-size:0.9em;word-break:break-all'>"
        f"{html.escape(s.replay)}</code></div>"
        if s.replay
        else ""
    )
    return (
        f"<div id='{SUMMARY_ID}' style='border:2px solid #2e7d32;background:#eef7ee;border-radius:6px;"
        f"padding:5px 8px;margin:2px 8px 6px;font-size:0.85em;line-height:1.4'>"
        f"<div style='font-size:1.15em;font-weight:700;color:#1b5e20'>&#10004; Episode finished</div>"
        f"<div>{html.escape(room)} · {html.escape(who)} · <b>{s.steps}</b> steps · "
        f"<b>{s.wall_s:.0f}</b> s</div>"
        f"<div style='color:#555'>ended: {html.escape(s.end_reason or '–')}</div>"
        f"<div title='{html.escape(tip)}'>{chips}</div>{unscored}{replay}</div>"
    )


def _swatch(rgb: palette.RGB, text: str) -> str:
    return (
        f"<span style='white-space:nowrap;margin-right:8px'><span style='display:inline-block;width:10px;"
        f"height:10px;border-radius:2px;background:{palette.css(rgb)};margin-right:3px'></span>{text}</span>"
    )


def _object_key_html() -> str:
    items = [
        (palette.TRACKED_RGB, "tracked"),
        (palette.WARNING_RGB, "out of place"),
        (palette.HELD_RGB, "held"),
        (palette.WALKTHROUGH_RGB, "walkthrough memory"),
        (palette.TRAJECTORY_RGB, "trajectory"),
        (palette.PATH_RGB, "planned path"),
        (palette.SEARCH_POINT_RGB, "search points"),
        (palette.FRUSTUM_RGB, "camera"),
        (palette.ORACLE_MOVED_RGB, "oracle: moved"),
    ]
    return (
        "<div style='font-size:0.8em;line-height:1.6'>" + "".join(_swatch(c, t) for c, t in items) + "</div>"
    )


def _map_key_html() -> str:
    items = [
        (images.FREE_RGB, "free, explored"),
        (images.SEEN_FREE_RGB, "seen"),
        (images.OBSTACLE_RGB, "obstacle"),
        (images.UNKNOWN_RGB, "unknown"),
        (images.AGENT_RGB, "agent"),
        (palette.PATH_RGB, "path"),
    ]
    return (
        "<div style='font-size:0.8em;line-height:1.6'>+x (start heading) is up. "
        + "".join(_swatch(c, t) for c, t in items)
        + "</div>"
    )
