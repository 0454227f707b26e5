"""One place decides the threads of every process: never more busy threads than cores."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tidee.threads import threads_per_process, use_threads


def test_threads_are_the_cores_shared_among_busy_processes() -> None:
    assert threads_per_process(1, cores=2) == 2
    assert threads_per_process(2, cores=2) == 1
    assert threads_per_process(3, cores=2) == 1  # never zero
    assert threads_per_process(2, cores=16) == 8
    with pytest.raises(ValueError, match="processes must be >= 1"):
        threads_per_process(0)


def test_use_threads_reaches_torch_whether_imported_before_or_after() -> None:
    code = (
        "from tidee.threads import use_threads\n"
        "use_threads(1)\n"
        "import os, torch\n"
        "print(torch.get_num_threads(), os.environ['OMP_NUM_THREADS'])\n"
        "use_threads(2); print(torch.get_num_threads())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["1", "1", "2"]
    with pytest.raises(ValueError):
        use_threads(0)


def test_use_threads_limits_the_blas_pool_numpy_started_before() -> None:
    """A spawned batch worker imports numpy (unpickling its job function) before it is set up."""
    code = (
        "import numpy, threadpoolctl\n"
        "from tidee.threads import use_threads\n"
        "use_threads(1)\n"
        "blas = [p for p in threadpoolctl.threadpool_info() if p['user_api'] == 'blas']\n"
        "print(sorted({p['num_threads'] for p in blas}))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[1]"


def test_tidee_run_gives_the_agent_the_cores_the_server_leaves(monkeypatch) -> None:
    import tidee.launch
    from tidee import cli

    monkeypatch.setattr("tidee.threads.available_cores", lambda: 2)
    seen = {}
    monkeypatch.setattr(tidee.launch, "run_all", lambda cfg: seen.setdefault("cfg", cfg) and 0)
    args = cli.build_parser().parse_args(["run"])
    args.func(args)
    fwd = seen["cfg"].agent_args
    assert fwd[fwd.index("--threads") + 1] == "1"
    seen.clear()
    args = cli.build_parser().parse_args(["run", "--threads", "2"])
    args.func(args)
    fwd = seen["cfg"].agent_args
    assert fwd[fwd.index("--threads") + 1] == "2"
