"""Who may command agents from the viewer: read-only mode, the access token off loopback,
and what ``tidee viewer`` prints."""

from __future__ import annotations

import pytest

from tests.support.net import wait_until
from tests.support.viewer_fakes import synthetic_source
from tidee.viewer import access
from tidee.viewer.synthetic import write_synthetic_log


@pytest.mark.parametrize("host", ["127.0.0.1", "127.1.2.3", "::1", "[::1]", "localhost", "LocalHost"])
def test_loopback_hosts_need_no_token(host):
    assert access.is_loopback(host)
    assert access.required_token(host, None) is None
    assert access.announce("http://127.0.0.1:8080", None, False) == "viewer: http://127.0.0.1:8080"


@pytest.mark.parametrize("host", ["0.0.0.0", "", "::", "192.168.1.5", "example.org"])
def test_other_hosts_get_a_fresh_random_token_printed_with_the_url(host):
    assert not access.is_loopback(host)
    first, second = access.required_token(host, None), access.required_token(host, None)
    assert first and second and first != second and len(first) >= 20
    line = access.announce("http://127.0.0.1:8080", first, False)
    assert line.startswith("viewer: http://127.0.0.1:8080") and first in line


def test_a_given_token_is_used_even_on_loopback_and_read_only_prints_none():
    assert access.required_token("127.0.0.1", "s3cret") == "s3cret"
    assert access.required_token("0.0.0.0", "s3cret") == "s3cret"
    line = access.announce("http://h:1", "s3cret", True)
    assert "s3cret" not in line and "read-only" in line


def test_the_gate_lets_through_only_clients_that_presented_the_token():
    gate = access.AccessGate("s3cret")
    assert gate.needs_token
    assert gate.refusal(1) is not None and gate.refusal(None) is not None
    assert not gate.unlock(1, "wrong") and gate.refusal(1) is not None
    assert gate.unlock(1, " s3cret ")
    assert gate.refusal(1) is None
    assert gate.refusal(2) is not None  # per client: another page stays locked
    assert not gate.unlock(1, "s3cre") and gate.refusal(1) is not None  # a wrong value locks again
    gate.unlock(1, "s3cret")
    gate.forget(1)  # disconnected: a new connection starts locked
    assert gate.refusal(1) is not None
    open_gate = access.AccessGate(None)
    assert not open_gate.needs_token and open_gate.refusal(None) is None and open_gate.refusal(7) is None
    read_only = access.AccessGate("s3cret", read_only=True)
    read_only.unlock(1, "s3cret")
    assert not read_only.needs_token and "read-only" in (read_only.refusal(1) or "")


def test_viewer_config_refuses_an_empty_token(tmp_path):
    from tidee.viewer.app import ViewerConfig

    with pytest.raises(ValueError, match="token must not be empty"):
        ViewerConfig(token=" ")


def test_cli_parses_read_only_and_token_and_run_forwards_read_only():
    from tidee.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["viewer", "--host", "0.0.0.0", "--token", "abc"])
    assert args.token == "abc" and not args.read_only
    assert parser.parse_args(["viewer", "--read-only"]).read_only
    with pytest.raises(SystemExit):
        parser.parse_args(["viewer", "--read-only", "--token", "abc"])
    assert parser.parse_args(["run", "--viewer-read-only"]).viewer_read_only
    assert not parser.parse_args(["demo"]).viewer_read_only


def test_read_only_viewer_builds_no_command_controls_and_refuses_commands():
    from tidee.viewer.app import ViewerConfig, run_viewer

    with synthetic_source() as src:
        with run_viewer(ViewerConfig(endpoint=src.endpoint, port=0, read_only=True)) as viewer:
            app = viewer.app
            assert app.panels.command_controls == []
            assert wait_until(lambda: app.feed.selected == src.session, 10.0)
            app.command("pause")
            app.command("new_episode", 3, room_type="Kitchen", seed=1, mess_index=0)
            assert not wait_until(lambda: src.agent.acks, 1.0)  # nothing reached the agent
            assert "sent to" not in app.panels.ack.content and not src.agent.paused


def test_token_gate_in_the_app_refuses_a_locked_client_and_sends_for_an_unlocked_one():
    from tidee.viewer.app import ViewerConfig, run_viewer

    with synthetic_source() as src:
        with run_viewer(ViewerConfig(endpoint=src.endpoint, port=0, token="s3cret")) as viewer:
            app = viewer.app
            assert len(app.panels.command_controls) == 3
            assert wait_until(lambda: app.feed.selected == src.session, 10.0)
            app.command("pause", 5)  # client 5 has not presented the token
            app.present_token(6, "wrong")
            app.command("pause", 6)
            assert not wait_until(lambda: src.agent.acks, 1.0) and not src.agent.paused
            app.present_token(5, "s3cret")
            app.command("pause", 5)
            assert wait_until(lambda: src.agent.paused, 10.0)
            assert [a.kind for a in src.agent.acks] == ["pause"]


def test_loopback_viewer_without_token_sends_as_before(tmp_path):
    from tidee.viewer.app import ViewerConfig, run_viewer

    write_synthetic_log(str(tmp_path), steps=5)
    with run_viewer(ViewerConfig(replay=str(tmp_path), port=0)) as viewer:
        assert viewer.app.access.token is None and viewer.app.access.refusal(4) is None
