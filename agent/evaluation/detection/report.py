"""The detector evaluations' reports: detector.md, oop.md (the paper's Table 3), fusion.md and
the example grids (detector_examples.png, oop_examples.png)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.evaluation.detection.config import EVAL_THRESHOLD
from tidee.agent.evaluation.detection.metrics import OOP_ROWS, SIZE_RANGES, VISUAL_ROW
from tidee.agent.perception.base import Detection
from tidee.protocol.episode_log import write_atomic

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
            f"; classes from the crop reclassifier `{rc['weights']}` (sha256 `{rc['sha256']}`, "
            f"alpha {rc['alpha']}, beta {rc['beta']})"
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
        f"{data['split']} rooms ({data['rooms_per_type']} per type; the tidy room + "
        f"{data['messes_per_room']} messes each; {data['walks']} random walk(s) x up to "
        f"{data['frames_per_walk']} frames; seed "
        f"{data['seed']})",
        f"- rooms: {', '.join(data['rooms'])}",
        f"- `detect_batch` time: {t['ms_per_frame_median']:.1f} ms/frame median "
        f"({t['ms_per_frame_mean']:.1f} mean), batch {t['batch']}, 1 torch thread",
        f"- one frame at a time (the agent's case), 1 torch thread: "
        f"{t['single_frame_ms_median']:.1f} ms median, {t['single_frame_ms_p90']:.1f} ms p90 "
        "(target <= 30 ms), including box decoding and depth masks"
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
            f"configurations ({data['rooms_per_type']} rooms per type x {data['messes_per_room']} messes); "
            f"target {data['views_per_config_target']} per configuration, got "
            f"{data['views_min']}-{data['views_max']} (mean {data['views_mean']:.1f}; {short} "
            "configuration(s) short of the target) from "
            f"{data['walks']} walks x up to {data['frames_per_walk']} frames, seed {data['seed']}",
            f"- pickupable GT objects in view: {r['n_gt_in_place']} in place, "
            f"{r['n_gt_out_of_place']} out of place; {r['n_detections']} detections of pickupable classes",
            "- a detection scores score x P(oop) as out-of-place and score x (1 - P(oop)) as in-place; "
            "it matches a GT box of that category by IoU, whatever the class. AP in %.",
            "",
            oop_table_markdown(r),
            "",
            "![examples](oop_examples.png)",
            "",
            'Examples: GT thin green ("oop": out of place); predictions with score >= 0.3, '
            "red when P(oop) > 0.5.",
            "",
        ]
    )


def _fusion_markdown(report: Mapping[str, Any]) -> str:
    """fusion.md: box mAP of the detector alone and of each (alpha, beta), the best starred."""
    command, split, rows, best = (
        report["command"],
        report["data"]["split"],
        report["rows"],
        report["best"],
    )
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
    gates = report.get("gates") or []
    if gates:
        lines += [
            "",
            f"Gates at the best fusion: a detection whose detector score is at least the gate keeps the "
            f"detector's class and score and skips the crop classifier. Chosen: the lowest gate within "
            f"the tolerance of the ungated mAP@0.5 (**{report.get('gate')}**).",
            "",
            "| gate | mAP@0.5 | mAP@[.5:.95] | crops classified | detections gated |",
            "|---|---:|---:|---:|---:|",
        ]
        for r in gates:
            gate = "none" if r["gate"] is None else f"{r['gate']:g}"
            star = " **(chosen)**" if r["gate"] is not None and r["gate"] == report.get("gate") else ""
            lines.append(
                f"| {gate} | {_pct(r['map50'])}{star} | {_pct(r['map'])} | {r['reclassified']} | "
                f"{r['gated']} |"
            )
    return "\n".join(lines) + "\n"


__all__ = [
    "NOT_BUILT",
    "PAPER_TABLE3",
    "oop_table_markdown",
    "save_detection_examples",
]
