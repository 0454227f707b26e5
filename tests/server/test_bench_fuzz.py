"""The fuzz benchmark: its cases are reproducible and hostile, and a short run meets every target."""

from __future__ import annotations

import json

import pytest
import zenoh

from tests.support.fakes import FakeEpisode
from tests.support.net import SPEC, start_server, wait_until
from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.messages import Action, ActionName, ResetRequest, StepRequest
from tidee.protocol.zenoh_config import make_config
from tidee.server.bench_fuzz import FAMILIES, Case, CaseMaker, run_fuzz_bench, send, write_fuzz_report
from tidee.server.config import FuzzBenchConfig


def test_the_same_seed_draws_the_same_cases_and_another_seed_others() -> None:
    a, b, c = (CaseMaker(seed, "srv", 1 << 20) for seed in (7, 7, 8))
    first = [(x.family, x.op, x.key, x.payload) for x in (a.next() for _ in range(300))]
    assert first == [(x.family, x.op, x.key, x.payload) for x in (b.next() for _ in range(300))]
    assert first != [(x.family, x.op, x.key, x.payload) for x in (c.next() for _ in range(300))]


def test_every_family_and_op_is_drawn_and_only_valid_cases_decode_unchanged() -> None:
    maker = CaseMaker(0, "srv", 1 << 20)
    cases = [maker.next() for _ in range(2000)]
    assert {c.family for c in cases} == set(FAMILIES)
    assert {c.op for c in cases} == {"reset", "step", "phase", "state", "close"}
    for case in cases:
        if case.family == "valid":
            decode(case.payload)  # a valid request is one the codec takes
        elif case.family in ("prefix", "deep", "oversized"):
            with pytest.raises(ProtocolError):
                decode(case.payload, max_bytes=1 << 20)


def test_an_episode_that_raises_is_counted_internal_and_a_key_nobody_serves_unrouted() -> None:
    srv = start_server(lambda: FakeEpisode(fail_on="LookUp"))
    z = zenoh.open(make_config(False, srv.config.endpoint))
    try:  # the raw session opens its own session (the server refuses steps to another client's)
        session = "fuzz-raw"
        reset = encode(ResetRequest(session, SPEC))
        reset_key = keys.sim_op(srv.config.server_id, session, "reset")
        assert wait_until(
            lambda: send(z, Case(0, "valid", "reset", reset_key, reset, "reset"), 2.0)[0] == "ok"
        )
        key = keys.sim_op(srv.config.server_id, session, "step")
        look_up = encode(StepRequest(session, Action(ActionName.LookUp)))
        outcome, reply, _ = send(z, Case(1, "valid", "step", key, look_up, "LookUp"), 10.0)
        assert outcome == "internal" and "fake failure on LookUp" in reply.message
        outcome, _, _ = send(z, Case(2, "key", "step", key + "/more", look_up, "extra chunk"), 10.0)
        assert outcome == "unrouted"
        move = encode(StepRequest(session, Action(ActionName.MoveAhead)))
        assert send(z, Case(3, "valid", "step", key, move, "MoveAhead"), 10.0)[0] == "ok"
    finally:
        z.close()
        srv.stop()


def test_a_short_run_against_a_real_server_meets_every_target(tmp_path) -> None:
    pytest.importorskip("pybullet")
    cfg = FuzzBenchConfig(cases=300, seed=3, batch=100, reply_timeout_s=120.0)
    result = run_fuzz_bench(cfg, tmp_path / "fuzz.json")
    assert sum(result["totals"].values()) == 300
    assert result["crashes"] == result["hangs"] == result["internal"] == 0, result["internal_cases"]
    assert result["honest_checks"] == 3 and result["honest_failures"] == 0
    assert result["totals"]["ok"] > 0 and result["totals"]["malformed"] > 0  # it reached both sides
    assert result["targets_met"]
    written = json.loads((tmp_path / "fuzz.json").read_text())
    assert (
        written["command"]
        == "tidee bench fuzz --cases 300 --seed 3 --batch 100 --reply-timeout 120 --processes 1"
    )
    assert "| crashes (server process exited) | 0 | 0 |" in (tmp_path / "fuzz.md").read_text()


def test_the_report_lists_each_internal_error_with_its_case(tmp_path) -> None:
    report = {
        "command": "tidee bench fuzz",
        "cases": 1,
        "processes": 1,
        "batch": 1,
        "machine": "m",
        "wall_s": 1.0,
        "load_avg_before": [0.0, 0.0, 0.0],
        "load_avg_after": [0.0, 0.0, 0.0],
        "load_1min_during": {"median": 0.0, "max": 0.0},
        "crashes": 0,
        "hangs": 0,
        "internal": 1,
        "reply_timeout_s": 1.0,
        "simulator_deaths": 0,
        "honest_failures": 0,
        "honest_checks": 1,
        "reply_ms": {"median": 1.0, "p90": 1.0, "max": 1.0},
        "by_family": {"type": {"internal": 1}},
        "totals": {"internal": 1},
        "internal_cases": [
            {"case": 5, "family": "type", "op": "step", "what": "action.x = 'x'", "message": "boom"}
        ],
        "hang_cases": [],
    }
    write_fuzz_report(tmp_path / "f.json", report)
    text = (tmp_path / "f.md").read_text()
    assert "- case 5 (type, step): action.x = 'x': boom" in text and "| `internal` errors | 1 | 0 |" in text
