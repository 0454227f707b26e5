"""Pictures of a room for people: corner views, the agent's first view and a top-down map."""

from __future__ import annotations

import math
import os

import cv2
import numpy as np

from tidee.server.episode import SceneLibrary
from tidee.server.rooms import NAV_CELL, nav_grid
from tidee.server.scene import Scene
from tidee.server.world import World


def _look_at(world: World, eye: np.ndarray, target: np.ndarray, res: int, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    rgb, _, _ = world.render(eye, fwd, np.array(up), res)
    return rgb


def top_down(world: World, scene: Scene, res: int, annotate: bool = True) -> np.ndarray:
    """A view from above the ceiling, moved objects circled in red when the scene is messy."""
    cx, cy = scene.width / 2, scene.depth / 2
    half = max(scene.width, scene.depth) / 2 + 0.3
    height = 1.25 * half / math.tan(math.radians(45)) + 1.0  # room edges stay in view
    eye = np.array([cx, cy, height])
    rgb = world.render(eye, np.array([0, 0, -1.0]), np.array([0, 1.0, 0]), res)[0].copy()
    if not annotate:
        return rgb

    def to_px(x: float, y: float, z: float) -> tuple[int, int]:
        d = height - z
        f = (res / 2) / math.tan(math.radians(45))
        return int(res / 2 + f * (x - cx) / d), int(res / 2 - f * (y - cy) / d)

    for m in scene.mess:
        u, v = to_px(*m.messy_position)
        cv2.circle(rgb, (u, v), max(6, res // 40), (230, 30, 30), 2, cv2.LINE_AA)
        cv2.putText(rgb, m.type, (u + 8, v - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (230, 30, 30), 1, cv2.LINE_AA)
    return rgb


def corner_views(world: World, scene: Scene, res: int) -> list[np.ndarray]:
    """From the walkable spot nearest each corner, at head height, towards the centre."""
    free = nav_grid(
        [world.aabb(o.id) for o in scene.objects if not o.pickupable and o.type != "Floor"],
        scene.width,
        scene.depth,
    )
    pts = (np.argwhere(free) + 0.5) * NAV_CELL
    views = []
    m = 0.35
    for corner in ((m, m), (scene.width - m, m), (scene.width - m, scene.depth - m), (m, scene.depth - m)):
        x, y = pts[int(np.argmin(np.linalg.norm(pts - np.array(corner), axis=1)))] if len(pts) else corner
        eye = np.array([x, y, 1.75])
        target = np.array([scene.width / 2, scene.depth / 2, 0.55])
        views.append(_look_at(world, eye, target, res))
    return views


def render_room(
    room_type: str, seed: int, mess: int | None, out_dir: str, resolution: int = 480, renderer: str = "auto"
) -> list[str]:
    os.makedirs(out_dir, exist_ok=True)
    world = World(renderer=renderer)
    try:
        scene = SceneLibrary().scene(world, room_type, seed, mess)
        tag = f"{room_type}_{seed}" + (f"_mess{mess}" if mess is not None else "")
        paths = []
        for k, img in enumerate(corner_views(world, scene, resolution)):
            paths.append(os.path.join(out_dir, f"{tag}_view{k}.png"))
            cv2.imwrite(paths[-1], img[:, :, ::-1])
        paths.append(os.path.join(out_dir, f"{tag}_topdown.png"))
        cv2.imwrite(paths[-1], top_down(world, scene, resolution)[:, :, ::-1])
        grid = np.concatenate(
            [
                np.concatenate(corner_views(world, scene, resolution // 2)[:2], axis=1),
                np.concatenate(corner_views(world, scene, resolution // 2)[2:], axis=1),
            ],
            axis=0,
        )
        paths.append(os.path.join(out_dir, f"{tag}_grid.png"))
        cv2.imwrite(paths[-1], grid[:, :, ::-1])
        return paths
    finally:
        world.close()


__all__ = ["render_room", "top_down", "corner_views"]
