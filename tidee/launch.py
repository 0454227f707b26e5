"""``tidee run``: server, agent and viewer as separate processes on embedded Zenoh.

The server listens on a free loopback port (the rendezvous endpoint); the agent and the
viewer connect to it. Prints the viewer's URL, waits for the agent's episodes to end,
keeps everything up for ``linger`` seconds so a person can look around, then stops the
processes in reverse order. Nothing here imports torch or pybullet.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (a wildcard host is probed on loopback)."""
    with socket.socket() as s:
        s.bind((host if host not in ("0.0.0.0", "") else "127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class RunConfig:
    agent_args: list[str] = field(default_factory=list)   # passed through to `tidee agent`
    viewer: bool = True
    host: str = "127.0.0.1"
    port: int = 8080
    linger: float = 30.0
    renderer: str = "tiny"              # = agent.perception.TRAINED_RENDERER (the viewer imports this module,
                                         # never the agent): what the shipped detector was trained on
    endpoint: str | None = None


def wait_for_signal() -> None:
    """Block until SIGINT or SIGTERM (a service's main thread), then restore the handlers."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop.wait(0.2):   # a bounded wait: the handler runs within 0.2 s of any signal
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _tidee(*args: str) -> list[str]:
    return [sys.executable, "-m", "tidee.cli", *args]


def _interrupt_on_sigterm() -> Callable[[], None]:
    """Make SIGTERM (``kill``) end this process like Ctrl-C; returns a function that undoes it."""
    def _raise(*_: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _raise)
    return lambda: signal.signal(signal.SIGTERM, previous)


def stop_children(procs: list[tuple[str, subprocess.Popen]], grace: float = 15.0) -> None:
    """SIGINT every child still running (in reverse start order), wait, then SIGTERM / SIGKILL stragglers."""
    for _, p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace
    for _, p in reversed(procs):
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.terminate()
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run_all(cfg: RunConfig) -> int:
    endpoint = cfg.endpoint or f"tcp/127.0.0.1:{free_port()}"
    procs: list[tuple[str, subprocess.Popen]] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    restore = _interrupt_on_sigterm()
    try:
        procs.append(("server", subprocess.Popen(_tidee("server", "--endpoint", endpoint, "--renderer", cfg.renderer),
                                                 env=env)))
        print(f"run: server on {endpoint}", flush=True)
        if cfg.viewer:
            procs.append(("viewer", subprocess.Popen(_tidee("viewer", "--endpoint", endpoint, "--host", cfg.host,
                                                            "--port", str(cfg.port)), env=env)))
            print(f"run: viewer at http://{cfg.host}:{cfg.port}  (open it in a browser)", flush=True)
        agent = subprocess.Popen(_tidee("agent", "--endpoint", endpoint, *cfg.agent_args), env=env)
        procs.append(("agent", agent))
        rc = agent.wait()
        print(f"run: agent finished (exit {rc})", flush=True)
        if cfg.viewer and cfg.linger > 0:
            print(f"run: keeping the viewer up for {cfg.linger:.0f} s (Ctrl-C to stop now)", flush=True)
            time.sleep(cfg.linger)
        return rc
    except KeyboardInterrupt:
        print("run: interrupted; stopping the agent, viewer and server", flush=True)
        return 130
    finally:
        # A second Ctrl-C while the children stop must not leave them behind.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            stop_children(procs)
        finally:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            restore()
