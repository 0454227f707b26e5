"""Learned perception: the shipped RGB-D detector behind the ``Perception`` interface.

Each detection carries the detector's class, score, box, its out-of-place probability (the
OOP head: the paper's dDETR-OOP) and a feature vector (the neck at the object's centre
cell, L2-normalised) for the downstream classifiers. A second stage (``reclassifier``:
a crop classifier, on by default when its weights ship) renames each detection from an RGB-D
crop of its box and can lower the score of a box that holds no object. The detector predicts boxes, not
masks; the mask handed to mapping is grown from the depth at the box centre: the pixels of
the box whose depth lies within the object's own extent of it, so the median-depth
centroid is the object's and not the wall behind it.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import torch

from tidee.agent.classes import CLASSES
from tidee.agent.learning import read_manifest, resolve_precision
from tidee.agent.perception import AGENT_THRESHOLD
from tidee.agent.perception.base import Detection
from tidee.agent.perception.detector.config import DEFAULT_WEIGHTS, DetectorConfig
from tidee.agent.perception.detector.model import (
    CenterDetector,
    RawDetection,
    check_peaks,
    decode,
    fold_batchnorm,
    preprocess,
)
from tidee.agent.perception.graph import FrozenNet
from tidee.agent.perception.reclassifier.config import DEFAULT_RECLASSIFIER
from tidee.agent.perception.reclassifier.model import (
    CropClassifier,
    crop_inputs,
    det_features,
    frame_tensor,
    fuse,
    load_reclassifier,
)
from tidee.protocol.messages import Observation


def depth_mask(
    depth: np.ndarray,
    box: tuple[int, int, int, int],
    focal: float,
    min_tol: float = 0.08,
    max_tol: float = 1.0,
) -> np.ndarray | None:
    """bool HxW: box pixels within the object's depth range around the centre's depth."""
    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        return None
    patch = depth[y0:y1, x0:x1]
    h, w = patch.shape
    cy, cx = h // 2, w // 2
    r = max(1, min(h, w) // 6)
    core = patch[max(cy - r, 0) : cy + r + 1, max(cx - r, 0) : cx + r + 1]
    core = core[core > 0.05]
    if core.size == 0:
        return None
    dc = float(np.median(core))
    extent = max(w, h) * dc / focal  # the object's size in metres, from the box
    tol = float(np.clip(0.6 * extent, min_tol, max_tol))
    m = np.zeros(depth.shape, bool)
    m[y0:y1, x0:x1] = (np.abs(patch - dc) <= tol) & (patch > 0.05)
    return m if m.any() else None


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> np.ndarray:
    """Indices kept by greedy per-class non-maximum suppression (a large object can raise
    several heatmap peaks; the 3x3 peak pooling alone keeps them all)."""
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    for i in order:
        ok = True
        for j in keep:
            if classes[j] != classes[i]:
                continue
            w = min(boxes[i, 2], boxes[j, 2]) - max(boxes[i, 0], boxes[j, 0])
            h = min(boxes[i, 3], boxes[j, 3]) - max(boxes[i, 1], boxes[j, 1])
            if w > 0 and h > 0 and w * h / (area[i] + area[j] - w * h) > iou:
                ok = False
                break
        if ok:
            keep.append(int(i))
    return np.array(keep, int)


class LearnedPerception:
    """The trained detector. ``threshold`` is the score below which detections are dropped.

    ``precision``: "auto" runs the networks in bf16, channels-last, where the CPU has native
    bf16 (AVX512-BF16/AMX; about 1.6x faster per frame), fp32 elsewhere; each as a frozen graph
    that gives the same outputs as the module under autocast (``graph.FrozenNet``).
    ``classes_per_peak``, ``peaks``: see ``detector.model.decode`` (1 and "class-max" for the agent).
    ``reclassifier``: the crop classifier that renames detections (``reclassifier.model.fuse`` with
    ``alpha``, ``beta``), or None for the detector's own classes and scores. ``gate``: detections
    whose detector score is at least this keep the detector's class and score without a crop
    (None: every detection is reclassified); chosen on the validation rooms with the fusion
    (``tidee eval reclassifier --gates ... --record``).
    """

    name = "learned"
    needs_ground_truth = False

    def __init__(
        self,
        model: CenterDetector,
        manifest: dict | None = None,
        threshold: float = AGENT_THRESHOLD,
        max_detections: int = 50,
        path: Path | None = None,
        nms_iou: float = 0.5,
        precision: str = "auto",
        classes_per_peak: int = 1,
        peaks: str = "class-max",
        reclassifier: CropClassifier | None = None,
        reclassifier_manifest: dict | None = None,
        alpha: float = 1.0,
        beta: float = 1.0,
        gate: float | None = None,
    ) -> None:
        self.peaks = check_peaks(peaks)
        if reclassifier is not None and reclassifier.cfg.num_classes != model.cfg.num_classes:
            raise ValueError(
                f"the reclassifier knows {reclassifier.cfg.num_classes} classes, the detector "
                f"{model.cfg.num_classes}: retrain it"
            )
        # Copies with batch norm folded into the convolutions (``fold_batchnorm``): the caller's
        # modules stay trainable, and inference skips one pass over every feature map.
        self.reclassifier = (
            fold_batchnorm(copy.deepcopy(reclassifier).eval()).to(memory_format=torch.channels_last)
            if reclassifier
            else None
        )
        self.reclassifier_manifest = reclassifier_manifest or {}
        self.alpha, self.beta = float(alpha), float(beta)
        self.gate = gate
        self.stats = {"reclassified": 0, "gated": 0}  # detections the crop classifier saw / skipped
        self.precision = resolve_precision(precision, "cpu")
        self.model = fold_batchnorm(copy.deepcopy(model).eval()).to(memory_format=torch.channels_last)
        # What runs them: frozen graphs where they give the same outputs (``graph.FrozenNet``).
        self.net = FrozenNet(self.model, self.precision)
        self.reclassifier_net = FrozenNet(self.reclassifier, self.precision) if self.reclassifier else None
        self.classes_per_peak = classes_per_peak
        self.path = path  # the weights file (its manifest is beside it)
        self.cfg = model.cfg
        self.manifest = manifest or {}
        self.threshold = threshold
        self.max_detections = max_detections
        self.nms_iou = nms_iou

    @staticmethod
    def load(
        path: str | Path | None = None,
        threshold: float = AGENT_THRESHOLD,
        verify: bool = True,
        precision: str = "auto",
        classes_per_peak: int = 1,
        reclassifier: str | Path | None = "default",
    ) -> LearnedPerception:
        """``reclassifier``: "default" loads the shipped crop classifier when it is there, a path
        loads that one (it must exist), None runs the detector alone. Its fusion weights
        (``alpha``, ``beta``) and its gate come from its manifest's ``fusion`` (``tidee eval
        reclassifier --record``)."""
        path = Path(path) if path else DEFAULT_WEIGHTS
        manifest = read_manifest(path, verify=verify)
        blob = torch.load(path, map_location="cpu", weights_only=False)
        cfg = DetectorConfig.from_dict(blob["config"])
        if cfg.num_classes != len(CLASSES):
            raise ValueError(
                f"{path} predicts {cfg.num_classes} classes; the catalog has {len(CLASSES)}: retrain"
            )
        model = CenterDetector(cfg)
        model.load_state_dict(blob["state_dict"])
        rc, rc_manifest = None, None
        if reclassifier == "default":
            reclassifier = DEFAULT_RECLASSIFIER if DEFAULT_RECLASSIFIER.exists() else None
        if reclassifier is not None:
            rc, rc_manifest = load_reclassifier(reclassifier, verify=verify)
        fusion = (rc_manifest or {}).get("metrics", {}).get("fusion", {})
        return LearnedPerception(
            model,
            manifest,
            threshold,
            path=path,
            precision=precision,
            classes_per_peak=classes_per_peak,
            reclassifier=rc,
            reclassifier_manifest=rc_manifest,
            alpha=fusion.get("alpha", 1.0),
            beta=fusion.get("beta", 1.0),
            gate=fusion.get("gate"),
        )

    def _reclassify(
        self,
        raw: list[list[RawDetection]],
        rgb: np.ndarray,
        depth: np.ndarray,
        heat: torch.Tensor,
        threshold: float,
        normalised: torch.Tensor | None = None,
    ) -> list[list[RawDetection]]:
        """Each detection renamed and rescored by the crop classifier (``reclassifier.model.fuse``);
        those whose score falls under ``threshold`` are dropped, the rest sorted best first.
        ``normalised``: the detector's input (its first three channels are the normalised RGB)."""
        rc = self.reclassifier
        assert rc is not None  # detect_batch asks for this only when there is a second stage
        gate = self.gate if self.gate is not None else float("inf")
        out: list[list[RawDetection]] = [[d for d in dets if d.score >= gate] for dets in raw]
        flat = [(i, d) for i, dets in enumerate(raw) for d in dets if d.score < gate]
        self.stats["reclassified"] += len(flat)
        self.stats["gated"] += sum(map(len, out))
        if not flat:
            return out
        fidx = torch.tensor([i for i, _ in flat])
        boxes = torch.tensor([d.box for _, d in flat], dtype=torch.float32)
        frames = frame_tensor(rgb, depth, None if normalised is None else normalised[:, :3])
        crops, side = crop_inputs(frames, fidx, boxes, rc.cfg)
        rows = torch.tensor([d.cell[0] for _, d in flat])
        cols = torch.tensor([d.cell[1] for _, d in flat])
        cell_heat, peak = heat[fidx, :, rows, cols], torch.tensor([d.score for _, d in flat])
        det = det_features(cell_heat, peak) if rc.cfg.det_inputs else None
        assert self.reclassifier_net is not None
        inputs = (crops.contiguous(memory_format=torch.channels_last), side)
        logits = self.reclassifier_net(*inputs) if det is None else self.reclassifier_net(*inputs, det)
        cls, score = fuse(logits, cell_heat, peak, self.alpha, self.beta)
        for (i, d), c, s in zip(flat, cls.tolist(), score.tolist()):
            if s >= threshold:
                out[i].append(dataclasses.replace(d, cls=int(c), score=float(s)))
        for dets in out:
            dets.sort(key=lambda d: -d.score)
        return out

    def reset_stats(self) -> None:
        self.stats = {"reclassified": 0, "gated": 0}

    @property
    def sha256(self) -> str | None:
        return self.manifest.get("sha256")

    def detect(self, obs: Observation) -> list[Detection]:
        return self.detect_batch(obs.rgb[None], obs.depth[None])[0]

    @torch.inference_mode()
    def raw_detections(
        self, rgb: np.ndarray, depth: np.ndarray, threshold: float
    ) -> tuple[list[list[RawDetection]], dict[str, torch.Tensor]]:
        """The network alone on frames at its input size: each frame's decoded peaks (before the
        reclassifier and NMS) and the network's outputs (float32; ``heat``: class logits)."""
        raw, out, _ = self._raw_detections(rgb, depth, threshold)
        return raw, out

    def _raw_detections(
        self, rgb: np.ndarray, depth: np.ndarray, threshold: float
    ) -> tuple[list[list[RawDetection]], dict[str, torch.Tensor], torch.Tensor]:
        """``raw_detections`` and the network's input."""
        x = preprocess(rgb, depth, self.cfg.use_depth).contiguous(memory_format=torch.channels_last)
        out = {k: v.float() for k, v in self.net(x).items()}
        raw = decode(
            out,
            k=self.max_detections,
            threshold=threshold,
            stride=self.cfg.stride,
            classes_per_peak=self.classes_per_peak,
            peaks=self.peaks,
        )
        return raw, out, x

    @torch.inference_mode()
    def detect_batch(
        self, rgbs: np.ndarray, depths: np.ndarray, threshold: float | None = None
    ) -> list[list[Detection]]:
        rgbs = np.asarray(rgbs)
        depths = np.asarray(depths, dtype=np.float32)
        if rgbs.ndim != 4 or rgbs.shape[-1] != 3 or depths.shape != rgbs.shape[:3]:
            raise ValueError(f"expected rgb BxHxWx3 and depth BxHxW, got {rgbs.shape} and {depths.shape}")
        n, h, w = depths.shape
        size = self.cfg.input_size
        if (h, w) != (size, size):
            import cv2

            rgb_in = np.stack([cv2.resize(r, (size, size), interpolation=cv2.INTER_AREA) for r in rgbs])
            depth_in = np.stack(
                [cv2.resize(d, (size, size), interpolation=cv2.INTER_NEAREST) for d in depths]
            )
        else:
            rgb_in, depth_in = rgbs, depths
        thr = self.threshold if threshold is None else threshold
        raw, out, x = self._raw_detections(rgb_in, depth_in, thr)
        if self.reclassifier is not None and any(raw):
            raw = self._reclassify(raw, rgb_in, depth_in, out["heat"], thr, x)
        feat = out["feat"]
        sx, sy = w / size, h / size
        focal = (w / 2) / np.tan(np.radians(45.0))
        result: list[list[Detection]] = []
        for i, dets in enumerate(raw):
            frame = []
            if len(dets) > 1 and self.nms_iou < 1.0:
                keep = nms(
                    np.array([d.box for d in dets]),
                    np.array([d.score for d in dets]),
                    np.array([d.cls for d in dets]),
                    self.nms_iou,
                )
                dets = [dets[k] for k in sorted(keep)]
            for d in dets:
                x0 = int(np.clip(np.floor(d.box[0] * sx), 0, w - 1))
                y0 = int(np.clip(np.floor(d.box[1] * sy), 0, h - 1))
                x1 = int(np.clip(np.ceil(d.box[2] * sx), x0 + 1, w))
                y1 = int(np.clip(np.ceil(d.box[3] * sy), y0 + 1, h))
                box = (x0, y0, x1, y1)
                frame.append(
                    Detection(
                        label=CLASSES[d.cls],
                        score=float(d.score),
                        box=box,
                        mask=depth_mask(depths[i], box, focal),
                        # L2-normalised where it is read, not over the whole map
                        feature=torch.nn.functional.normalize(feat[i, :, d.cell[0], d.cell[1]], dim=0)
                        .numpy()
                        .astype(np.float32),
                        oop_prob=float(d.oop_prob),
                        source=self.name,
                    )
                )
            result.append(frame)
        return result


__all__ = ["LearnedPerception", "depth_mask"]
