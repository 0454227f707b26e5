"""``tidee`` commands as subprocesses for tests: start one, read its output as it comes, end it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from tests.support import REPO
from tidee.launch import OutputLines

__all__ = ["OutputLines", "kill_group", "start_tidee"]


def start_tidee(*args: str, output: bool = True, **kw: object) -> subprocess.Popen:
    """``tidee ARGS`` in its own process group (so a kill reaches its children); ``output``: its
    stdout and stderr as one text pipe (read it with :class:`OutputLines`), else discarded."""
    pipes = (
        {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT}
        if output
        else {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    )
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **kw.pop("env", {})}  # type: ignore[dict-item]
    return subprocess.Popen(  # type: ignore[call-overload]
        [sys.executable, "-m", "tidee.cli", *args],
        cwd=REPO,
        text=True,
        start_new_session=True,
        env=env,
        **pipes,
        **kw,
    )


def kill_group(proc: subprocess.Popen, sig: int = signal.SIGKILL, grace: float = 30.0) -> None:
    """Send ``sig`` to the process and its children (no goodbye with SIGKILL) and reap it; a
    process still there after ``grace`` seconds is killed."""
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
