"""Which way a small object lies and what colour it is, from the depth and colour of its views.

The object memory keeps a centroid and an axis-aligned box per tracked object: good enough to
walk to it and to say where it stood, not which way it lay. Putting an object back is judged
finely (RoomR: the oriented boxes must overlap by IoU > 0.5, about 2 cm and the right heading
for a 10 cm object), so the rearrangement agent estimates each view's *footprint* of a small
object: its depth points standing above the lowest ones (the surface that a depth-cut box mask
also covers), of those its top face (the sides a camera sees would pull the axis), their
principal axes in (x, y) and the heading of the long one; and the mean colour of its points,
which tells two apples apart when the shuffle moved both; and the middle of its top face's
extent in (x, y) (trimmed of stray pixels), which says where it stood better than the tracked
box, whose corners any one view's stray points stretch. ``FootprintVotes`` pools the views of
one tracked object, each weighted by its point count (a nearer view has more), the heading
also by how elongated the view was (a round thing has none). The middle starts from the
weighted median of the views' middles (x and y each; one view's bad mask does not drag it).
A view sees the object's near side, so its middle falls short of the true one along the ray
from the eye (a box or a pan by about 5 cm) while it lies close to that ray (under 1 cm);
where the views' eyes are known the middle is the point nearest all their rays (weighted
least squares across each ray, a view whose ray misses by more than ``RAY_SLACK_M`` counts
less), held along each ray by a weak pull (``RAY_PULL``) towards the view's middle moved
``NEAR_SIDE_M`` further from the eye, which alone decides when every view looked one way.

A thing whose highest part is an edge along one side of it (an open laptop's lid, a book
leaning on its spine) has a top face that is a line off to that side: a view whose top is such an
edge (``top_is_an_edge``) takes its middle from the trimmed extent of its body instead, which the
thing's box spans: its points above the support, or where those show no body beside the edge
(the lift takes a laptop's base, seen alone, for its support), all its points.

A thing whose top is at or above the eye (on a kitchen counter or a dresser: the camera is at
0.9 m) shows no top face, only the sides facing the camera, and one view's side says little:
seen end-on, a tissue box's short end is a line across its long axis. Such a view (its eye less
than ``SIDE_VIEW_DEG`` above the top, as seen from the middle) keeps its top band's (x, y)
points as an *outline* instead of voting on the axis; the views' outlines together trace the
thing's sides from wherever the camera stood, and the rectangle whose sides they lie on
(``outline_axis``) lies along it. The axis comes from the views that saw the top when there
are any, else from the outlines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tidee.agent.mapping.geometry import column_percentiles

LIFT_M = 0.008  # points this far above the lowest ones belong to the object, not its support
MIN_POINTS = 12  # fewer points (after the lift) say nothing
TOP_BAND_M = 0.015  # the points this far below its highest are its top face
TRIM = (2.0, 98.0)  # percentiles that bound an extent (stray pixels at a mask's edge)
NEAR_SIDE_M = 0.015  # a view's middle lies about this much nearer the eye than the object's
RAY_PULL = 0.05  # weight of a view's middle along its own ray, against 1 across it
RAY_SLACK_M = 0.02  # a view whose ray misses the middle by more counts less (weight × slack / miss)
RAY_ROUNDS = 3  # rounds of reweighting
SIDE_VIEW_DEG = 5.0  # a view whose eye is less than this above the top (seen from the middle) sees only sides
EDGE_ELONGATION = 0.7  # a top face this elongated may be an edge (``top_is_an_edge``)
EDGE_SPREAD = 3.0  # ... when the body under it is this many times as wide across it
EDGE_M = 0.05  # ... and this much wider
OUTLINE_POINTS = 128  # a side view keeps at most this many of its outline's points
OUTLINE_UNION_POINTS = 2048  # the side views' outlines are fitted on at most this many points


@dataclass(frozen=True)
class Footprint:
    """One view's estimate: the long axis's heading in degrees ([0, 180): an axis has no
    direction), its elongation (0 round or square .. 1 a line) and the number of points it
    rests on; ``colour``: the mean RGB (0-1) of its points, when given; ``middle``: the middle
    (x, y) of its top face's trimmed extent (of its whole body's where the top is an edge
    along one side), start frame, metres; ``outline``: set when the
    view saw only the thing's sides (module docstring)."""

    axis_deg: float
    elongation: float
    n: int
    colour: np.ndarray | None = None
    middle: tuple[float, float] | None = None
    outline: np.ndarray | None = None  # a view of its sides only: its top band's (x, y) points (Mx2)


def footprint(
    points: np.ndarray,
    colours: np.ndarray | None = None,
    lift: float = LIFT_M,
    min_points: int = MIN_POINTS,
    top_band: float = TOP_BAND_M,
    eye: np.ndarray | None = None,
) -> Footprint | None:
    """A view's footprint of an object from its depth points (start frame, metres, Nx3), or None
    when too few points are left. Points no higher than ``lift`` above the lowest few percent
    are its support, unless that leaves too few (a flat thing seen from above: all of it); of
    the rest, those within ``top_band`` of the highest are its top face, unless too few.
    ``colours``: the points' RGB (Nx3, 0-255), averaged over the object's points. ``eye``: the
    camera's place (x, y, z); a view from less than ``SIDE_VIEW_DEG`` above the top keeps its
    outline (module docstring)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < min_points:
        return None
    every = pts[:, :2]
    z = pts[:, 2]
    keep = z > np.percentile(z, 5) + lift
    if keep.sum() < min_points:
        keep[:] = True
    pts = pts[keep]
    lifted = pts[:, :2]
    colour = None if colours is None else np.asarray(colours, np.float64).reshape(-1, 3)[keep].mean(0) / 255.0
    top_z = float(np.percentile(pts[:, 2], 98))
    top = pts[pts[:, 2] >= top_z - top_band]
    if len(top) >= min_points:  # its top face: the sides a camera sees would pull the axis
        pts = top
    xy = pts[:, :2]
    lo, hi = np.percentile(xy, TRIM, axis=0)
    xy = xy[np.all((xy >= lo) & (xy <= hi), axis=1)]
    if len(xy) < min_points:
        return None
    middle = (float(lo[0] + hi[0]) / 2.0, float(lo[1] + hi[1]) / 2.0)
    evals, evecs = np.linalg.eigh(np.cov((xy - xy.mean(axis=0)).T))
    major = evecs[:, 1]
    axis = math.degrees(math.atan2(major[1], major[0])) % 180.0
    elongation = 1.0 - math.sqrt(max(float(evals[0]), 0.0) / max(float(evals[1]), 1e-12))
    body = None
    if elongation >= EDGE_ELONGATION:
        # above the support; or all of them, where the lift took a laptop's base for its support
        body = next((b for b in (lifted, every) if top_is_an_edge(xy, b, evecs[:, 0])), None)
    if body is not None:
        frame = evecs[:, ::-1]  # (along the edge, across it): the body's extent is a box in it
        b_lo, b_hi = np.percentile(body @ frame, TRIM, axis=0)
        mid = frame @ ((b_lo + b_hi) / 2.0)
        middle = (float(mid[0]), float(mid[1]))
    outline = None
    if eye is not None:
        e = np.asarray(eye, np.float64)
        reach = math.hypot(middle[0] - float(e[0]), middle[1] - float(e[1]))
        if float(e[2]) - top_z < reach * math.tan(math.radians(SIDE_VIEW_DEG)):
            outline = thinned(xy, OUTLINE_POINTS).copy()
    return Footprint(axis, float(np.clip(elongation, 0.0, 1.0)), len(xy), colour, middle, outline)


def top_is_an_edge(top: np.ndarray, body: np.ndarray, across: np.ndarray) -> bool:
    """Whether a line-like top face (x, y points, Mx2) is an edge along one side of the body
    under it (x, y points, Nx2), as an open laptop's lid is: across
    the line (unit ``across``) the body's trimmed extent is at least ``EDGE_SPREAD`` times the
    top's and ``EDGE_M`` wider, and the top lies in its outer quarter on one side."""
    t_lo, t_hi = np.percentile(top @ across, TRIM)
    b_lo, b_hi = np.percentile(body @ across, TRIM)
    t_w, b_w = float(t_hi - t_lo), float(b_hi - b_lo)
    if b_w < EDGE_SPREAD * t_w or b_w - t_w < EDGE_M:
        return False
    return min(float(t_lo - b_lo), float(b_hi - t_hi)) < b_w / 4.0


def thinned(points: np.ndarray, most: int) -> np.ndarray:
    """Every k-th point (a view, not a copy), k the smallest step that leaves at most ``most``."""
    return points[:: max(1, -(-len(points) // most))]


def outline_axis(xy: np.ndarray, step_deg: float = 1.0) -> tuple[float, float] | None:
    """The long axis's heading (degrees, [0, 180)) and elongation (1 - short / long side) of
    the rectangle whose sides the points (x, y: a thing's sides seen from above) lie on: of
    the rectangles around them (each side at the points' trimmed extent, ``TRIM``), tried every
    ``step_deg``, the one with the least mean distance from a point to its nearest side (not the
    least area: two sides of a box, as one view of a corner shows, fit a rectangle along their
    diagonal as tightly); None when fewer than ``MIN_POINTS``."""
    pts = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(pts) < MIN_POINTS:
        return None
    pts = pts - pts.mean(axis=0)
    angles = np.radians(np.arange(0.0, 90.0, step_deg))
    along = pts @ np.stack([np.cos(angles), np.sin(angles)])  # N x A: each point along each heading
    across = pts @ np.stack([-np.sin(angles), np.cos(angles)])
    a_lo, a_hi = column_percentiles(along, *TRIM)
    c_lo, c_hi = column_percentiles(across, *TRIM)
    a_ext, c_ext = a_hi - a_lo, c_hi - c_lo
    gap = np.minimum(
        np.minimum(np.abs(along - a_lo), np.abs(a_hi - along)),
        np.minimum(np.abs(across - c_lo), np.abs(c_hi - across)),
    )
    best = int(np.argmin(gap.mean(axis=0)))
    heading = float(np.degrees(angles[best]))
    long_, short = float(a_ext[best]), float(c_ext[best])
    if short > long_:
        heading, long_, short = heading + 90.0, short, long_
    return heading % 180.0, (1.0 - short / long_) if long_ > 0 else 0.0


def axis_gap(a: float, b: float) -> float:
    """Signed turn (degrees, in [-90, 90)) that takes axis heading ``b`` onto axis heading ``a``."""
    return (a - b + 90.0) % 180.0 - 90.0


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The smallest value at which the sorted values' cumulative weight reaches half the total
    (the lower weighted median)."""
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(np.asarray(values)[order][int(np.searchsorted(cum, cum[-1] / 2.0))])


class FootprintVotes:
    """The views of one tracked object pooled: long-axis heading, colour and middle."""

    def __init__(self) -> None:
        self._middles: list[tuple[float, float, float]] = []  # (x, y, weight) per view with a middle
        self._eyes: list[tuple[float, float] | None] = []  # the eye (x, y) of each, when given
        self._axis = np.zeros(2)  # sum of weight * (cos 2θ, sin 2θ): an axis's doubled angle
        self._axis_weight = 0.0
        self._colour = np.zeros(3)
        self._colour_weight = 0.0
        self._top_weight = 0.0  # points of the views that saw its top (those that vote on the axis)
        self._outlines: list[np.ndarray] = []  # the views that saw only its sides

    def add(self, fp: Footprint, eye: tuple[float, float] | None = None) -> None:
        """One view; ``eye``: where the camera stood (x, y, the frame of ``fp.middle``)."""
        w = float(fp.n)
        if fp.middle is not None:
            self._middles.append((fp.middle[0], fp.middle[1], w))
            self._eyes.append(None if eye is None else (float(eye[0]), float(eye[1])))
        if fp.colour is not None:
            self._colour += w * fp.colour
            self._colour_weight += w
        if fp.outline is not None:
            self._outlines.append(fp.outline)
            return
        self._top_weight += w
        t = math.radians(2.0 * fp.axis_deg)
        aw = w * fp.elongation
        self._axis += aw * np.array([math.cos(t), math.sin(t)])
        self._axis_weight += aw

    @property
    def colour(self) -> np.ndarray | None:
        return self._colour / self._colour_weight if self._colour_weight > 0 else None

    def middle(self) -> tuple[float, float] | None:
        """Where the object stood (x, y): the point nearest the views' rays (module docstring)
        when every view with a middle gave its eye, else the weighted median (weights: the
        views' point counts) of the views' middles, x and y each (``weighted_median``); None
        when no view had one."""
        if not self._middles:
            return None
        m = np.array(self._middles)
        x = np.array([weighted_median(m[:, 0], m[:, 2]), weighted_median(m[:, 1], m[:, 2])])
        if any(e is None for e in self._eyes):
            return float(x[0]), float(x[1])
        rays = m[:, :2] - np.array(self._eyes, np.float64)
        length = np.linalg.norm(rays, axis=1)
        if (length < 1e-6).any():
            return float(x[0]), float(x[1])
        d = rays / length[:, None]
        across = np.eye(2)[None] - d[:, :, None] * d[:, None, :]  # projection across each ray
        along = m[:, :2] + NEAR_SIDE_M * d
        for _ in range(RAY_ROUNDS):
            miss = np.linalg.norm(np.einsum("nij,nj->ni", across, x - m[:, :2]), axis=1)
            w = m[:, 2] * RAY_SLACK_M / np.maximum(miss, RAY_SLACK_M)
            a = np.einsum("n,nij->ij", w, across + RAY_PULL * np.eye(2)[None])
            b = np.einsum("n,nij,nj->i", w, across, m[:, :2]) + RAY_PULL * (w[:, None] * along).sum(0)
            x = np.linalg.solve(a, b)
        return float(x[0]), float(x[1])

    def axis_deg(self, min_agreement: float = 0.5, min_elongation: float = 0.15) -> float | None:
        """The pooled long-axis heading of the views that saw the top, or None when they do not
        agree on one (resultant length below ``min_agreement``) or the object looks about as
        wide as long; where no view saw the top, the heading of the rectangle around the side
        views' outlines (``outline_axis``), None when it is less elongated than
        ``min_elongation``."""
        if self._top_weight <= 0:
            if not self._outlines:
                return None
            fit = outline_axis(thinned(np.concatenate(self._outlines), OUTLINE_UNION_POINTS))
            return fit[0] if fit is not None and fit[1] >= min_elongation else None
        if self._axis_weight <= 0 or self._axis_weight / self._top_weight < min_elongation:
            return None
        if float(np.linalg.norm(self._axis)) / self._axis_weight < min_agreement:
            return None
        return math.degrees(math.atan2(self._axis[1], self._axis[0])) / 2.0 % 180.0

    def heading_guess(self) -> float | None:
        """``axis_deg()``, else the pooled heading however weak (no agreement or elongation
        asked): a put that is given no heading lays the object along the agent's, which is as
        good as random (the rooms' objects lie at any yaw), so any guess the views lean to is
        better. None only when no view showed any spread."""
        strict = self.axis_deg()
        return strict if strict is not None else self.axis_deg(min_agreement=0.0, min_elongation=0.0)
