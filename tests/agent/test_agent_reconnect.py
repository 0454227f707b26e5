"""An agent whose server disappears plays the episode again from the start: on the same server once
it is back, or, when it chose its server (``--server-id auto``), on another live one.

Loopback only: a real ``tidee server`` and ``tidee agent`` as subprocesses; the server is
killed mid-episode (SIGKILL, no goodbye) and a new one started on the same endpoint. Moving to
another server is tests/test_deployment.py's (a router and two servers); here, its decisions.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.support.processes import OutputLines, kill_group, start_tidee
from tidee.agent.config import AgentConfig
from tidee.agent.process import AgentProcessConfig, _run_until_done
from tidee.launch import free_port
from tidee.protocol.client import RemoteError
from tidee.protocol.episode_log import TLOG_NAME, LogReader
from tidee.protocol.messages import EpisodeSpec, ErrorCode


@pytest.mark.timeout(180)
def test_agent_survives_a_server_restart(tmp_path: Path) -> None:
    deadline = time.monotonic() + 150  # a loaded 2-core machine plays the episode twice
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server_args = ("server", "--endpoint", endpoint, "--processes", "1")
    server = start_tidee(*server_args, output=False)
    agent = start_tidee(
        "agent",
        "--endpoint",
        endpoint,
        "--perception",
        "oracle",
        "--variant",
        "CommonMemory",
        "--oop",
        "relation_stats",
        "--max-steps",
        "80",
        "--reconnect-timeout",
        "40",
        "--log-dir",
        str(tmp_path / "runs"),
    )
    second = None
    try:
        out = OutputLines(agent)
        out.wait_for("agent: session", deadline)
        # A few steps into the episode (its log has them), long before its 80th: a fast machine
        # plays all 80 in about 2.5 s.
        while _steps_logged(tmp_path / "runs") < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert agent.poll() is None, out.text
        kill_group(server)
        second = start_tidee(*server_args, output=False)
        gone = out.wait_for("went away", deadline)
        assert gone.startswith("agent: server 'sim0' went away at step ")
        assert gone.endswith("; waiting up to 40 s for it to come back")
        back = out.wait_for("is back", deadline)
        assert back == "agent: server 'sim0' is back; running LivingRoom seed 200 mess 0 again from the start"
        out.wait_for(" moved", deadline)
        assert agent.wait(timeout=max(1.0, deadline - time.monotonic())) == 0, out.text
        assert "Traceback" not in out.text, out.text
        summaries = list((tmp_path / "runs").rglob("summary.json"))
        assert len(summaries) == 1, summaries  # the re-run's log is the finished one
    finally:
        kill_group(agent)
        kill_group(server)
        if second is not None:
            kill_group(second)


def _steps_logged(runs: Path) -> int:
    """Actions in the agent's episode logs so far (a log not yet begun counts none)."""
    n = 0
    for log in runs.rglob(TLOG_NAME):
        try:
            n += sum(e.get("kind") == "action" for e in LogReader(log.parent).events())
        except (FileNotFoundError, ValueError):
            pass
    return n


class _GoneClient:
    """A SimClient stand-in whose server never comes back."""

    auto, server_id = False, "sim0"

    def __init__(self) -> None:
        self.waits: list[float] = []

    def wait_for_server(self, timeout: float) -> None:
        self.waits.append(timeout)
        raise TimeoutError("not seen")


class _FailingRunner:
    def __init__(self, error: Exception) -> None:
        self.error, self.runs = error, 0

    def run(self, spec: EpisodeSpec, evaluate: bool = False) -> None:
        self.runs += 1
        raise self.error


def _cfg(reconnect_timeout: float) -> AgentProcessConfig:
    return AgentProcessConfig(
        agent=AgentConfig(),
        spec=EpisodeSpec(room_type="LivingRoom", seed=200, mess_index=0),
        reconnect_timeout=reconnect_timeout,
    )


def test_agent_gives_up_when_the_server_stays_away(capsys: pytest.CaptureFixture[str]) -> None:
    cfg, client, runner = _cfg(0.2), _GoneClient(), _FailingRunner(TimeoutError("no reply to step"))
    with pytest.raises(TimeoutError, match=r"^server 'sim0' did not come back within 0.2 s$"):
        _run_until_done(runner, client, cfg.spec, cfg, {"last": 7})  # type: ignore[arg-type]
    assert runner.runs == 1 and client.waits == [0.2]
    assert capsys.readouterr().out == (
        "agent: server 'sim0' went away at step 0; waiting up to 0.2 s for it to come back\n"
    )


def test_a_refused_episode_or_no_reconnect_fails_at_once() -> None:
    refused = RemoteError(ErrorCode.invalid_field, "no such room")
    for cfg, error in ((_cfg(5), refused), (_cfg(0), TimeoutError("no reply to step"))):
        runner, client = _FailingRunner(error), _GoneClient()
        with pytest.raises(type(error)):
            _run_until_done(runner, client, cfg.spec, cfg, {"last": 0})  # type: ignore[arg-type]
        assert runner.runs == 1 and client.waits == []


def test_reconnect_timeout_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="reconnect_timeout"):
        _cfg(-1)


class _AutoClient:
    """A SimClient stand-in that chose its server (``--server-id auto``); ``others``: where it may move."""

    auto = True

    def __init__(self, others: list[str]) -> None:
        self.server_id, self.others = "sim1", others
        self.chosen: list[tuple[float, set[str]]] = []

    def choose_server(self, timeout: float, avoid: set[str] = frozenset()) -> str:  # type: ignore[assignment]
        self.chosen.append((timeout, set(avoid)))
        if not self.others:
            raise TimeoutError("no live tidee server at tcp/router:7447 within 5 s")
        self.server_id = self.others.pop(0)
        return self.server_id


class _FlakyRunner:
    """Fails its first run with ``error`` (at step 12), then plays the episode."""

    def __init__(self, error: Exception, step: dict[str, int]) -> None:
        self.error, self.step, self.runs = error, step, 0

    def run(self, spec: EpisodeSpec, evaluate: bool = False) -> str:
        self.runs += 1
        if self.runs == 1:
            self.step["last"] = 12
            raise self.error
        return "finished"


def test_an_agent_that_chose_its_server_moves_to_another_and_runs_again(
    capsys: pytest.CaptureFixture[str],
) -> None:
    cfg, step = _cfg(5), {"last": 0}
    client, runner = _AutoClient(["sim0"]), _FlakyRunner(TimeoutError("no reply to step"), step)
    assert _run_until_done(runner, client, cfg.spec, cfg, step) == "finished"  # type: ignore[arg-type]
    assert runner.runs == 2 and client.chosen == [(5, {"sim1"})]  # a silent server: tried last
    assert capsys.readouterr().out == (
        "agent: server 'sim1' went away at step 12; moving to another live server "
        "(waiting up to 5 s for one with room)\n"
        "agent: on server 'sim0'; running LivingRoom seed 200 mess 0 again from the start\n"
    )
    # A server that restarted (it no longer knows the session) is as good as any other.
    client, runner = _AutoClient(["sim1"]), _FlakyRunner(RemoteError(ErrorCode.unknown_session, "gone"), step)
    assert _run_until_done(runner, client, cfg.spec, cfg, step) == "finished"  # type: ignore[arg-type]
    assert client.chosen == [(5, set())]


def test_an_agent_that_chose_its_server_gives_up_when_none_has_room(
    capsys: pytest.CaptureFixture[str],
) -> None:
    cfg, step = _cfg(5), {"last": 0}
    client, runner = _AutoClient([]), _FlakyRunner(TimeoutError("no reply to step"), step)
    with pytest.raises(TimeoutError) as info:
        _run_until_done(runner, client, cfg.spec, cfg, step)  # type: ignore[arg-type]
    assert str(info.value) == (
        "after server 'sim1' went away: no live tidee server at tcp/router:7447 within 5 s"
    )
    assert runner.runs == 1
