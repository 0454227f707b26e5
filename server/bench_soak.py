"""``tidee bench soak``: does a server's memory stay flat while sessions and rooms churn?

A ``tidee server`` subprocess serves ``sessions`` sessions one after another, each opened
with a reset in the next of ``rooms`` distinct tidy rooms (train-pool seeds, the four room
types in turn; a room not in the scene cache is generated once and stored there), stepped a
few times, then closed. The server's memory is the resident set (VmRSS from /proc) of its
process plus all its descendants (the simulator processes), read between sessions. Warm-up
is the first tenth of the sessions (simulator processes started, libraries loaded, the
scene LRU filled); the figure is the growth from the end of warm-up to the end, in percent
of the warm-up value (the target is at most 5 %). With the default 1000 sessions over 200
rooms, sessions 100-199 still bring rooms the server has never built, so a cost per
distinct room shows up in that growth as well as a cost per session. The machine's load
average goes into the report.
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


def run_soak_bench(
    sessions: int = 1000,
    rooms: int = 200,
    steps: int = 2,
    resolution: int = 64,
    processes: int = 1,
    out_path: Path = Path("bench/soak.json"),
) -> dict:
    room_list = soak_rooms(rooms)
    warmup = max(1, int(sessions * WARMUP_FRACTION))
    every = max(1, sessions // SAMPLES)
    endpoint, server_id = f"tcp/127.0.0.1:{free_port()}", f"soak{uuid.uuid4().hex[:6]}"
    command = [
        sys.executable,
        "-m",
        "tidee.cli",
        "server",
        "--endpoint",
        endpoint,
        "--server-id",
        server_id,
        "--processes",
        str(processes),
        "--max-sessions",
        "4",
        "--renderer",
        "tiny",
    ]
    load_before = os.getloadavg()
    samples: list[dict] = []
    with tempfile.TemporaryFile() as log:
        server = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        z = zenoh.open(make_config(False, endpoint))
        start = time.monotonic()
        try:
            for i in range(sessions):
                room_type, seed = room_list[i % len(room_list)]
                spec = EpisodeSpec(room_type=room_type, seed=seed, resolution=resolution, max_steps=steps + 1)
                with SimClient(
                    endpoint=endpoint,
                    server_id=server_id,
                    session=f"soak-{i}",
                    zsession=z,
                    timeout=300.0,
                    connect_timeout=60.0,
                ) as client:
                    client.reset(spec)
                    for k in range(steps):
                        client.step(Action(STEP_ACTIONS[k % len(STEP_ACTIONS)]))
                done = i + 1
                if done % every == 0 or done in (warmup, sessions):
                    samples.append(
                        {
                            "sessions": done,
                            "elapsed_s": round(time.monotonic() - start, 1),
                            **_tree_rss_mb(server.pid),
                        }
                    )
        except BaseException:
            log.seek(0)
            sys.stderr.write(log.read()[-4000:].decode(errors="replace"))
            raise
        finally:
            z.close()
            end_process(server)
    at = {s["sessions"]: s for s in samples}
    warm, end = at[warmup]["total_mb"], at[sessions]["total_mb"]
    growth = 100.0 * (end - warm) / warm
    result = {
        "command": f"tidee bench soak --sessions {sessions} --rooms {rooms} --steps {steps} "
        f"--resolution {resolution} --processes {processes}",
        "sessions": sessions,
        "rooms": rooms,
        "steps_per_session": steps,
        "resolution": resolution,
        "processes": processes,
        "warmup_sessions": warmup,
        "rss_warmup_mb": warm,
        "rss_end_mb": end,
        "growth_after_warmup_pct": round(growth, 2),
        "per_session_after_warmup_kb": round(1024 * (end - warm) / max(1, sessions - warmup), 1),
        "target_pct": GROWTH_TARGET_PCT,
        "within_target": growth <= GROWTH_TARGET_PCT,
        "wall_s": samples[-1]["elapsed_s"],
        "samples": samples,
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        "machine": f"{platform.machine()} {os.cpu_count()} cores, {available_cores()} available",
    }
    _write(out_path, result)
    return result


def _tree_rss_mb(pid: int) -> dict:
    """VmRSS of ``pid`` and of all its descendants, in MB."""
    parent = _rss_kb(pid)
    children = sum(_rss_kb(p) for p in _descendants(pid))
    return {
        "server_mb": round(parent / 1024, 1),
        "children_mb": round(children / 1024, 1),
        "total_mb": round((parent + children) / 1024, 1),
    }


def _descendants(pid: int) -> list[int]:
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
    lines = [
        "# Server soak benchmark (`tidee bench soak`)",
        "",
        f"`{r['command']}`: {r['sessions']} sessions opened, stepped {r['steps_per_session']} times and "
        f"closed one after another over {r['rooms']} distinct tidy rooms, {r['resolution']}² frames, "
        f"{r['processes']} simulator process(es); {r['machine']}; {r['wall_s']} s; load average "
        f"(1/5/15 min) {_triple(r['load_avg_before'])} before, {_triple(r['load_avg_after'])} after.",
        "",
        "| | server + simulator processes, RSS MB |",
        "|---|---|",
        f"| after warm-up ({r['warmup_sessions']} sessions) | {r['rss_warmup_mb']} |",
        f"| at the end ({r['sessions']} sessions) | {r['rss_end_mb']} |",
        f"| growth after warm-up | {r['growth_after_warmup_pct']} % (target ≤ {r['target_pct']:g} %; "
        f"{r['per_session_after_warmup_kb']} kB per session) |",
        "",
        "| sessions | elapsed s | server MB | simulator processes MB | total MB |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {s['sessions']} | {s['elapsed_s']} | {s['server_mb']} | {s['children_mb']} | {s['total_mb']} |"
        for s in r["samples"]
    ]
    write_atomic(os.path.splitext(str(out_path))[0] + ".md", ("\n".join(lines) + "\n").encode())


def _triple(xs: list[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in xs)
