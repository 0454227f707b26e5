"""Out-of-place detection: which tracked objects are not where they belong.

Every OOP detector scores a tracked object given the other tracked objects and the room
type, returning P(out of place). The non-learned twin here reads the placement
statistics of the training rooms; the learned visual / language / fused classifiers
(issues 5 and 6) implement the same ``OOPDetector`` protocol.

``OOP_DETECTORS`` maps each ``AgentConfig.oop`` name to a no-argument factory. Add your own
with the decorator; ``AgentConfig(oop="my_detector")`` then selects it::

    @register_oop_detector("my_detector")
    class MyDetector:
        name = "my_detector"

        def score_all(self, targets, objects, room_type):
            return {t.id: 0.0 for t in targets}
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, TypeVar

from tidee.agent.classes import RECEPTACLES
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.reasoning.relations import ObjectRef, Support, supported_by
from tidee.agent.reasoning.stats import PlacementStats

FLOOR = "Floor"


def as_ref(o: TrackedObject) -> ObjectRef:
    return ObjectRef(
        id=o.id,
        label=o.label,
        centroid=o.centroid,
        box_min=o.box_min,
        box_max=o.box_max,
        receptacle=o.label in RECEPTACLES,
    )


def support_label(obj: TrackedObject, others: list[TrackedObject]) -> str:
    """The receptacle type the object rests on, from the agent's own 3D estimates."""
    return support_labels([obj], others)[obj.id]


def support_labels(targets: list[TrackedObject], objects: list[TrackedObject]) -> dict[int, str]:
    """``support_label`` for many targets, building each object's reference once."""
    return {
        tid: sup if isinstance(sup, str) else sup.label for tid, sup in supports(targets, objects).items()
    }


def supports(targets: list[TrackedObject], objects: list[TrackedObject]) -> dict[int, Support]:
    """What each target rests on (``supported_by``): "Floor" or a receptacle's reference, whose
    ``id`` is its track's.

    The x, y margin is wide (0.7 m) because the agent's boxes of big receptacles come from
    the surfaces it saw: a counter seen from the front is a thin slab at its front edge,
    while the knife on it lies 0.4 m further back. The height rule picks the right one.
    """
    recs = [as_ref(o) for o in objects if o.label in RECEPTACLES]
    return {
        t.id: supported_by(as_ref(t), [r for r in recs if r.id != t.id], xy_margin_m=0.7) for t in targets
    }


class OOPDetector(Protocol):
    name: str

    def score_all(
        self, targets: list[TrackedObject], objects: list[TrackedObject], room_type: str
    ) -> dict[int, float]:
        """P(out of place) for each target (by id), given every tracked object."""
        ...


F = TypeVar("F", bound=Callable[..., Any])

OOP_DETECTORS: dict[str, Callable[[], OOPDetector]] = {}
"""OOP detectors by name, in registration order; the shipped four are registered below."""


def register_oop_detector(name: str) -> Callable[[F], F]:
    """Decorator: register an OOP detector class (or a no-argument factory) under ``name``."""

    def register(factory: F) -> F:
        if name == "auto":
            raise ValueError("'auto' is AgentConfig's choice by perception, not a detector name")
        if name in OOP_DETECTORS:
            raise ValueError(
                f"OOP detector {name!r} is already registered ({OOP_DETECTORS[name]!r}); "
                f"register yours under another name"
            )
        OOP_DETECTORS[name] = factory
        return factory

    return register


def check_oop_detector(name: str) -> Callable[[], OOPDetector]:
    """The factory registered as ``name``; a ValueError naming the registered ones if there is none."""
    try:
        return OOP_DETECTORS[name]
    except KeyError:
        raise ValueError(
            f"unknown OOP detector {name!r}; registered: {', '.join(OOP_DETECTORS)} "
            f"(register_oop_detector adds one)"
        ) from None


def make_oop(name: str) -> OOPDetector:
    return check_oop_detector(name)()


@register_oop_detector("relation_stats")
class RelationStatsOOP:
    """Out of place when the supporting receptacle is rare for the category (training rooms).

    ``rarity`` = count(receptacle) / count(most common receptacle) for the category in
    this room type; P(OOP) = 1 - min(rarity / (2 * rare), 1), so P >= 0.5 exactly when
    rarity <= ``rare`` (0.1: the same relative rule the catalog's plausibility uses).
    """

    name = "relation_stats"

    def __init__(self, stats: PlacementStats | None = None, rare: float = 0.1) -> None:
        self.stats = stats or PlacementStats.load()
        self.rare = rare

    def score_all(
        self, targets: list[TrackedObject], objects: list[TrackedObject], room_type: str
    ) -> dict[int, float]:
        supports = support_labels(targets, objects)
        for t in targets:
            t.meta["support"] = supports[t.id]  # for logs and the viewer
        return {t.id: self.probability(t.label, supports[t.id], room_type) for t in targets}

    def probability(self, label: str, support: str, room_type: str) -> float:
        rarity = self.stats.rarity(label, support, room_type)
        return 1.0 - min(rarity / (2 * self.rare), 1.0)


@register_oop_detector("visual")
class VisualOOP:
    """The detector's OOP head (dDETR-OOP): the running mean of the per-view P(out of place)
    the learned detector attached to each detection merged into the tracked object."""

    name = "visual"

    def score_all(
        self, targets: list[TrackedObject], objects: list[TrackedObject], room_type: str
    ) -> dict[int, float]:
        missing = [t.label for t in targets if t.oop_prob is None]
        if missing:
            raise ValueError(
                f"visual OOP needs learned perception (detections with an OOP head); "
                f"{missing[0]} has no oop_prob"
            )
        return {t.id: float(t.oop_prob) for t in targets}  # type: ignore[arg-type]


@register_oop_detector("language")
def _language() -> OOPDetector:
    """BERT-OOP: the language classifier (loads torch and the sentence encoder, so only when chosen)."""
    from tidee.agent.reasoning.language_oop.model import LanguageOOP

    return LanguageOOP()


@register_oop_detector("fused")
def _fused() -> OOPDetector:
    """dDETR+BERT-OOP: the language paragraph and the detector's feature."""
    from tidee.agent.reasoning.language_oop.model import FusedLanguageOOP

    return FusedLanguageOOP()
