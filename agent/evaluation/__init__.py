"""Evaluation of tidy episodes: a simulated placement judge, metrics and the written report.

* :mod:`.judge`: :func:`judge_score`, :func:`plausible`, :func:`prefer`,
  :func:`reference_records` (AI2THORPlacement / MessyPlacement rows).
* :mod:`.report`: :func:`variant_metrics`, :func:`pairwise_table`, :func:`write_report`,
  :func:`with_references`.
"""

from __future__ import annotations

import importlib
from typing import Any

_HOME = {
    "AI2THOR_PLACEMENT": "judge",
    "MESSY_PLACEMENT": "judge",
    "REFERENCE_VARIANTS": "judge",
    "judge_score": "judge",
    "plausible": "judge",
    "prefer": "judge",
    "reference_records": "judge",
    "OBJECT_KEYS": "report",
    "RECORD_KEYS": "report",
    "config_key": "report",
    "format_markdown": "report",
    "pairwise_table": "report",
    "validate_records": "report",
    "variant_metrics": "report",
    "with_references": "report",
    "write_report": "report",
}
__all__ = sorted(_HOME)


def __getattr__(name: str) -> Any:
    """The names above load their module on first use (the report needs SciPy; configs do not)."""
    if name in _HOME:
        return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
