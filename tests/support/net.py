"""Helpers for tests that talk to a server over loopback Zenoh: endpoints, a server with fake
episodes, clients and hand-made requests. Fixtures built on them live in tests/conftest.py."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from typing import Any

import zenoh

from tests.support import REPO
from tests.support.fakes import FakeEpisode
from tidee.launch import free_port
from tidee.protocol.client import SimClient
from tidee.protocol.codec import decode
from tidee.protocol.messages import EpisodeSpec
from tidee.server.service import ServerConfig, SimServer

SPEC = EpisodeSpec(resolution=32, max_steps=50)


def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def start_server(factory: Callable[[], Any] | None = FakeEpisode, **config: Any) -> SimServer:
    cfg = ServerConfig(endpoint=free_endpoint(), server_id=f"t{uuid.uuid4().hex[:8]}", **config)
    return SimServer(cfg, factory).start()


def client(server: SimServer, **kwargs: Any) -> SimClient:
    return SimClient(
        endpoint=server.config.endpoint, server_id=server.config.server_id, timeout=10.0, **kwargs
    )


def raw_request(z: zenoh.Session, key: str, payload: bytes) -> Any:
    """Send ``payload`` to ``key``; the decoded reply (ok or err)."""
    reply = z.get(key, payload=payload, timeout=10.0).recv()
    sample = reply.ok if reply.ok is not None else reply.err
    return decode(sample.payload.to_bytes())


__all__ = ["REPO", "SPEC", "client", "free_endpoint", "raw_request", "start_server", "wait_until"]
