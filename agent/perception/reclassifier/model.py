"""The second stage of the detector: a crop classifier that renames what the detector boxed.

The CenterNet-style detector finds and boxes most objects and then names some of them wrongly
(docs/limitations.md, "Perception"): on the validation frames, giving every detection of an
earlier detector the class of the ground-truth box it overlaps lifted box mAP@0.5 from 54.8
to 70.1. This network looks at each detection again, at a fixed scale: the RGB-D crop around its box
(resampled to ``crop`` x ``crop`` pixels, depth relative to the object's own), with the box's
size in the image and in metres as side inputs, and outputs a distribution over the catalog's
classes plus "background" (the box holds no object).

``LearnedPerception`` combines it with the detector's own class scores at the detection's
centre cell (``fuse``): the class is the argmax of log p_crop + ``alpha`` log sigmoid(heat),
and the score is the detector's peak score times p_crop(class)^``beta`` (with ``beta`` the
background, too, pulls a box's score down). A reclassifier trained with ``--boxes detector``
also reads the detector's class logits at the detection's cell and its peak score
(``det_features``): a learned fusion in place of the hand-set ``alpha``. Training:
:mod:`.train`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tidee.agent.perception.detector.model import DEPTH_SCALE, RGB_MEAN, RGB_STD, cbr
from tidee.agent.perception.reclassifier.config import DEFAULT_RECLASSIFIER, ReclassifierConfig

N_SIDE = 5  # side inputs: log box w, h (fraction of the image), log depth, log metric w, h


class CropClassifier(nn.Module):
    def __init__(self, cfg: ReclassifierConfig) -> None:
        super().__init__()
        self.cfg = cfg
        a, b, c = cfg.widths
        self.conv = nn.Sequential(cbr(4, a, 2), cbr(a, a), cbr(a, b, 2), cbr(b, b), cbr(b, c, 2), cbr(c, c))
        n_det = cfg.num_classes + 1 if cfg.det_inputs else 0
        self.mlp = nn.Sequential(
            nn.Linear(c + N_SIDE + n_det, cfg.hidden),
            nn.ReLU(inplace=True),
            nn.Linear(cfg.hidden, cfg.num_classes + 1),
        )

    def forward(
        self, crops: torch.Tensor, side: torch.Tensor, det: torch.Tensor | None = None
    ) -> torch.Tensor:
        """N x 4 x crop x crop, N x N_SIDE (, N x classes + 1 from ``det_features`` when the
        config has ``det_inputs``) -> N x (classes + 1) logits (the last: background)."""
        f = self.conv(crops).mean((2, 3))
        parts = [f, side]
        if self.cfg.det_inputs:
            if det is None or det.shape != (len(f), self.cfg.num_classes + 1):
                raise ValueError(
                    f"this reclassifier reads the detector's outputs: det must be N x "
                    f"{self.cfg.num_classes + 1} (det_features), got "
                    f"{None if det is None else tuple(det.shape)}"
                )
            parts.append(det.to(f.dtype))
        return self.mlp(torch.cat(parts, 1))


def det_features(heat: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
    """The detector's side of a detection for a ``det_inputs`` reclassifier: its class logits at
    the detection's cell (N x C) as log-sigmoid, and the log of its peak score (N), scaled to
    about [-3, 0] -> N x (C + 1)."""
    return (
        torch.cat(
            [
                F.logsigmoid(heat.float()).clamp(min=-12.0),
                score.float().clamp(min=1e-6).log().clamp(min=-12.0).view(-1, 1),
            ],
            1,
        )
        / 4.0
    )


def frame_tensor(rgb: np.ndarray, depth: np.ndarray, normalised: torch.Tensor | None = None) -> torch.Tensor:
    """uint8 BxHxWx3 + metres BxHxW -> B x 4 x H x W (normalised RGB, depth in metres).
    ``normalised``: the B x 3 x H x W normalised RGB when it is already made (the detector's
    input: ``detector.model.preprocess`` normalises alike), used instead of ``rgb``."""
    if normalised is not None:
        x = normalised
    else:
        x = torch.from_numpy(np.array(rgb, dtype=np.uint8)).permute(0, 3, 1, 2).float().div_(255.0)
        x = (x - torch.tensor(RGB_MEAN).view(1, 3, 1, 1)) / torch.tensor(RGB_STD).view(1, 3, 1, 1)
    d = torch.from_numpy(np.array(depth, dtype=np.float32)).unsqueeze(1)
    return torch.cat([x, d], 1)


def crop_inputs(
    frames: torch.Tensor,
    frame_idx: torch.Tensor,
    boxes: torch.Tensor,
    cfg: ReclassifierConfig,
    flip: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Crops and side inputs for boxes (N x 4, x0 y0 x1 y1 in pixels) of ``frames`` (B x 4 x H x W
    from ``frame_tensor``). The depth channel becomes the depth relative to the median of the
    crop's centre, in units of DEPTH_SCALE, clamped; the median itself is a side input.
    ``flip`` (bool N) mirrors crops left-right (training augmentation)."""
    n = len(boxes)
    _, _, h, w = frames.shape
    boxes = boxes.float()
    cx, cy = (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2
    bw = (boxes[:, 2] - boxes[:, 0]).clamp(min=1.0)
    bh = (boxes[:, 3] - boxes[:, 1]).clamp(min=1.0)
    # affine grid in normalised coordinates (align_corners=False: pixel edges at -1 and 1)
    sx, sy = bw * cfg.context / w, bh * cfg.context / h
    tx, ty = 2 * cx / w - 1, 2 * cy / h - 1
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = sx if flip is None else torch.where(flip, -sx, sx)
    theta[:, 0, 2] = tx
    theta[:, 1, 1] = sy
    theta[:, 1, 2] = ty
    grid = F.affine_grid(theta, [n, 4, cfg.crop, cfg.crop], align_corners=False)
    frame_idx = frame_idx.long()
    if n and bool((frame_idx == frame_idx[0]).all()):  # one frame (the agent's case): a view, not N copies
        src = frames[frame_idx[0]].expand(n, -1, -1, -1)
    else:
        src = frames[frame_idx]
    crops = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)
    k = max(cfg.crop // 4, 1)
    c0 = (cfg.crop - k) // 2
    core = crops[:, 3, c0 : c0 + k, c0 : c0 + k].reshape(n, -1)
    core = torch.where(core > 0.05, core, torch.full_like(core, float("nan")))
    med = core.nanmedian(1).values
    med = torch.where(torch.isnan(med), crops[:, 3].reshape(n, -1).median(1).values, med).clamp(min=0.05)
    crops = torch.cat(
        [crops[:, :3], ((crops[:, 3:] - med.view(n, 1, 1, 1)) / DEPTH_SCALE * 4).clamp(-2, 2)], 1
    )
    fw, fh = bw / w, bh / h
    # a 90-degree field of view: an object spanning fraction f of the image at depth d is 2 f d metres wide
    side = torch.stack([fw.log(), fh.log(), med.log(), (2 * fw * med).log(), (2 * fh * med).log()], 1)
    return crops, side


def fuse(
    crop_logits: torch.Tensor, det_heat: torch.Tensor, det_score: torch.Tensor, alpha: float, beta: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(class index N, score N) from the crop classifier's logits (N x C+1), the detector's class
    logits at each detection's cell (N x C) and its peak scores (N)."""
    logp = F.log_softmax(crop_logits.float(), 1)
    joint = logp[:, :-1] + alpha * F.logsigmoid(det_heat.float())
    cls = joint.argmax(1)
    p = logp.gather(1, cls.view(-1, 1))[:, 0].exp()
    return cls, det_score * p.pow(beta)


def load_reclassifier(
    path: str | Path | None = None, verify: bool = True
) -> tuple[CropClassifier, dict[str, Any]]:
    from tidee.agent.learning import read_manifest

    path = Path(path) if path else DEFAULT_RECLASSIFIER
    manifest = read_manifest(path, verify=verify)
    blob = torch.load(path, map_location="cpu", weights_only=False)
    model = CropClassifier(ReclassifierConfig.from_dict(blob["config"]))
    model.load_state_dict(blob["state_dict"])
    return model.eval(), {**manifest, "path": str(path)}


__all__ = [
    "CropClassifier",
    "crop_inputs",
    "frame_tensor",
    "fuse",
    "det_features",
    "load_reclassifier",
    "N_SIDE",
]
