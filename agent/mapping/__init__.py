"""Mapping: 2D occupancy and semantic maps, a 3D voxel grid and the object memory.

The names below load their module on first use, so ``tidee.agent.mapping.memory`` or the
light ``tidee.agent.mapping.config`` do not pull in the mapper (OpenCV, SciPy).
"""

from __future__ import annotations

import importlib
from typing import Any

_HOME = {
    "GridSpec": "geometry",
    "pixel_rays": "geometry",
    "project": "geometry",
    "unproject": "geometry",
    "valid_depth": "geometry",
    "MapConfig": "config",
    "FREE": "maps",
    "OBSTACLE": "maps",
    "UNKNOWN": "maps",
    "SemanticMapper": "maps",
    "ObjectMemory": "memory",
    "TrackedObject": "memory",
}

__all__ = sorted(_HOME)


def __getattr__(name: str) -> Any:
    if name in _HOME:
        return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
