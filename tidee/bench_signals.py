"""``tidee bench signals``: does every process go when ``tidee run`` or ``tidee server`` is told to stop?

Each ``tidee run`` try starts server + agent + viewer (small frames, a short episode) in a
session of its own (``start_new_session``: its pid is the session and process group id of
everything it starts), waits until it really runs (the viewer's URL printed, the viewer page
answering, the agent's frames arriving on the server's observation feed), waits a delay drawn
from ``seed``, then sends one SIGTERM (as ``kill`` or a supervisor does) or one SIGINT to the
``tidee run`` process alone. After ``exit_timeout_s`` it counts what is left: every process of
that session still alive (an *orphan*), every port of the run still listening (the viewer's,
the server's), and any traceback printed. Each ``tidee server`` try starts a server with two
simulator processes and a client resetting and stepping in a loop, and sends one SIGTERM after
a drawn delay, counted from its start (half the tries: during its start-up) or from the client's
first reset (the other half: while it serves): it must exit, with nothing left. Stragglers are
killed after counting, so one try never disturbs the next.

The children start with SIGINT at its default, as from a terminal (a shell's background job
would pass on an ignored SIGINT, which Python then keeps ignoring by design).
"""

from __future__ import annotations

import os
import platform
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from tidee.launch import OutputLines, SignalsBenchConfig, free_port

STARTUP_TIMEOUT_S = (
    300.0  # a loaded machine imports torch, loads models and binds the viewer well within this
)
FRAMES_BEFORE_SIGNAL = 2  # agent frames seen on the feed before the signal: it is stepping
RUN_DELAY_S = (0.0, 4.0)  # the signal comes this long after the run is seen running
SERVER_DELAY_S = (0.0, 3.0)  # after the server process starts, or after its client's first reset
CLEAR_TIMEOUT_S = 5.0  # the killed members of a try's session are gone within this


def session_processes(sid: int) -> dict[int, str]:
    """Live (non-zombie) processes of session ``sid``: pid -> command line."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            state, _ppid, _pgrp, session = stat.rsplit(")", 1)[1].split()[:4]
            if int(session) != sid or state == "Z":
                continue
            cmdline = (
                Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            )
        except (FileNotFoundError, ProcessLookupError, ValueError):
            continue
        found[int(entry)] = cmdline.strip()[:200]
    return found


def listening(port: int) -> bool:
    """Whether something accepts TCP connections on loopback ``port``."""
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _gone_or_left(sid: int, until: float) -> dict[int, str]:
    """Wait until session ``sid`` has no live process or ``until`` (monotonic) passes; what is left."""
    while (left := session_processes(sid)) and time.monotonic() < until:
        time.sleep(0.05)
    return left


def end_try(proc: subprocess.Popen, sig: int, exit_timeout: float) -> dict[str, Any]:
    """Send ``sig`` to ``proc`` alone; its exit code and time, and what of its session is left."""
    sid = proc.pid
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        code: int | None = proc.wait(timeout=exit_timeout)
    except subprocess.TimeoutExpired:
        code = None
    exit_s = time.monotonic() - t0
    left = _gone_or_left(sid, t0 + exit_timeout)  # the rest of the tree: same bound
    for pid in left:  # counted: now clear them, so the next try starts clean
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    # A SIGKILLed process lives on until the kernel delivers the signal, later on a busy machine.
    _gone_or_left(sid, time.monotonic() + CLEAR_TIMEOUT_S)
    return {"exit_code": code, "exit_s": round(exit_s, 2), "orphans": left}


def run_try(cfg: SignalsBenchConfig, sig: int, delay: float, log_dir: str) -> dict[str, Any]:
    import zenoh

    from tidee.protocol import keys
    from tidee.protocol.zenoh_config import make_config

    port = free_port()
    command = [
        *(sys.executable, "-m", "tidee.cli", "run", "--port", str(port), "--log-dir", log_dir),
        *("--resolution", str(cfg.resolution), "--max-steps", str(cfg.max_steps), "--linger", "0"),
    ]
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    out = OutputLines(proc)
    result: dict[str, Any] = {"signal": signal.Signals(sig).name, "delay_s": round(delay, 2)}
    z = None
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        server_line = out.first("run: server on ", deadline)
        endpoint = server_line.split()[-1] if server_line else None
        frames = threading.Semaphore(0)
        if endpoint is not None:
            z = zenoh.open(make_config(False, endpoint))
            z.declare_subscriber(keys.observations_wildcard("sim0"), lambda _sample: frames.release())
        viewer = out.first("run: viewer at ", deadline)
        stepping = viewer is not None and all(
            frames.acquire(timeout=max(0.0, deadline - time.monotonic())) for _ in range(FRAMES_BEFORE_SIGNAL)
        )
        result["started"] = bool(stepping and listening(port))
        ports = [port] + ([int(endpoint.rsplit(":", 1)[1])] if endpoint else [])
        if result["started"]:
            time.sleep(delay)
        result.update(end_try(proc, sig, cfg.exit_timeout_s))
        result["ports_open"] = [p for p in ports if listening(p)]
    finally:
        if z is not None:
            z.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = out.text
    result["traceback"] = "Traceback" in text
    result["ok"] = _clean(result) and result["started"]
    if not result["ok"]:
        result["output_tail"] = text[-3000:]
    return result


def server_try(cfg: SignalsBenchConfig, delay: float, serving: bool) -> dict[str, Any]:
    """One ``tidee server`` with a client stepping, one SIGTERM ``delay`` seconds after its start
    (``serving`` False) or after the client's first reset."""
    from tidee.protocol.client import SimClient
    from tidee.protocol.messages import Action, ActionName, EpisodeSpec

    port = free_port()
    endpoint, server_id = f"tcp/127.0.0.1:{port}", f"sig{os.getpid()}{port}"
    command = [
        *(sys.executable, "-m", "tidee.cli", "server", "--endpoint", endpoint, "--server-id", server_id),
        *("--processes", "2", "--renderer", "tiny"),
    ]
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    out = OutputLines(proc)
    stop, served = threading.Event(), threading.Event()
    spec = EpisodeSpec(
        room_type="LivingRoom", seed=200, mess_index=0, resolution=cfg.resolution, max_steps=50
    )

    def client_loop() -> None:  # keeps the server busy; its errors once the server goes are expected
        try:
            with SimClient(endpoint=endpoint, server_id=server_id, timeout=30.0, connect_timeout=60.0) as c:
                while not stop.is_set():
                    c.reset(spec)
                    served.set()
                    for _ in range(5):
                        c.step(Action(ActionName.RotateLeft))
        except Exception:
            pass

    client = threading.Thread(target=client_loop, daemon=True)
    client.start()
    try:
        result: dict[str, Any] = {"signal": "SIGTERM", "delay_s": round(delay, 2), "serving": serving}
        if serving:
            result["started"] = served.wait(STARTUP_TIMEOUT_S)
        time.sleep(delay)
        result.update(end_try(proc, signal.SIGTERM, cfg.exit_timeout_s))
        result["ports_open"] = [port] if listening(port) else []
    finally:
        stop.set()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    client.join(1.0)  # a client still waiting for a server killed in its start-up gives up on its own
    text = out.text
    result["traceback"] = "Traceback" in text
    result["ok"] = _clean(result) and result.get("started", True)
    if not result["ok"]:
        result["output_tail"] = text[-3000:]
    return result


def _clean(r: dict[str, Any]) -> bool:
    return r["exit_code"] is not None and not r["orphans"] and not r["ports_open"] and not r["traceback"]


def signals_command(cfg: SignalsBenchConfig) -> str:
    return (
        f"tidee bench signals --tries {cfg.tries} --server-tries {cfg.server_tries} --seed {cfg.seed} "
        f"--resolution {cfg.resolution} --max-steps {cfg.max_steps} --exit-timeout {cfg.exit_timeout_s:g}"
    )


def run_signals_bench(cfg: SignalsBenchConfig, out_path: Path) -> dict[str, Any]:
    from tidee.server.bench_sim import spread

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # children inherit an ignored SIGINT
        signal.signal(signal.SIGINT, signal.default_int_handler)
    rng = random.Random(cfg.seed)
    plan = [("run", sig) for _ in range(cfg.tries) for sig in (signal.SIGTERM, signal.SIGINT)]
    plan += [("server", signal.SIGTERM)] * cfg.server_tries
    load_before, loads = os.getloadavg(), []
    start = time.monotonic()
    tries: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as log_dir:
        for i, (what, sig) in enumerate(plan):
            delay = rng.uniform(*(RUN_DELAY_S if what == "run" else SERVER_DELAY_S))
            if what == "run":
                r = run_try(cfg, sig, delay, log_dir)
            else:
                r = server_try(cfg, delay, serving=i % 2 == 1)
            tries.append({"try": i, "command": f"tidee {what}", **r})
            loads.append(os.getloadavg()[0])
            state = "ok" if r["ok"] else "NOT CLEAN"
            print(f"signals: try {i + 1}/{len(plan)} tidee {what} {r['signal']}: {state}", flush=True)
    groups = {}
    for what, name in (("run", "SIGTERM"), ("run", "SIGINT"), ("server", "SIGTERM")):
        mine = [t for t in tries if t["command"] == f"tidee {what}" and t["signal"] == name]
        if not mine:
            continue
        exited = [t for t in mine if t["exit_code"] is not None]
        groups[f"tidee {what} {name}"] = {
            "tries": len(mine),
            "started": sum(t.get("started", True) for t in mine),
            "exited": len(exited),
            "exit_codes": sorted({t["exit_code"] for t in exited}),
            "exit_s": spread([t["exit_s"] for t in exited] or [float("nan")]),
            "orphans": sum(len(t["orphans"]) for t in mine),
            "ports_left_open": sum(len(t["ports_open"]) for t in mine),
            "tracebacks": sum(t["traceback"] for t in mine),
            "clean": sum(t["ok"] for t in mine),
        }
    result = {
        "command": signals_command(cfg),
        "groups": groups,
        "targets_met": all(g["clean"] == g["tries"] for g in groups.values()),
        "wall_s": round(time.monotonic() - start, 1),
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        "load_1min_during": spread(loads),
        "machine": f"{platform.machine()} {os.cpu_count()} cores",
        "tries": tries,
    }
    _write(out_path, result)
    return result


def _write(out_path: Path, r: dict[str, Any]) -> None:
    from tidee.protocol.episode_log import write_atomic, write_json_atomic

    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(str(out_path), r)
    lines = [
        "# Signals benchmark (`tidee bench signals`)",
        "",
        f"`{r['command']}`: each try starts the command in a session of its own and sends one signal to "
        "that process alone after a drawn delay: `tidee run` once it runs (the viewer answering, the "
        "agent's frames on the feed), `tidee server` during its start-up (half the tries) or while a "
        "client resets and steps (the other half). After the exit timeout it counts the processes of "
        "the session still alive, its ports still open and the tracebacks printed. "
        f"{r['machine']}; {r['wall_s']} s; load average (1/5/15 min) "
        f"{' / '.join(f'{x:.2f}' for x in r['load_avg_before'])} before, "
        f"{' / '.join(f'{x:.2f}' for x in r['load_avg_after'])} after; 1-minute load during the run: "
        f"median {r['load_1min_during']['median']}, max {r['load_1min_during']['max']}.",
        "",
        "| command, signal | tries | running when signalled | exited | exit codes "
        "| exit s (median / p90 / max) | orphaned processes | ports left open | tracebacks | clean |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, g in r["groups"].items():
        e = g["exit_s"]
        lines.append(
            f"| {name} | {g['tries']} | {g['started']} | {g['exited']} | {g['exit_codes']} | "
            f"{e['median']} / {e['p90']} / {e['max']} | {g['orphans']} | {g['ports_left_open']} | "
            f"{g['tracebacks']} | {g['clean']} |"
        )
    bad = [t for t in r["tries"] if not t["ok"]]
    if bad:
        lines += ["", "Tries that were not clean:", ""]
        lines += [
            f"- try {t['try']} ({t['command']} {t['signal']}, delay {t['delay_s']} s): "
            f"exit {t['exit_code']}, orphans {list(t['orphans'].values())}, ports {t['ports_open']}, "
            f"traceback {t['traceback']}"
            for t in bad
        ]
    write_atomic(os.path.splitext(str(out_path))[0] + ".md", ("\n".join(lines) + "\n").encode())
