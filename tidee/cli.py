"""The ``tidee`` command: one entry point, a subcommand per job.

Each subcommand imports only what it needs, so ``tidee server`` and ``tidee viewer``
start without torch.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from tidee import argtypes
from tidee.agent.perception import TRAINED_RENDERER  # a constant (no torch)

AGENT_RENDERER_HELP = (
    f"default {TRAINED_RENDERER}: the renderer the shipped detector was trained on (auto picks "
    "EGL when it loads: faster, but the detector scores lower on its frames)"
)

ROOM_TYPES = ("Kitchen", "LivingRoom", "Bedroom", "Bathroom")


def _cmd_server(args: argparse.Namespace) -> int:
    import zenoh

    from tidee.protocol.zenoh_config import open_error
    from tidee.server.service import ServerConfig, serve

    cfg = ServerConfig(
        endpoint=args.endpoint,
        router=args.router,
        max_sessions=args.max_sessions,
        renderer=args.renderer,
        server_id=args.server_id,
        processes=args.processes,
        idle_timeout_s=args.idle_timeout,
        max_sessions_per_client=args.max_sessions_per_client,
    )
    if not args.router:  # before the simulator processes start: a port in use is refused at once
        _check_listen_endpoint(args.endpoint)
    try:
        serve(cfg)
    except zenoh.ZError as e:  # opening the session: a bad endpoint, an unreachable router
        raise open_error(e, True, args.endpoint, args.router) from None
    return 0


def _check_listen_endpoint(endpoint: str | None) -> None:
    """Refuse a tcp/HOST:PORT listen endpoint whose port is taken, naming it (Zenoh's own error is long)."""
    from tidee.launch import check_bindable
    from tidee.protocol.zenoh_config import resolve_endpoint

    where = resolve_endpoint(endpoint)
    proto, _, address = where.partition("/")
    host, _, port = address.split("?", 1)[0].rpartition(":")
    if proto == "tcp" and port.isdigit() and int(port) > 0:
        flag = "--endpoint" if endpoint else "the default endpoint"
        check_bindable(
            host.strip("[]"),
            int(port),
            f"{flag} {where}",
            " (another tidee server? give it another --endpoint port)",
        )


def _cmd_scene_render(args: argparse.Namespace) -> int:
    from tidee.server.render import render_room

    paths = render_room(
        args.room_type,
        args.seed,
        args.mess_index,
        args.out,
        resolution=args.resolution,
        renderer=args.renderer,
    )
    for p in paths:
        print(p)
    return 0


def _cmd_scene_export(args: argparse.Namespace) -> int:
    from tidee.server.episode import SceneLibrary
    from tidee.server.world import World

    world = World(renderer="tiny")
    try:
        scene = SceneLibrary().scene(world, args.room_type, args.seed, args.mess_index)
    finally:
        world.close()
    scene.save(args.out)
    print(
        f"wrote {args.out}: {args.room_type} seed {args.seed} mess index {args.mess_index}, "
        f"{len(scene.objects)} objects"
    )
    return 0


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    from tidee.server.bench_sim import run_sim_bench

    result = run_sim_bench(
        args.resolution,
        args.steps,
        args.out,
        renderer=args.renderer,
        room_type=args.room_type,
        seed=args.seed,
    )
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_reset(args: argparse.Namespace) -> int:
    from tidee.server.bench_reset import run_reset_bench

    result = run_reset_bench(args.out, split=args.split, limit=args.limit)
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_episode(args: argparse.Namespace) -> int:
    from tidee.agent.bench_episode import run_episode_bench

    result = run_episode_bench(
        args.out,
        repeats=args.repeats,
        room_type=args.room_type,
        seed=args.seed,
        mess_index=args.mess_index,
        variant=args.variant,
        max_steps=args.max_steps,
        browser=args.browser,
    )
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_scale(args: argparse.Namespace) -> int:
    from tidee.agent.bench_scale import run_scale_bench

    result = run_scale_bench(
        args.out, configs=args.configs, variants=args.variants, repeats=args.repeats, split=args.split
    )
    print(json.dumps(result, indent=1))
    return 0


def _cmd_gen_cache(args: argparse.Namespace) -> int:
    from tidee.server.bench_reset import fill_cache

    print(
        json.dumps(
            fill_cache(args.split, workers=args.workers, directory=args.cache_dir, limit=args.limit), indent=1
        )
    )
    return 0


def _cmd_bench_transport(args: argparse.Namespace) -> int:
    from tidee.server.bench_transport import run_transport_bench

    result = run_transport_bench(args.resolution, args.steps, args.out)
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_soak(args: argparse.Namespace) -> int:
    from tidee.server.bench_soak import run_soak_bench

    run_soak_bench(args.sessions, args.rooms, args.steps, args.resolution, args.processes, Path(args.out))
    return 0


def _cmd_bench_scale_server(args: argparse.Namespace) -> int:
    from tidee.server.bench_scale import run_scale_server_bench

    result = run_scale_server_bench(
        args.out,
        steps=args.steps,
        resolution=args.resolution,
        processes=tuple(args.processes),
        renderer=args.renderer,
    )
    print(json.dumps(result, indent=1))
    return 0


def _cmd_scene_tour(args: argparse.Namespace) -> int:
    from tidee.server.demo import run_demo

    return run_demo(args.out, room_type=args.room_type, seed=args.seed, mess=args.mess_index)


# --- the agent -----------------------------------------------------------------------------

MISSING_TOP_CHOICES = ("skip", "search")  # agent.config.MISSING_TOP (not imported: it pulls in the mapper)
MISSING_TOP_HELP = (
    "the top-ranked receptacle class is not in memory: skip to the ranked classes in memory "
    "(search for it only after them) | search for it first (the paper's Algorithm S1)"
)

# (flag, kwargs) of every option `tidee agent` takes; `tidee run` takes them too and passes them on.
AGENT_OPTIONS: list[tuple[str, dict]] = [
    (
        "--variant",
        {
            "default": "TIDEE",
            "help": "TIDEE | WithoutMemex | 3DSmntMap2Place | CommonMemory | RandomReceptacle",
        },
    ),
    (
        "--perception",
        {
            "default": "learned",
            "help": "learned (the shipped RGB-D detector) | oracle (reads the simulator's segmentation)",
        },
    ),
    (
        "--depth",
        {
            "default": "sensor",
            "choices": ("sensor", "estimated"),
            "help": "estimated: depth from RGB by the shipped depth network (the paper's +est. depth)",
        },
    ),
    (
        "--oop",
        {
            "default": "auto",
            "help": "auto (visual with learned perception, language with oracle) | "
            "relation_stats | visual | language | fused",
        },
    ),
    ("--explorer", {"default": "random", "choices": ("random", "frontier")}),
    ("--missing-top", {"default": "skip", "choices": MISSING_TOP_CHOICES, "help": MISSING_TOP_HELP}),
    (
        "--detection-threshold",
        {
            "type": argtypes.non_negative_float,
            "default": None,
            "help": "learned detector's score threshold (default: 0.3, perception.AGENT_THRESHOLD)",
        },
    ),
    ("--room-type", {"default": "LivingRoom", "choices": ROOM_TYPES}),
    (
        "--seed",
        {"type": argtypes.non_negative_int, "default": 200, "help": "room seed (200-204 are test rooms)"},
    ),
    ("--mess-index", {"type": argtypes.non_negative_int, "default": 0}),
    ("--resolution", {"type": argtypes.resolution, "default": 256}),
    ("--max-steps", {"type": argtypes.max_steps, "default": 1000}),
    ("--pose-noise", {"action": "store_true"}),
    ("--depth-noise", {"action": "store_true"}),
    (
        "--episodes",
        {"type": argtypes.positive_int, "default": 1, "help": "episodes on consecutive mess indices"},
    ),
    ("--serve", {"action": "store_true", "help": "afterwards, wait for new_episode commands from a viewer"}),
    (
        "--log-dir",
        {
            "default": "runs",
            "type": argtypes.output_path,
            "help": "episode logs (replay with tidee viewer --replay)",
        },
    ),
    ("--session", {"default": None}),
    ("--server-id", {"default": "sim0"}),
    ("--agent-seed", {"type": argtypes.non_negative_int, "default": 0}),
    (
        "--connect-timeout",
        {
            "type": argtypes.non_negative_float,
            "default": 60.0,
            "help": "seconds to wait for the server to appear before giving up",
        },
    ),
    (
        "--reconnect-timeout",
        {
            "type": argtypes.non_negative_float,
            "default": 60.0,
            "help": "if the server goes away mid-episode, seconds to wait for it to come back "
            "before giving up; the episode then runs again from the start "
            "(at most 3 times; 0: give up at once)",
        },
    ),
    (
        "--threads",
        {
            "type": argtypes.non_negative_int,
            "default": 0,
            "help": "torch/OpenMP threads (0: the cores this process may use; tidee run gives the agent "
            "the cores the server does not use)",
        },
    ),
]


def _agent_config(args: argparse.Namespace):
    from tidee.agent.config import AgentConfig, PolicyConfig

    return AgentConfig(
        variant=args.variant,
        perception=args.perception,
        oop=args.oop,
        explorer=args.explorer,
        seed=args.agent_seed,
        depth=args.depth,
        detection_threshold=args.detection_threshold,
        policy=PolicyConfig(missing_top=args.missing_top),
    )


def _check_episodes(args: argparse.Namespace) -> None:
    """Refuse messy configuration indices outside the room's split before anything starts."""
    from tidee.server.splits import check_mess_index

    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    if args.mess_index is not None:
        try:
            check_mess_index(args.seed, args.mess_index)
            check_mess_index(args.seed, args.mess_index + args.episodes - 1)
        except ValueError as e:
            raise ValueError(f"--mess-index / --episodes: {e}") from None


def _cmd_agent(args: argparse.Namespace) -> int:
    from tidee.agent.process import AgentProcessConfig, run_agent_process
    from tidee.protocol.messages import EpisodeSpec

    _check_episodes(args)
    from tidee.threads import threads_per_process, use_threads

    use_threads(args.threads or threads_per_process(1))
    spec = EpisodeSpec(
        room_type=args.room_type,
        seed=args.seed,
        mess_index=args.mess_index,
        resolution=args.resolution,
        max_steps=args.max_steps,
        pose_noise=args.pose_noise,
        depth_noise=args.depth_noise,
    )
    return run_agent_process(
        AgentProcessConfig(
            agent=_agent_config(args),
            spec=spec,
            endpoint=args.endpoint,
            router=args.router,
            server_id=args.server_id,
            session=args.session,
            episodes=args.episodes,
            serve=args.serve,
            log_dir=args.log_dir,
            connect_timeout=args.connect_timeout,
            reconnect_timeout=args.reconnect_timeout,
        )
    )


def _cmd_run(args: argparse.Namespace) -> int:
    from tidee.launch import RunConfig, run_all

    _check_episodes(args)
    from tidee.threads import threads_per_process

    if not args.threads:  # the server renders on one core while the agent thinks: never oversubscribe
        args.threads = threads_per_process(2)
    forwarded: list[str] = []
    for flag, kw in AGENT_OPTIONS:
        if flag == "--server-id":  # tidee run starts its own server under the default id
            continue
        value = getattr(args, flag[2:].replace("-", "_"))
        if kw.get("action") == "store_true":
            forwarded += [flag] if value else []
        elif value is not None:
            forwarded += [flag, str(value)]
    return run_all(
        RunConfig(
            agent_args=forwarded,
            viewer=not args.no_viewer,
            viewer_read_only=args.viewer_read_only,
            host=args.host,
            port=args.port,
            linger=args.linger,
            renderer=args.renderer,
        )
    )


def _cmd_eval_tidy(args: argparse.Namespace) -> int:
    from tidee.agent.evaluation.tidy_eval import run_tidy_eval

    report = run_tidy_eval(
        args.out,
        split=args.split,
        episodes=args.episodes,
        variants=args.variants.split(","),
        perception=args.perception,
        oop=args.oop,
        explorer=args.explorer,
        resolution=args.resolution,
        max_steps=args.max_steps,
        workers=args.workers,
        renderer=args.renderer,
        keep_logs=args.keep_logs,
        depth=args.depth,
        detection_threshold=args.detection_threshold,
        missing_top=args.missing_top,
    )
    print((Path(args.out) / "report.md").read_text())
    return 0 if report else 1


def _cmd_eval_tidy_merge(args: argparse.Namespace) -> int:
    from tidee.agent.evaluation.report import merge_reports

    sources: list = []
    for item in (s for s in args.sources.split(",") if s):
        path, _, take = item.partition("=")
        sources.append((path, [v for v in take.split("+") if v]) if take else path)
    variants = [v for v in args.variants.split(",") if v] if args.variants else None
    command = (
        f"tidee eval tidy-merge --from {args.sources}"
        + (f" --variants {','.join(variants)}" if variants else "")
        + f" --out {args.out}"
    )
    try:
        merge_reports(sources, args.out, variants=variants, command=command)
    except ValueError as e:
        print(f"tidee eval tidy-merge: error: {e}", file=sys.stderr)
        return 2
    print((Path(args.out) / "report.md").read_text())
    return 0


def _cmd_bench_agent(args: argparse.Namespace) -> int:
    from tidee.agent.bench import run_agent_bench

    result = run_agent_bench(
        args.out,
        episodes=args.episodes,
        resolution=args.resolution,
        variant=args.variant,
        max_steps=args.max_steps,
        perception=args.perception,
    )
    print(json.dumps(result, indent=1))
    return 0


def _cmd_gen_stats(args: argparse.Namespace) -> int:
    from tidee.agent.reasoning.stats import DEFAULT_PATH, build_stats

    seeds: list[int] = []
    for part in args.seeds.split(","):
        lo, _, hi = part.partition("-")
        if not (lo.isdigit() and (hi.isdigit() or not hi)):
            raise ValueError(
                f"--seeds {args.seeds!r}: {part!r} is not a seed or a range; expected e.g. 0-19,10000-10179"
            )
        seeds += list(range(int(lo), int(hi or lo) + 1))
    data = build_stats(seeds, args.out or DEFAULT_PATH, command=f"tidee gen stats --seeds {args.seeds}")
    print(json.dumps(data["meta"], indent=1))
    return 0


def _cmd_gen_detection(args: argparse.Namespace) -> int:
    from tidee.agent.perception.dataset import GenConfig, describe, generate

    cfg = GenConfig(
        rooms_per_type=args.rooms_per_type,
        skip_rooms=args.skip_rooms,
        messes_per_room=args.messes,
        walks_per_config=args.walks,
        frames_per_walk=args.frames_per_walk,
        resolution=args.resolution,
        seed=args.seed,
        shard_size=args.shard_size,
    )
    print(describe(cfg), file=sys.stderr)
    command = "tidee gen detection " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else "tidee gen detection"
    manifest = generate(cfg, args.out, command=command, workers=args.workers)
    print(
        json.dumps({k: v for k, v in manifest.items() if k not in ("shards", "rooms", "classes")}, indent=1)
    )
    return 0


def _add_zenoh_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--endpoint",
        default=None,
        type=argtypes.endpoint,
        help="Zenoh rendezvous endpoint (default: loopback, see protocol/README.md)",
    )
    p.add_argument(
        "--router",
        default=None,
        type=argtypes.endpoint,
        help="connect to this Zenoh router instead of peer mode",
    )


class _Parser(argparse.ArgumentParser):
    """Refuses a bad command line in one line (argparse would print the whole usage first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tidee", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("server", help="run a simulation server on Zenoh")
    p.add_argument(
        "--endpoint",
        default=None,
        type=argtypes.endpoint,
        help="Zenoh endpoint to listen on (default: loopback, see protocol/README.md)",
    )
    p.add_argument(
        "--router",
        default=None,
        type=argtypes.endpoint,
        help="connect to this Zenoh router instead of peer mode",
    )
    p.add_argument("--max-sessions", type=argtypes.positive_int, default=16)
    p.add_argument(
        "--renderer", choices=("auto", "egl", "tiny"), default=TRAINED_RENDERER, help=AGENT_RENDERER_HELP
    )
    p.add_argument("--server-id", default="sim0")
    p.add_argument(
        "--processes",
        type=argtypes.non_negative_int,
        default=0,
        help="simulator processes, sessions spread over them (default 0: one per available core)",
    )
    p.add_argument(
        "--idle-timeout",
        type=argtypes.non_negative_float,
        default=300.0,
        metavar="S",
        help="free a session after S seconds without a request (default 300; 0: never)",
    )
    p.add_argument(
        "--max-sessions-per-client",
        type=argtypes.positive_int,
        default=4,
        metavar="N",
        help="sessions one client may hold at once (default 4)",
    )
    p.set_defaults(func=_cmd_server)

    scene = sub.add_parser("scene", help="generate, render and export rooms").add_subparsers(
        dest="scene_cmd", required=True
    )
    for name, func, help_ in (
        ("render", _cmd_scene_render, "PNGs of a room from several viewpoints + top-down"),
        ("export", _cmd_scene_export, "the room as JSON"),
    ):
        p = scene.add_parser(name, help=help_)
        p.add_argument("--room-type", choices=ROOM_TYPES, required=True)
        p.add_argument("--seed", type=argtypes.non_negative_int, required=True)
        p.add_argument(
            "--mess-index",
            type=argtypes.non_negative_int,
            default=None,
            help="messy configuration index (default: tidy)",
        )
        p.add_argument(
            "--out",
            required=True,
            type=argtypes.output_path,
            help="output directory (render) or file (export)",
        )
        if name == "render":
            p.add_argument("--resolution", type=argtypes.resolution, default=480)
            p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="auto")
        p.set_defaults(func=func)

    bench = sub.add_parser("bench", help="benchmarks that write JSON + Markdown").add_subparsers(
        dest="bench_cmd", required=True
    )
    p = bench.add_parser("sim", help="simulator step and render time")
    p.add_argument("--resolution", type=argtypes.resolution, default=300)
    p.add_argument("--steps", type=argtypes.positive_int, default=200)
    p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="auto")
    p.add_argument("--room-type", choices=ROOM_TYPES, default="LivingRoom")
    p.add_argument("--seed", type=argtypes.non_negative_int, default=200)
    p.add_argument("--out", type=argtypes.output_path, default="bench/sim.json")
    p.set_defaults(func=_cmd_bench_sim)
    p = bench.add_parser("reset", help="reset time over a split's configurations: cold (physics) vs cached")
    p.add_argument("--split", choices=("train", "val", "test"), default="test")
    p.add_argument(
        "--limit",
        type=argtypes.positive_int,
        default=None,
        help="only the first N configurations (default: all)",
    )
    p.add_argument("--out", type=argtypes.output_path, default="bench/reset.json")
    p.set_defaults(func=_cmd_bench_reset)
    p = bench.add_parser(
        "episode", help="one episode in process vs live (tidee run: server + agent + viewer), side by side"
    )
    p.add_argument("--repeats", type=argtypes.positive_int, default=3)
    p.add_argument("--room-type", choices=ROOM_TYPES, default="LivingRoom")
    p.add_argument("--seed", type=argtypes.non_negative_int, default=200)
    p.add_argument("--mess-index", type=argtypes.non_negative_int, default=0)
    p.add_argument("--variant", default="TIDEE")
    p.add_argument("--max-steps", type=argtypes.max_steps, default=1000)
    p.add_argument(
        "--browser", action="store_true", help="a headless Chromium shows the viewer during live runs"
    )
    p.add_argument("--out", type=argtypes.output_path, default="bench/episode.json")
    p.set_defaults(func=_cmd_bench_episode)
    p = bench.add_parser("scale", help="tidy episodes per minute with 1 vs 2 worker processes, side by side")
    p.add_argument(
        "--configs",
        type=argtypes.positive_int,
        default=4,
        help="test configurations (spread over the room types)",
    )
    p.add_argument("--variants", default="TIDEE", help="comma list of agents")
    p.add_argument("--repeats", type=argtypes.positive_int, default=1)
    p.add_argument("--split", choices=("val", "test"), default="test")
    p.add_argument("--out", type=argtypes.output_path, default="bench/scale.json")
    p.set_defaults(func=_cmd_bench_scale)
    p = bench.add_parser("transport", help="in-process vs Zenoh step latency")
    p.add_argument("--resolution", type=argtypes.resolution, default=256)
    p.add_argument("--steps", type=argtypes.positive_int, default=200)
    p.add_argument("--out", type=argtypes.output_path, default="bench/transport.json")
    p.set_defaults(func=_cmd_bench_transport)
    p = bench.add_parser(
        "scale-server", help="server steps/s for 1 vs 2 concurrent sessions, per process count"
    )
    p.add_argument(
        "--processes",
        type=argtypes.non_negative_int,
        nargs="+",
        default=[1, 2],
        help="server sizes to compare",
    )
    p.add_argument("--resolution", type=argtypes.resolution, default=256)
    p.add_argument("--steps", type=argtypes.positive_int, default=200, help="timed steps per session")
    p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="tiny")
    p.add_argument("--out", type=argtypes.output_path, default="bench/scale_server.json")
    p.set_defaults(func=_cmd_bench_scale_server)
    p = bench.add_parser("soak", help="server memory while many sessions open and close over many rooms")
    p.add_argument(
        "--sessions",
        type=argtypes.positive_int,
        default=1000,
        help="sessions opened and closed, one after another",
    )
    p.add_argument(
        "--rooms", type=argtypes.positive_int, default=200, help="distinct room configurations cycled over"
    )
    p.add_argument(
        "--steps", type=argtypes.non_negative_int, default=2, help="steps per session after its reset"
    )
    p.add_argument("--resolution", type=argtypes.resolution, default=64)
    p.add_argument(
        "--processes", type=argtypes.positive_int, default=1, help="the server's simulator processes"
    )
    p.add_argument("--out", type=argtypes.output_path, default="bench/soak.json")
    p.set_defaults(func=_cmd_bench_soak)

    p = scene.add_parser(
        "tour", help="start a server, look around a messy room over Zenoh, save what a client sees"
    )
    p.add_argument("--out", type=argtypes.output_path, default="demo_out")
    p.add_argument("--room-type", choices=ROOM_TYPES, default="LivingRoom")
    p.add_argument("--seed", type=argtypes.non_negative_int, default=200)
    p.add_argument("--mess-index", type=argtypes.non_negative_int, default=0)
    p.set_defaults(func=_cmd_scene_tour)

    p = sub.add_parser("agent", help="the tidying agent: connects to a server over Zenoh and runs episodes")
    _add_zenoh_args(p)
    for flag, kw in AGENT_OPTIONS:
        p.add_argument(flag, **kw)
    p.set_defaults(func=_cmd_agent)

    for name, help_ in (
        ("run", "server + agent + viewer as separate processes on embedded Zenoh"),
        (
            "demo",
            "what `make demo` runs: `tidee run` on the demo room (LivingRoom, test seed 200, "
            "mess index 0); takes the same options",
        ),
    ):
        p = sub.add_parser(name, help=help_)
        for flag, kw in AGENT_OPTIONS:
            if flag != "--server-id":
                p.add_argument(flag, **kw)
        p.add_argument("--no-viewer", action="store_true")
        p.add_argument(
            "--viewer-read-only",
            action="store_true",
            help="the viewer shows the agent but has no controls that send it commands",
        )
        p.add_argument(
            "--host", type=argtypes.host, default="127.0.0.1", help="viewer host (loopback by default)"
        )
        p.add_argument("--port", type=argtypes.port, default=8080, help="viewer port")
        p.add_argument(
            "--linger",
            type=argtypes.non_negative_float,
            default=30.0,
            help="seconds to keep the viewer up after the episodes",
        )
        p.add_argument(
            "--renderer", choices=("auto", "egl", "tiny"), default=TRAINED_RENDERER, help=AGENT_RENDERER_HELP
        )
        p.set_defaults(func=_cmd_run)

    ev = sub.add_parser("eval", help="evaluations that write JSON + Markdown + PNG").add_subparsers(
        dest="eval_cmd", required=True
    )
    p = ev.add_parser("tidy", help="tidy episodes on held-out rooms, scored by the simulated judge (Table 1)")
    p.add_argument("--split", choices=("val", "test"), default="test")
    p.add_argument(
        "--episodes",
        type=argtypes.positive_int,
        default=None,
        help="configurations (default: all; test has 100)",
    )
    p.add_argument(
        "--variants",
        default="TIDEE,WithoutMemex,3DSmntMap2Place,CommonMemory,RandomReceptacle,"
        "AI2THORPlacement,MessyPlacement",
    )
    p.add_argument("--perception", default="learned", choices=("learned", "oracle"))
    p.add_argument("--depth", default="sensor", choices=("sensor", "estimated"))
    p.add_argument("--oop", default="auto", help="auto | relation_stats | visual | language | fused")
    p.add_argument("--explorer", default="random", choices=("random", "frontier"))
    p.add_argument("--missing-top", default="skip", choices=MISSING_TOP_CHOICES, help=MISSING_TOP_HELP)
    p.add_argument(
        "--detection-threshold",
        type=argtypes.non_negative_float,
        default=None,
        help="learned detector's score threshold (default: perception.AGENT_THRESHOLD)",
    )
    p.add_argument("--resolution", type=argtypes.resolution, default=256)
    p.add_argument("--max-steps", type=argtypes.max_steps, default=1000)
    p.add_argument("--workers", type=argtypes.positive_int, default=1, help="parallel simulator processes")
    p.add_argument(
        "--renderer", choices=("auto", "egl", "tiny"), default=TRAINED_RENDERER, help=AGENT_RENDERER_HELP
    )
    p.add_argument("--keep-logs", action="store_true", help="write every episode's log under OUT/logs")
    p.add_argument("--out", type=argtypes.output_path, required=True)
    p.set_defaults(func=_cmd_eval_tidy)

    p = ev.add_parser(
        "tidy-merge",
        help="one Table 1 report from the episodes of several tidy runs "
        "(compare a new agent with earlier records without rerunning them)",
    )
    p.add_argument(
        "--from",
        dest="sources",
        required=True,
        help="comma list of report directories (report.json or report.json.gz) or report files, each "
        "optionally =VARIANT+VARIANT to take only those variants from it",
    )
    p.add_argument("--variants", default=None, help="comma list of agent variants to take (default: all)")
    p.add_argument("--out", type=argtypes.output_path, required=True)
    p.set_defaults(func=_cmd_eval_tidy_merge)

    p = bench.add_parser("agent", help="agent mapping/planning/step time and episode wall time")
    p.add_argument("--episodes", type=argtypes.positive_int, default=3)
    p.add_argument("--resolution", type=argtypes.resolution, default=256)
    p.add_argument("--variant", default="TIDEE")
    p.add_argument("--perception", default="learned", choices=("learned", "oracle"))
    p.add_argument("--max-steps", type=argtypes.max_steps, default=1000)
    p.add_argument("--out", type=argtypes.output_path, default="bench/agent.json")
    p.set_defaults(func=_cmd_bench_agent)

    gen = sub.add_parser("gen", help="generate data from training rooms").add_subparsers(
        dest="gen_cmd", required=True
    )
    p = gen.add_parser(
        "cache",
        help="store a split's settled rooms and messy configurations on disk, so resets "
        "load them instead of re-running physics",
    )
    p.add_argument("--split", choices=("train", "val", "test"), default="test")
    p.add_argument(
        "--limit",
        type=argtypes.positive_int,
        default=None,
        help="only the first N configurations (default: all)",
    )
    p.add_argument("--workers", type=argtypes.positive_int, default=1)
    p.add_argument(
        "--cache-dir",
        type=argtypes.output_path,
        default=None,
        help="default: $XDG_CACHE_HOME/tidee/scenes (~/.cache/tidee/scenes)",
    )
    p.set_defaults(func=_cmd_gen_cache)
    p = gen.add_parser(
        "stats", help="placement statistics of the training rooms (OOP + CommonMemory baselines)"
    )
    p.add_argument("--seeds", default="0-19,10000-10179", help="training seeds, e.g. 0-19,10000-10179")
    p.add_argument(
        "--out", type=argtypes.output_path, default=None, help="default: agent/data/placement_stats.json"
    )
    p.set_defaults(func=_cmd_gen_stats)
    p = gen.add_parser(
        "detection", help="RGB-D frames + instance targets from random walks in training rooms"
    )
    p.add_argument(
        "--out",
        type=argtypes.output_path,
        default="data/detection",
        help="directory of shards (default: data/detection)",
    )
    p.add_argument(
        "--rooms-per-type",
        type=argtypes.positive_int,
        default=60,
        help="training rooms per type: seeds 0-19, then the pool",
    )
    p.add_argument(
        "--skip-rooms",
        type=argtypes.non_negative_int,
        default=0,
        help="start after this many rooms per type (e.g. 60: rooms the shipped detector never saw)",
    )
    p.add_argument(
        "--messes",
        type=argtypes.non_negative_int,
        default=2,
        help="messy configurations per room (plus the tidy one)",
    )
    p.add_argument("--walks", type=argtypes.positive_int, default=2, help="random walks per configuration")
    p.add_argument("--frames-per-walk", type=argtypes.positive_int, default=6)
    p.add_argument("--resolution", type=argtypes.resolution, default=256)
    p.add_argument("--shard-size", type=argtypes.positive_int, default=256)
    p.add_argument("--seed", type=argtypes.non_negative_int, default=0)
    p.add_argument("--workers", type=argtypes.positive_int, default=2)
    p.set_defaults(func=_cmd_gen_detection)

    train = sub.add_parser("train", help="train the agent's learned models (GPU if present, else CPU)")
    train_sub = train.add_subparsers(dest="train_cmd", required=True)
    from tidee.agent.perception.commands import register as register_perception  # argparse only: no torch

    register_perception(train_sub, ev)

    from tidee.agent.evaluation.detection import register as register_detection_eval

    register_detection_eval(ev)
    from tidee.agent.reasoning.language_oop import register as register_language_oop

    register_language_oop(train_sub, ev)
    from tidee.agent.reasoning.fused_oop import register as register_fused_oop

    register_fused_oop(train_sub)
    from tidee.agent.reasoning.rgcn_commands import register as register_rgcn

    register_rgcn(train_sub, ev)
    from tidee.agent.reasoning.search_commands import register as register_search

    register_search(gen, train_sub)
    from tidee.agent.reasoning.memory_oop_data import register as register_memory_oop

    register_memory_oop(gen, ev)
    from tidee.agent.evaluation.search_eval import register as register_search_eval

    register_search_eval(ev)
    from tidee.agent.evaluation.ceiling import register as register_ceiling

    register_ceiling(ev)

    from tidee.viewer.cli import register as register_viewer  # argparse only: no viser import here

    register_viewer(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(
            level=logging.DEBUG if args.verbose else logging.INFO,
            format="%(asctime)s %(name)s %(levelname)s %(message)s",
        )
        func: Callable[[argparse.Namespace], int] = args.func
        return func(args)
    except KeyboardInterrupt:  # Ctrl-C before a command's own handler took over (e.g. while importing)
        print(f"tidee {_command_name(argv)}: interrupted".replace("  ", " "), file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as e:
        print(f"tidee: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the environment refused: a port in use, a path that cannot be written, ...
        print(f"tidee {_command_name(argv)}: error: {_os_error_text(e)}".replace("  ", " "), file=sys.stderr)
        return 1


def _os_error_text(e: OSError) -> str:
    """``e`` in words, with the path it concerns: "Permission denied: 'runs/x'" rather than "[Errno 13] ..."."""
    text = e.strerror or str(e)
    if e.filename is not None:
        text += f": {e.filename!r}" + (f" -> {e.filename2!r}" if e.filename2 is not None else "")
    return text


def _command_name(argv: list[str] | None) -> str:
    words = sys.argv[1:] if argv is None else argv
    return next((w for w in words if not w.startswith("-")), "")


if __name__ == "__main__":
    sys.exit(main())
