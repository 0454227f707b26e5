"""``tidee eval reclassifier`` (options: ``config.EvalFusionConfig``): the box mAP of the
detector alone and fused with its crop reclassifier over a grid of (alpha, beta), to choose the
fusion on the validation rooms, and optionally a gate: the detector score at and above which a
detection keeps the detector's class and score and skips the crop classifier (fewer crops a frame,
for the agent's step time)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tidee.agent.evaluation.detection.config import (
    FUSION_ALPHAS,
    FUSION_BETAS,
    GATE_TOLERANCE,
    EvalFusionConfig,
)
from tidee.agent.evaluation.detection.eval import (
    FrameDetector,
    _detect_all,
    _detector_info,
    _frames_summary,
    _weights_flags,
)
from tidee.agent.evaluation.detection.metrics import evaluate_boxes
from tidee.agent.evaluation.detection.report import _fusion_markdown
from tidee.agent.perception.detector.data import held_out_frames
from tidee.protocol.episode_log import write_atomic, write_json_atomic


def choose_gate(gate_rows: list[dict[str, Any]], tolerance: float) -> float | None:
    """The lowest gate whose mAP@0.5 is within ``tolerance`` of the ungated row's (the first,
    ``gate`` None), or None when no gate keeps it."""
    ungated = gate_rows[0]["map50"]
    kept = [r["gate"] for r in gate_rows[1:] if r["map50"] >= ungated - tolerance]
    return min(kept) if kept else None


def run_fusion_sweep(detector: FrameDetector, cfg: EvalFusionConfig, progress: bool = True) -> dict[str, Any]:
    """Box mAP of the detector alone and of every (alpha, beta) fusion with its crop reclassifier
    (``reclassifier.model.fuse``) on the same held-out frames; writes fusion.json and fusion.md
    under ``cfg.out``. The weights are chosen on the validation rooms
    (``tidee eval reclassifier --record``)."""
    out_dir, split, alphas, betas = cfg.out, cfg.split, cfg.alphas, cfg.betas
    rooms_per_type, messes, walks, frames_per_walk = (
        cfg.rooms_per_type,
        cfg.messes,
        cfg.walks,
        cfg.frames_per_walk,
    )
    seed, batch = cfg.seed, cfg.batch
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
    g0 = getattr(detector, "gate", None)
    rows: list[dict[str, Any]] = []
    gate_rows: list[dict[str, Any]] = []
    try:
        detector.gate = None  # type: ignore[attr-defined]
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
        best = max(rows[1:], key=lambda r: r["map50"])
        if cfg.gates:
            detector.alpha, detector.beta = best["alpha"], best["beta"]  # type: ignore[attr-defined]
            for g in (None, *sorted(cfg.gates)):
                detector.gate = g  # type: ignore[attr-defined]
                detector.reset_stats()  # type: ignore[attr-defined]
                dets, timing = _detect_all(detector, frames, batch, False)
                m = evaluate_boxes(dets, frames)
                stats = detector.stats  # type: ignore[attr-defined]
                gate_rows.append(
                    {
                        "gate": g,
                        "map50": m["map50"],
                        "map": m["map"],
                        "n_detections": m["n_detections"],
                        "reclassified": stats["reclassified"],
                        "gated": stats["gated"],
                        "ms_per_frame_median": timing["ms_per_frame_median"],
                    }
                )
                if progress:
                    print(
                        f"gate {g}: mAP@0.5 {100 * m['map50']:.1f}, {stats['reclassified']} crops", flush=True
                    )
    finally:
        detector.reclassifier, detector.alpha, detector.beta = rc, a0, b0  # type: ignore[attr-defined]
        detector.gate = g0  # type: ignore[attr-defined]
    chosen_gate = choose_gate(gate_rows, cfg.gate_tolerance) if gate_rows else None
    command = (
        f"tidee eval reclassifier --split {split} --rooms-per-type {rooms_per_type} --messes {messes} "
        f"--walks {walks} --frames-per-walk {frames_per_walk} --seed {seed}"
        + (
            ""
            if (tuple(alphas), tuple(betas)) == (FUSION_ALPHAS, FUSION_BETAS)
            else f" --alphas {','.join(f'{a:g}' for a in alphas)} --betas {','.join(f'{b:g}' for b in betas)}"
        )
        + (f" --gates {','.join(f'{g:g}' for g in cfg.gates)}" if cfg.gates else "")
        + (
            f" --gate-tolerance {cfg.gate_tolerance:g}"
            if cfg.gates and cfg.gate_tolerance != GATE_TOLERANCE
            else ""
        )
        + _weights_flags(detector)
        + f" --out {out}"
    )
    report: dict[str, Any] = {
        "command": command,
        "detector": _detector_info(detector),
        "rows": rows,
        "best": best,
        "gates": gate_rows,
        "gate": chosen_gate,
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
    write_json_atomic(out / "fusion.json", report)
    write_atomic(out / "fusion.md", _fusion_markdown(report).encode())
    return report


__all__ = ["choose_gate", "run_fusion_sweep"]
