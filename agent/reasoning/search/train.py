"""``tidee train search``: the visual search network on ``tidee gen search`` shards.

Loss: binary cross-entropy on every output cell with positives weighted (``pos_weight``);
each map is turned by a multiple of 90 degrees and mirrored at random, with its instances.
A tenth of the training rooms is held out to report validation metrics. Resumable: a
checkpoint in ``work_dir`` made with the same config is continued.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from tidee.agent.classes import CLASSES
from tidee.agent.reasoning.search.config import SearchTrainConfig
from tidee.agent.reasoning.search.data import load_search_data, target_heat
from tidee.agent.reasoning.search.eval import _as_eval_set, heldout_metrics
from tidee.agent.reasoning.search.model import C_IN, DEFAULT_WEIGHTS, VisualSearch, _build_model
from tidee.paths import PROJECT_DIR

DOCS_LOSS_PNG = PROJECT_DIR / "docs" / "models" / "search_net_loss.png"


def _augment(x: np.ndarray, inst: np.ndarray, k: int, flip: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the map by k*90 degrees about the start pose (and mirror y); the same for the instances."""
    inst = inst.copy()
    if flip:  # y -> -y
        x = x[:, :, ::-1]
        inst[:, 2] *= -1
        inst[:, 5] *= -1
    for _ in range(k):  # (x, y) -> (-y, x): rotate +90 degrees
        x = np.rot90(x, 1, axes=(1, 2))
        cx, cy = inst[:, 1].copy(), inst[:, 2].copy()
        inst[:, 1], inst[:, 2] = -cy, cx
        inst[:, 5] += math.pi / 2
    return np.ascontiguousarray(x), inst


def _batch(
    data: dict[str, Any], idx: Sequence[int] | np.ndarray, rng: np.random.Generator, k_cls: int, augment: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs, cs, ts = [], [], []
    for i in idx:
        x = data["x"][i].astype(np.float32) / 255.0
        inst = data["inst"][data["owner"][i]]
        if augment:
            x, inst = _augment(x, inst, int(rng.integers(4)), bool(rng.integers(2)))
        present = np.unique(inst[:, 0]).astype(np.int64)
        cls = rng.choice(present, size=k_cls, replace=len(present) < k_cls)
        xs.append(x)
        cs.append(cls)
        ts.append(target_heat(inst, cls))
    return np.stack(xs), np.stack(cs), np.stack(ts)


def split_rooms(data: dict[str, Any], val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Snapshot indices (train, val): whole rooms (room type, seed) go to one side."""
    rooms = sorted({(r[0], r[1]) for r in data["rooms"]})
    rng = np.random.default_rng(seed)
    n_val = int(round(val_fraction * len(rooms)))
    val_rooms = {rooms[i] for i in rng.permutation(len(rooms))[:n_val]}
    is_val = np.array([(data["rooms"][o][0], data["rooms"][o][1]) in val_rooms for o in data["owner"]])
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


def train_search_net(
    cfg: SearchTrainConfig,
    command: str = "",
    resume: bool = True,
    progress: bool = True,
    data: dict[str, Any] | None = None,
    ship: bool = True,
    docs_png: Path | None = DOCS_LOSS_PNG,
) -> dict[str, Any]:
    """Train from shards (or ``data``); ship weights + manifest when ``ship``. Returns a summary."""
    import torch
    from tqdm import tqdm

    from tidee.agent.learning import load_checkpoint, save_checkpoint, save_loss_curve, write_manifest

    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    data = data if data is not None else load_search_data(cfg.data)
    tr_idx, va_idx = split_rooms(data, cfg.val_fraction, cfg.seed)
    if len(tr_idx) == 0:
        raise ValueError("no training snapshots left after holding out validation rooms")
    model = _build_model(cfg.width, cfg.embed)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    rng = np.random.default_rng(cfg.seed)
    history: list[dict[str, float]] = []
    step = 0
    work = Path(cfg.work_dir)
    ckpt_path = work / "checkpoint.pt"
    if resume and (ck := load_checkpoint(ckpt_path)) is not None and ck.get("cfg") == asdict(cfg):
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        rng.bit_generator.state = ck["rng"]
        history, step = ck["history"], ck["step"]
    pos_weight = torch.tensor(cfg.pos_weight)
    t0 = time.time()
    model.train()
    bar = tqdm(total=cfg.steps, initial=step, desc="train search net", disable=not progress)
    running = []
    while step < cfg.steps:
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps))
        for g in opt.param_groups:
            g["lr"] = lr
        idx = rng.choice(tr_idx, size=min(cfg.batch_size, len(tr_idx)), replace=False)
        x, c, t = _batch(data, idx, rng, cfg.classes_per_map, augment=True)
        logits = model(torch.from_numpy(x), torch.from_numpy(c))
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            logits, torch.from_numpy(t), pos_weight=pos_weight
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        running.append(float(loss.detach()))
        bar.update()
        if step % cfg.log_every == 0 or step == cfg.steps:
            history.append({"step": step, "train_bce": float(np.mean(running))})
            bar.set_postfix(loss=f"{np.mean(running):.4f}")
            running = []
        if step % cfg.ckpt_every == 0 or step == cfg.steps:
            save_checkpoint(
                ckpt_path,
                model=model.state_dict(),
                opt=opt.state_dict(),
                rng=rng.bit_generator.state,
                history=history,
                step=step,
                cfg=asdict(cfg),
            )
    bar.close()
    model.eval()
    summary: dict[str, Any] = {
        "steps": step,
        "seconds": round(time.time() - t0, 1),
        "history": history,
        "train_snapshots": int(len(tr_idx)),
        "val_snapshots": int(len(va_idx)),
    }
    if len(va_idx):
        vs = VisualSearch(model)
        summary["val"] = heldout_metrics(vs, _as_eval_set(data, va_idx))
        summary["val_bce"] = _mean_bce(model, data, va_idx, cfg)
    save_loss_curve(history, work / "search_net_loss.png", "visual search network (weighted BCE)")
    if ship:
        out = Path(cfg.out) if cfg.out else DEFAULT_WEIGHTS
        save_checkpoint(
            out,
            model=model.state_dict(),
            config={"width": cfg.width, "embed": cfg.embed},
            threshold=0.5,
            classes=list(CLASSES),
            c_in=C_IN,
        )
        if docs_png is not None:
            save_loss_curve(history, docs_png, "visual search network (weighted BCE)")
        rooms = sorted({(r[0], r[1]) for r in data["rooms"]})
        write_manifest(
            out,
            command=command,
            data={
                "dir": cfg.data,
                "snapshots": int(len(data["x"])),
                "configurations": len(data["rooms"]),
                "room_seeds": sorted({s for _, s in rooms}),
                "gen_manifest": _read_gen_manifest(cfg.data),
            },
            metrics={k: summary[k] for k in ("val", "val_bce") if k in summary},
            train={
                **asdict(cfg),
                "seconds": summary["seconds"],
                "final_train_bce": history[-1]["train_bce"] if history else None,
            },
        )
        summary["out"] = str(out)
    return summary


def _read_gen_manifest(path: str | Path) -> dict[str, Any] | None:
    p = Path(path) / "manifest.json"
    if not p.exists():
        return None
    m = json.loads(p.read_text())
    return {k: m.get(k) for k in ("command", "perception", "seeds", "configurations", "note")}


def _mean_bce(model: Any, data: dict[str, Any], idx: np.ndarray, cfg: SearchTrainConfig) -> float:
    import torch

    rng = np.random.default_rng(12345)
    losses = []
    with torch.no_grad():
        for s in range(0, len(idx), cfg.batch_size):
            x, c, t = _batch(data, idx[s : s + cfg.batch_size], rng, cfg.classes_per_map, augment=False)
            losses.append(
                float(
                    torch.nn.functional.binary_cross_entropy_with_logits(
                        model(torch.from_numpy(x), torch.from_numpy(c)),
                        torch.from_numpy(t),
                        pos_weight=torch.tensor(cfg.pos_weight),
                    )
                )
            )
    return float(np.mean(losses))


__all__ = ["DOCS_LOSS_PNG", "split_rooms", "train_search_net"]
