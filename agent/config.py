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

import functools
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, get_args

from tidee import argtypes
from tidee.agent.mapping.config import MapConfig
from tidee.agent.perception import DETECTOR_SETS, PERCEPTIONS, DetectorSet, PerceptionMode
from tidee.agent.reasoning.oop import OOP_DETECTORS, check_oop_detector
from tidee.agent.reasoning.placement import PAPER_VARIANTS, PLACEMENT_MODELS, check_variant
from tidee.launch import RunConfig
from tidee.options import option
from tidee.paths import RUNS_DIR
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.vocab import check_choice

# The paper's agents (Table 1), the default of `tidee eval tidy`. Validation reads the registry,
# PLACEMENT_MODELS, which also holds any variant a user registers.
AGENT_VARIANTS = PAPER_VARIANTS
REFERENCE_VARIANTS = ("AI2THORPlacement", "MessyPlacement")
BUILT_VARIANTS = AGENT_VARIANTS
# How unexplored space is mapped: random reachable goals, or the nearest frontier.
Explorer = Literal["random", "frontier"]
EXPLORERS: tuple[Explorer, ...] = get_args(Explorer)
Localise = Literal["auto", "scan", "off"]
LOCALISE_MODES: tuple[Localise, ...] = get_args(Localise)
# Whether rays that pass through a mapped obstacle take it away again (MapConfig.carve).
Carve = Literal["auto", "on", "off"]
CARVE_MODES: tuple[Carve, ...] = get_args(Carve)
# Where depth comes from: the sensor, or the shipped depth network from RGB (the paper's +est. depth).
DepthSource = Literal["sensor", "estimated"]
DEPTH_SOURCES: tuple[DepthSource, ...] = get_args(DepthSource)
# The top-ranked receptacle class is not in memory: skip to the ranked classes in memory first,
# or search for it first (the paper's Algorithm S1).
MissingTop = Literal["skip", "search"]
MISSING_TOP: tuple[MissingTop, ...] = get_args(MissingTop)
# A rearrangement's unshuffle: what becomes of an object it sees but cannot match to the walkthrough.
Unmatched = Literal["leave", "commonsense"]
UNMATCHED: tuple[Unmatched, ...] = get_args(Unmatched)


class _OOPChoices:
    """``--oop`` choices: "auto" and every registered OOP detector (a live view of the registry)."""

    def __iter__(self) -> Iterator[str]:
        return iter(("auto", *OOP_DETECTORS))

    def __contains__(self, name: object) -> bool:
        return name == "auto" or name in OOP_DETECTORS

    def __len__(self) -> int:
        return 1 + len(OOP_DETECTORS)


def check_variant_built(variant: str) -> None:
    """A ValueError unless ``variant`` is a registered agent (reference rows are not agents)."""
    if variant in REFERENCE_VARIANTS:
        raise ValueError(
            f"variant {variant!r} is a reference row built by evaluation from the agents' "
            f"episodes, not an agent; agents: {', '.join(PLACEMENT_MODELS)}"
        )
    check_variant(variant)


@dataclass
class PolicyConfig:
    """Thresholds of Algorithm 1 (paper supplement 'Pseudo code')."""

    explore_unexplored_stop: float = option(
        0.12, "A: stop mapping when this fraction of the reachable map is unexplored"
    )
    mapping_step_budget: int = option(320, "mapping never takes more than this many steps")
    goal_step_budget: int = option(60, "steps to reach one navigation goal before giving up")
    oop_threshold: float = option(0.5, "P(out of place) at or above which an object is picked")
    sure_oop: float = option(
        0.9,
        "P(out of place) at which a track seen once is picked at its projected centroid when the "
        "detector misses it up close",
    )
    k_empty_goals: int = option(8, "k: stop after this many search goals without a new out-of-place object")
    m_place_tries: int = option(3, "m: placement attempts per receptacle class before moving on")
    max_receptacle_classes: int = option(3, "ranked receptacle classes tried before searching / dropping")
    search_goals: int = option(4, "goals visited when searching for a receptacle not in memory")
    missing_top: MissingTop = option(
        "skip",
        "the top-ranked receptacle class is not in memory: skip to the ranked classes in memory "
        "(search for it only after them) | search for it first (the paper's Algorithm S1)",
    )
    interact_m: float = option(1.35, "aim to interact within this eye-to-target distance, m (server: 1.5)")
    approach_m: float = option(0.9, "navigation stop radius around an object's (x, y), m")
    reserve_steps: int = option(15, "stop handling new objects when fewer steps than this remain")
    unmatched: Unmatched = option(
        "leave",
        "a rearrangement's unshuffle, after restoring what it matched: an object seen there (at "
        "least twice) that matches nothing of the walkthrough is left where it is | tidied with "
        "the tidy agent's commonsense when its OOP detector finds it out of place (picked and "
        "put where the --variant's placement model ranks first)",
    )

    def __post_init__(self) -> None:
        if not 0.0 <= self.explore_unexplored_stop < 1.0:
            raise ValueError(f"explore_unexplored_stop must be in [0, 1), got {self.explore_unexplored_stop}")
        if not 0.0 < self.oop_threshold <= 1.0:
            raise ValueError(f"oop_threshold must be in (0, 1], got {self.oop_threshold}")
        if not 0.0 < self.sure_oop <= 1.0:
            raise ValueError(f"sure_oop must be in (0, 1], got {self.sure_oop}")
        if self.missing_top not in MISSING_TOP:
            raise ValueError(f"missing_top must be one of {MISSING_TOP}, got {self.missing_top!r}")
        check_choice("unmatched", self.unmatched, UNMATCHED)
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


@dataclass
class AgentConfig:
    """The agent: which variant, which perception, which out-of-place detector, how it explores."""

    variant: str = option(
        "TIDEE",
        "the agent (placement + receptacle search; see agent/config.py); any registered placement model",
        choices=PLACEMENT_MODELS,
    )
    perception: PerceptionMode = option(
        "learned", "learned: the shipped RGB-D detector | oracle: reads the simulator's segmentation"
    )
    detector: DetectorSet = option(
        DETECTOR_SETS[0],
        "the learned detector and its crop classifier, by the renderers they were trained on: tiny "
        "(TinyRenderer frames) | tiny+egl (TinyRenderer and EGL frames alike: the one for --renderer egl)",
    )
    depth: DepthSource = option(
        "sensor", "estimated: depth from RGB by the shipped depth network (the paper's +est. depth)"
    )
    oop: str = option(
        "auto",
        "out-of-place detector; auto: visual (the detector's OOP head) with learned perception, "
        "language with oracle perception",
        choices=_OOPChoices(),
    )
    explorer: Explorer = option("random", "how unexplored space is mapped: random goals | frontier")
    localise: Localise = option(
        "auto",
        "scan: correct the odometry by matching each frame's depth against the map built so far "
        "(agent/mapping/localise.py); auto: scan when the episode has pose noise; off: trust the odometry",
    )
    carve: Carve = option(
        "auto",
        "on: a mapped obstacle stays only while frames with a point in it outnumber frames whose "
        "rays passed through it (free-space carving, agent/mapping/maps.py); off: one "
        "point makes an obstacle for good; auto: on with estimated depth",
    )
    detection_threshold: float | None = option(
        None,
        "learned detector's score threshold (default: 0.3, perception.AGENT_THRESHOLD)",
        type=argtypes.non_negative_float,
    )
    seed: int = option(
        0,
        "the agent's own random draws (goal sampling, RandomReceptacle)",
        flag="--agent-seed",
        type=argtypes.non_negative_int,
    )
    preferences: str | None = option(
        None,
        'a household\'s preferences, a JSON (or YAML) file {"household": ..., "preferences": [sentences]}: '
        "they decide whether an object is out of place and where it goes (agent/reasoning/preferences.py); "
        "sentences typed in the viewer are added to it",
        metavar="FILE",
    )
    policy: PolicyConfig = option(default_factory=PolicyConfig)
    map: MapConfig = option(default_factory=MapConfig, cli=False)

    def __post_init__(self) -> None:
        check_variant_built(self.variant)
        if self.perception not in PERCEPTIONS:
            raise ValueError(f"perception must be one of {PERCEPTIONS}, got {self.perception!r}")
        if self.explorer not in EXPLORERS:
            raise ValueError(f"explorer must be one of {EXPLORERS}, got {self.explorer!r}")
        if self.localise not in LOCALISE_MODES:
            raise ValueError(f"localise must be one of {LOCALISE_MODES}, got {self.localise!r}")
        if self.carve not in CARVE_MODES:
            raise ValueError(f"carve must be one of {CARVE_MODES}, got {self.carve!r}")
        if self.depth not in DEPTH_SOURCES:
            raise ValueError(f"depth must be one of {DEPTH_SOURCES}, got {self.depth!r}")
        check_choice("detector", self.detector, DETECTOR_SETS)
        if self.detector != DETECTOR_SETS[0] and self.perception != "learned":
            raise ValueError(
                f"--detector {self.detector} is a learned detector: it needs --perception learned"
            )
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
        if self.oop == "fused" and self.detector != DETECTOR_SETS[0]:
            raise ValueError(
                f"--oop fused reads the {DETECTOR_SETS[0]} detector's features (it was trained on them): "
                f"it cannot run with --detector {self.detector}"
            )


@dataclass
class AgentProcessConfig:
    """``tidee agent``: one agent process, its episodes and its connection to a server."""

    agent: AgentConfig = option(default_factory=AgentConfig)
    # mess 0 unless a rearrangement is asked for (``__post_init__``): a default mess index would
    # make every --rearrange-index a spec asking for both
    spec: EpisodeSpec = option(default_factory=functools.partial(EpisodeSpec, seed=200))
    endpoint: str | None = option(
        None,
        "Zenoh rendezvous endpoint (default: loopback, see protocol/README.md)",
        type=argtypes.endpoint,
    )
    router: str | None = option(
        None, "connect to this Zenoh router instead of peer mode", type=argtypes.endpoint
    )
    zenoh_config: str | None = option(
        None,
        "a Zenoh config file (JSON5) merged over tidee's settings, its keys winning: TLS, access "
        "control (default: $TIDEE_ZENOH_CONFIG; see deploy/secure/README.md)",
        metavar="FILE",
    )
    server_id: str = option(
        "sim0",
        "the simulation server to use; auto: the live server with the fewest sessions for its capacity "
        "(through a router: several servers; protocol/discovery.py), and another one if it goes away",
    )
    session: str | None = option(None, "session id (default: agent-<random>)")
    episodes: int = option(
        1, "episodes on consecutive mess indices from --mess-index", type=argtypes.positive_int
    )
    serve: bool = option(False, "afterwards, wait for new_episode commands from a viewer")
    log_dir: Path | None = option(
        None,
        "episode logs, replay with tidee viewer --replay (default: runs/ in the tidee checkout)",
        type=argtypes.output_path,
    )
    connect_timeout: float = option(
        60.0, "seconds to wait for the server to appear before giving up", type=argtypes.non_negative_float
    )
    reconnect_timeout: float = option(
        60.0,
        "if the server goes away mid-episode, seconds to wait for it to come back (--server-id auto: for "
        "another live server with room) before giving up; the episode then runs again from the start "
        "(at most 3 times; 0: give up at once)",
        type=argtypes.non_negative_float,
    )
    threads: int = option(
        0,
        "torch/OpenMP threads (0: the cores this process may use; tidee run gives the agent the cores "
        "the server does not use)",
        type=argtypes.non_negative_int,
    )
    score: bool = option(True, "score each episode at its end (the summary's moved / found)", cli=False)

    def __post_init__(self) -> None:
        if not self.reconnect_timeout >= 0:
            raise ValueError(
                f"reconnect_timeout must be a number of seconds >= 0, got {self.reconnect_timeout}"
            )
        if self.log_dir is None:
            self.log_dir = RUNS_DIR
        if self.spec.mess_index is None and self.spec.rearrange_index is None:
            self.spec = replace(self.spec, mess_index=0)  # the agent's episode: a messy room


@dataclass
class LiveRunConfig:
    """``tidee run`` / ``tidee demo``: server + agent + viewer as separate processes."""

    agent: AgentProcessConfig = option(default_factory=AgentProcessConfig)
    launch: RunConfig = option(default_factory=RunConfig)


# AgentProcessConfig flags `tidee run` does not take: it starts its own server on its own endpoint.
LIVE_RUN_SKIP = ("agent.endpoint", "agent.router", "agent.server_id")
