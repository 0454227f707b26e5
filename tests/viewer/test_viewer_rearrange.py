"""A rearrangement in the viewer: the phase banner, the walkthrough memory beside the current
one, the objects believed moved with a line to their walkthrough place, RoomR's summary,
the replay's step axis over both phases, and a real episode's log replayed."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from tests.support.net import wait_until
from tidee.protocol.episode_log import LogReader, LogWriter
from tidee.protocol.messages import (
    AgentStatus,
    EpisodeSummary,
    ObjectMemoryMsg,
    TrackedObjectMsg,
    WalkthroughMemoryMsg,
)
from tidee.viewer import palette
from tidee.viewer.phases import rearrangement_phase, unshuffle_began
from tidee.viewer.synthetic import SyntheticEpisode

EPISODE = {
    "room_type": "Kitchen",
    "seed": 201,
    "mess_index": None,
    "rearrange_index": 1,
    "variant": "Rearrange",
}
WALK_STEPS, UNSHUFFLE_STEPS = 12, 9  # the synthetic log's phases (steps 0..11, then 0..8)
RESULT = {
    "success": False,
    "fixed_strict": 0.75,
    "misplaced": 0.25,
    "energy": 0.25,
    "start_misplaced": 4,
    "fixed": 3,
    "newly_misplaced": 0,
}


def _obj(i: int, label: str, x: float, y: float, **kw) -> TrackedObjectMsg:
    return TrackedObjectMsg(
        i, label, 0.9, (x, y, 0.5), (x - 0.1, y - 0.1, 0.4), (x + 0.1, y + 0.1, 0.6), **kw
    )


WALKTHROUGH = [_obj(0, "Mug", 1.0, 0.5), _obj(1, "Book", -1.0, 1.5), _obj(2, "Fridge", 2.0, -1.0)]


def _status(step: int, phase: str, **kw) -> AgentStatus:
    return AgentStatus("rr", step, phase, dict(EPISODE), (0.0, 0.0, 0.0, 30.0), **kw)


def _unshuffle_memory(step: int) -> ObjectMemoryMsg:
    """The shuffled room: the mug moved (its walkthrough place known), the fridge toggled."""
    return ObjectMemoryMsg(
        "rr",
        step,
        [
            _obj(7, "Mug", -0.5, -1.5, out_of_place=True, goal_centroid=(1.0, 0.5, 0.5)),
            _obj(8, "Book", -1.0, 1.5),
            _obj(9, "Fridge", 2.0, -1.1, out_of_place=True),
        ],
    )


def write_rearrangement_log(directory: Path) -> None:
    """Both phases as the runner logs them: statuses every step, the walkthrough memory once as
    the walkthrough ends, the unshuffle's steps counted from 0 again, RoomR's summary last."""
    ep = SyntheticEpisode(session="rr")
    with LogWriter(directory) as writer:
        for step in range(WALK_STEPS):
            writer.message("status", _status(step, "walkthrough"))
            if step % 4 == 0:
                writer.message("maps", dataclasses.replace(ep.maps(100 + step), session="rr", step=step))
                writer.message("memory", ObjectMemoryMsg("rr", step, WALKTHROUGH[: 1 + step // 4]))
        writer.message("walkthrough", WalkthroughMemoryMsg("rr", WALK_STEPS - 1, WALKTHROUGH))
        for step in range(UNSHUFFLE_STEPS):
            writer.message("status", _status(step, "mapping" if step < 4 else "approaching", oop_found=2))
            if step % 4 == 0:
                writer.message("maps", dataclasses.replace(ep.maps(100 + step), session="rr", step=step))
                writer.message("memory", _unshuffle_memory(step))
        summary = EpisodeSummary("rr", dict(EPISODE), UNSHUFFLE_STEPS, 3.0, "restored what it found", 3)
        summary.rearrange = dict(RESULT)
        writer.message("summary", summary)
        writer.finish({"summary": dataclasses.asdict(summary)})


# --- phases -------------------------------------------------------------------------------------


def test_phases_tell_the_unshuffle_from_a_new_episode():
    walk, unshuffle = _status(11, "walkthrough"), _status(0, "mapping")
    assert rearrangement_phase(walk) == "walkthrough" and rearrangement_phase(unshuffle) == "unshuffle"
    assert unshuffle_began(walk, unshuffle)
    assert not unshuffle_began(unshuffle, _status(0, "walkthrough"))  # a new rearrangement
    tidy = AgentStatus("t", 3, "searching", {"room_type": "Kitchen", "mess_index": 0}, (0, 0, 0, 0))
    assert rearrangement_phase(tidy) is None and not unshuffle_began(tidy, tidy)
    other = dataclasses.replace(unshuffle, episode={**EPISODE, "seed": 202})
    assert not unshuffle_began(walk, other)


# --- panels -------------------------------------------------------------------------------------


def test_phase_banner_names_the_phase_and_hides_for_tidying():
    from tidee.viewer.panels import PHASE_ID, phase_html

    walk = phase_html(_status(5, "walkthrough"))
    assert f"id='{PHASE_ID}'" in walk and "WALKTHROUGH" in walk and "rearrangement 1" in walk
    assert palette.css(palette.WALKTHROUGH_RGB) in walk
    later = phase_html(_status(3, "placing", oop_found=2, objects_fixed=1))
    assert "UNSHUFFLE" in later and "2 changes believed" in later and "1 put back or reset" in later
    tidy = AgentStatus("t", 3, "searching", {"room_type": "Kitchen", "mess_index": 0}, (0, 0, 0, 0))
    assert phase_html(tidy) == ""


def test_summary_panel_shows_roomr_metrics_for_a_rearrangement():
    from tidee.viewer.panels import summary_html

    s = EpisodeSummary("rr", dict(EPISODE), 92, 4.1, "restored what it found", 3, rearrange=dict(RESULT))
    page = summary_html(s)
    assert "Kitchen seed 201 rearrangement 1" in page and "Episode finished" in page
    for text in (
        "success <b>no</b>",
        "FixedStrict <b>0.75</b>",
        "misplaced <b>0.25</b>",
        "energy <b>0.25</b>",
        "fixed <b>3</b>/4",
        "newly misplaced <b>0</b>",
    ):
        assert text in page, text
    assert "plausible" not in page and "false picks" not in page and "not scored" not in page
    odd = summary_html(dataclasses.replace(s, rearrange={"success": True, "fixed_strict": "<b>x</b>"}))
    assert "success <b>yes</b>" in odd and "FixedStrict –" in odd and "<b>x" not in odd


# --- the scene ----------------------------------------------------------------------------------


def test_scene_draws_the_walkthrough_beside_the_memory_and_lines_to_where_moved_objects_go(scene_view):
    scene_view.apply_maps(SyntheticEpisode().maps(300))
    scene_view.apply("walkthrough", WalkthroughMemoryMsg("rr", 11, WALKTHROUGH))
    scene_view.apply("memory", _unshuffle_memory(4))
    shown = scene_view.node_names()
    assert shown["/walkthrough/boxes"] and shown["/objects/boxes"] and shown["/objects/goals"]
    assert scene_view.counts["walkthrough"] == 3 and scene_view.counts["goals"] == 1
    assert scene_view.walkthrough_boxes.points.shape == (12 * 3, 2, 3)
    colours = np.asarray(scene_view.walkthrough_boxes.colors).reshape(-1, 3)
    assert {tuple(c) for c in colours} == {palette.WALKTHROUGH_RGB}
    assert np.allclose(scene_view.goal_lines.points, [[[-0.5, -1.5, 0.5], [1.0, 0.5, 0.5]]])
    assert [tuple(c) for c in scene_view.boxes.colors[::12, 0]] == [
        palette.WARNING_RGB,
        palette.TRACKED_RGB,
        palette.WARNING_RGB,
    ]
    texts = sorted(h.text for h in scene_view.labels.handles[: scene_view.labels.shown])
    assert texts == ["Fridge: out of place", "Mug: moved"]
    scene_view.set_layer("walkthrough", False)  # the "Walkthrough memory" checkbox
    assert not scene_view.walkthrough_boxes.visible and scene_view.boxes.visible
    scene_view.set_layer("walkthrough", True)
    assert scene_view.walkthrough_boxes.visible
    scene_view.apply("memory", ObjectMemoryMsg("rr", 5, [_obj(8, "Book", -1.0, 1.5)]))  # nothing moved
    assert not scene_view.goal_lines.visible and not scene_view.goal_points.visible
    scene_view.clear()
    assert not any(scene_view.node_names().values())


# --- replay -------------------------------------------------------------------------------------


def test_replay_puts_the_unshuffle_after_the_walkthrough_on_one_step_axis(tmp_path):
    from tidee.viewer.replay import ReplayLog

    write_rearrangement_log(tmp_path)
    log = ReplayLog(tmp_path)
    last = WALK_STEPS + UNSHUFFLE_STEPS - 1
    assert (log.first_step, log.last_step, log.unshuffle_step) == (0, last, WALK_STEPS)
    assert log.steps("walkthrough") == [WALK_STEPS - 1] and log.steps("summary") == [last]
    walk = log.at(WALK_STEPS - 2)
    assert walk["status"].phase == "walkthrough" and "walkthrough" not in walk
    later = log.at(WALK_STEPS + 5)
    assert later["status"].step == 5 and later["status"].phase == "approaching"
    assert later["memory"].step == 4 and later["walkthrough"].objects == WALKTHROUGH
    assert log.history(last)[:, 0].tolist() == list(range(last + 1))


def seek(app, step: int, timeout: float = 10.0) -> bool:
    """Move the replay to ``step``; wait until its status and step line are drawn."""
    app.replay_seek(step)
    return wait_until(
        lambda: app.stats.last_step == step and app.panels.replay_info.content.startswith(f"step {step} "),
        timeout,
    )


def test_replay_viewer_shows_the_phases_both_memories_and_roomr_summary(tmp_path):
    from tidee.viewer.app import ViewerConfig, run_viewer

    write_rearrangement_log(tmp_path)
    with run_viewer(ViewerConfig(replay=str(tmp_path), port=0)) as viewer:
        app = viewer.app
        assert wait_until(lambda: app.stats.last_step == 0, 10.0)
        assert "WALKTHROUGH" in app.panels.phase.content and app.panels.phase.visible
        assert seek(app, WALK_STEPS - 1)  # the walkthrough's end: its memory arrives
        assert app.scene.node_names()["/walkthrough/boxes"]
        assert seek(app, WALK_STEPS + 6)  # forward into the unshuffle: the same episode, nothing cleared
        assert "UNSHUFFLE" in app.panels.phase.content and "2 changes believed" in app.panels.phase.content
        shown = app.scene.node_names()
        assert shown["/walkthrough/boxes"] and shown["/objects/boxes"] and shown["/objects/goals"]
        assert "(unshuffle step 6)" in app.panels.replay_info.content
        assert not app.panels.summary.visible
        assert seek(app, WALK_STEPS + UNSHUFFLE_STEPS - 1)
        assert app.panels.summary.visible and "FixedStrict <b>0.75</b>" in app.panels.summary.content
        assert seek(app, 3)  # back into the walkthrough: its memory is not known yet
        assert "WALKTHROUGH" in app.panels.phase.content and not app.panels.summary.visible
        assert not app.scene.node_names()["/walkthrough/boxes"]


# --- a real episode -----------------------------------------------------------------------------


def test_a_real_rearrangement_logs_its_walkthrough_memory_and_replays(tmp_path):
    """A short oracle-perception rearrangement in this process, logged; the log holds the
    walkthrough memory once, the unshuffle's memory marks what the agent believes changed,
    and the replay viewer loads it and shows both phases."""
    from tidee.agent.config import AgentConfig
    from tidee.agent.runner import EpisodeRunner
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport
    from tidee.viewer.app import ViewerConfig, run_viewer
    from tidee.viewer.replay import ReplayLog

    spec = EpisodeSpec(
        room_type="Kitchen", seed=201, rearrange_index=1, resolution=96, walkthrough_steps=60, max_steps=100
    )
    transport = InProcessTransport(renderer="tiny")
    runner = EpisodeRunner(AgentConfig(perception="oracle"), transport, "rr", log_dir=tmp_path)
    result = runner.run(spec, evaluate=True, episode_name="ep")
    log_dir = tmp_path / "ep"
    messages = list(LogReader(log_dir).messages())
    (walk,) = [m for k, m in messages if k == "walkthrough"]
    assert isinstance(walk, WalkthroughMemoryMsg) and len(walk.objects) >= 5
    assert 0 < walk.step < spec.walkthrough_steps
    record = json.loads((log_dir / "summary.json").read_text())["record"]
    believed = record["believed_moved"] + record["believed_toggled"]
    memories = [m for k, m in messages if k == "memory"]
    flagged = {o.id for m in memories for o in m.objects if o.out_of_place}
    assert believed == 0 or flagged  # what it believes changed is marked in its memory
    with_goal = [o for m in memories for o in m.objects if o.goal_centroid is not None]
    assert all(o.out_of_place for o in with_goal) and (record["believed_moved"] == 0 or with_goal)
    assert result.summary is not None and result.summary.rearrange is not None

    log = ReplayLog(log_dir)  # what `tidee viewer --replay` loads
    assert log.unshuffle_step == walk.step + 1 and log.steps("walkthrough") == [walk.step]
    assert log.last_step == walk.step + 1 + result.steps
    with run_viewer(ViewerConfig(replay=str(log_dir), port=0)) as viewer:
        app = viewer.app
        assert seek(app, log.last_step, 15.0) and app.panels.summary.visible
        assert "UNSHUFFLE" in app.panels.phase.content and "FixedStrict" in app.panels.summary.content
        assert app.scene.node_names()["/walkthrough/boxes"]
        assert app.scene.counts["walkthrough"] == len(walk.objects)
