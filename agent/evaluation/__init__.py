"""Evaluation of tidy episodes: a simulated placement judge, metrics and the written report.

* :mod:`.judge`: :func:`judge_score`, :func:`plausible`, :func:`prefer`,
  :func:`reference_records` (AI2THORPlacement / MessyPlacement rows).
* :mod:`.report`: :func:`variant_metrics`, :func:`pairwise_table`, :func:`write_report`,
  :func:`with_references`.
"""

from __future__ import annotations

from .judge import (
    AI2THOR_PLACEMENT,
    MESSY_PLACEMENT,
    REFERENCE_VARIANTS,
    judge_score,
    plausible,
    prefer,
    reference_records,
)
from .report import (
    OBJECT_KEYS,
    RECORD_KEYS,
    config_key,
    format_markdown,
    pairwise_table,
    validate_records,
    variant_metrics,
    with_references,
    write_report,
)

__all__ = [
    "AI2THOR_PLACEMENT",
    "MESSY_PLACEMENT",
    "REFERENCE_VARIANTS",
    "judge_score",
    "plausible",
    "prefer",
    "reference_records",
    "OBJECT_KEYS",
    "RECORD_KEYS",
    "config_key",
    "format_markdown",
    "pairwise_table",
    "validate_records",
    "variant_metrics",
    "with_references",
    "write_report",
]
