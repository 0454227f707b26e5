"""Telemetry -> images for the GUI panels and the floor: detections, depth, maps, heatmaps.

Pure opencv/numpy functions; every image returned is ``uint8`` RGB (or RGBA), C-contiguous.

Top-down map images (the 2D occupancy panel) show the start frame with +x (the agent's
initial heading) *up* and +y (left) to the *left*: cell (i, j) of an X x Y grid is drawn at
row X-1-i, column Y-1-j. Floor textures (the search heatmap in 3D) follow viser's image
plane instead: column along +x, row along +y, i.e. the grid transposed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from tidee.protocol.messages import Detection2D
from tidee.viewer.palette import PATH_RGB, RGB, SEARCH_POINT_RGB, TRACKED_RGB, TRAJECTORY_RGB, WARNING_RGB

OOP_THRESHOLD = 0.5  # a detection with oop_prob above this is drawn as out of place
UNKNOWN_RGB: RGB = (44, 46, 52)
FREE_RGB: RGB = (236, 236, 228)
SEEN_FREE_RGB: RGB = (196, 206, 196)  # free but not yet explored (seen from afar)
OBSTACLE_RGB: RGB = (70, 84, 130)
AGENT_RGB: RGB = (220, 30, 30)


def _font_scale(width: int) -> float:
    return max(0.35, width / 900.0)


def _label(img: np.ndarray, text: str, org: tuple[int, int], color: RGB, scale: float) -> None:
    """Text on a filled box (readable over any image), kept inside the image."""
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, max(1, int(round(scale * 2)))
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    x = int(min(max(org[0], 0), max(img.shape[1] - tw - 4, 0)))
    y = int(min(max(org[1], th + 4), img.shape[0] - 1))
    cv2.rectangle(img, (x, y - th - base - 2), (x + tw + 4, y), color, -1)
    luminance = 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2]
    ink = (0, 0, 0) if luminance > 150 else (255, 255, 255)
    cv2.putText(img, text, (x + 2, y - base), font, scale, ink, thick, cv2.LINE_AA)


def upscale(img: np.ndarray, min_width: int) -> tuple[np.ndarray, int]:
    """``img`` enlarged by an integer factor to at least ``min_width`` pixels wide (nearest)."""
    factor = max(1, math.ceil(min_width / max(img.shape[1], 1)))
    if factor == 1:
        return np.ascontiguousarray(img), 1
    return cv2.resize(
        img, (img.shape[1] * factor, img.shape[0] * factor), interpolation=cv2.INTER_NEAREST
    ), factor


def draw_detections(rgb: np.ndarray, detections: Sequence[Detection2D], min_width: int = 512) -> np.ndarray:
    """The RGB frame enlarged, with each detection's box and ``label score`` drawn;
    out-of-place detections (``oop_prob`` > 0.5) in the warning colour with their probability."""
    img, factor = upscale(np.asarray(rgb, np.uint8), min_width)
    img = img.copy()
    scale = _font_scale(img.shape[1])
    for det in detections:
        oop = det.oop_prob is not None and det.oop_prob > OOP_THRESHOLD
        color = WARNING_RGB if oop else TRACKED_RGB
        x0, y0, x1, y1 = (int(round(v * factor)) for v in det.box)
        cv2.rectangle(img, (x0, y0), (x1, y1), color, max(2, factor))
        text = f"{det.label} {det.score:.2f}"
        if oop:
            text += f" OOP {det.oop_prob:.2f}"
        _label(img, text, (x0, y0), color, scale)
    return img


def colorize_depth(depth: np.ndarray, max_depth: float = 5.0, min_width: int = 512) -> np.ndarray:
    """Depth in metres as a colour image (near: bright, far: dark; invalid: black), with a scale note."""
    d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    valid = d > 0
    level = np.clip(255.0 * (1.0 - d / max_depth), 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_INFERNO)[..., ::-1].copy()
    rgb[~valid] = 0
    img, _ = upscale(rgb, min_width)
    if img.shape[1] >= 128:  # room for the scale note
        img = img.copy()
        _label(
            img, f"depth 0-{max_depth:g} m", (4, img.shape[0] - 4), (255, 255, 255), _font_scale(img.shape[1])
        )
    return np.ascontiguousarray(img)


class MapCanvas:
    """A top-down grid drawn +x up, +y left, ``scale`` pixels per cell; maps start-frame
    points to pixels so poses and paths can be drawn over it."""

    def __init__(self, origin: Sequence[float], cell: float, shape: tuple[int, int], scale: int) -> None:
        if cell <= 0 or scale < 1:
            raise ValueError(f"cell must be > 0 and scale >= 1, got cell={cell}, scale={scale}")
        self.x0, self.y0 = float(origin[0]), float(origin[1])
        self.cell, self.shape, self.scale = float(cell), shape, int(scale)

    def pixel(self, x: float, y: float) -> tuple[int, int]:
        """(column, row) of start-frame point (x, y)."""
        i, j = (x - self.x0) / self.cell, (y - self.y0) / self.cell
        return int(round((self.shape[1] - j) * self.scale)), int(round((self.shape[0] - i) * self.scale))

    def pixels(self, points: np.ndarray) -> np.ndarray:
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        cols = (self.shape[1] - (pts[:, 1] - self.y0) / self.cell) * self.scale
        rows = (self.shape[0] - (pts[:, 0] - self.x0) / self.cell) * self.scale
        return np.round(np.stack([cols, rows], axis=1)).astype(np.int32)

    def grid_to_image(self, grid_rgb: np.ndarray) -> np.ndarray:
        """An ``X x Y x 3`` per-cell colour grid as the map image (flipped, enlarged)."""
        flipped = np.ascontiguousarray(grid_rgb[::-1, ::-1])
        return cv2.resize(
            flipped,
            (flipped.shape[1] * self.scale, flipped.shape[0] * self.scale),
            interpolation=cv2.INTER_NEAREST,
        )


def occupancy_colors(occupancy: np.ndarray, explored: np.ndarray | None = None) -> np.ndarray:
    """``X x Y x 3`` cell colours: unknown dark, obstacle blue-grey, free light (explored lighter)."""
    occ = np.asarray(occupancy)
    if occ.ndim != 2:
        raise ValueError(f"occupancy must be a 2D grid, got shape {occ.shape}")
    out = np.empty(occ.shape + (3,), np.uint8)
    out[:] = UNKNOWN_RGB
    free = occ == 1
    if explored is not None:
        exp = np.asarray(explored, bool)
        if exp.shape != occ.shape:
            raise ValueError(f"explored {exp.shape} and occupancy {occ.shape} must have the same shape")
        out[free & ~exp] = SEEN_FREE_RGB
        out[free & exp] = FREE_RGB
        out[(occ == 0) & exp] = SEEN_FREE_RGB
    else:
        out[free] = FREE_RGB
    out[occ == 2] = OBSTACLE_RGB
    return out


def draw_agent(img: np.ndarray, canvas: MapCanvas, pose: Sequence[float], color: RGB = AGENT_RGB) -> None:
    """A filled arrowhead at (x, y) pointing along yaw (degrees, counter-clockwise from +x)."""
    x, y, yaw = float(pose[0]), float(pose[1]), math.radians(float(pose[2]))
    length = max(0.35, 6 / canvas.scale * canvas.cell)  # metres: visible at any zoom
    tip = (x + length * math.cos(yaw), y + length * math.sin(yaw))
    left = (x + 0.45 * length * math.cos(yaw + 2.4), y + 0.45 * length * math.sin(yaw + 2.4))
    right = (x + 0.45 * length * math.cos(yaw - 2.4), y + 0.45 * length * math.sin(yaw - 2.4))
    tri = canvas.pixels(np.array([tip, left, (x, y), right]))
    cv2.fillPoly(img, [tri], color, cv2.LINE_AA)
    cv2.polylines(img, [tri], True, (255, 255, 255), 1, cv2.LINE_AA)


def occupancy_image(
    occupancy: np.ndarray,
    explored: np.ndarray | None,
    origin: Sequence[float],
    cell: float,
    pose: Sequence[float] | None = None,
    trajectory: np.ndarray | None = None,
    path: np.ndarray | None = None,
    goal: Sequence[float] | None = None,
    search_points: np.ndarray | None = None,
    min_width: int = 360,
) -> np.ndarray:
    """The 2D occupancy / explored map (+x up) with the trajectory, planned path, goal,
    search points and the agent drawn over it."""
    occ = np.asarray(occupancy)
    colors = occupancy_colors(occ, explored)
    scale = max(1, math.ceil(min_width / max(occ.shape[1], 1)))
    canvas = MapCanvas(origin, cell, (occ.shape[0], occ.shape[1]), scale)
    img = canvas.grid_to_image(colors)
    thick = max(1, scale // 2)
    if trajectory is not None and len(trajectory) >= 2:
        cv2.polylines(img, [canvas.pixels(trajectory)], False, TRAJECTORY_RGB, thick, cv2.LINE_AA)
    if path is not None and len(path) >= 2:
        cv2.polylines(img, [canvas.pixels(path)], False, PATH_RGB, thick + 1, cv2.LINE_AA)
    if goal is not None:
        cv2.circle(img, canvas.pixel(goal[0], goal[1]), 3 * thick + 2, PATH_RGB, thick, cv2.LINE_AA)
    if search_points is not None:
        for rank, (col, row) in enumerate(canvas.pixels(search_points)[:5], start=1):
            cv2.circle(img, (int(col), int(row)), 2 * thick + 1, SEARCH_POINT_RGB, -1, cv2.LINE_AA)
            if rank <= 3:
                cv2.putText(
                    img,
                    str(rank),
                    (int(col) + 4, int(row) - 4),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    _font_scale(img.shape[1]),
                    SEARCH_POINT_RGB,
                    1,
                    cv2.LINE_AA,
                )
    if pose is not None:
        draw_agent(img, canvas, pose)
    return img


def heatmap_rgba(heatmap: np.ndarray, min_alpha: int = 0, max_alpha: int = 210) -> np.ndarray:
    """A top-down ``X x Y`` heatmap in [0, 1] as an RGBA floor texture for viser's image
    plane (``Y x X x 4``: column along +x, row along +y); cold cells are transparent."""
    h = np.asarray(heatmap, np.float32)
    if h.ndim != 2:
        raise ValueError(f"a heatmap must be a 2D grid, got shape {h.shape}")
    h = np.clip(np.nan_to_num(h, nan=0.0), 0.0, 1.0)
    level = (h * 255.0).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_JET)[..., ::-1]
    alpha = (min_alpha + np.sqrt(h) * (max_alpha - min_alpha)).astype(
        np.uint8
    )  # sqrt: the tails stay visible
    rgba = np.concatenate([rgb, alpha[..., None]], axis=2)
    return np.ascontiguousarray(rgba.transpose(1, 0, 2))


def placeholder(text: str, width: int = 512, height: int = 288) -> np.ndarray:
    """A dark image saying what is missing (``waiting for frames from session ...``)."""
    img = np.full((height, width, 3), 36, np.uint8)
    scale = _font_scale(width)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.putText(
        img,
        text,
        ((width - tw) // 2, (height + th) // 2),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        (200, 200, 200),
        1,
        cv2.LINE_AA,
    )
    return img


PLOT_SIZE = (360, 170)  # width, height of the progress plot image (px): about its size on the page
PLOT_SERIES = (("put away", WARNING_RGB), ("out of place found", TRAJECTORY_RGB))


def _nice_ticks(top: float, max_ticks: int = 6) -> np.ndarray:
    """Round tick values 0, s, 2s, ... covering [0, top] (s = 1, 2 or 5 x 10^k, integers at least)."""
    top = max(float(top), 1.0)
    raw = top / max(max_ticks - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next((m * mag for m in (1, 2, 5, 10) if m * mag >= raw), 10 * mag)
    step = max(step, 1.0)
    return np.arange(0.0, top + step * 0.999, step)


def progress_plot(history: np.ndarray, size: tuple[int, int] = PLOT_SIZE) -> np.ndarray:
    """The progress plot as an RGB image of a fixed ``size``: objects put away and
    out-of-place objects found against the agent's step (x), as step lines, with axes,
    ticks and a legend row above the plot area. ``history`` is ``K x 3`` (step, put away, found); an
    empty one gives the empty axes with a note, one row a dot per series."""
    width, height = size
    rows = np.asarray(history, np.float64).reshape(-1, 3)
    img = np.full((height, width, 3), 255, np.uint8)
    font, scale, ink, grid = cv2.FONT_HERSHEY_SIMPLEX, 0.45, (60, 60, 60), (228, 228, 228)
    left, right, top, bottom = 34, 14, 26, 26  # margins: ticks, legend row, x labels
    x0, x1, y0, y1 = left, width - right, top, height - bottom  # plot area (y down)
    # legend row: swatch + name per series, above the plot area so it never covers a line
    x = left
    for name, color in PLOT_SERIES:
        cv2.line(img, (x, 11), (x + 18, 11), color, 3, cv2.LINE_AA)
        cv2.putText(img, name, (x + 23, 16), font, scale, ink, 1, cv2.LINE_AA)
        x += 23 + cv2.getTextSize(name, font, scale, 1)[0][0] + 16
    last_step = float(rows[:, 0].max()) if len(rows) else 0.0
    xticks = _nice_ticks(max(last_step, 10.0))
    yticks = _nice_ticks(max(float(rows[:, 1:].max()) if len(rows) else 0.0, 3.0), max_ticks=5)
    x_top, y_top = float(xticks[-1]), float(yticks[-1])

    def px(step: np.ndarray, value: np.ndarray) -> np.ndarray:
        u = x0 + (np.asarray(step) / x_top) * (x1 - x0)
        v = y1 - (np.asarray(value) / y_top) * (y1 - y0)
        return np.round(np.stack([u, v], axis=-1)).astype(np.int32)

    for t in yticks:
        ((_, v),) = px(np.array([0.0]), np.array([t]))
        cv2.line(img, (x0, int(v)), (x1, int(v)), grid, 1)
        label = f"{t:g}"
        tw = cv2.getTextSize(label, font, scale, 1)[0][0]
        cv2.putText(img, label, (x0 - 6 - tw, int(v) + 5), font, scale, ink, 1, cv2.LINE_AA)
    for t in xticks:
        ((u, _),) = px(np.array([t]), np.array([0.0]))
        cv2.line(img, (int(u), y1), (int(u), y1 + 4), ink, 1)
        label = f"{t:g}"
        tw = cv2.getTextSize(label, font, scale, 1)[0][0]
        cv2.putText(img, label, (int(u) - tw // 2, y1 + 18), font, scale, ink, 1, cv2.LINE_AA)
    cv2.line(img, (x0, y1), (x1, y1), ink, 1)
    cv2.line(img, (x0, y0), (x0, y1), ink, 1)
    if not len(rows):
        note = "no steps yet"
        tw = cv2.getTextSize(note, font, scale, 1)[0][0]
        cv2.putText(
            img, note, ((x0 + x1 - tw) // 2, (y0 + y1) // 2), font, scale, (150, 150, 150), 1, cv2.LINE_AA
        )
        return img
    for k, (_, color) in reversed(list(enumerate(PLOT_SERIES, start=1))):
        steps, values = rows[:, 0], rows[:, k]
        if len(rows) == 1:
            cv2.circle(img, tuple(int(c) for c in px(steps, values)[0]), 4, color, -1, cv2.LINE_AA)
            continue
        # a step line: each value holds until the next step
        stairs_x = np.repeat(steps, 2)[1:]
        stairs_y = np.repeat(values, 2)[:-1]
        cv2.polylines(img, [px(stairs_x, stairs_y)], False, color, 3 if k == 1 else 2, cv2.LINE_AA)
    return img


def crop_to_known(
    occupancy: np.ndarray,
    explored: np.ndarray | None,
    origin: Sequence[float],
    cell: float,
    margin: float = 0.75,
) -> tuple[np.ndarray, np.ndarray | None, tuple[float, float]]:
    """The square part of a top-down grid around its known cells (occupancy > 0 or explored),
    ``margin`` metres wider on each side: ``(occupancy, explored, origin)`` of the crop. The
    whole grid when nothing is known yet."""
    occ = np.asarray(occupancy)
    known = occ > 0
    if explored is not None:
        known = known | np.asarray(explored, bool)
    idx = np.argwhere(known)
    if idx.size == 0 or cell <= 0:
        return occ, explored, (float(origin[0]), float(origin[1]))
    pad = int(math.ceil(margin / cell))
    lo, hi = idx.min(axis=0) - pad, idx.max(axis=0) + 1 + pad
    side = int(max(hi - lo))
    lo = np.clip((lo + hi) // 2 - side // 2, 0, None)
    hi = np.minimum(lo + side, occ.shape[:2])
    lo = np.maximum(hi - side, 0)
    sl = (slice(int(lo[0]), int(hi[0])), slice(int(lo[1]), int(hi[1])))
    crop_origin = (float(origin[0]) + lo[0] * cell, float(origin[1]) + lo[1] * cell)
    return occ[sl], (np.asarray(explored)[sl] if explored is not None else None), crop_origin
