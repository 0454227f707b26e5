"""``tidee eval tidy --conditions``: the paper's robustness rows (+noisy pose, +est. depth, +noisy
depth), each agent once per condition, one report row apiece; and rearrange's rows built the same way."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.evaluation.conditions import CONDITIONS, apply_condition, row_name
from tidee.agent.evaluation.config import RearrangeEvalConfig, TidyEvalConfig
from tidee.agent.evaluation.judge import REFERENCE_VARIANTS
from tidee.agent.evaluation.rearrange_eval import row_setup
from tidee.agent.evaluation.tidy_eval import build_jobs
from tidee.batch import read_records
from tidee.cli import build_parser, main
from tidee.options import from_args, to_argv
from tidee.protocol.messages import EpisodeSpec


def _cfg(*argv: str) -> TidyEvalConfig:
    args = build_parser().parse_args(["eval", "tidy", "--out", "unused", *argv])
    return from_args(TidyEvalConfig, args)


def test_each_agent_runs_once_per_condition_with_the_papers_row_names() -> None:
    cfg = _cfg("--episodes", "2", "--variants", "TIDEE,CommonMemory", "--conditions", ",".join(CONDITIONS))
    jobs = build_jobs(cfg)
    assert len(jobs) == 2 * 2 * 4
    rows = list(dict.fromkeys(j.row for j in jobs))
    assert rows == [
        "TIDEE",
        "TIDEE +noisy pose",
        "TIDEE +est. depth",
        "TIDEE +noisy depth",
        "CommonMemory",
        "CommonMemory +noisy pose",
        "CommonMemory +est. depth",
        "CommonMemory +noisy depth",
    ]
    settings = {
        "clean": (False, False, "sensor"),
        "noisy-pose": (True, False, "sensor"),
        "est-depth": (False, False, "estimated"),
        "noisy-depth": (False, True, "sensor"),
    }
    for j in jobs:
        assert (j.spec.pose_noise, j.spec.depth_noise, j.agent.depth) == settings[j.condition]
        assert j.row == row_name(j.agent.variant, j.condition)
    # One resume key per episode: the conditions change the digest.
    assert len({j.key() for j in jobs}) == len(jobs)
    # Every condition plays the same configurations with the same agent seed.
    per_condition = {
        c: [(j.agent.variant, j.spec.seed, j.spec.mess_index, j.agent.seed) for j in jobs if j.condition == c]
        for c in CONDITIONS
    }
    assert len({tuple(v) for v in per_condition.values()}) == 1


def test_the_default_is_the_clean_row_alone_with_the_keys_it_always_had() -> None:
    cfg = _cfg("--episodes", "1", "--variants", "TIDEE")
    assert cfg.conditions == ("clean",) and "--conditions" not in to_argv(cfg)
    (job,) = build_jobs(cfg)
    assert job.row == "TIDEE" and not job.spec.pose_noise and not job.spec.depth_noise
    # The clean job is the agent and episode as before conditions existed: the same resume key.
    assert job.agent == replace(cfg.agent, variant="TIDEE", seed=0) and job.key().startswith(
        "TIDEE/Kitchen/200/"
    )
    rec = job.label({"variant": "TIDEE", "steps": 3})
    assert rec["variant"] == "TIDEE" and rec["condition"] == "clean" and rec["agent_variant"] == "TIDEE"
    assert (rec["pose_noise"], rec["depth_noise"], rec["depth"]) == (False, False, "sensor")


def test_depth_estimated_alone_is_the_est_depth_row() -> None:
    cfg = _cfg("--episodes", "1", "--variants", "TIDEE", "--depth", "estimated")
    assert cfg.conditions == ("est-depth",)
    (job,) = build_jobs(cfg)
    assert job.row == "TIDEE +est. depth" and job.agent.depth == "estimated"
    assert _cfg("--depth", "estimated", "--conditions", "est-depth").conditions == ("est-depth",)


def test_contradictory_depth_and_conditions_are_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["eval", "tidy", "--out", str(tmp_path / "o"), "--depth", "estimated"]
    rc = main([*argv, "--conditions", "clean,est-depth"])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith("tidee: error: --depth estimated contradicts --conditions clean,est-depth")
    assert "est-depth" in lines[0] and not (tmp_path / "o").exists()
    with pytest.raises(ValueError, match="noisy-pose use the depth sensor"):
        TidyEvalConfig(out=tmp_path, agent=AgentConfig(depth="estimated"), conditions=("noisy-pose",))
    with pytest.raises(ValueError, match="conditions must be among"):
        TidyEvalConfig(out=tmp_path, conditions=("noisy",))  # type: ignore[arg-type]


def test_an_unknown_condition_is_refused_by_the_parser(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["eval", "tidy", "--out", "o", "--conditions", "clean,noisy"])
    assert "noisy not among" in capsys.readouterr().err


def test_rearrange_rows_use_the_same_conditions() -> None:
    agent, spec = AgentConfig(), EpisodeSpec(room_type="Kitchen", seed=200, rearrange_index=0)
    for c in CONDITIONS:
        assert row_setup(c, agent, spec) == apply_condition(c, agent, spec)
    assert row_setup("noisy-pose", agent, spec) == (agent, replace(spec, pose_noise=True))
    assert row_setup("est-depth", agent, spec) == (replace(agent, depth="estimated"), spec)
    assert row_setup("do-nothing", agent, spec) == (None, spec)
    oracle, same = row_setup("oracle", agent, spec)
    assert oracle is not None and oracle.perception == "oracle" and same == spec
    common, same = row_setup("commonsense", agent, spec)  # the clean row, plus the tidy agent's commonsense
    assert common == replace(agent, policy=replace(agent.policy, unmatched="commonsense")) and same == spec
    assert agent.policy.unmatched == "leave"


def test_the_commonsense_rearrangement_row_runs_only_when_named() -> None:
    default = from_args(RearrangeEvalConfig, build_parser().parse_args(["eval", "rearrange", "--out", "x"]))
    assert "commonsense" not in default.rows and "clean" in default.rows
    named = build_parser().parse_args(["eval", "rearrange", "--out", "x", "--rows", "clean,commonsense"])
    assert from_args(RearrangeEvalConfig, named).rows == ("clean", "commonsense")
    with pytest.raises(ValueError, match="unmatched must be one of leave, commonsense"):
        PolicyConfig(unmatched="tidy")  # type: ignore[arg-type]


def test_a_rearrangement_detection_threshold_reaches_the_learned_rows_only() -> None:
    args = build_parser().parse_args(
        ["eval", "rearrange", "--out", "unused", "--detection-threshold", "0.25"]
    )
    cfg = from_args(RearrangeEvalConfig, args)
    spec = EpisodeSpec(room_type="Kitchen", seed=200, rearrange_index=0)
    for row in ("clean", *CONDITIONS):
        agent, _ = row_setup(row, cfg.agent, spec)
        assert agent is not None and agent.perception == "learned" and agent.detection_threshold == 0.25
    oracle, _ = row_setup("oracle", cfg.agent, spec)  # the oracle has no scores: it would refuse one
    assert oracle is not None and oracle.perception == "oracle" and oracle.detection_threshold is None


def test_a_short_run_reports_a_row_per_condition(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    argv = ["eval", "tidy", "--out", str(out), "--episodes", "1", "--variants", "RandomReceptacle"]
    argv += ["--conditions", "clean,noisy-pose", "--perception", "oracle", "--resolution", "64"]
    argv += ["--max-steps", "40", "--localise", "off"]
    assert main(argv) == 0
    capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    rows = ["RandomReceptacle", "RandomReceptacle +noisy pose"]
    assert report["config"]["variants"] == [*rows, *REFERENCE_VARIANTS]
    assert set(report["metrics"]) == {*rows, *REFERENCE_VARIANTS}
    eps = {e["variant"]: e for e in report["episodes"]}
    assert len(report["episodes"]) == 4  # one reference record each, from the clean episode
    clean, noisy = eps["RandomReceptacle"], eps["RandomReceptacle +noisy pose"]
    assert (clean["condition"], clean["pose_noise"], clean["depth_noise"], clean["depth"]) == (
        "clean",
        False,
        False,
        "sensor",
    )
    assert (noisy["condition"], noisy["pose_noise"], noisy["depth_noise"]) == ("noisy-pose", True, False)
    assert noisy["agent_variant"] == clean["agent_variant"] == "RandomReceptacle"
    for ref in REFERENCE_VARIANTS:
        assert eps[ref]["condition"] == "clean"
    # The rows are variants like any other: pairwise and the human judge's columns have both.
    assert set(report["pairwise"]) == set(report["metrics"])
    assert set(rows) <= set(report["human"]["metrics"]["variants"])
    md = (out / "report.md").read_text()
    assert "| RandomReceptacle +noisy pose |" in md
    assert "VARIANT +noisy pose: noisy-pose, LoCoBot-like pose noise" in md
    assert "--conditions clean,noisy-pose" in md
    assert "--localise off" in md  # the report's command rebuilds the run, agent options too
    stored = read_records(out / "episodes.jsonl")
    assert sorted(r["variant"] for r in stored.values()) == rows
