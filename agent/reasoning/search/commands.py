"""The visual search network's commands: ``tidee gen search``, ``tidee train search`` and
``tidee eval search``. Light at import (argparse and the configs); each run function imports
torch and the simulator when it runs."""

from __future__ import annotations

import argparse
import json

from tidee.agent.reasoning.search.config import SearchEvalConfig, SearchGenConfig, SearchTrainCommand
from tidee.options import add_command, to_argv


def gen_search_command(cfg: SearchGenConfig) -> int:
    from tidee.agent.reasoning.search.data import generate_search_data

    command = " ".join(["tidee gen search", *to_argv(cfg)])
    print(json.dumps(generate_search_data(cfg, command=command), indent=1))
    return 0


def train_search_command(cfg: SearchTrainCommand) -> int:
    from tidee.agent.learning import ships
    from tidee.agent.reasoning.search.model import DEFAULT_WEIGHTS
    from tidee.agent.reasoning.search.train import DOCS_LOSS_PNG, train_search_net

    result = train_search_net(
        cfg.train,
        command=" ".join(["tidee train search", *to_argv(cfg)]),
        resume=cfg.resume,
        docs_png=DOCS_LOSS_PNG if ships(cfg.train.out or DEFAULT_WEIGHTS) else None,
    )
    result.pop("history", None)
    print(json.dumps(result, indent=1))
    return 0


def eval_search_command(cfg: SearchEvalConfig) -> int:
    from tidee.agent.reasoning.search.eval import markdown, run_search_eval

    # the main settings spelled out, defaults included: the report names the protocol it measured
    command = (
        f"tidee eval search --split {cfg.split} --methods {','.join(cfg.methods)} "
        f"--categories-per-room {cfg.categories_per_room or 0} --max-steps {cfg.max_steps} "
        f"--radius {cfg.radius} --perception {cfg.perception} --workers {cfg.workers} --seed {cfg.seed} "
        f"--out {cfg.out}"
        + (f" --weights {cfg.weights}" if cfg.weights else "")
        + (f" --rooms {cfg.rooms}" if cfg.rooms else "")
        + (f" --explored-discount {cfg.explored_discount}" if cfg.explored_discount else "")
        + (f" --network-fallback {cfg.network_fallback}" if cfg.network_fallback != "random" else "")
        + (f" --backend {cfg.batch.backend}" if cfg.batch.backend != "local" else "")
        + (f" --ray-address {cfg.batch.ray_address}" if cfg.batch.ray_address else "")
    )
    print(markdown(run_search_eval(cfg, command=command)))
    return 0


def register(
    gen_sub: argparse._SubParsersAction,
    train_sub: argparse._SubParsersAction,
    eval_sub: argparse._SubParsersAction,
) -> None:
    """``tidee gen search``, ``tidee train search`` and ``tidee eval search`` (Table 2)."""
    add_command(
        gen_sub,
        "search",
        SearchGenConfig,
        gen_search_command,
        help="map snapshots + ground-truth object positions for the search network",
    )
    add_command(
        train_sub,
        "search",
        SearchTrainCommand,
        train_search_command,
        help="the visual search network, on `tidee gen search` data",
    )
    add_command(
        eval_sub,
        "search",
        SearchEvalConfig,
        eval_search_command,
        help="object search on held-out rooms: search network vs frontier (Table 2)",
    )


__all__ = ["eval_search_command", "gen_search_command", "register", "train_search_command"]
