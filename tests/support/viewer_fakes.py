"""Telemetry sources for the viewer's tests: a synthetic agent on a private loopback endpoint.

``synthetic_source()`` is the one place the viewer tests get their telemetry from; to
run them against the real system, give it a twin that starts ``tidee server`` and
``tidee agent`` on the same endpoint and yields the same ``TelemetrySource``.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from tests.support.net import free_endpoint
from tidee.viewer.synthetic import SyntheticAgent


@dataclass
class TelemetrySource:
    endpoint: str  # the peer-mode rendezvous the viewer connects to
    session: str  # the session publishing telemetry
    server_id: str
    agent: SyntheticAgent | None  # the synthetic publisher (None for a real agent)


@contextmanager
def synthetic_source(rate_hz: float = 20.0, resolution: int = 128) -> Iterator[TelemetrySource]:
    """A ``SyntheticAgent`` listening on a fresh loopback endpoint (it is the rendezvous,
    as a server would be), declaring its session's liveliness like a server."""
    endpoint = free_endpoint()
    session, server_id = f"e2e{uuid.uuid4().hex[:8]}", f"t{uuid.uuid4().hex[:6]}"
    agent = SyntheticAgent(
        session=session,
        server_id=server_id,
        endpoint=endpoint,
        listen=True,
        rate_hz=rate_hz,
        resolution=resolution,
    ).start()
    try:
        yield TelemetrySource(endpoint, session, server_id, agent)
    finally:
        agent.close()
