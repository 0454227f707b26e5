"""The ``tidee`` command: one entry point, a subcommand per job.

Every command's options are the fields of its config dataclass (``tidee.options``): the
server's in ``server/config.py``, the agent's in ``agent/config.py``, the evaluations' and
benchmarks' in ``agent/evaluation/config.py``, each model family's in its ``config.py``.
Building the parser imports only those light modules; each command imports what it needs
when it runs, so ``tidee server`` and ``tidee viewer`` start without torch.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

from tidee.agent.config import LIVE_RUN_SKIP, AgentProcessConfig, LiveRunConfig
from tidee.agent.evaluation import config as ec
from tidee.launch import RouterConfig, SignalsBenchConfig
from tidee.options import add_command, to_argv
from tidee.paths import PROJECT_DIR, bench_out
from tidee.protocol.messages import EpisodeSpec
from tidee.server import config as sc
from tidee.server.config import ServerConfig


def _cmd_server(cfg: ServerConfig) -> int:
    import zenoh

    from tidee.protocol.zenoh_config import make_config, open_error, resolve_config_file
    from tidee.server.service import serve

    # Before the simulator processes start: a bad config file or a port in use is refused at once.
    make_config(True, cfg.endpoint, cfg.router, cfg.zenoh_config)
    if not cfg.router and not resolve_config_file(cfg.zenoh_config):  # a file may listen elsewhere
        _check_listen_endpoint(cfg.endpoint)
    try:
        serve(cfg)
    except zenoh.ZError as e:  # opening the session: a bad endpoint, an unreachable router
        raise open_error(e, True, cfg.endpoint, cfg.router, cfg.zenoh_config) from None
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


def _cmd_scene_render(cfg: sc.SceneRenderConfig) -> int:
    from tidee.server.render import render_room

    s = cfg.scene
    for p in render_room(
        s.room_type, s.seed, s.mess_index, str(cfg.out), resolution=cfg.resolution, renderer=cfg.renderer
    ):
        print(p)
    return 0


def _cmd_scene_export(cfg: sc.SceneExportConfig) -> int:
    from tidee.server.episode import SceneLibrary
    from tidee.server.world import World

    s = cfg.scene
    world = World(renderer="tiny")
    try:
        scene = SceneLibrary().scene(world, s.room_type, s.seed, s.mess_index)
    finally:
        world.close()
    scene.save(str(cfg.out))
    print(
        f"wrote {cfg.out}: {s.room_type} seed {s.seed} mess index {s.mess_index}, "
        f"{len(scene.objects)} objects"
    )
    return 0


def _cmd_scene_tour(cfg: sc.SceneTourConfig) -> int:
    from tidee.server.demo import run_demo

    out = cfg.out if cfg.out is not None else PROJECT_DIR / "demo_out"
    return run_demo(str(out), room_type=cfg.room_type, seed=cfg.seed, mess=cfg.mess_index)


def _print_json(result: object) -> int:
    print(json.dumps(result, indent=1))
    return 0


def _cmd_bench_sim(cfg: sc.SimBenchConfig) -> int:
    from tidee.server.bench_sim import run_sim_bench

    out = str(bench_out(cfg.out, "sim.json"))
    return _print_json(
        run_sim_bench(
            cfg.resolution, cfg.steps, out, renderer=cfg.renderer, room_type=cfg.room_type, seed=cfg.seed
        )
    )


def _cmd_bench_reset(cfg: sc.ResetBenchConfig) -> int:
    from tidee.server.bench_reset import run_reset_bench

    return _print_json(
        run_reset_bench(str(bench_out(cfg.out, "reset.json")), split=cfg.split, limit=cfg.limit)
    )


def _cmd_bench_transport(cfg: sc.TransportBenchConfig) -> int:
    from tidee.server.bench_transport import run_transport_bench

    return _print_json(
        run_transport_bench(
            cfg.resolution, cfg.steps, str(bench_out(cfg.out, "transport.json")), renderer=cfg.renderer
        )
    )


def _cmd_bench_soak(cfg: sc.SoakBenchConfig) -> int:
    from tidee.server.bench_soak import run_soak_bench

    out = bench_out(cfg.out, "soak.json")
    run_soak_bench(cfg, out)
    print(out.with_suffix(".md").read_text())
    return 0


def _cmd_bench_fuzz(cfg: sc.FuzzBenchConfig) -> int:
    from tidee.server.bench_fuzz import run_fuzz_bench

    out = bench_out(cfg.out, "fuzz.json")
    result = run_fuzz_bench(cfg, out)
    print(out.with_suffix(".md").read_text())
    return 0 if result["targets_met"] else 1


def _cmd_bench_signals(cfg: SignalsBenchConfig) -> int:
    from tidee.bench_signals import run_signals_bench

    out = bench_out(cfg.out, "signals.json")
    result = run_signals_bench(cfg, out)
    print(out.with_suffix(".md").read_text())
    return 0 if result["targets_met"] else 1


def _cmd_bench_scale_server(cfg: sc.ScaleServerBenchConfig) -> int:
    from tidee.server.bench_scale import run_scale_server_bench

    return _print_json(
        run_scale_server_bench(
            str(bench_out(cfg.out, "scale_server.json")),
            steps=cfg.steps,
            resolution=cfg.resolution,
            processes=tuple(cfg.processes),
            renderer=cfg.renderer,
        )
    )


def _cmd_bench_deployment(cfg: sc.DeploymentBenchConfig) -> int:
    from tidee.server.bench_deployment import run_deployment_bench

    out = str(bench_out(cfg.out, "deployment.json"))
    return _print_json(run_deployment_bench(out, cfg.steps, cfg.resolution, cfg.renderer))


def _cmd_bench_episode(cfg: ec.EpisodeBenchConfig) -> int:
    from tidee.agent.bench_episode import run_episode_bench

    return _print_json(
        run_episode_bench(
            str(bench_out(cfg.out, "episode.json")),
            repeats=cfg.repeats,
            room_type=cfg.room_type,
            seed=cfg.seed,
            mess_index=cfg.mess_index,
            variant=cfg.variant,
            max_steps=cfg.max_steps,
            browser=cfg.browser,
            renderer=cfg.renderer,
        )
    )


def _cmd_bench_scale(cfg: ec.ScaleBenchConfig) -> int:
    from tidee.agent.bench_scale import run_scale_bench

    return _print_json(
        run_scale_bench(
            str(bench_out(cfg.out, "scale.json")),
            configs=cfg.configs,
            variants=",".join(cfg.variants),
            repeats=cfg.repeats,
            split=cfg.split,
            backends=cfg.backends,
        )
    )


def _cmd_bench_agent(cfg: ec.AgentBenchConfig) -> int:
    from tidee.agent.bench import run_agent_bench

    return _print_json(
        run_agent_bench(
            str(bench_out(cfg.out, "agent.json")),
            episodes=cfg.episodes,
            resolution=cfg.resolution,
            variant=cfg.variant,
            max_steps=cfg.max_steps,
            perception=cfg.perception,
        )
    )


def _cmd_gen_cache(cfg: sc.CacheConfig) -> int:
    from tidee.server.bench_reset import fill_cache

    directory = str(cfg.cache_dir) if cfg.cache_dir is not None else None
    return _print_json(
        fill_cache(cfg.split, workers=cfg.workers, directory=directory, limit=cfg.limit, backend=cfg.batch)
    )


# --- the agent -----------------------------------------------------------------------------


def _check_episodes(spec: EpisodeSpec, episodes: int) -> None:
    """Refuse messy configuration indices outside the room's split before anything starts."""
    from tidee.server.splits import check_mess_index

    if spec.mess_index is not None:
        try:
            check_mess_index(spec.seed, spec.mess_index)
            check_mess_index(spec.seed, spec.mess_index + episodes - 1)
        except ValueError as e:
            raise ValueError(f"--mess-index / --episodes: {e}") from None


def _cmd_agent(cfg: AgentProcessConfig) -> int:
    from tidee.agent.process import run_agent_process
    from tidee.threads import threads_per_process, use_threads

    _check_episodes(cfg.spec, cfg.episodes)
    use_threads(cfg.threads or threads_per_process(1))
    return run_agent_process(cfg)


def _cmd_run(cfg: LiveRunConfig) -> int:
    from tidee.launch import run_all
    from tidee.protocol.zenoh_config import make_config
    from tidee.threads import threads_per_process

    _check_episodes(cfg.agent.spec, cfg.agent.episodes)
    make_config(False, zenoh_config=cfg.agent.zenoh_config)  # a bad file is refused before anything starts
    agent = cfg.agent
    if not agent.threads:  # the server renders on one core while the agent thinks: never oversubscribe
        agent = replace(agent, threads=threads_per_process(2))
    argv = to_argv(agent, skip=[s.removeprefix("agent.") for s in LIVE_RUN_SKIP])  # tidee run gives its own
    return run_all(replace(cfg.launch, agent_args=argv, zenoh_config=agent.zenoh_config))


def _cmd_router(cfg: RouterConfig) -> int:
    from tidee.launch import run_router

    return run_router(cfg)


def _cmd_eval_tidy(cfg: ec.TidyEvalConfig) -> int:
    from tidee.agent.evaluation.tidy_eval import run_tidy_eval

    report = run_tidy_eval(cfg)
    print((Path(cfg.out) / "report.md").read_text())
    return 0 if report else 1


def _cmd_eval_rearrange(cfg: ec.RearrangeEvalConfig) -> int:
    from tidee.agent.evaluation.rearrange_eval import run_rearrange_eval

    run_rearrange_eval(cfg)
    print((Path(cfg.out) / "report.md").read_text())
    return 0


def _cmd_eval_tidy_merge(cfg: ec.TidyMergeConfig) -> int:
    from tidee.agent.evaluation.report import merge_reports

    sources: list = []
    for item in (s for s in cfg.sources.split(",") if s):
        path, _, take = item.partition("=")
        sources.append((path, [v for v in take.split("+") if v]) if take else path)
    variants = list(cfg.variants) or None
    command = (
        f"tidee eval tidy-merge --from {cfg.sources}"
        + (f" --variants {','.join(variants)}" if variants else "")
        + f" --out {cfg.out}"
    )
    try:
        merge_reports(sources, str(cfg.out), variants=variants, command=command)
    except ValueError as e:
        print(f"tidee eval tidy-merge: error: {e}", file=sys.stderr)
        return 2
    print((Path(cfg.out) / "report.md").read_text())
    return 0


def _cmd_eval_compare(cfg: ec.CompareConfig) -> int:
    from tidee.agent.evaluation.compare import compare_reports, write_comparison

    try:
        result = compare_reports(cfg.before, cfg.after)
    except ValueError as e:
        print(f"tidee eval compare: error: {e}", file=sys.stderr)
        return 2
    print(write_comparison(result, cfg.out).read_text())
    return 0


def _cmd_eval_human(cfg: ec.HumanEvalConfig) -> int:
    from tidee.agent.evaluation.human_judge import run_human_eval

    command = "tidee eval human " + " ".join(f"--report {r}" for r in cfg.report) + f" --out {cfg.out}"
    run_human_eval(list(cfg.report), Path(cfg.out), command=command)
    print((Path(cfg.out) / "human.md").read_text())
    return 0


def _cmd_eval_preferences(cfg: ec.PreferenceEvalConfig) -> int:
    from tidee.agent.evaluation.preference_eval import run_preference_eval

    command = "tidee eval preferences " + " ".join(to_argv(cfg))
    run_preference_eval(cfg, command=command)
    print((Path(cfg.out) / "preferences.md").read_text())
    return 0


def _cmd_gen_stats(cfg: ec.StatsGenConfig) -> int:
    from tidee.agent.reasoning.stats import DEFAULT_PATH, build_stats

    seeds: list[int] = []
    for part in cfg.seeds.split(","):
        lo, _, hi = part.partition("-")
        if not (lo.isdigit() and (hi.isdigit() or not hi)):
            raise ValueError(
                f"--seeds {cfg.seeds!r}: {part!r} is not a seed or a range; expected e.g. 0-19,10000-10179"
            )
        seeds += list(range(int(lo), int(hi or lo) + 1))
    data = build_stats(
        seeds,
        cfg.out or DEFAULT_PATH,
        command=f"tidee gen stats --seeds {cfg.seeds}",
        workers=cfg.workers,
        backend=cfg.batch,
    )
    return _print_json(data["meta"])


class _Parser(argparse.ArgumentParser):
    """Refuses a bad command line in one line (argparse would print the whole usage first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _group(sub: argparse._SubParsersAction, name: str, help: str) -> argparse._SubParsersAction:
    return sub.add_parser(name, help=help, description=help).add_subparsers(dest=f"{name}_cmd", required=True)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tidee", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    add_command(sub, "server", ServerConfig, _cmd_server, "run a simulation server on Zenoh")
    add_command(
        sub,
        "router",
        RouterConfig,
        _cmd_router,
        "a Zenoh router for processes on several machines (TLS and access control: --zenoh-config)",
    )

    scene = _group(sub, "scene", "generate, render and export rooms")
    add_command(
        scene,
        "render",
        sc.SceneRenderConfig,
        _cmd_scene_render,
        "PNGs of a room from several viewpoints + top-down",
    )
    add_command(scene, "export", sc.SceneExportConfig, _cmd_scene_export, "the room as JSON")
    add_command(
        scene,
        "tour",
        sc.SceneTourConfig,
        _cmd_scene_tour,
        "start a server, look around a messy room over Zenoh, save what a client sees",
    )

    bench = _group(sub, "bench", "benchmarks that write JSON + Markdown")
    add_command(bench, "sim", sc.SimBenchConfig, _cmd_bench_sim, "simulator step and render time")
    add_command(
        bench,
        "reset",
        sc.ResetBenchConfig,
        _cmd_bench_reset,
        "reset time over a split's configurations: cold (physics) vs cached",
    )
    add_command(
        bench,
        "episode",
        ec.EpisodeBenchConfig,
        _cmd_bench_episode,
        "one episode in process vs live (tidee run: server + agent + viewer), side by side",
    )
    add_command(
        bench,
        "scale",
        ec.ScaleBenchConfig,
        _cmd_bench_scale,
        "tidy episodes per hour with 1 vs 2 workers, local processes and Ray actors, side by side",
    )
    add_command(
        bench, "transport", sc.TransportBenchConfig, _cmd_bench_transport, "in-process vs Zenoh step latency"
    )
    add_command(
        bench,
        "scale-server",
        sc.ScaleServerBenchConfig,
        _cmd_bench_scale_server,
        "server steps/s for 1 vs 2 concurrent sessions, per process count",
    )
    add_command(
        bench,
        "deployment",
        sc.DeploymentBenchConfig,
        _cmd_bench_deployment,
        "step latency peer-to-peer vs through a tidee router, side by side on one server",
    )
    add_command(
        bench,
        "soak",
        sc.SoakBenchConfig,
        _cmd_bench_soak,
        "server memory while many sessions open and close over many rooms",
    )
    add_command(
        bench,
        "fuzz",
        sc.FuzzBenchConfig,
        _cmd_bench_fuzz,
        "malformed, mutated and oversized requests of every op against a real server: crashes, "
        "hangs, internal errors",
    )
    add_command(
        bench,
        "signals",
        SignalsBenchConfig,
        _cmd_bench_signals,
        "SIGTERM and SIGINT to tidee run, SIGTERM to tidee server: orphaned processes, open ports, "
        "tracebacks",
    )
    add_command(
        bench,
        "agent",
        ec.AgentBenchConfig,
        _cmd_bench_agent,
        "agent mapping/planning/step time and episode wall time",
    )

    add_command(
        sub,
        "agent",
        AgentProcessConfig,
        _cmd_agent,
        "the tidying agent: connects to a server over Zenoh and runs episodes",
    )
    add_command(
        sub,
        "run",
        LiveRunConfig,
        _cmd_run,
        "server + agent + viewer as separate processes on embedded Zenoh",
        skip=LIVE_RUN_SKIP,
    )
    add_command(
        sub,
        "demo",
        LiveRunConfig,
        _cmd_run,
        "what `make demo` runs: `tidee run` on the demo room (LivingRoom, test seed 200, "
        "mess index 0); takes the same options",
        skip=LIVE_RUN_SKIP,
    )

    ev = _group(sub, "eval", "evaluations that write JSON + Markdown + PNG")
    add_command(
        ev,
        "tidy",
        ec.TidyEvalConfig,
        _cmd_eval_tidy,
        "tidy episodes on held-out rooms, scored by the simulated judge (Table 1)",
        skip=ec.TIDY_EVAL_SKIP,
    )
    add_command(
        ev,
        "rearrange",
        ec.RearrangeEvalConfig,
        _cmd_eval_rearrange,
        "2-phase rearrangement on held-out rooms, RoomR's metrics (Table 4)",
        skip=ec.REARRANGE_EVAL_SKIP,
    )
    add_command(
        ev,
        "tidy-merge",
        ec.TidyMergeConfig,
        _cmd_eval_tidy_merge,
        "one Table 1 report from the episodes of several tidy runs "
        "(compare a new agent with earlier records without rerunning them)",
    )

    add_command(
        ev,
        "compare",
        ec.CompareConfig,
        _cmd_eval_compare,
        "two runs of one tidy or rearrangement evaluation, episode by episode: better, worse, same",
    )
    add_command(
        ev,
        "human",
        ec.HumanEvalConfig,
        _cmd_eval_human,
        "tidy reports' placements judged by people (Housekeep annotations): correct, plausible, pairwise",
    )

    add_command(
        ev,
        "preferences",
        ec.PreferenceEvalConfig,
        _cmd_eval_preferences,
        "scripted household preferences: obeyed, generalised to a group, and side effects",
        skip=ec.PREFERENCE_EVAL_SKIP,
    )

    gen = _group(sub, "gen", "generate data from training rooms")
    add_command(
        gen,
        "cache",
        sc.CacheConfig,
        _cmd_gen_cache,
        "store a split's settled rooms and messy configurations on disk, so resets "
        "load them instead of re-running physics",
    )
    add_command(
        gen,
        "stats",
        ec.StatsGenConfig,
        _cmd_gen_stats,
        "placement statistics of the training rooms (OOP + CommonMemory baselines)",
    )

    train_sub = _group(sub, "train", "train the agent's learned models (GPU if present, else CPU)")
    from tidee.agent.perception.commands import register as register_perception  # argparse only: no torch

    register_perception(gen, train_sub, ev)

    from tidee.agent.evaluation.detection.commands import register as register_detection_eval

    register_detection_eval(ev)
    from tidee.agent.reasoning.language_oop.commands import register as register_language_oop

    register_language_oop(train_sub, ev, gen)

    from tidee.agent.reasoning.rgcn.commands import register as register_rgcn
    from tidee.agent.reasoning.search.commands import register as register_search

    register_rgcn(gen, train_sub, ev)
    register_search(gen, train_sub, ev)
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
    """``e`` in words, with its path: "Permission denied: 'runs/x'" rather than "[Errno 13] ..."."""
    text = e.strerror or str(e)
    if e.filename is not None:
        text += f": {e.filename!r}" + (f" -> {e.filename2!r}" if e.filename2 is not None else "")
    return text


def _command_name(argv: list[str] | None) -> str:
    words = sys.argv[1:] if argv is None else argv
    return next((w for w in words if not w.startswith("-")), "")


if __name__ == "__main__":
    sys.exit(main())
