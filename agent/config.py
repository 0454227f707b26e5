"""Typed configuration of the agent; every module choice is a name (ablations are flags).

``AgentConfig.variant`` picks one of the paper's tidying agents (Table 1):

=================  =========================================================
variant            placement (where does it belong?) and receptacle search
=================  =========================================================
TIDEE              Memex + rGCN (``agent/weights/rgcn.pt``); receptacles not
                   in memory are searched with the visual search network
WithoutMemex       rGCN on the scene graph only (``rgcn_without_memex.pt``);
                   visual search network
3DSmntMap2Place    the search network conditioned on the object's own class
                   proposes places; the first receptacle mapped near one
CommonMemory       most common receptacle for the category (training rooms);
                   receptacles not in memory: unexplored / random goals
RandomReceptacle   first receptacle found by random exploration
=================  =========================================================

Out-of-place detection is its own choice (``oop``), the same for every variant.

Both choices are registries, so a new placement policy or OOP detector is one decorated
class and its name is then a valid ``variant`` / ``oop``: ``PLACEMENT_MODELS`` and
``register_placement`` (``reasoning/placement.py``), ``OOP_DETECTORS`` and
``register_oop_detector`` (``reasoning/oop.py``). Validation reads those tables.

AI2THORPlacement and MessyPlacement are reference rows built from the episode record
(``tidee.agent.evaluation``), not agents.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tidee.agent.mapping.maps import MapConfig
from tidee.agent.perception import PERCEPTIONS
from tidee.agent.reasoning.oop import check_oop_detector
from tidee.agent.reasoning.placement import PAPER_VARIANTS, PLACEMENT_MODELS, check_variant

# The paper's agents (Table 1), the default of `tidee eval tidy`. Validation reads the registry,
# PLACEMENT_MODELS, which also holds any variant a user registers.
AGENT_VARIANTS = PAPER_VARIANTS
REFERENCE_VARIANTS = ("AI2THORPlacement", "MessyPlacement")
BUILT_VARIANTS = AGENT_VARIANTS
EXPLORERS = ("random", "frontier")


def check_variant_built(variant: str) -> None:
    """A ValueError unless ``variant`` is a registered agent (reference rows are not agents)."""
    if variant in REFERENCE_VARIANTS:
        raise ValueError(
            f"variant {variant!r} is a reference row built by evaluation from the agents' "
            f"episodes, not an agent; agents: {', '.join(PLACEMENT_MODELS)}"
        )
    check_variant(variant)


MISSING_TOP = ("skip", "search")


@dataclass
class PolicyConfig:
    """Thresholds of Algorithm 1 (paper supplement 'Pseudo code')."""

    explore_unexplored_stop: float = 0.12  # A: stop mapping when this fraction of reachable map is unexplored
    mapping_step_budget: int = 320  # mapping never takes more than this many steps
    goal_step_budget: int = 60  # steps to reach one navigation goal before giving up
    oop_threshold: float = 0.5  # P(OOP) at or above which an object is picked
    sure_oop: float = 0.9  # P(OOP) at which a track seen once is picked at its projected
    # centroid when the detector misses it up close
    k_empty_goals: int = 8  # k: stop after this many search goals without a new OOP object
    m_place_tries: int = 3  # m: placement attempts per receptacle class before moving on
    max_receptacle_classes: int = 3  # ranked receptacle classes tried before searching / dropping
    search_goals: int = 4  # goals visited when searching for a receptacle not in memory
    missing_top: str = "skip"  # the top-ranked receptacle class is not in memory: "skip" to
    # the ranked classes in memory first (search for it only after
    # them), or "search" for it first (Algorithm S1)
    interact_m: float = 1.35  # aim to interact within this eye-to-target distance (server: 1.5)
    approach_m: float = 0.9  # navigation stop radius around an object's (x, y)
    reserve_steps: int = 15  # stop handling new objects when fewer steps than this remain

    def __post_init__(self) -> None:
        if not 0.0 <= self.explore_unexplored_stop < 1.0:
            raise ValueError(f"explore_unexplored_stop must be in [0, 1), got {self.explore_unexplored_stop}")
        if not 0.0 < self.oop_threshold <= 1.0:
            raise ValueError(f"oop_threshold must be in (0, 1], got {self.oop_threshold}")
        if not 0.0 < self.sure_oop <= 1.0:
            raise ValueError(f"sure_oop must be in (0, 1], got {self.sure_oop}")
        if self.missing_top not in MISSING_TOP:
            raise ValueError(f"missing_top must be one of {MISSING_TOP}, got {self.missing_top!r}")
        for name in (
            "mapping_step_budget",
            "goal_step_budget",
            "k_empty_goals",
            "m_place_tries",
            "max_receptacle_classes",
            "search_goals",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


DEPTH_SOURCES = ("sensor", "estimated")


@dataclass
class AgentConfig:
    variant: str = "TIDEE"  # the paper's agent; see the table above
    perception: str = "learned"  # the shipped RGB-D detector; "oracle" reads the segmentation
    depth: str = "sensor"  # "estimated": depth from RGB by the shipped depth network
    oop: str = "auto"  # auto: the detector's OOP head (visual) with learned perception,
    # the language classifier with oracle perception
    explorer: str = "random"  # how unexplored space is mapped: random goals | frontier
    detection_threshold: float | None = None  # learned detector's score threshold (None: AGENT_THRESHOLD)
    seed: int = 0  # the agent's own random draws (goal sampling, RandomReceptacle)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    map: MapConfig = field(default_factory=MapConfig)

    def __post_init__(self) -> None:
        check_variant_built(self.variant)
        if self.perception not in PERCEPTIONS:
            raise ValueError(f"perception must be one of {PERCEPTIONS}, got {self.perception!r}")
        if self.explorer not in EXPLORERS:
            raise ValueError(f"explorer must be one of {EXPLORERS}, got {self.explorer!r}")
        if self.depth not in DEPTH_SOURCES:
            raise ValueError(f"depth must be one of {DEPTH_SOURCES}, got {self.depth!r}")
        if self.detection_threshold is not None:
            if self.perception != "learned":
                raise ValueError(
                    "--detection-threshold applies to the learned detector: it needs --perception learned"
                )
            if not 0.0 < self.detection_threshold < 1.0:
                raise ValueError(f"--detection-threshold must be in (0, 1), got {self.detection_threshold}")
        if self.oop == "auto":
            self.oop = "visual" if self.perception == "learned" else "language"
        check_oop_detector(self.oop)
        if self.oop == "visual" and self.perception != "learned":
            raise ValueError(
                "--oop visual reads the learned detector's OOP head: it needs --perception learned"
            )
