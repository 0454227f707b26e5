"""The agent's semantic mapping: geometry, 2D/3D maps and the object memory (start frame, metres)."""

from tidee.agent.mapping.geometry import GridSpec, pixel_rays, project, unproject, valid_depth
from tidee.agent.mapping.maps import FREE, OBSTACLE, UNKNOWN, MapConfig, SemanticMapper
from tidee.agent.mapping.memory import ObjectMemory, TrackedObject

__all__ = [
    "FREE",
    "OBSTACLE",
    "UNKNOWN",
    "GridSpec",
    "MapConfig",
    "ObjectMemory",
    "SemanticMapper",
    "TrackedObject",
    "pixel_rays",
    "project",
    "unproject",
    "valid_depth",
]
