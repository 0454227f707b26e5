"""What the viewer's commands take, each option declared once (``tidee.options`` makes the flags):
``tidee viewer``, the viewer benchmark and the synthetic agent.

A light module: no viser, no Zenoh. Output paths default to None, meaning a file under the
checkout's ``bench/`` (``tidee.paths``), never the working directory.

``ViewerConfig`` is what a running viewer takes (``tidee.viewer.app.run_viewer``);
``ViewerCommandConfig`` is the ``tidee viewer`` command line: a ``ViewerConfig`` and the
screenshot options.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

from tidee import argtypes
from tidee.options import option
from tidee.protocol import keys

RATE_HZ = 10.0  # scene updates per second, at most (the app's default too)
MAX_RATE_HZ = 60.0


class WindowSize(NamedTuple):
    """A browser window's size in pixels."""

    width: int
    height: int


def _rate(text: str) -> float:
    """Viewer updates per second: in (0, 60]."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"expected updates per second in (0, 60], got {text!r}") from None
    if not 0 < value <= MAX_RATE_HZ:  # also refuses nan
        raise ValueError(f"expected updates per second in (0, 60], got {text}")
    return value


def _window_size(text: str) -> WindowSize:
    """``WIDTHxHEIGHT`` in pixels, each side within 320x240 to 4096x4096 (``W,H``, as
    ``tidee.options.to_argv`` writes a tuple, is taken too)."""
    try:
        w, h = (int(v) for v in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise ValueError(f"--window must be WIDTHxHEIGHT in pixels, e.g. 1280x800; got {text!r}") from None
    if not (320 <= w <= 4096 and 240 <= h <= 4096):
        raise ValueError(f"--window {w}x{h}: each side must be within 320x240 to 4096x4096")
    return WindowSize(w, h)


def _replay_step(text: str) -> str:
    """``--at``: a step number, ``search`` or ``end`` (whether the log holds that step is checked
    when the log is open)."""
    if text in ("end", "search"):
        return text
    try:
        int(text)
    except ValueError:
        raise ValueError(f"expected a step number, 'search' or 'end'; got {text!r}") from None
    return text


@dataclass
class ViewerConfig:
    """A running viewer: where its telemetry comes from, where it serves the page, who may steer.

    ``endpoint``/``router`` and ``read_only``/``token`` are two pairs of which at most one may
    be given (the command line refuses both; see ``ViewerCommandConfig.EXCLUSIVE``).
    """

    endpoint: str | None = option(
        None,
        "Zenoh rendezvous to connect to (peer mode; default: TIDEE_ZENOH_ENDPOINT or tcp/127.0.0.1:7447)",
        type=argtypes.endpoint,
    )
    router: str | None = option(
        None, "connect through this Zenoh router instead (client mode)", type=argtypes.endpoint
    )
    zenoh_config: str | None = option(
        None,
        "a Zenoh config file (JSON5) merged over tidee's settings, its keys winning: TLS, access "
        "control (default: $TIDEE_ZENOH_CONFIG; see deploy/secure/README.md)",
        metavar="FILE",
    )
    read_only: bool = option(
        False, "no controls that send commands to agents (pause, new episode, preference)"
    )
    token: str | None = option(
        None,
        "the access token the agent controls need (default: a random one, printed, when --host is not "
        "loopback; none on loopback)",
    )
    host: str = option(
        "127.0.0.1",
        "address to serve the page on (default: loopback only; 0.0.0.0 exposes the agent controls to the "
        "network, behind an access token)",
        type=argtypes.host,
    )
    port: int = option(8080, "HTTP port (0: any free port); the URL is printed", type=argtypes.port_or_any)
    session: str | None = option(None, "show this session (default: follow the newest)")
    replay: str | None = option(
        None,
        "play back a saved episode log with a time slider instead of live telemetry",
        metavar="LOGDIR",
    )
    rate_hz: float = option(
        RATE_HZ, "scene updates per second, at most (default 10)", flag="--rate", type=_rate, metavar="RATE"
    )
    max_points: int = option(200_000, "voxel points sent to the browser, at most", cli=False)
    oracle_period_s: float = option(1.0, "ground-truth layer: how often to ask the server", cli=False)

    def __post_init__(self) -> None:
        if not 0 <= int(self.port) <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        if not 0 < float(self.rate_hz) <= MAX_RATE_HZ:
            raise ValueError(f"rate_hz must be in (0, 60], got {self.rate_hz}")
        if int(self.max_points) < 1:
            raise ValueError(f"max_points must be >= 1, got {self.max_points}")
        if self.session is not None:
            keys.check_id("session", self.session)
        if self.replay is not None and not os.path.isdir(self.replay):
            raise FileNotFoundError(
                f"--replay {self.replay!r} is not a directory (expected an episode log "
                f"directory holding telemetry.tlog)"
            )
        if self.token is not None and not self.token.strip():
            raise ValueError("token must not be empty (leave it out for a random one off loopback)")
        if self.endpoint and self.router:
            raise ValueError("give either endpoint (peer mode) or router (client mode), not both")


@dataclass
class ViewerCommandConfig:
    """``tidee viewer``: the live web viewer, or a replay of a saved episode log, or a screenshot of one."""

    viewer: ViewerConfig = option(default_factory=ViewerConfig)
    screenshot: str | None = option(
        None,
        "with --replay: write the page as headless Chromium draws it at --at, then exit",
        type=argtypes.output_path,
        metavar="PNG",
    )
    at: str = option(
        "end",
        "with --screenshot: a step number, 'search' (the first search heatmap) or 'end' (default)",
        type=_replay_step,
        metavar="AT",
    )
    annotated: str | None = option(
        None,
        "with --screenshot: also write the picture with each panel outlined, numbered and named",
        type=argtypes.output_path,
        metavar="PNG",
    )
    window: WindowSize = option(
        WindowSize(1280, 800),
        "with --screenshot: the browser window's size in pixels (default 1280x800)",
        type=_window_size,
        metavar="WxH",
    )

    # Pairs of fields the command line takes at most one of (argparse mutually exclusive groups).
    EXCLUSIVE: ClassVar[tuple[tuple[str, str], ...]] = (("endpoint", "router"), ("read_only", "token"))


@dataclass
class ViewerBenchConfig:
    """``python -m tidee.viewer.bench``: does the viewer keep up, does it slow the agent?"""

    steps: int = option(
        1000, "steps the synthetic agent publishes per run", type=argtypes.int_range(10, None, "a step count")
    )
    work_ms: float = option(
        30.0, "the synthetic agent's CPU time per step, in ms", type=argtypes.non_negative_float
    )
    no_browser: bool = option(False, "skip the run with headless Chromium")
    rate_hz: float = option(
        RATE_HZ, "the viewer's updates per second, at most", flag="--rate", type=_rate, metavar="RATE"
    )
    out: str | None = option(
        None,
        "where the JSON goes, a Markdown table beside it (default: bench/viewer.json in the checkout)",
        type=argtypes.output_path,
    )


@dataclass
class SyntheticConfig:
    """``python -m tidee.viewer.synthetic``: publish a synthetic episode (try the viewer without an agent)."""

    endpoint: str | None = option(
        None, "peer-mode rendezvous (default: loopback:7447)", type=argtypes.endpoint
    )
    router: str | None = option(None, "connect through this Zenoh router instead", type=argtypes.endpoint)
    connect: bool = option(
        False, "connect to the rendezvous instead of listening on it (when a server already listens)"
    )
    session: str = option("synthetic", "the session id the telemetry is published under")
    server_id: str = option("sim0", "the server id the session's liveliness is declared under")
    steps: int = option(0, "stop after this many steps (0: run until Ctrl-C)", type=argtypes.non_negative_int)
    rate_hz: float = option(
        10.0,
        "steps per second (0: as fast as possible)",
        flag="--rate",
        type=argtypes.non_negative_float,
        metavar="RATE",
    )
    work_ms: float = option(
        0.0, "CPU time burnt per step, in ms (an agent's compute)", type=argtypes.non_negative_float
    )
    wait_viewer: float = option(
        0.0, "wait up to this many seconds for a subscriber", type=argtypes.non_negative_float
    )
    resolution: int = option(128, "camera image side in pixels", type=argtypes.resolution)
