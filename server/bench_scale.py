"""``tidee bench scale-server``: does a server's throughput grow with concurrent sessions?

For each server size (``--processes``, default 1 and 2) a ``tidee server`` subprocess
serves first one client, then two concurrent clients (each its own session, in a thread of
this process), all walking the same room with the same fixed action sequence. A client
resets and walks a few warm-up steps (which starts its simulator process and loads the
scene), resets again, then waits for the others; the timed walks start together. The
figures: total steps/s over all sessions, per-step latency (median, p90, max) as the
clients see it, and the ratio of two sessions' total to one session's. With one process
the two sessions share one core, so the ratio shows what the processes bring.
The machine's load average before and after goes into the report: on a shared machine it
bounds what any ratio can show.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from tidee.launch import end_process
from tidee.protocol.client import SimClient
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.protocol.messages import Action, EpisodeSpec
from tidee.server.bench_sim import ACTIONS
from tidee.server.bench_transport import WARMUP_STEPS, bench_spec, loopback_endpoint, server_command
from tidee.server.workers import available_cores

SESSIONS = (1, 2)


def run_scale_server_bench(
    out_path: str = "bench/scale_server.json",
    steps: int = 200,
    resolution: int = 256,
    processes: tuple[int, ...] = (1, 2),
    renderer: str = "tiny",
    room_type: str = "LivingRoom",
    seed: int = 200,
    mess_index: int = 0,
) -> dict:
    spec = bench_spec(steps, resolution, room_type, seed, mess_index)
    load_before = os.getloadavg()
    runs = []
    for count in processes:
        with _server(count, renderer, max(SESSIONS)) as (endpoint, server_id):
            phases = {n: _phase(endpoint, server_id, spec, steps, n) for n in SESSIONS}
        one, many = phases[SESSIONS[0]], phases[SESSIONS[-1]]
        runs.append(
            {
                "processes": count,
                "phases": list(phases.values()),
                "ratio": round(many["steps_per_s"] / one["steps_per_s"], 3),
            }
        )
    load_after = os.getloadavg()
    result = {
        "room": f"{room_type}/{seed} mess {mess_index}",
        "resolution": resolution,
        "renderer": renderer,
        "steps_per_session": steps,
        "runs": runs,
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in load_after],
        "machine": f"{platform.machine()} {os.cpu_count()} cores, {available_cores()} available",
    }
    _write(out_path, result)
    return result


@contextmanager
def _server(processes: int, renderer: str, max_sessions: int) -> Iterator[tuple[str, str]]:
    """A ``tidee server`` subprocess; its log is shown only if it fails."""
    endpoint, server_id = loopback_endpoint(), f"scale{uuid.uuid4().hex[:6]}"
    with tempfile.TemporaryFile() as log:
        command = server_command(
            endpoint, server_id, renderer, "--processes", str(processes), "--max-sessions", str(max_sessions)
        )
        proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        try:
            yield endpoint, server_id
        except BaseException:
            log.seek(0)
            sys.stderr.write(log.read()[-4000:].decode(errors="replace"))
            raise
        finally:
            end_process(proc)


def _phase(endpoint: str, server_id: str, spec: EpisodeSpec, steps: int, sessions: int) -> dict:
    """``sessions`` clients walking at once; totals and per-step latencies."""
    clients = [
        SimClient(endpoint=endpoint, server_id=server_id, timeout=120.0, connect_timeout=60.0)
        for _ in range(sessions)
    ]
    go = threading.Barrier(sessions + 1)
    latencies: list[list[float]] = [[] for _ in clients]
    ends = [0.0] * sessions
    errors: list[BaseException] = []

    def walk(k: int, client: SimClient) -> None:
        try:
            client.reset(spec)  # starts the session's simulator process, loads the scene
            for i in range(WARMUP_STEPS):
                client.step(Action(ACTIONS[i % len(ACTIONS)]))
            client.reset(spec)
            go.wait()
            for i in range(steps):
                t = time.perf_counter()
                client.step(Action(ACTIONS[i % len(ACTIONS)]))
                latencies[k].append((time.perf_counter() - t) * 1000)
            ends[k] = time.perf_counter()
        except threading.BrokenBarrierError:
            pass  # another client failed: its error is the one reported
        except BaseException as e:
            errors.append(e)
            go.abort()

    threads = [threading.Thread(target=walk, args=(k, c), daemon=True) for k, c in enumerate(clients)]
    try:
        for t in threads:
            t.start()
        try:
            go.wait()
        except threading.BrokenBarrierError:
            pass
        start = time.perf_counter()
        for t in threads:
            t.join()
    finally:
        for c in clients:
            c.close()
    if errors:
        raise RuntimeError(f"a client failed in the {sessions}-session phase: {errors[0]!r}") from errors[0]
    wall = max(ends) - start
    ms = np.concatenate(latencies)
    return {
        "sessions": sessions,
        "total_steps": int(ms.size),
        "wall_s": round(wall, 3),
        "steps_per_s": round(ms.size / wall, 2),
        "per_session_steps_per_s": [round(len(x) / (e - start), 2) for x, e in zip(latencies, ends)],
        "step_ms_median": round(float(np.median(ms)), 3),
        "step_ms_p90": round(float(np.percentile(ms, 90)), 3),
        "step_ms_max": round(float(ms.max()), 3),
    }


def _write(out_path: str, result: dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(out_path)) or ".", exist_ok=True)
    write_json_atomic(out_path, result)
    lines = [
        "# Server scaling benchmark (`tidee bench scale-server`)",
        "",
        f"{result['room']}, {result['resolution']}² {result['renderer']} renderer, "
        f"{result['steps_per_session']} timed steps per session; {result['machine']}; "
        f"load average (1/5/15 min) {_triple(result['load_avg_before'])} before, "
        f"{_triple(result['load_avg_after'])} after.",
        "",
        "| server processes | sessions | total steps/s | per session steps/s | step ms median | p90 | max |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in result["runs"]:
        for ph in run["phases"]:
            per_session = " / ".join(str(x) for x in ph["per_session_steps_per_s"])
            lines.append(
                f"| {run['processes']} | {ph['sessions']} | {ph['steps_per_s']} | {per_session} "
                f"| {ph['step_ms_median']} | {ph['step_ms_p90']} | {ph['step_ms_max']} |"
            )
    lines += ["", "| server processes | total steps/s, 2 sessions / 1 session |", "|---|---|"]
    lines += [f"| {run['processes']} | {run['ratio']} |" for run in result["runs"]]
    write_atomic(os.path.splitext(out_path)[0] + ".md", ("\n".join(lines) + "\n").encode())


def _triple(xs: list[float]) -> str:
    return " / ".join(f"{x:.2f}" for x in xs)
