"""The language OOP family's commands: ``tidee train language-oop``, ``tidee train fused-oop``,
``tidee eval language-oop``, ``tidee eval instruct``, ``tidee gen oop-memory`` and
``tidee eval oop-memory``.

Each command's flags are the fields of its config dataclass (:mod:`.config`). Only that light
module is imported here: the handlers import torch, the simulator and the models when they
run, so building the parser stays cheap.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tidee.agent.reasoning.language_oop.config import (
    FusedTrainConfig,
    InstructEvalConfig,
    LanguageEvalConfig,
    MemoryEvalConfig,
    MemoryGenConfig,
    TrainConfig,
)
from tidee.options import add_command


def _set_threads(n: int) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


def train_language(cfg: TrainConfig) -> int:
    from tidee.agent.reasoning.language_oop.train import train_language_oop

    _set_threads(cfg.threads)
    command = "tidee train language-oop " + " ".join(sys.argv[3:])
    result = train_language_oop(cfg, command=command.strip())
    print(
        json.dumps(
            {
                "weights": result["weights"],
                "data": result["data"],
                "timing": result["timing"],
                "metrics": result["metrics"],
            },
            indent=1,
            default=float,
        )
    )
    return 0


def eval_language(cfg: LanguageEvalConfig) -> int:
    from tidee.agent.reasoning.language_oop.eval import run_language_eval

    _set_threads(cfg.threads)
    run_language_eval(cfg)
    print((Path(cfg.out) / "language_oop.md").read_text())
    return 0


def eval_instruct(cfg: InstructEvalConfig) -> int:
    from tidee.agent.reasoning.language_oop.instruct_eval import run_instruct_eval

    _set_threads(cfg.threads)
    run_instruct_eval(cfg)
    print((Path(cfg.out) / "instruct.md").read_text())
    return 0


def train_fused(cfg: FusedTrainConfig) -> int:
    import torch

    from tidee.agent.reasoning.language_oop.fused_train import train_fused_oop

    torch.set_num_threads(max(1, cfg.threads))
    r = train_fused_oop(cfg, command="tidee " + " ".join(sys.argv[1:]))
    print(json.dumps({k: r[k] for k in ("weights", "metrics", "data", "timing")}, indent=1, default=str))
    return 0


def gen_memory(cfg: MemoryGenConfig) -> int:
    from tidee.agent.reasoning.language_oop.memory_data import gen_memory_samples

    meta = gen_memory_samples(cfg, command="tidee gen oop-memory " + " ".join(sys.argv[3:]))
    print(json.dumps(meta, indent=1))
    return 0


def eval_memory(cfg: MemoryEvalConfig) -> int:
    from tidee.agent.reasoning.language_oop.eval import run_memory_eval

    run_memory_eval(cfg)
    print((Path(cfg.out) / "report.md").read_text())
    return 0


def register(
    train_sub: argparse._SubParsersAction,
    eval_sub: argparse._SubParsersAction,
    gen_sub: argparse._SubParsersAction,
) -> None:
    """``tidee train language-oop`` and ``fused-oop``; ``tidee eval language-oop``, ``instruct``
    and ``oop-memory``; ``tidee gen oop-memory``."""
    add_command(
        train_sub,
        "language-oop",
        TrainConfig,
        train_language,
        "the language out-of-place head (BERT-OOP) on training rooms",
    )
    add_command(
        train_sub,
        "fused-oop",
        FusedTrainConfig,
        train_fused,
        "the fused OOP head (dDETR+BERT-OOP) on real detector features",
    )
    add_command(
        eval_sub,
        "language-oop",
        LanguageEvalConfig,
        eval_language,
        "Oracle-language AP: the language head on ground-truth relations",
    )
    add_command(
        eval_sub,
        "instruct",
        InstructEvalConfig,
        eval_instruct,
        "altering placement priors by instruction (paper Table S2)",
    )
    add_command(
        gen_sub,
        "oop-memory",
        MemoryGenConfig,
        gen_memory,
        "OOP samples from the agent's own object memory (mapping phase)",
    )
    add_command(
        eval_sub,
        "oop-memory",
        MemoryEvalConfig,
        eval_memory,
        "OOP classifiers on held-out paragraphs of the agent's own memory",
    )
