"""Which tidee server a client should use, when it names none (``server_id="auto"``, ``keys.AUTO_SERVER``).

The client asks every live server at once: one ``ServerInfoRequest`` to ``tidee/sim/*/info``.
Each server answers on its own key with a ``ServerInfo``: how many sessions it holds now (those
being opened included), the most it may hold (``max_sessions``), and whether it already holds
the asking client's session id. A server that does not answer within the query's timeout (gone,
hung, refused by a router's access control) is not a candidate.

:func:`rank_servers` orders the answers, best first:

1. a server that already holds the session id: the session is there (the client's own, after a
   reconnection; or another client's, and that server refuses the reset by name, which keeps one
   session id to one agent across servers);
2. the fewest sessions relative to capacity (``sessions / max_sessions``), then the fewest sessions;
3. ties: a hash of (session id, server id), so a client's choice is reproducible and clients
   with different session ids spread over equally loaded servers (rendezvous hashing).

A full server (``sessions >= max_sessions``) is left out unless it holds the session; ``avoid``
moves servers to the end (a server that stopped answering mid-episode but still says it is up).
"""

from __future__ import annotations

import zlib
from collections.abc import Collection, Iterable

import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.messages import ServerInfo, ServerInfoRequest

INFO_TIMEOUT_S = 2.0  # how long a client waits for servers' answers to one info query


def ask_servers(
    z: zenoh.Session, session: str | None = None, timeout: float = INFO_TIMEOUT_S
) -> list[ServerInfo]:
    """Every live server's ``ServerInfo``, as answered within ``timeout`` s (unordered).

    An answer that does not decode, or whose server id is not the one in its key, is ignored.
    """
    replies = z.get(
        keys.server_info_wildcard(),
        payload=encode(ServerInfoRequest(session)),
        timeout=timeout,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
    )
    infos: dict[str, ServerInfo] = {}
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            info = decode(reply.ok.payload.to_bytes(), expected=ServerInfo)
            if keys.parse_server_info(reply.ok.key_expr) != info.server_id:
                continue
        except (ProtocolError, ValueError):  # another protocol version, a stray replier
            continue
        infos[info.server_id] = info
    return list(infos.values())


def rank_servers(infos: Iterable[ServerInfo], session: str, avoid: Collection[str] = ()) -> list[ServerInfo]:
    """The servers a new session may go to, best first (module docstring); full ones left out."""
    usable = [i for i in infos if i.holds_session or (0 <= i.sessions < i.max_sessions)]
    return sorted(
        usable,
        key=lambda i: (
            i.server_id in avoid,
            not i.holds_session,
            i.sessions / max(i.max_sessions, 1),
            i.sessions,
            _tie(session, i.server_id),
        ),
    )


def describe(infos: Iterable[ServerInfo]) -> str:
    """``sim0 (16/16 sessions), sim1 (3/16 sessions)``, or ``none`` for no server."""
    shown = [f"{i.server_id} ({i.sessions}/{i.max_sessions} sessions)" for i in sorted(infos, key=_id)]
    return ", ".join(shown) or "none"


def _tie(session: str, server_id: str) -> int:
    return zlib.crc32(f"{session}/{server_id}".encode())  # stable across processes, unlike hash()


def _id(info: ServerInfo) -> str:
    return info.server_id
