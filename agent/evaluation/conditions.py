"""The paper's robustness conditions: the same agent under noisy odometry or worse depth.

Shared by ``tidee eval tidy`` (``--conditions``: one report row per agent and condition) and
``tidee eval rearrange`` (its noise and depth rows). A light module: no torch.

==============  ===========================================================================
clean           sensor depth, exact odometry
noisy-pose      + LoCoBot-like pose noise (0.005 m per move, 0.5 deg per turn; the paper's)
est-depth       depth estimated from RGB by the shipped depth network, never the sensor
noisy-depth     + multiplicative Gaussian noise on the sensor's depth (2 % per pixel)
==============  ===========================================================================
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Literal, get_args

if TYPE_CHECKING:
    from tidee.agent.config import AgentConfig
    from tidee.protocol.messages import EpisodeSpec

Condition = Literal["clean", "noisy-pose", "est-depth", "noisy-depth"]
CONDITIONS: tuple[Condition, ...] = get_args(Condition)

# What each condition changes, in the words a report's notes use.
CONDITION_MEANINGS: dict[Condition, str] = {
    "clean": "sensor depth, exact odometry",
    "noisy-pose": "LoCoBot-like pose noise (Gaussian, 0.005 m per move, 0.5 deg per turn) that the "
    "agent's odometry does not see",
    "est-depth": "depth from RGB by the shipped depth network instead of the sensor",
    "noisy-depth": "multiplicative Gaussian noise on the sensor's depth (2 % per pixel)",
}

# The paper's row names: "TIDEE", "TIDEE +noisy pose", "TIDEE +est. depth", "TIDEE +noisy depth".
_SUFFIX: dict[Condition, str] = {
    "clean": "",
    "noisy-pose": " +noisy pose",
    "est-depth": " +est. depth",
    "noisy-depth": " +noisy depth",
}


def check_condition(condition: str) -> Condition:
    """``condition`` if it is one of :data:`CONDITIONS`; ValueError naming them otherwise."""
    if condition not in CONDITIONS:
        raise ValueError(f"conditions must be among {', '.join(CONDITIONS)}, got {condition!r}")
    return condition  # type: ignore[return-value]


def row_name(variant: str, condition: str) -> str:
    """The report row of ``variant`` under ``condition``, named as in the paper (clean: the
    variant's own name)."""
    return variant + _SUFFIX[check_condition(condition)]


def apply_condition(condition: str, agent: AgentConfig, spec: EpisodeSpec) -> tuple[AgentConfig, EpisodeSpec]:
    """The agent and episode of ``condition`` from the clean ones: pose and depth noise are the
    server's (``EpisodeSpec.pose_noise`` / ``depth_noise``), estimated depth the agent's
    (``AgentConfig.depth``). Clean returns both unchanged."""
    check_condition(condition)
    if condition == "noisy-pose":
        return agent, replace(spec, pose_noise=True)
    if condition == "noisy-depth":
        return agent, replace(spec, depth_noise=True)
    if condition == "est-depth":
        return replace(agent, depth="estimated"), spec
    return agent, spec
