"""``tidee bench episode``: the same episode in process and live, side by side.

Each repeat runs the configuration twice, in alternating order so that machine noise falls
on both: **in-process** (a fresh ``python`` process running ``EpisodeRunner`` over the
in-process transport, as ``tidee eval tidy --workers 1`` does) and **live** (``tidee run``:
server, agent and viewer as three processes on embedded Zenoh, the viewer subscribed to the
agent's telemetry; optionally a headless Chromium showing the viewer page). Both report the
agent's own episode wall time (reset to end, from the episode record) and the steps; the
live run also its whole command time (process start-up and model load included) and the CPU
seconds each of its processes used (agent, server, simulator, viewer: who competes for the
cores), and with a browser the CPU seconds of its main, GPU and renderer processes. Writes
JSON and Markdown with median, p90 and max, the live / in-process ratio of the medians, and
the load average before and after.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

_INPROC = """
import json, sys, time
t0 = time.perf_counter()
from tidee.agent.config import AgentConfig
from tidee.agent.runner import EpisodeRunner
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.transport import InProcessTransport
from tidee.threads import threads_per_process, use_threads
use_threads(threads_per_process(1))
a = json.loads(sys.argv[1])
with InProcessTransport(renderer=a["renderer"]) as transport:
    drawn_by = transport.episode.renderer
    runner = EpisodeRunner(AgentConfig(variant=a["variant"]), transport, session="bench")
    res = runner.run(EpisodeSpec(room_type=a["room_type"], seed=a["seed"], mess_index=a["mess_index"],
                                 max_steps=a["max_steps"]))
print(json.dumps({"steps": res.steps, "episode_s": res.wall_s, "command_s": time.perf_counter() - t0,
                  "put_away": res.objects_fixed, "renderer": drawn_by}))
"""


# Which process of ``tidee run`` a command line belongs to (the first match names it).
ROLES = (
    ("agent", " agent "),
    ("viewer", " viewer "),
    ("server", " server "),
    ("simulator", "multiprocessing.spawn"),
)
# Which process of a headless Chromium a command line belongs to (the rest: its main process).
BROWSER_ROLES = (
    ("gpu", "--type=gpu-process"),
    ("renderer", "--type=renderer"),
)


class CpuSampler(threading.Thread):
    """The CPU seconds (user + system) of a process tree, by role (``roles``, the first mark
    found in a command line names it; others: ``rest``), sampled every ``period`` s while the
    tree runs: a process's last sample counts."""

    def __init__(
        self, root: int, period: float = 0.5, roles: tuple[tuple[str, str], ...] = ROLES, rest: str = "other"
    ) -> None:
        super().__init__(daemon=True)
        self.root, self.period, self.roles, self.rest = root, period, roles, rest
        self._last: dict[int, tuple[str, float]] = {}
        self._finished = threading.Event()
        self._tick = os.sysconf("SC_CLK_TCK")
        from tidee.server.bench_soak import descendants  # imported now, not at the first sample

        self._descendants = descendants

    def sample(self) -> None:
        for pid in [self.root, *self._descendants(self.root)]:
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            role = next((r for r, mark in self.roles if mark in f" {cmd} "), self.rest)
            if not cmd.strip() and pid in self._last:  # exited, not yet reaped: no command line left
                role = self._last[pid][0]
            self._last[pid] = (role, (int(fields[11]) + int(fields[12])) / self._tick)

    def run(self) -> None:
        while not self._finished.is_set():
            self.sample()
            self._finished.wait(self.period)

    def stop(self) -> dict[str, float]:
        """Stop sampling; the CPU seconds by role."""
        self._finished.set()
        self.join(timeout=5)
        out: dict[str, float] = {}
        for role, cpu in self._last.values():
            out[role] = round(out.get(role, 0.0) + cpu, 2)
        return out


def _inprocess(args: dict[str, Any]) -> dict[str, Any]:
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-c", _INPROC, json.dumps(args)], capture_output=True, text=True, timeout=1800
    )
    if r.returncode != 0:
        raise RuntimeError(f"in-process episode failed: {r.stderr[-1500:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["command_s"] = time.perf_counter() - t0
    return out


def live_argv(args: dict[str, Any], port: int, logs: str) -> list[str]:
    """The ``tidee run`` command of a live run: the configuration and renderer of ``args``."""
    return [
        sys.executable,
        "-m",
        "tidee.cli",
        "run",
        "--variant",
        args["variant"],
        "--room-type",
        args["room_type"],
        "--seed",
        str(args["seed"]),
        "--mess-index",
        str(args["mess_index"]),
        "--max-steps",
        str(args["max_steps"]),
        "--renderer",
        args["renderer"],
        "--linger",
        "0",
        "--port",
        str(port),
        "--log-dir",
        logs,
    ]


def _live(args: dict[str, Any], browser: bool) -> dict[str, Any]:
    from tidee.launch import free_port

    port = free_port()
    with tempfile.TemporaryDirectory(prefix="tidee-bench-episode-") as logs:
        cmd = live_argv(args, port, logs)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        sampler = CpuSampler(proc.pid)
        sampler.start()
        chromium = None
        browser_sampler: CpuSampler | None = None
        try:
            if browser:
                from tidee.viewer.browser import HeadlessChromium, find_chromium

                if find_chromium() is None:
                    raise RuntimeError("--browser: no chromium found")
                chromium = HeadlessChromium()
                # its own tree, apart from tidee run's: the GPU process draws the 3D panel (in software here)
                browser_sampler = CpuSampler(chromium.pids()[0], roles=BROWSER_ROLES, rest="main")
                browser_sampler.start()
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:
                    try:
                        chromium.navigate(f"http://127.0.0.1:{port}", timeout=10)
                        break
                    except Exception:  # the viewer is not listening yet
                        time.sleep(0.5)
            rc = proc.wait(timeout=1800)
        finally:
            cpu = sampler.stop()
            if browser_sampler is not None:
                cpu |= {f"browser_{role}": v for role, v in browser_sampler.stop().items()}
            if chromium is not None:
                chromium.close()
            if proc.poll() is None:
                proc.kill()
        command_s = time.perf_counter() - t0
        if rc != 0:
            raise RuntimeError(f"tidee run exited {rc}")
        name = f"{args['room_type']}_{args['seed']}_mess{args['mess_index']}"
        summary = json.loads((Path(logs) / name / "summary.json").read_text())
    return {
        "steps": summary["steps"],
        "episode_s": summary["wall_s"],
        "command_s": command_s,
        "put_away": summary["objects_fixed"],
        "cpu_s": cpu,
    }


def run_episode_bench(
    out: str,
    repeats: int = 3,
    room_type: str = "LivingRoom",
    seed: int = 200,
    mess_index: int = 0,
    variant: str = "TIDEE",
    max_steps: int = 1000,
    browser: bool = False,
    renderer: str = "tiny",
) -> dict[str, Any]:
    """``renderer``: tiny or egl, the same for both sides (auto could resolve differently in the
    live server's simulator process)."""
    from tidee.protocol.vocab import RENDERERS
    from tidee.server.bench_sim import spread, write_report

    named = [r for r in RENDERERS if r != "auto"]
    if renderer not in named:
        raise ValueError(f"--renderer must be {' or '.join(named)} (both sides draw alike), got {renderer!r}")
    args = {
        "room_type": room_type,
        "seed": seed,
        "mess_index": mess_index,
        "variant": variant,
        "max_steps": max_steps,
        "renderer": renderer,
    }
    load0 = os.getloadavg()[0]
    runs: dict[str, list[dict[str, Any]]] = {"inprocess": [], "live": []}
    for k in range(repeats):
        order = ("inprocess", "live") if k % 2 == 0 else ("live", "inprocess")
        for mode in order:
            runs[mode].append(_inprocess(args) if mode == "inprocess" else _live(args, browser))
    result: dict[str, Any] = {
        "configuration": f"{room_type} seed {seed} mess {mess_index}, {variant}, max {max_steps} steps",
        "repeats": repeats,
        "browser_attached": browser,
        "renderer": sorted({r["renderer"] for r in runs["inprocess"]}),  # what drew the in-process frames
        "steps": {m: [r["steps"] for r in rs] for m, rs in runs.items()},
    }
    for mode, rs in runs.items():
        result[f"{mode}_episode_s"] = spread([r["episode_s"] for r in rs])
        result[f"{mode}_command_s"] = spread([r["command_s"] for r in rs])
    for role in sorted({r for run in runs["live"] for r in run["cpu_s"]}):
        # where a live run's CPU went (samples every 0.5 s: the last half second may be missed)
        result[f"live_cpu_s_{role}"] = spread([run["cpu_s"].get(role, 0.0) for run in runs["live"]])
    result["live_over_inprocess_episode"] = round(
        result["live_episode_s"]["median"] / result["inprocess_episode_s"]["median"], 3
    )
    result["live_over_inprocess_per_step"] = round(
        float(np.median([r["episode_s"] / r["steps"] for r in runs["live"]]))
        / float(np.median([r["episode_s"] / r["steps"] for r in runs["inprocess"]])),
        3,
    )
    result["machine"] = f"{platform.machine()} {os.cpu_count()} cores"
    result["load_avg_1m_before_after"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    result["command"] = (
        f"tidee bench episode --repeats {repeats} --room-type {room_type} --seed {seed} "
        f"--mess-index {mess_index} --variant {variant} --max-steps {max_steps} --renderer {renderer}"
        + (" --browser" if browser else "")
        + f" --out {out}"
    )
    write_report(out, result, "Episode benchmark (`tidee bench episode`): in-process vs live (`tidee run`)")
    return result
