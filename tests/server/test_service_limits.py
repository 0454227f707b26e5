"""The server's bounds: a per-client session quota, idle sessions reclaimed, request size checked
before the payload is copied. Fake episodes in server threads, loopback Zenoh."""

from __future__ import annotations

import time
import tracemalloc
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from tests.support.net import SPEC, client, raw_request, start_server, wait_until
from tidee.protocol import keys
from tidee.protocol.client import RemoteError
from tidee.protocol.codec import encode
from tidee.protocol.messages import Action, ActionName, ErrorCode, ErrorReply, ResetRequest
from tidee.protocol.zenoh_config import make_config
from tidee.server.service import ServerConfig, SimServer


@pytest.fixture
def shared_zenoh() -> Iterator[Any]:
    """A factory of Zenoh sessions on a server's network, closed after the test."""
    opened: list[zenoh.Session] = []

    def open_for(server: SimServer) -> zenoh.Session:
        opened.append(zenoh.open(make_config(False, server.config.endpoint)))
        assert wait_until(lambda: _served(opened[-1], server))
        return opened[-1]

    yield open_for
    for z in opened:
        z.close()


def test_config_refuses_nonsense_limits() -> None:
    with pytest.raises(ValueError, match="max_sessions_per_client must be >= 1"):
        ServerConfig(max_sessions_per_client=0)
    with pytest.raises(ValueError, match="idle_timeout_s must be >= 0"):
        ServerConfig(idle_timeout_s=-1)


def test_one_client_holds_at_most_its_quota_and_a_close_releases_a_slot(shared_zenoh: Any) -> None:
    server = start_server(max_sessions=8, max_sessions_per_client=2)
    try:
        z = shared_zenoh(server)  # one Zenoh session: one client, however many session ids it uses
        clients = [client(server, zsession=z) for _ in range(3)]
        clients[0].reset(SPEC)
        clients[1].reset(SPEC)
        with pytest.raises(RemoteError) as refused:
            clients[2].reset(SPEC)
        assert refused.value.code == ErrorCode.server_busy
        assert "holds 2 sessions" in refused.value.message
        assert "max_sessions_per_client=2" in refused.value.message
        assert len(server.sessions) == 2

        other = client(server)  # its own Zenoh session: another client, with its own quota
        other.reset(SPEC)

        clients[0].close()
        clients[2].reset(SPEC)  # the freed slot is usable at once
        assert set(server.sessions) == {clients[1].session_id, clients[2].session_id, other.session_id}
        for c in (*clients[1:], other):
            c.close()
    finally:
        server.stop()


def test_without_source_info_the_session_prefix_names_the_client(shared_zenoh: Any) -> None:
    server = start_server(max_sessions=8, max_sessions_per_client=1)
    try:
        z = shared_zenoh(server)
        sid = server.config.server_id
        for session in ("agentA-0", "agentB-0"):  # hand-made requests carry no source_info
            reply = raw_request(z, keys.sim_op(sid, session, "reset"), _reset(session))
            assert not isinstance(reply, ErrorReply), reply
        reply = raw_request(z, keys.sim_op(sid, "agentA-1", "reset"), _reset("agentA-1"))
        assert isinstance(reply, ErrorReply) and reply.code == ErrorCode.server_busy
        assert "session prefix 'agentA' holds 1 sessions" in reply.message
    finally:
        server.stop()


def test_an_idle_session_is_reclaimed_and_its_next_step_says_so() -> None:
    server = start_server(max_sessions=2, max_sessions_per_client=2, idle_timeout_s=1.0)
    try:
        with client(server) as idle, client(server) as busy:
            idle.reset(SPEC)
            busy.reset(SPEC)
            deadline = time.monotonic() + 2.5
            while time.monotonic() < deadline:  # requests keep a session alive
                busy.step(Action(ActionName.MoveAhead))
                time.sleep(0.2)
            assert server.sessions == (busy.session_id,)
            with pytest.raises(RemoteError) as gone:
                idle.step(Action(ActionName.MoveAhead))
            assert gone.value.code == ErrorCode.unknown_session
            assert f"session {idle.session_id!r} was reclaimed after 1 s idle" in gone.value.message
            idle.reset(SPEC)  # a reset starts afresh, as after a close
            idle.step(Action(ActionName.MoveAhead))
    finally:
        server.stop()


def test_idle_timeout_zero_never_reclaims() -> None:
    server = start_server(idle_timeout_s=0)
    try:
        with client(server) as c:
            c.reset(SPEC)
            time.sleep(0.5)
            assert server._reaper is None
            c.step(Action(ActionName.MoveAhead))
    finally:
        server.stop()


def test_an_oversized_request_is_refused_without_copying_it(shared_zenoh: Any) -> None:
    server = start_server(max_request_bytes=1 << 20)
    try:
        z = shared_zenoh(server)
        session = "big-0"
        key = keys.sim_op(server.config.server_id, session, "reset")
        size = 20 << 20
        payload = zenoh.ZBytes(bytes(size))
        tracemalloc.start()  # Python's allocations only: Zenoh's own buffers are not traced
        try:
            reply = raw_request(z, key, payload)
            _, python_peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert isinstance(reply, ErrorReply) and reply.code == ErrorCode.oversized
        assert f"request is {size} bytes, the limit is {1 << 20}" in reply.message
        assert session not in server.sessions
        assert python_peak < size // 20, f"{python_peak} bytes allocated in Python for a {size}-byte request"
    finally:
        server.stop()


def _served(z: zenoh.Session, server: SimServer) -> bool:
    token = keys.alive_server(server.config.server_id)
    return any(r.ok is not None for r in z.liveliness().get(token, timeout=1.0))


def _reset(session: str) -> bytes:
    return encode(ResetRequest(session, SPEC))
