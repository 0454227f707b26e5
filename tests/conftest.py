"""Fixtures shared across the test tree (helpers without fixtures are in tests/support/)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from tests.support.net import start_server, wait_until
from tidee.protocol import keys
from tidee.protocol.zenoh_config import make_config
from tidee.server.service import SimServer


@pytest.fixture
def server() -> Iterator[SimServer]:
    srv = start_server(max_sessions=3)
    yield srv
    srv.stop()


@pytest.fixture
def raw_zenoh(server: SimServer) -> Iterator[zenoh.Session]:
    """A bare Zenoh session on the server's network, for hand-made requests and viewers."""
    z = zenoh.open(make_config(False, server.config.endpoint))
    server_token = keys.alive_server(server.config.server_id)
    assert wait_until(lambda: any(r.ok is not None for r in z.liveliness().get(server_token, timeout=1.0)))
    yield z
    z.close()


@pytest.fixture
def scene_view() -> Iterator[object]:
    """The viewer's 3D scene on a viser server bound to an ephemeral loopback port."""
    import viser

    from tidee.viewer.scene_view import SceneView

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        yield SceneView(server)
    finally:
        server.stop()
