"""Helpers the tests share (no tests here): fakes, scene fixtures, loopback servers."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]  # the checkout: tests/support/__init__.py -> ../..
