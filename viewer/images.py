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

OOP_THRESHOLD = 0.5          # a detection with oop_prob above this is drawn as out of place
UNKNOWN_RGB: RGB = (44, 46, 52)
FREE_RGB: RGB = (236, 236, 228)
SEEN_FREE_RGB: RGB = (196, 206, 196)   # free but not yet explored (seen from afar)
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
    return cv2.resize(img, (img.shape[1] * factor, img.shape[0] * factor), interpolation=cv2.INTER_NEAREST), factor


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
        _label(img, f"depth 0-{max_depth:g} m", (4, img.shape[0] - 4), (255, 255, 255), _font_scale(img.shape[1]))
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
        return cv2.resize(flipped, (flipped.shape[1] * self.scale, flipped.shape[0] * self.scale),
                          interpolation=cv2.INTER_NEAREST)


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
    length = max(0.35, 6 / canvas.scale * canvas.cell)          # metres: visible at any zoom
    tip = (x + length * math.cos(yaw), y + length * math.sin(yaw))
    left = (x + 0.45 * length * math.cos(yaw + 2.4), y + 0.45 * length * math.sin(yaw + 2.4))
    right = (x + 0.45 * length * math.cos(yaw - 2.4), y + 0.45 * length * math.sin(yaw - 2.4))
    tri = canvas.pixels(np.array([tip, left, (x, y), right]))
    cv2.fillPoly(img, [tri], color, cv2.LINE_AA)
    cv2.polylines(img, [tri], True, (255, 255, 255), 1, cv2.LINE_AA)


def occupancy_image(occupancy: np.ndarray, explored: np.ndarray | None, origin: Sequence[float], cell: float,
                    pose: Sequence[float] | None = None, trajectory: np.ndarray | None = None,
                    path: np.ndarray | None = None, goal: Sequence[float] | None = None,
                    search_points: np.ndarray | None = None, min_width: int = 360) -> np.ndarray:
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
                cv2.putText(img, str(rank), (int(col) + 4, int(row) - 4), cv2.FONT_HERSHEY_SIMPLEX,
                            _font_scale(img.shape[1]), SEARCH_POINT_RGB, 1, cv2.LINE_AA)
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
    alpha = (min_alpha + np.sqrt(h) * (max_alpha - min_alpha)).astype(np.uint8)  # sqrt: the tails stay visible
    rgba = np.concatenate([rgb, alpha[..., None]], axis=2)
    return np.ascontiguousarray(rgba.transpose(1, 0, 2))


def placeholder(text: str, width: int = 512, height: int = 288) -> np.ndarray:
    """A dark image saying what is missing (``waiting for frames from session ...``)."""
    img = np.full((height, width, 3), 36, np.uint8)
    scale = _font_scale(width)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.putText(img, text, ((width - tw) // 2, (height + th) // 2), cv2.FONT_HERSHEY_SIMPLEX, scale,
                (200, 200, 200), 1, cv2.LINE_AA)
    return img

