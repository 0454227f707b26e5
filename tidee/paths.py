"""Where default outputs go: folders of the tidee checkout, never the working directory.

``tidee bench sim`` writes ``<checkout>/bench/sim.json`` wherever it is started from; an
explicit ``--out`` always wins.
"""

from __future__ import annotations

from pathlib import Path

PROJECT_DIR = Path(__file__).resolve().parent.parent  # holds agent/, server/, bench/, runs/ ...
BENCH_DIR = PROJECT_DIR / "bench"
RUNS_DIR = PROJECT_DIR / "runs"


def in_checkout(path: str | Path) -> str:
    """``path`` relative to the checkout when it lies inside it (as a user types it there, and
    not this machine's absolute path), else as given."""
    try:
        return Path(path).resolve().relative_to(PROJECT_DIR).as_posix()
    except ValueError:
        return str(path)


def bench_out(out: str | Path | None, name: str) -> Path:
    """``out``, else ``bench/<name>`` in the checkout."""
    return Path(out) if out is not None else BENCH_DIR / name
