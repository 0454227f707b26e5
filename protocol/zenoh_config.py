"""Zenoh session configuration: peer mode on loopback by default, a router on request.

Without a router (the default), processes on one machine find each other through one
well-known *rendezvous* endpoint, ``TIDEE_ZENOH_ENDPOINT`` (default
``tcp/127.0.0.1:7447``): the server listens there, every other process connects to it
and listens on an ephemeral loopback port, and gossip scouting (over those links, not
multicast) lets agents and viewers connect to each other directly. Multicast scouting is
off, so nothing is announced beyond the configured endpoints.

``zenoh.open`` returns at once (``scouting/delay`` 0: Zenoh's default makes a peer's
open wait up to 500 ms for gossip): wait for what you need before the first request,
as ``SimClient`` waits for the server's liveliness token.

With a router endpoint (``TIDEE_ZENOH_ROUTER`` or ``router=``, e.g. ``tcp/zenohd:7447``
in compose), every process runs in client mode connected to that router instead.
"""

from __future__ import annotations

import json
import os
import re

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ENDPOINT_ENV = "TIDEE_ZENOH_ENDPOINT"
ROUTER_ENV = "TIDEE_ZENOH_ROUTER"
_EPHEMERAL_LOOPBACK = "tcp/127.0.0.1:0"


def resolve_endpoint(endpoint: str | None = None) -> str:
    """The rendezvous endpoint: the argument, else ``TIDEE_ZENOH_ENDPOINT``, else the default."""
    return endpoint or os.environ.get(ENDPOINT_ENV) or DEFAULT_ENDPOINT


def resolve_router(router: str | None = None) -> str | None:
    """The router endpoint: the argument, else ``TIDEE_ZENOH_ROUTER``, else None (peer mode)."""
    return router or os.environ.get(ROUTER_ENV) or None


def make_config(listen: bool, endpoint: str | None = None, router: str | None = None) -> zenoh.Config:
    """A Zenoh config for one process.

    ``listen``: this process is the rendezvous (the server): it listens on the endpoint;
    otherwise it connects to it. Ignored in router mode, where everyone connects to the router.
    """
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    router = resolve_router(router)
    if router:
        _set(conf, "mode", "client")
        _set(conf, "connect/endpoints", [router])
        return conf
    rendezvous = resolve_endpoint(endpoint)
    _set(conf, "mode", "peer")
    _set(conf, "scouting/gossip/enabled", True)
    _set(conf, "scouting/delay", 0)
    if listen:
        _set(conf, "listen/endpoints", [rendezvous])
        _set(conf, "connect/endpoints", [])
    else:
        _set(conf, "listen/endpoints", [_EPHEMERAL_LOOPBACK])
        _set(conf, "connect/endpoints", [rendezvous])
    return conf


def _set(conf: zenoh.Config, key: str, value: object) -> None:
    conf.insert_json5(key, json.dumps(value))


class ZenohOpenError(ConnectionError):
    """A Zenoh session could not be opened: a bad endpoint, a port in use, an unreachable router."""


def open_session(listen: bool, endpoint: str | None = None, router: str | None = None) -> zenoh.Session:
    """``zenoh.open(make_config(...))``, with Zenoh's refusal turned into a ``ZenohOpenError``
    naming the endpoint."""
    try:
        return zenoh.open(make_config(listen, endpoint, router))
    except zenoh.ZError as e:
        raise open_error(e, listen, endpoint, router) from None


def open_error(
    error: Exception, listen: bool, endpoint: str | None = None, router: str | None = None
) -> ZenohOpenError:
    """One line for a failed ``zenoh.open``: which endpoint (and which flag or variable gave it) and why."""
    router = resolve_router(router)
    if router:
        where, verb = _origin(router, ROUTER_ENV, "--router", "router"), "connect to it"
        hint = " (is a Zenoh router, zenohd, running there? Without --router, tidee runs in peer mode)"
    else:
        where = _origin(endpoint, ENDPOINT_ENV, "--endpoint", "endpoint")
        verb, hint = ("listen on it" if listen else "connect to it"), ""
    return ZenohOpenError(f"{where}: Zenoh could not {verb}: {zenoh_error_text(error)}{hint}")


def zenoh_error_text(error: Exception) -> str:
    """Zenoh's message without its Rust source locations and debug wrappers."""
    text = str(error)
    m = re.search(r'msg: "(.*?)"', text)
    if m:
        text = m.group(1)
    text = re.sub(r"\s*at /\S+\.rs:\d+\.?", "", text)  # "... at /root/.cargo/.../tcp.rs:61."
    return " ".join(text.split()).rstrip(" .!")


def _origin(given: str | None, env: str, flag: str, what: str) -> str:
    """``--endpoint X``, ``TIDEE_ZENOH_ENDPOINT=X`` or ``the default endpoint X``: where a value came from."""
    if given:
        return f"{flag} {given}"
    if os.environ.get(env):
        return f"{env}={os.environ[env]}"
    return f"the default {what} {DEFAULT_ENDPOINT}"
