"""A screenshot of the viewer with each panel outlined, numbered and named (for the docs).

``annotate(shot, boxes)`` draws, with opencv, a numbered box around each panel found on the
page (``HeadlessChromium.panel_boxes()``: the DOM says where each one is) and a key below the
picture naming them. ``tidee viewer --replay LOG --screenshot PNG --annotated PNG`` writes both
images from one page.
"""

from __future__ import annotations

import cv2
import numpy as np

# panel key (browser.PANEL_BOXES) -> what the docs call it; numbered in this order
PANELS = (
    ("camera", "Camera: what the agent sees, with its detections (orange: out of place)"),
    ("map", "2D map: occupancy, explored floor, the path walked and planned"),
    ("canvas", "3D map: voxels by class (or camera RGB), tracked objects, labels, the agent"),
    ("summary", "Episode finished: moved, found, put away, plausible, false picks, replay command"),
    ("phase", "Rearrangement phase: walkthrough (mapping the goal room) or unshuffle"),
    ("episode", "Episode: phase, step, target, held object"),
    ("predictions", "Receptacle predictions: where the held object belongs (top 5)"),
    ("plot", "Progress: objects put away and found, by step"),
    ("controls", "Controls: replay slider and play (live: session, pause / resume / step)"),
    ("layers", "Layers: what the 3D map shows, its colours, labels"),
)
INK = (200, 20, 110)  # RGB: a magenta no panel uses
FOLDERS = ("episode", "controls", "layers")  # their title sits on their top border: the box starts below it
FONT = cv2.FONT_HERSHEY_SIMPLEX


def annotate(
    shot: np.ndarray, boxes: dict[str, tuple[int, int, int, int]], key_scale: float = 0.55
) -> np.ndarray:
    """``shot`` (RGB) with the panels in ``boxes`` outlined and numbered, and a key below it.
    Panels missing from ``boxes`` (not on the page, or scrolled out of it) are left out."""
    img = np.ascontiguousarray(shot.copy())
    h, w = img.shape[:2]
    shown = [
        (n, key, caption)
        for n, (key, caption) in enumerate(((k, c) for k, c in PANELS if k in boxes), start=1)
    ]
    for n, key, _ in shown:
        x0, y0, x1, y1 = boxes[key]
        y0 += 9 if key in FOLDERS else 0
        x0, y0, x1, y1 = max(x0, 1), max(y0, 1), min(x1, w - 2), min(y1, h - 2)
        cv2.rectangle(img, (x0, y0), (x1, y1), INK, 3, cv2.LINE_AA)
        # on the box's top edge, at its right end: over the border, not over the panel's title
        r = _badge_radius(0.7)
        _badge(img, n, (max(x0, min(x1 - 2 * r - 8, w - 2 * r - 2)), max(0, y0 - r)))
    # the key: one line per panel, in two columns under the picture
    line = int(round(30 * key_scale / 0.55))
    rows = (len(shown) + 1) // 2
    legend = np.full((rows * line + 16, w, 3), 255, np.uint8)
    for i, (n, _, caption) in enumerate(shown):
        col, row = divmod(i, rows)
        x, y = 12 + col * (w // 2), 10 + row * line
        _badge(legend, n, (x, y), scale=key_scale)
        cv2.putText(
            legend,
            caption,
            (x + int(34 * key_scale / 0.55), y + int(19 * key_scale / 0.55)),
            FONT,
            key_scale,
            (40, 40, 40),
            1,
            cv2.LINE_AA,
        )
    cv2.line(legend, (0, 0), (w, 0), (200, 200, 200), 1)
    return np.vstack([img, legend])


def _badge_radius(scale: float) -> int:
    return int(round(13 * scale / 0.7 + 1))


def _badge(img: np.ndarray, n: int, corner: tuple[int, int], scale: float = 0.7) -> None:
    """A filled disc with the number ``n`` in it, its top-left at ``corner``."""
    r = _badge_radius(scale)
    cx, cy = corner[0] + r, corner[1] + r
    cv2.circle(img, (cx, cy), r, INK, -1, cv2.LINE_AA)
    text = str(n)
    (tw, th), _ = cv2.getTextSize(text, FONT, scale, 2)
    cv2.putText(img, text, (cx - tw // 2, cy + th // 2), FONT, scale, (255, 255, 255), 2, cv2.LINE_AA)
