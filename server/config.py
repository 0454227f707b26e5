"""What the server's commands take, each option declared once (``tidee.options`` makes the
flags): the server itself, scenes, the simulator benchmarks and the scene cache.

A light module: no PyBullet, no Zenoh. Output paths default to None, meaning a file under the
checkout's ``bench/`` (``tidee.paths``), never the working directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tidee import argtypes
from tidee.batch import BackendConfig
from tidee.options import option
from tidee.protocol import keys
from tidee.protocol.vocab import RENDERERS, Renderer, RoomType, Split

# The renderer the shipped detector was trained on (= tidee.agent.perception.TRAINED_RENDERER,
# which the server does not import): the server's default, so agents see what they learned on.
TRAINED_RENDERER: Renderer = "tiny"
# Resets a simulator process runs before a fresh one replaces it (ServerConfig.recycle_after).
DEFAULT_RECYCLE_AFTER = 50
RENDERER_HELP = (
    f"who draws the frames; {TRAINED_RENDERER}: what the default detector was trained on (auto picks "
    "EGL when it loads: faster; the agent's --detector tiny+egl was trained on both)"
)


@dataclass
class ServerConfig:
    """``tidee server``: a simulation server on Zenoh."""

    endpoint: str | None = option(
        None,
        "Zenoh endpoint to listen on (default: $TIDEE_ZENOH_ENDPOINT, else loopback; see protocol/README.md)",
        type=argtypes.endpoint,
    )
    router: str | None = option(
        None, "connect to this Zenoh router instead of peer mode", type=argtypes.endpoint
    )
    zenoh_config: str | None = option(
        None,
        "a Zenoh config file (JSON5) merged over tidee's settings, its keys winning: TLS, access "
        "control (default: $TIDEE_ZENOH_CONFIG; see deploy/secure/README.md)",
        metavar="FILE",
    )
    max_sessions: int = option(16, "sessions open at once", type=argtypes.positive_int)
    renderer: Renderer = option(TRAINED_RENDERER, RENDERER_HELP)
    server_id: str = option("sim0", "this server's id in the Zenoh key space")
    processes: int = option(
        0,
        "simulator processes, sessions spread over them (0: one per available core)",
        type=argtypes.non_negative_int,
    )
    recycle_after: int = option(
        DEFAULT_RECYCLE_AFTER,
        "replace a simulator process after N resets (PyBullet keeps ~0.1 MB a reset): it takes no new "
        "session, its sessions move at their next reset, it stops when it holds none (0: never)",
        type=argtypes.non_negative_int,
        metavar="N",
    )
    workers: int = option(1, "threads running episodes when a factory is given", cli=False)
    max_request_bytes: int = option(1 << 20, "largest request accepted (requests carry no arrays)", cli=False)
    max_sessions_per_client: int = option(
        4, "sessions one client may hold at once", type=argtypes.positive_int, metavar="N"
    )
    idle_timeout_s: float = option(
        300.0,
        "free a session after S seconds without a request (0: never)",
        flag="--idle-timeout",
        type=argtypes.non_negative_float,
        metavar="S",
    )

    def __post_init__(self) -> None:
        keys.check_id("server_id", self.server_id)
        if self.server_id == keys.AUTO_SERVER:
            raise ValueError(
                f"server_id {keys.AUTO_SERVER!r} is reserved: clients ask for it to choose a live server; "
                "give this server another id"
            )
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        for name in ("max_sessions", "workers", "max_request_bytes", "max_sessions_per_client"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if int(self.processes) < 0:
            raise ValueError(f"processes must be >= 0 (0: one per available core), got {self.processes}")
        if int(self.recycle_after) < 0:
            raise ValueError(f"recycle_after must be >= 0 (0: never), got {self.recycle_after}")
        if not float(self.idle_timeout_s) >= 0:
            raise ValueError(f"idle_timeout_s must be >= 0 seconds (0: never), got {self.idle_timeout_s}")

    def process_count(self) -> int:
        """How many child processes the default episodes run in."""
        from tidee.server.workers import available_cores

        return min(self.processes or available_cores(), self.max_sessions)


@dataclass
class SceneConfig:
    """One room configuration: a room type, its seed and a messy configuration (or the tidy room)."""

    room_type: RoomType = option(help="the room type")
    seed: int = option(help="room seed (200-204 are test rooms)", type=argtypes.non_negative_int)
    mess_index: int | None = option(
        None, "messy configuration index (default: the tidy room)", type=argtypes.non_negative_int
    )


@dataclass
class SceneRenderConfig:
    """``tidee scene render``."""

    scene: SceneConfig
    out: Path = option(help="output directory", type=argtypes.output_path)
    resolution: int = option(480, "image side, pixels", type=argtypes.resolution)
    renderer: Renderer = option("auto", "who draws the frames")


@dataclass
class SceneExportConfig:
    """``tidee scene export``."""

    scene: SceneConfig
    out: Path = option(help="output file (JSON)", type=argtypes.output_path)


@dataclass
class SceneTourConfig:
    """``tidee scene tour``."""

    out: Path | None = option(
        None, "output directory (default: demo_out/ in the checkout)", type=argtypes.output_path
    )
    room_type: RoomType = option("LivingRoom", "the room type")
    seed: int = option(200, "room seed (200-204 are test rooms)", type=argtypes.non_negative_int)
    mess_index: int = option(0, "messy configuration index", type=argtypes.non_negative_int)


@dataclass
class SimBenchConfig:
    """``tidee bench sim``."""

    resolution: int = option(300, "image side, pixels", type=argtypes.resolution)
    steps: int = option(200, "timed steps", type=argtypes.positive_int)
    renderer: Renderer = option("auto", "who draws the frames")
    room_type: RoomType = option("LivingRoom", "the room type")
    seed: int = option(200, "room seed", type=argtypes.non_negative_int)
    out: Path | None = option(None, "report path (default: bench/sim.json)", type=argtypes.output_path)


@dataclass
class ResetBenchConfig:
    """``tidee bench reset``."""

    split: Split = option("test", "whose configurations")
    limit: int | None = option(
        None, "only the first N configurations (default: all)", type=argtypes.positive_int
    )
    out: Path | None = option(None, "report path (default: bench/reset.json)", type=argtypes.output_path)


@dataclass
class TransportBenchConfig:
    """``tidee bench transport``."""

    resolution: int = option(256, "image side, pixels", type=argtypes.resolution)
    steps: int = option(200, "timed steps", type=argtypes.positive_int)
    renderer: Renderer = option("auto", "who draws the frames (tiny: what agents see by default)")
    out: Path | None = option(None, "report path (default: bench/transport.json)", type=argtypes.output_path)


@dataclass
class ScaleServerBenchConfig:
    """``tidee bench scale-server``."""

    processes: tuple[int, ...] = option(
        (1, 2), "server sizes to compare", type=argtypes.non_negative_int, nargs="+"
    )
    resolution: int = option(256, "image side, pixels", type=argtypes.resolution)
    steps: int = option(200, "timed steps per session", type=argtypes.positive_int)
    renderer: Renderer = option("tiny", "who draws the frames")
    out: Path | None = option(
        None, "report path (default: bench/scale_server.json)", type=argtypes.output_path
    )


@dataclass
class DeploymentBenchConfig:
    """``tidee bench deployment``."""

    resolution: int = option(256, "image side, pixels", type=argtypes.resolution)
    steps: int = option(200, "timed steps each way", type=argtypes.positive_int)
    renderer: Renderer = option("tiny", "who draws the frames")
    out: Path | None = option(None, "report path (default: bench/deployment.json)", type=argtypes.output_path)


@dataclass
class SoakBenchConfig:
    """``tidee bench soak``."""

    sessions: int = option(300, "sessions opened and closed, one after another", type=argtypes.positive_int)
    rooms: int = option(40, "distinct room configurations cycled over", type=argtypes.positive_int)
    steps: int = option(2, "steps per session after its reset", type=argtypes.non_negative_int)
    resolution: int = option(64, "image side, pixels", type=argtypes.resolution)
    processes: int = option(1, "the server's simulator processes", type=argtypes.positive_int)
    recycle_after: int = option(
        DEFAULT_RECYCLE_AFTER,
        "the server's --recycle-after: resets before a simulator process is replaced (0: never)",
        type=argtypes.non_negative_int,
        metavar="N",
    )
    out: Path | None = option(None, "report path (default: bench/soak.json)", type=argtypes.output_path)


@dataclass
class FuzzBenchConfig:
    """``tidee bench fuzz``."""

    cases: int = option(20_000, "requests sent", type=argtypes.positive_int)
    seed: int = option(
        0, "draws the requests: the same seed sends the same ones", type=argtypes.non_negative_int
    )
    batch: int = option(
        250, "an honest episode is checked after every N requests", type=argtypes.positive_int, metavar="N"
    )
    reply_timeout_s: float = option(
        120.0,
        "a request without a reply in S seconds is a hang",
        flag="--reply-timeout",
        type=argtypes.positive_float,
        metavar="S",
    )
    processes: int = option(1, "the server's simulator processes", type=argtypes.positive_int)
    out: Path | None = option(None, "report path (default: bench/fuzz.json)", type=argtypes.output_path)


@dataclass
class CacheConfig:
    """``tidee gen cache``."""

    split: Split = option("test", "whose configurations")
    limit: int | None = option(
        None, "only the first N configurations (default: all)", type=argtypes.positive_int
    )
    workers: int = option(
        1, "worker processes (local) or Ray actors generating rooms", type=argtypes.positive_int
    )
    batch: BackendConfig = option(default_factory=BackendConfig)
    cache_dir: Path | None = option(
        None, "default: $XDG_CACHE_HOME/tidee/scenes (~/.cache/tidee/scenes)", type=argtypes.output_path
    )


__all__ = [
    "CacheConfig",
    "DeploymentBenchConfig",
    "FuzzBenchConfig",
    "ResetBenchConfig",
    "ScaleServerBenchConfig",
    "SceneConfig",
    "SceneExportConfig",
    "SceneRenderConfig",
    "SceneTourConfig",
    "ServerConfig",
    "SimBenchConfig",
    "SoakBenchConfig",
    "TransportBenchConfig",
]
