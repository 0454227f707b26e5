"""Zenoh session configuration: peer mode on loopback by default, a router on request, and an
operator's own Zenoh config file merged over both.

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

A Zenoh config file (``--zenoh-config FILE``, ``zenoh_config=``, else ``TIDEE_ZENOH_CONFIG``;
JSON5, JSON or YAML as Zenoh reads them) is merged over those defaults: tidee's keys
(``mode``, ``connect/endpoints``, ``listen/endpoints``, ``scouting/...``, themselves built from
``--endpoint``/``--router``/``--listen``) come first, and every key the file sets wins, key by
key (a list such as ``connect/endpoints`` is one key). Relative certificate paths under
``transport/link/tls`` are taken relative to the file's folder. This is how TLS, mutual TLS and
access control are configured (``deploy/secure/``).
"""

from __future__ import annotations

import functools
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ENDPOINT_ENV = "TIDEE_ZENOH_ENDPOINT"
ROUTER_ENV = "TIDEE_ZENOH_ROUTER"
CONFIG_ENV = "TIDEE_ZENOH_CONFIG"
_EPHEMERAL_LOOPBACK = "tcp/127.0.0.1:0"
# Files under transport/link/tls: a relative path is taken relative to the config file.
TLS_FILES = (
    "root_ca_certificate",
    "listen_private_key",
    "listen_certificate",
    "connect_private_key",
    "connect_certificate",
)


def resolve_endpoint(endpoint: str | None = None) -> str:
    """The rendezvous endpoint: the argument, else ``TIDEE_ZENOH_ENDPOINT``, else the default."""
    return endpoint or os.environ.get(ENDPOINT_ENV) or DEFAULT_ENDPOINT


def resolve_router(router: str | None = None) -> str | None:
    """The router endpoint: the argument, else ``TIDEE_ZENOH_ROUTER``, else None (peer mode)."""
    return router or os.environ.get(ROUTER_ENV) or None


def resolve_config_file(zenoh_config: str | os.PathLike[str] | None = None) -> str | None:
    """The Zenoh config file: the argument, else ``TIDEE_ZENOH_CONFIG``, else None (tidee's defaults)."""
    return os.fspath(zenoh_config) if zenoh_config else os.environ.get(CONFIG_ENV) or None


class ZenohConfigError(ValueError):
    """A Zenoh config file tidee cannot use: missing, unparsable, refused by Zenoh as it reads it,
    or naming a certificate file that is missing or not PEM. The message names the file (and the
    flag or variable that gave it) and the problem, in one line."""


def tidee_defaults(listen: bool, endpoint: str | None = None, router: str | None = None) -> dict[str, object]:
    """The keys tidee sets for one process, before any config file: ``{"a/b": value}``.

    ``listen``: this process is the rendezvous (the server): it listens on the endpoint;
    otherwise it connects to it. Ignored in router mode, where everyone connects to the router.
    """
    keys: dict[str, object] = {"scouting/multicast/enabled": False}
    router = resolve_router(router)
    if router:
        keys.update({"mode": "client", "connect/endpoints": [router]})
        return keys
    rendezvous = resolve_endpoint(endpoint)
    keys.update({"mode": "peer", "scouting/gossip/enabled": True, "scouting/delay": 0})
    if listen:
        keys.update({"listen/endpoints": [rendezvous], "connect/endpoints": []})
    else:
        keys.update({"listen/endpoints": [_EPHEMERAL_LOOPBACK], "connect/endpoints": [rendezvous]})
    return keys


def router_defaults(listen: Sequence[str]) -> dict[str, object]:
    """The keys tidee sets for ``tidee router``: a Zenoh router listening on ``listen``, connecting
    nowhere, announcing nothing by multicast."""
    return {
        "mode": "router",
        "listen/endpoints": list(listen),
        "connect/endpoints": [],
        "scouting/multicast/enabled": False,
    }


def make_config(
    listen: bool,
    endpoint: str | None = None,
    router: str | None = None,
    zenoh_config: str | os.PathLike[str] | None = None,
) -> zenoh.Config:
    """A Zenoh config for one process: tidee's defaults (:func:`tidee_defaults`), then the
    config file's keys over them. Raises :class:`ZenohConfigError` for a bad file."""
    return merged_config(tidee_defaults(listen, endpoint, router), zenoh_config)


def merged_config(
    defaults: dict[str, object], zenoh_config: str | os.PathLike[str] | None = None
) -> zenoh.Config:
    """``defaults`` (``{"a/b": value}``) with the config file (argument, else ``TIDEE_ZENOH_CONFIG``)
    over them: a key the file sets keeps the file's value.

    A key counts as set when Zenoh's reading of the file differs there from Zenoh's own default,
    so a file that sets a key to exactly Zenoh's default (``connect: {endpoints: []}``) leaves it
    to tidee.
    """
    path = resolve_config_file(zenoh_config)
    if path is None:
        conf = zenoh.Config()
        for key, value in defaults.items():
            _set(conf, key, value)
        return conf
    origin = _file_origin(zenoh_config)
    conf = load_config_file(path, origin)
    for key, value in defaults.items():
        if conf.get_json(key) == _zenoh_default(key):  # the file leaves it to tidee
            try:
                _set(conf, key, value)
            except zenoh.ZError as e:  # e.g. the file's mode has no such key
                raise ZenohConfigError(f"{origin}: cannot set {key}: {zenoh_error_text(e)}") from None
    return conf


def load_config_file(path: str, origin: str | None = None) -> zenoh.Config:
    """Zenoh's reading of ``path``, relative TLS file paths made relative to its folder, each
    TLS file checked to exist. ``origin`` names the file in errors (default: the path)."""
    origin = origin or path
    if not os.path.isfile(path):
        why = "is a directory" if os.path.isdir(path) else "no such file"
        raise ZenohConfigError(f"{origin}: {why}")
    try:
        conf = zenoh.Config.from_file(path)
    except zenoh.ZError as e:
        raise ZenohConfigError(f"{origin}: Zenoh cannot read it: {zenoh_error_text(e)}") from None
    except OSError as e:
        raise ZenohConfigError(f"{origin}: {e.strerror or e}") from None
    folder = Path(path).resolve().parent
    for name in TLS_FILES:
        key = f"transport/link/tls/{name}"
        value = json.loads(conf.get_json(key))
        if not isinstance(value, str) or not value:
            continue
        file = Path(value).expanduser()
        if not file.is_absolute():
            file = folder / file
            _set(conf, key, str(file))
        if not file.is_file():
            raise ZenohConfigError(f"{origin}: {key}: no such file {str(file)!r}")
        try:
            pem = b"-----BEGIN " in file.read_bytes()
        except OSError as e:
            raise ZenohConfigError(f"{origin}: {key}: cannot read {str(file)!r}: {e.strerror}") from None
        if not pem:
            raise ZenohConfigError(f"{origin}: {key}: {str(file)!r} is not a PEM file")
    return conf


@functools.cache
def _zenoh_default(key: str) -> str:
    return zenoh.Config().get_json(key)


def _set(conf: zenoh.Config, key: str, value: object) -> None:
    conf.insert_json5(key, json.dumps(value))


class ZenohOpenError(ConnectionError):
    """A Zenoh session could not be opened: a bad endpoint, a port in use, an unreachable router."""


def open_session(
    listen: bool,
    endpoint: str | None = None,
    router: str | None = None,
    zenoh_config: str | os.PathLike[str] | None = None,
) -> zenoh.Session:
    """``zenoh.open(make_config(...))``, with Zenoh's refusal turned into a ``ZenohOpenError``
    naming the endpoint (and the config file, if any). A bad config file raises ``ZenohConfigError``."""
    conf = make_config(listen, endpoint, router, zenoh_config)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise open_error(e, listen, endpoint, router, zenoh_config) from None


def router_config(
    listen: Sequence[str], zenoh_config: str | os.PathLike[str] | None = None
) -> tuple[zenoh.Config, list[str]]:
    """The config of ``tidee router`` and the endpoints it will listen on (the file's, if it names them)."""
    conf = merged_config(router_defaults(listen), zenoh_config)
    endpoints = json.loads(conf.get_json("listen/endpoints"))
    return conf, endpoints if isinstance(endpoints, list) else [json.dumps(endpoints)]


def open_router(
    listen: Sequence[str], zenoh_config: str | os.PathLike[str] | None = None
) -> tuple[zenoh.Session, list[str]]:
    """A Zenoh router in this process: the session and the endpoints it listens on."""
    conf, endpoints = router_config(listen, zenoh_config)
    try:
        return zenoh.open(conf), endpoints
    except zenoh.ZError as e:
        where = f"--listen {' '.join(listen)}"
        raise ZenohOpenError(
            f"{where}{_with_file(zenoh_config)}: Zenoh could not start the router: {zenoh_error_text(e)}"
        ) from None


def open_error(
    error: Exception,
    listen: bool,
    endpoint: str | None = None,
    router: str | None = None,
    zenoh_config: str | os.PathLike[str] | None = None,
) -> ZenohOpenError:
    """One line for a failed ``zenoh.open``: which endpoint (and which flag or variable gave it),
    which config file if any, and why."""
    router = resolve_router(router)
    if router:
        where, verb = _origin(router, ROUTER_ENV, "--router", "router"), "connect to it"
        hint = " (is a Zenoh router, zenohd, running there? Without --router, tidee runs in peer mode)"
    else:
        where = _origin(endpoint, ENDPOINT_ENV, "--endpoint", "endpoint")
        verb, hint = ("listen on it" if listen else "connect to it"), ""
    with_file = _with_file(zenoh_config)
    if with_file and (router or not listen):  # the file's certificates are as likely a cause
        hint = (
            f" (is {'a router' if router else 'a tidee server'} running there, and do both ends accept "
            "each other's certificates? see deploy/secure/README.md)"
        )
    return ZenohOpenError(f"{where}{with_file}: Zenoh could not {verb}: {zenoh_error_text(error)}{hint}")


def zenoh_error_text(error: Exception) -> str:
    """Zenoh's message without its Rust source locations and debug wrappers, on one line."""
    text = re.sub(r"\s*at /\S+\.rs:\d+\.?", "", str(error))  # "... at /root/.cargo/.../tcp.rs:61."
    where = re.search(r"line: (\d+), column: (\d+)", text) or re.search(r"-->\s*(\d+):(\d+)", text)
    m = re.search(r'msg: "(.*?)"', text) or re.search(r"^\s*=\s*(.+)$", text, re.M)  # JSON, JSON5 syntax
    if m:
        text = m.group(1)
    if where:
        text = f"line {where.group(1)}, column {where.group(2)}: {text}"
    return " ".join(text.split()).rstrip(" .!")


def _origin(given: str | None, env: str, flag: str, what: str) -> str:
    """``--endpoint X``, ``TIDEE_ZENOH_ENDPOINT=X`` or ``the default endpoint X``: where a value came from."""
    if given:
        return f"{flag} {given}"
    if os.environ.get(env):
        return f"{env}={os.environ[env]}"
    return f"the default {what} {DEFAULT_ENDPOINT}"


def _file_origin(zenoh_config: str | os.PathLike[str] | None) -> str:
    """``--zenoh-config FILE`` or ``TIDEE_ZENOH_CONFIG=FILE``."""
    if zenoh_config:
        return f"--zenoh-config {os.fspath(zenoh_config)}"
    return f"{CONFIG_ENV}={os.environ.get(CONFIG_ENV, '')}"


def _with_file(zenoh_config: str | os.PathLike[str] | None) -> str:
    """`` with --zenoh-config FILE`` when a config file is in use, else empty."""
    return f" with {_file_origin(zenoh_config)}" if resolve_config_file(zenoh_config) else ""
