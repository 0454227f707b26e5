"""Python client of a tidee simulation server over Zenoh: one client, one session."""

from __future__ import annotations

import functools
import itertools
import threading
import time
import uuid
from collections.abc import Callable, Collection
from typing import Any, cast

import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.discovery import ask_servers, describe, rank_servers
from tidee.protocol.messages import (
    IMAGE_ENCODINGS,
    Action,
    CloseReply,
    CloseRequest,
    EpisodeSpec,
    ErrorCode,
    ErrorReply,
    Observation,
    PhaseRequest,
    ResetRequest,
    StateReply,
    StateRequest,
    StepRequest,
)
from tidee.protocol.zenoh_config import open_session, resolve_config_file, resolve_endpoint, resolve_router

DEFAULT_SERVER_ID = "sim0"
_ZENOH_TIMEOUT = b"Timeout"  # what Zenoh itself answers when a query's time runs out


class RemoteError(RuntimeError):
    """The server refused a request: ``code`` says why, ``message`` says what was wrong."""

    def __init__(self, code: ErrorCode, message: str, session: str | None = None) -> None:
        super().__init__(f"{ErrorCode(code).value}: {message}")
        self.code = ErrorCode(code)
        self.message = message
        self.session = session


class SimClient:
    """One episode session on a tidee server: ``reset``, ``step``, ``state``, ``close``.

    Declares ``tidee/alive/client/{server_id}/{session}``, so the server frees the
    session when this client closes, its Zenoh session closes, or its process dies.
    The constructor waits (up to ``connect_timeout`` s) until the server is visible.
    ``server_id="auto"`` names no server: the constructor waits for a live server with a free
    session and takes the best one (``tidee.protocol.discovery``: fewest sessions for its
    capacity); ``server_id`` is then the chosen server's. A reset that server refuses as full
    (``server_busy``) moves the client to the next one; ``choose_server`` moves it on demand
    (after its server went away). A session id another client holds is refused by name
    (``RemoteError``, ``invalid_field``) wherever it is held.
    ``zenoh_config``: a Zenoh config file merged over tidee's defaults (TLS, access control;
    see ``tidee.protocol.zenoh_config``); default ``TIDEE_ZENOH_CONFIG``, else none. With one,
    a request the visible server never answers raises ``PermissionError`` (a router's access
    control drops what a client's certificate may not send) instead of ``TimeoutError``.
    Observations' raw arrays are read-only views of the received frame; copy to modify.
    ``depth`` is float32 metres whatever the wire carried: exact from a default server, 1 mm
    precision from one started with ``TIDEE_WIRE_DEPTH=mm`` (protocol/README.md).
    Not thread-safe: one caller at a time (the server handles a session's requests in order).
    """

    def __init__(
        self,
        endpoint: str | None = None,
        router: str | None = None,
        server_id: str = DEFAULT_SERVER_ID,
        session: str | None = None,
        timeout: float = 60.0,
        encoding: str = "raw",
        zsession: zenoh.Session | None = None,
        connect_timeout: float = 10.0,
        zenoh_config: str | None = None,
    ) -> None:
        if encoding not in IMAGE_ENCODINGS:
            raise ValueError(f"encoding must be one of {IMAGE_ENCODINGS}, got {encoding!r}")
        self.auto = server_id == keys.AUTO_SERVER
        self.server_id = server_id if self.auto else keys.check_id("server_id", server_id)
        self.session_id = keys.check_id("session", session or uuid.uuid4().hex[:16])
        self.timeout, self.encoding = timeout, encoding
        self._sequence = itertools.count()
        self._router = resolve_router(router)
        self._where = self._router or resolve_endpoint(endpoint)
        self._owns_zenoh = zsession is None
        self._zenoh_config = resolve_config_file(zenoh_config)
        self._z: zenoh.Session | None = zsession or open_session(False, endpoint, router, zenoh_config)
        self._token: Any = None
        try:
            if self.auto:
                self.choose_server(connect_timeout)
            else:
                self._declare_token()
                self._wait_for_server(connect_timeout)
        except BaseException:
            self._release()
            raise

    # --- the session ----------------------------------------------------------------
    def reset(self, spec: EpisodeSpec, ground_truth: bool = False) -> Observation:
        request = ResetRequest(self.session_id, spec, ground_truth, self.encoding)
        refused: dict[str, str] = {}  # server id -> why it refused (auto: each full server in turn)
        while True:
            try:
                return self._call("reset", request, Observation)
            except RemoteError as e:
                if not self.auto or e.code != ErrorCode.server_busy:
                    raise
                refused[self.server_id] = e.message
            infos = ask_servers(self._live(), self.session_id)
            untried = [
                i.server_id for i in rank_servers(infos, self.session_id) if i.server_id not in refused
            ]
            if not untried:
                why = "; ".join(f"{server}: {message}" for server, message in refused.items())
                others = [i for i in infos if i.server_id not in refused]
                why += f"; the others are full: {describe(others)}" if others else ""
                raise RemoteError(
                    ErrorCode.server_busy,
                    f"no live server took session {self.session_id!r}: {why}",
                    self.session_id,
                )
            self._move_to(untried[0])

    def step(self, action: Action, ground_truth: bool = False) -> Observation:
        return self.send_step(action, ground_truth)()

    def send_step(self, action: Action, ground_truth: bool = False) -> Callable[[], Observation]:
        """Send a step now; the returned function waits for its observation (the agent does
        other work, its telemetry, while the server acts)."""
        request = StepRequest(self.session_id, action, ground_truth, self.encoding)
        return self._send("step", request, Observation)

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation:
        """A rearrangement (reset with ``spec.rearrange_index``): end the walkthrough and start
        the unshuffle phase; the reply is its first observation."""
        return self._call(
            "phase", PhaseRequest(self.session_id, "unshuffle", ground_truth, self.encoding), Observation
        )

    def state(self) -> dict[str, Any]:
        return self._call("state", StateRequest(self.session_id), StateReply).scene

    def close(self) -> None:
        """Ask the server to free the session, then leave Zenoh. Idempotent."""
        if self._z is None:
            return
        try:
            self._call("close", CloseRequest(self.session_id), CloseReply, timeout=min(self.timeout, 5.0))
        except (RemoteError, TimeoutError, PermissionError):
            pass  # the token going away frees the session anyway
        finally:
            self._release()

    def __enter__(self) -> SimClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- plumbing ---------------------------------------------------------------------
    def _call(self, op: str, request: Any, reply_type: type, timeout: float | None = None) -> Any:
        return self._send(op, request, reply_type, timeout)()

    def _send(
        self, op: str, request: Any, reply_type: type, timeout: float | None = None
    ) -> Callable[[], Any]:
        """Send ``request``; returns the function that waits for (and decodes) its reply."""
        if self._z is None:
            raise RuntimeError(f"session {self.session_id} is closed")
        key = keys.sim_op(self.server_id, self.session_id, op)
        timeout = self.timeout if timeout is None else timeout
        # source_info names this Zenoh session: the server's per-client quota counts by it.
        replies = self._z.get(
            key,
            payload=encode(request),
            timeout=timeout,
            congestion_control=zenoh.CongestionControl.BLOCK,  # the reply inherits it
            source_info=zenoh.SourceInfo(self._z.id, next(self._sequence)),
        )
        return functools.partial(self._receive, replies, op, key, reply_type, timeout)

    def _receive(self, replies: Any, op: str, key: str, reply_type: type, timeout: float) -> Any:
        try:
            reply = replies.recv()
        except zenoh.ZError:  # the query finished with no reply: nobody serves that key
            if self._server_visible():
                if self._zenoh_config:  # the server is there: the router's access control refused op
                    raise PermissionError(
                        f"no reply to {op} on {key}: server {self.server_id!r} is up but nothing answered: "
                        f"the Zenoh router's access control may refuse {op} to this client's certificate "
                        f"({self._zenoh_config})"
                    ) from None
                raise TimeoutError(
                    f"no reply to {op} on {key}: is server {self.server_id!r} running at {self._where}?"
                ) from None
            raise TimeoutError(
                f"no reply to {op} on {key}: server {self.server_id!r} at {self._where} went away "
                f"(its liveliness token is gone)"
            ) from None
        if reply.ok is not None:  # to_bytes: the one copy (ZBytes has no buffer protocol); decode adds none
            return self._decode(reply.ok.payload.to_bytes(), (reply_type, ErrorReply), op)
        # A zenoh reply holds exactly one of ok and err; its stubs type each as optional.
        payload = cast("zenoh.ReplyError", reply.err).payload.to_bytes()
        if payload == _ZENOH_TIMEOUT:
            raise TimeoutError(f"no reply to {op} on {key} within {timeout} s")
        return self._decode(payload, ErrorReply, op)

    def _decode(self, payload: bytes, expected: type | tuple[type, ...], op: str) -> Any:
        try:
            msg = decode(payload, expected=expected)
        except ProtocolError as e:
            raise RemoteError(e.code, f"undecodable reply to {op}: {e.message}", self.session_id) from None
        if isinstance(msg, ErrorReply):
            raise RemoteError(msg.code, msg.message, msg.session)
        return msg

    def choose_server(self, timeout: float, avoid: Collection[str] = ()) -> str:
        """(``server_id="auto"``) Move this client to the best live server that has a free session
        (``tidee.protocol.discovery``), waiting up to ``timeout`` s for one; returns its id.

        ``avoid``: servers to take only when no other has room (one that stopped answering).
        A session held on the server left behind is freed there (its client token goes).
        Raises TimeoutError naming what it saw when no live server has room in time.
        """
        if not self.auto:
            raise RuntimeError(
                f"this client uses server {self.server_id!r}; choose_server needs server_id='auto'"
            )
        z = self._live()
        deadline = time.monotonic() + timeout
        while True:
            infos = ask_servers(z, self.session_id, timeout=max(0.1, min(2.0, deadline - time.monotonic())))
            ranked = rank_servers(infos, self.session_id, avoid)
            if ranked:
                self._move_to(ranked[0].server_id)
                return self.server_id
            left = deadline - time.monotonic()
            if left <= 0:
                break
            time.sleep(min(0.25, left))
        if infos:
            raise TimeoutError(
                f"no live tidee server at {self._where} had a free session within {timeout:g} s: "
                f"{describe(infos)}"
            )
        raise TimeoutError(
            f"no live tidee server at {self._where} within {timeout:g} s "
            f"(start one with: tidee server {self._flag()} {self._where})"
        )

    def wait_for_server(self, timeout: float) -> None:
        """Block until the server's liveliness token is visible (e.g. after a restart).

        Raises TimeoutError when it does not appear within ``timeout`` s.
        """
        if self._z is None:
            raise RuntimeError(f"session {self.session_id} is closed")
        self._wait_for_server(timeout)

    def _wait_for_server(self, timeout: float) -> None:
        assert self._z is not None
        seen = threading.Event()
        sub = self._z.liveliness().declare_subscriber(
            keys.alive_server(self.server_id), lambda sample: seen.set(), history=True
        )
        try:
            if not seen.wait(timeout):
                raise TimeoutError(
                    f"no tidee server {self.server_id!r} at {self._where} within {timeout:g} s "
                    f"(start one with: tidee server {self._flag()} {self._where})"
                )
        finally:
            sub.undeclare()

    def _flag(self) -> str:
        return "--router" if self._where == self._router else "--endpoint"

    def _live(self) -> zenoh.Session:
        if self._z is None:
            raise RuntimeError(f"session {self.session_id} is closed")
        return self._z

    def _declare_token(self) -> None:
        self._token = (
            self._live().liveliness().declare_token(keys.alive_client(self.server_id, self.session_id))
        )

    def _move_to(self, server_id: str) -> None:
        """Use ``server_id`` from now on: the client token moves with it."""
        if server_id == self.server_id and self._token is not None:
            return
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self.server_id = server_id
        self._declare_token()

    def _server_visible(self, timeout: float = 1.0) -> bool:
        """Whether the server's liveliness token is there now (asked once, at most ``timeout`` s)."""
        assert self._z is not None
        replies = self._z.liveliness().get(keys.alive_server(self.server_id), timeout=timeout)
        return any(reply.ok is not None for reply in replies)

    def _release(self) -> None:
        z, self._z = self._z, None
        if z is None:
            return
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self._owns_zenoh:
            z.close()
