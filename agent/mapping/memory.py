"""Object tracking and semantic aggregation: the agent's memory of the objects it has seen.

Each detection lifted to 3D (a centroid and an axis-aligned box in the start frame,
metres) is merged into the nearest remembered object with the same label whose
centroid lies within ``merge_distance`` metres (the original TIDEE code: same label,
within 1.0 m); otherwise it starts a new entry. Merging keeps score-weighted running
averages of the centroid and the box, the best score, the latest feature and a running
mean of the out-of-place probability.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

_MIN_WEIGHT = 1e-6  # a detection with score 0 still counts a little, so averages stay defined


def _vec3(name: str, value: Any) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,):
        raise ValueError(f"{name} must have 3 components (x, y, z metres), got shape {np.shape(value)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v.tolist()}")
    return v


@dataclass
class TrackedObject:
    """One remembered object. Positions are start-frame metres; steps are episode steps."""

    id: int
    label: str
    score: float  # best detection score so far
    centroid: np.ndarray  # float64 3
    box_min: np.ndarray  # float64 3: axis-aligned box, lower corner
    box_max: np.ndarray  # float64 3: upper corner
    n_obs: int = 1  # detections merged into it
    first_seen: int = 0
    last_seen: int = 0
    feature: np.ndarray | None = None  # latest non-None detection feature
    oop_prob: float | None = None  # running mean of the non-None P(out of place)
    out_of_place: bool = False  # set by the policy
    meta: dict[str, Any] = field(default_factory=dict)  # free slot for the policy
    weight: float = 0.0  # sum of the merged detections' scores (averaging weight)
    oop_count: int = 0  # detections that carried an oop_prob

    @property
    def xy(self) -> np.ndarray:
        """float64 2: the centroid's (x, y)."""
        return self.centroid[:2]


class ObjectMemory:
    """Remembered objects keyed by id; ids increase from 0 and are never reused
    (until ``clear``, which starts a fresh memory for a new episode)."""

    def __init__(
        self,
        merge_distance: float = 1.0,
        box_merge: str = "mean",
        label_merge: Mapping[str, float] | None = None,
    ) -> None:
        """``box_merge``: how a merged detection's 3D box combines with the entry's:
        ``"mean"`` (score-weighted running average) or ``"union"`` (the hull of all views).
        ``label_merge``: merge distances of particular labels, instead of ``merge_distance``."""
        if not merge_distance > 0:
            raise ValueError(f"merge_distance must be > 0 metres, got {merge_distance}")
        bad = {k: v for k, v in (label_merge or {}).items() if not v > 0}
        if bad:
            raise ValueError(f"label_merge distances must be > 0 metres, got {bad}")
        self.label_merge = dict(label_merge or {})
        if box_merge not in ("mean", "union"):
            raise ValueError(f"box_merge must be 'mean' or 'union', got {box_merge!r}")
        self.merge_distance = float(merge_distance)
        self.box_merge = box_merge
        self._objects: dict[int, TrackedObject] = {}
        self._next_id = 0

    # ------------------------------------------------------------------ updates
    def add_or_merge(
        self,
        label: str,
        score: float,
        centroid: np.ndarray,
        box_min: np.ndarray,
        box_max: np.ndarray,
        step: int,
        feature: np.ndarray | None = None,
        oop_prob: float | None = None,
    ) -> TrackedObject:
        """Merge a 3D detection into the nearest same-label entry within ``merge_distance``
        (3D distance between centroids, metres), or add a new entry. Returns the entry."""
        c = _vec3("centroid", centroid)
        lo, hi = _vec3("box_min", box_min), _vec3("box_max", box_max)
        if np.any(lo > hi):
            raise ValueError(f"box_min {lo.tolist()} exceeds box_max {hi.tolist()}")
        score = float(score)
        if not 0.0 <= score <= 1.0:
            raise ValueError(f"score must be in [0, 1], got {score}")
        if oop_prob is not None and not 0.0 <= float(oop_prob) <= 1.0:
            raise ValueError(f"oop_prob must be in [0, 1] or None, got {oop_prob}")
        w = max(score, _MIN_WEIGHT)

        target = self._nearest_within(label, c, self.label_merge.get(label, self.merge_distance))
        if target is None:
            obj = TrackedObject(
                id=self._next_id,
                label=label,
                score=score,
                centroid=c,
                box_min=lo,
                box_max=hi,
                n_obs=1,
                first_seen=int(step),
                last_seen=int(step),
                feature=None if feature is None else np.array(feature),
                oop_prob=None if oop_prob is None else float(oop_prob),
                weight=w,
                oop_count=0 if oop_prob is None else 1,
            )
            self._objects[obj.id] = obj
            self._next_id += 1
            return obj

        total = target.weight + w
        a, b = target.weight / total, w / total
        target.centroid = a * target.centroid + b * c
        if self.box_merge == "union":
            # Views of a big receptacle each see part of it: the union approaches its extent.
            target.box_min = np.minimum(target.box_min, lo)
            target.box_max = np.maximum(target.box_max, hi)
        else:
            target.box_min = a * target.box_min + b * lo
            target.box_max = a * target.box_max + b * hi
        target.weight = total
        target.score = max(target.score, score)
        target.n_obs += 1
        target.last_seen = max(target.last_seen, int(step))
        target.first_seen = min(target.first_seen, int(step))
        if feature is not None:
            target.feature = np.array(feature)
        if oop_prob is not None:
            n = target.oop_count
            prev = 0.0 if target.oop_prob is None else target.oop_prob
            target.oop_prob = (prev * n + float(oop_prob)) / (n + 1)
            target.oop_count = n + 1
        return target

    def remove(self, obj_id: int) -> TrackedObject:
        """Forget an entry; its id is not reused. Raises KeyError for an unknown id."""
        try:
            return self._objects.pop(int(obj_id))
        except KeyError:
            raise KeyError(f"no tracked object with id {obj_id}") from None

    def clear(self) -> None:
        """Forget everything and restart ids at 0 (a new episode)."""
        self._objects.clear()
        self._next_id = 0

    # ------------------------------------------------------------------ queries
    def get(self, obj_id: int) -> TrackedObject | None:
        return self._objects.get(int(obj_id))

    def of_label(self, label: str) -> list[TrackedObject]:
        """Entries with this label, in id order."""
        return [o for o in self._objects.values() if o.label == label]

    def labels(self) -> list[str]:
        """The distinct labels remembered, sorted."""
        return sorted({o.label for o in self._objects.values()})

    def nearest(self, label: str, xy: np.ndarray | tuple[float, ...]) -> TrackedObject | None:
        """The entry with ``label`` nearest to ``xy`` (2D distance on the floor plane when xy
        has 2 components, 3D when it has 3), or None when there is none. Ties: lowest id."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1)
        if p.shape not in ((2,), (3,)):
            raise ValueError(f"xy must have 2 or 3 components, got shape {np.shape(xy)}")
        best, best_d = None, np.inf
        for o in self._objects.values():
            if o.label != label:
                continue
            d = float(np.linalg.norm(o.centroid[: p.size] - p))
            if d < best_d:
                best, best_d = o, d
        return best

    def _nearest_within(self, label: str, c: np.ndarray, radius: float) -> TrackedObject | None:
        o = self.nearest(label, c)
        if o is None or np.linalg.norm(o.centroid - c) > radius:
            return None
        return o

    def __iter__(self) -> Iterator[TrackedObject]:
        return iter(list(self._objects.values()))

    def __len__(self) -> int:
        return len(self._objects)

    def __contains__(self, obj_id: object) -> bool:
        return obj_id in self._objects
