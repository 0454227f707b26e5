"""Jobs for ``tidee.batch.run_jobs`` in tests that run the batch runner in a subprocess (its workers
import this module: a job function must be importable by name)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any


def mark_and_sleep(job: tuple[str, int, float]) -> dict[str, Any]:
    """Leave a file named ``<n>-<pid>`` in the folder, then sleep: (folder, n, seconds)."""
    folder, n, seconds = job
    Path(folder, f"{n}-{os.getpid()}").touch()
    time.sleep(seconds)
    return {"n": n}
