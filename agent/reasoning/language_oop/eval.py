"""Evaluation of the language / fused OOP heads.

* :func:`evaluate_language_oop` / :func:`run_language_eval` (``tidee eval language-oop``):
  Oracle-language, object-level AP on the test rooms' messy configurations (Table 3).
* :func:`oracle_language_row` and :func:`language_row` give Table-3 rows for
  ``run_oop_eval(extra_rows=...)`` (``tidee eval oop``).
* :func:`evaluate_memory` / :func:`run_memory_eval` (``tidee eval oop-memory``): the heads on
  held-out paragraphs of the agent's own tracked objects (:mod:`.memory_data`).
"""

from __future__ import annotations

import math
import sys
import time
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tidee.agent.reasoning.language_oop.config import (
    DEFAULT_CACHE_DIR,
    LanguageEvalConfig,
    MemoryEvalConfig,
)
from tidee.agent.reasoning.language_oop.data import SceneSource, config_paragraphs, language_oop_samples
from tidee.agent.reasoning.language_oop.frames import frame_paragraphs
from tidee.agent.reasoning.language_oop.memory_data import (
    load_memory_samples,
    memory_features,
    memory_meta,
)
from tidee.agent.reasoning.language_oop.model import LanguageOOPClassifier, feature_matrix
from tidee.protocol.vocab import HELD_OUT_SPLITS, ROOM_TYPES

if TYPE_CHECKING:
    from tidee.agent.perception.base import Detection


def object_ap(probs: Sequence[float] | np.ndarray, labels: Sequence[int] | np.ndarray) -> dict[str, Any]:
    """Object-level AP (COCO 101-point, as Table 3): out-of-place ranks by P(oop), in-place by
    1 - P(oop); ``map`` is their mean. Also accuracy at 0.5 and the counts."""
    from tidee.agent.evaluation.detection.metrics import average_precision

    p = np.asarray(probs, np.float64).reshape(-1)
    y = np.asarray(labels).astype(bool).reshape(-1)
    ap_oop = average_precision(p, y, int(y.sum()))
    ap_ip = average_precision(1 - p, ~y, int((~y).sum()))
    return {
        "map": float(np.nanmean([ap_oop, ap_ip])) if len(p) else math.nan,
        "ap_out_of_place": ap_oop,
        "ap_in_place": ap_ip,
        "accuracy": float(np.mean((p > 0.5) == y)) if len(p) else math.nan,
        "n_out_of_place": int(y.sum()),
        "n_in_place": int((~y).sum()),
    }


# ================================================================================ Oracle-language
def evaluate_language_oop(
    classifier: LanguageOOPClassifier,
    split: str = "test",
    rooms_per_type: int = 5,
    messes_per_room: int = 5,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    progress: bool = True,
) -> dict[str, Any]:
    """Oracle-language: object-level AP on the messy configurations of held-out rooms, every
    pickupable object described from ground-truth boxes. Overall and per room type."""
    if split not in HELD_OUT_SPLITS:
        raise ValueError(
            f"the language OOP classifier is evaluated on held-out rooms (test or val), not {split!r}"
        )
    samples = language_oop_samples(
        split, rooms_per_type, messes_per_room, cache_dir=cache_dir, progress=progress
    )
    probs = classifier.predict([s.paragraph for s in samples])
    labels = np.array([s.label for s in samples])
    per_type = {
        rt: object_ap(probs[m], labels[m])
        for rt in ROOM_TYPES
        if (m := np.array([s.room_type == rt for s in samples])).any()
    }
    return {
        "split": split,
        "rooms_per_type": rooms_per_type,
        "messes_per_room": messes_per_room,
        "configurations": rooms_per_type * len(ROOM_TYPES) * messes_per_room,
        "samples": len(samples),
        **object_ap(probs, labels),
        "per_room_type": per_type,
    }


def show_path(path: str | Path) -> str:
    """A path relative to the working directory when it lies under it (reports stay portable)."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


def run_language_eval(cfg: LanguageEvalConfig, progress: bool = True) -> dict[str, Any]:
    """``tidee eval language-oop``: the Oracle-language AP table as language_oop.json + .md."""
    from tidee.agent.evaluation.detection.report import PAPER_TABLE3, _pct
    from tidee.agent.learning import read_manifest
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    split, rooms_per_type, messes_per_room, weights = (
        cfg.split,
        cfg.rooms_per_type,
        cfg.messes_per_room,
        cfg.weights,
    )
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    clf = LanguageOOPClassifier.load(weights, cfg.encoder_path)
    clf.encoder.load_cache(cfg.cache_dir)
    res = evaluate_language_oop(clf, split, rooms_per_type, messes_per_room, cfg.cache_dir, progress)
    clf.encoder.save_cache(cfg.cache_dir)
    command = (
        f"tidee eval language-oop --split {split} --rooms-per-type {rooms_per_type} "
        f"--messes {messes_per_room} --out {out}"
    )
    report = {
        "command": command,
        "weights": show_path(weights),
        "sha256": read_manifest(weights)["sha256"],
        "seconds": round(time.time() - t0, 1),
        **res,
        "paper_ai2thor_oracle_bert_oop_iou0.5": list(PAPER_TABLE3["Oracle-language"][3:]),
    }
    write_json_atomic(out / "language_oop.json", report)
    lines = [
        f"# Oracle-language out-of-place classification ({split} rooms)",
        "",
        f"`{command}`",
        "",
        (
            f"- weights `{show_path(weights)}` (sha256 `{report['sha256'][:16]}...`), "
            "text encoder MiniLM-L6 (frozen)"
        ),
        (
            f"- {res['samples']} pickupable objects ({res['n_out_of_place']} out of place) of "
            f"{res['configurations']} messy configurations ({rooms_per_type} rooms per type x "
            f"{messes_per_room} messes); paragraphs from ground-truth 3D boxes"
        ),
        "- object-level AP in % (COCO 101-point): out-of-place ranked by P(oop), in-place by 1 - P(oop)",
        "",
        "| rooms | objects | OOP | mAP | AP in-place | AP out-of-place | accuracy@0.5 |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in [("all", res), *res["per_room_type"].items()]:
        lines.append(
            f"| {name} | {r['n_in_place'] + r['n_out_of_place']} | {r['n_out_of_place']} | "
            f"{_pct(r['map'])} | {_pct(r['ap_in_place'])} | {_pct(r['ap_out_of_place'])} | "
            f"{_pct(r['accuracy'])} |"
        )
    paper = PAPER_TABLE3["Oracle-language"]
    lines += [
        "",
        (
            f"Paper (oracle-BERT-OOP, AI2THOR, detection-level at IoU 0.5): mAP {paper[3]:.2f}, "
            f"in-place {paper[4]:.2f}, out-of-place {paper[5]:.2f}."
        ),
        "",
    ]
    write_atomic(out / "language_oop.md", "\n".join(lines).encode())
    return report


# ================================================================================ Table-3 rows
RowFn = Any  # (frames, detections per frame) -> P(out of place) per detection


def oracle_language_row(
    classifier: LanguageOOPClassifier,
    scenes: Mapping[str, Sequence[Mapping[str, Any]]] | None = None,
    cache_dir: str | Path | None = DEFAULT_CACHE_DIR,
    min_iou: float = 0.5,
) -> RowFn:
    """Oracle-language for ``run_oop_eval(extra_rows=...)``.

    Each detection takes its best-IoU ground-truth instance of the frame (IoU >= ``min_iou``,
    any class) and that object's paragraph from ground-truth boxes in its configuration
    ("RoomType:seed:mess", re-created once per configuration or read from ``scenes`` /
    the disk cache); detections with no such instance get 0.5 (no opinion).
    """
    from tidee.agent.evaluation.detection.metrics import box_iou

    scenes = dict(scenes or {})

    def row(frames: Mapping[str, np.ndarray], dets: list[list[Detection]]) -> list[list[float]]:
        src = SceneSource(cache_dir)
        paragraphs: dict[tuple[str, str], str] = {}
        want: list[tuple[int, int, tuple[str, str]]] = []  # (frame, detection, (config, object id))
        obj_frame = np.asarray(frames["obj_frame"])
        try:
            for i, ds in enumerate(dets):
                if not ds:
                    continue
                rows = np.nonzero(obj_frame == i)[0]
                if not len(rows):
                    continue
                config = str(frames["frame_room"][i])
                iou = box_iou(np.array([d.box for d in ds], np.float64), np.asarray(frames["obj_box"])[rows])
                for k in range(len(ds)):
                    g = int(np.argmax(iou[k]))
                    if iou[k, g] >= min_iou:
                        want.append((i, k, (config, str(frames["obj_id"][rows[g]]))))
            by_config: dict[str, set[str]] = defaultdict(set)
            for _, _, (config, oid) in want:
                by_config[config].add(oid)
            for config, ids in by_config.items():
                if config not in scenes:
                    rt, seed, mess = config.split(":")
                    if mess in ("None", ""):
                        raise ValueError(
                            f"frame of the tidy configuration {config}: Table 3 uses messy views only"
                        )
                    scenes[config] = src.records(rt, int(seed), int(mess))
                for oid, (para, _, _) in config_paragraphs(scenes[config], sorted(ids)).items():
                    paragraphs[(config, oid)] = para
        finally:
            src.close()
        out = [[0.5] * len(ds) for ds in dets]
        if want:
            probs = classifier.predict([paragraphs[key] for _, _, key in want])
            for (i, k, _), p in zip(want, probs):
                out[i][k] = float(p)
        return out

    return row


def language_row(classifier: LanguageOOPClassifier, context_score: float = 0.3) -> RowFn:
    """BERT-OOP (or the fused head, when ``classifier`` has one) from a frame's detections alone.

    Each detection is unprojected with the frame's depth (:func:`.frames.detection_refs`; the
    frames do not record the pitch, so it is estimated from the depth among the agent's
    four horizons); its paragraph uses as context the frame's other detections with score
    >= ``context_score``. No tracking over views, so receptacles are partial (what one
    view shows): a rougher picture than the agent's object memory. A detection with no
    valid depth gets 0.5.
    """

    def row(frames: Mapping[str, np.ndarray], dets: list[list[Detection]]) -> list[list[float]]:
        out = [[0.5] * len(ds) for ds in dets]
        paras: list[str] = []
        feats: list[np.ndarray | None] = []
        where: list[tuple[int, int]] = []
        for i, ds in enumerate(dets):
            for k, para in frame_paragraphs(np.asarray(frames["depth"][i], np.float32), ds, context_score):
                paras.append(para)
                feats.append(ds[k].feature)
                where.append((i, k))
        if paras:
            visual = feature_matrix(feats, classifier.visual_dim) if classifier.visual_dim else None
            for (i, k), p in zip(where, classifier.predict(paras, visual)):
                out[i][k] = float(p)
        return out

    return row


# ================================================================================ agent memory
def evaluate_memory(classifier: Any, path: str | Path, split: str = "test") -> dict[str, Any]:
    """Object-level AP of a language / fused classifier on held-out memory samples: how well
    it separates moved from in-place objects as the agent describes them (per room type too)."""
    rows = load_memory_samples(path, split=split)
    if not rows:
        raise ValueError(f"{path} holds no samples")
    visual = memory_features(rows, classifier.visual_dim) if getattr(classifier, "visual_dim", 0) else None
    probs = classifier.predict([r["paragraph"] for r in rows], visual)
    return {"data": str(path), "split": split, **memory_scores(probs, rows)}


def memory_scores(probs: np.ndarray, rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """AP overall and per room type, and what a 0.5 threshold flags, of ``probs`` on ``rows``."""
    labels = np.array([r["label"] for r in rows])
    out = {"samples": len(rows), **object_ap(probs, labels)}
    per: dict[str, Any] = {}
    for rt in sorted({r["room_type"] for r in rows}):
        idx = [i for i, r in enumerate(rows) if r["room_type"] == rt]
        per[rt] = object_ap(probs[idx], labels[idx])
    out["per_room_type"] = per
    at = probs >= 0.5
    out["at_0.5"] = {
        "flagged": int(at.sum()),
        "true": int((at & (labels == 1)).sum()),
        "false": int((at & (labels == 0)).sum()),
    }
    return out


def run_memory_eval(cfg: MemoryEvalConfig) -> dict[str, Any]:
    """``tidee eval oop-memory``: each classifier's AP on held-out memory samples; JSON + Markdown."""
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    data = cfg.data
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = memory_meta(data)
    rows = {}
    samples = load_memory_samples(data, split=meta["split"])
    if samples and all(r.get("visual_oop") is not None for r in samples):
        # learned perception: the detector's OOP head (running mean over the track's views)
        rows["visual (detector OOP head)"] = memory_scores(
            np.array([r["visual_oop"] for r in samples]), samples
        )
    for w in cfg.weights:
        rows[Path(w).name] = evaluate_memory(LanguageOOPClassifier.load(w), data, split=meta["split"])
    report = {"data": meta, "classifiers": rows}
    write_json_atomic(out / "report.json", report)
    lines = [
        "# OOP classifiers on the agent's own memory paragraphs",
        "",
        f"Samples: `{data}` ({meta['split']} rooms, {meta['configurations']} configurations, "
        f"{meta['samples']} samples, {meta['out_of_place']} out of place; perception {meta['perception']}; "
        f"made by `{meta['command']}`). Each sample is the paragraph of one tracked object after the agent's "
        "mapping phase or a later search goal, labelled by the simulator's mess-up (evaluation only).",
        "",
        "| Classifier | mAP | AP out-of-place | AP in-place | flagged at 0.5 | of them in place |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        a = r["at_0.5"]
        lines.append(
            f"| {name} | {100 * r['map']:.1f} | {100 * r['ap_out_of_place']:.1f} | "
            f"{100 * r['ap_in_place']:.1f} | {a['flagged']} | {a['false']} |"
        )
    lines += ["", "command: `tidee eval oop-memory " + " ".join(sys.argv[3:]) + "`"]
    write_atomic(out / "report.md", ("\n".join(lines) + "\n").encode())
    return report
