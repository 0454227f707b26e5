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
background, too, pulls a box's score down).

Trained by ``tidee train reclassifier`` on frames of ``tidee gen detection``: crops of the
ground-truth boxes, jittered as the detector's boxes are, and background crops (boxes that
overlap no object by IoU 0.3). Reproducible from a seed, resumable, progress bar, loss curve.

``--boxes detector`` (how the shipped weights were trained) trains on the detector's own
boxes instead: the shipped detector runs over the training frames (rooms it was not trained
on) at the evaluation's threshold, each detection is labelled by the ground-truth box it
overlaps (IoU >= 0.5: that class; < 0.4: background; between: ignored), and the network also
reads the detector's class logits at the detection's cell and its peak score
(``det_features``): a learned fusion, on the box errors the detector really makes, in place
of the hand-set ``alpha``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tidee.agent.learning import (
    WEIGHTS_DIR,
    dataset_record,
    load_checkpoint,
    pick_device,
    resolve_precision,
    resume_training,
    save_checkpoint,
    save_loss_curve,
    ship_weights,
    write_manifest,
)
from tidee.agent.perception.detector import DEPTH_SCALE, RGB_MEAN, RGB_STD, cbr

DEFAULT_RECLASSIFIER = WEIGHTS_DIR / "reclassifier.pt"
IGNORE = -100
N_SIDE = 5  # side inputs: log box w, h (fraction of the image), log depth, log metric w, h


@dataclass
class ReclassifierConfig:
    num_classes: int = 92  # + 1 output: background
    crop: int = 40  # crop side in pixels
    context: float = 1.2  # the crop covers the box grown by this factor
    widths: tuple[int, int, int] = (32, 64, 128)
    hidden: int = 128
    det_inputs: bool = False  # also read the detector's class logits and score (det_features)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> ReclassifierConfig:
        d = dict(d)
        d["widths"] = tuple(d["widths"])
        return ReclassifierConfig(**d)


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


def warm_start(model: CropClassifier, path: str | Path) -> None:
    """Load a reclassifier's weights into ``model`` (same crop network); the detector inputs a
    ``det_inputs`` model adds to the first MLP layer start at zero, so it starts as that model."""
    blob = load_checkpoint(path)
    if blob is None or "state_dict" not in blob:
        raise ValueError(f"--init {path}: not a reclassifier weights file (missing, or no state_dict)")
    state = dict(blob["state_dict"])
    own = model.state_dict()
    w = state["mlp.0.weight"]
    if w.shape != own["mlp.0.weight"].shape:
        if w.shape[0] != own["mlp.0.weight"].shape[0] or w.shape[1] > own["mlp.0.weight"].shape[1]:
            raise ValueError(
                f"{path}: its first MLP layer is {tuple(w.shape)}, this model's "
                f"{tuple(own['mlp.0.weight'].shape)}: not a warm start of it"
            )
        grown = torch.zeros_like(own["mlp.0.weight"])
        grown[:, : w.shape[1]] = w
        state["mlp.0.weight"] = grown
    model.load_state_dict(state)


def frame_tensor(rgb: np.ndarray, depth: np.ndarray) -> torch.Tensor:
    """uint8 BxHxWx3 + metres BxHxW -> B x 4 x H x W (normalised RGB, depth in metres)."""
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
    src = frames[frame_idx.long()]
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


# ------------------------------------------------------------------------- training


@dataclass
class ReclassifierTrainConfig:
    data: str = "data/detection_d"
    out: str = str(DEFAULT_RECLASSIFIER)
    work_dir: str = "runs/reclassifier"
    steps: int = 3000
    batch_size: int = 256
    frames_per_batch: int = 32
    background: float = 0.2  # share of each batch drawn as background boxes
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: int = 100
    seed: int = 0
    device: str = "auto"
    threads: int = 0
    ckpt_every: int = 200
    log_every: int = 20
    limit_frames: int | None = None
    precision: str = "auto"
    boxes: str = "jitter"  # jitter: ground-truth boxes, jittered | detector: the detector's own
    detector: str | None = None  # boxes=detector: its weights (None: the shipped detector)
    init: str | None = None  # start from these reclassifier weights (warm_start)


BOX_SOURCES = ("jitter", "detector")


def rows_by_frame(frame_of_row: np.ndarray, n_frames: int) -> list[np.ndarray]:
    """For each of ``n_frames`` frames, the indices of the rows (objects, detections) in it."""
    order = np.argsort(frame_of_row, kind="stable")
    starts = np.searchsorted(frame_of_row[order], np.arange(n_frames + 1))
    return [order[starts[i] : starts[i + 1]] for i in range(n_frames)]


DET_POS_IOU, DET_NEG_IOU = 0.5, 0.4  # detector boxes: a class at IoU >= 0.5, background < 0.4


@torch.inference_mode()
def detector_boxes(
    data: dict[str, np.ndarray],
    detector: str | None = None,
    threshold: float = 0.05,
    batch: int = 32,
    progress: bool = True,
) -> dict[str, np.ndarray]:
    """Run the detector (no reclassifier) over every frame of ``data`` as the evaluation does
    (class-max peaks, one class each, score >= ``threshold``, before NMS) and label each
    detection by the ground truth it overlaps. Returns det_frame, det_box (pixels), det_heat
    (class logits at its cell, float16), det_score, det_label (class, background = C, IGNORE)."""
    from tqdm import tqdm

    from tidee.agent.evaluation.detection import box_iou
    from tidee.agent.perception.learned import LearnedPerception

    perc = LearnedPerception.load(detector, threshold=threshold, reclassifier=None)
    dcfg = perc.cfg
    n, size = len(data["rgb"]), data["rgb"].shape[1]
    if size != dcfg.input_size:
        raise ValueError(
            f"frames are {size} px; the detector reads {dcfg.input_size}: generate them at its resolution"
        )
    objects_of = rows_by_frame(data["obj_frame"], n)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("frame", "box", "heat", "score", "label")}
    for s in tqdm(range(0, n, batch), desc="detector boxes", disable=not progress):
        rgb = np.ascontiguousarray(data["rgb"][s : s + batch])
        depth = np.asarray(data["depth"][s : s + batch], np.float32)
        raw, out = perc.raw_detections(rgb, depth, threshold)
        for i, dets in enumerate(raw):
            if not dets:
                continue
            f = s + i
            boxes = np.array([d.box for d in dets], np.float64)
            rows = objects_of[f]
            label = np.full(len(dets), -1, np.int64)
            if len(rows):
                ious = box_iou(boxes, data["obj_box"][rows].astype(np.float64))
                best = ious.argmax(1)
                top = ious[np.arange(len(dets)), best]
                label = np.where(
                    top >= DET_POS_IOU,
                    data["obj_cls"][rows][best].astype(np.int64),
                    np.where(top < DET_NEG_IOU, -1, IGNORE),
                )
            cells = torch.tensor([d.cell for d in dets])
            cols["frame"].append(np.full(len(dets), f, np.int32))
            cols["box"].append(boxes.astype(np.float32))
            cols["heat"].append(out["heat"][i, :, cells[:, 0], cells[:, 1]].T.numpy().astype(np.float16))
            cols["score"].append(np.array([d.score for d in dets], np.float32))
            cols["label"].append(label)
    c = out["heat"].shape[1] if n else 0
    res = {f"det_{k}": (np.concatenate(v) if v else np.zeros((0,), np.float32)) for k, v in cols.items()}
    # -1 marked background: it becomes the last class
    res["det_label"] = np.where(res["det_label"] == -1, c, res["det_label"]).astype(np.int64)
    res["detector_sha256"] = np.array(perc.sha256 or "")
    return res


class _FrameBatches:
    """What both batch samplers share: a seeded generator whose state a checkpoint keeps, a
    few frames per batch, and those frames' colours jittered."""

    rng: np.random.Generator
    frames_with_objects: np.ndarray

    def __init__(
        self, data: dict[str, np.ndarray], cfg: ReclassifierConfig, tc: ReclassifierTrainConfig
    ) -> None:
        self.data, self.cfg, self.tc = data, cfg, tc
        self.rng = np.random.default_rng(tc.seed)

    def state(self) -> dict:
        return self.rng.bit_generator.state

    def set_state(self, s: dict) -> None:
        self.rng.bit_generator.state = s

    def _pick_frames(self) -> np.ndarray:
        n = min(self.tc.frames_per_batch, len(self.frames_with_objects))
        return self.rng.choice(self.frames_with_objects, n, replace=False)

    def _jittered_frames(self, fids: np.ndarray) -> torch.Tensor:
        """``frame_tensor`` of frames ``fids``, each with its colours scaled by a random gain."""
        rgb = self.data["rgb"][fids].copy()
        gain = self.rng.uniform(0.8, 1.2, (len(fids), 1, 1, 3)) * self.rng.uniform(
            0.85, 1.15, (len(fids), 1, 1, 1)
        )
        rgb = np.clip(rgb * gain, 0, 255).astype(np.uint8)
        return frame_tensor(rgb, self.data["depth"][fids].astype(np.float32))


class DetectorBoxBatches(_FrameBatches):
    """Minibatches of the detector's own detections from a few frames each (``detector_boxes``):
    objects drawn uniformly, background boxes at most ``background`` of the batch; crops are
    mirrored and the frames' colours jittered as in ``CropBatches``."""

    def __init__(
        self,
        data: dict[str, np.ndarray],
        boxes: dict[str, np.ndarray],
        cfg: ReclassifierConfig,
        tc: ReclassifierTrainConfig,
    ) -> None:
        super().__init__(data, cfg, tc)
        self.boxes = boxes
        self.rows = rows_by_frame(boxes["det_frame"], len(data["rgb"]))
        is_object = (boxes["det_label"] >= 0) & (boxes["det_label"] < cfg.num_classes)
        self.frames_with_objects = np.array(
            [i for i, r in enumerate(self.rows) if is_object[r].any()], np.int64
        )
        if not len(self.frames_with_objects):
            raise ValueError("the detector found no object in any frame: nothing to train on")

    def __call__(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        b, rng, tc, nc = self.boxes, self.rng, self.tc, self.cfg.num_classes
        fids = self._pick_frames()
        rows = np.concatenate([self.rows[f] for f in fids])
        lab = b["det_label"][rows]
        obj, bg = rows[(lab >= 0) & (lab < nc)], rows[lab == nc]
        n_bg = min(int(round(tc.batch_size * tc.background)), len(bg))
        pick = np.concatenate(
            [
                rng.choice(obj, tc.batch_size - n_bg, replace=len(obj) < tc.batch_size - n_bg),
                rng.choice(bg, n_bg, replace=False),
            ]
        )
        local = {int(f): j for j, f in enumerate(fids)}
        fidx = torch.tensor([local[int(f)] for f in b["det_frame"][pick]])
        frames = self._jittered_frames(fids)
        flip = torch.from_numpy(rng.random(len(pick)) < 0.5)
        boxes = torch.from_numpy(b["det_box"][pick].astype(np.float32))
        crops, side = crop_inputs(frames, fidx, boxes, self.cfg, flip)
        det = det_features(
            torch.from_numpy(b["det_heat"][pick].astype(np.float32)), torch.from_numpy(b["det_score"][pick])
        )
        return crops, side, torch.from_numpy(b["det_label"][pick]), det


class CropBatches(_FrameBatches):
    """Minibatches of jittered ground-truth crops and background crops from a few frames each.

    Object boxes move by up to 15 % of their size and scale by up to +-25 % (the detector's box
    errors at IoU >= 0.5); a jittered box that no longer overlaps its object by IoU 0.5 is
    ignored in the loss. Background boxes are object boxes moved by 0.7-2 box sizes, or random
    boxes, that overlap every object by IoU < 0.3."""

    def __init__(
        self, data: dict[str, np.ndarray], cfg: ReclassifierConfig, tc: ReclassifierTrainConfig
    ) -> None:
        super().__init__(data, cfg, tc)
        n = len(data["rgb"])
        self.rows = rows_by_frame(data["obj_frame"], n)
        self.frames_with_objects = np.array([i for i in range(n) if len(self.rows[i])], np.int64)
        if not len(self.frames_with_objects):
            raise ValueError("no frame has an object to crop")

    def __call__(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, None]:
        from tidee.agent.evaluation.detection import box_iou

        d, rng, tc = self.data, self.rng, self.tc
        fids = self._pick_frames()
        size = d["rgb"].shape[1]
        n_bg = int(round(tc.batch_size * tc.background))
        n_obj = tc.batch_size - n_bg
        fidx, boxes, labels = [], [], []
        for k in range(tc.batch_size):
            j = int(rng.integers(len(fids)))
            rows = self.rows[fids[j]]
            gt = d["obj_box"][rows].astype(np.float64)
            r = int(rng.integers(len(rows)))
            x0, y0, x1, y1 = gt[r]
            w, h = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
            if k < n_obj:
                cx = (x0 + x1) / 2 + rng.uniform(-0.15, 0.15) * w
                cy = (y0 + y1) / 2 + rng.uniform(-0.15, 0.15) * h
                w2, h2 = w * math.exp(rng.uniform(-0.25, 0.25)), h * math.exp(rng.uniform(-0.25, 0.25))
            elif rng.random() < 0.6:
                ang = rng.uniform(0, 2 * math.pi)
                dist = rng.uniform(0.7, 2.0)
                cx, cy = (x0 + x1) / 2 + math.cos(ang) * dist * w, (y0 + y1) / 2 + math.sin(ang) * dist * h
                w2, h2 = w * math.exp(rng.uniform(-0.4, 0.4)), h * math.exp(rng.uniform(-0.4, 0.4))
            else:
                w2, h2 = size * math.exp(rng.uniform(-3.0, -0.5)), size * math.exp(rng.uniform(-3.0, -0.5))
                cx, cy = rng.uniform(0, size), rng.uniform(0, size)
            box = np.array([[cx - w2 / 2, cy - h2 / 2, cx + w2 / 2, cy + h2 / 2]])
            box[:, [0, 2]] = box[:, [0, 2]].clip(0, size)
            box[:, [1, 3]] = box[:, [1, 3]].clip(0, size)
            if box[0, 2] - box[0, 0] < 2 or box[0, 3] - box[0, 1] < 2:
                box = np.array([[x0, y0, x1, y1]])
                label = int(d["obj_cls"][rows[r]])
            else:
                ious = box_iou(box, gt)[0]
                best = int(np.argmax(ious))
                if ious[best] >= 0.5:
                    label = int(d["obj_cls"][rows[best]])
                elif ious[best] < 0.3:
                    label = self.cfg.num_classes  # background
                else:
                    label = IGNORE
            fidx.append(j)
            boxes.append(box[0])
            labels.append(label)
        frames = self._jittered_frames(fids)
        flip = torch.from_numpy(rng.random(tc.batch_size) < 0.5)
        crops, side = crop_inputs(
            frames, torch.tensor(fidx), torch.from_numpy(np.array(boxes)), self.cfg, flip
        )
        return crops, side, torch.tensor(labels, dtype=torch.long), None


def train_reclassifier(
    tc: ReclassifierTrainConfig,
    cfg: ReclassifierConfig | None = None,
    resume: bool = True,
    progress: bool = True,
    command: str = "",
    data: dict[str, np.ndarray] | None = None,
    ship: bool = True,
) -> dict[str, Any]:
    """Train; returns {"history": [...], "out": path, ...}. ``data`` overrides loading shards (tests)."""
    from tqdm import tqdm

    from tidee.agent.perception.dataset import load_datasets
    from tidee.agent.perception.train_detector import lr_at

    if tc.boxes not in BOX_SOURCES:
        raise ValueError(f"boxes must be one of {BOX_SOURCES}, got {tc.boxes!r}")
    if tc.threads:
        torch.set_num_threads(tc.threads)
    device = pick_device(tc.device)
    torch.manual_seed(tc.seed)
    cfg = cfg or ReclassifierConfig()
    if tc.boxes == "detector":
        cfg = ReclassifierConfig.from_dict({**cfg.to_dict(), "det_inputs": True})
    manifests: list[dict[str, Any]] = []
    if data is None:
        data, manifests = load_datasets(tc.data, limit=tc.limit_frames)
    model = CropClassifier(cfg)
    init_sha = None
    if tc.init:
        from tidee.agent.learning import sha256_file

        init_sha = sha256_file(tc.init)  # the init file may be replaced by these weights when shipped
        warm_start(model, tc.init)
    model = model.to(device, memory_format=torch.channels_last)
    precision = resolve_precision(tc.precision, device)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    work = Path(tc.work_dir)
    det_boxes: dict[str, np.ndarray] | None = None
    if tc.boxes == "detector":
        det_boxes = cached_detector_boxes(data, tc, work / "detector_boxes.npz", progress)
        batches: CropBatches | DetectorBoxBatches = DetectorBoxBatches(data, det_boxes, cfg, tc)
    else:
        batches = CropBatches(data, cfg, tc)
    ckpt_path = work / "checkpoint.pt"
    step, history = (
        resume_training(ckpt_path, tc.seed, cfg.to_dict(), model, opt, batches) if resume else (0, [])
    )
    t0 = time.time()
    model.train()
    bar = tqdm(total=tc.steps, initial=step, desc="train reclassifier", disable=not progress)
    running = {"total": 0.0, "acc": 0.0}
    while step < tc.steps:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, tc)  # the detector's warm-up + cosine schedule
        crops, side, labels, det = batches()
        crops = crops.to(device, memory_format=torch.channels_last)
        side, labels = side.to(device), labels.to(device)
        det = det.to(device) if det is not None else None
        with torch.autocast(device.split(":")[0], dtype=torch.bfloat16, enabled=precision == "bf16"):
            logits = model(crops, side, det)
        loss = F.cross_entropy(logits.float(), labels, ignore_index=IGNORE, label_smoothing=0.05)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        step += 1
        valid = labels != IGNORE
        running["total"] += loss.item()
        running["acc"] += (
            float((logits.argmax(1)[valid] == labels[valid]).float().mean()) if valid.any() else 0.0
        )
        if step % tc.log_every == 0 or step == tc.steps:
            n = tc.log_every if step % tc.log_every == 0 else step % tc.log_every
            history.append({"step": step, **{k: v / n for k, v in running.items()}})
            running = {"total": 0.0, "acc": 0.0}
            bar.set_postfix(loss=f"{history[-1]['total']:.3f}", acc=f"{history[-1]['acc']:.3f}")
        bar.update(1)
        if step % tc.ckpt_every == 0 or step == tc.steps:
            save_checkpoint(
                ckpt_path,
                model=model.state_dict(),
                optimizer=opt.state_dict(),
                sampler=batches.state(),
                torch_rng=torch.get_rng_state(),
                step=step,
                history=history,
                train_config=asdict(tc),
                model_config=cfg.to_dict(),
            )
            save_loss_curve(
                [{k: v for k, v in h.items() if k != "acc"} for h in history],
                work / "loss.png",
                f"reclassifier ({step} steps, batch {tc.batch_size})",
            )
    bar.close()
    result: dict[str, Any] = {
        "history": history,
        "seconds": round(time.time() - t0, 1),
        "steps": step,
        "device": device,
        "precision": precision,
        "work_dir": str(work),
    }
    if ship:
        curve = ship_weights(tc.out, model, cfg.to_dict(), work / "loss.png", "reclassifier_loss.png")
        result["manifest"] = write_manifest(
            tc.out,
            command=command,
            data=dataset_record(
                tc.data,
                data,
                manifests,
                "train rooms only, never val/test",
                objects=int(len(data["obj_cls"])),
                **(
                    {}
                    if det_boxes is None
                    else {
                        "detector_boxes": int(len(det_boxes["det_label"])),
                        "detector_sha256": str(det_boxes["detector_sha256"]),
                    }
                ),
            ),
            metrics={"train_loss_final": history[-1] if history else None},
            train_config={**asdict(tc), "precision_used": precision, "device_used": device},
            model_config=cfg.to_dict(),
            init=None if not tc.init else {"path": tc.init, "sha256": init_sha},
            parameters=int(sum(p.numel() for p in model.parameters())),
            loss_curve=curve,
        )
        result["out"] = str(tc.out)
    return result


def cached_detector_boxes(
    data: dict[str, np.ndarray], tc: ReclassifierTrainConfig, path: Path, progress: bool
) -> dict[str, np.ndarray]:
    """``detector_boxes`` of ``data``, kept in ``path`` (work dir) and reused while the detector's
    weights and the frames are the same (a resumed run does not detect again)."""
    from tidee.agent.learning import read_manifest
    from tidee.agent.perception.train_detector import DEFAULT_WEIGHTS

    sha = read_manifest(Path(tc.detector) if tc.detector else DEFAULT_WEIGHTS).get("sha256", "")
    key = f"{sha}:{len(data['rgb'])}:{int(data['obj_cls'].sum())}"
    if path.exists():
        with np.load(path) as z:
            if str(z["key"]) == key:
                return {k: z[k] for k in z.files if k != "key"}
    boxes = detector_boxes(data, tc.detector, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, key=np.array(key), **boxes)
    tmp.replace(path)
    return boxes


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
    "ReclassifierConfig",
    "CropClassifier",
    "crop_inputs",
    "frame_tensor",
    "fuse",
    "det_features",
    "warm_start",
    "rows_by_frame",
    "ReclassifierTrainConfig",
    "CropBatches",
    "DetectorBoxBatches",
    "detector_boxes",
    "train_reclassifier",
    "load_reclassifier",
    "DEFAULT_RECLASSIFIER",
]
