"""``tidee train rgcn``: the Memex + rGCN (or WithoutMemex) on tidy training rooms.

Each step samples objects of the training rooms, takes each out of its room's scene graph
with some other nodes dropped (the agent never maps every object) and its box size
jittered (the agent's boxes are estimates), and learns the receptacle type it was on.
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
from torch import nn

from tidee.agent.learning import save_checkpoint, save_loss_curve, write_manifest
from tidee.agent.reasoning.rgcn.config import DEFAULT_CACHE, RGCNConfig, RGCNTrainConfig
from tidee.agent.reasoning.rgcn.data import PlacementData, placement_data
from tidee.agent.reasoning.rgcn.memex import Graph
from tidee.agent.reasoning.rgcn.model import PlacementRGCN, collate
from tidee.agent.reasoning.stats import _ranges
from tidee.protocol.vocab import ROOM_TYPES


def _augment(g: Graph, t: int, rng: np.random.Generator, drop: float) -> tuple[np.ndarray, np.ndarray]:
    """Scene nodes kept (the agent never maps every object) and the OOP box with estimation noise."""
    keep = rng.random(len(g)) >= drop
    geom = g.geom[t].copy()
    geom[:3] += rng.normal(0.0, 0.12, 3)  # log sizes: +-12 % (its heights are not read)
    return keep, geom


def train_rgcn(
    cfg: RGCNTrainConfig,
    out: str | Path | None = None,
    loss_png: str | Path | None = None,
    command: str = "tidee train rgcn",
    data: PlacementData | None = None,
    progress: bool = True,
    cache_dir: str | Path | None = DEFAULT_CACHE,
) -> dict[str, Any]:
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    data = data or placement_data(cfg.train_rooms_per_type, cache_dir=cache_dir, progress=progress)
    index = [(r, k) for r, room in enumerate(data.rooms) for k in range(len(room.targets))]
    if not index:
        raise ValueError("no training samples: the training rooms have no pickupable object on a receptacle")
    model = PlacementRGCN(RGCNConfig(hidden=cfg.hidden, use_memex=cfg.use_memex))
    if cfg.use_memex:
        model.set_memex(data.memex)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    history: list[dict[str, float]] = []
    t0 = time.time()
    model.train()
    running = []
    bar = tqdm(
        range(cfg.steps), desc="rgcn" if cfg.use_memex else "rgcn (without memex)", disable=not progress
    )
    for step in bar:
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps))
        for group in opt.param_groups:
            group["lr"] = lr
        pick = rng.integers(0, len(index), cfg.batch_size)
        items, keep, geoms, ys = [], [], [], []
        for p in pick:
            r, k = index[p]
            room = data.rooms[r]
            t = int(room.targets[k])
            kp, geom = _augment(room.graph, t, rng, cfg.node_drop)
            items.append((room.graph, t, None, ROOM_TYPES.index(room.room_type)))
            keep.append(kp)
            geoms.append(geom)
            ys.append(int(room.labels[k]))
        batch = collate(items, keep, geoms)
        loss = F.cross_entropy(model(batch), torch.as_tensor(ys))
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        running.append(float(loss.detach()))
        if (step + 1) % 50 == 0 or step + 1 == cfg.steps:
            history.append({"step": step + 1, "cross_entropy": float(np.mean(running))})
            bar.set_postfix(loss=f"{np.mean(running):.3f}")
            running = []
    seconds = time.time() - t0
    result: dict[str, Any] = {
        "history": history,
        "seconds": round(seconds, 1),
        "samples": len(index),
        "memex_nodes": len(data.memex) if cfg.use_memex else 0,
        "model": model,
    }
    if out is not None:
        out = Path(out)
        save_checkpoint(out, state_dict=model.state_dict(), config=asdict(model.cfg))
        if loss_png is not None:
            save_loss_curve(
                history, loss_png, "rGCN placement" + ("" if cfg.use_memex else " (WithoutMemex)")
            )
        write_manifest(
            out,
            command=command,
            data={
                "memory_rooms": {"room_types": list(ROOM_TYPES), "seeds": data.memory_seeds},
                "training_rooms": {
                    "room_types": list(ROOM_TYPES),
                    "seeds": _ranges(data.train_seeds),
                    "n_per_type": len(data.train_seeds),
                },
                "samples": len(index),
                "memex_nodes": result["memex_nodes"],
                "memex_edges": int(len(data.memex.edges)) if cfg.use_memex else 0,
            },
            metrics={"final_train_cross_entropy": history[-1]["cross_entropy"]},
            train_config=asdict(cfg),
            train_seconds=round(seconds, 1),
            parameters=int(sum(p.numel() for p in model.parameters())),
        )
        result["out"] = str(out)
    return result


__all__ = ["train_rgcn"]
