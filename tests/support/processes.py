"""``tidee`` commands as subprocesses for tests: start one, read its output as it comes, end it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from tests.support import REPO


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


class OutputLines:
    """Collects a process's output lines in a thread, so waiting for one never blocks on the pipe."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, deadline: float) -> str:
        """The first line holding ``text``, waiting until ``deadline`` (``time.monotonic()``)."""
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if text in line:
                    return line
            time.sleep(0.1)
        raise AssertionError(f"no line with {text!r} in time; output so far:\n" + "\n".join(self.lines))

    @property
    def text(self) -> str:
        self._thread.join(timeout=5)
        return "\n".join(self.lines)
