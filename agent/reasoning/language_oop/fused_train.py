"""``tidee train fused-oop``: dDETR+BERT-OOP (paper §3.2, Table 3 "fused"), the language
paragraph and the detector's feature, trained on real detector features.

The command runs the shipped detector over frames of training rooms it never trained on
(``data/detection_unseen``: ``tidee gen detection --skip-rooms 60``; on its own training
frames its features are near-perfect and the head learns to over-trust them). Each
pickupable detection that matches a ground-truth instance (IoU >= 0.5, class-agnostic as in
the Table 3 protocol) becomes one sample: the paragraph :func:`.eval.language_row` writes for
it (single-view relations from the frame's depth, :func:`.frames.frame_paragraphs`) and its
64-d detector feature, labelled by whether the mess-up moved that instance. The
``FusedOOPHead`` learns from [text embedding, feature]. A tenth of the rooms (seed % 10 == 9)
is held out from the head for the manifest's validation AP (the manifest counts how many
of the data's rooms the detector trained on). The held-out figures are ``tidee eval oop``
on the test rooms (Table 3). The replay set for instructions is the language head's (text only).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.reasoning.language_oop.config import VISUAL_DIM, FusedTrainConfig
from tidee.agent.reasoning.language_oop.eval import object_ap, show_path
from tidee.agent.reasoning.language_oop.frames import frame_paragraphs
from tidee.agent.reasoning.language_oop.model import (
    FusedOOPHead,
    LanguageOOPClassifier,
    feature_matrix,
    fit_head,
)


def held_out_room(room: str) -> bool:
    """Training rooms kept for validation: seed % 10 == 9 (``frame_room`` is "Type:seed:...")."""
    return int(str(room).split(":")[1]) % 10 == 9


def detector_rooms(detector: Any) -> set[str]:
    """The "Type:seed" rooms of the frames the detector was trained on (from its manifest's
    data directories, comma-separated; a directory that is not here adds nothing)."""
    from tidee.agent.perception.detector.data import split_data_spec

    rooms: set[str] = set()
    for d in split_data_spec(detector.manifest.get("data", {}).get("dir", "")):
        try:
            rooms |= set(json.loads((d / "manifest.json").read_text()).get("rooms", []))
        except (OSError, ValueError):
            continue
    return rooms


def detection_samples(
    frames: dict[str, np.ndarray],
    detections: list[list[Any]],
    context_score: float = 0.3,
    match_iou: float = 0.5,
) -> dict[str, Any]:
    """One sample per pickupable detection matched to a pickupable ground-truth instance:
    paragraphs, features (N x 64, zero where missing), labels, categories, rooms."""
    from tidee.agent.evaluation.detection.metrics import matched_oop_labels

    rooms = frames.get("frame_room")
    out: dict[str, list] = {"paragraphs": [], "features": [], "labels": [], "categories": [], "rooms": []}
    for i, (dets, labels) in enumerate(zip(detections, matched_oop_labels(frames, detections, match_iou))):
        if not labels:
            continue
        paras = dict(frame_paragraphs(np.asarray(frames["depth"][i], np.float32), dets, context_score))
        for k, label in labels.items():
            if k not in paras:
                continue
            out["paragraphs"].append(paras[k])
            out["features"].append(dets[k].feature)
            out["labels"].append(label)
            out["categories"].append(dets[k].label)
            out["rooms"].append(str(rooms[i]) if rooms is not None else "")
    samples: dict[str, Any] = dict(out)
    samples["features"] = feature_matrix(out["features"], VISUAL_DIM)
    return samples


def add_memory_samples(samples: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """Append `tidee gen oop-memory` samples (paragraphs of tracked objects, their detector
    features) to ``samples`` in place; their meta. Needs learned-perception samples: with
    oracle perception the tracks have no features and the head would learn zeros."""
    from tidee.agent.reasoning.language_oop.memory_data import (
        load_memory_samples,
        memory_features,
        memory_meta,
    )

    meta = memory_meta(path)
    if meta.get("perception") != "learned":
        raise ValueError(
            f"{path} was made with {meta.get('perception')!r} perception; the fused head needs "
            "detector features (`tidee gen oop-memory --perception learned`)"
        )
    rows = load_memory_samples(path, split="train")
    samples["paragraphs"] += [r["paragraph"] for r in rows]
    samples["features"] = np.concatenate([samples["features"], memory_features(rows, VISUAL_DIM)])
    samples["labels"] += [int(r["label"]) for r in rows]
    samples["categories"] += [r["category"] for r in rows]
    samples["rooms"] += [r["config"] for r in rows]
    return meta


def train_fused_oop(
    cfg: FusedTrainConfig, command: str = "tidee train fused-oop", progress: bool = True
) -> dict[str, Any]:
    """Detect, build samples, train the fused head, write weights + manifest."""
    import torch

    from tidee.agent.evaluation.detection.eval import _detect_all
    from tidee.agent.learning import loss_curve_path, save_loss_curve, write_manifest
    from tidee.agent.perception.detector.data import load_shards
    from tidee.agent.perception.learned import LearnedPerception

    t0 = time.time()
    data_dir = Path(cfg.data)
    manifest = json.loads((data_dir / "manifest.json").read_text())
    if manifest.get("config", {}).get("split") != "train":
        raise ValueError(
            f"{data_dir} is not training data (split {manifest.get('config', {}).get('split')!r})"
        )
    frames = load_shards(data_dir, limit=cfg.max_frames)
    if cfg.max_frames is not None:
        n = cfg.max_frames
        keep = np.asarray(frames["obj_frame"]) < n
        frames = {k: (v[keep] if k.startswith("obj_") else v[:n]) for k, v in frames.items()}
    detector = LearnedPerception.load(threshold=cfg.detection_threshold)
    detections, det_timing = _detect_all(detector, frames, batch=16, progress=progress)
    samples = detection_samples(frames, detections, cfg.context_score, cfg.match_iou)
    n_frame_samples = len(samples["labels"])
    memory_meta = None
    if cfg.memory_data:
        memory_meta = add_memory_samples(samples, cfg.memory_data)
    if not samples["labels"]:
        raise ValueError("no detection matched a ground-truth instance: nothing to train on")
    t_data = time.time() - t0
    language = LanguageOOPClassifier.load(cfg.language_weights)
    encoder = language.encoder
    encoder.load_cache(cfg.cache_dir)
    emb = encoder.encode(samples["paragraphs"], progress=progress)
    encoder.save_cache(cfg.cache_dir)
    x = np.concatenate([emb, samples["features"]], 1)
    y = np.asarray(samples["labels"], np.float32)
    val = np.asarray([held_out_room(r) for r in samples["rooms"]], bool)
    torch.manual_seed(cfg.seed)
    head = FusedOOPHead()
    history = fit_head(
        head,
        x[~val],
        y[~val],
        cfg.steps,
        cfg.batch_size,
        cfg.lr,
        cfg.weight_decay,
        cfg.seed,
        "cpu",
        cfg.log_every,
        progress,
    )
    clf = LanguageOOPClassifier(
        head,
        encoder,
        language.replay,
        {
            "encoder": encoder.path.name,
            "encoder_identity": encoder.identity,
            "train": "detector features on data/detection",
            "config": vars(cfg),
        },
    )

    def ap(mask: np.ndarray) -> dict[str, Any]:
        return object_ap(clf.predict_embeddings(emb[mask], samples["features"][mask]), y[mask])

    text_only = LanguageOOPClassifier(language.head, encoder)
    # Rooms the detector trained on give it near-perfect features: a head trained there
    # learns to trust the feature more than it deserves on new rooms, and its validation
    # there is optimistic. Hence data from rooms the detector never saw (--skip-rooms).
    seen = detector_rooms(detector) & set(manifest.get("rooms", []))
    metrics: dict[str, Any] = {
        "train": ap(~val),
        "val_rooms": ap(val),
        "val_language_head_same_samples": object_ap(text_only.predict_embeddings(emb[val]), y[val]),
        "note": (
            f"{len(seen)} of the data's {len(manifest.get('rooms', []))} rooms were in the detector's "
            "training frames"
            + (": validation optimistic" if seen else "")
            + "; held-out figures: tidee eval oop on the test rooms (Table 3)"
        ),
    }
    if cfg.eval_memory_data:
        from tidee.agent.reasoning.language_oop.eval import evaluate_memory

        metrics["test_agent_memory"] = evaluate_memory(clf, cfg.eval_memory_data)
    out = Path(cfg.out)
    clf.save(out)
    curve = loss_curve_path(out, "language_oop_fused_loss.png", cfg.loss_png)
    save_loss_curve(history, curve, "fused OOP head (text + detector feature): class-balanced BCE")
    rooms = sorted({r.rsplit(":", 1)[0] if r.count(":") > 1 else r for r in samples["rooms"]})
    data = {
        "split": "train",
        # relative to the working directory where it lies under it (the default is absolute)
        "source": f"{show_path(data_dir)} ({manifest.get('command', 'tidee gen detection')})",
        "frames": int(len(frames["rgb"])),
        "samples": int(len(y)),
        "out_of_place": int(y.sum()),
        "val_rooms": "seed % 10 == 9",
        "val_samples": int(val.sum()),
        "rooms": len(rooms),
        "rooms_in_detector_training": len(seen),
        "frame_samples": n_frame_samples,
        "memory_samples": int(len(y)) - n_frame_samples,
        "memory_data": memory_meta,
        "detector": {
            "sha256": detector.sha256,
            "threshold": cfg.detection_threshold,
            "ms_per_frame_median": det_timing["ms_per_frame_median"],
        },
    }
    timing = {
        "data_s": round(t_data, 1),
        "total_s": round(time.time() - t0, 1),
        "device": "cpu",
        "torch_threads": torch.get_num_threads(),
    }
    write_manifest(
        out,
        command,
        data,
        metrics,
        timing=timing,
        head=head.config(),
        loss_curve=curve,
        final_loss=history[-1]["bce"] if history else None,
        table3="tidee eval oop --split test --views 5 --rooms-per-type 5 --messes 5 --walks 2 --seed 11",
    )
    return {"weights": str(out), "metrics": metrics, "data": data, "timing": timing}
