"""How many CPU threads each tidee process may use: decided here, once, for every command.

Torch (OpenMP) and BLAS default to one thread per core in every process. When a command runs
several busy processes (``tidee run``: server + agent + viewer; ``tidee eval`` with N
workers), those threads outnumber the cores, and OpenMP's spinning threads then stall each
other: on 2 cores a one-episode eval took 6 times longer with another process on the second
core. The rule: a process gets ``cores // busy processes`` threads, at least one.

Call :func:`use_threads` before the process does any numeric work (it also sets the
environment variables that a child process or a late ``import torch`` reads, and limits the
OpenMP and BLAS pools already loaded: a spawned batch worker has imported numpy, and so started
OpenBLAS with a thread per core, before it is told its share).
"""

from __future__ import annotations

import os
import sys

_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def available_cores() -> int:
    """Cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def threads_per_process(processes: int, cores: int | None = None) -> int:
    """Threads for each of ``processes`` busy processes sharing ``cores`` (default: available)."""
    if processes < 1:
        raise ValueError(f"processes must be >= 1, got {processes}")
    cores = available_cores() if cores is None else cores
    return max(1, cores // processes)


def use_threads(n: int) -> int:
    """Limit this process (and children it starts) to ``n`` compute threads; returns ``n``."""
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    for var in _ENV_VARS:
        os.environ[var] = str(n)
    torch = sys.modules.get("torch")
    if torch is not None:  # imported already; otherwise torch reads OMP_NUM_THREADS when imported
        torch.set_num_threads(n)
    from threadpoolctl import threadpool_limits

    threadpool_limits(n)  # the native pools loaded already (numpy's OpenBLAS, torch's OpenMP)
    return n


__all__ = ["available_cores", "threads_per_process", "use_threads"]
