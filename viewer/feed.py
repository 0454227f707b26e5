"""The live telemetry feed: Zenoh subscriptions, session discovery, commands, oracle state.

Threads and Zenoh (see protocol/README.md): every subscription delivers into a Zenoh
ring channel (latest wins; a slow viewer drops frames, never lags, never stalls the
agent) and nothing runs on Zenoh's own threads. ``poll()`` drains the channels without
blocking; the viewer's update worker calls it a few times a second and decodes only the
newest message of each kind for the session on screen. Memory is bounded: ring channels
of a few samples, one pending sample per kind, at most ``MAX_SESSIONS`` known sessions.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, cast

import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.messages import (
    TELEMETRY_KINDS,
    AgentCommand,
    AgentFrame,
    AgentStatus,
    CommandAck,
    EpisodeSummary,
    ErrorReply,
    MapSnapshot,
    ObjectMemoryMsg,
    Observation,
    SearchHeatmap,
    StateReply,
    StateRequest,
    WalkthroughMemoryMsg,
)
from tidee.protocol.zenoh_config import open_session, resolve_endpoint, resolve_router

log = logging.getLogger("tidee.viewer.feed")

OBSERVATION = "observation"  # the server's raw feed, beside the agent's telemetry kinds
MESSAGE_TYPES: dict[str, type] = {
    "status": AgentStatus,
    "frame": AgentFrame,
    "maps": MapSnapshot,
    "memory": ObjectMemoryMsg,
    "walkthrough": WalkthroughMemoryMsg,
    "search": SearchHeatmap,
    "ack": CommandAck,
    "summary": EpisodeSummary,
    OBSERVATION: Observation,
}
RING_CAPACITY = 8  # per kind, all sessions together
MAX_SESSIONS = 64  # known sessions kept (the oldest gone ones are forgotten first)
LIVELINESS_INBOX = 256  # liveliness events between two polls (a ring: Zenoh never waits on us)


@dataclass
class SessionInfo:
    session: str
    server_id: str | None = None  # from liveliness or the observation key
    alive: bool = False  # a server hosts it now (liveliness token present)
    last_telemetry: float = 0.0  # monotonic time of the last agent telemetry seen
    last_seen: float = 0.0  # monotonic time of anything about it

    def describe(self) -> str:
        where = f" on {self.server_id}" if self.server_id else ""
        state = "live" if self.alive else ("telemetry" if self.last_telemetry else "gone")
        return f"{self.session}{where} ({state})"


def _telemetry_of_kind(kind: str) -> str:
    """``tidee/agent/*/telemetry/{kind}``: one kind, every session (one ring channel per kind,
    so a burst of frames cannot push the latest map out)."""
    prefix = keys.agent_telemetry_wildcard().rsplit("/", 1)[0]
    return f"{prefix}/{keys.check_id('kind', kind)}"


class LiveFeed:
    """Subscribes to every session's telemetry and observations; decodes the selected one's.

    ``session``: pin this session; None follows the most recently active session.
    """

    def __init__(
        self,
        endpoint: str | None = None,
        router: str | None = None,
        session: str | None = None,
        zenoh_config: str | None = None,
    ) -> None:
        if session is not None:
            keys.check_id("session", session)
        self.where = resolve_router(router) or resolve_endpoint(endpoint)
        self._pinned = session
        self._auto: str | None = None
        self._sessions: dict[str, SessionInfo] = {}
        self._pending: dict[str, zenoh.Sample] = {}  # newest undecoded sample per kind (selected session)
        self._lock = threading.Lock()
        self.decode_errors = 0
        self.last_error = ""
        self._z: zenoh.Session | None = open_session(False, endpoint, router, zenoh_config)
        try:
            self._subs: dict[str, Any] = {
                kind: self._z.declare_subscriber(
                    _telemetry_of_kind(kind), zenoh.handlers.RingChannel(RING_CAPACITY)
                )
                for kind in TELEMETRY_KINDS
                if kind in MESSAGE_TYPES
            }  # a kind this viewer cannot show: not heard
            self._subs[OBSERVATION] = self._z.declare_subscriber(
                keys.observations_wildcard(), zenoh.handlers.RingChannel(RING_CAPACITY)
            )
            self._alive = self._z.liveliness().declare_subscriber(
                keys.alive_sessions_wildcard(), zenoh.handlers.RingChannel(LIVELINESS_INBOX), history=True
            )
        except BaseException:
            self.close()
            raise

    # --- sessions -----------------------------------------------------------------------
    @property
    def selected(self) -> str | None:
        with self._lock:
            return self._pinned or self._auto

    @property
    def pinned(self) -> bool:
        return self._pinned is not None

    def select(self, session: str | None) -> None:
        """Show ``session`` (None: follow the most recently active one)."""
        if session is not None:
            keys.check_id("session", session)
        with self._lock:
            if session != (self._pinned or self._auto):
                self._pending.clear()
            self._pinned = session

    def sessions(self) -> list[SessionInfo]:
        """Known sessions, live ones first, most recently active first."""
        with self._lock:
            infos = [SessionInfo(**vars(s)) for s in self._sessions.values()]
        return sorted(infos, key=lambda s: (not s.alive, -max(s.last_telemetry, s.last_seen)))

    def server_of(self, session: str) -> str | None:
        with self._lock:
            info = self._sessions.get(session)
            return info.server_id if info else None

    def _touch(self, session: str, now: float, **changes: Any) -> SessionInfo:
        info = self._sessions.get(session)
        if info is None:
            info = self._sessions[session] = SessionInfo(session)
            if len(self._sessions) > MAX_SESSIONS:
                stale = min(
                    (s for s in self._sessions.values() if not s.alive and s.session != session),
                    key=lambda s: s.last_seen,
                    default=None,
                )
                if stale is not None:
                    del self._sessions[stale.session]
        info.last_seen = now
        for name, value in changes.items():
            setattr(info, name, value)
        return info

    # --- polling --------------------------------------------------------------------------
    def poll(self) -> dict[str, Any]:
        """Newest message of each kind for the selected session since the last poll (decoded).

        Never blocks. Undecodable messages are counted in ``decode_errors`` and skipped.
        """
        if self._z is None:
            return {}
        now = time.monotonic()
        self._drain_liveliness(now)
        with self._lock:
            for kind, sub in self._subs.items():
                while (sample := sub.try_recv()) is not None:
                    self._route(kind, sample, now)
            if self._pinned is None:
                self._auto = self._most_active()
            selected = self._pinned or self._auto
            pending, self._pending = self._pending, {}
        out: dict[str, Any] = {}
        for kind, sample in pending.items():
            msg = self._decode(kind, sample)
            if msg is not None and getattr(msg, "session", selected) == selected:
                out[kind] = msg
        return out

    def _route(self, kind: str, sample: zenoh.Sample, now: float) -> None:
        key = str(sample.key_expr)
        try:
            if kind == OBSERVATION:
                server_id, session = keys.parse_observations(key)
                self._touch(session, now, server_id=server_id)
            else:
                session, _ = keys.parse_agent_telemetry(key)
                self._touch(session, now, last_telemetry=now)
        except ValueError:
            return
        selected = self._pinned or self._auto
        if selected is None:  # auto mode, nothing chosen yet: the first one heard
            self._auto = selected = session
        if session == selected:
            self._pending[kind] = sample

    def _most_active(self) -> str | None:
        """Auto mode: stay on the current session while it lives; else the newest active one."""
        current = self._sessions.get(self._auto) if self._auto else None
        if current is not None and (current.alive or time.monotonic() - current.last_telemetry < 10.0):
            return self._auto
        best = max(
            self._sessions.values(), key=lambda s: (s.alive, s.last_telemetry, s.last_seen), default=None
        )
        if best is not None and best.session != self._auto:
            self._pending.clear()
            return best.session
        return self._auto

    def _drain_liveliness(self, now: float) -> None:
        while (sample := self._alive.try_recv()) is not None:
            try:
                role, server_id, session = keys.parse_alive(str(sample.key_expr))
            except ValueError:
                continue
            if role != "session" or session is None:
                continue
            alive = sample.kind != zenoh.SampleKind.DELETE
            with self._lock:
                self._touch(session, now, server_id=server_id, alive=alive)

    def _decode(self, kind: str, sample: zenoh.Sample) -> Any:
        try:
            return decode(sample.payload.to_bytes(), expected=MESSAGE_TYPES[kind])
        except ProtocolError as e:
            self.decode_errors += 1
            self.last_error = f"{kind} on {sample.key_expr}: {e}"
            if self.decode_errors in (1, 10, 100) or self.decode_errors % 1000 == 0:
                log.warning("undecodable telemetry (%d so far): %s", self.decode_errors, self.last_error)
            return None

    # --- commands and oracle --------------------------------------------------------------
    def send(self, command: AgentCommand, session: str | None = None) -> str:
        """Put ``command`` on the agent's command key of ``session`` (default: the selected one);
        returns the session it went to."""
        target = session or self.selected
        if target is None:
            raise RuntimeError("no session to command yet: no agent telemetry or live session seen")
        if self._z is None:
            raise RuntimeError("the feed is closed")
        self._z.put(keys.agent_cmd(target), encode(command), congestion_control=zenoh.CongestionControl.BLOCK)
        return target

    def fetch_state(self, session: str, timeout: float = 2.0) -> dict[str, Any]:
        """The server's privileged scene state of ``session`` (the oracle layer). Raises
        ``LookupError`` when no server is known for it, ``TimeoutError`` with no reply."""
        server_id = self.server_of(session)
        if server_id is None:
            raise LookupError(
                f"no server known for session {session!r} (no liveliness token or observation seen)"
            )
        if self._z is None:
            raise RuntimeError("the feed is closed")
        replies = self._z.get(
            keys.sim_op(server_id, session, "state"), payload=encode(StateRequest(session)), timeout=timeout
        )
        for reply in replies:
            if reply.ok is not None:
                return decode(reply.ok.payload.to_bytes(), expected=StateReply).scene
            # A zenoh reply holds exactly one of ok and err; its stubs type each as optional.
            payload = cast("zenoh.ReplyError", reply.err).payload.to_bytes()
            try:
                err = decode(payload, expected=ErrorReply)
                raise RuntimeError(
                    f"server {server_id!r} refused the state of {session!r}: {err.code.value}: {err.message}"
                )
            except ProtocolError:
                raise TimeoutError(
                    f"no state from server {server_id!r} for {session!r}: {payload[:80]!r}"
                ) from None
        raise TimeoutError(f"no reply from server {server_id!r} to a state request for {session!r}")

    def close(self) -> None:
        z, self._z = self._z, None
        if z is None:
            return
        for sub in list(getattr(self, "_subs", {}).values()) + [getattr(self, "_alive", None)]:
            if sub is not None:
                try:
                    sub.undeclare()
                except Exception:
                    pass
        z.close()
