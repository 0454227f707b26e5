"""Depth from RGB: a small U-Net for the paper's "+est. depth" setting.

``DepthNet`` maps an RGB frame to metric depth along the optical axis (metres, bounded to
``[min_depth, max_depth]``). It is small enough for the agent's CPU budget: about 4 ms per
256^2 frame on one thread of an AVX512 EPYC (``tidee eval depth``) with BatchNorm folded into
the convolutions (``DepthEstimator`` does that when it loads the weights).

``tidee train depth`` fits it (:mod:`.train`) on the detector frames of the training rooms
(``tidee gen detection``); ``tidee eval depth`` (:mod:`.eval`) measures it on held-out test
(or val) rooms rendered on the fly.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from tidee.agent.learning import pick_device, read_manifest
from tidee.agent.perception.depth.config import DEFAULT_WEIGHTS

RESOLUTION = 256  # the network's input size; other frames are resized to it
VALID_MIN, VALID_MAX = 0.05, 8.0  # metres scored; 0 is "nothing", the far plane (20 m) shows through doors
TYPICAL_DEPTH = 1.0  # metres: about the median of the training frames (mostly near views)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# --- the network ---------------------------------------------------------------------------------


def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)
    )


class DepthNet(nn.Module):
    """RGB in [0, 1] (B x 3 x H x W, H and W multiples of 16) -> depth in metres (B x H x W).

    Encoder: one stride-2 stage per entry of ``widths`` (1/2 ... 1/16), two 3x3 conv-BN-ReLU
    each. With ``context``, a vector pooled over the whole 1/16 map (a 1x1 conv and ReLU of its
    mean) is added to every cell of it, so each pixel sees the room's layout. Decoder:
    bilinear x2, a 1x1 projection added to the skip of the same scale, one 3x3 conv-BN-ReLU.
    The head predicts at 1/2 resolution and is upsampled bilinearly; its
    output is squashed to log depth in [log min_depth, log max_depth].
    """

    mean: torch.Tensor  # buffers (register_buffer below): ImageNet normalisation
    std: torch.Tensor

    def __init__(
        self,
        widths: tuple[int, ...] | list[int] = (16, 24, 48, 96),
        min_depth: float = 0.1,
        max_depth: float = 8.0,
        context: bool = False,
    ):
        super().__init__()
        if len(widths) != 4:
            raise ValueError(f"widths needs 4 entries (scales 1/2 to 1/16), got {list(widths)}")
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        self.widths = tuple(int(w) for w in widths)
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.context = bool(context)
        w = self.widths
        self.encoder = nn.ModuleList(
            nn.Sequential(_conv_bn_relu(c_in, c_out, 2), _conv_bn_relu(c_out, c_out))
            for c_in, c_out in zip((3,) + w[:-1], w)
        )
        self.lateral = nn.ModuleList(nn.Conv2d(w[i + 1], w[i], 1) for i in range(len(w) - 1))
        self.decoder = nn.ModuleList(_conv_bn_relu(w[i], w[i]) for i in range(len(w) - 1))
        self.head = nn.Conv2d(w[0], 1, 3, 1, 1)
        self.global_context = (
            nn.Sequential(nn.Conv2d(w[-1], w[-1], 1), nn.ReLU(inplace=True)) if self.context else None
        )
        # Start at a typical room depth, not the geometric middle of the range (0.9 m).
        start = (math.log(TYPICAL_DEPTH) - math.log(min_depth)) / (math.log(max_depth) - math.log(min_depth))
        assert self.head.bias is not None
        nn.init.constant_(self.head.bias, math.log(start / (1 - start)))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def config(self) -> dict[str, Any]:
        config: dict[str, Any] = {
            "widths": list(self.widths),
            "min_depth": self.min_depth,
            "max_depth": self.max_depth,
        }
        if self.context:  # older weights files have no key: no context branch
            config["context"] = True
        return config

    def log_depth(self, rgb: torch.Tensor) -> torch.Tensor:
        if rgb.shape[-1] % 16 or rgb.shape[-2] % 16:
            raise ValueError(f"DepthNet needs H and W divisible by 16, got {tuple(rgb.shape[-2:])}")
        x = (rgb - self.mean) / self.std
        skips = []
        for stage in self.encoder:
            x = stage(x)
            skips.append(x)
        if self.global_context is not None:
            x = x + self.global_context(x.mean(dim=(2, 3), keepdim=True))
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
            if (
                isinstance(block, nn.Sequential)
                and len(block) == 3
                and isinstance(block[0], nn.Conv2d)
                and isinstance(block[1], nn.BatchNorm2d)
            ):
                block[0] = fuse_conv_bn_eval(block[0], block[1])
                block[1] = nn.Identity()
        return net


# --- inference -----------------------------------------------------------------------------------


class DepthModel(Protocol):
    def predict(self, rgb: np.ndarray) -> np.ndarray: ...


class DepthEstimator:
    """A trained ``DepthNet`` behind ``predict(rgb uint8 HxWx3) -> float32 HxW metres``."""

    def __init__(self, model: DepthNet, device: str = "cpu"):
        self.device = device
        # Module.to takes memory_format (torch's docs); its type stubs' overloads leave it out
        self.net = model.fused().to(device).to(memory_format=torch.channels_last)  # type: ignore[call-overload]

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


__all__ = [
    "DepthNet",
    "DepthEstimator",
    "DepthModel",
    "RESOLUTION",
    "VALID_MIN",
    "VALID_MAX",
]
