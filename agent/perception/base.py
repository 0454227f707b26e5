"""What perception hands to the rest of the agent: 2D detections in the current frame.

Every perception module (the oracle here, the learned detector later) implements
``Perception.detect(obs) -> list[Detection]``; mapping, the object memory, the OOP
classifiers and the policy only ever see ``Detection`` objects.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from tidee.protocol.messages import Observation


@dataclass
class Detection:
    label: str  # catalog category (AI2THOR type name)
    score: float  # confidence in [0, 1]
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 pixels, half-open: [x0, x1) x [y0, y1)
    mask: np.ndarray | None = None  # bool HxW instance mask, when the detector gives one
    feature: np.ndarray | None = None  # float32 D: per-detection feature (learned perception)
    oop_prob: float | None = None  # P(out of place) from a detector with an OOP head
    source: str = "oracle"  # which perception produced it

    def box_mask(self, shape: tuple[int, int]) -> np.ndarray:
        m = np.zeros(shape, bool)
        x0, y0, x1, y1 = self.box
        m[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = True
        return m

    def region(self, shape: tuple[int, int]) -> np.ndarray:
        """bool HxW: the pixels that belong to the object (mask if any, else box)."""
        return self.mask if self.mask is not None else self.box_mask(shape)


class Perception(Protocol):
    name: str  # one of PERCEPTIONS, or a name of your own
    needs_ground_truth: bool  # True only for oracle modes

    def detect(self, obs: Observation) -> list[Detection]: ...
