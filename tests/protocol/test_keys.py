"""Key expressions: builders, parsers, id validation."""

from __future__ import annotations

import pytest

from tidee.protocol import keys


def test_sim_keys_round_trip() -> None:
    for op in keys.SESSION_OPS:
        key = keys.sim_op("sim0", "agent_1-a", op)
        assert key == f"tidee/sim/sim0/session/agent_1-a/{op}"
        assert keys.parse_sim_op(key) == ("sim0", "agent_1-a", op)
    assert keys.sim_op_wildcard("sim0") == "tidee/sim/sim0/session/*/*"
    assert keys.sim_op_wildcard("sim0", "step") == "tidee/sim/sim0/session/*/step"
    assert keys.observations("sim0", "s1") == "tidee/sim/sim0/obs/s1"
    assert keys.parse_observations("tidee/sim/sim0/obs/s1") == ("sim0", "s1")
    assert keys.observations_wildcard() == "tidee/sim/*/obs/*"


def test_liveliness_keys() -> None:
    assert keys.alive_server("sim0") == "tidee/alive/server/sim0"
    assert keys.alive_session("sim0", "s1") == "tidee/alive/session/sim0/s1"
    assert keys.alive_client("sim0", "s1") == "tidee/alive/client/sim0/s1"
    assert keys.alive_clients_wildcard("sim0") == "tidee/alive/client/sim0/*"
    assert keys.alive_sessions_wildcard() == "tidee/alive/session/*/*"
    assert keys.parse_alive("tidee/alive/server/sim0") == ("server", "sim0", None)
    assert keys.parse_alive("tidee/alive/session/sim0/s1") == ("session", "sim0", "s1")
    assert keys.parse_alive("tidee/alive/client/sim0/s1") == ("client", "sim0", "s1")


def test_agent_keys() -> None:
    assert keys.agent_telemetry("s1", "map2d") == "tidee/agent/s1/telemetry/map2d"
    assert keys.parse_agent_telemetry("tidee/agent/s1/telemetry/map2d") == ("s1", "map2d")
    assert keys.agent_telemetry_wildcard() == "tidee/agent/*/telemetry/*"
    assert keys.agent_cmd("s1") == "tidee/agent/s1/cmd"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a b", "é", "x" * 129, None, 7, "a$"])
def test_invalid_ids_are_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="session must be 1-128 characters"):
        keys.sim_op("sim0", bad, "step")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="server_id"):
        keys.alive_server(bad)  # type: ignore[arg-type]
    assert not keys.is_valid_id(bad)


def test_longest_valid_id() -> None:
    assert keys.check_id("session", "x" * 128) == "x" * 128


@pytest.mark.parametrize(
    "key",
    [
        "tidee/sim/sim0/session/s1",  # no op
        "tidee/sim/sim0/session/s1/fly",  # unknown op
        "tidee/sim/sim0/sessions/s1/step",  # wrong literal
        "tidee/sim/sim0/session/*/step",  # a wildcard is not a session
        "other/sim/sim0/session/s1/step",
        "tidee/sim/sim0/session/s1/step/extra",
    ],
)
def test_parse_sim_op_rejects(key: str) -> None:
    with pytest.raises(ValueError):
        keys.parse_sim_op(key)


def test_unknown_op_is_rejected_by_the_builder() -> None:
    with pytest.raises(ValueError, match="op must be one of"):
        keys.sim_op("sim0", "s1", "jump")
    with pytest.raises(ValueError, match="op must be"):
        keys.sim_op_wildcard("sim0", "jump")


@pytest.mark.parametrize(
    "key", ["tidee/alive/agent/sim0/s1", "tidee/alive/server", "tidee/alive/client/sim0/*"]
)
def test_parse_alive_rejects(key: str) -> None:
    with pytest.raises(ValueError):
        keys.parse_alive(key)
