"""The perception models' commands: ``tidee train detector``, ``tidee train reclassifier``, ``tidee train depth``,
``tidee eval depth``. Argparse only at import: the handlers import torch when they run, so
``tidee server`` and ``tidee viewer`` work on an install without torch."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path


def _cmd_train_detector(args: argparse.Namespace) -> int:
    from tidee.agent.perception.detector import DetectorConfig
    from tidee.agent.perception.train_detector import TrainConfig, train_detector

    try:
        extra = tuple(int(x) for x in args.extra_blocks.split(","))
    except ValueError:
        raise SystemExit(f"--extra-blocks wants integers like 0,1,1, not {args.extra_blocks!r}") from None
    if len(extra) not in (3, 4) or min(extra) < 0:
        raise SystemExit(
            "--extra-blocks wants three non-negative integers (stride 8, 16, 32) or four "
            f"(stride 4, 8, 16, 32), not {args.extra_blocks!r}"
        )
    extra_s4, extra = (extra[0], extra[1:]) if len(extra) == 4 else (0, extra)
    cfg = TrainConfig(
        data=args.data,
        out=args.out,
        work_dir=args.work_dir,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        threads=args.threads,
        limit_frames=args.limit_frames,
        init=args.init,
        warmup=args.warmup,
        precision=args.precision,
        loader_workers=args.loader_workers,
    )
    model_cfg = DetectorConfig(extra_blocks=extra, head_conv=args.head_conv, extra_s4=extra_s4)
    command = "tidee train detector " + " ".join(sys.argv[3:])
    result = train_detector(cfg, model_cfg, resume=not args.no_resume, command=command.strip())
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


def _cmd_train_reclassifier(args: argparse.Namespace) -> int:
    from tidee.agent.perception.reclassifier import (
        ReclassifierConfig,
        ReclassifierTrainConfig,
        train_reclassifier,
    )

    tc = ReclassifierTrainConfig(
        data=args.data,
        out=args.out,
        work_dir=args.work_dir,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        threads=args.threads,
        limit_frames=args.limit_frames,
        precision=args.precision,
        boxes=args.boxes,
        detector=args.detector,
        init=args.init,
        background=args.background,
    )
    command = "tidee train reclassifier " + " ".join(sys.argv[3:])
    result = train_reclassifier(
        tc, ReclassifierConfig(crop=args.crop), resume=not args.no_resume, command=command.strip()
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


def register(train_sub: argparse._SubParsersAction, eval_sub: argparse._SubParsersAction) -> None:
    """``tidee train detector``, ``tidee train reclassifier``, ``tidee train depth`` and ``tidee eval depth``."""
    p = train_sub.add_parser(
        "detector", help="the RGB-D detector with its OOP head, on `tidee gen detection` data"
    )
    p.add_argument(
        "--data",
        default="data/detection",
        help="directory of `tidee gen detection` shards, or several, comma-separated (different rooms)",
    )
    p.add_argument("--out", default="agent/weights/detector.pt", help="shipped weights (+ .json manifest)")
    p.add_argument("--work-dir", default="runs/detector", help="checkpoints and the loss curve (resumable)")
    p.add_argument("--steps", type=int, default=5500)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default)")
    p.add_argument(
        "--limit-frames", type=int, default=None, help="train on the first N frames only (smoke runs)"
    )
    p.add_argument("--no-resume", action="store_true", help="ignore a checkpoint in --work-dir")
    p.add_argument("--warmup", type=int, default=200, help="steps of linear learning-rate warm-up")
    p.add_argument(
        "--loader-workers",
        type=int,
        default=0,
        help="build batches in this many processes (a GPU outruns one); a run is reproducible "
        "for a given count. 0: in the training process",
    )
    p.add_argument(
        "--init",
        default=None,
        help="start from these detector weights; with --extra-blocks / --head-conv the model grows "
        "around them, starting as exactly the same function",
    )
    p.add_argument(
        "--extra-blocks",
        default="0,0,0",
        help="extra residual blocks at stride 8,16,32, or 4,8,16,32 (identity at start)",
    )
    p.add_argument(
        "--precision",
        choices=("auto", "fp32", "bf16"),
        default="auto",
        help="bf16 autocast + channels-last (about 2x faster on a CPU with AVX512-BF16); "
        "auto: bf16 where the CPU or GPU supports it, fp32 otherwise",
    )
    p.add_argument(
        "--head-conv",
        action="store_true",
        help="a depthwise-separable conv before the heads (identity at start)",
    )
    p.set_defaults(func=_cmd_train_detector)

    p = train_sub.add_parser(
        "reclassifier",
        help="the crop classifier that renames the detector's detections, on `tidee gen detection` data",
    )
    p.add_argument(
        "--data", default="data/detection_d", help="comma-separated `tidee gen detection` directories"
    )
    p.add_argument(
        "--out", default="agent/weights/reclassifier.pt", help="shipped weights (+ .json manifest)"
    )
    p.add_argument(
        "--work-dir", default="runs/reclassifier", help="checkpoints and the loss curve (resumable)"
    )
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--batch-size", type=int, default=256, help="crops per step")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--crop", type=int, default=40, help="crop side in pixels")
    p.add_argument(
        "--boxes",
        choices=("jitter", "detector"),
        default="jitter",
        help="jitter: jittered ground-truth boxes; detector: the detector's own detections on the "
        "frames, and the network also reads the detector's class logits (a learned fusion)",
    )
    p.add_argument(
        "--detector",
        default=None,
        help="--boxes detector: the detector's weights (default: the shipped ones)",
    )
    p.add_argument("--init", default=None, help="start from these reclassifier weights (same crop network)")
    p.add_argument(
        "--background", type=float, default=0.2, help="share of each batch drawn as background boxes"
    )
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default)")
    p.add_argument(
        "--limit-frames", type=int, default=None, help="train on the first N frames only (smoke runs)"
    )
    p.add_argument("--no-resume", action="store_true", help="ignore a checkpoint in --work-dir")
    p.add_argument(
        "--precision",
        choices=("auto", "fp32", "bf16"),
        default="auto",
        help="auto: bf16 autocast where the CPU or GPU has it",
    )
    p.set_defaults(func=_cmd_train_reclassifier)

    p = train_sub.add_parser("depth", help="the depth-from-RGB network (the '+est. depth' setting)")
    p.add_argument("--data", default="data/detection", help="frames from `tidee gen detection`")
    p.add_argument(
        "--out",
        default=None,
        help="weights file, default agent/weights/depth.pt (its manifest .json goes beside it)",
    )
    p.add_argument("--steps", type=int, default=1200)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto | cpu | cuda")
    p.add_argument("--work-dir", default="runs/depth", help="checkpoint and loss curve")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint in --work-dir")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.set_defaults(func=_cmd_train_depth)

    p = eval_sub.add_parser("depth", help="depth network on held-out rooms: abs rel, RMSE, delta<1.25")
    p.add_argument("--split", default="test", help="test or val (held-out rooms only)")
    p.add_argument("--weights", default=None, help="default: agent/weights/depth.pt")
    p.add_argument("--rooms-per-type", type=int, default=5)
    p.add_argument("--messes", type=int, default=1, help="messy configurations per room (plus the tidy one)")
    p.add_argument("--frames-per-walk", type=int, default=5)
    p.add_argument("--out", required=True, help="directory for depth.json, depth.md, depth_examples.png")
    p.set_defaults(func=_cmd_eval_depth)


def _cmd_train_depth(args: argparse.Namespace) -> int:
    from tidee.agent.learning import ships
    from tidee.agent.perception.depth_net import DEFAULT_WEIGHTS, DOCS_LOSS_PNG, train_depth

    command = (
        f"tidee train depth --data {args.data} --steps {args.steps} --batch-size {args.batch_size} "
        f"--lr {args.lr} --seed {args.seed}" + (f" --out {args.out}" if args.out else "")
    )
    out = Path(args.out) if args.out else DEFAULT_WEIGHTS
    result = train_depth(
        args.data,
        out,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        device=args.device,
        resume=args.resume,
        command=command,
        work_dir=args.work_dir,
        checkpoint_every=args.checkpoint_every,
        docs_png=DOCS_LOSS_PNG if ships(out) else None,
    )  # the docs show the shipped curve only
    print(json.dumps(result, indent=1))
    return 0


def _cmd_eval_depth(args: argparse.Namespace) -> int:
    from tidee.agent.perception.depth_net import (
        DEFAULT_WEIGHTS,
        DepthEstimator,
        EvalSet,
        evaluate_depth,
        heldout_frames,
        metrics_markdown,
        save_examples,
        time_inference,
    )
    from tidee.protocol.episode_log import write_json_atomic

    if args.split not in ("val", "test"):
        raise ValueError(
            f"tidee eval depth scores held-out rooms: --split must be test or val, got "
            f"{args.split!r} (training rooms would measure memorisation)"
        )
    eval_set = EvalSet(
        rooms_per_type=args.rooms_per_type, messes=args.messes, frames_per_walk=args.frames_per_walk
    )
    weights = Path(args.weights) if args.weights else DEFAULT_WEIGHTS
    estimator = DepthEstimator.load(weights)
    frames = heldout_frames(args.split, eval_set)
    command = (
        f"tidee eval depth --split {args.split} --rooms-per-type {args.rooms_per_type} "
        f"--messes {args.messes} --frames-per-walk {args.frames_per_walk} --out {args.out}"
        + (f" --weights {args.weights}" if args.weights else "")
    )
    result = {
        "split": args.split,
        "weights": str(weights),
        "command": command,
        "eval_set": asdict(eval_set),
        "metrics": evaluate_depth(estimator, frames),
        "speed": time_inference(estimator),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "depth.json", result)
    (out / "depth.md").write_text(metrics_markdown(result))
    save_examples(estimator, frames, out / "depth_examples.png")
    print(metrics_markdown(result))
    return 0
