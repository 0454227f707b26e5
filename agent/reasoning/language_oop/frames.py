"""Paragraphs of one frame's detections, from the frame's depth alone (no object memory).

What the Table-3 language rows (:func:`.eval.language_row`) and the fused head's training
data (:mod:`.fused_train`) read: each detection is unprojected with the frame's depth in a
gravity-aligned frame (the pitch, which the frames do not record, is estimated from the
depth among the agent's horizons) and described among the frame's other detections.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from tidee.agent.classes import RECEPTACLES
from tidee.agent.reasoning.language_oop.paragraphs import object_paragraph
from tidee.agent.reasoning.relations import ObjectRef

if TYPE_CHECKING:
    from tidee.agent.perception.base import Detection

# Camera of the evaluation frames (EpisodeSpec defaults): 90 deg FOV, height 0.9015 m; the
# pitch is one of the agent's horizons (LookUp / LookDown in 30 deg steps within -30..60).
CAMERA_HEIGHT_M = 0.9015
PITCH_CANDIDATES_DEG = (-30.0, 0.0, 30.0, 60.0)


def _gravity_points(depth: np.ndarray, pitch_deg: float, stride: int = 1) -> np.ndarray:
    """(H', W', 3) points in a gravity-aligned frame at the camera's foot: x forward
    (horizontal), y left, z up from the floor; NaN where depth is missing."""
    h, w = depth.shape
    f, c = w / 2.0, (w - 1) / 2.0
    v, u = np.mgrid[0:h:stride, 0:w:stride].astype(np.float64)
    d = np.asarray(depth, np.float64)[::stride, ::stride]
    d = np.where(d > 0.05, d, np.nan)
    x_cam, y_cam = (u - c) / f * d, (v - c) / f * d  # right, down; d = forward (z-depth)
    th = math.radians(pitch_deg)
    fwd = d * math.cos(th) - y_cam * math.sin(th)
    up = CAMERA_HEIGHT_M - y_cam * math.cos(th) - d * math.sin(th)
    return np.stack([fwd, -x_cam, up], -1)


def estimate_pitch(depth: np.ndarray, candidates: Sequence[float] = PITCH_CANDIDATES_DEG) -> float:
    """The horizon (deg, positive down) under which the frame's points look most like a room:
    horizontal surfaces (floor, table tops) pile up at few heights and nothing lies below the
    floor. Score: share of points in the fullest 2 cm height bin minus 4 x share below -5 cm."""
    best, best_score = float(candidates[0]), -math.inf
    for pitch in candidates:
        z = _gravity_points(depth, pitch, stride=4)[..., 2].reshape(-1)
        z = z[np.isfinite(z)]
        if not len(z):
            continue
        hist, _ = np.histogram(z, bins=np.arange(-1.01, 3.0, 0.02))
        score = hist.max() / len(z) - 4.0 * float(np.mean(z < -0.05))
        if score > best_score:
            best, best_score = float(pitch), score
    return best


def detection_refs(
    depth: np.ndarray, dets: Sequence[Detection], pitch_deg: float | None = None, min_points: int = 4
) -> list[ObjectRef | None]:
    """One ``ObjectRef`` per detection from its depth pixels (mask, else the box's inner half)
    unprojected in the gravity-aligned camera-foot frame: centroid = median point, box =
    5th-95th percentiles. None where the detection has too few valid depth pixels."""
    pitch = estimate_pitch(depth) if pitch_deg is None else pitch_deg
    pts = _gravity_points(depth, pitch)
    h, w = depth.shape
    out: list[ObjectRef | None] = []
    for k, d in enumerate(dets):
        if d.mask is not None:
            region = d.mask
        else:
            x0, y0, x1, y1 = d.box
            dx, dy = (x1 - x0) / 4.0, (y1 - y0) / 4.0
            region = np.zeros((h, w), bool)
            region[
                max(int(y0 + dy), 0) : max(math.ceil(y1 - dy), 0),
                max(int(x0 + dx), 0) : max(math.ceil(x1 - dx), 0),
            ] = True
        p = pts[region]
        p = p[np.all(np.isfinite(p), 1)]
        if len(p) >= min_points:  # keep the object's depth layer, not the wall behind it
            r = np.linalg.norm(p[:, :2], axis=1)
            p = p[np.abs(r - np.median(r)) < max(0.25, 0.25 * float(np.median(r)))]
        if len(p) < min_points:
            out.append(None)
            continue
        lo, hi = np.percentile(p, 5, axis=0), np.percentile(p, 95, axis=0)
        out.append(
            ObjectRef(
                id=k,
                label=d.label,
                centroid=np.median(p, 0),
                box_min=lo,
                box_max=hi,
                receptacle=d.label in RECEPTACLES,
            )
        )
    return out


def frame_paragraphs(
    depth: np.ndarray, dets: Sequence[Detection], context_score: float = 0.3
) -> list[tuple[int, str]]:
    """(detection index, paragraph) of one frame's detections that have depth, with the
    frame's detections of score >= ``context_score`` as context (:func:`.eval.language_row`)."""
    if not dets:
        return []
    refs = detection_refs(depth, dets)
    context = [r for r, d in zip(refs, dets) if r is not None and d.score >= context_score]
    return [(k, object_paragraph(r, context)) for k, r in enumerate(refs) if r is not None]
