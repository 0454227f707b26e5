"""Where default outputs go: folders of the tidee checkout, never the working directory.

``tidee bench sim`` writes ``<checkout>/bench/sim.json`` wherever it is started from; an
explicit ``--out`` always wins.
"""

from __future__ import annotations

from pathlib import Path

PROJECT_DIR = Path(__file__).resolve().parent.parent  # holds agent/, server/, bench/, runs/ ...
BENCH_DIR = PROJECT_DIR / "bench"
RUNS_DIR = PROJECT_DIR / "runs"


def bench_out(out: str | Path | None, name: str) -> Path:
    """``out``, else ``bench/<name>`` in the checkout."""
    return Path(out) if out is not None else BENCH_DIR / name
