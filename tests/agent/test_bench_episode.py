"""The episode benchmark's CPU accounting: who in a process tree used the cores."""

from __future__ import annotations

import subprocess
import sys

from tidee.agent.bench_episode import CpuSampler

BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6:\n    pass\n"


def test_the_cpu_sampler_charges_a_grandchild_to_its_role() -> None:
    # root (other) -> child "agent" that burns 0.6 s of CPU; the root itself only waits
    spawn = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {BURN!r}, 'agent'])"
    root = subprocess.Popen([sys.executable, "-c", spawn])
    sampler = CpuSampler(root.pid, period=0.05)
    sampler.start()
    root.wait(timeout=60)
    cpu = sampler.stop()
    assert 0.4 <= cpu["agent"] <= 1.5, cpu
    assert cpu.get("other", 0.0) < cpu["agent"], cpu


def test_a_browsers_processes_are_told_apart_by_their_type() -> None:
    from tidee.agent.bench_episode import BROWSER_ROLES

    spawn = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {BURN!r}, '--type=gpu-process'])"
    root = subprocess.Popen([sys.executable, "-c", spawn])
    sampler = CpuSampler(root.pid, period=0.05, roles=BROWSER_ROLES, rest="main")
    sampler.start()
    root.wait(timeout=60)
    cpu = sampler.stop()
    assert 0.4 <= cpu["gpu"] <= 1.5, cpu
    assert set(cpu) <= {"gpu", "main"} and cpu.get("main", 0.0) < cpu["gpu"], cpu


def test_a_child_that_exited_but_is_not_yet_reaped_keeps_its_role() -> None:
    # An exited child lingers until its parent waits for it, with an empty command line: its
    # CPU seconds still belong to the agent, not to "other".
    spawn = (
        "import subprocess, sys, time\n"
        f"p = subprocess.Popen([sys.executable, '-c', {BURN!r}, 'agent'])\n"
        "import os\n"
        "os.waitid(os.P_PID, p.pid, os.WEXITED | os.WNOWAIT)\n"  # exited; not reaped yet
        "time.sleep(0.5)\n"
        "p.wait()\n"
    )
    root = subprocess.Popen([sys.executable, "-c", spawn])
    sampler = CpuSampler(root.pid, period=0.05)
    sampler.start()
    root.wait(timeout=60)
    cpu = sampler.stop()
    assert 0.4 <= cpu.get("agent", 0.0) <= 1.5, cpu
    assert cpu.get("other", 0.0) < 0.4, cpu


def test_both_sides_draw_with_the_renderer_asked_for(monkeypatch, tmp_path) -> None:
    import pytest

    from tidee.agent import bench_episode

    seen: list[tuple[str, str]] = []

    def fake(mode: str):
        def run(args, *rest):
            seen.append((mode, args["renderer"]))
            out = {
                "steps": 10,
                "episode_s": 1.0,
                "command_s": 2.0,
                "put_away": 0,
                "renderer": args["renderer"],
            }
            return out | ({"cpu_s": {"agent": 1.0}} if mode == "live" else {})

        return run

    monkeypatch.setattr(bench_episode, "_inprocess", fake("inprocess"))
    monkeypatch.setattr(bench_episode, "_live", fake("live"))
    result = bench_episode.run_episode_bench(str(tmp_path / "episode.json"), repeats=2, renderer="egl")
    assert sorted(seen) == [("inprocess", "egl")] * 2 + [("live", "egl")] * 2
    assert result["renderer"] == ["egl"] and "--renderer egl" in result["command"]
    argv = bench_episode.live_argv(
        {
            **dict.fromkeys(("variant", "room_type"), "x"),
            "seed": 1,
            "mess_index": 0,
            "max_steps": 5,
            "renderer": "egl",
        },
        8080,
        "/tmp/logs",
    )
    assert argv[argv.index("--renderer") + 1] == "egl"
    # auto could resolve apart in the two processes
    with pytest.raises(ValueError, match="both sides draw alike"):
        bench_episode.run_episode_bench(str(tmp_path / "x.json"), repeats=1, renderer="auto")
