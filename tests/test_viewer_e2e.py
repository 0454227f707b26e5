"""End to end in a real browser: telemetry -> viewer -> headless Chromium -> pixels.

The telemetry comes from the real system: ``tidee server`` and ``tidee agent`` start as
separate processes on a loopback endpoint (a small test room at a small resolution, oracle
perception), the viewer runs in this process, and Chromium loads its page.
Set ``TIDEE_VIEWER_SCREENSHOT=docs/viewer.png`` to refresh the README's screenshot.
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
from tidee.viewer.browser import (CANVAS, DISMISS_SOFTWARE_GL_NOTE, HEIGHT, WIDTH, HeadlessChromium,
                                  distinct_colors, find_chromium, map_drawn)
from tidee.agent.classes import CLASSES  # the agent's class list (plain data, no torch)

from tests.test_service import free_endpoint

pytestmark = pytest.mark.skipif(find_chromium() is None,
                                reason="no chromium binary (install Debian's chromium: scripts/install_chromium.sh)")

CLICK_BUTTON = """(label => {
  const b = [...document.querySelectorAll('button')].find(b => b.textContent.trim() === label);
  if (b) { b.click(); return true; } return false; })"""


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
    agent = subprocess.Popen(tidee + ["agent", "--endpoint", endpoint, "--session", session,
                                      "--room-type", "LivingRoom", "--seed", "200", "--mess-index", "0",
                                      "--resolution", "128", "--max-steps", "800", "--serve", "--perception", "oracle",
                                      "--oop", "relation_stats",   # flags the most: labels to see
                                      "--log-dir", str(tmp_path / "runs")])
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


def test_viewer_draws_the_map_and_objects_in_headless_chromium(telemetry_source: TelemetrySource, tmp_path):
    from tidee.viewer.app import ViewerConfig, run_viewer

    t0 = time.monotonic()
    viewer = run_viewer(ViewerConfig(endpoint=telemetry_source.endpoint, port=0, session=telemetry_source.session))
    try:
        app = viewer.app
        wait_until(lambda: app.stats.applied["maps"] > 0 and app.stats.applied["memory"] > 0, 60,
                   "the viewer to receive a map and the object memory")
        # After mapping, the agent flags out-of-place objects (the viewer labels them).
        wait_until(lambda: any("out of place" in h.text
                               for h in app.scene.labels.handles[:app.scene.labels.shown]), 60,
                   "an out-of-place object in the viewer's scene")
        with HeadlessChromium(width=WIDTH, height=HEIGHT) as browser:
            browser.navigate(viewer.url)
            wait_until(lambda: browser.evaluate("document.querySelectorAll('canvas').length") or False, 20,
                       "the page's canvas")
            first = browser.wait_for(lambda img: map_drawn(img, len(CLASSES)), timeout=30)
            assert distinct_colors(first[CANVAS]) > 500

            # the controls reach the agent, and its acknowledgement comes back to the page
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            assert browser.evaluate(f"{CLICK_BUTTON}('Pause')") is True
            wait_until(lambda: "pause" in app.panels.ack.content and "agent: ok" in app.panels.ack.content, 15,
                       "the agent's ack of the pause command")
            time.sleep(1.5)  # the paused status and a last frame reach the page
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            shot = browser.screenshot()

        # the viewer's scene holds the map and the object memory
        shown = app.scene.node_names()
        assert shown["/map/voxels"] and shown["/objects/boxes"] and shown["/agent/camera"]
        assert app.scene.counts["voxels"] > 300 and app.scene.counts["objects"] >= 3
        # (the out-of-place label was waited for above: by now the agent may have put that
        # object away, which removes its label)
        labels = [h.text for h in app.scene.labels.handles[:app.scene.labels.shown]]
        assert len(labels) >= 3, labels
        assert app.feed is not None and app.feed.selected == telemetry_source.session

        # and the browser drew it: a varied picture, not a blank page
        canvas = shot[CANVAS]
        assert map_drawn(shot, len(CLASSES))
        assert float(canvas.astype(np.float32).std()) > 20.0
        assert distinct_colors(canvas) > 500 and distinct_colors(shot) > 2000
        path = os.environ.get("TIDEE_VIEWER_SCREENSHOT") or str(tmp_path / "viewer.png")
        cv2.imwrite(path, cv2.cvtColor(shot, cv2.COLOR_RGB2BGR))
        assert time.monotonic() - t0 < 150
    finally:
        viewer.stop()
