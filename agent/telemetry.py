"""Telemetry for viewers: rate-limited, latest-wins, never blocking the agent's loop.

The agent hands messages to ``TelemetryPublisher.offer(kind, build)``: ``build`` is
called (in the agent's thread, cheap) only when that kind is due under its rate limit;
the message goes into a one-slot mailbox per kind, and a worker thread encodes and puts
whatever is newest. A slow network or viewer therefore drops frames, never slows the
agent. Commands from viewers arrive on a FIFO channel the runner polls each step.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from tidee.protocol import codec, keys
from tidee.protocol.codec import ProtocolError
from tidee.protocol.messages import AgentCommand, CommandAck

log = logging.getLogger("tidee.agent.telemetry")

# Maximum publish rate per kind (Hz). ``status`` is tiny and goes every step. A rearrangement's
# ``walkthrough`` memory goes once when the walkthrough ends, then this often for late viewers.
DEFAULT_RATES = {
    "status": 1000.0,
    "frame": 10.0,
    "maps": 4.0,
    "memory": 5.0,
    "walkthrough": 0.2,
    "search": 2.0,
    "ack": 1000.0,
    "summary": 1000.0,
}


class RateLimiter:
    def __init__(
        self, rates: dict[str, float] | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.rates = dict(DEFAULT_RATES if rates is None else rates)
        self.clock = clock
        self._last: dict[str, float] = {}

    def due(self, kind: str) -> bool:
        """True at most ``rate`` times a second on average (the schedule does not drift)."""
        now = self.clock()
        period = 1.0 / self.rates.get(kind, 5.0)
        last = self._last.get(kind)
        if last is None or now >= last + period:
            # Keep to the schedule, but never bank more than one period of credit.
            self._last[kind] = now if last is None else max(last + period, now - period)
            return True
        return False


class TelemetryPublisher:
    """Publishes telemetry for one session over a Zenoh session (which it does not own)."""

    def __init__(
        self, zsession: Any, session_id: str, rates: dict[str, float] | None = None, encoding: str = "jpeg"
    ) -> None:
        import zenoh

        self.session_id = keys.check_id("session", session_id)
        self.limiter = RateLimiter(rates)
        self.encoding = encoding
        self._z = zsession
        self._pubs = {
            k: zsession.declare_publisher(
                keys.agent_telemetry(session_id, k), congestion_control=zenoh.CongestionControl.DROP
            )
            for k in DEFAULT_RATES
        }
        self._slots: dict[str, Any] = {}
        self._cv = threading.Condition()
        self._stop = False
        self.sent = 0
        self.dropped = 0
        self._worker = threading.Thread(target=self._run, name="telemetry", daemon=True)
        self._worker.start()
        self._cmd_sub = zsession.declare_subscriber(
            keys.agent_cmd(session_id), zenoh.handlers.FifoChannel(64)
        )

    def offer(self, kind: str, build: Callable[[], Any], force: bool = False) -> Any | None:
        """Build and queue a message of ``kind`` if it is due (or ``force``); returns it or None."""
        if not (force or self.limiter.due(kind)):
            return None
        msg = build()
        with self._cv:
            if kind in self._slots:
                self.dropped += 1
            self._slots[kind] = msg
            self._cv.notify()
        return msg

    def ack(self, command_id: str, kind: str, ok: bool, message: str) -> None:
        """Answer a viewer's command (always sent, whatever the rate limits)."""
        self.offer("ack", lambda: CommandAck(self.session_id, command_id, kind, ok, message), force=True)

    def commands(self) -> list[AgentCommand | str]:
        """Commands received since the last call; a malformed one comes back as an error string."""
        out: list[AgentCommand | str] = []
        while True:
            sample = self._cmd_sub.try_recv()
            if sample is None:
                return out
            try:
                out.append(codec.decode(bytes(sample.payload.to_bytes()), expected=AgentCommand))
            except ProtocolError as e:
                out.append(f"rejected a malformed command: {e}")

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._slots and not self._stop:
                    self._cv.wait(0.5)
                if self._stop and not self._slots:
                    return
                slots, self._slots = self._slots, {}
            for kind, msg in slots.items():
                try:
                    self._pubs[kind].put(codec.encode(msg, self.encoding))
                    self.sent += 1
                except Exception as e:  # noqa: BLE001 - a failed put must never kill the agent
                    log.warning("telemetry %s not sent: %s", kind, e)

    def close(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._worker.join(timeout=2.0)
        for p in self._pubs.values():
            p.undeclare()
        self._cmd_sub.undeclare()
