"""``tidee bench soak``: does a server's memory stay flat while sessions and rooms churn?

A ``tidee server`` subprocess serves ``sessions`` sessions one after another, each opened
with a reset in the next of ``rooms`` distinct tidy rooms (train-pool seeds, the four room
types in turn; a room not in the scene cache is generated once and stored there), stepped a
few times, then closed. What a user pays is the resident set (VmRSS from /proc) of the server
process plus all its descendants (the simulator processes, fresh ones included once the
server recycles them: ``--recycle-after``), read in every session after its steps, while its
simulator process is up, with the machine's load average beside it. Warm-up is the first
tenth of the sessions (libraries loaded, the scene LRU filled). Recycled simulator processes
make memory a saw tooth, so the figure compares peaks: the growth after warm-up is the peak of
the last few sessions over the peak of the first few after warm-up, in percent
(``growth_window``: a tenth of the run, at least two recycling periods); the target is at most
5 %. The median, p90 and max of the memory after warm-up and the reset times (of a room built
before, and of the first reset in a fresh simulator process: what recycling costs) go in the
report too.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import zenoh

from tidee.launch import end_process, free_port
from tidee.protocol.client import SimClient
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.protocol.messages import Action, ActionName, EpisodeSpec
from tidee.protocol.zenoh_config import make_config
from tidee.server.bench_sim import spread
from tidee.server.config import SoakBenchConfig
from tidee.server.splits import ROOM_TYPES, TRAIN_POOL
from tidee.server.workers import available_cores

WARMUP_FRACTION = 0.1
SAMPLES = 50  # memory readings over the run (plus warm-up and end)
GROWTH_TARGET_PCT = 5.0
STEP_ACTIONS = (ActionName.RotateLeft, ActionName.MoveAhead)


def soak_rooms(count: int) -> list[tuple[str, int]]:
    """``count`` distinct tidy rooms from the train pool: room types in turn, seeds in order."""
    if count > len(TRAIN_POOL) * len(ROOM_TYPES):
        raise ValueError(f"at most {len(TRAIN_POOL) * len(ROOM_TYPES)} distinct rooms, asked for {count}")
    return [(ROOM_TYPES[i % len(ROOM_TYPES)], TRAIN_POOL.start + i // len(ROOM_TYPES)) for i in range(count)]


def soak_command(cfg: SoakBenchConfig) -> str:
    return (
        f"tidee bench soak --sessions {cfg.sessions} --rooms {cfg.rooms} --steps {cfg.steps} "
        f"--resolution {cfg.resolution} --processes {cfg.processes} --recycle-after {cfg.recycle_after}"
    )


def run_soak_bench(cfg: SoakBenchConfig, out_path: Path) -> dict:
    room_list = soak_rooms(cfg.rooms)
    sessions = cfg.sessions
    warmup = max(1, int(sessions * WARMUP_FRACTION))
    every = max(1, sessions // SAMPLES)
    endpoint, server_id = f"tcp/127.0.0.1:{free_port()}", f"soak{uuid.uuid4().hex[:6]}"
    command = [
        *(sys.executable, "-m", "tidee.cli", "server", "--endpoint", endpoint, "--server-id", server_id),
        *("--processes", str(cfg.processes), "--max-sessions", "4", "--renderer", "tiny"),
        *("--recycle-after", str(cfg.recycle_after)),
    ]
    load_before = os.getloadavg()
    totals: list[float] = []  # the whole tree's RSS, MB, read in every session after its steps
    samples: list[dict] = []  # every few sessions, in detail (the Markdown table)
    reset_s: list[float] = []
    fresh: list[bool] = []  # the session's reset ran in a simulator process it was the first to use
    simulators: set[int] = set()
    with tempfile.TemporaryFile() as log:
        server = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        z = zenoh.open(make_config(False, endpoint))
        start = time.monotonic()
        try:
            for i in range(sessions):
                room_type, seed = room_list[i % len(room_list)]
                spec = EpisodeSpec(
                    room_type=room_type, seed=seed, resolution=cfg.resolution, max_steps=cfg.steps + 1
                )
                with SimClient(
                    endpoint=endpoint,
                    server_id=server_id,
                    session=f"soak-{i}",
                    zsession=z,
                    timeout=300.0,
                    connect_timeout=60.0,
                ) as client:
                    t0 = time.perf_counter()
                    client.reset(spec)
                    reset_s.append(time.perf_counter() - t0)
                    live = {p for p in descendants(server.pid) if _is_simulator(p)}
                    fresh.append(bool(live - simulators))
                    simulators |= live
                    for k in range(cfg.steps):
                        client.step(Action(STEP_ACTIONS[k % len(STEP_ACTIONS)]))
                    rss = _tree_rss_mb(server.pid)  # while the session is open: its simulator is up
                totals.append(rss["total_mb"])
                done = i + 1
                if done % every == 0 or done in (warmup, sessions):
                    samples.append(
                        {
                            "sessions": done,
                            "elapsed_s": round(time.monotonic() - start, 1),
                            **rss,
                            "load_1min": round(os.getloadavg()[0], 2),
                        }
                    )
        except BaseException:
            log.seek(0)
            sys.stderr.write(log.read()[-4000:].decode(errors="replace"))
            raise
        finally:
            z.close()
            end_process(server)
    window = growth_window(sessions, warmup, cfg.recycle_after)
    memory = soak_summary(totals, warmup, window)
    seen = [i >= cfg.rooms for i in range(sessions)]  # the room was built before: a cached reset
    result = {
        "command": soak_command(cfg),
        "sessions": sessions,
        "rooms": cfg.rooms,
        "steps_per_session": cfg.steps,
        "resolution": cfg.resolution,
        "processes": cfg.processes,
        "recycle_after": cfg.recycle_after,
        "warmup_sessions": warmup,
        "window_sessions": window,
        **memory,
        "target_pct": GROWTH_TARGET_PCT,
        "within_target": memory["growth_after_warmup_pct"] <= GROWTH_TARGET_PCT,
        "simulator_processes_started": len(simulators),
        "reset_s": spread(reset_s, 3),
        "reset_s_seen_room": _spread_where(reset_s, [s and not f for s, f in zip(seen, fresh)]),
        "reset_s_seen_room_fresh_simulator": _spread_where(reset_s, [s and f for s, f in zip(seen, fresh)]),
        "wall_s": round(time.monotonic() - start, 1),
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        "load_1min_during": spread([s["load_1min"] for s in samples]),
        "machine": f"{platform.machine()} {os.cpu_count()} cores, {available_cores()} available",
        "samples": samples,
        "total_mb_per_session": totals,
    }
    _write(out_path, result)
    return result


def growth_window(sessions: int, warmup: int, recycle_after: int) -> int:
    """Sessions whose peak memory is compared, early against late: a tenth of the run, and at least
    two recycling periods (so each window holds a whole tooth), at most half of what follows warm-up."""
    return max(1, min(max(sessions // 10, 2 * recycle_after), (sessions - warmup) // 2))


def soak_summary(totals: list[float], warmup: int, window: int) -> dict:
    """The memory figures from each session's reading (``totals``, MB, in session order).

    Growth after warm-up: the peak of the last ``window`` sessions over the peak of the first
    ``window`` after warm-up, in percent. Recycled simulator processes make memory a saw tooth;
    comparing peaks of windows that each hold whole teeth says whether the teeth grow.
    """
    after = totals[warmup:] or totals[-1:]
    early, late = max(after[:window]), max(after[-window:])
    return {
        "rss_warmup_mb": totals[warmup - 1],
        "rss_after_warmup_mb": spread(after, 1),
        "rss_peak_early_mb": early,
        "rss_peak_late_mb": late,
        "rss_end_mb": totals[-1],
        "growth_after_warmup_pct": round(100.0 * (late - early) / early, 2),
    }


def _spread_where(xs: list[float], keep: list[bool]) -> dict[str, float] | None:
    chosen = [x for x, k in zip(xs, keep) if k]
    return spread(chosen, 3) if chosen else None


def _tree_rss_mb(pid: int) -> dict:
    """VmRSS of ``pid`` and of all its descendants, in MB."""
    parent = _rss_kb(pid)
    children = sum(_rss_kb(p) for p in descendants(pid))
    return {
        "server_mb": round(parent / 1024, 1),
        "children_mb": round(children / 1024, 1),
        "total_mb": round((parent + children) / 1024, 1),
    }


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (children, theirs, ...), from /proc (Linux)."""
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{current}/task")
        except FileNotFoundError:
            continue
        for tid in tasks:
            try:
                kids = [int(x) for x in Path(f"/proc/{current}/task/{tid}/children").read_text().split()]
            except (FileNotFoundError, ProcessLookupError):
                continue
            found += kids
            todo += kids
    return found


def _is_simulator(pid: int) -> bool:
    """A simulator process (a multiprocessing "spawn" child), not the resource tracker beside them."""
    try:
        return b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError):
        return False


def _rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0


def _write(out_path: Path, result: dict) -> None:
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(str(out_path), result)
    r = result
    rss, w = r["rss_after_warmup_mb"], r["window_sessions"]
    lines = [
        "# Server soak benchmark (`tidee bench soak`)",
        "",
        f"`{r['command']}`: {r['sessions']} sessions opened, stepped {r['steps_per_session']} times and "
        f"closed one after another over {r['rooms']} distinct tidy rooms, {r['resolution']}² frames, "
        f"{r['processes']} simulator process(es) at a time, each replaced after {r['recycle_after']} resets "
        f"(0: never; {r['simulator_processes_started']} started in all); {r['machine']}; {r['wall_s']} s; "
        f"load average (1/5/15 min) {_triple(r['load_avg_before'])} before, "
        f"{_triple(r['load_avg_after'])} after; 1-minute load during the run: median "
        f"{r['load_1min_during']['median']}, max {r['load_1min_during']['max']}.",
        "",
        "Memory is the resident set of the server and all its processes, read in every session after "
        "its steps.",
        "",
        "| server + simulator processes, RSS | MB |",
        "|---|---|",
        f"| at the end of warm-up ({r['warmup_sessions']} sessions) | {r['rss_warmup_mb']} |",
        f"| after warm-up: median / p90 / max | {rss['median']} / {rss['p90']} / {rss['max']} |",
        f"| peak of the first {w} sessions after warm-up | {r['rss_peak_early_mb']} |",
        f"| peak of the last {w} sessions | {r['rss_peak_late_mb']} |",
        f"| **growth after warm-up** (late peak over early peak) | **{r['growth_after_warmup_pct']} %** "
        f"(target ≤ {r['target_pct']:g} %: {'met' if r['within_target'] else 'not met'}) |",
        "",
        "| reset time, client side (s) | median | p90 | max |",
        "|---|---|---|---|",
    ]
    for label, key in (
        ("every session (new rooms are generated)", "reset_s"),
        ("a room built before", "reset_s_seen_room"),
        (
            "a room built before, first reset in a fresh simulator process",
            "reset_s_seen_room_fresh_simulator",
        ),
    ):
        if r[key] is not None:
            lines.append(f"| {label} | {r[key]['median']} | {r[key]['p90']} | {r[key]['max']} |")
    lines += [
        "",
        "| sessions | elapsed s | server MB | simulator processes MB | total MB | 1-min load |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {s['sessions']} | {s['elapsed_s']} | {s['server_mb']} | {s['children_mb']} | {s['total_mb']} "
        f"| {s['load_1min']} |"
        for s in r["samples"]
    ]
    write_atomic(os.path.splitext(str(out_path))[0] + ".md", ("\n".join(lines) + "\n").encode())


def _triple(xs: list[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in xs)
