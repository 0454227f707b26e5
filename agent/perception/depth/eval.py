"""``tidee eval depth`` (options: ``config.DepthEvalConfig``): a depth model on held-out test
(or val) rooms rendered on the fly: abs rel, RMSE, delta < 1.25, an example grid and the
inference time.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tidee.agent.perception.depth.config import EvalSet
from tidee.agent.perception.depth.model import RESOLUTION, VALID_MAX, VALID_MIN, DepthEstimator, DepthModel
from tidee.protocol.vocab import HeldOutSplit


def time_inference(estimator: DepthEstimator, repeats: int = 30, threads: int = 1) -> dict[str, float]:
    """Median and best ms per 256^2 frame on ``threads`` CPU threads (after a warm-up)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rgb = np.random.default_rng(0).integers(0, 256, (RESOLUTION, RESOLUTION, 3), dtype=np.uint8)
        for _ in range(5):
            estimator.predict(rgb)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            estimator.predict(rgb)
            times.append(1000 * (time.perf_counter() - t))
    finally:
        torch.set_num_threads(previous)
    return {
        "threads": threads,
        "median_ms": round(float(np.median(times)), 2),
        "min_ms": round(min(times), 2),
    }


def heldout_frames(split: HeldOutSplit, eval_set: EvalSet, progress: bool = True) -> dict[str, np.ndarray]:
    """The ``eval_set`` frames of the val or test rooms (``detector.data.held_out_frames``)."""
    from tidee.agent.perception.detector.data import held_out_frames

    return held_out_frames(
        split,
        rooms_per_type=eval_set.rooms_per_type,
        messes=eval_set.messes,
        frames_per_walk=eval_set.frames_per_walk,
        seed=eval_set.seed,
        progress=progress,
    )


def evaluate_depth(estimator: DepthModel, frames: dict[str, np.ndarray]) -> dict[str, Any]:
    """Abs rel, RMSE (m), delta < 1.25 over each frame's valid pixels; mean over frames and per room type."""
    per_frame: list[tuple[str, float, float, float]] = []
    rooms = frames.get("frame_room", np.array(["?"] * len(frames["rgb"])))
    for rgb, depth, room in zip(frames["rgb"], frames["depth"], rooms):
        d = depth.astype(np.float32)
        valid = (d > VALID_MIN) & (d < VALID_MAX)
        if not valid.any():
            continue
        est = np.maximum(np.asarray(estimator.predict(rgb), np.float32)[valid], 1e-3)
        d = d[valid]
        ratio = np.maximum(est / d, d / est)
        per_frame.append(
            (
                str(room).split(":")[0],
                float(np.mean(np.abs(est - d) / d)),
                float(np.sqrt(np.mean((est - d) ** 2))),
                float(np.mean(ratio < 1.25)),
            )
        )
    if not per_frame:
        raise ValueError("no frame has valid depth pixels to score")
    by_type: dict[str, list[float]] = {}
    for rt, abs_rel, _, _ in per_frame:
        by_type.setdefault(rt, []).append(abs_rel)
    return {
        "frames": len(per_frame),
        "abs_rel": round(float(np.mean([f[1] for f in per_frame])), 4),
        "rmse": round(float(np.mean([f[2] for f in per_frame])), 4),
        "delta1": round(float(np.mean([f[3] for f in per_frame])), 4),
        "abs_rel_by_room_type": {rt: round(float(np.mean(v)), 4) for rt, v in sorted(by_type.items())},
    }


def colorize_depth(depth: np.ndarray, max_depth: float = 6.0) -> np.ndarray:
    """BGR uint8 (turbo colour map, near = blue); pixels without depth are black."""
    import cv2

    scaled = np.clip(depth / max_depth * 255, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    img[depth <= VALID_MIN] = 0
    return img


def save_examples(estimator: DepthModel, frames: dict[str, np.ndarray], png: str | Path, n: int = 6) -> Path:
    """A PNG grid, one row per frame (spread over the set): RGB | true depth | estimated depth."""
    import cv2

    total = len(frames["rgb"])
    picks = np.unique(np.linspace(0, total - 1, min(n, total)).round().astype(int))
    rows = []
    for i in picks:
        rgb = frames["rgb"][i]
        true = frames["depth"][i].astype(np.float32)
        est = np.asarray(estimator.predict(rgb), np.float32)
        row = np.concatenate(
            [cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), colorize_depth(true), colorize_depth(est)], 1
        )
        label = str(frames["frame_room"][i]) if "frame_room" in frames else str(i)
        cv2.putText(row, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    header = np.zeros((18, rows[0].shape[1], 3), np.uint8)
    w = rgb.shape[1]
    for k, text in enumerate(("RGB", "true depth", "estimated depth")):
        cv2.putText(
            header, text, (k * w + 4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA
        )
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(png), np.concatenate([header] + rows, 0))
    return png


def metrics_markdown(result: dict[str, Any]) -> str:
    m, e = result["metrics"], result["eval_set"]
    lines = [
        f"# Depth from RGB: {result['split']} rooms",
        "",
        f"Weights `{result['weights']}` (sha256 {result.get('sha256', '?')[:12]}); "
        f"{m['frames']} frames: {e['rooms_per_type']} rooms per type, "
        f"tidy + {e['messes']} messy configurations each, {e['frames_per_walk']} frames per walk, "
        f"seed {e['seed']}.",
        "",
        "| metric | value |",
        "|---|---|",
        f"| abs rel | {m['abs_rel']:.3f} |",
        f"| RMSE (m) | {m['rmse']:.3f} |",
        f"| delta < 1.25 | {m['delta1']:.3f} |",
    ]
    lines += [f"| abs rel, {rt} | {v:.3f} |" for rt, v in m["abs_rel_by_room_type"].items()]
    if "speed" in result:
        s = result["speed"]
        lines += [f"| ms / frame (1 CPU thread, median) | {s['median_ms']:.1f} |"]
    lines += ["", f"Command: `{result['command']}`", ""]
    return "\n".join(lines)


__all__ = [
    "colorize_depth",
    "evaluate_depth",
    "heldout_frames",
    "metrics_markdown",
    "save_examples",
    "time_inference",
]
