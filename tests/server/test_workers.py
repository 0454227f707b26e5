"""Episodes in child processes behind the Zenoh server: placement, errors, dead children, shutdown."""

from __future__ import annotations

import dataclasses
import functools
import os
import signal
import subprocess
import uuid
from collections.abc import Iterator

import numpy as np
import pytest

from tests.support.fakes import FakeEpisode
from tests.support.net import REPO, SPEC, client, free_endpoint, start_server, wait_until
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.codec import decode
from tidee.protocol.messages import Action, ActionName, EpisodeSpec, ErrorCode, Observation
from tidee.server.bench_transport import server_command
from tidee.server.service import ServerConfig, SimServer
from tidee.server.workers import (
    MIN_FRAME_AREA,
    EncodedObservation,
    EpisodeProcess,
    EpisodeProcesses,
    RemoteEpisodeError,
    Wire,
    _portable,
)


@pytest.fixture
def two_process_server() -> Iterator[SimServer]:
    """Fake episodes (no physics) in two child processes: the process machinery, fast."""
    srv = start_server(EpisodeProcesses(2, make_episode=FakeEpisode), max_sessions=4)
    yield srv
    srv.stop()


def pid_of(server: SimServer, session: str) -> int:
    episode = server._sessions[session].episode
    assert episode is not None
    return episode.pid  # type: ignore[attr-defined]


def assert_same_observation(a: Observation, b: Observation) -> None:
    for field in dataclasses.fields(Observation):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if field.name == "ground_truth" and x is not None:
            assert np.array_equal(x.instance_seg, y.instance_seg) and x.objects == y.objects
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), field.name
        else:
            assert x == y, field.name


def test_process_count_follows_the_cores_and_the_session_limit() -> None:
    assert ServerConfig(processes=3).process_count() == 3
    assert ServerConfig(processes=0, max_sessions=1).process_count() == 1
    assert ServerConfig(processes=0, max_sessions=64).process_count() == len(os.sched_getaffinity(0))
    with pytest.raises(ValueError, match="processes must be >= 0"):
        ServerConfig(processes=-1)


def test_real_episode_in_a_child_process_matches_one_in_this_process() -> None:
    pytest.importorskip("pybullet")
    from tidee.server.episode import Episode

    spec = EpisodeSpec(room_type="Kitchen", seed=3, mess_index=None, resolution=64, max_steps=20)
    actions = [
        Action(ActionName.RotateLeft),
        Action(ActionName.MoveAhead),
        Action(ActionName.LookDown),
        Action(ActionName.PickupObject, 0.5, 0.6),
    ]
    srv = start_server(None, renderer="tiny", processes=1)  # None: real episodes in child processes
    local = Episode(renderer="tiny")
    try:
        assert srv.processes is not None and len(srv.processes) == 1
        with client(srv) as c:
            remote_obs = [c.reset(spec, ground_truth=True)] + [c.step(a, ground_truth=True) for a in actions]
            assert pid_of(srv, c.session_id) not in (None, os.getpid())
            local_obs = [local.reset(spec, session=c.session_id, ground_truth=True)]
            local_obs += [local.step(a, ground_truth=True) for a in actions]
            assert c.state() == local.state()
        for remote, here in zip(remote_obs, local_obs):
            assert_same_observation(remote, here)
    finally:
        local.close()
        srv.stop()
    assert srv.processes.pids == [None]  # stop() ended the child


def test_encoded_frames_come_through_shared_memory_and_a_dead_childs_block_is_removed() -> None:
    process = EpisodeProcess(make_episode=FakeEpisode)
    here = FakeEpisode()
    try:
        remote = process.open()
        small = dataclasses.replace(SPEC, resolution=32)
        got = remote.encoded(Wire(), "reset", small, session="s", ground_truth=False)
        assert isinstance(got, EncodedObservation) and not got.private and got.feed is None
        assert_same_observation(decode(got.frame), here.reset(small, session="s"))
        area = process._current.frames.shm  # type: ignore[union-attr]
        assert area is not None and area.size == MIN_FRAME_AREA
        # ground truth, and a viewer listening: the feed's copy without it rides along
        action = Action(ActionName.MoveAhead)
        got = remote.encoded(Wire(feed=True), "step", action, ground_truth=True)
        want = here.step(action, ground_truth=True)
        assert got.private and got.feed is not None
        assert_same_observation(decode(got.frame), want)
        assert_same_observation(decode(got.feed), dataclasses.replace(want, ground_truth=None))
        # a frame bigger than the block: the child makes a bigger one, the parent follows it
        big = dataclasses.replace(SPEC, resolution=512)  # 512² rgb + float32 depth: 1.75 MB
        got = remote.encoded(Wire(raw_depth="mm"), "reset", big, session="s")
        back = decode(got.frame)
        assert back.depth.shape == (512, 512) and back.step == 0
        grown = process._current.frames.shm  # type: ignore[union-attr]
        assert grown is not None and grown.name != area.name and grown.size > MIN_FRAME_AREA
        assert not os.path.exists(f"/dev/shm/{area.name.lstrip('/')}")  # the child removed the old one
        with pytest.raises(ValueError, match="cannot observe 'state'"):
            remote.encoded(Wire(), "state")
        os.kill(remote.pid, signal.SIGKILL)  # type: ignore[arg-type]
        with pytest.raises(Exception, match="gone"):
            remote.encoded(Wire(), "step", action)
        assert not os.path.exists(f"/dev/shm/{grown.name.lstrip('/')}")  # the parent removed it
    finally:
        process.stop()


def test_new_sessions_go_to_the_least_loaded_process(two_process_server: SimServer) -> None:
    srv = two_process_server
    a, b, c = client(srv), client(srv), client(srv)
    a.reset(SPEC)
    b.reset(SPEC)
    assert pid_of(srv, a.session_id) != pid_of(srv, b.session_id)
    assert {srv._sessions[s].worker for s in (a.session_id, b.session_id)} == {0, 1}
    freed = pid_of(srv, a.session_id)
    a.close()
    c.reset(SPEC)  # the process a left has no session now: c goes there, not beside b
    assert pid_of(srv, c.session_id) == freed
    assert b.step(Action(ActionName.MoveAhead)).step == 1 and c.step(Action(ActionName.MoveAhead)).step == 1
    b.close()
    c.close()


def test_an_exception_in_the_child_becomes_internal_error_and_the_session_survives() -> None:
    srv = start_server(EpisodeProcesses(1, make_episode=functools.partial(FakeEpisode, fail_on="LookUp")))
    try:
        with client(srv) as c:
            c.reset(SPEC)
            with pytest.raises(RemoteError) as info:
                c.step(Action(ActionName.LookUp))
            assert info.value.code == ErrorCode.internal
            assert "step failed: RuntimeError: fake failure on LookUp" in info.value.message
            assert c.step(Action(ActionName.MoveAhead)).step == 1
    finally:
        srv.stop()


def test_an_exception_that_cannot_be_pickled_is_named() -> None:
    class Local(Exception):  # a local class does not pickle
        pass

    portable = _portable(Local("boom"))
    assert isinstance(portable, RemoteEpisodeError) and str(portable) == "Local: boom"
    same = ValueError("kept")
    assert _portable(same) is same


def test_a_killed_child_fails_its_session_clearly_and_others_keep_working(
    two_process_server: SimServer,
) -> None:
    srv = two_process_server
    victim, survivor = client(srv), client(srv)
    victim.reset(SPEC)
    survivor.reset(SPEC)
    dead_pid = pid_of(srv, victim.session_id)
    os.kill(dead_pid, signal.SIGKILL)
    with pytest.raises(RemoteError) as info:
        victim.step(Action(ActionName.MoveAhead))
    assert info.value.code == ErrorCode.internal
    assert "EpisodeProcessDied" in info.value.message and "killed by SIGKILL" in info.value.message
    assert "send reset" in info.value.message
    with pytest.raises(RemoteError, match="EpisodeProcessDied"):  # still lost, until a reset
        victim.state()
    assert survivor.step(Action(ActionName.MoveAhead)).step == 1
    # A reset starts the session again in a fresh child on the same worker.
    assert victim.reset(SPEC).step == 0
    assert pid_of(srv, victim.session_id) not in (dead_pid, pid_of(srv, survivor.session_id))
    assert victim.step(Action(ActionName.MoveAhead)).step == 1
    newcomer = client(srv)
    assert newcomer.reset(SPEC).step == 0
    for c in (victim, survivor, newcomer):
        c.close()


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_retired_child_takes_no_new_session_keeps_its_live_ones_and_stops_when_empty() -> None:
    srv = start_server(EpisodeProcesses(1, make_episode=FakeEpisode, recycle_after=2), max_sessions=4)
    slot = srv.processes.processes[0]  # type: ignore[union-attr]
    reference = FakeEpisode()
    try:
        a, b, c = client(srv), client(srv), client(srv)
        a.reset(SPEC)
        b.reset(SPEC)  # the child's second reset: it retires, holding a and b
        old = pid_of(srv, a.session_id)
        assert slot.pid is None and slot.pids == [old]
        c.reset(SPEC)  # a new session goes to a fresh child
        fresh = pid_of(srv, c.session_id)
        assert fresh != old and pid_alive(old) and slot.started == 2
        # a lives on in the retired child, undisturbed: the same frames as an episode never moved
        reference.reset(SPEC, session=a.session_id)
        for action in (Action(ActionName.MoveAhead), Action(ActionName.RotateLeft)):
            assert_same_observation(a.step(action), reference.step(action))
        assert pid_of(srv, a.session_id) == old
        # its next reset moves it to the fresh child; the retired one still holds b
        assert_same_observation(a.reset(SPEC), reference.reset(SPEC, session=a.session_id))
        assert pid_of(srv, a.session_id) == fresh and pid_alive(old)
        b.close()  # the retired child's last session: it stops
        assert not pid_alive(old)
        assert (
            a.step(Action(ActionName.MoveAhead)).step == 1 and c.step(Action(ActionName.MoveAhead)).step == 1
        )
        a.close()
        c.close()
    finally:
        srv.stop()
    assert slot.pids == []


def test_recycling_off_keeps_one_child() -> None:
    srv = start_server(EpisodeProcesses(1, make_episode=FakeEpisode, recycle_after=0))
    try:
        pids = set()
        with client(srv) as c:
            for _ in range(5):
                c.reset(SPEC)
                pids.add(pid_of(srv, c.session_id))
        assert len(pids) == 1 and srv.processes.processes[0].started == 1  # type: ignore[union-attr]
    finally:
        srv.stop()
    with pytest.raises(ValueError, match="recycle_after must be >= 0"):
        ServerConfig(recycle_after=-1)


def test_a_real_episode_gives_the_same_frames_after_its_child_is_recycled() -> None:
    pytest.importorskip("pybullet")
    spec = EpisodeSpec(room_type="Kitchen", seed=3, mess_index=None, resolution=48, max_steps=20)
    actions = [Action(ActionName.RotateLeft), Action(ActionName.MoveAhead), Action(ActionName.LookDown)]
    srv = start_server(None, renderer="tiny", processes=1, recycle_after=1)
    try:
        with client(srv) as c:
            before = [c.reset(spec, ground_truth=True)] + [c.step(a, ground_truth=True) for a in actions]
            first = pid_of(srv, c.session_id)  # retired after that reset; the steps still ran there
            after = [c.reset(spec, ground_truth=True)] + [c.step(a, ground_truth=True) for a in actions]
            assert pid_of(srv, c.session_id) != first and not pid_alive(first)
        for x, y in zip(before, after):
            assert_same_observation(x, y)
    finally:
        srv.stop()
    assert srv.processes is not None and srv.processes.processes[0].started == 2


def test_sigterm_to_tidee_server_leaves_no_process_behind() -> None:
    pytest.importorskip("pybullet")
    endpoint, sid = free_endpoint(), f"t{uuid.uuid4().hex[:8]}"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    command = server_command(endpoint, sid, "tiny", "--processes", "2")
    # Its own process group: what must be empty at the end.
    proc = subprocess.Popen(command, cwd=REPO, env=env, start_new_session=True)
    group = proc.pid

    def group_alive() -> bool:
        try:
            os.killpg(group, 0)
            return True
        except ProcessLookupError:
            return False

    try:
        with (
            SimClient(endpoint=endpoint, server_id=sid, timeout=60.0, connect_timeout=30.0) as a,
            SimClient(endpoint=endpoint, server_id=sid, timeout=60.0, connect_timeout=30.0) as b,
        ):
            small = EpisodeSpec(room_type="Kitchen", seed=3, resolution=32)
            a.reset(small)
            b.reset(small)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=20) == 0
        assert wait_until(lambda: not group_alive(), timeout=10.0), "processes of the server's group remain"
    finally:
        if group_alive():
            os.killpg(group, signal.SIGKILL)
        if proc.poll() is None:
            proc.wait()
