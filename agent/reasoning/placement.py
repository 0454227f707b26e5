"""Where does an object belong? Ranked receptacle classes for a picked-up object.

``PlacementModel.predict`` returns receptacle types with probabilities, best first; the
policy tries them in order (first the ones already in its object memory). Learned twins
(Memex + rGCN, ``rgcn.RGCNPlacement``) implement the same protocol. RandomReceptacle is not a ranking:
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


def make_placement(variant: str) -> tuple[PlacementModel | None, object | None]:
    """(placement model, visual search network) of an agent variant (``config.AGENT_VARIANTS``).

    RandomReceptacle and 3DSmntMap2Place rank nothing (placement None); the learned
    variants load the shipped weights (checksums verified)."""
    from tidee.agent.config import SEARCH_VARIANTS, check_variant_built

    check_variant_built(variant)
    searcher = None
    if variant in SEARCH_VARIANTS:
        from tidee.agent.reasoning.search_net import VisualSearch

        searcher = VisualSearch.load()
    if variant == "TIDEE":
        from tidee.agent.reasoning.rgcn import DEFAULT_WEIGHTS, RGCNPlacement

        return RGCNPlacement.load(DEFAULT_WEIGHTS), searcher
    if variant == "WithoutMemex":
        from tidee.agent.reasoning.rgcn import DEFAULT_WITHOUT_MEMEX, RGCNPlacement

        return RGCNPlacement.load(DEFAULT_WITHOUT_MEMEX), searcher
    if variant == "CommonMemory":
        return CommonMemory(), None
    return None, searcher
