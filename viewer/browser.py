"""Headless Chromium over the DevTools protocol: load the viewer's page, screenshot it.

Used by the end-to-end test (does a real browser draw the scene?) and by the benchmark
(a real client connected while telemetry streams). Needs Debian's ``chromium`` package
(``scripts/install_chromium.sh``); ``find_chromium()`` returns None without it.
Uses the ``websockets`` client that viser already depends on; nothing else.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from tidee.viewer.palette import UNLABELLED_RGB, class_color
from websockets.sync.client import ClientConnection, connect

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# WebGL without a GPU: SwiftShader (software). Newer Chromium needs it asked for by name.
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-extensions", "--mute-audio",
         "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--hide-scrollbars")


# The viewer's page at the default window size: the 3D canvas lies between the left
# (camera/map) and right (controls) panels, 330 px each.
WIDTH, HEIGHT = 1280, 800
CANVAS = (slice(40, HEIGHT - 40), slice(360, WIDTH - 360))
# Chromium without a GPU shows a "Software WebGL" notification over the canvas: close it.
DISMISS_SOFTWARE_GL_NOTE = """(() => { let n = 0;
  document.querySelectorAll('[class*="Notification-root"]').forEach(el => {
    if (el.textContent.includes('Software WebGL')) { const b = el.querySelector('button'); if (b) { b.click(); n++; } }
  }); return n; })()"""


def find_chromium() -> str | None:
    """Path of a Chromium binary (``TIDEE_CHROMIUM`` first), or None."""
    override = os.environ.get("TIDEE_CHROMIUM")
    if override:
        return override if shutil.which(override) else None
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class HeadlessChromium:
    """One headless Chromium with a fresh profile and one page, driven over DevTools."""

    def __init__(self, binary: str | None = None, width: int = WIDTH, height: int = HEIGHT,
                 start_timeout: float = 30.0) -> None:
        found = binary or find_chromium()
        if found is None:
            raise FileNotFoundError("no chromium binary found (install Debian's chromium: scripts/install_chromium.sh)")
        self.width, self.height = width, height
        self._profile = tempfile.mkdtemp(prefix="tidee-chromium-")
        self._ids = itertools.count(1)
        self._proc = subprocess.Popen(
            [found, *FLAGS, f"--user-data-dir={self._profile}", f"--window-size={width},{height}",
             "--remote-debugging-port=0", "--remote-allow-origins=*", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port = self._devtools_port(start_timeout)
            self._ws: ClientConnection = connect(self._page_socket(port, start_timeout), max_size=64 << 20,
                                                 open_timeout=start_timeout)
            self.call("Page.enable")
            self.call("Emulation.setDeviceMetricsOverride",
                      {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        path = os.path.join(self._profile, "DevToolsActivePort")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise RuntimeError(f"chromium exited with code {self._proc.returncode} before opening DevTools")
            try:
                with open(path) as f:
                    first = f.readline().strip()
                if first:
                    return int(first)
            except (FileNotFoundError, ValueError):
                pass
            time.sleep(0.05)
        raise TimeoutError(f"chromium did not open DevTools within {timeout} s")

    @staticmethod
    def _page_socket(port: int, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                targets = json.load(r)
            pages = [t for t in targets if t.get("type") == "page" and t.get("webSocketDebuggerUrl")]
            if pages:
                return str(pages[0]["webSocketDebuggerUrl"])
            if time.monotonic() > deadline:
                raise TimeoutError("chromium has no page target to drive")
            time.sleep(0.1)

    def call(self, method: str, params: dict[str, Any] | None = None, timeout: float = 30.0) -> dict[str, Any]:
        """One DevTools command; returns its result (events arriving meanwhile are skipped)."""
        msg_id = next(self._ids)
        self._ws.send(json.dumps({"id": msg_id, "method": method, "params": params or {}}))
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no DevTools answer to {method} within {timeout} s")
            reply = json.loads(self._ws.recv(timeout=left))
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise RuntimeError(f"DevTools {method} failed: {reply['error']}")
                return reply.get("result", {})

    def pids(self) -> list[int]:
        """The browser's process and its descendants (renderer, GPU, utility processes)."""
        pids, frontier = [self._proc.pid], [self._proc.pid]
        while frontier:
            pid = frontier.pop()
            try:
                with open(f"/proc/{pid}/task/{pid}/children") as f:
                    kids = [int(k) for k in f.read().split()]
            except OSError:
                kids = []
            pids += kids
            frontier += kids
        return pids

    def navigate(self, url: str, timeout: float = 30.0) -> None:
        """Load ``url`` and wait until the document has loaded (while the page swaps
        processes, DevTools answers "Not attached to an active page": retried)."""
        self.call("Page.navigate", {"url": url})
        deadline = time.monotonic() + timeout
        while True:
            try:
                if self.evaluate("document.readyState") == "complete":
                    return
            except RuntimeError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"{url} did not load within {timeout} s")
            time.sleep(0.1)

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        return result.get("result", {}).get("value")

    def screenshot(self) -> np.ndarray:
        """The page as RGB ``uint8 H x W x 3``."""
        data = base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise RuntimeError("chromium returned a screenshot opencv cannot decode")
        return bgr[..., ::-1].copy()

    def wait_for(self, predicate: Callable[[np.ndarray], bool], timeout: float, interval: float = 0.5) -> np.ndarray:
        """Screenshots until ``predicate(image)`` holds; returns that image (``TimeoutError`` otherwise)."""
        deadline = time.monotonic() + timeout
        while True:
            img = self.screenshot()
            if predicate(img):
                return img
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page did not reach the expected state within {timeout} s")
            time.sleep(interval)

    def close(self) -> None:
        ws = getattr(self, "_ws", None)
        if ws is not None:
            try:
                ws.close()
            except Exception:
                pass
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=10)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def palette_pixels(img: np.ndarray, colors: np.ndarray, tolerance: int = 24) -> int:
    """How many pixels of ``img`` lie within ``tolerance`` (per channel) of one of ``colors``."""
    flat = img.reshape(-1, 1, 3).astype(np.int16)
    near = np.all(np.abs(flat - np.asarray(colors, np.int16)[None]) <= tolerance, axis=2)
    return int(near.any(axis=1).sum())


def distinct_colors(img: np.ndarray) -> int:
    """Distinct RGB values in an image (a blank page has a handful)."""
    packed = img.reshape(-1, 3).astype(np.uint32)
    return int(len(np.unique(packed[:, 0] << 16 | packed[:, 1] << 8 | packed[:, 2])))


def map_drawn(img: np.ndarray, n_classes: int) -> bool:
    """The voxel map (the colours of ``n_classes`` classes, and the grey of voxels no
    detection labelled: walls, floor) covers a real part of the 3D canvas, and some voxels
    carry class colours."""
    colors = np.array([class_color(i) for i in range(n_classes)])
    labelled = palette_pixels(img[CANVAS], colors, tolerance=20)
    grey = palette_pixels(img[CANVAS], np.array([UNLABELLED_RGB]), tolerance=30)
    return labelled > 300 and labelled + grey > 3000
