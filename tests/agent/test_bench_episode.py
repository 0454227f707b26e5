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
