"""Colours the viewer draws with: semantic classes, warnings, layers, and the legend.

Pure functions of their arguments (no viser, no Zenoh), so they are unit-tested directly.
Colours are RGB ``uint8`` triples.
"""

from __future__ import annotations

import colorsys
import html
from collections.abc import Sequence

import cv2
import numpy as np

RGB = tuple[int, int, int]

# Layer colours: one meaning each, used in the 3D scene and in the 2D panels alike.
TRACKED_RGB: RGB = (40, 170, 90)  # a tracked object that is where it belongs
WARNING_RGB: RGB = (255, 110, 0)  # out of place (orange: visible on light and dark)
HELD_RGB: RGB = (0, 170, 255)  # the object in the agent's hand
UNLABELLED_RGB: RGB = (150, 150, 150)  # an occupied voxel with no class
TRAJECTORY_RGB: RGB = (40, 90, 220)
PATH_RGB: RGB = (20, 190, 60)
FRUSTUM_RGB: RGB = (220, 30, 30)
SEARCH_POINT_RGB: RGB = (230, 0, 200)
ORACLE_RGB: RGB = (120, 120, 120)  # ground truth, in place
ORACLE_MOVED_RGB: RGB = (200, 0, 0)  # ground truth, moved by the mess-up
WALKTHROUGH_RGB: RGB = (150, 40, 255)  # a rearrangement's walkthrough memory (the goal room)

# Twenty well-separated hues first (then golden-ratio hues): class i always gets colour i.
_BASE = np.array(
    [
        (31, 119, 180),
        (214, 39, 40),
        (44, 160, 44),
        (148, 103, 189),
        (255, 187, 0),
        (23, 190, 207),
        (140, 86, 75),
        (227, 119, 194),
        (188, 189, 34),
        (0, 90, 60),
        (120, 160, 230),
        (255, 140, 120),
        (130, 220, 130),
        (200, 170, 230),
        (180, 120, 20),
        (0, 130, 140),
        (200, 160, 140),
        (250, 190, 220),
        (90, 90, 20),
        (80, 0, 120),
    ],
    dtype=np.uint8,
)
_GOLDEN = 0.618033988749895


def class_color(index: int) -> RGB:
    """The colour of semantic class ``index`` (``-1``: unlabelled). Stable across calls."""
    if index < 0:
        return UNLABELLED_RGB
    if index < len(_BASE):
        r, g, b = _BASE[index]
        return int(r), int(g), int(b)
    hue = (index * _GOLDEN) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.9)
    return int(round(r * 255)), int(round(g * 255)), int(round(b * 255))


def class_colors(labels: np.ndarray) -> np.ndarray:
    """``uint8 Nx3`` colours for ``int N`` class indices (``-1`` or below: unlabelled)."""
    labels = np.asarray(labels).astype(np.int64).reshape(-1)
    if labels.size == 0:
        return np.zeros((0, 3), np.uint8)
    top = max(int(labels.max()), 0)
    lut = np.array([class_color(i) for i in range(-1, top + 1)], dtype=np.uint8)  # row 0 is -1
    return lut[np.clip(labels, -1, top) + 1]


def height_colors(z: np.ndarray, z_min: float = 0.0, z_max: float = 2.0) -> np.ndarray:
    """``uint8 Nx3`` colours by height (the occupancy-only view): a perceptual colormap."""
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if z.size == 0:
        return np.zeros((0, 3), np.uint8)
    span = max(z_max - z_min, 1e-6)
    level = np.clip((z - z_min) / span * 255.0, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(level.reshape(1, -1), cv2.COLORMAP_VIRIDIS).reshape(-1, 3)
    return np.ascontiguousarray(bgr[:, ::-1])


def legend_html(classes: Sequence[str], counts: np.ndarray | None = None, max_rows: int = 40) -> str:
    """An HTML legend of class -> colour swatch (only classes with points when ``counts``
    is given; most points first). Names are escaped: they come from the network."""
    rows: list[tuple[int, str, int]] = []
    for i, name in enumerate(classes):
        n = int(counts[i]) if counts is not None and i < len(counts) else -1
        if counts is None or n > 0:
            rows.append((i, name, n))
    if counts is not None:
        rows.sort(key=lambda r: -r[2])
    if not rows:
        return "<div style='font-size:0.8em;color:#888'>no labelled voxels yet</div>"
    shown = rows[:max_rows]
    items = []
    for i, name, n in shown:
        r, g, b = class_color(i)
        count = f" <span style='color:#888'>({n})</span>" if n >= 0 else ""
        items.append(
            f"<span style='display:inline-block;margin:1px 6px 1px 0;white-space:nowrap'>"
            f"<span style='display:inline-block;width:10px;height:10px;border-radius:2px;"
            f"background:rgb({r},{g},{b});margin-right:3px;vertical-align:middle'></span>"
            f"{html.escape(name)}{count}</span>"
        )
    more = (
        f" <span style='color:#888'>+{len(rows) - len(shown)} more</span>" if len(rows) > len(shown) else ""
    )
    return f"<div style='font-size:0.8em;line-height:1.5'>{''.join(items)}{more}</div>"


def object_color(held: bool, out_of_place: bool) -> RGB:
    """Box colour of a tracked object: held wins over out of place, which wins over tracked."""
    if held:
        return HELD_RGB
    return WARNING_RGB if out_of_place else TRACKED_RGB


def css(rgb: RGB) -> str:
    return f"rgb({rgb[0]},{rgb[1]},{rgb[2]})"
