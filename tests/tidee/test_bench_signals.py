"""The signals benchmark's pieces: it sees a process session's members and a server's ports, and one
SIGTERM in its start-up ends a ``tidee server`` with nothing left behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tidee.bench_signals import end_try, listening, server_try, session_processes
from tidee.launch import SignalsBenchConfig, free_port


def test_a_session_is_found_by_its_id_and_an_ignored_sigterm_leaves_an_orphan() -> None:
    code = "import signal, subprocess, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
    code += "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); time.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", code], start_new_session=True)
    try:
        deadline = time.monotonic() + 20
        while len(session_processes(proc.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(session_processes(proc.pid)) == 2 and os.getpid() not in session_processes(proc.pid)
        result = end_try(proc, signal.SIGTERM, exit_timeout=1.0)
        assert result["exit_code"] is None and len(result["orphans"]) == 2  # both counted...
        assert session_processes(proc.pid) == {}  # ...then cleared
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_listening_tells_an_open_port_from_a_closed_one() -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        assert listening(s.getsockname()[1])
    assert not listening(free_port())


def test_one_sigterm_in_its_start_up_ends_tidee_server_with_nothing_left() -> None:
    """Before its handler is in place the default action ends it; its simulators are not started yet.
    (A SIGTERM while it serves: tests/server/test_workers.py.)"""
    pytest.importorskip("pybullet")
    result = server_try(SignalsBenchConfig(resolution=32), delay=0.5, serving=False)
    assert result["ok"], result
    assert result["exit_code"] in (0, -signal.SIGTERM), result
