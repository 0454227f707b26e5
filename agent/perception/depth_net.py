"""Depth from RGB: a small U-Net for the paper's "+est. depth" setting.

``DepthNet`` maps an RGB frame to metric depth along the optical axis (metres, bounded to
``[min_depth, max_depth]``). It is small enough for the agent's CPU budget: about 8 ms per
256^2 frame on one thread with BatchNorm folded into the convolutions (``DepthEstimator``
does that when it loads the weights).

``tidee train depth`` fits it on the detector frames of the training rooms
(``tidee gen detection``); ``tidee eval depth`` measures it on held-out test (or val)
rooms rendered on the fly. Training is reproducible from its seed (batch order and
augmentation are functions of the seed and the step number) and resumable from the
checkpoint in ``--work-dir``.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from tidee.agent.learning import (
    WEIGHTS_DIR,
    load_checkpoint,
    pick_device,
    read_manifest,
    save_checkpoint,
    save_loss_curve,
    write_manifest,
)

DEFAULT_WEIGHTS = WEIGHTS_DIR / "depth.pt"
DOCS_LOSS_PNG = Path(__file__).resolve().parents[2] / "docs" / "models" / "depth_loss.png"
RESOLUTION = 256  # the network's input size; other frames are resized to it
VALID_MIN, VALID_MAX = 0.05, 8.0  # metres scored; 0 is "nothing", the far plane (20 m) shows through doors
TYPICAL_DEPTH = 1.0  # metres: about the median of the training frames (mostly near views)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class EvalSet:
    """The held-out frames a depth model is scored on (training's final eval and ``tidee eval depth``)."""

    rooms_per_type: int = 5
    messes: int = 1
    frames_per_walk: int = 5
    seed: int = 7


# --- the network ---------------------------------------------------------------------------------


def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)
    )


class DepthNet(nn.Module):
    """RGB in [0, 1] (B x 3 x H x W, H and W multiples of 16) -> depth in metres (B x H x W).

    Encoder: one stride-2 stage per entry of ``widths`` (1/2 ... 1/16), two 3x3 conv-BN-ReLU
    each. Decoder: bilinear x2, a 1x1 projection added to the skip of the same scale, one
    3x3 conv-BN-ReLU. The head predicts at 1/2 resolution and is upsampled bilinearly; its
    output is squashed to log depth in [log min_depth, log max_depth].
    """

    def __init__(
        self,
        widths: tuple[int, ...] | list[int] = (16, 24, 48, 96),
        min_depth: float = 0.1,
        max_depth: float = 8.0,
    ):
        super().__init__()
        if len(widths) != 4:
            raise ValueError(f"widths needs 4 entries (scales 1/2 to 1/16), got {list(widths)}")
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        self.widths = tuple(int(w) for w in widths)
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        w = self.widths
        self.encoder = nn.ModuleList(
            nn.Sequential(_conv_bn_relu(c_in, c_out, 2), _conv_bn_relu(c_out, c_out))
            for c_in, c_out in zip((3,) + w[:-1], w)
        )
        self.lateral = nn.ModuleList(nn.Conv2d(w[i + 1], w[i], 1) for i in range(len(w) - 1))
        self.decoder = nn.ModuleList(_conv_bn_relu(w[i], w[i]) for i in range(len(w) - 1))
        self.head = nn.Conv2d(w[0], 1, 3, 1, 1)
        # Start at a typical room depth, not the geometric middle of the range (0.9 m).
        start = (math.log(TYPICAL_DEPTH) - math.log(min_depth)) / (math.log(max_depth) - math.log(min_depth))
        nn.init.constant_(self.head.bias, math.log(start / (1 - start)))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def config(self) -> dict[str, Any]:
        return {"widths": list(self.widths), "min_depth": self.min_depth, "max_depth": self.max_depth}

    def log_depth(self, rgb: torch.Tensor) -> torch.Tensor:
        if rgb.shape[-1] % 16 or rgb.shape[-2] % 16:
            raise ValueError(f"DepthNet needs H and W divisible by 16, got {tuple(rgb.shape[-2:])}")
        x = (rgb - self.mean) / self.std
        skips = []
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        for i in range(len(skips) - 2, -1, -1):
            up = F.interpolate(self.lateral[i](x), scale_factor=2, mode="bilinear", align_corners=False)
            x = self.decoder[i](up + skips[i])
        x = F.interpolate(self.head(x), scale_factor=2, mode="bilinear", align_corners=False)[:, 0]
        lo, hi = math.log(self.min_depth), math.log(self.max_depth)
        return lo + (hi - lo) * torch.sigmoid(x)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.log_depth(rgb).exp()

    def fused(self) -> DepthNet:
        """An inference copy with each BatchNorm folded into its convolution (eval mode only)."""
        from torch.nn.utils.fusion import fuse_conv_bn_eval

        net = copy.deepcopy(self).eval()
        for block in net.modules():
            if isinstance(block, nn.Sequential) and len(block) == 3 and isinstance(block[1], nn.BatchNorm2d):
                block[0] = fuse_conv_bn_eval(block[0], block[1])
                block[1] = nn.Identity()
        return net


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
    model: DepthNet, opt: torch.optim.Optimizer, rgb: torch.Tensor, depth: torch.Tensor, lr: float
) -> dict[str, float]:
    for group in opt.param_groups:
        group["lr"] = lr
    model.train()
    losses = depth_loss(model.log_depth(rgb), depth)
    opt.zero_grad(set_to_none=True)
    losses["loss"].backward()
    opt.step()
    return {k: v.detach().item() for k, v in losses.items()}


# --- training ------------------------------------------------------------------------------------


def _data_summary(data_dir: Path) -> dict[str, Any]:
    man_path = data_dir / "manifest.json"
    if not man_path.exists():
        raise FileNotFoundError(
            f"no manifest.json in {data_dir}: generate training frames with "
            f"`tidee gen detection --out {data_dir}` (or let a running one finish)"
        )
    manifest = json.loads(man_path.read_text())
    return {
        "dir": str(data_dir),
        "command": manifest.get("command", ""),
        "rooms": len(manifest.get("rooms", [])),
        "frames": manifest.get("frames"),
    }


def train_depth(
    data_dir: str | Path = "data/detection",
    out_weights: str | Path = DEFAULT_WEIGHTS,
    steps: int = 2000,
    batch_size: int = 16,
    lr: float = 2e-3,
    seed: int = 0,
    device: str = "auto",
    resume: bool = False,
    progress: bool = True,
    command: str = "",
    work_dir: str | Path = "runs/depth",
    checkpoint_every: int = 100,
    log_every: int = 10,
    eval_set: EvalSet | None = EvalSet(),
    docs_png: str | Path | None = None,
    widths: tuple[int, ...] = (16, 24, 48, 96),
) -> dict[str, Any]:
    """Train ``DepthNet`` on the frames under ``data_dir``; write weights + manifest; return a summary.

    The checkpoint ``work_dir/checkpoint.pt`` is rewritten every ``checkpoint_every`` steps;
    ``resume`` continues from it (same seed, batch size, lr, steps and widths, or a
    ValueError). At the end the model is scored on ``eval_set`` (held-out test rooms; None
    skips it) and the loss curve is written to ``work_dir/depth_loss.png`` (and copied to
    ``docs_png`` when given).
    """
    from tqdm import tqdm

    from tidee.agent.perception.dataset import load_shards

    if steps < 1 or batch_size < 1 or lr <= 0:
        raise ValueError(f"need steps >= 1, batch_size >= 1 and lr > 0, got {steps}, {batch_size}, {lr}")
    data_dir, out_weights, work_dir = Path(data_dir), Path(out_weights), Path(work_dir)
    data = _data_summary(data_dir)
    device = pick_device(device)
    t0 = time.time()
    frames = load_shards(data_dir)
    rgb_all, depth_all = frames["rgb"], frames["depth"]
    n = len(rgb_all)
    if n < batch_size:
        raise ValueError(f"{data_dir} has {n} frames, fewer than one batch of {batch_size}")

    run = {
        "seed": seed,
        "steps": steps,
        "batch_size": batch_size,
        "lr": lr,
        "widths": list(widths),
        "frames": n,
    }
    torch.manual_seed(seed)  # the initial weights; batches and augmentation draw from (seed, step)
    model = DepthNet(widths).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    ckpt_path = work_dir / "checkpoint.pt"
    start, history, sums = 0, [], {}
    if resume:
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
        losses = train_step(model, opt, rgb, depth, lr_at(step, steps, lr))
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


# --- inference -----------------------------------------------------------------------------------


class DepthModel(Protocol):
    def predict(self, rgb: np.ndarray) -> np.ndarray: ...


class DepthEstimator:
    """A trained ``DepthNet`` behind ``predict(rgb uint8 HxWx3) -> float32 HxW metres``."""

    def __init__(self, model: DepthNet, device: str = "cpu"):
        self.device = device
        self.net = model.fused().to(device).to(memory_format=torch.channels_last)

    @classmethod
    def load(cls, path: str | Path | None = None, device: str = "cpu") -> DepthEstimator:
        """Shipped weights (``agent/weights/depth.pt`` by default), checked against their manifest."""
        path = Path(path) if path is not None else DEFAULT_WEIGHTS
        if not path.exists():
            raise FileNotFoundError(
                f"no depth weights at {path}: train them with `tidee train depth` "
                "(see the README) or pass another path"
            )
        read_manifest(path)  # FileNotFoundError without a manifest, ValueError on a checksum mismatch
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or "state_dict" not in state or "config" not in state:
            raise ValueError(f"{path} is not a depth network file (expected a dict with state_dict, config)")
        model = DepthNet(**state["config"])
        model.load_state_dict(state["state_dict"])
        return cls(model, pick_device(device))

    @torch.inference_mode()
    def predict(self, rgb: np.ndarray) -> np.ndarray:
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"predict wants a uint8 H x W x 3 image, got {rgb.dtype} {rgb.shape}")
        import cv2

        h, w = rgb.shape[:2]
        resize = (h, w) != (RESOLUTION, RESOLUTION)
        if resize:
            interp = cv2.INTER_AREA if min(h, w) > RESOLUTION else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (RESOLUTION, RESOLUTION), interpolation=interp)
        x = torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device).permute(2, 0, 1)[None].float() / 255.0
        depth = self.net(x.contiguous(memory_format=torch.channels_last))[0].float().cpu().numpy()
        if resize:
            depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_LINEAR)
        return depth.astype(np.float32, copy=False)


def time_inference(estimator: DepthEstimator, repeats: int = 30, threads: int = 1) -> dict[str, float]:
    """Median and best ms per 256^2 frame on ``threads`` CPU threads (after a warm-up)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rgb = np.random.default_rng(0).integers(0, 256, (RESOLUTION, RESOLUTION, 3), dtype=np.uint8)
        for _ in range(5):
            estimator.predict(rgb)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            estimator.predict(rgb)
            times.append(1000 * (time.perf_counter() - t))
    finally:
        torch.set_num_threads(previous)
    return {
        "threads": threads,
        "median_ms": round(float(np.median(times)), 2),
        "min_ms": round(min(times), 2),
    }


# --- evaluation ----------------------------------------------------------------------------------


def heldout_frames(split: str, eval_set: EvalSet, progress: bool = True) -> dict[str, np.ndarray]:
    """The ``eval_set`` frames of the val or test rooms (``dataset.held_out_frames``)."""
    from tidee.agent.perception.dataset import held_out_frames

    return held_out_frames(
        split,
        rooms_per_type=eval_set.rooms_per_type,
        messes=eval_set.messes,
        frames_per_walk=eval_set.frames_per_walk,
        seed=eval_set.seed,
        progress=progress,
    )


def evaluate_depth(estimator: DepthModel, frames: dict[str, np.ndarray]) -> dict[str, Any]:
    """Abs rel, RMSE (m), delta < 1.25 over each frame's valid pixels; mean over frames and per room type."""
    per_frame: list[tuple[str, float, float, float]] = []
    rooms = frames.get("frame_room", np.array(["?"] * len(frames["rgb"])))
    for rgb, depth, room in zip(frames["rgb"], frames["depth"], rooms):
        d = depth.astype(np.float32)
        valid = (d > VALID_MIN) & (d < VALID_MAX)
        if not valid.any():
            continue
        est = np.maximum(np.asarray(estimator.predict(rgb), np.float32)[valid], 1e-3)
        d = d[valid]
        ratio = np.maximum(est / d, d / est)
        per_frame.append(
            (
                str(room).split(":")[0],
                float(np.mean(np.abs(est - d) / d)),
                float(np.sqrt(np.mean((est - d) ** 2))),
                float(np.mean(ratio < 1.25)),
            )
        )
    if not per_frame:
        raise ValueError("no frame has valid depth pixels to score")
    by_type: dict[str, list[float]] = {}
    for rt, abs_rel, _, _ in per_frame:
        by_type.setdefault(rt, []).append(abs_rel)
    return {
        "frames": len(per_frame),
        "abs_rel": round(float(np.mean([f[1] for f in per_frame])), 4),
        "rmse": round(float(np.mean([f[2] for f in per_frame])), 4),
        "delta1": round(float(np.mean([f[3] for f in per_frame])), 4),
        "abs_rel_by_room_type": {rt: round(float(np.mean(v)), 4) for rt, v in sorted(by_type.items())},
    }


def colorize_depth(depth: np.ndarray, max_depth: float = 6.0) -> np.ndarray:
    """BGR uint8 (turbo colour map, near = blue); pixels without depth are black."""
    import cv2

    scaled = np.clip(depth / max_depth * 255, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    img[depth <= VALID_MIN] = 0
    return img


def save_examples(estimator: DepthModel, frames: dict[str, np.ndarray], png: str | Path, n: int = 6) -> Path:
    """A PNG grid, one row per frame (spread over the set): RGB | true depth | estimated depth."""
    import cv2

    total = len(frames["rgb"])
    picks = np.unique(np.linspace(0, total - 1, min(n, total)).round().astype(int))
    rows = []
    for i in picks:
        rgb = frames["rgb"][i]
        true = frames["depth"][i].astype(np.float32)
        est = np.asarray(estimator.predict(rgb), np.float32)
        row = np.concatenate(
            [cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), colorize_depth(true), colorize_depth(est)], 1
        )
        label = str(frames["frame_room"][i]) if "frame_room" in frames else str(i)
        cv2.putText(row, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    header = np.zeros((18, rows[0].shape[1], 3), np.uint8)
    w = rgb.shape[1]
    for k, text in enumerate(("RGB", "true depth", "estimated depth")):
        cv2.putText(
            header, text, (k * w + 4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA
        )
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(png), np.concatenate([header] + rows, 0))
    return png


def metrics_markdown(result: dict[str, Any]) -> str:
    m, e = result["metrics"], result["eval_set"]
    lines = [
        f"# Depth from RGB: {result['split']} rooms",
        "",
        f"Weights `{result['weights']}`; {m['frames']} frames: {e['rooms_per_type']} rooms per type, "
        f"tidy + {e['messes']} messy configurations each, {e['frames_per_walk']} frames per walk, "
        f"seed {e['seed']}.",
        "",
        "| metric | value |",
        "|---|---|",
        f"| abs rel | {m['abs_rel']:.3f} |",
        f"| RMSE (m) | {m['rmse']:.3f} |",
        f"| delta < 1.25 | {m['delta1']:.3f} |",
    ]
    lines += [f"| abs rel, {rt} | {v:.3f} |" for rt, v in m["abs_rel_by_room_type"].items()]
    if "speed" in result:
        s = result["speed"]
        lines += [f"| ms / frame (1 CPU thread, median) | {s['median_ms']:.1f} |"]
    lines += ["", f"Command: `{result['command']}`", ""]
    return "\n".join(lines)


__all__ = [
    "DepthNet",
    "DepthEstimator",
    "EvalSet",
    "depth_loss",
    "train_depth",
    "evaluate_depth",
    "save_examples",
    "heldout_frames",
    "time_inference",
    "metrics_markdown",
    "DEFAULT_WEIGHTS",
    "DOCS_LOSS_PNG",
]
