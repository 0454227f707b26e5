"""The ``tidee`` command: one entry point, a subcommand per job.

Each subcommand imports only what it needs, so ``tidee server`` and ``tidee viewer``
start without torch.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Callable

ROOM_TYPES = ("Kitchen", "LivingRoom", "Bedroom", "Bathroom")


def _cmd_server(args: argparse.Namespace) -> int:
    from tidee.server.service import ServerConfig, serve

    cfg = ServerConfig(endpoint=args.endpoint, router=args.router, max_sessions=args.max_sessions,
                       renderer=args.renderer, server_id=args.server_id)
    serve(cfg)
    return 0


def _cmd_scene_render(args: argparse.Namespace) -> int:
    from tidee.server.render import render_room

    paths = render_room(args.room_type, args.seed, args.mess, args.out, resolution=args.resolution,
                        renderer=args.renderer)
    for p in paths:
        print(p)
    return 0


def _cmd_scene_export(args: argparse.Namespace) -> int:
    from tidee.server.episode import SceneLibrary
    from tidee.server.world import World

    world = World(renderer="tiny")
    try:
        scene = SceneLibrary().scene(world, args.room_type, args.seed, args.mess)
    finally:
        world.close()
    scene.save(args.out)
    print(f"wrote {args.out}: {args.room_type} seed {args.seed} mess {args.mess}, {len(scene.objects)} objects")
    return 0


def _cmd_bench_sim(args: argparse.Namespace) -> int:
    from tidee.server.bench_sim import run_sim_bench

    result = run_sim_bench(args.resolution, args.steps, args.out, renderer=args.renderer,
                           room_type=args.room_type, seed=args.seed)
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_transport(args: argparse.Namespace) -> int:
    from tidee.server.bench_transport import run_transport_bench

    result = run_transport_bench(args.resolution, args.steps, args.out)
    print(json.dumps(result, indent=1))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from tidee.server.demo import run_demo

    return run_demo(args.out, room_type=args.room_type, seed=args.seed, mess=args.mess)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tidee", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("server", help="run a simulation server on Zenoh")
    p.add_argument("--endpoint", default=None, help="Zenoh endpoint to listen on (default: loopback, see protocol/README.md)")
    p.add_argument("--router", default=None, help="connect to this Zenoh router instead of peer mode")
    p.add_argument("--max-sessions", type=int, default=16)
    p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="auto")
    p.add_argument("--server-id", default="sim0")
    p.set_defaults(func=_cmd_server)

    scene = sub.add_parser("scene", help="generate, render and export rooms").add_subparsers(dest="scene_cmd", required=True)
    for name, func, help_ in (("render", _cmd_scene_render, "PNGs of a room from several viewpoints + top-down"),
                              ("export", _cmd_scene_export, "the room as JSON")):
        p = scene.add_parser(name, help=help_)
        p.add_argument("--room-type", choices=ROOM_TYPES, required=True)
        p.add_argument("--seed", type=int, required=True)
        p.add_argument("--mess", type=int, default=None, help="messy configuration index (default: tidy)")
        p.add_argument("--out", required=True, help="output directory (render) or file (export)")
        if name == "render":
            p.add_argument("--resolution", type=int, default=480)
            p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="auto")
        p.set_defaults(func=func)

    bench = sub.add_parser("bench", help="benchmarks that write JSON + Markdown").add_subparsers(dest="bench_cmd", required=True)
    p = bench.add_parser("sim", help="simulator step and render time")
    p.add_argument("--resolution", type=int, default=300)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default="auto")
    p.add_argument("--room-type", choices=ROOM_TYPES, default="LivingRoom")
    p.add_argument("--seed", type=int, default=200)
    p.add_argument("--out", default="bench/sim.json")
    p.set_defaults(func=_cmd_bench_sim)
    p = bench.add_parser("transport", help="in-process vs Zenoh step latency")
    p.add_argument("--resolution", type=int, default=256)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--out", default="bench/transport.json")
    p.set_defaults(func=_cmd_bench_transport)

    p = sub.add_parser("demo", help="start a server, play a messy room over Zenoh, save what the agent sees")
    p.add_argument("--out", default="demo_out")
    p.add_argument("--room-type", choices=ROOM_TYPES, default="LivingRoom")
    p.add_argument("--seed", type=int, default=200)
    p.add_argument("--mess", type=int, default=0)
    p.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError) as e:
        print(f"tidee: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
