"""End to end in a real browser: telemetry -> viewer -> headless Chromium -> pixels.

The telemetry comes from the real system: ``tidee server`` and ``tidee agent`` start as
separate processes on a loopback endpoint (a small test room at a small resolution, oracle
perception, a short step budget), the viewer runs in this process, and Chromium loads its
page. Three moments are screenshotted and checked panel by panel (each panel's region, found
in the page's DOM, must hold a picture): early (the first map), mid-episode (an object
labelled out of place, the agent paused from the page) and after the episode ended (the
"Episode finished" panel with the agent's summary, the page still live, not dimmed).
A second test replays a real rearrangement's log (run in this process) at the first step
where the agent believes objects moved: the phase banner, the walkthrough memory's violet
boxes and the orange lines from moved objects to their walkthrough places must be on the page.
Set ``TIDEE_VIEWER_SHOTS=DIR`` to keep the screenshots (early.png, mid.png, finished.png,
finished_rgb.png: the 3D map in camera colours, and rearrange.png). The docs' pictures come from a replayed
episode instead: ``tidee viewer --replay LOG --screenshot docs/viewer.png --annotated
docs/viewer_annotated.png --window 1280x960``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from tests.support.net import free_endpoint
from tidee.agent.classes import CLASSES  # the agent's class list (plain data, no torch)
from tidee.viewer import palette
from tidee.viewer.browser import (
    CANVAS,
    DISMISS_SOFTWARE_GL_NOTE,
    HEIGHT,
    WIDTH,
    HeadlessChromium,
    distinct_colors,
    find_chromium,
    map_drawn,
    palette_pixels,
    region_drawn,
)

pytestmark = pytest.mark.skipif(
    find_chromium() is None,
    reason="no chromium binary (install Debian's chromium: scripts/install_chromium.sh)",
)

CLICK_BUTTON = """(label => {
  const b = [...document.querySelectorAll('button')].find(b => b.textContent.trim() === label);
  if (b) { b.click(); return true; } return false; })"""
# viser dims the whole GUI (opacity 0.5) while its websocket is down: count the dimmed wrappers
DIMMED = """[...document.querySelectorAll('div')].filter(d => d.style.transition.startsWith('opacity')
  && d.style.opacity === '0.5').length"""
MAX_STEPS = 180  # the episode ends on its step budget (about 6 steps/s here) after the agent flags objects


@dataclass
class TelemetrySource:
    endpoint: str
    session: str


@pytest.fixture
def telemetry_source(tmp_path) -> Iterator[TelemetrySource]:
    """A real server and a real agent, each its own process, on a fresh loopback endpoint."""
    endpoint, session = free_endpoint(), "viewer-e2e"
    tidee = [sys.executable, "-m", "tidee.cli"]
    server = subprocess.Popen(tidee + ["server", "--endpoint", endpoint, "--renderer", "tiny"])
    agent = subprocess.Popen(
        tidee
        + [
            "agent",
            "--endpoint",
            endpoint,
            "--session",
            session,
            "--room-type",
            "LivingRoom",
            "--seed",
            "200",
            "--mess-index",
            "0",
            "--resolution",
            "128",
            "--max-steps",
            str(MAX_STEPS),
            "--serve",
            "--perception",
            "oracle",
            "--oop",
            "relation_stats",  # flags the most: labels to see
            "--log-dir",
            str(tmp_path / "runs"),
        ]
    )
    try:
        yield TelemetrySource(endpoint, session)
    finally:
        for p in (agent, server):
            p.terminate()
        for p in (agent, server):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()


def wait_until(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.1)


def check_panels(shot: np.ndarray, boxes: dict, names: tuple[str, ...], moment: str) -> None:
    """Each named panel is on the page and its region holds a picture."""
    for name in names:
        assert name in boxes, f"{moment}: no {name} panel on the page (found {sorted(boxes)})"
        assert region_drawn(shot, boxes[name]), f"{moment}: the {name} panel at {boxes[name]} is blank"


def save(shot: np.ndarray, directory: str, name: str) -> None:
    os.makedirs(directory, exist_ok=True)
    cv2.imwrite(os.path.join(directory, name), cv2.cvtColor(shot, cv2.COLOR_RGB2BGR))


def test_viewer_early_mid_and_finished_in_headless_chromium(telemetry_source: TelemetrySource, tmp_path):
    from tidee.viewer.app import ViewerConfig, run_viewer

    t0 = time.monotonic()
    shots_dir = os.environ.get("TIDEE_VIEWER_SHOTS") or str(tmp_path / "shots")
    viewer = run_viewer(
        ViewerConfig(endpoint=telemetry_source.endpoint, port=0, session=telemetry_source.session)
    )
    try:
        app = viewer.app
        with HeadlessChromium(width=WIDTH, height=HEIGHT) as browser:
            browser.navigate(viewer.url)
            wait_until(
                lambda: browser.evaluate("document.querySelectorAll('canvas').length") or False,
                20,
                "the page's canvas",
            )
            # 1. early: the first map reaches the page. The agent is paused meanwhile (a browser
            # drawing WebGL in software is slow beside a running agent on a small machine).
            wait_until(
                lambda: app.stats.applied["maps"] > 0 and app.stats.applied["frame"] > 0,
                60,
                "the viewer to receive a map and a frame",
            )
            app.command("pause")
            browser.wait_for(lambda img: map_drawn(img, len(CLASSES)), timeout=60)
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            early = browser.wait_settled(timeout=15)
            save(early, shots_dir, "early.png")
            check_panels(
                early, browser.panel_boxes(), ("camera", "map", "canvas", "plot", "episode"), "early"
            )
            assert distinct_colors(early[CANVAS]) > 500
            assert app.stats.last_step < MAX_STEPS / 2, f"not early: step {app.stats.last_step}"
            app.command("resume")

            # 2. mid-episode: the agent flags objects (labelled in 3D) and is paused at once (its
            # episode would otherwise run on while the browser draws); then the page's own Pause
            # button reaches the agent, and its acknowledgement comes back to the page
            wait_until(
                lambda: any(
                    "out of place" in h.text for h in app.scene.labels.handles[: app.scene.labels.shown]
                ),
                90,
                "an out-of-place object labelled in the viewer's scene",
            )
            app.command("pause")
            assert browser.evaluate(f"{CLICK_BUTTON}('Pause')") is True
            wait_until(
                lambda: "pause" in app.panels.ack.content and "agent: ok" in app.panels.ack.content,
                15,
                "the agent's ack of the pause command",
            )
            assert "summary" not in app._latest, "the episode ended before the agent was paused"
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            mid = browser.wait_settled(timeout=15)  # the paused status, a last frame and the labels drawn
            save(mid, shots_dir, "mid.png")
            boxes = browser.panel_boxes()
            check_panels(mid, boxes, ("camera", "map", "canvas", "plot", "controls"), "mid")
            assert map_drawn(mid, len(CLASSES))
            assert float(mid[CANVAS].astype(np.float32).std()) > 20.0
            assert distinct_colors(mid[CANVAS]) > 500 and distinct_colors(mid) > 2000
            shown = app.scene.node_names()
            assert shown["/map/voxels"] and shown["/objects/boxes"] and shown["/agent/camera"]
            assert app.scene.counts["voxels"] > 300 and app.scene.counts["objects"] >= 3
            # only the objects that matter are labelled (out of place, target, held), not all
            assert 1 <= app.scene.counts["labels"] <= app.scene.counts["objects"]
            assert app.feed is not None and app.feed.selected == telemetry_source.session

            # 3. the end: resumed, the agent spends its step budget and sends its summary
            assert browser.evaluate(f"{CLICK_BUTTON}('Resume')") is True
            wait_until(lambda: "summary" in app._latest, 150, "the agent's episode summary")
            wait_until(
                lambda: "Episode finished" in browser.text(), 10, "the Episode finished panel on the page"
            )
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            finished = browser.wait_settled(timeout=15)
            save(finished, shots_dir, "finished.png")
            boxes = browser.panel_boxes()
            check_panels(finished, boxes, ("summary", "camera", "map", "canvas"), "finished")
            text = browser.text()
            summary = app._latest["summary"]
            for words in (
                "Episode finished",
                "moved",
                "found",
                "put away",
                "plausible",
                "false picks",
                f"{summary.steps} steps",
                "tidee viewer --replay",
            ):
                assert words in text, f"{words!r} is not on the finished page"
            assert browser.evaluate(DIMMED) == 0, "the page is dimmed: its connection to the viewer dropped"
            assert map_drawn(finished, len(CLASSES))

            # the 3D map in camera colours: the agent's frames fused into a coloured cloud
            app.set_colour_mode("rgb")
            wait_until(lambda: app.scene.node_names()["/map/rgb"], 10, "the camera-coloured cloud")
            assert app.scene.counts["rgb_points"] > 1000
            rgb = browser.wait_settled(timeout=15)
            save(rgb, shots_dir, "finished_rgb.png")
            canvas, semantic = rgb[CANVAS], finished[CANVAS]
            assert region_drawn(rgb, boxes["canvas"]) and distinct_colors(canvas) > 500
            assert (
                float(np.any(canvas != semantic, axis=2).mean()) > 0.05
            )  # other colours than the semantic map's
        assert time.monotonic() - t0 < 240
    finally:
        viewer.stop()


def test_rearrangement_replay_shows_both_phases_memories_in_headless_chromium(tmp_path):
    """A real rearrangement (LivingRoom 200, configuration 0: the oracle agent believes objects
    moved), logged in this process, replayed at the first step with a walkthrough place known."""
    from tidee.agent.config import AgentConfig
    from tidee.agent.runner import EpisodeRunner
    from tidee.protocol.messages import EpisodeSpec
    from tidee.protocol.transport import InProcessTransport
    from tidee.viewer.app import ViewerConfig, run_viewer

    shots_dir = os.environ.get("TIDEE_VIEWER_SHOTS") or str(tmp_path / "shots")
    spec = EpisodeSpec(
        room_type="LivingRoom",
        seed=200,
        rearrange_index=0,
        resolution=128,
        walkthrough_steps=100,
        max_steps=150,
    )
    runner = EpisodeRunner(
        AgentConfig(perception="oracle"), InProcessTransport(renderer="tiny"), "rearrange", log_dir=tmp_path
    )
    runner.run(spec, evaluate=True, episode_name="ep")
    viewer = run_viewer(ViewerConfig(replay=str(tmp_path / "ep"), port=0))
    try:
        app = viewer.app
        assert app.replay is not None
        log = app.replay
        step = next(
            s for s in log.steps("memory") if any(o.goal_centroid for o in log.at(s)["memory"].objects)
        )
        assert log.unshuffle_step is not None and step > log.unshuffle_step
        app.replay_seek(step)
        wait_until(lambda: app.stats.last_step == step, 30, f"the replay to draw step {step}")
        shown = app.scene.node_names()
        assert shown["/walkthrough/boxes"] and shown["/objects/goals"] and shown["/objects/boxes"]
        with HeadlessChromium(width=WIDTH, height=HEIGHT) as browser:
            browser.navigate(viewer.url)
            maps = log.at(step)["maps"]
            browser.wait_for(lambda img: map_drawn(img, len(maps.classes)), timeout=60)
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            shot = browser.wait_settled(timeout=15)
            save(shot, shots_dir, "rearrange.png")
            boxes = browser.panel_boxes()
            check_panels(shot, boxes, ("phase", "camera", "map", "canvas", "episode"), "rearrangement")
            text = browser.text()
            for words in (
                "UNSHUFFLE",
                "phase 2 of 2",
                "changes believed",
                "rearrangement 0",
                "unshuffle step",
            ):
                assert words in text, f"{words!r} is not on the page"
            labels = [h.text for h in app.scene.labels.handles[: app.scene.labels.shown]]
            assert any(t.endswith(": moved") for t in labels), labels
            x0, y0, x1, y1 = boxes["canvas"]
            canvas = shot[y0:y1, x0:x1]
            assert palette_pixels(canvas, np.array([palette.WALKTHROUGH_RGB]), tolerance=30) > 50
            assert palette_pixels(canvas, np.array([palette.WARNING_RGB]), tolerance=30) > 20
    finally:
        viewer.stop()
