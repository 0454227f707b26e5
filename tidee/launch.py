"""``tidee run``: server, agent and viewer as separate processes on embedded Zenoh; and
``tidee router``, a Zenoh router for processes on several machines.

The server listens on a free loopback port (the rendezvous endpoint); the agent and the
viewer connect to it. Prints the viewer's URL, waits for the agent's episodes to end,
keeps everything up for ``linger`` seconds so a person can look around, then stops the
processes in reverse order. A ``--zenoh-config`` file given to ``tidee run`` goes to all
three. Nothing here imports torch or pybullet (nor Zenoh, until a command runs).
"""

from __future__ import annotations

import errno
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tidee import argtypes
from tidee.options import option
from tidee.protocol.vocab import Renderer
from tidee.server.config import RENDERER_HELP, TRAINED_RENDERER


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (a wildcard host is probed on loopback)."""
    with socket.socket() as s:
        s.bind((host if host not in ("0.0.0.0", "") else "127.0.0.1", 0))
        return int(s.getsockname()[1])


def check_bindable(host: str, port: int, what: str, hint: str = "") -> None:
    """Raise ``OSError`` naming ``what`` unless a TCP server could listen on ``host``:``port`` now.

    A probe, not a reservation: the caller binds right after. ``port`` 0 checks the host alone.
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except (socket.gaierror, UnicodeError) as e:
        raise OSError(
            f"{what}: cannot resolve host {host!r} ({getattr(e, 'strerror', None) or e}); "
            f"give an IP address of this machine, e.g. 127.0.0.1 or 0.0.0.0"
        ) from None
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers bind: TIME_WAIT is no conflict
        try:
            s.bind(address)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise OSError(
                    errno.EADDRINUSE,
                    f"{what}: port {port} on {host} is already in use by another process{hint}",
                ) from None
            raise OSError(e.errno, f"{what}: cannot listen on {host}:{port} ({e.strerror}){hint}") from None


@dataclass
class RunConfig:
    """The processes ``tidee run`` starts: a server, an agent (``agent_args``) and a viewer."""

    agent_args: list[str] = option(default_factory=list, help="passed through to `tidee agent`", cli=False)
    viewer: bool = option(True, "start the web viewer")
    viewer_read_only: bool = option(
        False, "the viewer shows the agent but has no controls that send it commands"
    )
    host: str = option("127.0.0.1", "viewer host (loopback by default)", type=argtypes.host)
    port: int = option(8080, "viewer port", type=argtypes.port)
    linger: float = option(
        30.0, "seconds to keep the viewer up after the episodes", type=argtypes.non_negative_float
    )
    renderer: Renderer = option(TRAINED_RENDERER, RENDERER_HELP)
    endpoint: str | None = option(None, "Zenoh endpoint (default: a free loopback port)", cli=False)
    zenoh_config: str | None = option(None, "Zenoh config file for the server and viewer", cli=False)


@dataclass
class SignalsBenchConfig:
    """``tidee bench signals`` (tidee/bench_signals.py)."""

    tries: int = option(
        20, "tidee run tries per signal (SIGTERM and SIGINT, in turn)", type=argtypes.non_negative_int
    )
    server_tries: int = option(
        20, "tidee server tries, one SIGTERM each", type=argtypes.non_negative_int, metavar="N"
    )
    seed: int = option(0, "draws the delay before each signal", type=argtypes.non_negative_int)
    resolution: int = option(64, "the episode's image side, pixels", type=argtypes.resolution)
    max_steps: int = option(
        300, "the episode's step budget (it must outlast the signal)", type=argtypes.max_steps
    )
    exit_timeout_s: float = option(
        60.0,
        "what of a try's process session is still alive this long after the signal is orphaned",
        flag="--exit-timeout",
        type=argtypes.positive_float,
        metavar="S",
    )
    out: Path | None = option(None, "report path (default: bench/signals.json)", type=argtypes.output_path)


# = tidee.protocol.zenoh_config.DEFAULT_ENDPOINT (this module imports no Zenoh)
ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass
class RouterConfig:
    """``tidee router``: a Zenoh router (the Python API's router mode; no zenohd needed)."""

    listen: tuple[str, ...] = option(
        (ROUTER_ENDPOINT,),
        f"endpoints to listen on (default: {ROUTER_ENDPOINT}, loopback only; tls/HOST:PORT needs a "
        "--zenoh-config that holds the router's certificate)",
        type=argtypes.endpoint,
        nargs="+",
        metavar="ENDPOINT",
    )
    zenoh_config: str | None = option(
        None,
        "a Zenoh config file (JSON5) merged over tidee's settings, its keys winning: TLS, access "
        "control (default: $TIDEE_ZENOH_CONFIG; see deploy/secure/README.md)",
        metavar="FILE",
    )


def run_router(cfg: RouterConfig) -> int:
    """Run a Zenoh router until SIGINT or SIGTERM; one line when it is ready, one when it stops."""
    from tidee.protocol.zenoh_config import open_router, resolve_config_file, router_config

    for endpoint in router_config(cfg.listen, cfg.zenoh_config)[1]:  # a port in use, named
        proto, _, address = endpoint.partition("/")
        host, _, port = address.split("?", 1)[0].rpartition(":")
        if proto in ("tcp", "tls") and port.isdigit() and int(port) > 0:
            check_bindable(host.strip("[]"), int(port), f"--listen {endpoint}", " (another router?)")
    z, endpoints = open_router(cfg.listen, cfg.zenoh_config)
    try:
        config = resolve_config_file(cfg.zenoh_config)
        print(
            f"router: ready, listening on {', '.join(endpoints)}"
            f"{f' with {config}' if config else ''} (zenoh id {z.zid()}); Ctrl-C to stop",
            flush=True,
        )
        wait_for_signal()
    finally:
        z.close()
    print("router: stopped", flush=True)
    return 0


def wait_for_signal() -> None:
    """Block until SIGINT or SIGTERM (a service's main thread). The handlers stay: a signal that
    comes while the service shuts down (Ctrl-C reaches the whole group, and ``tidee run`` then
    signals each child it started) is absorbed rather than raised inside the shutdown; every
    step of a shutdown is bounded, and ``end_process`` kills a process that outstays its grace."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.2):  # a bounded wait: the handler runs within 0.2 s of any signal
        pass


def tidee_command(*args: str) -> list[str]:
    """``tidee ARGS`` as a subprocess's command line, with this interpreter."""
    return [sys.executable, "-m", "tidee.cli", *args]


def _interrupt_on_sigterm() -> Callable[[], object]:
    """Make SIGTERM (``kill``) end this process like Ctrl-C; returns a function that undoes it."""

    def _raise(*_: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _raise)
    return lambda: signal.signal(signal.SIGTERM, previous)


class OutputLines:
    """A child's output lines (stdout, and stderr when it goes to the same pipe; text mode), read on
    a thread as they come: a full pipe would stall the child, and waiting for a line never blocks."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def first(self, text: str, deadline: float) -> str | None:
        """The first line holding ``text``, waiting until ``deadline`` (``time.monotonic()``); None
        when the deadline passes or the child has ended without one."""
        while True:
            ended = self.proc.poll() is not None  # before the look: its last lines are in by then
            for line in list(self.lines):
                if text in line:
                    return line
            if ended and not self._thread.is_alive() or time.monotonic() >= deadline:
                return None
            time.sleep(0.1)

    def wait_for(self, text: str, deadline: float) -> str:
        """``first``, or a ``TimeoutError`` that shows the output so far."""
        line = self.first(text, deadline)
        if line is None:
            raise TimeoutError(f"no line with {text!r} in time; output so far:\n{self.text}")
        return line

    @property
    def text(self) -> str:
        """Every line so far (all of them once the child has ended and closed its output)."""
        self._thread.join(timeout=5)
        return "\n".join(self.lines)


def end_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, grace: float = 30.0) -> None:
    """Send ``sig`` and wait up to ``grace`` seconds, then kill: the process is gone on return."""
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


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


VIEWER_START_S = 60.0  # the viewer imports viser and binds its port well within this
CHILD_POLL_S = 0.2  # how often the server and viewer are checked while the agent runs
_NO_PROXY = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback never goes via a proxy


def _wait_until_listening(proc: subprocess.Popen, host: str, port: int, timeout: float) -> bool:
    """Wait until ``proc`` answers HTTP on ``port``; False if it exits first or never does.

    A whole request, not a bare connect: the viewer's web server logs a connection that sends nothing as a
    failed handshake, with a traceback.
    """
    target = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
    url = f"http://[{target}]:{port}/" if ":" in target else f"http://{target}:{port}/"
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            with _NO_PROXY.open(url, timeout=2):
                return True
        except urllib.error.HTTPError:  # an answer all the same
            return True
        except OSError:
            time.sleep(0.1)
    return False


def _child_failed(name: str, proc: subprocess.Popen) -> int:
    """One line naming the child (server or viewer) that exited or never listened; exit status 1."""
    rc = proc.poll()
    why = (
        f"exited with status {rc} (its error is above)"
        if rc is not None
        else "did not start listening in time"
    )
    print(f"run: error: the {name} {why}; stopping the others", file=sys.stderr, flush=True)
    return 1


def run_all(cfg: RunConfig) -> int:
    if cfg.viewer:  # refused before anything starts (the viewer would refuse it too, in its own process)
        check_bindable(cfg.host, cfg.port, f"--host {cfg.host} --port {cfg.port}", " (choose another --port)")
    endpoint = cfg.endpoint or f"tcp/127.0.0.1:{free_port()}"
    zenoh_config = ["--zenoh-config", cfg.zenoh_config] if cfg.zenoh_config else []
    procs: list[tuple[str, subprocess.Popen]] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    restore = _interrupt_on_sigterm()
    try:
        procs.append(
            (
                "server",
                subprocess.Popen(
                    tidee_command(
                        "server", "--endpoint", endpoint, "--renderer", cfg.renderer, *zenoh_config
                    ),
                    env=env,
                ),
            )
        )
        print(f"run: server on {endpoint}", flush=True)
        if cfg.viewer:
            procs.append(
                (
                    "viewer",
                    subprocess.Popen(
                        tidee_command(
                            "viewer",
                            "--endpoint",
                            endpoint,
                            "--host",
                            cfg.host,
                            "--port",
                            str(cfg.port),
                            *(["--read-only"] if cfg.viewer_read_only else []),
                            *zenoh_config,
                        ),
                        env=env,
                    ),
                )
            )
        agent = subprocess.Popen(tidee_command("agent", "--endpoint", endpoint, *cfg.agent_args), env=env)
        procs.append(("agent", agent))
        if cfg.viewer:
            viewer = procs[1][1]
            if not _wait_until_listening(viewer, cfg.host, cfg.port, VIEWER_START_S):
                return _child_failed("viewer", viewer)
            print(f"run: viewer at http://{cfg.host}:{cfg.port}  (open it in a browser)", flush=True)
        while (rc := agent.poll()) is None:
            for name, p in procs:
                if name != "agent" and p.poll() is not None:
                    return _child_failed(name, p)
            time.sleep(CHILD_POLL_S)
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
