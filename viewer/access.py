"""Who may send commands to agents from the viewer: read-only mode and the access token.

A viewer served beyond loopback needs a credential for its controls (pause / resume /
step, new episode, placement preference): it makes a random token (or takes ``--token``)
and prints it with the URL. viser 1.x gives the app no way to read a client's URL: its
browser client opens the websocket at the page's address with the query string cut off,
and the HTTP handshake is not exposed per client. So the gate is a GUI text input,
"Access token", created for each client on its own (a client-scoped widget, so what one
browser types is never sent to the others); the right value unlocks that client's
controls until it disconnects. A command from a client that has not presented the token
is refused, and that client is told so.

``read_only`` goes further: no command controls are built and every command is refused.
"""

from __future__ import annotations

import ipaddress
import secrets
import threading

LOOPBACK_NAMES = ("localhost",)


def is_loopback(host: str) -> bool:
    """127.0.0.0/8, ::1 and ``localhost``; ``0.0.0.0``, ``""`` and other names are not."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def required_token(host: str, token: str | None) -> str | None:
    """The token the controls need: ``token`` when given; a fresh random one when ``host``
    is not loopback; otherwise None (loopback: no token needed)."""
    if token is not None:
        return token
    return None if is_loopback(host) else secrets.token_urlsafe(16)


def announce(url: str, token: str | None, read_only: bool) -> str:
    """The line ``tidee viewer`` prints: the URL, and what the controls need."""
    if read_only:
        return f"viewer: {url} (read-only: no agent controls)"
    if token is None:
        return f"viewer: {url}"
    return (
        f"viewer: {url} (the agent controls need the access token {token}: "
        f"paste it into 'Access token' on the page)"
    )


class AccessGate:
    """Which clients may send commands. Thread-safe (viser calls back on its thread pool)."""

    def __init__(self, token: str | None, read_only: bool = False) -> None:
        self.token, self.read_only = token, read_only
        self._lock = threading.Lock()
        self._unlocked: set[int] = set()

    @property
    def needs_token(self) -> bool:
        return self.token is not None and not self.read_only

    def unlock(self, client_id: int, presented: str) -> bool:
        """Record whether ``client_id`` presented the right token; True when it did."""
        expected = self.token
        ok = expected is not None and secrets.compare_digest(presented.strip().encode(), expected.encode())
        with self._lock:
            if ok:
                self._unlocked.add(client_id)
            else:
                self._unlocked.discard(client_id)
        return ok

    def forget(self, client_id: int) -> None:
        with self._lock:
            self._unlocked.discard(client_id)

    def refusal(self, client_id: int | None) -> str | None:
        """Why a command from ``client_id`` is refused, or None when it may go."""
        if self.read_only:
            return "this viewer is read-only (started with --read-only)"
        if self.token is None:
            return None
        with self._lock:
            if client_id is not None and client_id in self._unlocked:
                return None
        return "enter the access token (printed where the viewer started) under 'Access token' first"
