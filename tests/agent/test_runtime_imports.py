"""The agent at run time loads its models and nothing that generates data, trains or parses a
command line: each model family keeps those roles in their own modules."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

# Role modules the runtime must not import (see docs/architecture.md, "role files").
FORBIDDEN = re.compile(
    r"^tidee\..*\.(train|train_\w+|data|dataset|eval|instruct_eval|commands|cli)$|^tidee\.cli$"
)

PROBE = """
import json, sys
from tidee.agent.config import AgentConfig
from tidee.agent.runner import AgentModels, EpisodeRunner
import tidee.agent.process
for kw in ({CONFIGS}):
    AgentModels.load(AgentConfig(**kw))
print(json.dumps({"modules": sorted(m for m in sys.modules if m.startswith("tidee")),
                  "argparse": "argparse" in sys.modules, "torch": "torch" in sys.modules}))
"""

CONFIGS = [
    {
        "variant": "TIDEE",
        "perception": "learned",
        "depth": "estimated",
    },  # detector, depth, rGCN+Memex, search
    {"variant": "WithoutMemex", "perception": "oracle", "oop": "language"},
    {"variant": "3DSmntMap2Place", "perception": "learned", "oop": "fused"},
]


@pytest.mark.timeout(240)
def test_the_agent_runtime_imports_no_training_data_or_cli_module() -> None:
    code = PROBE.replace("{CONFIGS}", repr(tuple(CONFIGS)))
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=230, check=True
    )
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["torch"], "the probe should have loaded the learned models"
    bad = [m for m in got["modules"] if FORBIDDEN.match(m)]
    assert not bad, f"the runtime imported role modules it does not need: {bad}"
    assert not any(m.endswith(".commands") for m in got["modules"])


def test_building_the_command_line_loads_no_model_library() -> None:
    code = (
        "import sys; from tidee.cli import build_parser; build_parser(); "
        "heavy = ('torch', 'scipy', 'cv2', 'pybullet', 'viser', 'zenoh'); "
        "print(sorted(m for m in heavy if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout
