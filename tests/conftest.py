"""Fixtures shared across the test tree (helpers without fixtures are in tests/support/)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator

import pytest
import zenoh

from tests.support.net import start_server, wait_until
from tidee.protocol import keys
from tidee.protocol.zenoh_config import make_config
from tidee.server.service import SimServer

_EXIT_STATUS: list[int] = []


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _EXIT_STATUS.append(int(exitstatus))


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    """End the test process once pytest is done, without the interpreter's finalization. A
    native thread (Zenoh's runtime and others) that calls into Python while the interpreter
    finalizes is ended by CPython with a forced unwind, which native frames can swallow: the
    process then aborts ("FATAL: exception not rethrown") after every test has passed, and the
    command fails. Output is flushed first; the exit status is pytest's."""
    if _EXIT_STATUS:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])


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
