"""Oracle perception: detections read from the simulator's instance segmentation.

Privileged: it needs ``Observation.ground_truth`` (the agent must ask the server for it),
and every output that used it is labelled "oracle".
"""

from __future__ import annotations

import numpy as np

from tidee.agent.classes import CLASS_INDEX
from tidee.agent.perception.base import Detection
from tidee.protocol.messages import Observation


class OraclePerception:
    name = "oracle"
    needs_ground_truth = True

    def __init__(self, min_pixels: int = 12, max_depth: float = 8.0) -> None:
        self.min_pixels = min_pixels
        self.max_depth = max_depth

    def detect(self, obs: Observation) -> list[Detection]:
        gt = obs.ground_truth
        if gt is None:
            raise ValueError(
                "oracle perception needs ground truth in the observation; reset/step with ground_truth=True"
            )
        seg = gt.instance_seg
        valid = (seg >= 0) & (obs.depth > 0.05) & (obs.depth < self.max_depth)
        ids, counts = np.unique(seg[valid], return_counts=True)
        min_px = max(4, int(self.min_pixels * (seg.shape[0] / 256.0) ** 2))
        out = []
        for k, n in zip(ids.tolist(), counts.tolist()):
            if n < min_px:
                continue
            label = gt.objects[k]["type"]
            if label not in CLASS_INDEX:
                continue
            mask = (seg == k) & valid
            ys, xs = np.nonzero(mask)
            out.append(
                Detection(
                    label=label,
                    score=1.0,
                    box=(int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1),
                    mask=mask,
                    source=self.name,
                )
            )
        return out
