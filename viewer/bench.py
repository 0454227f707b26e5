"""``run_viewer_bench``: does the viewer keep up, does it slow the agent, does it stay flat?

Three runs of the same synthetic agent (``tidee.viewer.synthetic``, its own process,
publishing ``steps`` steps of telemetry as fast as ``work_ms`` of CPU per step allows):

1. alone, no viewer: the agent's baseline steps/s;
2. with a viewer attached (this process): viewer updates/s, the agent's steps/s;
3. the same with a headless Chromium showing the page (when one is installed): the whole
   pipeline, browser included, on the same machine.

The viewer's resident memory is sampled through runs 2-3 (``VmRSS``); ``rss_growth_mb``
is the change from a quarter of the way through a run to its end (warm-up excluded).
"""

from __future__ import annotations

import json
import os
import platform
import socket
import subprocess
import sys
import threading
import time
from typing import Any

from tidee.viewer.app import ViewerConfig, run_viewer
from tidee.viewer.browser import HeadlessChromium, find_chromium


def _rss_mb() -> float:
    """This process's resident set size in MiB (Linux ``/proc``; 0 elsewhere)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _run_agent(
    endpoint: str, steps: int, work_ms: float, wait_viewer: float, timeout: float
) -> dict[str, Any]:
    cmd = [
        sys.executable,
        "-m",
        "tidee.viewer.synthetic",
        "--endpoint",
        endpoint,
        "--session",
        "bench",
        "--steps",
        str(steps),
        "--rate",
        "0",
        "--work-ms",
        str(work_ms),
        "--wait-viewer",
        str(wait_viewer),
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"the synthetic agent failed ({out.returncode}): {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _chromium_cpu_s(chromium: HeadlessChromium | None) -> float:
    """CPU seconds used so far by the browser's process tree (Linux ``/proc``; 0 elsewhere)."""
    if chromium is None:
        return 0.0
    total, tick = 0.0, os.sysconf("SC_CLK_TCK")
    for pid in chromium.pids():
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick  # utime + stime
        except (OSError, IndexError, ValueError):
            pass
    return total


def _attached_run(
    endpoint: str, steps: int, work_ms: float, timeout: float, browser: bool, rate_hz: float
) -> dict[str, Any]:
    handle = run_viewer(ViewerConfig(endpoint=endpoint, port=0, session="bench", rate_hz=rate_hz))
    chromium = None
    try:
        if browser:
            chromium = HeadlessChromium()
            chromium.navigate(handle.url)
            time.sleep(3.0)  # the page loads and its WebGL context starts
        stats = handle.app.stats
        samples: list[tuple[float, float, int]] = []  # (time, rss MiB, updates)
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                samples.append((time.monotonic(), _rss_mb(), stats.updates))
                done.wait(0.5)

        sampler = threading.Thread(target=sample, daemon=True)
        rss_before = _rss_mb()
        sampler.start()
        t0, updates0, cpu0 = time.monotonic(), stats.updates, _chromium_cpu_s(chromium)
        agent = _run_agent(endpoint, steps, work_ms, wait_viewer=20.0, timeout=timeout)
        elapsed = time.monotonic() - t0
        browser_cpu = _chromium_cpu_s(chromium) - cpu0
        done.set()
        sampler.join()
        updates = stats.updates - updates0
        active = [s for s in samples if s[2] > updates0]
        span = (active[-1][0] - active[0][0]) if len(active) > 1 else elapsed
        quarter = active[len(active) // 4] if active else (0.0, rss_before, 0)
        return {
            "agent_steps_per_s": agent["steps_per_s"],
            "viewer_updates": updates,
            "viewer_updates_per_s": round((active[-1][2] - active[0][2]) / span, 2)
            if len(active) > 1
            else 0.0,
            "viewer_last_step": stats.last_step,
            "rss_before_mb": round(rss_before, 1),
            "rss_after_mb": round(_rss_mb(), 1),
            "rss_growth_mb": round((active[-1][1] if active else rss_before) - quarter[1], 1),
            "rss_max_mb": round(max((s[1] for s in samples), default=rss_before), 1),
            "viewer_matched": agent["viewer_matched"],
            "browser_cpu_share": round(browser_cpu / elapsed, 3),  # cores the browser kept busy
        }
    finally:
        if chromium is not None:
            chromium.close()
        handle.stop()


def run_viewer_bench(
    steps: int,
    out_json: str,
    work_ms: float = 30.0,
    browser: bool | None = None,
    rate_hz: float = ViewerConfig.rate_hz,
) -> dict[str, Any]:
    """Measure, write ``out_json`` and a Markdown table beside it, and return the figures."""
    from tidee.server.bench_sim import write_report

    if steps < 10:
        raise ValueError(f"steps must be >= 10 for a meaningful rate, got {steps}")
    browser = find_chromium() is not None if browser is None else browser
    timeout = 120.0 + steps * (work_ms / 1000.0 + 0.05) * 4
    alone = _run_agent(_free_endpoint(), steps, work_ms, wait_viewer=0.0, timeout=timeout)
    attached = _attached_run(_free_endpoint(), steps, work_ms, timeout, browser=False, rate_hz=rate_hz)
    result: dict[str, Any] = {
        "steps": steps,
        "agent_work_ms_per_step": work_ms,
        "viewer_rate_hz": rate_hz,
        "agent_steps_per_s_alone": alone["steps_per_s"],
        "agent_steps_per_s_with_viewer": attached["agent_steps_per_s"],
        "agent_slowdown_pct_with_viewer": round(
            100 * (1 - attached["agent_steps_per_s"] / alone["steps_per_s"]), 1
        ),
        "viewer_updates_per_s": attached["viewer_updates_per_s"],
        "viewer_updates": attached["viewer_updates"],
        "viewer_rss_before_mb": attached["rss_before_mb"],
        "viewer_rss_after_mb": attached["rss_after_mb"],
        "viewer_rss_growth_mb": attached["rss_growth_mb"],
    }
    if browser:
        with_browser = _attached_run(_free_endpoint(), steps, work_ms, timeout, browser=True, rate_hz=rate_hz)
        result.update(
            {
                "agent_steps_per_s_with_viewer_and_browser": with_browser["agent_steps_per_s"],
                "agent_slowdown_pct_with_viewer_and_browser": round(
                    100 * (1 - with_browser["agent_steps_per_s"] / alone["steps_per_s"]), 1
                ),
                "viewer_updates_per_s_with_browser": with_browser["viewer_updates_per_s"],
                "viewer_rss_growth_mb_with_browser": with_browser["rss_growth_mb"],
                "browser_cpu_share": with_browser["browser_cpu_share"],
            }
        )
    result["machine"] = f"{platform.machine()} {os.cpu_count()} cores"
    write_report(out_json, result, "Viewer benchmark (`tidee.viewer.bench`)")
    return result


def main(argv: list[str] | None = None) -> int:
    import argparse

    from tidee.options import add_options, from_args
    from tidee.paths import bench_out
    from tidee.viewer.config import ViewerBenchConfig

    p = argparse.ArgumentParser(
        prog="python -m tidee.viewer.bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_options(p, ViewerBenchConfig)
    cfg = from_args(ViewerBenchConfig, p.parse_args(argv))
    result = run_viewer_bench(
        cfg.steps,
        str(bench_out(cfg.out, "viewer.json")),
        work_ms=cfg.work_ms,
        browser=False if cfg.no_browser else None,
        rate_hz=cfg.rate_hz,
    )
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
