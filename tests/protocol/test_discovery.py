"""Choosing a server (``server_id="auto"``): the ranking, and clients moving between live servers.

The ranking is checked on hand-made ``ServerInfo``s; the rest runs two servers with fake episodes
(in this process) behind a Zenoh router (in this process too), on loopback.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from tests.support.fakes import FakeEpisode
from tests.support.net import SPEC, free_endpoint, wait_until
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.discovery import ask_servers, describe, rank_servers
from tidee.protocol.messages import Action, ActionName, ErrorCode, ServerInfo
from tidee.protocol.zenoh_config import open_router, open_session
from tidee.server.service import ServerConfig, SimServer

# --- the ranking ------------------------------------------------------------------------------


def _ids(infos: list[ServerInfo]) -> list[str]:
    return [i.server_id for i in infos]


def test_the_emptiest_server_for_its_capacity_comes_first_and_full_ones_not_at_all() -> None:
    infos = [
        ServerInfo("big", sessions=4, max_sessions=16),  # a quarter full
        ServerInfo("small", sessions=1, max_sessions=2),  # half full, though it holds fewer sessions
        ServerInfo("full", sessions=2, max_sessions=2),
        ServerInfo("empty", sessions=0, max_sessions=4),
    ]
    assert _ids(rank_servers(infos, "s1")) == ["empty", "big", "small"]
    assert describe(infos) == (
        "big (4/16 sessions), empty (0/4 sessions), full (2/2 sessions), small (1/2 sessions)"
    )
    assert describe([]) == "none"


def test_a_server_holding_the_session_comes_first_even_full_and_avoided_ones_last() -> None:
    infos = [
        ServerInfo("a", 0, 4),
        ServerInfo("b", 4, 4, holds_session=True),  # the session is there: go there, full or not
        ServerInfo("c", 1, 4),
    ]
    assert _ids(rank_servers(infos, "s1")) == ["b", "a", "c"]
    assert _ids(rank_servers(infos, "s1", avoid={"b", "a"})) == ["c", "b", "a"]


def test_ties_are_broken_by_session_id_reproducibly_and_spread_over_servers() -> None:
    infos = [ServerInfo(f"sim{k}", 0, 16) for k in range(4)]
    firsts = {rank_servers(infos, f"agent-{n}")[0].server_id for n in range(40)}
    assert firsts == {"sim0", "sim1", "sim2", "sim3"}, "equally loaded servers share new sessions"
    once = _ids(rank_servers(infos, "agent-7"))
    assert _ids(rank_servers(list(reversed(infos)), "agent-7")) == once, (
        "the order of answers does not matter"
    )


# --- clients choosing among live servers -------------------------------------------------------


@dataclass
class Fleet:
    router: str  # the endpoint clients connect to
    servers: dict[str, SimServer]

    def client(self, session: str | None = None, **kw: object) -> SimClient:
        return SimClient(router=self.router, server_id="auto", session=session, timeout=10.0, **kw)  # type: ignore[arg-type]


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    """A router and two servers of 2 sessions each, fake episodes."""
    endpoint = free_endpoint()
    router, _ = open_router([endpoint])
    tag = uuid.uuid4().hex[:6]
    servers = {}
    try:
        for k in range(2):
            cfg = ServerConfig(router=endpoint, server_id=f"s{k}{tag}", max_sessions=2)
            servers[cfg.server_id] = SimServer(cfg, FakeEpisode).start()
        yield Fleet(endpoint, servers)
    finally:
        for server in servers.values():
            server.stop()
        router.close()


def test_clients_fill_the_servers_evenly_and_wait_when_all_are_full(fleet: Fleet) -> None:
    clients = []
    for _ in range(4):
        c = fleet.client()
        c.reset(SPEC)
        clients.append(c)
    held = {sid: len(server.sessions) for sid, server in fleet.servers.items()}
    assert held == dict.fromkeys(fleet.servers, 2), held
    assert {c.server_id for c in clients[:2]} == set(fleet.servers), "the second client took the other server"
    start = time.monotonic()
    with pytest.raises(TimeoutError) as info:
        fleet.client(connect_timeout=0.5)
    assert "had a free session within 0.5 s: " in str(info.value)
    assert all(f"{sid} (2/2 sessions)" in str(info.value) for sid in fleet.servers)
    assert time.monotonic() - start < 5
    clients.pop().close()
    late = fleet.client(connect_timeout=5)  # a slot came free: it is found
    assert late.reset(SPEC).step == 0
    for c in [*clients, late]:
        c.close()


def test_a_client_that_chose_a_server_counts_there_before_its_first_reset(fleet: Fleet) -> None:
    first = fleet.client()
    assert wait_until(lambda: first.session_id in fleet.servers[first.server_id]._announced)
    # A session id whose tie-break alone would pick the first client's server too.
    empty = [ServerInfo(sid, 0, 2) for sid in fleet.servers]
    twin = next(f"b{n}" for n in range(100) if rank_servers(empty, f"b{n}")[0].server_id == first.server_id)
    second = fleet.client(session=twin)  # no session is open yet, but the first client is there
    assert second.server_id != first.server_id
    for c in (first, second):
        c.close()


def test_a_full_server_refusing_the_reset_sends_the_client_to_the_next(fleet: Fleet) -> None:
    first = fleet.client()
    # Fill the first client's server behind its back, as another agent starting at the same time would.
    chosen, other = first.server_id, next(sid for sid in fleet.servers if sid != first.server_id)
    fillers = [SimClient(router=fleet.router, server_id=chosen, timeout=10.0) for _ in range(2)]
    for f in fillers:
        f.reset(SPEC)
    assert first.reset(SPEC).step == 0
    assert first.server_id == other
    assert first.session_id in fleet.servers[other].sessions
    assert fleet.servers[chosen].sessions == tuple(f.session_id for f in fillers)
    for c in (first, *fillers):
        c.close()


def test_when_every_server_refuses_the_error_names_each(fleet: Fleet) -> None:
    c = fleet.client()
    sids = list(fleet.servers)
    fillers = [SimClient(router=fleet.router, server_id=sid, timeout=10.0) for sid in sids for _ in range(2)]
    for f in fillers:
        f.reset(SPEC)
    with pytest.raises(RemoteError) as info:
        c.reset(SPEC)
    assert info.value.code == ErrorCode.server_busy
    assert info.value.message.startswith(f"no live server took session {c.session_id!r}: ")
    tried, other = (c.server_id, *(s for s in sids if s != c.server_id))
    assert f"{tried}: server {tried!r} holds 2 sessions" in info.value.message
    assert info.value.message.endswith(f"; the others are full: {other} (2/2 sessions)")
    for f in (c, *fillers):
        f.close()


def test_a_session_id_held_on_one_server_is_refused_by_that_server(fleet: Fleet) -> None:
    first = fleet.client(session="agent0")
    first.reset(SPEC)
    other = next(sid for sid in fleet.servers if sid != first.server_id)
    twin = fleet.client(session="agent0")  # the other server is emptier, but agent0 lives on the first
    assert twin.server_id == first.server_id != other
    with pytest.raises(RemoteError) as info:
        twin.reset(SPEC)
    assert info.value.code == ErrorCode.invalid_field and "session 'agent0' is held by another client" in str(
        info.value
    )
    twin.close()
    assert first.step(Action(ActionName.MoveAhead)).step == 1
    first.close()


def test_a_client_whose_server_goes_away_moves_to_another(fleet: Fleet) -> None:
    c = fleet.client()
    c.reset(SPEC)
    c.step(Action(ActionName.MoveAhead))
    gone = c.server_id
    fleet.servers[gone].stop()
    with pytest.raises(TimeoutError, match="went away"):
        c.step(Action(ActionName.MoveAhead))
    assert c.choose_server(5.0) != gone
    assert c.reset(SPEC).step == 0 and c.step(Action(ActionName.MoveAhead)).step == 1
    assert fleet.servers[c.server_id].sessions == (c.session_id,)
    c.close()


def test_only_live_servers_answer_and_a_named_client_cannot_choose(fleet: Fleet) -> None:
    z = open_session(False, router=fleet.router)
    try:
        assert wait_until(lambda: len(ask_servers(z)) == 2, timeout=5)
        sid = next(iter(fleet.servers))
        fleet.servers[sid].stop()
        assert wait_until(lambda: _ids(ask_servers(z)) == [s for s in fleet.servers if s != sid], timeout=5)
        named = SimClient(
            router=fleet.router, server_id=next(s for s in fleet.servers if s != sid), zsession=z
        )
        with pytest.raises(RuntimeError, match="choose_server needs server_id='auto'"):
            named.choose_server(1.0)
        named.close()
    finally:
        z.close()


def test_no_server_at_all_is_a_timeout_that_says_how_to_start_one() -> None:
    endpoint = free_endpoint()
    router, _ = open_router([endpoint])
    try:
        with pytest.raises(TimeoutError) as info:
            SimClient(router=endpoint, server_id="auto", connect_timeout=0.3)
        start_one = f"(start one with: tidee server --router {endpoint})"
        assert str(info.value) == f"no live tidee server at {endpoint} within 0.3 s {start_one}"
    finally:
        router.close()
