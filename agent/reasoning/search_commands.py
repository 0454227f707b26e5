"""The visual search network's commands: ``tidee gen search``, ``tidee train search`` and
``tidee eval search``. Argparse only at import: the handlers import torch when they run."""

from __future__ import annotations

import argparse
import json
import sys


def _command(prefix: str) -> str:
    """The command line as typed (``tidee gen search ...``), for manifests and reports."""
    return (prefix + " " + " ".join(sys.argv[3:])).strip()


def _cmd_gen_search(args: argparse.Namespace) -> int:
    from tidee.agent.reasoning.search_net import SearchGenConfig, generate_search_data

    cfg = SearchGenConfig(
        out=args.out,
        split=args.split,
        rooms_per_type=args.rooms_per_type,
        messes_per_room=args.messes,
        snapshots=args.snapshots,
        max_steps=args.max_steps,
        perception=args.perception,
        seed=args.seed,
        workers=args.workers,
    )
    print(json.dumps(generate_search_data(cfg, command=_command("tidee gen search")), indent=1))
    return 0


def _cmd_train_search(args: argparse.Namespace) -> int:
    from tidee.agent.learning import ships
    from tidee.agent.reasoning.search_net import DOCS_LOSS_PNG, SearchTrainConfig, train_search_net

    cfg = SearchTrainConfig(
        data=args.data,
        out=args.out,
        work_dir=args.work_dir,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        pos_weight=args.pos_weight,
        seed=args.seed,
        threads=args.threads,
    )
    result = train_search_net(
        cfg,
        command=_command("tidee train search"),
        resume=not args.no_resume,
        docs_png=DOCS_LOSS_PNG if ships(args.out) else None,
    )
    result.pop("history", None)
    print(json.dumps(result, indent=1))
    return 0


def int_at_least(minimum: int):
    """An argparse type: a whole number >= ``minimum``, with an error that says which was wrong."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected a number >= {minimum}, got {v}")
        return v

    return parse


_positive_int = int_at_least(1)


def register(gen_sub: argparse._SubParsersAction, train_sub: argparse._SubParsersAction) -> None:
    """``tidee gen search`` and ``tidee train search``."""
    p = gen_sub.add_parser(
        "search", help="map snapshots + ground-truth object positions for the search network"
    )
    p.add_argument("--out", default="data/search")
    p.add_argument(
        "--split",
        default="train",
        choices=("train", "val", "test"),
        help="train for training data; val/test only for held-out evaluation sets",
    )
    p.add_argument(
        "--rooms-per-type",
        type=_positive_int,
        default=25,
        help="train: seeds 0-19 first, then the training pool",
    )
    p.add_argument("--messes", type=int, default=1, help="messy configurations per room besides the tidy one")
    p.add_argument("--snapshots", type=_positive_int, default=6, help="map snapshots per configuration")
    p.add_argument("--max-steps", type=_positive_int, default=200, help="exploration steps per configuration")
    p.add_argument(
        "--perception",
        default="oracle",
        choices=("oracle", "learned"),
        help="detections that build the maps (oracle: the simulator's segmentation, cheaper)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, choices=(1, 2))
    p.set_defaults(func=_cmd_gen_search)

    p = train_sub.add_parser("search", help="the visual search network, on `tidee gen search` data")
    p.add_argument("--data", default="data/search")
    p.add_argument("--out", default="agent/weights/search_net.pt", help="shipped weights (+ .json manifest)")
    p.add_argument("--work-dir", default="runs/search/train", help="checkpoint and loss curve (resumable)")
    p.add_argument("--steps", type=_positive_int, default=1200)
    p.add_argument("--batch-size", type=_positive_int, default=8)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--pos-weight", type=float, default=10.0, help="BCE weight of positive cells")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="CPU threads (0: torch's default)")
    p.add_argument("--no-resume", action="store_true", help="ignore a checkpoint in --work-dir")
    p.set_defaults(func=_cmd_train_search)


def register_eval(eval_sub: argparse._SubParsersAction) -> None:
    """``tidee eval search`` (Table 2)."""
    from tidee.agent.evaluation.search_eval import add_eval_arguments

    p = eval_sub.add_parser(
        "search", help="object search on held-out rooms: search network vs frontier (Table 2)"
    )
    add_eval_arguments(p)


__all__ = ["register", "register_eval"]
