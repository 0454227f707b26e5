"""``tidee eval detector`` and ``tidee eval oop`` (options: :mod:`.config`): box AP and
in/out-of-place AP (:mod:`.metrics`) on held-out rooms.

Both render frames from the *test* (or val) rooms on the fly with
:mod:`tidee.agent.perception.detector.data` (never from training shards), run a detector's
``detect_batch`` on them and score the detections against the simulator's instances.

A detector here is anything with ``name`` and ``detect_batch(rgbs, depths)``
(:class:`FrameDetector`), e.g. ``LearnedPerception``.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from tidee.agent.evaluation.detection.config import (
    EVAL_THRESHOLD,
    SECOND_GUESSES,
    EvalDetectorConfig,
    EvalOopConfig,
)
from tidee.agent.evaluation.detection.metrics import (
    CEILING_ROW,
    OOP_ROWS,
    VISUAL_ROW,
    OopRowFn,
    evaluate_boxes,
    evaluate_oop,
    oracle_label_row,
)
from tidee.agent.evaluation.detection.report import (
    PAPER_TABLE3,
    _detector_markdown,
    _oop_markdown,
    save_detection_examples,
)
from tidee.agent.perception import AGENT_THRESHOLD, TRAINED_RENDERER
from tidee.agent.perception.base import Detection
from tidee.agent.perception.detector.config import DEFAULT_WEIGHTS
from tidee.agent.perception.detector.data import held_out_frames
from tidee.agent.perception.reclassifier.config import DEFAULT_RECLASSIFIER
from tidee.paths import in_checkout
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.protocol.vocab import ROOM_TYPES


class FrameDetector(Protocol):
    name: str

    def detect_batch(self, rgbs: np.ndarray, depths: np.ndarray) -> list[list[Detection]]: ...


def _config_counts(frames: Mapping[str, np.ndarray]) -> dict[str, int]:
    names, counts = np.unique(np.asarray(frames["frame_room"]), return_counts=True)
    return {str(k): int(v) for k, v in zip(names, counts)}


def _detect_all(
    detector: FrameDetector, frames: Mapping[str, np.ndarray], batch: int, progress: bool
) -> tuple[list[list[Detection]], dict[str, Any]]:
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
    detector: FrameDetector, cfg: EvalDetectorConfig, progress: bool = True
) -> dict[str, Any]:
    """Box AP of ``detector`` on held-out frames; writes detector.json, detector.md,
    detector_examples.png under ``cfg.out``.

    The headline is the detector as the agent runs it. Where the detector can offer several
    classes per heatmap peak (``classes_per_peak`` attribute) and ``cfg.classes_per_peak`` > 1,
    the report adds box AP with its ``classes_per_peak`` best classes per peak (``multiclass``).
    ``cfg.peaks`` other than "class-max" (the agent's) evaluates another decoding
    (``detector.model.decode``), without the multiclass pass."""
    out_dir, split, renderer, peaks = cfg.out, cfg.split, cfg.renderer, cfg.peaks
    rooms_per_type, messes, walks, frames_per_walk = (
        cfg.rooms_per_type,
        cfg.messes,
        cfg.walks,
        cfg.frames_per_walk,
    )
    seed, batch, classes_per_peak = cfg.seed, cfg.batch, cfg.classes_per_peak
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
        + _weights_flags(detector)
        + f" --out {out}"
    )
    report: dict[str, Any] = {
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


def _weights_flags(detector: FrameDetector) -> str:
    """The ``--weights`` and ``--reclassifier`` options that reload ``detector`` ("" for the
    defaults)."""
    if not hasattr(detector, "reclassifier"):
        return ""
    path = getattr(detector, "path", None)
    flag = ""
    if path is not None and Path(path).resolve() != DEFAULT_WEIGHTS.resolve():
        flag = f" --weights {in_checkout(path)}"
    return flag + _reclassifier_flag(detector)


def _reclassifier_flag(detector: FrameDetector) -> str:
    """The ``--reclassifier`` option that reloads ``detector``'s second stage ("" for the default)."""
    rc = _detector_info(detector).get("reclassifier")
    if rc is None:
        return " --reclassifier none" if DEFAULT_RECLASSIFIER.exists() else ""
    return (
        ""
        if Path(rc["weights"]).resolve() == DEFAULT_RECLASSIFIER.resolve()
        else f" --reclassifier {in_checkout(rc['weights'])}"
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


def run_oop_eval(
    detector: FrameDetector,
    cfg: EvalOopConfig,
    extra_rows: Mapping[str, OopRowFn | None] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Table 3: in/out-of-place AP on views of the messy held-out configurations.

    Views: frames of each messy configuration with at least one out-of-place object in view,
    the first ``cfg.views`` of ``cfg.walks`` random walks (default: enough walks for twice
    as many, since not every walk finds that many); fewer where the walks do not find enough,
    and the report says how many each configuration got. The visual row is the detector's
    ``oop_prob``; ``extra_rows`` maps a row name (e.g. "BERT-OOP (language)") to a function of
    (frames, detections) giving P(out of place) per detection. Standard rows without a
    classifier are reported as not built. Writes oop.json, oop.md and oop_examples.png under
    ``cfg.out``.
    """
    out_dir, split, views_per_config, walks = cfg.out, cfg.split, cfg.views, cfg.walks
    rooms_per_type, messes, frames_per_walk = cfg.rooms_per_type, cfg.messes, cfg.frames_per_walk
    seed, batch = cfg.seed, cfg.batch
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
        f"{_weights_flags(detector)} --out {out}"
    )
    report: dict[str, Any] = {
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


def _language_rows() -> dict[str, OopRowFn | None]:
    """The language, fused and oracle-language rows, from the shipped language heads."""
    from tidee.agent.reasoning.language_oop.config import DEFAULT_FUSED_WEIGHTS
    from tidee.agent.reasoning.language_oop.eval import language_row, oracle_language_row
    from tidee.agent.reasoning.language_oop.model import LanguageOOPClassifier

    clf = LanguageOOPClassifier.load()
    fused = LanguageOOPClassifier.load(DEFAULT_FUSED_WEIGHTS, encoder=clf.encoder)
    return {
        "BERT-OOP (language)": language_row(clf),
        "dDETR+BERT-OOP (fused)": language_row(fused),
        "Oracle-language": oracle_language_row(clf),
        CEILING_ROW: oracle_label_row,
    }


__all__ = [
    "FrameDetector",
    "run_detector_eval",
    "run_oop_eval",
]
