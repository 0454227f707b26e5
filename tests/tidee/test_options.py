"""The dataclass is the command line: every flag of every command comes from a config field."""

from __future__ import annotations

import argparse
import dataclasses
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import pytest

from tidee.argtypes import positive_int
from tidee.cli import build_parser
from tidee.options import add_options, configs_of, from_args, leaves, option, to_argv


def _leaf_parsers(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, child in action.choices.items():
            yield from _leaf_parsers(child, (*path, name))


COMMANDS = list(_leaf_parsers(build_parser()))


def test_the_cli_has_its_commands() -> None:
    names = {" ".join(path) for path, _ in COMMANDS}
    assert {"server", "agent", "run", "demo", "viewer", "eval tidy", "bench sim", "gen cache"} <= names
    assert len(names) >= 30


@pytest.mark.parametrize("path,parser", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_every_flag_is_a_config_field_with_the_fields_default(path: tuple[str, ...], parser) -> None:
    configs = configs_of(parser)
    assert configs, f"tidee {' '.join(path)} declares no config dataclass"
    fields = {}
    for cls, skip in configs:
        for leaf in leaves(cls):
            if leaf.path[-1] in skip or ".".join(leaf.path) in skip:
                continue
            fields[leaf.dest] = leaf
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.dest in fields, f"tidee {' '.join(path)} {action.option_strings}: not a config field"
        leaf = fields.pop(action.dest)
        want = None if leaf.default is dataclasses.MISSING else leaf.default
        assert action.default == want, f"tidee {' '.join(path)} {action.option_strings}"
        assert action.required == (leaf.default is dataclasses.MISSING)
    assert not fields, f"fields without a flag: {sorted(fields)}"


@dataclass
class _Inner:
    k: int = option(3, "k")
    mode: Literal["a", "b"] = option("a", "mode")


@dataclass
class _Outer:
    out: str = option(help="required")
    n: int = option(5, "n", type=positive_int)
    flag: bool = option(False, "off by default")
    viewer: bool = option(True, "on by default")
    names: tuple[str, ...] = option(("x", "y"), "comma list")
    sizes: tuple[int, ...] = option((1, 2), "several values", nargs="+")
    maybe: float | None = option(None, "optional")
    hidden: int = option(9, "not on the command line", cli=False)
    inner: _Inner = option(default_factory=functools.partial(_Inner, k=7))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(exit_on_error=False)
    add_options(p, _Outer)
    return p


def test_flags_types_and_nested_defaults_come_from_the_fields() -> None:
    args = _parser().parse_args(
        ["--out", "o", "--no-viewer", "--names", "q,r", "--sizes", "3", "4", "--mode", "b", "--maybe", "0.5"]
    )
    cfg = from_args(_Outer, args)
    assert cfg == _Outer(
        out="o", viewer=False, names=("q", "r"), sizes=(3, 4), maybe=0.5, inner=_Inner(k=7, mode="b")
    )
    defaults = from_args(_Outer, _parser().parse_args(["--out", "o"]))
    assert defaults.inner.k == 7 and defaults.hidden == 9 and defaults.n == 5


def test_to_argv_round_trips_only_what_differs_from_the_defaults() -> None:
    cfg = _Outer(out="o", n=6, flag=True, viewer=False, sizes=(5,), inner=_Inner(k=2, mode="b"))
    argv = to_argv(cfg)
    assert argv == [
        "--out",
        "o",
        "--n",
        "6",
        "--flag",
        "--no-viewer",
        "--sizes",
        "5",
        "--k",
        "2",
        "--mode",
        "b",
    ]
    assert from_args(_Outer, _parser().parse_args(argv)) == cfg


def test_a_validator_refuses_in_its_own_words_and_choices_are_enforced() -> None:
    with pytest.raises(argparse.ArgumentError, match="expected an integer >= 1, got 0"):
        _parser().parse_args(["--out", "o", "--n", "0"])
    with pytest.raises(argparse.ArgumentError, match="invalid choice"):
        _parser().parse_args(["--out", "o", "--mode", "c"])


def test_the_agent_flags_reach_the_policy_thresholds() -> None:
    from tidee.agent.config import AgentProcessConfig

    args = build_parser().parse_args(
        ["agent", "--oop-threshold", "0.6", "--k-empty-goals", "5", "--seed", "201"]
    )
    cfg = from_args(AgentProcessConfig, args)
    assert cfg.agent.policy.oop_threshold == 0.6 and cfg.agent.policy.k_empty_goals == 5
    assert cfg.spec.seed == 201 and cfg.spec.mess_index == 0 and cfg.agent.seed == 0


def test_what_a_config_computes_never_becomes_a_default() -> None:
    """AgentConfig resolves oop "auto" in __post_init__; the flag's default stays "auto", so
    --perception oracle alone still picks the language detector."""
    from tidee.agent.config import AgentProcessConfig

    parser = build_parser()
    cfg = from_args(AgentProcessConfig, parser.parse_args(["agent", "--perception", "oracle"]))
    assert cfg.agent.oop == "language"
    run = from_args(AgentProcessConfig, parser.parse_args(["agent"]))
    assert run.agent.oop == "visual"
    assert from_args(AgentProcessConfig, parser.parse_args(["agent", *to_argv(run)])) == run
