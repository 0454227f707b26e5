"""The perception models' commands: ``tidee gen detection``, ``tidee train detector``, ``tidee
train reclassifier``, ``tidee train depth`` and ``tidee eval depth``.

Their options are the fields of the families' ``config`` modules; only those (light) are
imported here. The run functions import torch and the simulator when they run, so ``tidee
server`` and ``tidee viewer`` work on an install without torch.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from tidee.agent.perception.depth.config import DepthEvalConfig, DepthTrainConfig
from tidee.agent.perception.detector.config import GenDetectionConfig, TrainDetectorConfig
from tidee.agent.perception.reclassifier.config import TrainReclassifierConfig
from tidee.options import add_command, to_argv
from tidee.protocol.vocab import HELD_OUT_SPLITS


def run_gen_detection(cfg: GenDetectionConfig) -> int:
    from tidee.agent.perception.detector.data import describe, generate

    print(describe(cfg.gen), file=sys.stderr)
    command = "tidee gen detection " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else "tidee gen detection"
    manifest = generate(cfg, command=command)
    print(
        json.dumps({k: v for k, v in manifest.items() if k not in ("shards", "rooms", "classes")}, indent=1)
    )
    return 0


def run_train_detector(cfg: TrainDetectorConfig) -> int:
    from tidee.agent.perception.detector.train import train_detector

    command = "tidee train detector " + " ".join(sys.argv[3:])
    result = train_detector(cfg.train, cfg.model_config(), resume=not cfg.no_resume, command=command.strip())
    last = result["history"][-1] if result["history"] else {}
    print(
        json.dumps(
            {
                "steps": result["steps"],
                "seconds": result["seconds"],
                "device": result["device"],
                "final_losses": last,
                "weights": result.get("out"),
            },
            indent=1,
        )
    )
    return 0


def run_train_reclassifier(cfg: TrainReclassifierConfig) -> int:
    from tidee.agent.perception.reclassifier.train import train_reclassifier

    command = "tidee train reclassifier " + " ".join(sys.argv[3:])
    result = train_reclassifier(
        cfg.train, cfg.model_config(), resume=not cfg.no_resume, command=command.strip()
    )
    last = result["history"][-1] if result["history"] else {}
    print(
        json.dumps(
            {
                "steps": result["steps"],
                "seconds": result["seconds"],
                "device": result["device"],
                "final": last,
                "weights": result.get("out"),
            },
            indent=1,
        )
    )
    return 0


def run_train_depth(cfg: DepthTrainConfig) -> int:
    from tidee.agent.learning import ships
    from tidee.agent.perception.depth.config import DOCS_LOSS_PNG
    from tidee.agent.perception.depth.train import train_depth

    # every option that shapes the weights, the data as given (else the checkout's data/detection)
    shaping = to_argv(
        cfg,
        skip=("data", "steps", "batch_size", "lr", "seed", "out", "work_dir", "resume", "checkpoint_every"),
    )
    command = " ".join(
        [
            f"tidee train depth --data {cfg.data_spec} --steps {cfg.steps} --batch-size {cfg.batch_size}",
            f"--lr {cfg.lr} --seed {cfg.seed}",
            *shaping,
            *([f"--out {cfg.out}"] if cfg.out else []),
        ]
    )
    # the docs show the shipped curve only
    result = train_depth(cfg, command=command, docs_png=DOCS_LOSS_PNG if ships(cfg.out_path) else None)
    print(json.dumps(result, indent=1))
    return 0


def run_eval_depth(cfg: DepthEvalConfig) -> int:
    from pathlib import Path

    from tidee.agent.learning import sha256_file
    from tidee.agent.perception.depth.eval import (
        evaluate_depth,
        heldout_frames,
        metrics_markdown,
        save_examples,
        time_inference,
    )
    from tidee.agent.perception.depth.model import DepthEstimator
    from tidee.paths import in_checkout
    from tidee.protocol.episode_log import write_json_atomic

    if cfg.split not in HELD_OUT_SPLITS:
        raise ValueError(
            f"tidee eval depth scores held-out rooms: --split must be test or val, got "
            f"{cfg.split!r} (training rooms would measure memorisation)"
        )
    eval_set = cfg.eval_set
    weights = cfg.weights_path
    estimator = DepthEstimator.load(weights)
    frames = heldout_frames(cfg.split, eval_set)
    command = (
        f"tidee eval depth --split {cfg.split} --rooms-per-type {eval_set.rooms_per_type} "
        f"--messes {eval_set.messes} --frames-per-walk {eval_set.frames_per_walk} --out {cfg.out}"
        + (f" --weights {cfg.weights}" if cfg.weights else "")
    )
    result = {
        "split": cfg.split,
        # as given, else the shipped file's place in the checkout (not this machine's path)
        "weights": cfg.weights or in_checkout(weights),
        "sha256": sha256_file(weights),
        "command": command,
        "eval_set": asdict(eval_set),
        "metrics": evaluate_depth(estimator, frames),
        "speed": time_inference(estimator),
    }
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "depth.json", result)
    (out / "depth.md").write_text(metrics_markdown(result))
    save_examples(estimator, frames, out / "depth_examples.png")
    print(metrics_markdown(result))
    return 0


def register(
    gen_sub: argparse._SubParsersAction,
    train_sub: argparse._SubParsersAction,
    eval_sub: argparse._SubParsersAction,
) -> None:
    """``tidee gen detection``, ``tidee train detector|reclassifier|depth`` and ``tidee eval depth``."""
    add_command(
        gen_sub,
        "detection",
        GenDetectionConfig,
        run_gen_detection,
        "RGB-D frames + instance targets from random walks in training rooms",
    )
    add_command(
        train_sub,
        "detector",
        TrainDetectorConfig,
        run_train_detector,
        "the RGB-D detector with its OOP head, on `tidee gen detection` data",
    )
    add_command(
        train_sub,
        "reclassifier",
        TrainReclassifierConfig,
        run_train_reclassifier,
        "the crop classifier that renames the detector's detections, on `tidee gen detection` data",
    )
    add_command(
        train_sub,
        "depth",
        DepthTrainConfig,
        run_train_depth,
        "the depth-from-RGB network (the '+est. depth' setting)",
    )
    add_command(
        eval_sub,
        "depth",
        DepthEvalConfig,
        run_eval_depth,
        "depth network on held-out rooms: abs rel, RMSE, delta<1.25",
    )


__all__ = [
    "register",
    "run_eval_depth",
    "run_gen_detection",
    "run_train_depth",
    "run_train_detector",
    "run_train_reclassifier",
]
