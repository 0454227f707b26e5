"""``tidee train detector`` (options: ``config.TrainDetectorConfig``): the CenterNet-style RGB-D
detector with its OOP head, from scratch.

Reproducible from a seed (the sampling order and augmentation draw from one generator),
resumable (a checkpoint every ``ckpt_every`` steps in the work directory holds the model,
optimiser, schedule, sampler state and loss history), a tqdm progress bar, and a loss curve
PNG. Uses the GPU when torch sees one, the CPU otherwise.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from tidee.agent.learning import (
    dataset_record,
    load_checkpoint,
    pick_device,
    resolve_precision,
    resume_training,
    save_checkpoint,
    save_loss_curve,
    sha256_file,
    ship_weights,
    write_manifest,
)
from tidee.agent.perception.detector.config import DetectorConfig, TrainConfig
from tidee.agent.perception.detector.data import TRAIN_ROOMS, load_datasets
from tidee.agent.perception.detector.model import CenterDetector, detector_loss, encode_targets, preprocess


class Batches:
    """Random minibatches with flips and brightness jitter, targets encoded on the fly."""

    def __init__(
        self, data: dict[str, np.ndarray], cfg: DetectorConfig, batch_size: int, seed: int | list[int]
    ) -> None:
        self.data, self.cfg, self.batch_size = data, cfg, batch_size
        self.rng = np.random.default_rng(seed)
        n = len(data["rgb"])
        order = np.argsort(data["obj_frame"], kind="stable")
        frames = data["obj_frame"][order]
        starts = np.searchsorted(frames, np.arange(n + 1))
        self.rows = [order[starts[i] : starts[i + 1]] for i in range(n)]

    def state(self) -> dict:
        return dict(self.rng.bit_generator.state)

    def set_state(self, s: dict) -> None:
        if "parallel_workers" in s:
            raise ValueError(
                f"the checkpoint's sampler was a {s['parallel_workers']}-worker stream; resume with "
                f"--loader-workers {s['parallel_workers']} or pass --no-resume"
            )
        self.rng.bit_generator.state = s

    def __call__(self) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        d, rng = self.data, self.rng
        idx = rng.integers(0, len(d["rgb"]), self.batch_size)
        rgb = d["rgb"][idx].copy()
        depth = d["depth"][idx].astype(np.float32)
        size = rgb.shape[2]
        targets: dict[str, list[np.ndarray]] = {}
        for b, i in enumerate(idx):
            rows = self.rows[i]
            boxes = d["obj_box"][rows].copy()
            if rng.random() < 0.5:
                rgb[b] = rgb[b, :, ::-1]
                depth[b] = depth[b, :, ::-1]
                boxes[:, [0, 2]] = size - boxes[:, [2, 0]]
            gain = rng.uniform(0.8, 1.2, 3) * rng.uniform(0.85, 1.15)
            rgb[b] = np.clip(rgb[b] * gain, 0, 255).astype(np.uint8)
            t = encode_targets(
                boxes,
                d["obj_cls"][rows],
                d["obj_oop"][rows],
                self.cfg.num_classes,
                size=size,
                stride=self.cfg.stride,
            )
            for k, v in t.items():
                targets.setdefault(k, []).append(v)
        x = preprocess(rgb, depth, self.cfg.use_depth)
        return x, {k: torch.from_numpy(np.stack(v)) for k, v in targets.items()}


class _BatchStream(torch.utils.data.IterableDataset):
    """Endless ``Batches`` in a DataLoader worker, seeded by (seed, worker, start step)."""

    def __init__(
        self, data: dict[str, np.ndarray], cfg: DetectorConfig, batch_size: int, seed: int, start: int
    ) -> None:
        super().__init__()
        self.data, self.cfg, self.batch_size, self.seed, self.start = data, cfg, batch_size, seed, start

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        worker = info.id if info is not None else 0
        torch.set_num_threads(1)
        batches = Batches(self.data, self.cfg, self.batch_size, [self.seed, worker, self.start])
        while True:
            yield batches()


class ParallelBatches:
    """``Batches`` built in ``workers`` processes, for a GPU that one process cannot keep busy.

    Worker k draws from its own generator seeded by (seed, k, start step) and the DataLoader
    takes the workers' batches in turn, so a run is reproducible for a given worker count. The
    sampler state is the step the stream has reached: a resumed run restarts every worker's
    generator from (seed, k, that step), which is deterministic but not the stream an
    uninterrupted run would have drawn.
    """

    def __init__(
        self, data: dict[str, np.ndarray], cfg: DetectorConfig, batch_size: int, seed: int, workers: int
    ) -> None:
        if workers < 1:
            raise ValueError(f"ParallelBatches needs at least one worker, not {workers}")
        self.data, self.cfg, self.batch_size, self.seed, self.workers = data, cfg, batch_size, seed, workers
        self.start, self.drawn = 0, 0
        self._it: Iterator[Any] | None = None

    def state(self) -> dict:
        return {"parallel_workers": self.workers, "start": self.start + self.drawn}

    def set_state(self, s: dict) -> None:
        if not isinstance(s, dict) or s.get("parallel_workers") != self.workers:
            raise ValueError(
                f"the checkpoint's sampler was not a {self.workers}-worker stream; resume with the "
                "same --loader-workers or pass --no-resume"
            )
        self.start, self.drawn, self._it = int(s["start"]), 0, None

    def __call__(self) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        if self._it is None:
            stream = _BatchStream(self.data, self.cfg, self.batch_size, self.seed, self.start)
            loader = torch.utils.data.DataLoader(
                stream,
                batch_size=None,
                num_workers=self.workers,
                prefetch_factor=4,
                pin_memory=torch.cuda.is_available(),
            )
            self._it = iter(loader)
        self.drawn += 1
        return next(self._it)

    def close(self) -> None:
        """Stop the workers: dropping the loader's iterator shuts them down (one left to the interpreter's
        exit dies noisily in its pin-memory thread). A later call starts a stream at the step reached."""
        self.start, self.drawn, self._it = self.start + self.drawn, 0, None


def init_from(model: CenterDetector, weights: str | Path) -> dict[str, Any]:
    """Load trained detector weights into ``model``, which may be a grown copy of theirs.

    Every tensor of ``weights`` must exist in ``model`` with the same shape; tensors of the model
    that ``weights`` lacks must belong to the grown modules (extra residual blocks, the head
    conv), which start as the identity, so the model computes what ``weights`` computed.
    Returns the lineage for the manifest: the file's checksum and its own manifest's command.
    """
    weights = Path(weights)
    blob = load_checkpoint(weights)
    if blob is None or "state_dict" not in blob:
        raise ValueError(f"--init {weights}: not a detector weights file (no state_dict)")
    old = DetectorConfig.from_dict(blob["config"])
    new = model.cfg
    if (old.num_classes, old.widths, old.neck, old.stride, old.use_depth) != (
        new.num_classes,
        new.widths,
        new.neck,
        new.stride,
        new.use_depth,
    ):
        raise ValueError(
            f"--init {weights}: its architecture {old.to_dict()} is not a subset of {new.to_dict()}"
        )
    own = model.state_dict()
    for k, v in blob["state_dict"].items():
        if k not in own or own[k].shape != v.shape:
            raise ValueError(f"--init {weights}: tensor {k} {tuple(v.shape)} has no place in the grown model")
    missing = [k for k in own if k not in blob["state_dict"]]
    model.load_state_dict(blob["state_dict"], strict=False)
    lineage: dict[str, Any] = {
        "weights": str(weights),
        "sha256": sha256_file(weights),
        "config": old.to_dict(),
        "new_tensors": len(missing),
    }
    man = weights.with_suffix(".json")
    if man.exists():
        m = json.loads(man.read_text())
        lineage.update({k: m.get(k) for k in ("command", "train_config", "init")})
        d = m.get("data") or {}
        lineage["data_command"] = d.get("command") or [part.get("command") for part in d.get("parts", [])]
    return lineage


class Schedule(Protocol):
    """What the learning-rate schedule reads from a training config (the detector's, the reclassifier's)."""

    lr: float
    warmup: int
    steps: int


def lr_at(step: int, cfg: Schedule) -> float:
    """Linear warm-up over ``cfg.warmup`` steps, then cosine decay to 2% of ``cfg.lr``."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = (step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1)
    return cfg.lr * (0.02 + 0.98 * 0.5 * (1 + np.cos(np.pi * min(t, 1.0))))


def train_detector(
    cfg: TrainConfig,
    model_cfg: DetectorConfig | None = None,
    resume: bool = True,
    progress: bool = True,
    command: str = "",
    data: dict[str, np.ndarray] | None = None,
    ship: bool = True,
) -> dict[str, Any]:
    """Train; returns {"history": [...], "out": path, ...}. ``data`` overrides loading shards (tests)."""
    from tqdm import tqdm

    cfg = cfg.resolved()  # default paths filled in, as the checkpoint and manifest record them
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    model_cfg = model_cfg or DetectorConfig()
    data_manifests: list[dict[str, Any]] = []
    if data is None:
        data, data_manifests = load_datasets(cfg.data_spec, limit=cfg.limit_frames)
    if cfg.limit_frames is not None:
        keep = data["obj_frame"] < cfg.limit_frames
        data = {
            **{k: v[: cfg.limit_frames] for k, v in data.items() if not k.startswith("obj_")},
            **{k: v[keep] for k, v in data.items() if k.startswith("obj_")},
        }
    model = CenterDetector(model_cfg)
    lineage = init_from(model, cfg.init) if cfg.init else None
    precision = resolve_precision(cfg.precision, device)
    model = model.to(device, memory_format=torch.channels_last)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    batches = (
        ParallelBatches(data, model_cfg, cfg.batch_size, cfg.seed, cfg.loader_workers)
        if cfg.loader_workers
        else Batches(data, model_cfg, cfg.batch_size, cfg.seed)
    )
    work = cfg.work_path
    ckpt_path = work / "checkpoint.pt"
    step, history = (
        resume_training(ckpt_path, cfg.seed, model_cfg.to_dict(), model, opt, batches) if resume else (0, [])
    )
    t0 = time.time()
    model.train()
    bar = tqdm(total=cfg.steps, initial=step, desc="train detector", disable=not progress)
    running: dict[str, float] = {}
    while step < cfg.steps:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, cfg)
        x, tgt = batches()
        x = x.to(device, memory_format=torch.channels_last, non_blocking=True)
        tgt = {k: v.to(device, non_blocking=True) for k, v in tgt.items()}
        with torch.autocast(device.split(":")[0], dtype=torch.bfloat16, enabled=precision == "bf16"):
            out = model(x)
        losses = detector_loss({k: v.float() for k, v in out.items()}, tgt)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        step += 1
        for k, v in losses.items():
            running[k] = running.get(k, 0.0) + v.item()
        if step % cfg.log_every == 0 or step == cfg.steps:
            n = cfg.log_every if step % cfg.log_every == 0 else step % cfg.log_every
            history.append({"step": step, **{k: v / n for k, v in running.items()}})
            running = {}
            bar.set_postfix(loss=f"{history[-1]['total']:.3f}", heat=f"{history[-1]['heat']:.3f}")
        bar.update(1)
        if step % cfg.ckpt_every == 0 or step == cfg.steps:
            save_checkpoint(
                ckpt_path,
                model=model.state_dict(),
                optimizer=opt.state_dict(),
                sampler=batches.state(),
                torch_rng=torch.get_rng_state(),
                step=step,
                history=history,
                train_config=asdict(cfg),
                model_config=model_cfg.to_dict(),
            )
            save_loss_curve(history, work / "loss.png", f"detector ({step} steps, batch {cfg.batch_size})")
    bar.close()
    if isinstance(batches, ParallelBatches):
        batches.close()
    result: dict[str, Any] = {
        "history": history,
        "seconds": round(time.time() - t0, 1),
        "steps": step,
        "device": device,
        "precision": precision,
        "work_dir": str(work),
    }
    if ship:
        curve = ship_weights(cfg.out_path, model, model_cfg.to_dict(), work / "loss.png", "detector_loss.png")
        result["manifest"] = write_manifest(
            cfg.out_path,
            command=command,
            data=dataset_record(cfg.data_spec, data, data_manifests, TRAIN_ROOMS),
            metrics={"train_loss_final": history[-1] if history else None},
            train_config={**asdict(cfg), "precision_used": precision, "device_used": device},
            model_config=model_cfg.to_dict(),
            parameters=int(sum(p.numel() for p in model.parameters())),
            **({"init": lineage} if lineage else {}),
            loss_curve=curve,
        )
        result["out"] = cfg.out_path
    return result


__all__ = [
    "Batches",
    "ParallelBatches",
    "train_detector",
    "lr_at",
    "init_from",
]
