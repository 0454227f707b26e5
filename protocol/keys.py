"""Every Zenoh key expression tidee uses, built and parsed in one place.

Ids (server ids, session ids, telemetry kinds) are single key chunks of
``[A-Za-z0-9_-]`` (1 to 128 characters): no ``/``, no wildcards. Builders raise
``ValueError`` on anything else, so a key built here never addresses more than it names.
Builders whose name ends in ``_wildcard`` accept ``"*"`` for an id.

Simulation (one server, many sessions)::

    tidee/sim/{server_id}/session/{session}/{op}   queryable; op in reset|step|phase|state|close
    tidee/sim/{server_id}/obs/{session}            publisher: every observation (viewers)
    tidee/sim/{server_id}/info                     queryable: how full the server is (clients
                                                   choosing a server ask tidee/sim/*/info)

Liveliness::

    tidee/alive/server/{server_id}                 the server is up
    tidee/alive/session/{server_id}/{session}      the server hosts this session (viewers list these)
    tidee/alive/client/{server_id}/{session}       the client owning the session is up; when the
                                                   token goes, the server frees the session

Agent <-> viewer (reserved for the agent and viewer)::

    tidee/agent/{session}/telemetry/{kind}         the agent publishes maps, detections, ...
    tidee/agent/{session}/cmd                      a viewer sends pause, new episode, ...
"""

from __future__ import annotations

import re
from typing import Literal, NamedTuple, get_args

ROOT = "tidee"
# The server id a client gives to name no server: it then chooses a live one (protocol/discovery.py).
# Reserved: no server may take it.
AUTO_SERVER = "auto"
SessionOp = Literal["reset", "step", "phase", "state", "close"]
SESSION_OPS: tuple[str, ...] = get_args(SessionOp)
MAX_ID_LENGTH = 128
_ID_PATTERN = re.compile(rf"[A-Za-z0-9_-]{{1,{MAX_ID_LENGTH}}}")


def is_valid_id(value: object) -> bool:
    return isinstance(value, str) and _ID_PATTERN.fullmatch(value) is not None


def check_id(what: str, value: object) -> str:
    """Return ``value`` if it is a valid key chunk, else raise ``ValueError`` naming ``what``."""
    if not is_valid_id(value):
        raise ValueError(f"{what} must be 1-{MAX_ID_LENGTH} characters of [A-Za-z0-9_-], got {value!r}")
    return value  # type: ignore[return-value]


def _id_or_any(what: str, value: str) -> str:
    return value if value == "*" else check_id(what, value)


def _split(key: object, pattern: str) -> list[str]:
    """Split ``key`` on ``/`` and match it against ``pattern`` (``<x>`` chunks are free)."""
    parts, expected = str(key).split("/"), pattern.split("/")
    if len(parts) != len(expected) or any(e != p for e, p in zip(expected, parts) if not e.startswith("<")):
        raise ValueError(f"expected a key like {pattern}, got {str(key)!r}")
    return parts


# --- simulation -------------------------------------------------------------------------


class SimOpKey(NamedTuple):
    server_id: str
    session: str
    op: str


def sim_op(server_id: str, session: str, op: str) -> str:
    """Key of ``op`` (reset, step, state, close) on one session."""
    if op not in SESSION_OPS:
        raise ValueError(f"op must be one of {SESSION_OPS}, got {op!r}")
    return f"{ROOT}/sim/{check_id('server_id', server_id)}/session/{check_id('session', session)}/{op}"


def sim_op_wildcard(server_id: str, op: str = "*") -> str:
    """What a server's queryable listens on: ``op`` (default: every op) of every session."""
    if op != "*" and op not in SESSION_OPS:
        raise ValueError(f"op must be '*' or one of {SESSION_OPS}, got {op!r}")
    return f"{ROOT}/sim/{check_id('server_id', server_id)}/session/*/{op}"


def parse_sim_op(key: object) -> SimOpKey:
    """Inverse of :func:`sim_op`; ``ValueError`` saying what is wrong otherwise."""
    _, _, server_id, _, session, op = _split(key, f"{ROOT}/sim/<server_id>/session/<session>/<op>")
    if op not in SESSION_OPS:
        raise ValueError(f"unknown op {op!r} in {str(key)!r}; expected one of {SESSION_OPS}")
    return SimOpKey(check_id("server_id", server_id), check_id("session", session), op)


def observations(server_id: str, session: str) -> str:
    """Where the server publishes every observation of ``session``."""
    return f"{ROOT}/sim/{check_id('server_id', server_id)}/obs/{check_id('session', session)}"


def observations_wildcard(server_id: str = "*", session: str = "*") -> str:
    return f"{ROOT}/sim/{_id_or_any('server_id', server_id)}/obs/{_id_or_any('session', session)}"


def parse_observations(key: object) -> tuple[str, str]:
    """``(server_id, session)`` of an observation key."""
    _, _, server_id, _, session = _split(key, f"{ROOT}/sim/<server_id>/obs/<session>")
    return check_id("server_id", server_id), check_id("session", session)


def server_info(server_id: str) -> str:
    """Where a server answers ``ServerInfoRequest``: its load and capacity."""
    return f"{ROOT}/sim/{check_id('server_id', server_id)}/info"


def server_info_wildcard() -> str:
    """What a client asks to hear from every live server at once."""
    return f"{ROOT}/sim/*/info"


def parse_server_info(key: object) -> str:
    """The server id of an info key."""
    _, _, server_id, _ = _split(key, f"{ROOT}/sim/<server_id>/info")
    return check_id("server_id", server_id)


# --- liveliness -------------------------------------------------------------------------


def alive_server(server_id: str) -> str:
    return f"{ROOT}/alive/server/{check_id('server_id', server_id)}"


def alive_servers_wildcard() -> str:
    return f"{ROOT}/alive/server/*"


def alive_session(server_id: str, session: str) -> str:
    """Declared by the server while it hosts ``session``."""
    return f"{ROOT}/alive/session/{check_id('server_id', server_id)}/{check_id('session', session)}"


def alive_sessions_wildcard(server_id: str = "*") -> str:
    return f"{ROOT}/alive/session/{_id_or_any('server_id', server_id)}/*"


def alive_client(server_id: str, session: str) -> str:
    """Declared by the client owning ``session``; the server watches it."""
    return f"{ROOT}/alive/client/{check_id('server_id', server_id)}/{check_id('session', session)}"


def alive_clients_wildcard(server_id: str) -> str:
    return f"{ROOT}/alive/client/{check_id('server_id', server_id)}/*"


def parse_alive(key: object) -> tuple[str, str, str | None]:
    """``(role, server_id, session)`` of a liveliness key; role is server, session or client;
    ``session`` is None for a server token."""
    parts = str(key).split("/")
    if len(parts) == 4:
        _, _, server_id = _split(key, f"{ROOT}/alive/server/<server_id>")[1:]
        return "server", check_id("server_id", server_id), None
    _, _, role, server_id, session = _split(key, f"{ROOT}/alive/<role>/<server_id>/<session>")
    if role not in ("session", "client"):
        raise ValueError(f"unknown liveliness role {role!r} in {str(key)!r}; expected session or client")
    return role, check_id("server_id", server_id), check_id("session", session)


# --- agent <-> viewer -------------------------------------------------------------------


def agent_telemetry(session: str, kind: str) -> str:
    return f"{ROOT}/agent/{check_id('session', session)}/telemetry/{check_id('kind', kind)}"


def agent_telemetry_wildcard(session: str = "*") -> str:
    return f"{ROOT}/agent/{_id_or_any('session', session)}/telemetry/*"


def parse_agent_telemetry(key: object) -> tuple[str, str]:
    """``(session, kind)`` of a telemetry key."""
    _, _, session, _, kind = _split(key, f"{ROOT}/agent/<session>/telemetry/<kind>")
    return check_id("session", session), check_id("kind", kind)


def agent_cmd(session: str) -> str:
    return f"{ROOT}/agent/{check_id('session', session)}/cmd"
