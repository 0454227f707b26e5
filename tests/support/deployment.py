"""The compose files as the deployment tests run them: each service's command, on loopback.

``docker compose`` runs a service's ``command`` after interpolating ``${NAME:-default}`` from the
environment. The tests run that same argv, changed in one way only (:func:`loopback_argv`), so
that it runs on this machine's loopback instead of a compose network:

* ``${NAME:-default}``: the test's value for NAME when it gives one, else the default (as compose);
* an address: ``0.0.0.0`` (listen on every interface) becomes ``127.0.0.1``, and a compose service
  name (``router``) becomes ``service_host`` (``127.0.0.1``; ``localhost`` for the secure
  deployment, whose router certificate names it), in an endpoint ``PROTO/HOST:PORT`` or after
  ``--host``;
* a port, in an endpoint or after ``--port``: the test's free loopback port standing for it;
* a container path (``/runs/...``, ``/secure/...``): the test's folder standing for its prefix.

A port or path the test gives no stand-in for is an error, so a new one in a compose file makes
the tests say so instead of running something else.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml  # PyYAML: a dev dependency (pyproject.toml), for these tests only

from tests.support import REPO

COMPOSE = REPO / "compose.yaml"
SECURE_COMPOSE = REPO / "deploy" / "secure" / "compose.yaml"
_VARIABLE = re.compile(r"\$\{(\w+)(?::-([^}]*))?\}")
_ENDPOINT = re.compile(r"^(\w+)/([^/:\[\]]+):(\d+)$")


def load_compose(path: Path = COMPOSE) -> dict[str, Any]:
    """The compose file as YAML (merge keys ``<<`` resolved)."""
    return yaml.safe_load(path.read_text())


def interpolate(text: str, env: Mapping[str, str]) -> str:
    """``${NAME:-default}`` and ``${NAME}`` as compose interpolates them, from ``env`` only."""

    def value(m: re.Match[str]) -> str:
        name, default = m.group(1), m.group(2)
        if name in env:
            return env[name]
        if default is None:
            raise KeyError(f"${{{name}}} has no default and the test gives no value")
        return default

    return _VARIABLE.sub(value, text)


def loopback_argv(
    command: list[str],
    ports: Mapping[int, int],
    paths: Mapping[str, str | Path] | None = None,
    env: Mapping[str, str] | None = None,
    service_host: str = "127.0.0.1",
) -> list[str]:
    """``command`` (a service's, from a compose file) as it runs on loopback (module docstring)."""
    out: list[str] = []
    for k, arg in enumerate(command):
        arg = interpolate(arg, env or {})
        flag = command[k - 1] if k else ""
        endpoint = _ENDPOINT.match(arg)
        if endpoint:
            proto, host, port = endpoint.groups()
            arg = f"{proto}/{_host(host, service_host)}:{_port(int(port), ports)}"
        elif flag == "--host":
            arg = _host(arg, service_host)
        elif flag == "--port":
            arg = str(_port(int(arg), ports))
        elif arg.startswith("/"):
            prefix = next((p for p in (paths or {}) if arg == p or arg.startswith(p.rstrip("/") + "/")), None)
            if prefix is None:
                raise KeyError(f"no stand-in for the container path {arg!r}")
            arg = str(paths[prefix]) + arg[len(prefix.rstrip("/")) :]  # type: ignore[index]
        out.append(arg)
    return out


def _host(host: str, service_host: str) -> str:
    if host == "0.0.0.0":
        return "127.0.0.1"
    return host if host in ("127.0.0.1", "localhost") else service_host


def _port(port: int, ports: Mapping[int, int]) -> int:
    if port not in ports:
        raise KeyError(f"no stand-in for port {port}")
    return ports[port]
