"""``tidee train reclassifier`` (options: ``config.TrainReclassifierConfig``): the crop
reclassifier (:mod:`.model`), on frames of ``tidee gen detection``.

``--boxes jitter``: crops of the ground-truth boxes, jittered as the detector's boxes are, and
background crops (boxes that overlap no object by IoU 0.3). Reproducible from a seed,
resumable, progress bar, loss curve.

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
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from tidee.agent.learning import (
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
from tidee.agent.perception.reclassifier.config import (
    BOX_SOURCES,
    ReclassifierConfig,
    ReclassifierTrainConfig,
)
from tidee.agent.perception.reclassifier.model import CropClassifier, crop_inputs, det_features, frame_tensor

IGNORE = -100  # a training label the loss skips (a box between object and background)


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

    from tidee.agent.evaluation.detection.metrics import box_iou
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
        return dict(self.rng.bit_generator.state)

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
        from tidee.agent.evaluation.detection.metrics import box_iou

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

    from tidee.agent.perception.detector.data import load_datasets
    from tidee.agent.perception.detector.train import lr_at

    if tc.boxes not in BOX_SOURCES:
        raise ValueError(f"boxes must be one of {BOX_SOURCES}, got {tc.boxes!r}")
    tc = tc.resolved()  # default paths filled in, as the checkpoint and manifest record them
    if tc.threads:
        torch.set_num_threads(tc.threads)
    device = pick_device(tc.device)
    torch.manual_seed(tc.seed)
    cfg = cfg or ReclassifierConfig()
    if tc.boxes == "detector":
        cfg = ReclassifierConfig.from_dict({**cfg.to_dict(), "det_inputs": True})
    manifests: list[dict[str, Any]] = []
    if data is None:
        data, manifests = load_datasets(tc.data_spec, limit=tc.limit_frames)
    model = CropClassifier(cfg)
    init_sha = None
    if tc.init:
        from tidee.agent.learning import sha256_file

        init_sha = sha256_file(tc.init)  # the init file may be replaced by these weights when shipped
        warm_start(model, tc.init)
    model = model.to(device, memory_format=torch.channels_last)
    precision = resolve_precision(tc.precision, device)
    opt = torch.optim.AdamW(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
    work = tc.work_path
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
        curve = ship_weights(tc.out_path, model, cfg.to_dict(), work / "loss.png", "reclassifier_loss.png")
        result["manifest"] = write_manifest(
            tc.out_path,
            command=command,
            data=dataset_record(
                tc.data_spec,
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
        result["out"] = tc.out_path
    return result


def cached_detector_boxes(
    data: dict[str, np.ndarray], tc: ReclassifierTrainConfig, path: Path, progress: bool
) -> dict[str, np.ndarray]:
    """``detector_boxes`` of ``data``, kept in ``path`` (work dir) and reused while the detector's
    weights and the frames are the same (a resumed run does not detect again)."""
    from tidee.agent.learning import read_manifest
    from tidee.agent.perception.detector.config import DEFAULT_WEIGHTS

    sha = read_manifest(Path(tc.detector) if tc.detector else DEFAULT_WEIGHTS).get("sha256", "")
    key = f"{sha}:{len(data['rgb'])}:{int(data['obj_cls'].sum())}"
    if path.exists():
        with np.load(path) as z:
            if str(z["key"]) == key:
                return {k: z[k] for k in z.files if k != "key"}
    boxes = detector_boxes(data, tc.detector, progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    arrays: dict[str, Any] = {"key": np.array(key), **boxes}
    np.savez(tmp, **arrays)
    tmp.replace(path)
    return boxes


__all__ = [
    "CropBatches",
    "DetectorBoxBatches",
    "detector_boxes",
    "cached_detector_boxes",
    "rows_by_frame",
    "train_reclassifier",
    "warm_start",
    "IGNORE",
]
