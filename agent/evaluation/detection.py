"""``tidee eval detector`` and ``tidee eval oop``: box AP and in/out-of-place AP on held-out rooms.

Both commands render frames from the *test* (or val) rooms on the fly with
:mod:`tidee.agent.perception.dataset` (never from training shards), run a detector's
``detect_batch`` on them and score the detections against the simulator's instances.

**Box AP** (:func:`evaluate_boxes`) is COCO-style: per class, detections are matched
greedily by score to the ground-truth (GT) boxes of their frame at an IoU threshold, each GT
at most once; AP is the 101-point interpolated precision envelope; mAP averages the classes
that have at least one GT. Reported: mAP@0.5, mAP@[.5:.95] (10 thresholds) and AP@0.5 by
object size (small < 32², medium < 96², large; box areas in pixels of the frame).

**OOP AP** (:func:`evaluate_oop`) is the paper's Table 3 (§4.3): two categories, "in-place"
and "out-of-place", over pickupable objects only. The GT category of an object is its
``obj_oop`` label; a detection of a pickupable class takes part in *both* categories: in
"out-of-place" with confidence ``score * p`` and in "in-place" with ``score * (1 - p)``,
``p`` being a classifier's P(out of place) for it. Within a category a detection matches any
GT box of that category by IoU (the object's class label plays no part, as in the paper's
two-category setting). AP per category at IoU 0.25 and 0.5; mAP is their mean. Several
classifiers ("rows": visual, language, fused, oracle-language) are scored over the *same*
detections, each giving its own ``p`` per detection.

A detector here is anything with ``name`` and ``detect_batch(rgbs, depths)``
(:class:`FrameDetector`), e.g. ``LearnedPerception``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from tidee.agent.classes import CLASS_INDEX, CLASSES, PICKUPABLE
from tidee.agent.perception import AGENT_THRESHOLD, PEAK_MODES, TRAINED_RENDERER
from tidee.agent.perception.base import Detection
from tidee.agent.perception.dataset import held_out_frames
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.server.splits import ROOM_TYPES

__all__ = [
    "FrameDetector",
    "COCO_IOUS",
    "OOP_IOUS",
    "OOP_ROWS",
    "PAPER_TABLE3",
    "SIZE_RANGES",
    "average_precision",
    "box_iou",
    "match_detections",
    "evaluate_boxes",
    "evaluate_oop",
    "oop_table_markdown",
    "save_detection_examples",
    "run_detector_eval",
    "run_oop_eval",
    "register",
]

COCO_IOUS: tuple[float, ...] = tuple(round(0.5 + 0.05 * i, 2) for i in range(10))  # .50:.05:.95
OOP_IOUS: tuple[float, ...] = (0.25, 0.5)
RECALL_POINTS = np.linspace(0.0, 1.0, 101)
# COCO's area ranges (box area, pixels): small < 32^2 <= medium < 96^2 <= large.
SIZE_RANGES: dict[str, tuple[float, float]] = {
    "small": (0.0, 32.0**2),
    "medium": (32.0**2, 96.0**2),
    "large": (96.0**2, math.inf),
}

VISUAL_ROW = "dDETR-OOP (visual)"
OOP_ROWS: tuple[str, ...] = (VISUAL_ROW, "BERT-OOP (language)", "dDETR+BERT-OOP (fused)", "Oracle-language")
NOT_BUILT = "not run (`--visual-only`)"
# Table 3 of the paper (tidee-eccv2022.tex, tab:oop_supp), AP in %, on AI2THOR test rooms:
# (mAP, AP in-place, AP out-of-place) at IoU 0.25, then at IoU 0.5; None where the paper has "--".
# The paper's names: dDETR-OOP, BERT-OOP, dDETR+BERT-OOP, oracle-BERT-OOP.
PAPER_TABLE3: dict[str, tuple[float | None, ...]] = {
    VISUAL_ROW: (49.98, 57.60, 42.37, 44.98, 52.79, 37.17),
    "BERT-OOP (language)": (31.71, 41.13, 22.30, 25.25, 33.79, 16.71),
    "dDETR+BERT-OOP (fused)": (51.09, 58.41, 43.78, 46.26, 53.64, 38.88),
    "Oracle-language": (None, None, None, 90.70, 96.24, 85.16),
}

# A classifier row computed after detection: (frames, detections per frame) -> P(oop) per detection.
OopRowFn = Callable[[Mapping[str, np.ndarray], list[list[Detection]]], list[list[float]]]

SECOND_GUESSES = 3  # classes per heatmap peak in the report's second mAP (see run_detector_eval)


class FrameDetector(Protocol):
    name: str

    def detect_batch(self, rgbs: np.ndarray, depths: np.ndarray) -> list[list[Detection]]: ...


# ------------------------------------------------------------------------- AP and matching


def average_precision(
    scores: Sequence[float] | np.ndarray, is_tp: Sequence[bool] | np.ndarray, n_gt: int
) -> float:
    """COCO-style AP: precision envelope sampled at 101 recall points (0, 0.01, ..., 1).

    ``scores`` and ``is_tp`` describe every (non-ignored) detection of one class; ``n_gt``
    counts its GT objects. Ties in score keep their given order (stable sort, as COCO).
    Returns nan when ``n_gt`` is 0 (such classes are left out of every mean).
    """
    if n_gt <= 0:
        return math.nan
    scores = np.asarray(scores, np.float64).reshape(-1)
    is_tp = np.asarray(is_tp, bool).reshape(-1)
    if scores.shape != is_tp.shape:
        raise ValueError(f"scores and is_tp differ in length: {scores.shape[0]} vs {is_tp.shape[0]}")
    if scores.size == 0:
        return 0.0
    order = np.argsort(-scores, kind="mergesort")
    tp = np.cumsum(is_tp[order])
    fp = np.cumsum(~is_tp[order])
    recall = tp / n_gt
    precision = tp / np.maximum(tp + fp, 1)
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    idx = np.searchsorted(recall, RECALL_POINTS, side="left")
    sampled = np.where(idx < len(envelope), envelope[np.minimum(idx, len(envelope) - 1)], 0.0)
    return float(sampled.mean())


def _box_area(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    return np.maximum(boxes[:, 2] - boxes[:, 0], 0) * np.maximum(boxes[:, 3] - boxes[:, 1], 0)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix (len(a) x len(b)) of half-open x0, y0, x1, y1 boxes."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    w = np.maximum(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0)
    h = np.maximum(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0)
    inter = w * h
    union = _box_area(a)[:, None] + _box_area(b)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def _greedy_match(
    ious: np.ndarray, scores: np.ndarray, iou_thresholds: np.ndarray, gt_ignore: np.ndarray
) -> np.ndarray:
    """R x D: for each of R settings (IoU threshold, R x G ignore flags), each detection's GT or -1."""
    n_r, (n_d, n_g) = len(iou_thresholds), ious.shape
    matched = np.full((n_r, n_d), -1, np.int64)
    if n_g == 0:
        return matched
    free = np.ones((n_r, n_g), bool)
    rows = np.arange(n_r)
    for d in np.argsort(-scores, kind="mergesort"):
        ok = free & (ious[d][None, :] >= iou_thresholds[:, None])
        # COCO: the best unmatched non-ignored GT; only when there is none, an ignored one.
        for allowed in (~gt_ignore, gt_ignore):
            cand = np.where(ok & allowed & (matched[:, d] < 0)[:, None], ious[d][None, :], -1.0)
            g = cand.argmax(1)
            hit = cand[rows, g] >= 0
            matched[hit, d] = g[hit]
            free[rows[hit], g[hit]] = False
    return matched


def match_detections(
    det_boxes: np.ndarray,
    det_scores: np.ndarray,
    gt_boxes: np.ndarray,
    iou_threshold: float,
    gt_ignore: np.ndarray | None = None,
) -> np.ndarray:
    """Greedy matching of one frame's detections of one class to its GT boxes.

    Detections in decreasing score take the unmatched GT of highest IoU >= ``iou_threshold``;
    each GT is matched at most once. GTs flagged in ``gt_ignore`` (e.g. outside a size range)
    are matched only when no other GT qualifies, and such a match counts neither way.
    Returns, per detection in input order, the index of its GT or -1 (a false positive).
    """
    gt_boxes = np.asarray(gt_boxes, np.float64).reshape(-1, 4)
    ignore = np.zeros(len(gt_boxes), bool) if gt_ignore is None else np.asarray(gt_ignore, bool)
    return _greedy_match(
        box_iou(det_boxes, gt_boxes),
        np.asarray(det_scores, np.float64),
        np.array([iou_threshold], np.float64),
        ignore[None, :],
    )[0]


def _index_by(group: np.ndarray, frame: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """{(group, frame): indices of the rows with that group and frame}."""
    if not len(group):
        return {}
    order = np.lexsort((frame, group))
    keys = np.stack([group[order], frame[order]], 1)
    starts = np.nonzero(np.any(np.diff(keys, axis=0) != 0, axis=1))[0] + 1
    return {(int(k[0]), int(k[1])): part for k, part in zip(keys[np.r_[0, starts]], np.split(order, starts))}


Setting = tuple[float, tuple[float, float] | None]  # (IoU threshold, box-area range or None)


def _group_ap(
    det_frame: np.ndarray,
    det_group: np.ndarray,
    det_score: np.ndarray,
    det_box: np.ndarray,
    gt_frame: np.ndarray,
    gt_group: np.ndarray,
    gt_box: np.ndarray,
    settings: Sequence[Setting],
) -> dict[int, dict[str, Any]]:
    """AP per group (class, or OOP category) for each setting, over every frame.

    A setting is an IoU threshold and an optional box-area range: GT outside the range are
    ignored, and so are unmatched detections outside it (COCO's area ranges). Returns
    {group: {"n_gt": [per setting], "n_det": int, "ap": [per setting]}} for every group that
    has a GT or a detection. Each (group, frame) is matched once for all settings.
    """
    n_r = len(settings)
    thresholds = np.array([t for t, _ in settings], np.float64)
    gt_area, det_area = _box_area(gt_box), _box_area(det_box)
    gt_ign = np.zeros((n_r, len(gt_frame)), bool)
    det_out = np.zeros((n_r, len(det_frame)), bool)
    for r, (_, size_range) in enumerate(settings):
        if size_range is not None:
            lo, hi = size_range
            gt_ign[r] = (gt_area < lo) | (gt_area >= hi)
            det_out[r] = (det_area < lo) | (det_area >= hi)
    tp = np.zeros((n_r, len(det_frame)), bool)
    ignored = det_out.copy()  # unmatched detections outside the size range
    gt_by = _index_by(gt_group, gt_frame)
    for key, dl in _index_by(det_group, det_frame).items():
        gl = gt_by.get(key)
        if gl is None:  # no GT of this group in this frame: all false positives
            continue
        m = _greedy_match(box_iou(det_box[dl], gt_box[gl]), det_score[dl], thresholds, gt_ign[:, gl])
        hit = m >= 0
        hit_ignored = hit & np.take_along_axis(gt_ign[:, gl], np.maximum(m, 0), 1)
        tp[:, dl] = hit & ~hit_ignored
        ignored[:, dl] = np.where(hit, hit_ignored, det_out[:, dl])
    out: dict[int, dict[str, Any]] = {}
    for g in sorted(set(det_group.tolist()) | set(gt_group.tolist())):
        d = det_group == g
        n_gt = [int(((gt_group == g) & ~gt_ign[r]).sum()) for r in range(n_r)]
        aps = [
            average_precision(det_score[d & ~ignored[r]], tp[r][d & ~ignored[r]], n_gt[r]) for r in range(n_r)
        ]
        out[int(g)] = {"n_gt": n_gt, "n_det": int(d.sum()), "ap": aps}
    return out


def _nanmean(xs: Sequence[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return float(np.mean(xs)) if xs else math.nan


def _num_frames(frames: Mapping[str, np.ndarray], detections_per_frame: Sequence[Sequence[Any]]) -> int:
    n = len(detections_per_frame)
    for key in ("rgb", "frame_room"):
        if key in frames and len(frames[key]) != n:
            raise ValueError(
                f"{len(detections_per_frame)} lists of detections for {len(frames[key])} frames "
                f"(frames[{key!r}]); give one list per frame, in order"
            )
    if len(frames["obj_frame"]) and int(np.max(frames["obj_frame"])) >= n:
        raise ValueError(
            f"frames has objects in frame {int(np.max(frames['obj_frame']))} but only {n} lists of detections"
        )
    return n


def _flatten(detections_per_frame: Sequence[Sequence[Detection]]) -> tuple[np.ndarray, ...]:
    """(frame, class index, score, box) arrays over every detection, in frame order."""
    frame, cls, score, box = [], [], [], []
    for i, dets in enumerate(detections_per_frame):
        for d in dets:
            if d.label not in CLASS_INDEX:
                raise ValueError(
                    f"detection in frame {i} has label {d.label!r}, which is not one of the "
                    f"{len(CLASSES)} classes in tidee.agent.classes.CLASSES"
                )
            frame.append(i)
            cls.append(CLASS_INDEX[d.label])
            score.append(float(d.score))
            box.append(d.box)
    return (
        np.asarray(frame, np.int64),
        np.asarray(cls, np.int64),
        np.asarray(score, np.float64),
        np.asarray(box, np.float64).reshape(-1, 4),
    )


# ------------------------------------------------------------------------- box AP


def evaluate_boxes(
    detections_per_frame: Sequence[Sequence[Detection]],
    frames: Mapping[str, np.ndarray],
    iou_thresholds: Sequence[float] = COCO_IOUS,
) -> dict[str, Any]:
    """COCO-style box AP of detections against the GT rows of ``frames`` (a packed dict).

    Returns ``map50`` (mAP at IoU 0.5), ``map`` (mAP averaged over ``iou_thresholds``: the
    COCO mAP@[.5:.95] by default), ``per_class`` rows (class, n_gt, n_det, ap50, ap) sorted by
    GT count, and ``by_size`` ({small, medium, large}: n_gt, map50). Classes without GT are
    left out of the means (their detections are false positives of no consequence).
    """
    thresholds = [float(t) for t in iou_thresholds]
    if 0.5 not in thresholds:
        thresholds = [0.5] + thresholds
    i50 = thresholds.index(0.5)
    n = _num_frames(frames, detections_per_frame)
    det_frame, det_cls, det_score, det_box = _flatten(detections_per_frame)
    gt_frame = np.asarray(frames["obj_frame"], np.int64)
    gt_cls = np.asarray(frames["obj_cls"], np.int64)
    gt_box = np.asarray(frames["obj_box"], np.float64).reshape(-1, 4)
    settings: list[Setting] = [(t, None) for t in thresholds] + [(0.5, rng) for rng in SIZE_RANGES.values()]
    groups = _group_ap(det_frame, det_cls, det_score, det_box, gt_frame, gt_cls, gt_box, settings)
    range_idx = [i for i, t in enumerate(thresholds) if t in [float(x) for x in iou_thresholds]]
    per_class = []
    for c, r in groups.items():
        if r["n_gt"][i50] == 0:
            continue
        per_class.append(
            {
                "class": CLASSES[c],
                "n_gt": r["n_gt"][i50],
                "n_det": r["n_det"],
                "ap50": r["ap"][i50],
                "ap": float(np.mean([r["ap"][i] for i in range_idx])),
            }
        )
    per_class.sort(key=lambda row: (-row["n_gt"], row["class"]))
    by_size = {}
    for k, name in enumerate(SIZE_RANGES, start=len(thresholds)):
        by_size[name] = {
            "n_gt": sum(r["n_gt"][k] for r in groups.values()),
            "map50": _nanmean([r["ap"][k] for r in groups.values()]),
        }
    return {
        "iou_thresholds": [float(x) for x in iou_thresholds],
        "n_frames": n,
        "n_gt": len(gt_cls),
        "n_detections": len(det_cls),
        "n_classes": len(per_class),
        "map50": _nanmean([r["ap50"] for r in per_class]),
        "map": _nanmean([r["ap"] for r in per_class]),
        "per_class": per_class,
        "by_size": by_size,
    }


# ------------------------------------------------------------------------- OOP AP (Table 3)


def evaluate_oop(
    rows: Mapping[str, Sequence[Sequence[float]] | None],
    detections_per_frame: Sequence[Sequence[Detection]],
    frames: Mapping[str, np.ndarray],
    iou_thresholds: Sequence[float] = OOP_IOUS,
) -> dict[str, Any]:
    """In-place / out-of-place AP (paper Table 3) for each classifier row over the same detections.

    ``rows[name][i][k]`` is that classifier's P(out of place) for detection ``k`` of frame
    ``i`` (the visual row: each detection's ``oop_prob``); a row given as None is recorded as
    not built. GT and detections are restricted to pickupable classes. Each detection counts
    in "out-of-place" with confidence ``score * p`` and in "in-place" with ``score * (1 - p)``:
    the detector's confidence that there is an object, times the classifier's confidence in
    its category, so a detection the classifier is unsure about ranks low in both. Matching
    within a category is by IoU alone (class labels ignored).

    Returns {"rows": {name: {"built", "iou": {"0.25": {"map", "ap_in_place",
    "ap_out_of_place"}, ...}}}, "n_gt_in_place", "n_gt_out_of_place", "n_detections", ...}.
    """
    n = _num_frames(frames, detections_per_frame)
    keep = [[d.label in PICKUPABLE for d in dets] for dets in detections_per_frame]
    det_frame = np.asarray([i for i, ks in enumerate(keep) for k in ks if k], np.int64)
    det_score = np.asarray(
        [d.score for dets, ks in zip(detections_per_frame, keep) for d, k in zip(dets, ks) if k], np.float64
    )
    det_box = np.asarray(
        [d.box for dets, ks in zip(detections_per_frame, keep) for d, k in zip(dets, ks) if k], np.float64
    ).reshape(-1, 4)
    pickupable = np.asarray([CLASSES[c] in PICKUPABLE for c in np.asarray(frames["obj_cls"]).tolist()], bool)
    gt_frame = np.asarray(frames["obj_frame"], np.int64)[pickupable]
    gt_cat = np.asarray(frames["obj_oop"], np.int64)[pickupable]
    gt_box = np.asarray(frames["obj_box"], np.float64).reshape(-1, 4)[pickupable]
    m = len(det_frame)
    out_rows: dict[str, Any] = {}
    for name, probs in rows.items():
        if probs is None:
            out_rows[name] = {"built": False}
            continue
        if len(probs) != n or any(len(p) != len(d) for p, d in zip(probs, detections_per_frame)):
            raise ValueError(
                f"row {name!r} must give one P(out of place) per detection of each of the {n} frames"
            )
        p = np.asarray([float(x) for ps, ks in zip(probs, keep) for x, k in zip(ps, ks) if k], np.float64)
        if np.any(np.isnan(p)) or np.any((p < 0) | (p > 1)):
            raise ValueError(f"row {name!r} has P(out of place) outside [0, 1]")
        # Each detection twice: category 0 (in-place) and category 1 (out-of-place).
        res = _group_ap(
            np.concatenate([det_frame, det_frame]),
            np.repeat([0, 1], m),
            np.concatenate([det_score * (1 - p), det_score * p]),
            np.concatenate([det_box, det_box]),
            gt_frame,
            gt_cat,
            gt_box,
            [(float(t), None) for t in iou_thresholds],
        )
        iou: dict[str, dict[str, float]] = {}
        for t, thr in enumerate(iou_thresholds):
            ip = res[0]["ap"][t] if 0 in res else math.nan
            oop = res[1]["ap"][t] if 1 in res else math.nan
            iou[f"{thr:g}"] = {"map": _nanmean([ip, oop]), "ap_in_place": ip, "ap_out_of_place": oop}
        out_rows[name] = {"built": True, "iou": iou}
    return {
        "iou_thresholds": [float(t) for t in iou_thresholds],
        "n_frames": n,
        "n_detections": m,
        "n_gt_in_place": int((gt_cat == 0).sum()),
        "n_gt_out_of_place": int((gt_cat == 1).sum()),
        "rows": out_rows,
    }


def _pct(x: float | None) -> str:
    return "--" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.2f}"


def oop_table_markdown(result: Mapping[str, Any], paper: bool = True) -> str:
    """Table 3 as Markdown: our rows (every standard row, built or not), then the paper's."""
    thr = [f"{t:g}" for t in result["iou_thresholds"]]
    head = "| | " + " | ".join(f"mAP@{t} | AP@{t} IP | AP@{t} OOP" for t in thr) + " |"
    sep = "|---" * (1 + 3 * len(thr)) + "|"
    names = list(OOP_ROWS) + [r for r in result["rows"] if r not in OOP_ROWS]
    lines = [head, sep]
    for name in names:
        row = result["rows"].get(name, {"built": False})
        if not row["built"]:
            lines.append(f"| {name} | {NOT_BUILT} |" + " |" * (3 * len(thr) - 1))
            continue
        cells = [_pct(row["iou"][t][k]) for t in thr for k in ("map", "ap_in_place", "ap_out_of_place")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if paper:
        lines += [
            "",
            "**paper (AI2THOR)**: Table 3 of Sarch et al., ECCV 2022 (their names: dDETR-OOP, BERT-OOP, "
            "dDETR+BERT-OOP, oracle-BERT-OOP), the paper's models on AI2THOR test rooms, not this "
            "simulator: for scale only.",
            "",
            "| paper (AI2THOR) | mAP@0.25 | AP@0.25 IP | AP@0.25 OOP | mAP@0.5 | AP@0.5 IP | AP@0.5 OOP |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, vals in PAPER_TABLE3.items():
            lines.append(f"| {name} | " + " | ".join("--" if v is None else f"{v:.2f}" for v in vals) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------- frames


def _config_counts(frames: Mapping[str, np.ndarray]) -> dict[str, int]:
    names, counts = np.unique(np.asarray(frames["frame_room"]), return_counts=True)
    return {str(k): int(v) for k, v in zip(names, counts)}


# ------------------------------------------------------------------------- running a detector


def _detect_all(
    detector: FrameDetector, frames: Mapping[str, np.ndarray], batch: int, progress: bool
) -> tuple[list[list[Detection]], dict[str, float]]:
    """Detections for every frame, and the time ``detect_batch`` took (on one torch thread)."""
    from tqdm import tqdm

    torch = sys.modules.get("torch")  # a torch detector has imported it; others need not
    threads = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(1)
    rgb, depth = frames["rgb"], frames["depth"]
    out: list[list[Detection]] = []
    per_frame_ms: list[float] = []  # per batch
    total_s = 0.0
    try:
        for s in tqdm(range(0, len(rgb), batch), desc=f"{detector.name} detect", disable=not progress):
            r = np.ascontiguousarray(rgb[s : s + batch])
            d = np.asarray(depth[s : s + batch], np.float32)
            t0 = time.perf_counter()
            dets = detector.detect_batch(r, d)
            dt = time.perf_counter() - t0
            total_s += dt
            if len(dets) != len(r):
                raise ValueError(
                    f"{detector.name}.detect_batch returned {len(dets)} lists for {len(r)} frames"
                )
            out += [list(x) for x in dets]
            per_frame_ms.append(1000 * dt / len(r))
    finally:
        if torch is not None:
            torch.set_num_threads(threads)
    timing = {
        "batch": batch,
        "threads": 1,
        "ms_per_frame_median": float(np.median(per_frame_ms)),
        "ms_per_frame_mean": 1000 * total_s / len(rgb),
        "frames": len(rgb),
    }
    return out, timing


def _detector_info(detector: FrameDetector) -> dict[str, Any]:
    """Name and, where the detector exposes them, its weights path and manifest sha256."""
    info: dict[str, Any] = {"name": getattr(detector, "name", type(detector).__name__)}
    manifest = getattr(detector, "manifest", None)
    sha = getattr(detector, "manifest_sha256", None) or getattr(detector, "sha256", None)
    if sha is None and isinstance(manifest, Mapping):
        sha = manifest.get("sha256")
    info["sha256"] = sha
    path = getattr(detector, "path", None) or getattr(detector, "weights_path", None)
    info["weights"] = str(path) if path is not None else None
    rc = getattr(detector, "reclassifier_manifest", None)
    if getattr(detector, "reclassifier", None) is not None and isinstance(rc, Mapping):
        info["reclassifier"] = {
            "weights": rc.get("path"),
            "sha256": rc.get("sha256"),
            "alpha": getattr(detector, "alpha", None),
            "beta": getattr(detector, "beta", None),
        }
    return info


def _label(img: np.ndarray, text: str, x: int, y: int, fs: float, color: tuple[int, int, int]) -> None:
    """Black text on a filled box whose bottom-left is near (x, y), kept inside the image."""
    import cv2

    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)
    x = int(min(max(x, 0), img.shape[1] - tw - 2))
    y = int(min(max(y, th + 3), img.shape[0]))
    cv2.rectangle(img, (x, y - th - 4), (x + tw + 2, y), color, -1)
    cv2.putText(img, text, (x + 1, y - 3), cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 0, 0), 1, cv2.LINE_AA)


def save_detection_examples(
    frames: Mapping[str, np.ndarray],
    detections_per_frame: Sequence[Sequence[Detection]],
    png: str | Path,
    n: int = 8,
    min_score: float = 0.3,
    cols: int = 4,
    scale: int = 2,
) -> list[int]:
    """A grid of ``n`` frames (spread evenly over ``frames``) with GT and predicted boxes.

    GT boxes: thin green (an out-of-place GT is tagged "oop"). Predictions with score >=
    ``min_score``: label and score, red when ``oop_prob`` > 0.5, else yellow. Frames are
    upscaled ``scale`` x so that the labels can be read. Returns the frame indices shown.
    """
    import cv2

    total = len(frames["rgb"])
    idx = sorted({round(i) for i in np.linspace(0, total - 1, min(n, total))})
    tiles = []
    for i in idx:
        img = cv2.cvtColor(np.asarray(frames["rgb"][i]), cv2.COLOR_RGB2BGR)
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        fs = 0.21 * img.shape[0] / 256  # font scale: 0.42 on a 512-pixel tile
        rows = np.nonzero(np.asarray(frames["obj_frame"]) == i)[0]
        for r in rows:
            x0, y0, x1, y1 = (np.asarray(frames["obj_box"][r]) * scale).astype(int)
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (0, 200, 0), 1)
            if frames["obj_oop"][r]:
                cv2.putText(
                    img, "oop", (x0 + 2, y1 - 4), cv2.FONT_HERSHEY_SIMPLEX, fs, (0, 200, 0), 1, cv2.LINE_AA
                )
        for d in sorted(detections_per_frame[i], key=lambda d: d.score):
            if d.score < min_score:
                continue
            x0, y0, x1, y1 = (np.asarray(d.box) * scale).astype(int)
            color = (0, 0, 255) if d.oop_prob is not None and d.oop_prob > 0.5 else (0, 220, 255)
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), color, 2)
            text = f"{d.label} {d.score:.2f}"
            _label(img, text, x0, y0, fs, color)
        room = str(frames["frame_room"][i]).replace(":None", ":tidy") if "frame_room" in frames else ""
        _label(img, f"#{i} {room}", 0, img.shape[0], fs * 1.2, (255, 255, 255))
        tiles.append(cv2.copyMakeBorder(img, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=(255, 255, 255)))
    cols = min(cols, len(tiles))
    blank = np.zeros_like(tiles[0])
    tiles += [blank] * (-len(tiles) % cols)
    grid = np.vstack([np.hstack(tiles[r : r + cols]) for r in range(0, len(tiles), cols)])
    ok, buf = cv2.imencode(".png", grid)
    if not ok:
        raise RuntimeError(f"could not encode {png}")
    write_atomic(png, buf.tobytes())
    return idx


def _frames_summary(frames: Mapping[str, np.ndarray]) -> dict[str, Any]:
    counts = _config_counts(frames)
    return {
        "frames": len(frames["rgb"]),
        "configurations": len(counts),
        "rooms": sorted({":".join(k.split(":")[:2]) for k in counts}),
        "frames_per_configuration": counts,
    }


@contextmanager
def _decoding(detector: FrameDetector, **settings: Any) -> Iterator[None]:
    """Switch the detector's decoding attributes (``peaks``, ``classes_per_peak``) for one pass,
    then put its own back."""
    own = {k: getattr(detector, k) for k in settings}
    try:
        for k, v in settings.items():
            setattr(detector, k, v)
        yield
    finally:
        for k, v in own.items():
            setattr(detector, k, v)


def run_detector_eval(
    detector: FrameDetector,
    out_dir: str | Path,
    rooms_per_type: int = 5,
    messes: int = 2,
    frames_per_walk: int = 5,
    walks: int = 1,
    seed: int = 7,
    batch: int = 16,
    split: str = "test",
    renderer: str = TRAINED_RENDERER,
    progress: bool = True,
    classes_per_peak: int = SECOND_GUESSES,
    peaks: str = "class-max",
) -> dict[str, Any]:
    """Box AP of ``detector`` on held-out frames; writes detector.json, detector.md, detector_examples.png.

    The headline is the detector as the agent runs it. Where the detector can offer several
    classes per heatmap peak (``classes_per_peak`` attribute) and ``classes_per_peak`` > 1, the
    report adds box AP with its ``classes_per_peak`` best classes per peak (``multiclass``).
    ``peaks`` other than "class-max" (the agent's) evaluates another decoding (``detector.decode``),
    without the multiclass pass."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames = held_out_frames(
        split,
        rooms_per_type=rooms_per_type,
        messes=messes,
        walks=walks,
        frames_per_walk=frames_per_walk,
        seed=seed,
        renderer=renderer,
        progress=progress,
    )
    if peaks != "class-max" and not hasattr(detector, "peaks"):
        raise ValueError(f"peaks={peaks!r}: {detector.name} has no heatmap peaks to decode another way")
    with _decoding(detector, **({"peaks": peaks} if hasattr(detector, "peaks") else {})):
        dets, timing = _detect_all(detector, frames, batch, progress)
        # the agent's case: its score threshold (fewer detections to box, mask and reclassify than the eval's)
        with _decoding(
            detector, **({"threshold": AGENT_THRESHOLD} if hasattr(detector, "threshold") else {})
        ):
            timing.update(_single_frame_latency(detector, frames))
        timing.update({f"{k}_eval_threshold": v for k, v in _single_frame_latency(detector, frames).items()})
        timing["agent_threshold"] = AGENT_THRESHOLD if hasattr(detector, "threshold") else None
    metrics = evaluate_boxes(dets, frames)
    # second guesses are the detector's runner-up classes: a crop reclassifier renames them all alike
    second_guesses = (
        peaks == "class-max"
        and classes_per_peak > 1
        and hasattr(detector, "classes_per_peak")
        and getattr(detector, "reclassifier", None) is None
    )
    if second_guesses:
        with _decoding(detector, classes_per_peak=classes_per_peak):
            multi, _ = _detect_all(detector, frames, batch, progress)
        mm = evaluate_boxes(multi, frames)
        metrics["multiclass"] = {
            "classes_per_peak": classes_per_peak,
            "map50": mm["map50"],
            "map": mm["map"],
            "n_detections": mm["n_detections"],
            "by_size": {k: v["map50"] for k, v in mm["by_size"].items()},
        }
    command = (
        f"tidee eval detector --split {split} --rooms-per-type {rooms_per_type} --messes {messes} "
        f"--walks {walks} --frames-per-walk {frames_per_walk} --seed {seed}"
        + (
            f" --classes-per-peak {classes_per_peak}"
            if peaks == "class-max" and classes_per_peak != SECOND_GUESSES
            else ""
        )
        + (f" --peaks {peaks}" if peaks != "class-max" else "")
        + (f" --renderer {renderer}" if renderer != TRAINED_RENDERER else "")
        + _reclassifier_flag(detector)
        + f" --out {out}"
    )
    report = {
        "command": command,
        "detector": _detector_info(detector),
        "peaks": peaks,
        "timing": timing,
        "data": {
            "split": split,
            "renderer": renderer,
            "rooms_per_type": rooms_per_type,
            "messes_per_room": messes,
            "tidy": True,
            "walks": walks,
            "frames_per_walk": frames_per_walk,
            "seed": seed,
            **_frames_summary(frames),
        },
        **metrics,
    }
    save_detection_examples(frames, dets, out / "detector_examples.png")
    write_json_atomic(out / "detector.json", report)
    write_atomic(out / "detector.md", _detector_markdown(report).encode())
    return report


FUSION_ALPHAS = (0.0, 1.0, 2.0, 3.0, 4.0)
FUSION_BETAS = (0.0, 0.25, 0.5, 1.0)


def run_fusion_sweep(
    detector: FrameDetector,
    out_dir: str | Path,
    split: str = "val",
    rooms_per_type: int = 5,
    messes: int = 2,
    frames_per_walk: int = 5,
    walks: int = 1,
    seed: int = 7,
    batch: int = 16,
    alphas: Sequence[float] = FUSION_ALPHAS,
    betas: Sequence[float] = FUSION_BETAS,
    progress: bool = True,
) -> dict[str, Any]:
    """Box mAP of the detector alone and of every (alpha, beta) fusion with its crop reclassifier
    (``reclassifier.fuse``) on the same held-out frames; writes fusion.json and fusion.md. The
    weights are chosen on the validation rooms (``tidee eval reclassifier --record``)."""
    if getattr(detector, "reclassifier", None) is None:
        raise ValueError("the fusion sweep needs a detector with a crop reclassifier")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames = held_out_frames(
        split,
        rooms_per_type=rooms_per_type,
        messes=messes,
        walks=walks,
        frames_per_walk=frames_per_walk,
        seed=seed,
        progress=progress,
    )
    rc, a0, b0 = detector.reclassifier, detector.alpha, detector.beta  # type: ignore[attr-defined]
    rows: list[dict[str, Any]] = []
    try:
        detector.reclassifier = None  # type: ignore[attr-defined]
        dets, _ = _detect_all(detector, frames, batch, False)
        m = evaluate_boxes(dets, frames)
        rows.append(
            {
                "alpha": None,
                "beta": None,
                "map50": m["map50"],
                "map": m["map"],
                "n_detections": m["n_detections"],
                "by_size": {k: v["map50"] for k, v in m["by_size"].items()},
            }
        )
        detector.reclassifier = rc  # type: ignore[attr-defined]
        for a in alphas:
            for b in betas:
                detector.alpha, detector.beta = float(a), float(b)  # type: ignore[attr-defined]
                dets, _ = _detect_all(detector, frames, batch, False)
                m = evaluate_boxes(dets, frames)
                rows.append(
                    {
                        "alpha": float(a),
                        "beta": float(b),
                        "map50": m["map50"],
                        "map": m["map"],
                        "n_detections": m["n_detections"],
                        "by_size": {k: v["map50"] for k, v in m["by_size"].items()},
                    }
                )
                if progress:
                    print(f"alpha {a} beta {b}: mAP@0.5 {100 * m['map50']:.1f}", flush=True)
    finally:
        detector.reclassifier, detector.alpha, detector.beta = rc, a0, b0  # type: ignore[attr-defined]
    best = max(rows[1:], key=lambda r: r["map50"])
    command = (
        f"tidee eval reclassifier --split {split} --rooms-per-type {rooms_per_type} --messes {messes} "
        f"--walks {walks} --frames-per-walk {frames_per_walk} --seed {seed}"
        + (
            ""
            if (tuple(alphas), tuple(betas)) == (FUSION_ALPHAS, FUSION_BETAS)
            else f" --alphas {','.join(f'{a:g}' for a in alphas)} --betas {','.join(f'{b:g}' for b in betas)}"
        )
        + _reclassifier_flag(detector)
        + f" --out {out}"
    )
    report = {
        "command": command,
        "detector": _detector_info(detector),
        "rows": rows,
        "best": best,
        "data": {
            "split": split,
            "rooms_per_type": rooms_per_type,
            "messes_per_room": messes,
            "walks": walks,
            "frames_per_walk": frames_per_walk,
            "seed": seed,
            **_frames_summary(frames),
        },
    }
    lines = [
        f"# Crop reclassifier: fusion with the detector's classes ({split} rooms)",
        "",
        f"`{command}`",
        "",
        _detector_line(report["detector"]),
        f"- frames: {report['data']['frames']} of {split} rooms",
        "",
        "class = argmax log p_crop + alpha log sigmoid(heat); score = peak score x p_crop(class)^beta",
        "",
        "| alpha | beta | mAP@0.5 | mAP@[.5:.95] | small | medium | large | detections |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        sz = r["by_size"]
        name = ("detector alone", "") if r["alpha"] is None else (f"{r['alpha']:g}", f"{r['beta']:g}")
        star = " **(best)**" if r is best else ""
        lines.append(
            f"| {name[0]} | {name[1]} | {_pct(r['map50'])}{star} | {_pct(r['map'])} | {_pct(sz['small'])} | "
            f"{_pct(sz['medium'])} | {_pct(sz['large'])} | {r['n_detections']} |"
        )
    write_json_atomic(out / "fusion.json", report)
    write_atomic(out / "fusion.md", ("\n".join(lines) + "\n").encode())
    return report


def _cmd_eval_reclassifier(args: Any) -> int:
    if args.record and args.split != "val":
        raise SystemExit(
            "tidee eval reclassifier: --record chooses the fusion weights on the validation rooms; "
            "use --split val (the test rooms stay for the final figures)"
        )
    det = _load_detector(args.weights, args.reclassifier)
    try:
        alphas = [float(x) for x in args.alphas.split(",")]
        betas = [float(x) for x in args.betas.split(",")]
    except ValueError:
        raise SystemExit(
            f"--alphas / --betas want comma-separated numbers, not {args.alphas!r} / {args.betas!r}"
        ) from None
    r = run_fusion_sweep(
        det,
        args.out,
        split=args.split,
        rooms_per_type=args.rooms_per_type,
        messes=args.messes,
        frames_per_walk=args.frames_per_walk,
        walks=args.walks,
        seed=args.seed,
        batch=args.batch,
        alphas=alphas,
        betas=betas,
    )
    if args.record:
        b = r["best"]
        _record_in_manifest(
            det,
            {
                "fusion": {
                    "alpha": b["alpha"],
                    "beta": b["beta"],
                    "val_map50": b["map50"],
                    "val_map50_detector_alone": r["rows"][0]["map50"],
                    "command": r["command"],
                }
            },
        )
    print((Path(args.out) / "fusion.md").read_text())
    return 0


def _reclassifier_flag(detector: FrameDetector) -> str:
    """The ``--reclassifier`` option that reloads ``detector``'s second stage ("" for the default)."""
    from tidee.agent.perception.reclassifier import DEFAULT_RECLASSIFIER

    if not hasattr(detector, "reclassifier"):
        return ""
    rc = _detector_info(detector).get("reclassifier")
    if rc is None:
        return " --reclassifier none" if DEFAULT_RECLASSIFIER.exists() else ""
    return (
        ""
        if Path(rc["weights"]).resolve() == DEFAULT_RECLASSIFIER.resolve()
        else f" --reclassifier {rc['weights']}"
    )


def _single_frame_latency(
    detector: FrameDetector, frames: Mapping[str, np.ndarray], n: int = 60
) -> dict[str, float]:
    """What the agent pays: one frame at a time, one torch thread (the 30 ms target), after a warm-up."""
    torch = sys.modules.get("torch")
    threads = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(1)
    try:
        times = []
        for i in range(min(n, len(frames["rgb"])) + 3):
            r = np.ascontiguousarray(frames["rgb"][i % len(frames["rgb"])][None])
            d = np.asarray(frames["depth"][i % len(frames["rgb"])][None], np.float32)
            t0 = time.perf_counter()
            detector.detect_batch(r, d)
            if i >= 3:
                times.append(1000 * (time.perf_counter() - t0))
    finally:
        if torch is not None:
            torch.set_num_threads(threads)
    return {
        "single_frame_ms_median": float(np.median(times)),
        "single_frame_ms_p90": float(np.percentile(times, 90)),
    }


def _detector_line(det: Mapping[str, Any]) -> str:
    rc = det.get("reclassifier")
    return (
        f"- detector: **{det['name']}**"
        + (f", weights `{det['weights']}`" if det.get("weights") else "")
        + (
            f", manifest sha256 `{det['sha256']}`"
            if det.get("sha256")
            else ", manifest sha256: not available"
        )
        + (
            f"; classes from the crop reclassifier `{rc['weights']}` (sha256 `{rc['sha256']}`, alpha {rc['alpha']}, "
            f"beta {rc['beta']})"
            if rc
            else "; classes from the detector alone"
        )
    )


def _detector_markdown(r: Mapping[str, Any]) -> str:
    det, data, t = r["detector"], r["data"], r["timing"]
    lines = [
        f"# Detector evaluation: {det['name']}",
        "",
        f"`{r['command']}`",
        "",
        _detector_line(det),
        f"- frames: {data['frames']} from {data['configurations']} configurations of {len(data['rooms'])} "
        f"{data['split']} rooms ({data['rooms_per_type']} per type; the tidy room + {data['messes_per_room']} "
        f"messes each; {data['walks']} random walk(s) x up to {data['frames_per_walk']} frames; seed "
        f"{data['seed']})",
        f"- rooms: {', '.join(data['rooms'])}",
        f"- `detect_batch` time: {t['ms_per_frame_median']:.1f} ms/frame median ({t['ms_per_frame_mean']:.1f} mean), "
        f"batch {t['batch']}, 1 torch thread",
        f"- one frame at a time (the agent's case), 1 torch thread: {t['single_frame_ms_median']:.1f} ms median, "
        f"{t['single_frame_ms_p90']:.1f} ms p90 (target <= 30 ms), including box decoding and depth masks"
        + (
            f", at the agent's score threshold {t['agent_threshold']}; at the evaluation's {EVAL_THRESHOLD} "
            f"(more detections): {t['single_frame_ms_median_eval_threshold']:.1f} ms median, "
            f"{t['single_frame_ms_p90_eval_threshold']:.1f} ms p90"
            if t.get("agent_threshold") is not None
            else ""
        ),
        "",
        "| metric | value |",
        "|---|---|",
        f"| mAP@0.5 | {_pct(r['map50'])} |",
        f"| mAP@[.5:.95] | {_pct(r['map'])} |",
    ]
    if r.get("peaks", "class-max") != "class-max":
        lines.insert(
            4, f"- decoding: `--peaks {r['peaks']}` (an ablation; the agent decodes class-max peaks)"
        )
    mc = r.get("multiclass")
    if mc:
        lines += [
            f"| mAP@0.5, {mc['classes_per_peak']} best classes per peak | {_pct(mc['map50'])} |",
            f"| mAP@[.5:.95], {mc['classes_per_peak']} best classes per peak | {_pct(mc['map'])} |",
        ]
    for name, s in r["by_size"].items():
        lo, hi = SIZE_RANGES[name]
        span = (
            f"< {int(math.sqrt(hi))}²"
            if lo == 0
            else (
                f">= {int(math.sqrt(lo))}²"
                if math.isinf(hi)
                else f"{int(math.sqrt(lo))}²-{int(math.sqrt(hi))}²"
            )
        )
        lines.append(f"| mAP@0.5 {name} ({span} px, {s['n_gt']} GT) | {_pct(s['map50'])} |")
    if mc:
        lines += [
            "",
            f"The first rows decode as the agent does: one class per heatmap peak. The "
            f"'{mc['classes_per_peak']} best classes per peak' rows also keep each peak's runner-up classes "
            f"as detections with their own scores ({mc['n_detections']} detections), as a COCO-style "
            "evaluation of CenterNet (top 100 over classes and cells) does; the agent does not use them.",
        ]
    lines += [
        "",
        f"AP in %, over the {r['n_classes']} classes with at least one GT object "
        f"({r['n_gt']} GT objects, {r['n_detections']} detections); sorted by GT count.",
        "",
        "| class | GT | detections | AP@0.5 | AP@[.5:.95] |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {c['class']} | {c['n_gt']} | {c['n_det']} | {_pct(c['ap50'])} | {_pct(c['ap'])} |"
        for c in r["per_class"]
    ]
    lines += [
        "",
        "![examples](detector_examples.png)",
        "",
        "Examples: GT thin green; predictions with score >= 0.3 labelled, red when P(out of place) > 0.5.",
        "",
    ]
    return "\n".join(lines)


def run_oop_eval(
    detector: FrameDetector,
    out_dir: str | Path,
    views_per_config: int = 20,
    messes: int = 5,
    rooms_per_type: int = 5,
    seed: int = 11,
    extra_rows: Mapping[str, OopRowFn | None] | None = None,
    split: str = "test",
    frames_per_walk: int = 5,
    walks: int | None = None,
    batch: int = 16,
    progress: bool = True,
) -> dict[str, Any]:
    """Table 3: in/out-of-place AP on views of the messy held-out configurations.

    Views: frames of each messy configuration with at least one out-of-place object in view,
    the first ``views_per_config`` of ``walks`` random walks (default: enough walks for twice
    as many, since not every walk finds that many); fewer where the walks do not find enough,
    and the report says how many each configuration got. The visual row is the detector's
    ``oop_prob``; ``extra_rows`` maps a row name (e.g. "BERT-OOP (language)") to a function of
    (frames, detections) giving P(out of place) per detection. Standard rows without a
    classifier are reported as not built. Writes oop.json, oop.md and oop_examples.png.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if walks is None:
        walks = 2 * math.ceil(views_per_config / frames_per_walk)
    if walks * frames_per_walk < views_per_config:
        raise ValueError(
            f"{walks} walks x {frames_per_walk} frames cannot give {views_per_config} views per "
            "configuration; raise --walks or --frames-per-walk"
        )
    frames = held_out_frames(
        split,
        rooms_per_type=rooms_per_type,
        messes=messes,
        walks=walks,
        frames_per_walk=frames_per_walk,
        seed=seed,
        oop_views_only=True,
        tidy=False,
        per_config=views_per_config,
        progress=progress,
    )
    dets, timing = _detect_all(detector, frames, batch, progress)
    missing = [(i, d.label) for i, ds in enumerate(dets) for d in ds if d.oop_prob is None]
    if missing:
        raise ValueError(
            f"{detector.name} gave detections without oop_prob (e.g. frame {missing[0][0]}, "
            f"{missing[0][1]}); the OOP evaluation needs a detector with an OOP head"
        )
    rows: dict[str, list[list[float]] | None] = {name: None for name in OOP_ROWS}
    rows[VISUAL_ROW] = [[float(d.oop_prob) for d in ds] for ds in dets]
    for name, fn in (extra_rows or {}).items():
        rows[name] = None if fn is None else fn(frames, dets)
    metrics = evaluate_oop(rows, dets, frames)
    counts = _config_counts(frames)
    expected = len(ROOM_TYPES) * rooms_per_type * messes
    command = (
        f"tidee eval oop --split {split} --views {views_per_config} --rooms-per-type {rooms_per_type} "
        f"--messes {messes} --walks {walks} --seed {seed}{'' if extra_rows else ' --visual-only'}"
        f"{_reclassifier_flag(detector)} --out {out}"
    )
    report = {
        "command": command,
        "detector": _detector_info(detector),
        "timing": timing,
        "data": {
            "split": split,
            "rooms_per_type": rooms_per_type,
            "messes_per_room": messes,
            "views_per_config_target": views_per_config,
            "walks": walks,
            "frames_per_walk": frames_per_walk,
            "seed": seed,
            "configurations_expected": expected,
            "configurations_with_views": len(counts),
            "views_min": min(counts.values()),
            "views_mean": float(np.mean(list(counts.values()))),
            "views_max": max(counts.values()),
            "configurations_short": sum(v < views_per_config for v in counts.values())
            + expected
            - len(counts),
            **_frames_summary(frames),
        },
        "paper_ai2thor": {k: list(v) for k, v in PAPER_TABLE3.items()},
        **metrics,
    }
    save_detection_examples(frames, dets, out / "oop_examples.png")
    write_json_atomic(out / "oop.json", report)
    write_atomic(out / "oop.md", _oop_markdown(report).encode())
    return report


def _oop_markdown(r: Mapping[str, Any]) -> str:
    det, data = r["detector"], r["data"]
    short = data["configurations_short"]
    return "\n".join(
        [
            f"# Out-of-place detection (paper Table 3): {det['name']}",
            "",
            f"`{r['command']}`",
            "",
            _detector_line(det),
            f"- views: {data['frames']} frames with at least one out-of-place object in view, from "
            f"{data['configurations_with_views']} of {data['configurations_expected']} messy {data['split']} "
            f"configurations ({data['rooms_per_type']} rooms per type x {data['messes_per_room']} messes); target "
            f"{data['views_per_config_target']} per configuration, got {data['views_min']}-{data['views_max']} "
            f"(mean {data['views_mean']:.1f}; {short} configuration(s) short of the target) from "
            f"{data['walks']} walks x up to {data['frames_per_walk']} frames, seed {data['seed']}",
            f"- pickupable GT objects in view: {r['n_gt_in_place']} in place, {r['n_gt_out_of_place']} out of place; "
            f"{r['n_detections']} detections of pickupable classes",
            "- a detection scores score x P(oop) as out-of-place and score x (1 - P(oop)) as in-place; it matches "
            "a GT box of that category by IoU, whatever the class. AP in %.",
            "",
            oop_table_markdown(r),
            "",
            "![examples](oop_examples.png)",
            "",
            'Examples: GT thin green ("oop": out of place); predictions with score >= 0.3, red when P(oop) > 0.5.',
            "",
        ]
    )


# ------------------------------------------------------------------------- command line


def _eval_split(value: str) -> str:
    if value not in ("test", "val"):
        raise argparse.ArgumentTypeError(
            f"{value!r}: the detector is evaluated on held-out rooms only; use --split test (or val)"
        )
    return value


EVAL_THRESHOLD = 0.05  # AP integrates over the whole precision/recall curve: keep low-score detections


def _load_detector(weights: str | None, reclassifier: str | None = "default") -> FrameDetector:
    """The learned detector at the evaluation threshold; ``reclassifier``: "default" (the shipped
    crop classifier when it is there), "none", or a path."""
    from tidee.agent.perception.learned import LearnedPerception

    return LearnedPerception.load(
        weights, threshold=EVAL_THRESHOLD, reclassifier=None if reclassifier == "none" else reclassifier
    )


def _record_in_manifest(detector: FrameDetector, metrics: dict[str, Any]) -> None:
    """Merge held-out metrics into the evaluated weights' manifest (the weights are unchanged):
    the crop reclassifier's when it renamed the detections, else the detector's."""
    from tidee.agent.learning import update_manifest_metrics

    rc = _detector_info(detector).get("reclassifier")
    path = Path(rc["weights"]) if rc else Path(detector.path)  # type: ignore[attr-defined]
    update_manifest_metrics(path, metrics)
    print(f"recorded in {path.with_suffix('.json')}: {sorted(metrics)}")


def _cmd_eval_detector(args: Any) -> int:
    if args.record and args.renderer != TRAINED_RENDERER:
        raise SystemExit(
            f"tidee eval detector: --record keeps the manifest's figures on {TRAINED_RENDERER} frames, "
            f"the detector's own; drop --record with --renderer {args.renderer}"
        )
    if args.record and args.peaks != "class-max":
        raise SystemExit(
            f"tidee eval detector: --record keeps the manifest's figures for the agent's decoding "
            f"(class-max); drop --record with --peaks {args.peaks}"
        )
    det = _load_detector(args.weights, args.reclassifier)
    r = run_detector_eval(
        det,
        args.out,
        rooms_per_type=args.rooms_per_type,
        messes=args.messes,
        frames_per_walk=args.frames_per_walk,
        walks=args.walks,
        seed=args.seed,
        batch=args.batch,
        split=args.split,
        renderer=args.renderer,
        classes_per_peak=args.classes_per_peak,
        peaks=args.peaks,
    )
    if args.record:
        mc = r.get("multiclass")
        _record_in_manifest(
            det,
            {
                "box_map50": r["map50"],
                "box_map50_95": r["map"],
                **(
                    {"box_map50_multiclass": mc["map50"], "classes_per_peak": mc["classes_per_peak"]}
                    if mc
                    else {}
                ),
                "box_eval": {
                    "command": r["command"],
                    "frames": r["data"]["frames"],
                    "single_frame_ms_median": r["timing"]["single_frame_ms_median"],
                },
            },
        )
    print((Path(args.out) / "detector.md").read_text())
    return 0


CEILING_ROW = "Oracle-label (ceiling)"


def matched_oop_labels(
    frames: Mapping[str, np.ndarray], dets: list[list[Detection]], iou_threshold: float = 0.5
) -> list[dict[int, int]]:
    """Per frame, {detection index: out-of-place label of the ground-truth instance it
    matches}: pickupable detections against pickupable instances, IoU >= ``iou_threshold``,
    class-agnostic and greedy by score, as the Table 3 AP matches them."""
    pick = np.asarray([CLASSES[c] in PICKUPABLE for c in np.asarray(frames["obj_cls"]).tolist()], bool)
    obj_frame = np.asarray(frames["obj_frame"])
    out: list[dict[int, int]] = []
    for i, ds in enumerate(dets):
        ks = [k for k, d in enumerate(ds) if d.label in PICKUPABLE]  # the detections the AP counts
        gt = np.flatnonzero((obj_frame == i) & pick)
        labels: dict[int, int] = {}
        if ks and len(gt):
            match = match_detections(
                np.asarray([ds[k].box for k in ks], np.float64),
                np.asarray([ds[k].score for k in ks], np.float64),
                np.asarray(frames["obj_box"])[gt],
                iou_threshold,
            )
            labels = {k: int(frames["obj_oop"][gt[g]]) for k, g in zip(ks, match.tolist()) if g >= 0}
        out.append(labels)
    return out


def oracle_label_row(
    frames: Mapping[str, np.ndarray], dets: list[list[Detection]], iou_threshold: float = 0.5
) -> list[list[float]]:
    """ORACLE, the ceiling of any classifier over these detections: P(out of place) is the
    ground truth of the instance a detection matches (:func:`matched_oop_labels`), 0.5 for a
    detection that matches none. What is left below 100 is the detector's: missed and
    misplaced boxes."""
    return [
        [float(labels.get(k, 0.5)) for k in range(len(ds))]
        for ds, labels in zip(dets, matched_oop_labels(frames, dets, iou_threshold))
    ]


def _language_rows() -> dict[str, OopRowFn | None]:
    """The language, fused and oracle-language rows, from the shipped language heads."""
    from tidee.agent.reasoning.language_oop import (
        DEFAULT_FUSED_WEIGHTS,
        LanguageOOPClassifier,
        language_row,
        oracle_language_row,
    )

    clf = LanguageOOPClassifier.load()
    fused = LanguageOOPClassifier.load(DEFAULT_FUSED_WEIGHTS, encoder=clf.encoder)
    return {
        "BERT-OOP (language)": language_row(clf),
        "dDETR+BERT-OOP (fused)": language_row(fused),
        "Oracle-language": oracle_language_row(clf),
        CEILING_ROW: oracle_label_row,
    }


def _cmd_eval_oop(args: Any) -> int:
    det = _load_detector(args.weights, args.reclassifier)
    r = run_oop_eval(
        det,
        args.out,
        views_per_config=args.views,
        messes=args.messes,
        rooms_per_type=args.rooms_per_type,
        seed=args.seed,
        split=args.split,
        walks=args.walks,
        batch=args.batch,
        extra_rows=None if args.visual_only else _language_rows(),
    )
    if args.record:
        _record_in_manifest(det, {"oop_visual": r["rows"][VISUAL_ROW], "oop_eval_command": r["command"]})
    print((Path(args.out) / "oop.md").read_text())
    return 0


RECLASSIFIER_HELP = (
    "the crop classifier that renames detections: default (the shipped one when it is there), "
    "none (the detector's own classes), or a weights path"
)


def register(eval_sub: Any) -> None:
    """Add ``detector`` and ``oop`` to the ``tidee eval`` subcommands (an argparse subparsers group)."""
    p = eval_sub.add_parser("detector", help="box AP of the learned detector on held-out rooms")
    p.add_argument("--split", type=_eval_split, default="test", help="test (default) or val")
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default=None, help="detector weights (default: the installed ones)")
    p.add_argument("--rooms-per-type", type=int, default=5)
    p.add_argument("--messes", type=int, default=2, help="messy configurations per room (plus the tidy one)")
    p.add_argument("--walks", type=int, default=1, help="random walks per configuration")
    p.add_argument("--frames-per-walk", type=int, default=5, help="frames kept per walk")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--record", action="store_true", help="merge the metrics into the weights' manifest")
    p.add_argument(
        "--classes-per-peak",
        type=int,
        default=SECOND_GUESSES,
        help="also report mAP with this many best classes per heatmap peak (1: skip)",
    )
    p.add_argument(
        "--renderer",
        choices=("auto", "egl", "tiny"),
        default=TRAINED_RENDERER,
        help=f"who draws the test frames (default {TRAINED_RENDERER}: what the detector was trained on)",
    )
    p.add_argument(
        "--peaks",
        choices=PEAK_MODES,
        default="class-max",
        help="how heatmap peaks become detections (default class-max: the agent's; the others are "
        "an ablation, see detector.decode)",
    )
    p.add_argument("--reclassifier", default="default", help=RECLASSIFIER_HELP)
    p.set_defaults(func=_cmd_eval_detector)

    p = eval_sub.add_parser(
        "reclassifier",
        help="box AP of the detector alone and fused with its crop reclassifier "
        "(alpha x beta), to choose the fusion on the validation rooms",
    )
    p.add_argument(
        "--split", type=_eval_split, default="val", help="val (default: where the fusion is chosen) or test"
    )
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default=None, help="detector weights (default: the installed ones)")
    p.add_argument("--reclassifier", default="default", help=RECLASSIFIER_HELP)
    p.add_argument("--rooms-per-type", type=int, default=5)
    p.add_argument("--messes", type=int, default=2)
    p.add_argument("--walks", type=int, default=1)
    p.add_argument("--frames-per-walk", type=int, default=5)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument(
        "--alphas",
        default=",".join(f"{a:g}" for a in FUSION_ALPHAS),
        help="weights of the detector's class scores to try (comma-separated)",
    )
    p.add_argument(
        "--betas",
        default=",".join(f"{b:g}" for b in FUSION_BETAS),
        help="exponents of the crop's class probability in the score to try (comma-separated)",
    )
    p.add_argument(
        "--record", action="store_true", help="write the best fusion into the reclassifier's manifest"
    )
    p.set_defaults(func=_cmd_eval_reclassifier)

    p = eval_sub.add_parser("oop", help="in/out-of-place AP on messy held-out rooms (paper Table 3)")
    p.add_argument("--split", type=_eval_split, default="test", help="test (default) or val")
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default=None, help="detector weights (default: the installed ones)")
    p.add_argument("--views", type=int, default=20, help="views per messy configuration (paper: 20)")
    p.add_argument("--rooms-per-type", type=int, default=5)
    p.add_argument("--messes", type=int, default=5, help="messy configurations per room (test has 5)")
    p.add_argument(
        "--walks",
        type=int,
        default=None,
        help="random walks per configuration to find the views (default: enough for 2 x --views)",
    )
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--record", action="store_true", help="merge the visual row into the weights' manifest")
    p.add_argument(
        "--visual-only", action="store_true", help="skip the language, fused and oracle-language rows"
    )
    p.add_argument("--reclassifier", default="default", help=RECLASSIFIER_HELP)
    p.set_defaults(func=_cmd_eval_oop)
