"""Perception: RGB-D observation -> 2D detections. Choose an implementation by name.

A light package (no torch): the agent's configuration and every command line import these
names. The model families live in subpackages, one module per role (``config`` light,
``model`` the runtime, ``data``, ``train``, ``eval``):

* :mod:`.detector`: the RGB-D detector with its OOP head, and ``tidee gen detection`` data.
* :mod:`.reclassifier`: the crop classifier that renames the detector's detections.
* :mod:`.depth`: the depth-from-RGB network (the paper's "+est. depth").
* :mod:`.learned`: the agent's learned perception (detector + reclassifier); :mod:`.oracle`:
  the simulator's segmentation. :mod:`.commands`: their ``tidee`` commands.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

from tidee.agent.perception.base import Detection, Perception
from tidee.server.config import TRAINED_RENDERER

# The renderer the shipped vision models (detector, depth network) were trained on
# (TRAINED_RENDERER, declared with the server's options). The simulator's own default is EGL
# when it loads (faster); its frames are lit differently and the default detector scores lower
# on them (`tidee eval detector --split test --renderer egl`: docs/eval/detector_egl), so the
# agent's commands ask for this one. The "tiny+egl" detector set (DETECTORS) was trained on
# frames of both renderers and serves either.

PerceptionMode = Literal["learned", "oracle"]
PERCEPTIONS: tuple[PerceptionMode, ...] = get_args(PerceptionMode)
# How the detector's heatmap peaks become detections (``detector.model.decode``); the agent's is the first.
PeakMode = Literal["class-max", "per-class", "per-class-single"]
PEAK_MODES: tuple[PeakMode, ...] = get_args(PeakMode)
AGENT_THRESHOLD = 0.3  # the learned detector's score below which the agent drops a detection
# The learned detector and its crop classifier, by the renderers their training frames came
# from: weights file names in agent/weights (the first: the default).
DetectorSet = Literal["tiny", "tiny+egl"]
DETECTORS: dict[str, tuple[str, str]] = {
    "tiny": ("detector.pt", "reclassifier.pt"),
    "tiny+egl": ("detector_tiny_egl.pt", "reclassifier_tiny_egl.pt"),
}
DETECTOR_SETS: tuple[DetectorSet, ...] = get_args(DetectorSet)


def _oracle(threshold: float | None, detector: str = DETECTOR_SETS[0]) -> Perception:
    from tidee.agent.perception.oracle import OraclePerception

    if threshold is not None:
        raise ValueError("a detection threshold applies to learned perception only")
    if detector != DETECTOR_SETS[0]:
        raise ValueError(f"the {detector} detector is learned perception: oracle perception has none")
    return OraclePerception()


def _learned(threshold: float | None, detector: str = DETECTOR_SETS[0]) -> Perception:
    from tidee.agent.learning import WEIGHTS_DIR
    from tidee.agent.perception.learned import LearnedPerception

    if detector not in DETECTORS:
        raise ValueError(f"unknown detector {detector!r}; choose one of {DETECTOR_SETS}")
    weights, reclassifier = DETECTORS[detector]
    return LearnedPerception.load(
        WEIGHTS_DIR / weights,
        threshold=AGENT_THRESHOLD if threshold is None else threshold,
        reclassifier=WEIGHTS_DIR / reclassifier,
    )


# Perception modes by name (the keys are PERCEPTIONS): each builds its Perception from the
# detection threshold it is given (None: the default) and the detector set (DETECTORS).
PERCEPTION_MODES: dict[str, Callable[[float | None, str], Perception]] = {
    "learned": _learned,
    "oracle": _oracle,
}


def make_perception(
    name: str, threshold: float | None = None, detector: str = DETECTOR_SETS[0]
) -> Perception:
    """``threshold``: the learned detector's score threshold (None: ``AGENT_THRESHOLD``);
    ``detector``: which learned detector (``DETECTORS``). Oracle perception has no scores to
    threshold and no detector, and refuses either."""
    if threshold is not None and not 0.0 < threshold < 1.0:
        raise ValueError(f"the detection threshold must be in (0, 1), got {threshold}")
    if name not in PERCEPTION_MODES:
        raise ValueError(f"unknown perception {name!r}; choose one of {PERCEPTIONS}")
    return PERCEPTION_MODES[name](threshold, detector)


__all__ = [
    "Detection",
    "Perception",
    "PerceptionMode",
    "PERCEPTIONS",
    "PERCEPTION_MODES",
    "PeakMode",
    "PEAK_MODES",
    "AGENT_THRESHOLD",
    "DETECTORS",
    "DETECTOR_SETS",
    "DetectorSet",
    "TRAINED_RENDERER",
    "make_perception",
]
