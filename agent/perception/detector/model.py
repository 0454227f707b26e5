"""The RGB-D detector: a CenterNet-style dense head on a small backbone, with an OOP head.

Input: RGB (normalised) and depth (metres / 5) at 256 x 256. Output at stride 4 (64 x 64):
  heat   C  class-centre heatmaps (focal loss, Gaussian targets)
  size   2  log box width / height in input pixels
  off    2  sub-cell offset of the centre
  oop    1  logit of P(out of place) for the object centred there (the paper's dDETR-OOP head)
and a ``feat`` map (the shared neck) from which each detection takes its feature vector,
the per-object feature that the OOP classifiers and the rGCN nodes read.

Everything here is torch-only; numpy target encoding and decoding sit beside the model so
the training code, the evaluation and the agent all use the same ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tidee.agent.perception import PEAK_MODES
from tidee.agent.perception.detector.config import DetectorConfig

DEPTH_SCALE = 5.0
RGB_MEAN = (0.5, 0.5, 0.5)
RGB_STD = (0.25, 0.25, 0.25)


def cbr(cin: int, cout: int, stride: int = 1, k: int = 3) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)
    )


def fold_batchnorm(module: nn.Module) -> nn.Module:
    """``module`` (in eval mode) with every BatchNorm2d that follows a Conv2d in a Sequential
    folded into the convolution's weights and bias, and replaced by an identity, in place.

    The same function to within float rounding (about 1e-5 on the heatmap logits), one pass
    over each feature map fewer: about 15 % of the detector's time per frame on one core.
    For inference only: a folded module must not be trained again."""
    if module.training:
        raise ValueError("fold_batchnorm folds running statistics: call .eval() first")
    for seq in [m for m in module.modules() if isinstance(m, nn.Sequential)]:
        for i in range(len(seq) - 1):
            conv, bn = seq[i], seq[i + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[i] = torch.nn.utils.fusion.fuse_conv_bn_eval(conv, bn)
                seq[i + 1] = nn.Identity()
    return module


class Residual(nn.Module):
    def __init__(self, c: int, identity: bool = False) -> None:
        super().__init__()
        self.a = cbr(c, c)
        conv, bn = nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c)
        self.b = nn.Sequential(conv, bn)
        if identity:  # the branch's last BN scale at 0: x is post-ReLU, so relu(x + 0) == x
            nn.init.zeros_(bn.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.b(self.a(x)), inplace=True)


def identity_dw_block(c: int) -> nn.Sequential:
    """Depthwise 3x3 + pointwise 1x1 (with biases, no BN) + ReLU, initialised to the identity
    on non-negative input: a head layer that can be added to trained weights without changing them."""
    dw = nn.Conv2d(c, c, 3, 1, 1, groups=c)
    pw = nn.Conv2d(c, c, 1)
    assert dw.bias is not None and pw.bias is not None  # Conv2d has a bias unless told otherwise
    with torch.no_grad():
        dw.weight.zero_()
        dw.weight[:, 0, 1, 1] = 1.0
        dw.bias.zero_()
        pw.weight.copy_(torch.eye(c).view(c, c, 1, 1))
        pw.bias.zero_()
    return nn.Sequential(dw, pw, nn.ReLU(inplace=True))


class CenterDetector(nn.Module):
    def __init__(self, cfg: DetectorConfig) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.widths
        cin = 4 if cfg.use_depth else 3
        self.stem = nn.Sequential(
            cbr(cin, w[0], 2),
            cbr(w[0], w[1], 2),
            cbr(w[1], w[1]),  # /4
            *[Residual(w[1], identity=True) for _ in range(cfg.extra_s4)],
        )
        extra = cfg.extra_blocks
        self.s8 = nn.Sequential(
            cbr(w[1], w[2], 2),
            Residual(w[2]),  # /8
            *[Residual(w[2], identity=True) for _ in range(extra[0])],
        )
        self.s16 = nn.Sequential(
            cbr(w[2], w[3], 2),
            Residual(w[3]),  # /16
            *[Residual(w[3], identity=True) for _ in range(extra[1])],
        )
        self.s32 = nn.Sequential(
            cbr(w[3], w[4], 2),
            Residual(w[4]),
            Residual(w[4]),  # /32
            *[Residual(w[4], identity=True) for _ in range(extra[2])],
        )
        n = cfg.neck
        self.lat = nn.ModuleList([nn.Conv2d(c, n, 1) for c in (w[1], w[2], w[3], w[4])])
        self.smooth8 = cbr(n, n)
        # at stride 4 every MAC counts: a depthwise-separable smoothing conv, heads read it directly
        self.smooth4 = nn.Sequential(
            nn.Conv2d(n, n, 3, 1, 1, groups=n, bias=False),
            nn.BatchNorm2d(n),
            nn.Conv2d(n, n, 1, bias=False),
            nn.BatchNorm2d(n),
            nn.ReLU(inplace=True),
        )
        self.head_conv = identity_dw_block(n) if cfg.head_conv else nn.Identity()
        self.heat = nn.Conv2d(n, cfg.num_classes, 1)
        self.box = nn.Conv2d(n, 5, 1)  # size (2), offset (2), oop (1)
        assert self.heat.bias is not None
        nn.init.constant_(self.heat.bias, -4.6)  # prior 0.01, as CenterNet / RetinaNet

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        c4 = self.stem(x)
        c8 = self.s8(c4)
        c16 = self.s16(c8)
        c32 = self.s32(c16)
        p = self.lat[3](c32)
        p = self.lat[2](c16) + F.interpolate(p, scale_factor=2, mode="nearest")
        p = self.smooth8(self.lat[1](c8) + F.interpolate(p, scale_factor=2, mode="nearest"))
        feat = self.smooth4(self.lat[0](c4) + F.interpolate(p, scale_factor=2, mode="nearest"))
        h = self.head_conv(feat)
        b = self.box(h)
        return {"heat": self.heat(h), "size": b[:, 0:2], "off": b[:, 2:4], "oop": b[:, 4:5], "feat": feat}


def preprocess(rgb: np.ndarray, depth: np.ndarray | None, use_depth: bool = True) -> torch.Tensor:
    """uint8 BxHxWx3 (+ float BxHxW metres) -> float tensor Bx(3|4)xHxW."""
    # copies: frames decoded from messages are read-only buffers, which torch must not alias
    x = torch.from_numpy(np.array(rgb, dtype=np.uint8)).permute(0, 3, 1, 2).float().div_(255.0)
    mean = torch.tensor(RGB_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(RGB_STD).view(1, 3, 1, 1)
    x = (x - mean) / std
    if use_depth:
        if depth is None:
            raise ValueError("this detector was trained on RGB-D; pass depth")
        d = torch.from_numpy(np.array(depth, dtype=np.float32)).unsqueeze(1) / DEPTH_SCALE
        x = torch.cat([x, d.clamp_(0, 2)], 1)
    return x


# ------------------------------------------------------------------ targets
def gaussian_radius(h: float, w: float, min_overlap: float = 0.7) -> float:
    """CenterNet's radius: the centre may move this far and the box still has IoU >= min_overlap."""
    a1, b1, c1 = 1, h + w, w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2, b2, c2 = 4, 2 * (h + w), (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3, b3, c3 = 4 * min_overlap, -2 * min_overlap * (h + w), (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def draw_gaussian(heat: np.ndarray, cx: int, cy: int, radius: int) -> None:
    d = 2 * radius + 1
    sigma = d / 6
    ys, xs = np.ogrid[-radius : radius + 1, -radius : radius + 1]
    g = np.exp(-(xs * xs + ys * ys) / (2 * sigma * sigma))
    H, W = heat.shape
    left, r = min(cx, radius), min(W - cx, radius + 1)
    t, b = min(cy, radius), min(H - cy, radius + 1)
    patch = heat[cy - t : cy + b, cx - left : cx + r]
    np.maximum(patch, g[radius - t : radius + b, radius - left : radius + r], out=patch)


def encode_targets(
    boxes: np.ndarray,
    classes: np.ndarray,
    oop: np.ndarray,
    num_classes: int,
    size: int = 256,
    stride: int = 4,
    max_objs: int = 64,
) -> dict[str, np.ndarray]:
    """Dense CenterNet targets for one frame; boxes in input pixels (x0, y0, x1, y1)."""
    out = size // stride
    heat = np.zeros((num_classes, out, out), np.float32)
    ind = np.zeros(max_objs, np.int64)
    reg = np.zeros((max_objs, 4), np.float32)  # log w, log h, off x, off y
    oopt = np.zeros(max_objs, np.float32)
    msk = np.zeros(max_objs, np.float32)
    order: np.ndarray | list[int] = (
        np.argsort(-(boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]))[:max_objs]
        if len(boxes)
        else []
    )
    for k, i in enumerate(order):
        x0, y0, x1, y1 = boxes[i]
        w, h = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
        cx, cy = (x0 + x1) / 2 / stride, (y0 + y1) / 2 / stride
        ix, iy = min(int(cx), out - 1), min(int(cy), out - 1)
        r = max(0, int(gaussian_radius(h / stride, w / stride)))
        draw_gaussian(heat[int(classes[i])], ix, iy, r)
        ind[k] = iy * out + ix
        reg[k] = (math.log(w), math.log(h), cx - ix, cy - iy)
        oopt[k] = float(oop[i])
        msk[k] = 1.0
    return {"heat": heat, "ind": ind, "reg": reg, "oop": oopt, "mask": msk}


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4), normalised by #centres."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    neg = 1 - pos
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p**2 * (1 - target) ** 4 * neg
    n = pos.sum().clamp(min=1)
    return -(pos_loss.sum() + neg_loss.sum()) / n


def gather(x: torch.Tensor, ind: torch.Tensor) -> torch.Tensor:
    """B x C x H x W at flat indices B x K -> B x K x C."""
    b, c = x.shape[:2]
    flat = x.view(b, c, -1)
    return flat.gather(2, ind.unsqueeze(1).expand(b, c, ind.shape[1])).permute(0, 2, 1)


def detector_loss(
    out: dict[str, torch.Tensor],
    tgt: dict[str, torch.Tensor],
    w_size: float = 0.1,
    w_off: float = 1.0,
    w_oop: float = 1.0,
) -> dict[str, torch.Tensor]:
    heat = focal_loss(out["heat"], tgt["heat"])
    m = tgt["mask"]
    n = m.sum().clamp(min=1)
    size = gather(out["size"], tgt["ind"])
    off = gather(out["off"], tgt["ind"])
    oop = gather(out["oop"], tgt["ind"])[..., 0]
    l_size = (F.l1_loss(size, tgt["reg"][..., :2], reduction="none").sum(-1) * m).sum() / n
    l_off = (F.l1_loss(off, tgt["reg"][..., 2:], reduction="none").sum(-1) * m).sum() / n
    l_oop = (F.binary_cross_entropy_with_logits(oop, tgt["oop"], reduction="none") * m).sum() / n
    total = heat + w_size * l_size + w_off * l_off + w_oop * l_oop
    return {"total": total, "heat": heat, "size": l_size, "off": l_off, "oop": l_oop}


# ------------------------------------------------------------------ decoding
@dataclass
class RawDetection:
    cls: int
    score: float
    box: tuple[float, float, float, float]
    oop_prob: float
    cell: tuple[int, int]  # (row, col) on the output grid


def check_peaks(peaks: str) -> str:
    """``peaks`` if it names a decoding of ``decode`` (``PEAK_MODES``), else a ValueError."""
    if peaks not in PEAK_MODES:
        raise ValueError(f"peaks={peaks!r}: expected one of {', '.join(PEAK_MODES)}")
    return peaks


def decode(
    out: dict[str, torch.Tensor],
    k: int = 50,
    threshold: float = 0.2,
    stride: int = 4,
    classes_per_peak: int = 1,
    peaks: str = "class-max",
) -> list[list[RawDetection]]:
    """Peaks of the class-max heatmap (3x3 max-pool NMS) -> boxes, per image, best first.

    Peaks are found on the max over classes (logits: sigmoid is monotonic), so NMS costs a
    64 x 64 pool instead of C of them. ``classes_per_peak`` = 1 gives one class per centre
    cell (what the agent uses); m > 1 offers the m best classes of each peak as separate
    detections sharing its box, ranked together (the detector's second guesses: a COCO-style
    evaluation keeps them, as CenterNet's top-100 over classes and cells does).

    ``peaks`` (an ablation of this choice; the agent uses "class-max"): "per-class" pools each
    class's heatmap on its own, as CenterNet does, so a small object's peak survives beside a
    larger object's and one box may come out under several classes; "per-class-single" keeps a
    per-class peak only where its class is the cell's best, one class per cell.
    ``classes_per_peak`` applies to "class-max" only.
    """
    check_peaks(peaks)
    logits = out["heat"]
    b, c, h, w = logits.shape
    if peaks == "class-max":
        m = min(max(classes_per_peak, 1), c)
        # B x m x H x W, best class first (the agent's m = 1: one max, not a top-k)
        vals, cls_m = logits.topk(m, dim=1) if m > 1 else logits.max(1, keepdim=True)
        best = vals[:, 0]  # B x H x W
        keep = F.max_pool2d(best.unsqueeze(1), 3, 1, 1)[:, 0] == best
        vals = torch.where(keep.unsqueeze(1), vals, torch.full_like(vals, -1e4)).reshape(b, -1)
        top, idx = vals.topk(min(k, m * h * w))
        cls_sel = torch.gather(cls_m.reshape(b, -1), 1, idx)
    else:
        keep = F.max_pool2d(logits, 3, 1, 1) == logits  # B x C x H x W
        if peaks == "per-class-single":
            keep &= logits == logits.max(1, keepdim=True).values
        vals = torch.where(keep, logits, torch.full_like(logits, -1e4)).reshape(b, -1)
        top, idx = vals.topk(min(k, c * h * w))
        cls_sel = idx // (h * w)
    cells = idx % (h * w)
    scores = torch.sigmoid(top)
    size = out["size"].reshape(b, 2, -1)
    off = out["off"].reshape(b, 2, -1)
    oop = torch.sigmoid(out["oop"]).reshape(b, -1)
    res: list[list[RawDetection]] = []
    for i in range(b):
        dets = []
        n = int((scores[i] >= threshold).sum())  # scores are sorted: the first n pass
        if n:
            sel = cells[i, :n]
            sc = scores[i, :n].tolist()
            cl = cls_sel[i, :n].tolist()
            sz = size[i][:, sel].clamp(max=7.0).exp().tolist()
            of = off[i][:, sel].tolist()
            op = oop[i, sel].tolist()
            for j, cell in enumerate(sel.tolist()):
                row, col = divmod(cell, w)
                cx, cy = (col + of[0][j]) * stride, (row + of[1][j]) * stride
                bw, bh = sz[0][j], sz[1][j]
                dets.append(
                    RawDetection(
                        int(cl[j]),
                        float(sc[j]),
                        (cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2),
                        float(op[j]),
                        (row, col),
                    )
                )
        res.append(dets)
    return res


__all__ = [
    "CenterDetector",
    "preprocess",
    "encode_targets",
    "detector_loss",
    "decode",
    "check_peaks",
    "RawDetection",
    "gather",
    "focal_loss",
    "draw_gaussian",
    "gaussian_radius",
    "DEPTH_SCALE",
]
