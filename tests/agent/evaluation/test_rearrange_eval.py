"""``tidee eval rearrange`` end to end on one test configuration: the rows, the records, the report."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from tidee.agent.config import AgentConfig
from tidee.agent.evaluation.config import RearrangeEvalConfig
from tidee.agent.evaluation.rearrange_eval import RearrangeJob, _run_one, run_rearrange_eval
from tidee.cli import build_parser
from tidee.options import from_args
from tidee.protocol.messages import EpisodeSpec


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("rearrange")
    cfg = RearrangeEvalConfig(
        out=out,
        episodes=1,  # test configuration 0: Kitchen 200, rearrangement 0
        rows=("do-nothing", "oracle"),
        resolution=128,
        walkthrough_steps=100,
        max_steps=150,
        progress=False,
        agent=AgentConfig(carve="off"),  # as auto with sensor depth: the report's command must say it
    )
    return run_rearrange_eval(cfg), out


def test_do_nothing_scores_the_shuffled_room_as_it_is(report: tuple[dict, Path]) -> None:
    rep, _ = report
    floor = rep["rows"]["do-nothing"]
    assert floor["episodes"] == 1 and floor["fixed_strict"] == 0.0 and floor["success"] == 0.0
    assert floor["misplaced"] == 1.0 and floor["energy"] == 1.0


def test_the_oracle_row_plays_both_phases_and_the_report_says_so(report: tuple[dict, Path]) -> None:
    rep, out = report
    (ep,) = [r for r in rep["episodes"] if r["row"] == "oracle"]
    assert 0 < ep["walkthrough_steps"] <= 100 and 0 < ep["steps"] <= 150
    m = ep["rearrange"]
    assert m["start_misplaced"] >= 1 and 0.0 <= m["fixed_strict"] <= 1.0
    assert 0 <= ep["changed_found"] <= m["start_misplaced"]
    stored = json.loads((out / "report.json").read_text())
    assert stored["rows"]["oracle"]["fixed_strict"] == rep["rows"]["oracle"]["fixed_strict"]
    assert stored["rows"]["oracle"]["walkthrough_steps_median"] == ep["walkthrough_steps"]
    assert stored["rows"]["do-nothing"]["walkthrough_steps_median"] is None  # it never walks through
    md = (out / "report.md").read_text()
    assert "| walkthrough steps (median) |" in md
    assert "TIDEE, ORACLE perception" in md and "Table 4 (RoomR 2022)" in md and "11.6" in md
    assert (out / "report.png").read_bytes()[:4] == b"\x89PNG"
    assert len((out / "episodes.jsonl").read_bytes().splitlines()) == 2


def test_the_reports_command_rebuilds_the_run(report: tuple[dict, Path]) -> None:
    rep, out = report
    (command,) = [n.removeprefix("command: ") for n in rep["notes"] if n.startswith("command: ")]
    words = shlex.split(command)
    assert words[:3] == ["tidee", "eval", "rearrange"] and "--carve" in words
    again = from_args(RearrangeEvalConfig, build_parser().parse_args(words[1:]))
    assert again.agent.carve == "off" and again.rows == ("do-nothing", "oracle")
    assert (again.walkthrough_steps, again.max_steps, again.out) == (100, 150, out)


def test_the_oracle_agent_restores_a_kitchen_it_walked_through() -> None:
    """Kitchen 201 rearrangement 1: a cabinet, a fridge and a microwave toggled, a fork moved
    out of sight (into the garbage can). The agent finds the toggles from its own map (the
    oracle only labels its detections) and sets them back without breaking anything."""
    spec = EpisodeSpec(
        room_type="Kitchen", seed=201, rearrange_index=1, resolution=128, max_steps=300, walkthrough_steps=160
    )
    job = RearrangeJob("oracle", AgentConfig(perception="oracle"), spec, "test", 6, "tiny")
    rec = _run_one(job)
    m = rec["rearrange"]
    assert m["start_misplaced"] == 4 and m["by_kind"]["openable"]["start_misplaced"] == 3
    assert m["fixed"] >= 2 and m["newly_misplaced"] == 0 and m["fixed_strict"] >= 0.5
    assert rec["changed_found"] >= 2 and rec["walkthrough_steps"] > 0


def test_bad_rows_are_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["eval", "rearrange", "--out", "/tmp/x", "--rows", "clean,telepathy"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) >= 1 and "telepathy" in err[-1]
