"""``tidee train depth`` (options: ``config.DepthTrainConfig``): fits ``DepthNet`` on the detector
frames of the training rooms (``tidee gen detection``).

Training is reproducible from its seed (batch order and augmentation are functions of the
seed and the step number) and resumable from the checkpoint in ``--work-dir``.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tidee.agent.learning import (
    dataset_record,
    load_checkpoint,
    pick_device,
    resolve_precision,
    save_checkpoint,
    save_loss_curve,
    write_manifest,
)
from tidee.agent.perception.depth.config import DepthTrainConfig
from tidee.agent.perception.depth.eval import evaluate_depth, heldout_frames
from tidee.agent.perception.depth.model import VALID_MAX, VALID_MIN, DepthEstimator, DepthNet

# --- loss and data -------------------------------------------------------------------------------


def depth_loss(
    log_pred: torch.Tensor, depth: torch.Tensor, grad_weight: float = 0.5
) -> dict[str, torch.Tensor]:
    """L1 on log depth over valid pixels (absolute, so the scale counts) + multi-scale gradient matching.

    The gradient term (as in MiDaS) penalises x/y differences of the log-depth residual at
    strides 1, 2 and 4, which sharpens edges at almost no cost.
    """
    valid = (depth > VALID_MIN) & (depth < VALID_MAX)
    n = valid.sum().clamp(min=1)
    residual = torch.where(valid, log_pred - depth.clamp(min=VALID_MIN).log(), torch.zeros_like(log_pred))
    l1 = residual.abs().sum() / n
    grad = log_pred.new_zeros(())
    for s in (1, 2, 4):
        r, m = residual[:, ::s, ::s], valid[:, ::s, ::s]
        mx = m[:, :, 1:] & m[:, :, :-1]
        my = m[:, 1:, :] & m[:, :-1, :]
        gx = (r[:, :, 1:] - r[:, :, :-1]).abs() * mx
        gy = (r[:, 1:, :] - r[:, :-1, :]).abs() * my
        grad = grad + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp(min=1)
    grad = grad / 3
    return {"loss": l1 + grad_weight * grad, "l1_log": l1, "grad": grad}


def batch_indices(n: int, batch_size: int, seed: int, step: int) -> np.ndarray:
    """Frames of training step ``step``: consecutive slices of one seeded permutation per epoch."""
    pos = np.arange(step * batch_size, (step + 1) * batch_size)
    out = np.empty(batch_size, np.int64)
    for epoch in np.unique(pos // n):
        perm = np.random.default_rng([seed, int(epoch)]).permutation(n)
        sel = pos // n == epoch
        out[sel] = perm[pos[sel] % n]
    return out


def augment(
    rgb: torch.Tensor, depth: torch.Tensor, seed: int, step: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Horizontal flip and mild colour jitter, drawn from (seed, step): the same on a resumed run."""
    rng = np.random.default_rng([seed, step, 1])
    b = rgb.shape[0]
    flip = torch.from_numpy(rng.random(b) < 0.5).to(rgb.device)
    bright, contrast, sat = (
        torch.from_numpy(rng.uniform(0.8, 1.2, b).astype(np.float32)).to(rgb.device).view(b, 1, 1, 1)
        for _ in range(3)
    )
    rgb = torch.where(flip.view(b, 1, 1, 1), rgb.flip(-1), rgb)
    depth = torch.where(flip.view(b, 1, 1), depth.flip(-1), depth)
    rgb = rgb * bright
    mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
    rgb = (rgb - mean) * contrast + mean
    gray = rgb.mean(dim=1, keepdim=True)
    rgb = (rgb - gray) * sat + gray
    return rgb.clamp(0, 1), depth


def to_tensors(rgb: np.ndarray, depth: np.ndarray, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 N x H x W x 3 and float16 N x H x W -> float32 N x 3 x H x W in [0, 1], depth N x H x W."""
    x = torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(0, 3, 1, 2).float() / 255.0
    d = torch.from_numpy(np.ascontiguousarray(depth)).to(device).float()
    return x, d


def lr_at(step: int, steps: int, lr: float, warmup: int = 50) -> float:
    """Linear warm-up, then cosine decay to 1% of ``lr``."""
    warm = min(1.0, (step + 1) / max(1, min(warmup, steps // 10)))
    return lr * warm * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(step, steps) / max(1, steps))))


def train_step(
    model: DepthNet,
    opt: torch.optim.Optimizer,
    rgb: torch.Tensor,
    depth: torch.Tensor,
    lr: float,
    precision: str = "fp32",
) -> dict[str, float]:
    """One AdamW step; ``precision`` "bf16" runs the network under bf16 autocast (the loss in fp32)."""
    for group in opt.param_groups:
        group["lr"] = lr
    model.train()
    with torch.autocast(rgb.device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
        log_pred = model.log_depth(rgb)
    losses = depth_loss(log_pred.float(), depth)
    opt.zero_grad(set_to_none=True)
    losses["loss"].backward()
    opt.step()
    return {k: v.detach().item() for k, v in losses.items()}


# --- training ------------------------------------------------------------------------------------


def train_depth(
    cfg: DepthTrainConfig,
    progress: bool = True,
    command: str = "",
    docs_png: str | Path | None = None,
) -> dict[str, Any]:
    """Train ``DepthNet`` on the frames under ``cfg.data``; write weights + manifest; return a summary.

    The checkpoint ``work_dir/checkpoint.pt`` is rewritten every ``checkpoint_every`` steps;
    ``resume`` continues from it (same seed, batch size, lr, steps and widths, or a
    ValueError). At the end the model is scored on ``eval_set`` (held-out test rooms; None
    skips it) and the loss curve is written to ``work_dir/depth_loss.png`` (and copied to
    ``docs_png`` when given).
    """
    from tqdm import tqdm

    from tidee.agent.perception.detector.data import TRAIN_ROOMS, load_datasets

    steps, batch_size, lr, seed, widths = cfg.steps, cfg.batch_size, cfg.lr, cfg.seed, cfg.widths
    log_every, checkpoint_every, eval_set = cfg.log_every, cfg.checkpoint_every, cfg.eval_set
    if steps < 1 or batch_size < 1 or lr <= 0:
        raise ValueError(f"need steps >= 1, batch_size >= 1 and lr > 0, got {steps}, {batch_size}, {lr}")
    out_weights, work_dir = cfg.out_path, cfg.work_path
    device = pick_device(cfg.device)
    t0 = time.time()
    frames, manifests = load_datasets(cfg.data_spec)  # ValueError naming a directory without a manifest
    data = dataset_record(cfg.data_spec, frames, manifests, TRAIN_ROOMS)
    rgb_all, depth_all = frames["rgb"], frames["depth"]
    n = len(rgb_all)
    if n < batch_size:
        raise ValueError(f"{cfg.data_spec} has {n} frames, fewer than one batch of {batch_size}")

    run = {
        "seed": seed,
        "steps": steps,
        "batch_size": batch_size,
        "lr": lr,
        "widths": list(widths),
        "context": cfg.context,
        "precision": resolve_precision(cfg.precision, device),
        "frames": n,
    }
    precision = run["precision"]
    torch.manual_seed(seed)  # the initial weights; batches and augmentation draw from (seed, step)
    model = DepthNet(widths, context=cfg.context).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    ckpt_path = work_dir / "checkpoint.pt"
    start, history, sums = 0, [], {}
    if cfg.resume:
        ckpt = load_checkpoint(ckpt_path)
        if ckpt is None:
            raise FileNotFoundError(f"--resume: no checkpoint at {ckpt_path}; run without --resume to start")
        if ckpt["run"] != run:
            diff = {k: (ckpt["run"].get(k), v) for k, v in run.items() if ckpt["run"].get(k) != v}
            raise ValueError(
                f"--resume: {ckpt_path} was written by a different run (checkpoint vs now: "
                f"{diff}); use the same options or another --work-dir"
            )
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["opt"])
        start, history, sums = ckpt["step"], ckpt["history"], ckpt["sums"]

    def checkpoint(step: int) -> None:
        save_checkpoint(
            ckpt_path,
            model=model.state_dict(),
            opt=opt.state_dict(),
            step=step,
            history=history,
            sums=sums,
            run=run,
        )

    bar = tqdm(range(start, steps), desc="train depth", disable=not progress, initial=start, total=steps)
    for step in bar:
        idx = batch_indices(n, batch_size, seed, step)
        rgb, depth = augment(*to_tensors(rgb_all[idx], depth_all[idx], device), seed, step)
        losses = train_step(model, opt, rgb, depth, lr_at(step, steps, lr), precision)
        for k, v in losses.items():
            sums[k] = sums.get(k, 0.0) + v
        if (step + 1) % log_every == 0 or step + 1 == steps:
            count = (step + 1) - (history[-1]["step"] if history else 0)
            history.append({"step": step + 1, **{k: v / count for k, v in sums.items()}})
            sums = {}
            bar.set_postfix(loss=f"{history[-1]['loss']:.4f}")
        if (step + 1) % checkpoint_every == 0 or step + 1 == steps:
            checkpoint(step + 1)
    bar.close()
    train_seconds = time.time() - t0

    model = model.cpu().eval()
    out_weights.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": model.state_dict(), "config": model.config()}, out_weights)
    work_dir.mkdir(parents=True, exist_ok=True)
    loss_png = work_dir / "depth_loss.png"
    save_loss_curve(history, loss_png, f"depth net: {n} frames, batch {batch_size}, lr {lr}, seed {seed}")
    if docs_png is not None and loss_png.exists():
        Path(docs_png).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(loss_png, docs_png)

    metrics: dict[str, Any] = {}
    if eval_set is not None:
        held_out = heldout_frames("test", eval_set, progress=progress)
        metrics = {
            **evaluate_depth(DepthEstimator(model), held_out),
            "eval_set": {"split": "test", **asdict(eval_set)},
        }
    manifest = write_manifest(
        out_weights,
        command,
        data,
        metrics,
        train=run,
        device=device,
        train_seconds=round(train_seconds, 1),
        final_loss=history[-1]["loss"] if history else None,
    )
    return {
        "weights": str(out_weights),
        "loss_png": str(loss_png),
        "final_loss": manifest["final_loss"],
        "metrics": metrics,
        "train_seconds": manifest["train_seconds"],
    }


__all__ = [
    "augment",
    "batch_indices",
    "depth_loss",
    "lr_at",
    "to_tensors",
    "train_depth",
    "train_step",
]
