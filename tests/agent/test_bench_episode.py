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
