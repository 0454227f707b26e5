"""The Zenoh server end to end on loopback: sessions, errors, liveliness, shutdown."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
import zenoh

from tests.support.fakes import FakeEpisode
from tests.support.net import REPO, SPEC, client, free_endpoint, raw_request, start_server, wait_until
from tidee.protocol import keys
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.codec import decode, encode
from tidee.protocol.messages import (
    Action,
    ActionName,
    EpisodeSpec,
    ErrorCode,
    ErrorReply,
    Observation,
    ResetRequest,
    ServerInfo,
    ServerInfoRequest,
    StateRequest,
    StepRequest,
)
from tidee.protocol.zenoh_config import make_config
from tidee.server.service import ServerConfig, SimServer


def test_episode_end_to_end(server: SimServer, raw_zenoh: zenoh.Session) -> None:
    frames: list[bytes] = []
    # The client shares the viewer's Zenoh session, so the server learns of the feed's
    # subscriber (same link, in order) before the first reset arrives.
    with client(server, zsession=raw_zenoh) as c:
        feed = raw_zenoh.declare_subscriber(
            keys.observations(server.config.server_id, c.session_id),
            lambda sample: frames.append(sample.payload.to_bytes()),
        )
        obs = c.reset(SPEC)
        assert isinstance(obs, Observation) and obs.session == c.session_id and obs.step == 0
        assert obs.rgb.shape == (32, 32, 3) and obs.depth.dtype == np.float32
        assert server.sessions == (c.session_id,)
        live = [
            str(r.ok.key_expr)
            for r in raw_zenoh.liveliness().get(
                keys.alive_sessions_wildcard(server.config.server_id), timeout=5.0
            )
            if r.ok is not None
        ]
        assert live == [keys.alive_session(server.config.server_id, c.session_id)]

        obs = c.step(Action(ActionName.MoveAhead))
        assert obs.step == 1 and obs.agent_pose[0] == pytest.approx(0.25) and obs.ground_truth is None
        obs = c.step(Action(ActionName.PickupObject, 0.2, 0.5), ground_truth=True)
        assert not obs.success and obs.error == "nothing_there"
        assert obs.ground_truth is not None and obs.ground_truth.instance_seg.shape == (32, 32)
        assert c.state()["steps"] == 2
        obs = c.step(Action(ActionName.Done))
        assert obs.done and obs.steps_left == 47
        obs = c.step(Action(ActionName.MoveAhead))
        assert not obs.success and obs.error == "episode_over"

        assert wait_until(lambda: len(frames) == 5), f"viewer feed got {len(frames)} of 5 frames"
        published = [decode(f) for f in frames]
        assert [o.step for o in published] == [0, 1, 2, 3, 3]
        assert all(o.ground_truth is None for o in published)  # privileged data stays off the feed
        feed.undeclare()
    assert wait_until(lambda: server.sessions == ())


def test_compressed_observations_over_the_wire(server: SimServer) -> None:
    with client(server, encoding="png") as c:
        c.reset(SPEC)
        obs = c.step(Action(ActionName.RotateLeft))
        assert obs.rgb.shape == (32, 32, 3) and obs.depth.dtype == np.float32
        assert obs.agent_pose[2] == pytest.approx(90.0)


def test_two_sessions_step_concurrently(server: SimServer) -> None:
    steps = 25
    clients = [client(server), client(server)]
    seen: dict[str, list[tuple[int, float]]] = {}
    errors: list[BaseException] = []

    def run(c: SimClient, seed: int) -> None:
        try:
            c.reset(EpisodeSpec(resolution=32, seed=seed, max_steps=100))
            seen[c.session_id] = [
                (o.step, o.agent_pose[0], o.session == c.session_id)
                for o in (c.step(Action(ActionName.MoveAhead)) for _ in range(steps))
            ]
        except BaseException as e:  # surfaced below
            errors.append(e)

    threads = [threading.Thread(target=run, args=(c, seed)) for seed, c in enumerate(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert not errors, errors
    assert set(server.sessions) == {c.session_id for c in clients}
    for c in clients:
        assert seen[c.session_id] == [(i, pytest.approx(0.25 * i), True) for i in range(1, steps + 1)]
    # Interleaved from one thread too: each session keeps its own state.
    a, b = clients
    assert a.step(Action(ActionName.MoveAhead)).step == steps + 1
    assert b.step(Action(ActionName.RotateLeft)).step == steps + 1
    assert a.step(Action(ActionName.MoveAhead)).step == steps + 2
    for c in clients:
        c.close()


def test_bad_requests_get_precise_errors_and_others_keep_working(
    server: SimServer, raw_zenoh: zenoh.Session
) -> None:
    sid = server.config.server_id
    with client(server) as good:
        good.reset(SPEC)
        key = keys.sim_op(sid, good.session_id, "step")

        garbage = raw_request(raw_zenoh, key, b"\x00garbage\xff" * 3)
        assert isinstance(garbage, ErrorReply) and garbage.code == ErrorCode.malformed
        assert "bad magic" in garbage.message

        empty = raw_request(raw_zenoh, key, b"")
        assert empty.code == ErrorCode.malformed and "shorter than" in empty.message

        wrong_type = raw_request(raw_zenoh, key, encode(ResetRequest(good.session_id, SPEC)))
        assert wrong_type.code == ErrorCode.malformed
        assert "expected StepRequest, got ResetRequest" in wrong_type.message

        other = raw_request(raw_zenoh, key, encode(StepRequest("someone_else", Action(ActionName.MoveAhead))))
        assert other.code == ErrorCode.invalid_field and "'someone_else'" in other.message

        bad_op = raw_request(raw_zenoh, f"tidee/sim/{sid}/session/{good.session_id}/teleport", b"x")
        assert bad_op.code == ErrorCode.malformed and "unknown op 'teleport'" in bad_op.message

        bad_id = raw_request(raw_zenoh, f"tidee/sim/{sid}/session/no.dots/step", b"x")
        assert bad_id.code == ErrorCode.malformed and "session must be" in bad_id.message

        big = raw_request(raw_zenoh, key, b"TIDE" + b"\0" * (server.config.max_request_bytes + 1))
        assert big.code == ErrorCode.oversized

        # None of that disturbed the session it was aimed at.
        assert good.step(Action(ActionName.MoveAhead)).step == 1
        assert good.state()["steps"] == 1


def test_unknown_session(server: SimServer) -> None:
    with client(server) as c:
        with pytest.raises(RemoteError) as info:
            c.step(Action(ActionName.MoveAhead))
        assert info.value.code == ErrorCode.unknown_session and "send reset first" in info.value.message
        with pytest.raises(RemoteError, match="unknown_session"):
            c.state()


def test_a_mess_index_outside_the_rooms_split_is_refused_with_the_valid_range(server: SimServer) -> None:
    with client(server) as c:
        with pytest.raises(RemoteError) as info:
            c.reset(EpisodeSpec(seed=200, mess_index=5, resolution=32, max_steps=50))
        assert info.value.code == ErrorCode.invalid_field
        assert "spec.mess_index" in info.value.message and "configurations 0-4" in info.value.message
        obs = c.reset(EpisodeSpec(seed=200, mess_index=4, resolution=32, max_steps=50))  # still usable
        assert obs.step == 0


def test_session_limit(server: SimServer) -> None:
    clients = [client(server) for _ in range(3)]
    for c in clients:
        c.reset(SPEC)
    extra = client(server)
    with pytest.raises(RemoteError) as info:
        extra.reset(SPEC)
    assert info.value.code == ErrorCode.server_busy and "max_sessions" in info.value.message
    clients.pop().close()
    assert extra.reset(SPEC).step == 0
    for c in [*clients, extra]:
        c.close()


def test_episode_exception_becomes_internal_error_and_session_survives() -> None:
    srv = start_server(lambda: FakeEpisode(fail_on="LookUp"))
    try:
        with client(srv) as c:
            c.reset(SPEC)
            with pytest.raises(RemoteError) as info:
                c.step(Action(ActionName.LookUp))
            assert info.value.code == ErrorCode.internal and "fake failure on LookUp" in info.value.message
            assert c.step(Action(ActionName.MoveAhead)).step == 1
    finally:
        srv.stop()


def test_session_of_a_vanished_client_is_freed(server: SimServer) -> None:
    z = zenoh.open(make_config(False, server.config.endpoint))
    c = client(server, zsession=z)
    c.reset(SPEC)
    survivor = client(server)
    survivor.reset(SPEC)
    assert set(server.sessions) == {c.session_id, survivor.session_id}
    z.close()  # no close request: the liveliness token just disappears
    assert wait_until(lambda: server.sessions == (survivor.session_id,), timeout=5.0), server.sessions
    assert survivor.step(Action(ActionName.MoveAhead)).step == 1
    survivor.close()


def test_request_sent_by_a_client_that_then_vanished_opens_no_session(
    server: SimServer, raw_zenoh: zenoh.Session
) -> None:
    sid = server.config.server_id
    raw_zenoh.liveliness().declare_token(keys.alive_client(sid, "ghost")).undeclare()
    assert wait_until(lambda: "ghost" in server._departed)  # the server saw the client leave
    late = raw_request(raw_zenoh, keys.sim_op(sid, "ghost", "reset"), encode(ResetRequest("ghost", SPEC)))
    assert late.code == ErrorCode.unknown_session and "disconnected" in late.message
    assert server.sessions == ()
    with client(server, session="ghost") as c:  # a new client may take the id again
        assert c.reset(SPEC).step == 0


def test_no_server_is_a_timeout() -> None:
    start = time.monotonic()
    with pytest.raises(TimeoutError, match="no tidee server 'nobody'"):
        SimClient(endpoint=free_endpoint(), server_id="nobody", connect_timeout=0.3)
    assert time.monotonic() - start < 5


def test_serve_shuts_down_cleanly_on_sigterm() -> None:
    endpoint, sid = free_endpoint(), f"t{uuid.uuid4().hex[:8]}"
    code = (
        "from tidee.server.service import ServerConfig, serve; from tests.support.fakes import FakeEpisode; "
        f"serve(ServerConfig(endpoint={endpoint!r}, server_id={sid!r}), FakeEpisode)"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env)
    try:
        with SimClient(endpoint=endpoint, server_id=sid, timeout=10.0, connect_timeout=30.0) as c:
            c.reset(SPEC)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=15) == 0
            with pytest.raises(TimeoutError):
                c.step(Action(ActionName.MoveAhead))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_real_episode_over_zenoh() -> None:
    """The real simulator behind the server (a small room, the tiny renderer)."""
    pytest.importorskip("pybullet")
    srv = start_server(factory=None, renderer="tiny")  # None: the real Episode
    try:
        with client(srv) as c:
            obs = c.reset(EpisodeSpec(room_type="Kitchen", seed=3, resolution=64), ground_truth=True)
            assert obs.rgb.shape == (64, 64, 3) and obs.depth.max() > 0
            assert obs.ground_truth is not None and len(obs.ground_truth.objects) > 0
            obs = c.step(Action(ActionName.RotateLeft))
            assert obs.success and obs.agent_pose[2] == pytest.approx(90.0, abs=1.0)
            assert "objects" in c.state()
    finally:
        srv.stop()


def test_a_second_client_asking_for_a_held_session_id_is_refused_by_name(server: SimServer) -> None:
    with client(server, session="shared-id") as first:
        first.reset(SPEC)
        first.step(Action(ActionName.MoveAhead))
        second = client(server, session="shared-id")  # its own Zenoh session: another client
        for call in (lambda: second.reset(SPEC), lambda: second.step(Action(ActionName.MoveAhead))):
            with pytest.raises(RemoteError) as info:
                call()
            assert info.value.code == ErrorCode.invalid_field
            assert info.value.message == (
                f"field 'session': session 'shared-id' is held by another client on server "
                f"{server.config.server_id!r}; use another session id (tidee agent --session)"
            )
        second.close()  # its close is refused too (and swallowed): the first's session stays
        assert server.sessions == ("shared-id",)
        assert first.step(Action(ActionName.MoveAhead)).step == 2, "the first client's episode went on"
        assert first.reset(SPEC).step == 0, "its own client may still reset it"
    assert wait_until(lambda: server.sessions == ())
    with client(server, session="shared-id") as third:  # once freed, the id is anyone's again
        assert third.reset(SPEC).step == 0


def test_the_info_queryable_says_how_full_the_server_is(server: SimServer, raw_zenoh: zenoh.Session) -> None:
    sid = server.config.server_id
    key = keys.server_info(sid)

    def info(session: str | None = None) -> ServerInfo:
        return raw_request(raw_zenoh, key, encode(ServerInfoRequest(session)))

    assert info() == ServerInfo(sid, sessions=0, max_sessions=3, holds_session=False)
    with client(server) as c:
        c.reset(SPEC)
        assert info(c.session_id) == ServerInfo(sid, 1, 3, holds_session=True)
        assert info("someone-else") == ServerInfo(sid, 1, 3, holds_session=False)
    bad = raw_request(raw_zenoh, key, b"not a frame")
    assert isinstance(bad, ErrorReply) and bad.code == ErrorCode.malformed
    wrong = raw_request(raw_zenoh, key, encode(StateRequest("s1")))
    assert wrong.code == ErrorCode.malformed and "expected ServerInfoRequest" in wrong.message
    assert info().server_id == sid, "still answering after bad requests"


def test_no_server_may_take_the_reserved_id_auto() -> None:
    with pytest.raises(ValueError, match="server_id 'auto' is reserved"):
        ServerConfig(server_id="auto")
