"""``tidee bench sim``: how fast the simulator steps, and how much of that is rendering."""

from __future__ import annotations

import os
import platform
import time

import numpy as np

from tidee.protocol.messages import Action, ActionName, EpisodeSpec
from tidee.server.episode import Episode

# A walk that exercises moves, turns and looks (each step renders one frame).
ACTIONS = [
    ActionName.MoveAhead,
    ActionName.RotateLeft,
    ActionName.MoveAhead,
    ActionName.LookDown,
    ActionName.MoveAhead,
    ActionName.RotateRight,
    ActionName.LookUp,
    ActionName.MoveBack,
    ActionName.MoveLeft,
    ActionName.MoveRight,
]


def run_sim_bench(
    resolution: int,
    steps: int,
    out_path: str,
    renderer: str = "auto",
    room_type: str = "LivingRoom",
    seed: int = 200,
) -> dict:
    ep = Episode(renderer=renderer)
    try:
        t0 = time.perf_counter()
        ep.reset(
            EpisodeSpec(
                room_type=room_type, seed=seed, mess_index=0, resolution=resolution, max_steps=steps + 10
            )
        )
        reset_s = time.perf_counter() - t0
        render_ms: list[float] = []
        original_render = ep.world.render

        def timed_render(*a, **kw):
            t = time.perf_counter()
            out = original_render(*a, **kw)
            render_ms.append((time.perf_counter() - t) * 1000)
            return out

        ep.world.render = timed_render  # type: ignore[method-assign]
        step_ms = []
        for _ in range(5):  # warm-up
            ep.step(Action(ActionName.RotateLeft))
        render_ms.clear()
        t_all = time.perf_counter()
        for k in range(steps):
            t = time.perf_counter()
            ep.step(Action(ACTIONS[k % len(ACTIONS)]))
            step_ms.append((time.perf_counter() - t) * 1000)
        wall = time.perf_counter() - t_all
        n_bodies = len(ep.world.bodies)
        renderer_used = ep.renderer
    finally:
        ep.close()
    result = {
        "resolution": resolution,
        "steps": steps,
        "renderer": renderer_used,
        "room": f"{room_type}/{seed}",
        "bodies": n_bodies,
        "reset_s": round(reset_s, 3),
        "step_ms_median": round(float(np.median(step_ms)), 3),
        "step_ms_p90": round(float(np.percentile(step_ms, 90)), 3),
        "render_ms_median": round(float(np.median(render_ms)), 3),
        "render_fraction": round(float(np.median(render_ms) / np.median(step_ms)), 3),
        "steps_per_s": round(steps / wall, 2),
        "machine": f"{platform.machine()} {os.cpu_count()} cores",
    }
    write_report(out_path, result, "Simulator benchmark (`tidee bench sim`)")
    return result


def spread(xs: list[float], digits: int = 2) -> dict[str, float]:
    """Median, p90 and max of a benchmark's samples."""
    a = np.asarray(xs, float)
    return {
        "median": round(float(np.median(a)), digits),
        "p90": round(float(np.percentile(a, 90)), digits),
        "max": round(float(a.max()), digits),
    }


def write_report(out_path: str, result: dict, title: str) -> None:
    """JSON plus a Markdown table beside it, both written atomically."""
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    write_json_atomic(out_path, result)
    lines = [f"# {title}", "", "| metric | value |", "|---|---|"]
    lines += [
        f"| {k} | {', '.join(f'{kk} {vv}' for kk, vv in v.items()) if isinstance(v, dict) else v} |"
        for k, v in result.items()
    ]
    write_atomic(os.path.splitext(out_path)[0] + ".md", ("\n".join(lines) + "\n").encode())
