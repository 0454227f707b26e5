"""Perception: RGB-D observation -> 2D detections. Choose an implementation by name."""

from __future__ import annotations

from tidee.agent.perception.base import Detection, Perception

PERCEPTIONS = ("oracle", "learned")
# The renderer the shipped vision models (detector, depth network) were trained on. The
# simulator's own default is EGL when it loads (faster); its frames are lit differently and
# the detector scores lower on them (`tidee eval detector --split test --renderer egl`:
# docs/eval/detector_egl), so the
# agent's commands ask for this one until the models are retrained on EGL frames.
TRAINED_RENDERER = "tiny"
# How the detector's heatmap peaks become detections (``detector.decode``); the agent's is the first.
PEAK_MODES = ("class-max", "per-class", "per-class-single")
AGENT_THRESHOLD = 0.3  # the learned detector's score below which the agent drops a detection


def make_perception(name: str, threshold: float | None = None) -> Perception:
    """``threshold``: the learned detector's score threshold (None: ``AGENT_THRESHOLD``); oracle
    perception has no scores to threshold and refuses one."""
    if threshold is not None and not 0.0 < threshold < 1.0:
        raise ValueError(f"the detection threshold must be in (0, 1), got {threshold}")
    if name == "oracle":
        from tidee.agent.perception.oracle import OraclePerception

        if threshold is not None:
            raise ValueError("a detection threshold applies to learned perception only")
        return OraclePerception()
    if name == "learned":
        from tidee.agent.perception.learned import LearnedPerception

        return LearnedPerception.load(threshold=AGENT_THRESHOLD if threshold is None else threshold)
    raise ValueError(f"unknown perception {name!r}; choose one of {PERCEPTIONS}")


__all__ = [
    "Detection",
    "Perception",
    "PERCEPTIONS",
    "PEAK_MODES",
    "AGENT_THRESHOLD",
    "TRAINED_RENDERER",
    "make_perception",
]
