"""What ``tidee eval tidy`` and the other evaluations take, each option declared once (a light
module: no torch)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

from tidee import argtypes
from tidee.agent.config import (
    PAPER_VARIANTS,
    PLACEMENT_MODELS,
    REFERENCE_VARIANTS,
    AgentConfig,
    PerceptionMode,
)
from tidee.agent.evaluation.conditions import CONDITIONS, Condition, check_condition
from tidee.batch import BACKENDS, Backend, BackendConfig, BatchConfig
from tidee.options import option
from tidee.protocol.vocab import HeldOutSplit, Renderer, RoomType
from tidee.server.config import RENDERER_HELP, TRAINED_RENDERER


@dataclass
class TidyEvalConfig:
    """``tidee eval tidy``: the agents on held-out rooms, scored by the simulated judge (Table 1).

    ``agent`` holds every agent option (perception, OOP detector, policy thresholds ...) except
    ``variant`` and ``seed``: each episode runs each of ``variants`` with the agent seed set to
    the configuration's index, once under each of ``conditions`` (one report row each).

    ``agent.depth`` "estimated" is the est-depth condition for every row: alone (conditions left
    at clean) it runs the est-depth rows; with conditions that use the sensor it is refused.
    """

    out: Path = option(help="directory for report.json, report.md and the plots", type=argtypes.output_path)
    split: HeldOutSplit = option("test", "held-out rooms only")
    episodes: int | None = option(
        None, "configurations (default: all; test has 100)", type=argtypes.positive_int
    )
    variants: tuple[str, ...] = option(
        (*PAPER_VARIANTS, *REFERENCE_VARIANTS), "comma list of agents and reference rows"
    )
    conditions: tuple[Condition, ...] = option(
        ("clean",),
        "comma list; each agent runs under each, one report row apiece: clean (the variant's name), "
        "noisy-pose (VARIANT +noisy pose: LoCoBot-like odometry noise), est-depth (VARIANT +est. depth: "
        "depth from RGB by the depth network), noisy-depth (VARIANT +noisy depth)",
    )
    agent: AgentConfig = option(default_factory=AgentConfig)
    resolution: int = option(256, "square images, pixels a side", type=argtypes.resolution)
    max_steps: int = option(1000, "each episode's step budget", type=argtypes.max_steps)
    workers: int = option(1, "parallel simulator processes", type=argtypes.positive_int)
    renderer: Renderer = option(TRAINED_RENDERER, RENDERER_HELP)
    keep_logs: bool = option(False, "write every episode's log under OUT/logs")
    batch: BatchConfig = option(default_factory=BatchConfig)
    progress: bool = option(True, "a progress bar", cli=False)

    def __post_init__(self) -> None:
        self.conditions = tuple(dict.fromkeys(check_condition(c) for c in self.conditions))
        if not self.conditions:
            raise ValueError(f"give at least one condition ({', '.join(CONDITIONS)})")
        if self.agent.depth == "estimated":
            if self.conditions == ("clean",):
                self.conditions = ("est-depth",)  # every row estimates depth: name them so
            elif self.conditions != ("est-depth",):
                sensor = [c for c in self.conditions if c != "est-depth"]
                raise ValueError(
                    f"--depth estimated contradicts --conditions {','.join(self.conditions)}: "
                    f"{', '.join(sensor)} use the depth sensor; drop --depth estimated and list est-depth "
                    "among the conditions"
                )


# Flags of AgentConfig that eval tidy sets per episode rather than from the command line.
TIDY_EVAL_SKIP = ("agent.variant", "agent.seed")

# The rows of ``tidee eval rearrange``: the paper's Table 4 rows, the oracle and a floor.
# Agent flags a rearrangement row decides (perception, depth) or that it does not use.
REARRANGE_EVAL_SKIP = (
    "agent.variant",
    "agent.seed",
    "agent.oop",
    "agent.preferences",
    "agent.perception",
    "agent.depth",
)
RearrangeRow = Literal[
    "clean", "noisy-pose", "est-depth", "noisy-depth", "oracle", "do-nothing", "commonsense"
]
REARRANGE_ROWS: tuple[RearrangeRow, ...] = get_args(RearrangeRow)
DEFAULT_REARRANGE_ROWS = tuple(r for r in REARRANGE_ROWS if r != "commonsense")  # that one: on request


@dataclass
class RearrangeEvalConfig:
    """``tidee eval rearrange``: 2-phase rearrangement on held-out rooms, scored with RoomR's
    metrics (the paper's Table 4): each row is the reduced TIDEE agent under one condition."""

    out: Path = option(help="directory for report.json, report.md and report.png", type=argtypes.output_path)
    split: HeldOutSplit = option("test", "held-out rooms only")
    episodes: int | None = option(
        None, "configurations (default: all; test has 100)", type=argtypes.positive_int
    )
    rows: tuple[RearrangeRow, ...] = option(
        DEFAULT_REARRANGE_ROWS,
        "comma list of rows: clean (learned perception), noisy-pose, est-depth (depth from RGB), "
        "noisy-depth, oracle (ORACLE perception: the simulator's segmentation), do-nothing, "
        "commonsense (clean, and what matches nothing of the walkthrough is tidied with the tidy "
        "agent's commonsense: --unmatched commonsense; not run unless named)",
    )
    agent: AgentConfig = option(default_factory=AgentConfig)
    resolution: int = option(256, "square images, pixels a side", type=argtypes.resolution)
    walkthrough_steps: int = option(250, "the walkthrough's step budget", type=argtypes.max_steps)
    max_steps: int = option(500, "the unshuffle phase's step budget", type=argtypes.max_steps)
    workers: int = option(1, "parallel simulator processes", type=argtypes.positive_int)
    renderer: Renderer = option(TRAINED_RENDERER, RENDERER_HELP)
    batch: BatchConfig = option(default_factory=BatchConfig)
    keep_logs: bool = option(False, "write every episode's log under OUT/logs")
    progress: bool = option(True, "a progress bar", cli=False)

    def __post_init__(self) -> None:
        for row in self.rows:
            if row not in REARRANGE_ROWS:
                raise ValueError(f"rows must be among {', '.join(REARRANGE_ROWS)}, got {row!r}")
        if not self.rows:
            raise ValueError("give at least one row")


@dataclass
class TidyMergeConfig:
    """``tidee eval tidy-merge``: one Table 1 report from the episodes of several tidy runs."""

    sources: str = option(
        flag="--from",
        help="comma list of report directories (report.json or report.json.gz) or report files, each "
        "optionally =VARIANT+VARIANT to take only those variants from it",
    )
    out: Path = option(help="directory for the merged report", type=argtypes.output_path)
    variants: tuple[str, ...] = option((), "comma list of agent variants to take (default: all)")


@dataclass
class CompareConfig:
    """``tidee eval compare``: two runs of one evaluation, episode by episode."""

    before: Path = option(help="the earlier report: a directory (report.json or report.json.gz) or the file")
    after: Path = option(help="the later report, of the same kind (tidy or rearrange)")
    out: Path = option(help="directory for compare.json and compare.md", type=argtypes.output_path)


@dataclass
class AgentBenchConfig:
    """``tidee bench agent``: mapping, planning and step time, and episode wall time."""

    episodes: int = option(3, "episodes (test configurations)", type=argtypes.positive_int)
    resolution: int = option(256, "square images, pixels a side", type=argtypes.resolution)
    variant: str = option("TIDEE", "the agent", choices=PLACEMENT_MODELS)
    perception: PerceptionMode = option("learned", "where detections come from")
    max_steps: int = option(1000, "each episode's step budget", type=argtypes.max_steps)
    out: Path | None = option(None, "report path (default: bench/agent.json)", type=argtypes.output_path)


@dataclass
class EpisodeBenchConfig:
    """``tidee bench episode``: one episode in process vs live (server + agent + viewer)."""

    repeats: int = option(3, "runs of each", type=argtypes.positive_int)
    room_type: RoomType = option("LivingRoom", "the room type")
    seed: int = option(200, "room seed", type=argtypes.non_negative_int)
    mess_index: int = option(0, "messy configuration index", type=argtypes.non_negative_int)
    variant: str = option("TIDEE", "the agent", choices=PLACEMENT_MODELS)
    max_steps: int = option(1000, "the episode's step budget", type=argtypes.max_steps)
    browser: bool = option(False, "a headless Chromium shows the viewer during live runs")
    renderer: Renderer = option(
        TRAINED_RENDERER,
        f"who draws the frames of both sides: tiny or egl ({TRAINED_RENDERER}: what the default detector was "
        "trained on; not auto, which each process resolves on its own)",
    )
    out: Path | None = option(None, "report path (default: bench/episode.json)", type=argtypes.output_path)


@dataclass
class ScaleBenchConfig:
    """``tidee bench scale``: tidy episodes per hour with 1 vs 2 workers, local and on Ray."""

    configs: int = option(8, "test configurations (spread over the room types)", type=argtypes.positive_int)
    variants: tuple[str, ...] = option(("TIDEE",), "comma list of agents")
    repeats: int = option(1, "runs of each", type=argtypes.positive_int)
    split: HeldOutSplit = option("test", "held-out rooms only")
    backends: tuple[Backend, ...] = option(("local", "ray"), "comma list: local, ray")
    out: Path | None = option(None, "report path (default: bench/scale.json)", type=argtypes.output_path)

    def __post_init__(self) -> None:
        for backend in self.backends:
            if backend not in BACKENDS:
                raise ValueError(f"--backends must be among {', '.join(BACKENDS)}, got {backend!r}")
        if not self.backends:
            raise ValueError("give at least one backend")


@dataclass
class StatsGenConfig:
    """``tidee gen stats``: placement statistics of the training rooms."""

    seeds: str = option("0-19,10000-10179", "training seeds, e.g. 0-19,10000-10179")
    out: Path | None = option(
        None, "default: agent/data/placement_stats.json (the shipped file)", type=argtypes.output_path
    )
    workers: int = option(1, "worker processes (local) or Ray actors", type=argtypes.positive_int)
    batch: BackendConfig = option(default_factory=BackendConfig)


@dataclass
class HumanEvalConfig:
    """``tidee eval human``: tidy reports' episodes judged by people (the Housekeep annotations)."""

    report: tuple[str, ...] = option(
        help="a tidy report (its folder or report.json[.gz]); repeat for several with other variants",
        metavar="REPORT",
        repeat=True,
    )
    out: Path = option(help="directory for human.json, human.md and human.png", type=argtypes.output_path)


@dataclass
class PreferenceEvalConfig:
    """``tidee eval preferences``: scripted household preferences, each episode without and with them."""

    out: Path = option(
        help="directory for preferences.json, .md, .png and the profiles", type=argtypes.output_path
    )
    split: HeldOutSplit = option("test", "held-out rooms only")
    episodes: int = option(12, "configurations, spread over the split", type=argtypes.positive_int)
    variants: tuple[str, ...] = option(("TIDEE", "CommonMemory"), "comma list of agents")
    agent: AgentConfig = option(default_factory=AgentConfig)
    resolution: int = option(256, "square images, pixels a side", type=argtypes.resolution)
    max_steps: int = option(1000, "each episode's step budget", type=argtypes.max_steps)
    workers: int = option(1, "parallel simulator processes", type=argtypes.positive_int)
    renderer: Renderer = option(TRAINED_RENDERER, RENDERER_HELP)
    seed: int = option(0, "the scripted preferences' random choices", type=argtypes.non_negative_int)
    keep_logs: bool = option(
        False, "write every episode's log under OUT/logs/without, OUT/logs/with (and OUT/logs/reseeded)"
    )
    reseeded: bool = option(
        True, "also run every episode without preferences under another agent seed: the run-to-run share"
    )
    batch: BatchConfig = option(default_factory=BatchConfig)
    progress: bool = option(True, "a progress bar", cli=False)


# Flags of AgentConfig that eval preferences sets per episode.
PREFERENCE_EVAL_SKIP = ("agent.variant", "agent.seed", "agent.preferences")
