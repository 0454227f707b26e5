"""Box AP and in/out-of-place AP of detections against the simulator's instances.

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

Pure numpy: no detector, no simulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tidee.agent.classes import CLASS_INDEX, CLASSES, PICKUPABLE
from tidee.agent.perception.base import Detection

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
CEILING_ROW = "Oracle-label (ceiling)"

# A classifier row computed after detection: (frames, detections per frame) -> P(oop) per detection.
OopRowFn = Callable[[Mapping[str, np.ndarray], list[list[Detection]]], list[list[float]]]


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


__all__ = [
    "CEILING_ROW",
    "COCO_IOUS",
    "OOP_IOUS",
    "OOP_ROWS",
    "OopRowFn",
    "SIZE_RANGES",
    "VISUAL_ROW",
    "average_precision",
    "box_iou",
    "evaluate_boxes",
    "evaluate_oop",
    "match_detections",
    "matched_oop_labels",
    "oracle_label_row",
]
