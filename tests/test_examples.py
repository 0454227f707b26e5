"""Every script in examples/ runs to the end and prints what only a real run can print."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import REPO as SUPPORT_REPO

REPO = SUPPORT_REPO
EXAMPLES = sorted((REPO / "examples").glob("*.py"))

# Per example: patterns its output must contain (numbers the simulator or the agent produced).
EXPECTED: dict[str, list[str]] = {
    "01_step_simulator.py": [
        r"reset: rgb \(256, 256, 3\) uint8, depth \(256, 256\) float32",
        r"step 4: PutObject\s+failed: hands_empty",
        r"the mess-up moved [1-9]\d* of \d+ objects",
    ],
    "02_gym_env.py": [r"reset: rgb \(256, 256, 3\), depth \(256, 256\)", r"step 8: \w+\s+reward 0\.0"],
    "03_agent_episode.py": [
        r"TIDEE \(OOP detector 'language'\): \d+ steps",
        r"found [1-9]\d* of [1-9]\d* moved objects",
    ],
    "04_custom_placement.py": [
        r"registered placement models: TIDEE, .*NearestReceptacle",
        r"NearestReceptacle: \d+ steps",
        r"picked \w+ +found on",
    ],
    "05_custom_oop_detector.py": [
        r"registered OOP detectors: relation_stats, .*on_the_floor",
        r"OOP detector on_the_floor: \d+ steps",
        r"lay on Floor +moved=True +found=True",
    ],
    "06_vector_env.py": [
        r"reset: rgb \(2, 64, 64, 3\), rooms differ: True",
        r"steps \[3, 3\], truncated \[True, True\]\nsteps \[0, 0\]",  # the cap, then autoreset
    ],
}
SLOW = {"03_agent_episode.py"}  # the paper's agent with its learned models: ~25 s
NEEDS_TORCH = {"03_agent_episode.py"}  # the agent extra (pip install 'tidee[agent]')


def test_every_example_has_expected_output() -> None:
    assert EXAMPLES, "no examples found"
    assert sorted(p.name for p in EXAMPLES) == sorted(EXPECTED)


@pytest.mark.parametrize(
    "script", [pytest.param(p, id=p.name, marks=[pytest.mark.slow] * (p.name in SLOW)) for p in EXAMPLES]
)
def test_example_runs(script: Path) -> None:
    if script.name in NEEDS_TORCH:
        pytest.importorskip("torch")
    proc = subprocess.run(
        [sys.executable, str(script)], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, f"{script.name} failed:\n{proc.stdout}\n{proc.stderr[-3000:]}"
    for pattern in EXPECTED.get(script.name, []):
        assert re.search(pattern, proc.stdout), f"{script.name}: no {pattern!r} in its output:\n{proc.stdout}"
