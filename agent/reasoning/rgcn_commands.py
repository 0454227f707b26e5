"""The placement models' commands: ``tidee train rgcn`` and ``tidee eval placement``.
Argparse only at import (the handlers import torch when they run)."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_train(args: argparse.Namespace) -> int:
    from tidee.agent.learning import loss_curve_path
    from tidee.agent.reasoning.rgcn import DEFAULT_WEIGHTS, DEFAULT_WITHOUT_MEMEX, RGCNTrainConfig, train_rgcn

    cfg = RGCNTrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        train_rooms_per_type=args.rooms_per_type,
        use_memex=not args.without_memex,
        threads=args.threads,
    )
    out = args.out or (DEFAULT_WITHOUT_MEMEX if args.without_memex else DEFAULT_WEIGHTS)
    png = loss_curve_path(
        out, "rgcn_without_memex_loss.png" if args.without_memex else "rgcn_loss.png", args.loss_png
    )
    command = ("tidee train rgcn " + " ".join(sys.argv[3:])).strip()
    result = train_rgcn(cfg, out=out, loss_png=png, command=command, cache_dir=args.cache_dir)
    print(
        json.dumps(
            {
                "out": result.get("out"),
                "samples": result["samples"],
                "seconds": result["seconds"],
                "memex_nodes": result["memex_nodes"],
                "final": result["history"][-1],
            },
            indent=1,
        )
    )
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from tidee.agent.reasoning.rgcn import run_placement_eval

    command = ("tidee eval placement " + " ".join(sys.argv[3:])).strip()
    report = run_placement_eval(
        args.out,
        split=args.split,
        weights=args.weights,
        without_memex=args.without_memex_weights,
        cache_dir=args.cache_dir,
        command=command,
        record=args.record,
    )
    print((__import__("pathlib").Path(args.out) / "report.md").read_text())
    return 0 if report["rows"] else 1


def register(train_sub: argparse._SubParsersAction, eval_sub: argparse._SubParsersAction) -> None:
    p = train_sub.add_parser(
        "rgcn", help="Memex + rGCN placement model (or --without-memex) on training rooms"
    )
    p.add_argument(
        "--rooms-per-type",
        type=int,
        default=200,
        help="training rooms per type (training seeds after the 5 Memex memory rooms)",
    )
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--batch-size", type=int, default=128)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--without-memex", action="store_true", help="the WithoutMemex ablation (scene graph only)"
    )
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (0: torch's default)")
    p.add_argument("--out", default=None, help="default agent/weights/rgcn.pt (rgcn_without_memex.pt)")
    p.add_argument("--loss-png", default=None)
    p.add_argument("--cache-dir", default="runs/cache/rgcn", help="generated rooms, reused across runs")
    p.set_defaults(func=_cmd_train)

    p = eval_sub.add_parser("placement", help="rGCN vs WithoutMemex vs CommonMemory on held-out tidy rooms")
    p.add_argument("--split", choices=("test", "val"), default="test")
    p.add_argument("--out", required=True)
    p.add_argument("--weights", default="agent/weights/rgcn.pt")
    p.add_argument("--without-memex-weights", default="agent/weights/rgcn_without_memex.pt")
    p.add_argument("--cache-dir", default="runs/cache/rgcn")
    p.add_argument("--record", action="store_true", help="write the metrics into the weights' manifests")
    p.set_defaults(func=_cmd_eval)
