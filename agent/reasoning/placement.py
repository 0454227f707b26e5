"""Where does an object belong? Ranked receptacle classes for a picked-up object.

``PlacementModel.predict`` returns receptacle types with probabilities, best first; the
policy tries them in order (first the ones already in its object memory). Learned twins
(Memex + rGCN, ``rgcn.model.RGCNPlacement``) implement the same protocol. RandomReceptacle is not a ranking:
the policy handles it by putting the object on the first receptacle it comes across.

Each agent variant (``AgentConfig.variant``) is one entry of ``PLACEMENT_MODELS``: a
factory of its placement model and whether it loads the visual search network. Add your
own with the decorator; ``AgentConfig(variant="MyPlacement")`` then selects it::

    @register_placement("MyPlacement")
    class MyPlacement:
        name = "MyPlacement"

        def predict(self, obj, memory, room_type):
            return [("DiningTable", 1.0)]
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from tidee.agent.classes import PLACEABLE_RECEPTACLES
from tidee.agent.mapping.memory import ObjectMemory, TrackedObject
from tidee.agent.reasoning.stats import PlacementStats


class PlacementModel(Protocol):
    name: str

    def predict(
        self, obj: TrackedObject, memory: ObjectMemory, room_type: str
    ) -> list[tuple[str, float]]: ...


PlacementFactory = Callable[[], PlacementModel | None]
F = TypeVar("F", bound=Callable[..., Any])


@dataclass(frozen=True)
class PlacementEntry:
    """One agent variant: how to build its placement model and whether it searches for
    receptacles not in memory with the visual search network (otherwise with unexplored /
    random goals). A factory that returns None ranks nothing: the policy puts the object on
    the first receptacle it finds (RandomReceptacle; 3DSmntMap2Place has its own branch)."""

    factory: PlacementFactory
    search: bool = False


PLACEMENT_MODELS: dict[str, PlacementEntry] = {}
"""Agent variants by name, in registration order; the paper's five are registered below."""


def register_placement(name: str, *, search: bool = False) -> Callable[[F], F]:
    """Decorator: register a placement model class (or a no-argument factory) as variant ``name``."""

    def register(factory: F) -> F:
        if name in PLACEMENT_MODELS:
            raise ValueError(
                f"placement model {name!r} is already registered "
                f"({PLACEMENT_MODELS[name].factory!r}); register yours under another name"
            )
        PLACEMENT_MODELS[name] = PlacementEntry(factory, search)
        return factory

    return register


def check_variant(variant: str) -> PlacementEntry:
    """The registry entry of ``variant``; a ValueError naming the registered ones if there is none."""
    try:
        return PLACEMENT_MODELS[variant]
    except KeyError:
        raise ValueError(
            f"unknown variant {variant!r}; registered: {', '.join(PLACEMENT_MODELS)} "
            f"(register_placement adds one)"
        ) from None


def make_placement(variant: str) -> tuple[PlacementModel | None, object | None]:
    """(placement model, visual search network) of a registered agent variant.

    RandomReceptacle and 3DSmntMap2Place rank nothing (placement None); the learned
    variants load the shipped weights (checksums verified)."""
    entry = check_variant(variant)
    searcher = None
    if entry.search:
        from tidee.agent.reasoning.search.model import VisualSearch

        searcher = VisualSearch.load()
    return entry.factory(), searcher


# ---------------------------------------------------------------- the paper's variants (Table 1)
@register_placement("TIDEE", search=True)
def _tidee() -> PlacementModel:
    """Memex + rGCN."""
    from tidee.agent.reasoning.rgcn.model import DEFAULT_WEIGHTS, RGCNPlacement

    return RGCNPlacement.load(DEFAULT_WEIGHTS)


@register_placement("WithoutMemex", search=True)
def _without_memex() -> PlacementModel:
    """rGCN on the scene graph only."""
    from tidee.agent.reasoning.rgcn.model import DEFAULT_WITHOUT_MEMEX, RGCNPlacement

    return RGCNPlacement.load(DEFAULT_WITHOUT_MEMEX)


@register_placement("3DSmntMap2Place", search=True)
def _semantic_map_to_place() -> None:
    """No ranking: the search network, conditioned on the object's own class, proposes places
    (``TidyPolicy.put_near_proposals``)."""
    return None


@register_placement("CommonMemory")
class CommonMemory:
    """The most common receptacles for the category in the training rooms (category only)."""

    name = "CommonMemory"

    def __init__(self, stats: PlacementStats | None = None) -> None:
        self.stats = stats or PlacementStats.load()

    def predict(self, obj: TrackedObject, memory: ObjectMemory, room_type: str) -> list[tuple[str, float]]:
        return [(r, p) for r, p in self.stats.ranked(obj.label) if r in PLACEABLE_RECEPTACLES or r == "Floor"]


@register_placement("RandomReceptacle")
def _random_receptacle() -> None:
    """No ranking: the object goes on the first receptacle found (``TidyPolicy.put_on_first_found``)."""
    return None


# The paper's agents (Table 1): what this module registered, before any user's registration.
PAPER_VARIANTS: tuple[str, ...] = tuple(PLACEMENT_MODELS)
