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
from websockets.sync.client import ClientConnection, connect

from tidee.viewer.palette import UNLABELLED_RGB, class_color

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# WebGL without a GPU: SwiftShader (software). Newer Chromium needs it asked for by name.
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--mute-audio",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--hide-scrollbars",
)


# The viewer's page at the default window size: the 3D canvas lies between the left
# (camera/map) and right (controls) panels, 330 px each.
WIDTH, HEIGHT = 1280, 800
CANVAS = (slice(40, HEIGHT - 40), slice(360, WIDTH - 360))
# Chromium without a GPU shows a "Software WebGL" notification over the canvas: close it.
# (The scripts here are split into adjacent literals only to keep source lines short.)
DISMISS_SOFTWARE_GL_NOTE = (
    """(() => { let n = 0;
  document.querySelectorAll('[class*="Notification-root"]').forEach(el => {
    if (el.textContent.includes('Software WebGL')) { """
    """const b = el.querySelector('button'); if (b) { b.click(); n++; } }
  }); return n; })()"""
)


# Where each panel of the viewer's page is (viewport pixels: x0, y0, x1, y1), found in the DOM:
# images by their label (the 2D map's has none), HTML panels by id, folders by their title.
PANEL_BOXES = (
    """(() => {
  const box = el => { if (!el) return null; const b = el.getBoundingClientRect();
    return b.width > 4 && b.height > 4 ? [b.left, b.top, b.right, b.bottom].map(Math.round) : null; };
  const out = {};
  document.querySelectorAll('img').forEach(img => {
    const p = img.parentElement && img.parentElement.parentElement && """
    """img.parentElement.parentElement.querySelector('p');
    const label = p ? p.textContent : '';
    const b = box(img);
    if (!b || b[2] - b[0] < 40) return;                       // hidden tabs, icons
    if (label.startsWith('RGB')) out.camera = b;
    else if (label.startsWith('Progress')) out.plot = b;
    else if (!label && b[0] < window.innerWidth / 2) out.map = b;
  });
  const canvas = document.querySelector('canvas');
  if (canvas) out.canvas = box(canvas);
  for (const [name, id] of [['summary', 'tidee-summary'], ['predictions', 'tidee-predictions'],
                            ['phase', 'tidee-phase']]) {
    const b = box(document.getElementById(id)); if (b) out[name] = b; }
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  const folders = {Episode: 'episode', Agent: 'controls', Replay: 'controls', Layers: 'layers'};
  while (walker.nextNode()) {
    const name = folders[walker.currentNode.textContent.trim()];
    const label = name && walker.currentNode.parentElement.closest('.mantine-Paper-root');   """
    """// the folder's title bar
    const folder = label && label.parentElement && label.parentElement.closest('.mantine-Paper-root');
    if (folder && !out[name]) { const b = box(folder); if (b) out[name] = b; }
  }
  return out; })()"""
)


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

    def __init__(
        self, binary: str | None = None, width: int = WIDTH, height: int = HEIGHT, start_timeout: float = 30.0
    ) -> None:
        found = binary or find_chromium()
        if found is None:
            raise FileNotFoundError(
                "no chromium binary found (install Debian's chromium: scripts/install_chromium.sh)"
            )
        self.width, self.height = width, height
        self._profile = tempfile.mkdtemp(prefix="tidee-chromium-")
        self._ids = itertools.count(1)
        self._proc = subprocess.Popen(
            [
                found,
                *FLAGS,
                f"--user-data-dir={self._profile}",
                f"--window-size={width},{height}",
                "--remote-debugging-port=0",
                "--remote-allow-origins=*",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            port = self._devtools_port(start_timeout)
            self._ws: ClientConnection = connect(
                self._page_socket(port, start_timeout), max_size=64 << 20, open_timeout=start_timeout
            )
            self.call("Page.enable")
            self.call(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
            )
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        path = os.path.join(self._profile, "DevToolsActivePort")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                raise RuntimeError(
                    f"chromium exited with code {self._proc.returncode} before opening DevTools"
                )
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

    def call(
        self, method: str, params: dict[str, Any] | None = None, timeout: float = 30.0
    ) -> dict[str, Any]:
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

    def wait_for(
        self, predicate: Callable[[np.ndarray], bool], timeout: float, interval: float = 0.5
    ) -> np.ndarray:
        """Screenshots until ``predicate(image)`` holds; returns that image (``TimeoutError`` otherwise)."""
        deadline = time.monotonic() + timeout
        while True:
            img = self.screenshot()
            if predicate(img):
                return img
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page did not reach the expected state within {timeout} s")
            time.sleep(interval)

    def wait_settled(self, timeout: float, interval: float = 0.7, max_changed: float = 0.002) -> np.ndarray:
        """Screenshots until two in a row differ in at most ``max_changed`` of their pixels (the
        page has finished drawing: fades, new nodes, labels); returns the last. On timeout, the
        last one taken (a page that never settles is for the caller's checks to judge)."""
        deadline = time.monotonic() + timeout
        last = self.screenshot()
        while time.monotonic() < deadline:
            time.sleep(interval)
            img = self.screenshot()
            changed = float(np.any(img != last, axis=2).mean())
            last = img
            if changed <= max_changed:
                break
        return last

    def panel_boxes(self) -> dict[str, tuple[int, int, int, int]]:
        """Where the viewer's panels are on the page now (``PANEL_BOXES``), clipped to the window."""
        found = self.evaluate(PANEL_BOXES) or {}
        out = {}
        for name, (x0, y0, x1, y1) in found.items():
            x0, y0 = max(0, int(x0)), max(0, int(y0))
            x1, y1 = min(self.width, int(x1)), min(self.height, int(y1))
            if x1 - x0 > 4 and y1 - y0 > 4:
                out[name] = (x0, y0, x1, y1)
        return out

    def text(self) -> str:
        """The page's visible text (``document.body.innerText``)."""
        return str(self.evaluate("document.body.innerText") or "")

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


def region_drawn(
    img: np.ndarray, box: tuple[int, int, int, int], min_std: float = 12.0, min_colors: int = 64
) -> bool:
    """A panel's region of a screenshot holds a picture, not a blank or flat area."""
    x0, y0, x1, y1 = box
    crop = img[y0:y1, x0:x1]
    return (
        crop.size > 0
        and float(crop.astype(np.float32).std()) > min_std
        and distinct_colors(crop) >= min_colors
    )
