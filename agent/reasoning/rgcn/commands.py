"""The placement models' commands: ``tidee train rgcn``, ``tidee eval placement`` and
``tidee eval ceiling``. Light at import (argparse and the configs); each run function imports
torch and the simulator when it runs."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from tidee.agent.reasoning.rgcn.config import (
    SURVEY_FIRST_SEED,
    CeilingConfig,
    PlacementEvalConfig,
    RGCNTrainCommand,
)
from tidee.options import add_command, to_argv


def train_rgcn_command(cfg: RGCNTrainCommand) -> int:
    from tidee.agent.learning import loss_curve_path
    from tidee.agent.reasoning.rgcn.model import DEFAULT_WEIGHTS, DEFAULT_WITHOUT_MEMEX
    from tidee.agent.reasoning.rgcn.train import train_rgcn

    train = dataclasses.replace(cfg.train, use_memex=cfg.train.use_memex and not cfg.without_memex)
    out = cfg.out or (DEFAULT_WEIGHTS if train.use_memex else DEFAULT_WITHOUT_MEMEX)
    png = loss_curve_path(
        out, "rgcn_loss.png" if train.use_memex else "rgcn_without_memex_loss.png", cfg.loss_png
    )
    command = " ".join(["tidee train rgcn", *to_argv(cfg)])
    result = train_rgcn(train, out=out, loss_png=png, command=command, cache_dir=cfg.cache_dir)
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


def eval_placement_command(cfg: PlacementEvalConfig) -> int:
    from tidee.agent.reasoning.rgcn.eval import run_placement_eval

    report = run_placement_eval(cfg, command=" ".join(["tidee eval placement", *to_argv(cfg)]))
    print((Path(cfg.out) / "report.md").read_text())
    return 0 if report["rows"] else 1


def eval_ceiling_command(cfg: CeilingConfig) -> int:
    from tidee.agent.evaluation.ceiling import markdown, run_ceiling

    # every survey setting spelled out: the report names the survey it measured
    command = (
        "tidee eval ceiling "
        + " ".join(f"--report {r}" for r in cfg.report)
        + f" --rooms-per-type {cfg.rooms_per_type} --rooms-version {cfg.rooms_version}"
        + (f" --first-seed {cfg.first_seed}" if cfg.first_seed != SURVEY_FIRST_SEED else "")
        + f" --out {cfg.out}"
    )
    print(markdown(run_ceiling(cfg, command=command)))
    return 0


def register(
    gen_sub: argparse._SubParsersAction,
    train_sub: argparse._SubParsersAction,
    eval_sub: argparse._SubParsersAction,
) -> None:
    """``tidee train rgcn``, ``tidee eval placement`` and ``tidee eval ceiling``. The placement
    family has no ``gen`` command (its rooms are generated and cached by training); ``gen_sub``
    keeps every family's ``register`` the same."""
    add_command(
        train_sub,
        "rgcn",
        RGCNTrainCommand,
        train_rgcn_command,
        help="Memex + rGCN placement model (or --without-memex) on training rooms",
    )
    add_command(
        eval_sub,
        "placement",
        PlacementEvalConfig,
        eval_placement_command,
        help="rGCN vs WithoutMemex vs CommonMemory on held-out tidy rooms",
    )
    add_command(
        eval_sub,
        "ceiling",
        CeilingConfig,
        eval_ceiling_command,
        help="the judge preference a perfect learner of the tidy rooms could reach",
    )


__all__ = ["eval_ceiling_command", "eval_placement_command", "register", "train_rgcn_command"]
