"""``tidee viewer --replay LOG --screenshot PNG``: the viewer's page at one step of a log, as a PNG.

Starts the replay viewer in this process on a free port, seeks to the asked step (or to
the first search heatmap the agent published, ``--at search``), loads the page in a
headless Chromium, waits until the 3D canvas has drawn the map and the page has settled,
and writes the screenshot; with ``annotated``, also the same picture with each panel
outlined and named (``viewer/annotate.py``). For documentation and bug reports: the
picture a person would see.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from tidee.viewer.annotate import annotate
from tidee.viewer.app import ViewerConfig, run_viewer
from tidee.viewer.browser import DISMISS_SOFTWARE_GL_NOTE, HEIGHT, WIDTH, HeadlessChromium, map_drawn


def resolve_step(log, at: str) -> int:
    """``at`` is a step number, ``search`` (the first step with a search heatmap) or ``end``."""
    if at == "end":
        return int(log.last_step)
    if at == "search":
        steps = log.steps("search")
        if not steps:
            raise ValueError(
                f"the log {log.directory} holds no search heatmap (the agent never searched "
                "for a receptacle in that episode)"
            )
        return int(steps[0])
    try:
        step = int(at)
    except ValueError:
        raise ValueError(f"--at must be a step number, 'search' or 'end'; got {at!r}") from None
    if not log.first_step <= step <= log.last_step:
        raise ValueError(f"--at {step} is outside the log's steps {log.first_step}-{log.last_step}")
    return step


def screenshot_replay(
    log_dir: str,
    out_png: str,
    at: str = "end",
    timeout: float = 60.0,
    annotated_png: str | None = None,
    size: tuple[int, int] = (WIDTH, HEIGHT),
) -> int:
    """Write the page at ``at`` to ``out_png`` (and its annotated copy to ``annotated_png``);
    return the step shown. ``size``: the browser window (width, height)."""
    handle = run_viewer(ViewerConfig(replay=log_dir, port=0))
    try:
        app = handle.app
        assert app.replay is not None
        step = resolve_step(app.replay, at)
        app.replay_seek(step)
        deadline = time.monotonic() + timeout
        while app.stats.last_step != step:  # the status of every step is in the log
            if time.monotonic() > deadline:
                raise TimeoutError(f"the viewer did not draw step {step} within {timeout} s")
            time.sleep(0.1)
        with HeadlessChromium(width=size[0], height=size[1]) as browser:
            browser.navigate(handle.url)
            maps = app.replay.at(step).get("maps")
            n_classes = len(maps.classes) if maps is not None else 1
            browser.wait_for(lambda img: map_drawn(img, n_classes), timeout=timeout)
            browser.evaluate(DISMISS_SOFTWARE_GL_NOTE)
            shot = browser.wait_settled(timeout=15)  # fades, labels and the closed notification done
            boxes = browser.panel_boxes()
        _write_png(out_png, shot)
        if annotated_png:
            _write_png(annotated_png, annotate(shot, boxes))
        return step
    finally:
        handle.stop()


def _write_png(path: str, rgb: np.ndarray) -> None:
    if not cv2.imwrite(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
