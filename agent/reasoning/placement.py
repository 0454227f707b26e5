"""Where does an object belong? Ranked receptacle classes for a picked-up object.

``PlacementModel.predict`` returns receptacle types with probabilities, best first; the
policy tries them in order (first the ones already in its object memory). Learned twins
(Memex + rGCN, issue 6) implement the same protocol. RandomReceptacle is not a ranking:
the policy handles it by putting the object on the first receptacle it comes across.
"""

from __future__ import annotations

from typing import Protocol

from tidee.agent.classes import PLACEABLE_RECEPTACLES
from tidee.agent.mapping.memory import ObjectMemory, TrackedObject
from tidee.agent.reasoning.stats import PlacementStats


class PlacementModel(Protocol):
    name: str

    def predict(self, obj: TrackedObject, memory: ObjectMemory, room_type: str) -> list[tuple[str, float]]: ...


class CommonMemory:
    """The most common receptacles for the category in the training rooms (category only)."""

    name = "CommonMemory"

    def __init__(self, stats: PlacementStats | None = None) -> None:
        self.stats = stats or PlacementStats.load()

    def predict(self, obj: TrackedObject, memory: ObjectMemory, room_type: str) -> list[tuple[str, float]]:
        return [(r, p) for r, p in self.stats.ranked(obj.label) if r in PLACEABLE_RECEPTACLES or r == "Floor"]
