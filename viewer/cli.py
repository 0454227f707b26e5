"""``tidee viewer``: argument parsing only (viser is imported when the command runs)."""

from __future__ import annotations

import argparse

from tidee import argtypes


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("viewer", help="the live web viewer (viser): watch and steer agents in a browser")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--endpoint",
        default=None,
        type=argtypes.endpoint,
        help="Zenoh rendezvous to connect to (peer mode; default: TIDEE_ZENOH_ENDPOINT or "
        "tcp/127.0.0.1:7447)",
    )
    where.add_argument(
        "--router",
        default=None,
        type=argtypes.endpoint,
        help="connect through this Zenoh router instead (client mode)",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        type=argtypes.host,
        help="address to serve the page on (default: loopback only; 0.0.0.0 exposes the agent "
        "controls to the network, behind an access token)",
    )
    access = p.add_mutually_exclusive_group()
    access.add_argument(
        "--read-only",
        action="store_true",
        help="no controls that send commands to agents (pause, new episode, preference)",
    )
    access.add_argument(
        "--token",
        default=None,
        help="the access token the agent controls need (default: a random one, printed, when "
        "--host is not loopback; none on loopback)",
    )
    p.add_argument(
        "--port",
        type=argtypes.port_or_any,
        default=8080,
        help="HTTP port (0: any free port); the URL is printed",
    )
    p.add_argument("--session", default=None, help="show this session (default: follow the newest)")
    p.add_argument(
        "--replay",
        default=None,
        metavar="LOGDIR",
        help="play back a saved episode log with a time slider instead of live telemetry",
    )
    p.add_argument("--rate", type=_rate, default=10.0, help="scene updates per second, at most (default 10)")
    p.add_argument(
        "--screenshot",
        default=None,
        metavar="PNG",
        type=argtypes.output_path,
        help="with --replay: write the page as headless Chromium draws it at --at, then exit",
    )
    p.add_argument(
        "--at",
        default="end",
        help="with --screenshot: a step number, 'search' (the first search heatmap) or 'end' (default)",
    )
    p.add_argument(
        "--annotated",
        default=None,
        metavar="PNG",
        type=argtypes.output_path,
        help="with --screenshot: also write the picture with each panel outlined, numbered and named",
    )
    p.add_argument(
        "--window",
        default="1280x800",
        type=_window_size,
        metavar="WxH",
        help="with --screenshot: the browser window's size in pixels (default 1280x800)",
    )
    p.set_defaults(func=_run)


def _rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected updates per second in (0, 60], got {text!r}") from None
    if not 0 < value <= 60:
        raise argparse.ArgumentTypeError(f"expected updates per second in (0, 60], got {text}")
    return value


def _window_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--window must be WIDTHxHEIGHT in pixels, e.g. 1280x800; got {text!r}"
        ) from None
    if not (320 <= w <= 4096 and 240 <= h <= 4096):
        raise argparse.ArgumentTypeError(f"--window {w}x{h}: each side must be within 320x240 to 4096x4096")
    return w, h


def _run(args: argparse.Namespace) -> int:
    if args.annotated and not args.screenshot:
        raise SystemExit("tidee viewer: --annotated needs --screenshot PNG (and --replay LOGDIR)")
    if args.screenshot:
        if not args.replay:
            raise SystemExit("tidee viewer: --screenshot needs --replay LOGDIR")
        from tidee.viewer.screenshot import screenshot_replay

        step = screenshot_replay(
            args.replay, args.screenshot, at=args.at, annotated_png=args.annotated, size=args.window
        )
        also = f" and {args.annotated}" if args.annotated else ""
        print(f"viewer: {args.screenshot}{also} (step {step} of {args.replay})")
        return 0
    import zenoh

    from tidee.protocol.zenoh_config import open_error
    from tidee.viewer.app import ViewerConfig, serve

    config = ViewerConfig(
        endpoint=args.endpoint,
        router=args.router,
        host=args.host,
        port=args.port,
        session=args.session,
        replay=args.replay,
        rate_hz=args.rate,
        read_only=args.read_only,
        token=args.token,
    )
    try:
        serve(config)
    except zenoh.ZError as e:  # opening the live feed's session: an unreachable router
        raise open_error(e, False, args.endpoint, args.router) from None
    return 0
