"""Validators for option values (``option(type=...)``): a bad value is refused while parsing, in one line.

argparse prefixes each message with the flag (``argument --port: ...``), so a message here
says what was wrong and what would be right, without repeating the flag. Nothing here
binds, connects or creates anything.
"""

from __future__ import annotations

import ipaddress
import os
import re
import socket
from collections.abc import Callable

# EpisodeSpec's resolution range (protocol/messages.py): square images this many pixels a side.
MIN_RESOLUTION, MAX_RESOLUTION = 16, 1024
MAX_STEPS = 100_000  # EpisodeSpec.max_steps, at most

# Zenoh locators this project uses: PROTOCOL/HOST:PORT (HOST a name, IPv4 or [IPv6]).
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock", "serial")
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.%a-zA-Z]+\]|[A-Za-z0-9._-]+):(?P<port>[0-9]+)$")


def int_range(lo: int | None, hi: int | None, what: str = "an integer") -> Callable[[str], int]:
    """An integer in [lo, hi] (either bound may be open)."""
    if lo is not None and hi is not None:
        want = f"{what} in {lo}-{hi}"
    elif lo is not None:
        want = f"{what} >= {lo}"
    else:
        want = f"{what} <= {hi}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise ValueError(f"expected {want}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ValueError(f"expected {want}, got {value}")
        return value

    parse.__name__ = what.replace(" ", "_")
    return parse


positive_int = int_range(1, None)
non_negative_int = int_range(0, None)
port = int_range(1, 65535, "a TCP port")
port_or_any = int_range(0, 65535, "a TCP port (0: any free port)")
resolution = int_range(MIN_RESOLUTION, MAX_RESOLUTION, "an image side in pixels")
max_steps = int_range(1, MAX_STEPS)


def non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"expected a number >= 0, got {text!r}") from None
    if not value >= 0:  # also refuses nan
        raise ValueError(f"expected a number >= 0, got {text}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"expected a number > 0, got {text!r}") from None
    if not 0 < value < float("inf"):  # also refuses nan
        raise ValueError(f"expected a finite number > 0, got {text}")
    return value


def host(text: str) -> str:
    """An address to serve on: an IP address or a name this machine resolves (no binding here)."""
    try:
        ipaddress.ip_address(text)
        return text
    except ValueError:
        pass
    if re.fullmatch(r"[0-9.]+", text):  # looks like IPv4 but is not one (e.g. 256.1.1.1): no DNS lookup
        raise ValueError(f"{text!r} is not an IPv4 address (four numbers 0-255, e.g. 127.0.0.1)")
    try:
        socket.getaddrinfo(text, None)
    except (socket.gaierror, UnicodeError) as e:
        raise ValueError(
            f"{text!r} is not an IP address or a host name this machine resolves "
            f"({getattr(e, 'strerror', None) or e}); e.g. 127.0.0.1 or 0.0.0.0"
        ) from None
    return text


def endpoint(text: str) -> str:
    """A Zenoh endpoint: ``tcp/HOST:PORT`` (or udp, tls, quic, ws), or a unix socket
    ``unixsock-stream/PATH``."""
    proto, sep, address = text.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]  # Zenoh's ?metadata and #config suffixes
    example = "e.g. tcp/127.0.0.1:7447"
    if not sep or not address:
        raise ValueError(f"{text!r} is not a Zenoh endpoint: expected PROTOCOL/ADDRESS, {example}")
    if proto in _OTHER_PROTOCOLS:
        return text
    if proto not in _IP_PROTOCOLS:
        raise ValueError(
            f"{text!r}: unknown protocol {proto!r}; expected one of "
            f"{', '.join(_IP_PROTOCOLS + _OTHER_PROTOCOLS)}, {example}"
        )
    m = _HOST_PORT.match(address)
    if not m:
        raise ValueError(f"{text!r}: the address must be HOST:PORT, {example}")
    if not 1 <= int(m["port"]) <= 65535:
        raise ValueError(f"{text!r}: port {m['port']} is not in 1-65535, {example}")
    name = m["host"].strip("[]")
    if re.fullmatch(r"[0-9.]+", name):
        try:
            ipaddress.ip_address(name)
        except ValueError:
            raise ValueError(f"{text!r}: {name!r} is not an IPv4 address, {example}") from None
    return text


def output_path(text: str) -> str:
    """A file or directory this process could create: its nearest existing ancestor is a writable
    directory."""
    if not text:
        raise ValueError("expected a path, got an empty string")
    path = os.path.abspath(text)
    if os.path.exists(path):
        return text
    parent = os.path.dirname(path)
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise ValueError(f"cannot create {text!r}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"cannot create {text!r}: directory {parent} is not writable")
    return text
