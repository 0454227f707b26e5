"""Metrics of the 2-phase room-rearrangement task, as RoomR defines them.

RoomR (Weihs et al. 2021, "Visual Room Rearrangement"; code: ai2thor-rearrangement,
``rearrange/environment.py`` and ``rearrange/tasks.py``) scores an unshuffle episode by comparing,
object by object, three states of the room: the *goal* (the room the agent walked through), the
*start* of the unshuffle phase (after the shuffle) and the *end* (when the agent stops). This
module computes the same quantities from the object lists the simulator exports
(``Episode.object_states()`` or the ``objects`` of ``Episode.state()``).

Objects
-------
Each object is a dict with at least ``id``, ``type``, ``pickupable``, ``openable``, ``is_open``,
``position`` (world metres: the centre of the *bottom face* of the object's bounding box),
``orientation`` (quaternion x, y, z, w) and ``size`` (the box's extents sx, sy, sz in the object's
own frame). The oriented box is ``position + R(orientation) @ p`` for ``p`` in
``[-sx/2, sx/2] x [-sy/2, sy/2] x [0, sz]``: the rotation turns the box about its bottom-centre.
An optional ``openness`` in [0, 1] overrides ``is_open`` (which reads as 1.0 open, 0.0 closed).

Which objects are scored, and how (the *kind*, read from the goal object):

* **pickupable** (``pickupable`` true): compared by the 3D IoU of the two oriented boxes;
* **openable** (``openable`` true and ``pickupable`` false): compared by openness;
* anything else (furniture that neither moves nor opens) is not scored.

An object of the goal that is missing from the start or end list counts as misplaced there
with energy 1 (RoomR treats a vanished object as broken). An object the agent holds sits at
z = -5 m, so its box meets nothing of the room: IoU 0, energy 1, misplaced. Objects that are
not in the goal list are ignored.

Pose comparison (``compare_poses`` / ``pose_difference_energy`` / ``are_poses_equal``)
--------------------------------------------------------------------------------------
* ``pose_iou``: if the two bottom-centres are less than 1 cm apart and the rotation between
  the two orientations is under 10 degrees, the IoU is taken to be 1 (RoomR's short cut);
  otherwise it is ``iou_3d`` of the two oriented boxes.
* ``pose_difference_energy(goal, cur)`` in [0, 1], 0 meaning "in place":

  - pickupable: ``0.5 * max(1 - iou / 0.5, 0) + 0.5 * d``, where ``d`` is 0 when the boxes
    overlap (iou > 0) and otherwise ``min(c / 2.0, 1)`` with ``c`` the smallest distance
    between a corner of one box and a corner of the other (the 2 m "position barrier"). So
    any IoU of at least 0.5 gives 0; a box with no overlap has energy between 0.5 and 1, and
    1 once its nearest corners are 2 m or more apart;
  - openable: 1 if ``|openness(goal) - openness(cur)| > 0.2`` else 0.

* ``poses_equal(goal, cur)``: pickupable: iou > 0.5; openable: openness difference <= 0.2.
  (RoomR's comparison is strict for the IoU, so at an IoU of exactly 0.5 an object has
  energy 0, and is *not* misplaced in the metrics, yet ``poses_equal`` is False.)

Episode metrics (``UnshuffleTask.metrics`` in RoomR's ``rearrange/tasks.py``)
-----------------------------------------------------------------------------
With ``E_start`` / ``E_end`` each scored object's energy against the goal at the start / end,
an object is *misplaced* when its energy is > 0, and

* ``start_misplaced``: objects misplaced at the start; ``end_misplaced``: at the end;
* ``fixed``: objects misplaced at the start and in place at the end;
* ``newly_misplaced``: objects in place at the start and misplaced at the end;
* ``prop_fixed`` = fixed / start_misplaced, and 1.0 when nothing was misplaced at the start;
* ``fixed_strict`` (RoomR's "% FixedStrict", ``prop_fixed_strict``): ``prop_fixed`` when no object
  is newly misplaced, else 0;
* ``misplaced`` ("% Misplaced", ``prop_misplaced``) = end_misplaced / start_misplaced: it can
  exceed 1 when the agent disturbs more than it fixes. None when nothing was misplaced at the
  start (RoomR leaves the metric out of such an episode);
* ``start_energy`` / ``end_energy``: sums of the energies; ``energy`` ("% Energy",
  ``energy_prop``) = end_energy / start_energy, None when start_energy is 0 (likewise left out);
* ``success``: every scored object is in place at the end (end_energy == 0).

``by_kind`` repeats these for the pickupable and the openable objects alone (a kind with
nothing misplaced at the start then has ``prop_fixed`` 1.0, ``misplaced`` and ``energy`` None,
and ``success`` as at the end). ``aggregate`` averages ``success``, ``fixed_strict``, ``misplaced``
and ``energy`` over episodes, each over the episodes where it is defined (not None), as RoomR's
per-task metric means do.

Differences from RoomR
----------------------
* RoomR estimates the IoU by sampling 13^3 points in one box; ``iou_3d`` computes it exactly
  (up to rounding), for any rotation.
* There is no "broken" state: only a missing object scores as RoomR's broken one does
  (energy 1).
* Openness is boolean here (``is_open`` -> 0.0 / 1.0), so the 0.2 tolerance matters only when
  an ``openness`` value is given.
* An object that is both pickupable and openable is compared by IoU alone, as RoomR's
  ProcTHOR environment does for the energy (its iTHOR version compares such objects by
  openness).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from scipy.spatial import ConvexHull, QhullError

Kind = Literal["pickupable", "openable"]
KINDS: tuple[Kind, ...] = ("pickupable", "openable")

IOU_THRESHOLD = 0.5
OPENNESS_TOLERANCE = 0.2
POSITION_BARRIER_M = 2.0
SAME_POSITION_M = 0.01  # with SAME_ROTATION_DEG: poses this close have IoU 1 (RoomR's short cut)
SAME_ROTATION_DEG = 10.0

_EPS = 1e-9
# Corner i of a box has local offsets (bit 2, bit 1, bit 0) = (x high, y high, z high).
_CORNER_BITS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=float)
_EDGES = [(i, i | b) for i in range(8) for b in (1, 2, 4) if not i & b]


def object_kind(obj: Mapping[str, Any]) -> Kind | None:
    """How an object is scored: "pickupable", "openable", or None (not scored)."""
    if obj.get("pickupable"):
        return "pickupable"
    if obj.get("openable"):
        return "openable"
    return None


def openness(obj: Mapping[str, Any]) -> float:
    """The object's openness in [0, 1]: its ``openness`` if given, else 1.0 open / 0.0 closed."""
    if obj.get("openness") is not None:
        return float(obj["openness"])
    return 1.0 if obj.get("is_open") else 0.0


def rotation_matrix(q: Sequence[float]) -> np.ndarray:
    """The 3x3 rotation of a quaternion (x, y, z, w); it need not be normalised."""
    x, y, z, w = (float(v) for v in q)
    n = x * x + y * y + z * z + w * w
    if n < _EPS:
        raise ValueError(f"zero quaternion {list(q)}")
    s = 2.0 / n
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
        ]
    )


def rotation_angle_deg(qa: Sequence[float], qb: Sequence[float]) -> float:
    """The angle of the rotation taking orientation ``qa`` to ``qb``, in degrees [0, 180]."""
    a = np.asarray(qa, float)
    b = np.asarray(qb, float)
    dot = abs(float(a @ b)) / (float(np.linalg.norm(a)) * float(np.linalg.norm(b)))
    return math.degrees(2.0 * math.acos(min(1.0, dot)))


def _frame(obj: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, rotation, half extents) of the object's oriented box."""
    rot = rotation_matrix(obj["orientation"])
    half = np.asarray(obj["size"], float) / 2.0
    if half.shape != (3,) or (half < 0).any():
        raise ValueError(f"object {obj.get('id')!r} has a bad size {obj['size']}")
    centre = np.asarray(obj["position"], float) + rot @ np.array([0.0, 0.0, half[2]])
    return centre, rot, half


def box_corners(obj: Mapping[str, Any]) -> np.ndarray:
    """The 8 world corners (8x3) of the object's oriented bounding box.

    Corner i is at local ``((2 * bit2 - 1) * sx/2, (2 * bit1 - 1) * sy/2, bit0 * sz)`` about the
    bottom-centre ``position``, turned by ``orientation``.
    """
    centre, rot, half = _frame(obj)
    local = (2.0 * _CORNER_BITS - 1.0) * half
    return centre + local @ rot.T


def _volume(obj: Mapping[str, Any]) -> float:
    return float(np.prod(np.asarray(obj["size"], float)))


def _clip_edges(
    corners: np.ndarray, centre: np.ndarray, rot: np.ndarray, half: np.ndarray
) -> list[np.ndarray]:
    """The parts of a box's 12 edges inside another box (centre, rot, half): their end points.

    Liang-Barsky clipping in the other box's frame, where that box is ``[-half, half]``.
    """
    local = (corners - centre) @ rot  # world -> the other box's frame
    out: list[np.ndarray] = []
    for i, j in _EDGES:
        p0, d = local[i], local[j] - local[i]
        t0, t1 = 0.0, 1.0
        for axis in range(3):
            for p, q in ((-d[axis], p0[axis] + half[axis]), (d[axis], half[axis] - p0[axis])):
                if abs(p) < _EPS:
                    if q < -_EPS:
                        t0, t1 = 1.0, 0.0  # parallel to and outside this face
                elif p < 0:
                    t0 = max(t0, q / p)
                else:
                    t1 = min(t1, q / p)
        if t0 <= t1 + _EPS:
            for t in (t0, min(max(t1, t0), 1.0)):
                out.append(centre + rot @ (p0 + t * d))
    return out


def intersection_volume(a: Mapping[str, Any], b: Mapping[str, Any]) -> float:
    """Volume of the intersection of two objects' oriented boxes (m^3).

    The intersection of two boxes is a convex polytope whose vertices are the corners of
    each box inside the other and the points where an edge of one crosses a face of the
    other; both sets are the end points of each box's edges clipped to the other box. The
    volume is that of their convex hull (scipy's Qhull): exact up to rounding for any
    rotation, and deterministic. Fewer than 4 points, or points on one plane (boxes that
    only touch), give 0.
    """
    ca, cb = box_corners(a), box_corners(b)
    if (ca.min(0) > cb.max(0) + _EPS).any() or (cb.min(0) > ca.max(0) + _EPS).any():
        return 0.0  # the axis-aligned hulls are apart
    pts = _clip_edges(ca, *_frame(b)) + _clip_edges(cb, *_frame(a))
    if len(pts) < 4:
        return 0.0
    try:
        vol = float(ConvexHull(np.array(pts)).volume)
    except QhullError:
        return 0.0  # flat: the boxes touch without overlapping
    return max(0.0, min(vol, _volume(a), _volume(b)))


def iou_3d(a: Mapping[str, Any], b: Mapping[str, Any]) -> float:
    """Intersection over union of two objects' oriented 3D boxes, in [0, 1].

    Exact for any rotation (see ``intersection_volume``); 0 when both boxes have no volume.
    """
    inter = intersection_volume(a, b)
    union = _volume(a) + _volume(b) - inter
    if union <= 0:
        return 0.0
    return float(min(1.0, max(0.0, inter / union)))


def pose_iou(goal: Mapping[str, Any], cur: Mapping[str, Any]) -> float:
    """The IoU RoomR compares poses by: 1 when the bottom-centres are under 1 cm apart and the
    orientations under 10 degrees apart, else ``iou_3d``."""
    dist = float(np.linalg.norm(np.asarray(goal["position"], float) - np.asarray(cur["position"], float)))
    if (
        dist < SAME_POSITION_M
        and rotation_angle_deg(goal["orientation"], cur["orientation"]) < SAME_ROTATION_DEG
    ):
        return 1.0
    return iou_3d(goal, cur)


def min_corner_distance(a: Mapping[str, Any], b: Mapping[str, Any]) -> float:
    """The smallest distance between a corner of one box and a corner of the other (m)."""
    ca, cb = box_corners(a), box_corners(b)
    return float(np.sqrt(((ca[:, None, :] - cb[None, :, :]) ** 2).sum(-1)).min())


def _scored_kind(goal: Mapping[str, Any]) -> Kind:
    kind = object_kind(goal)
    if kind is None:
        raise ValueError(f"object {goal.get('id')!r} ({goal.get('type')}) is neither pickupable nor openable")
    return kind


def pose_difference_energy(
    goal: Mapping[str, Any],
    cur: Mapping[str, Any] | None,
    *,
    min_iou: float = IOU_THRESHOLD,
    open_tol: float = OPENNESS_TOLERANCE,
    pos_barrier: float = POSITION_BARRIER_M,
) -> float:
    """RoomR's energy of ``cur`` against ``goal`` in [0, 1]; 0 means "in place".

    ``cur`` None (the object is missing) gives 1. Raises ValueError for an object that is
    neither pickupable nor openable (not scored). See the module docstring for the formula.
    """
    kind = _scored_kind(goal)
    if cur is None:
        return 1.0
    if kind == "openable":
        return 1.0 if abs(openness(goal) - openness(cur)) > open_tol else 0.0
    iou = pose_iou(goal, cur)
    iou_energy = max(1.0 - iou / min_iou, 0.0)
    position_energy = 0.0 if iou > 0 else min(min_corner_distance(goal, cur) / pos_barrier, 1.0)
    return float(0.5 * iou_energy + 0.5 * position_energy)


def poses_equal(
    goal: Mapping[str, Any],
    cur: Mapping[str, Any] | None,
    *,
    min_iou: float = IOU_THRESHOLD,
    open_tol: float = OPENNESS_TOLERANCE,
) -> bool:
    """RoomR's ``are_poses_equal``: pickupable: IoU > ``min_iou``; openable: openness within
    ``open_tol``. A missing object (None) is never in place."""
    kind = _scored_kind(goal)
    if cur is None:
        return False
    if kind == "openable":
        return abs(openness(goal) - openness(cur)) <= open_tol
    return pose_iou(goal, cur) > min_iou


def _by_id(objects: Sequence[Mapping[str, Any]], what: str) -> dict[str, Mapping[str, Any]]:
    out: dict[str, Mapping[str, Any]] = {}
    for o in objects:
        if o["id"] in out:
            raise ValueError(f"{what} lists object {o['id']!r} twice")
        out[o["id"]] = o
    return out


def _ratio(num: float, den: float) -> float | None:
    return float(num / den) if den > 0 else None


def _summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The episode metrics over a set of per-object rows."""
    start = sum(r["misplaced_start"] for r in rows)
    end = sum(r["misplaced_end"] for r in rows)
    fixed = sum(r["misplaced_start"] and not r["misplaced_end"] for r in rows)
    newly = sum(r["misplaced_end"] and not r["misplaced_start"] for r in rows)
    start_energy = float(sum(r["energy_start"] for r in rows))
    end_energy = float(sum(r["energy_end"] for r in rows))
    prop_fixed = 1.0 if start == 0 else fixed / start
    return {
        "objects_scored": len(rows),
        "success": end == 0,
        "fixed_strict": float(prop_fixed) if newly == 0 else 0.0,
        "prop_fixed": float(prop_fixed),
        "misplaced": _ratio(end, start),
        "energy": _ratio(end_energy, start_energy),
        "start_misplaced": int(start),
        "end_misplaced": int(end),
        "newly_misplaced": int(newly),
        "fixed": int(fixed),
        "start_energy": start_energy,
        "end_energy": end_energy,
    }


def episode_metrics(
    goal: Sequence[Mapping[str, Any]],
    start: Sequence[Mapping[str, Any]],
    end: Sequence[Mapping[str, Any]],
) -> dict[str, Any]:
    """RoomR's unshuffle metrics of one episode (a JSON-serialisable dict).

    ``goal``: the objects of the walkthrough room; ``start``: at the start of the unshuffle
    phase; ``end``: when the agent stopped. Keys: ``success``, ``fixed_strict``, ``prop_fixed``,
    ``misplaced``, ``energy``, ``start_misplaced``, ``end_misplaced``, ``newly_misplaced``,
    ``fixed``, ``start_energy``, ``end_energy``, ``objects_scored``; ``by_kind`` with the same
    keys for "pickupable" and "openable"; ``objects``: one row per scored goal object (sorted
    by id) with ``id``, ``type``, ``kind``, ``misplaced_start``, ``misplaced_end``,
    ``energy_start``, ``energy_end``, ``missing_start``, ``missing_end``. The ratios and their
    values for a zero denominator are defined in the module docstring.
    """
    goal_by_id = _by_id(goal, "goal")
    start_by_id = _by_id(start, "start")
    end_by_id = _by_id(end, "end")
    rows: list[dict[str, Any]] = []
    for oid in sorted(goal_by_id):
        g = goal_by_id[oid]
        kind = object_kind(g)
        if kind is None:
            continue
        s, e = start_by_id.get(oid), end_by_id.get(oid)
        es, ee = pose_difference_energy(g, s), pose_difference_energy(g, e)
        rows.append(
            {
                "id": oid,
                "type": g.get("type"),
                "kind": kind,
                "misplaced_start": es > 0,
                "misplaced_end": ee > 0,
                "energy_start": es,
                "energy_end": ee,
                "missing_start": s is None,
                "missing_end": e is None,
            }
        )
    out = _summary(rows)
    out["by_kind"] = {k: _summary([r for r in rows if r["kind"] == k]) for k in KINDS}
    out["objects"] = rows
    return out


AGGREGATED = ("success", "fixed_strict", "misplaced", "energy")


def _means(items: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"episodes": len(items)}
    for key in AGGREGATED:
        vals = [float(m[key]) for m in items if m.get(key) is not None]
        out[key] = float(np.mean(vals)) if vals else None
        out[f"{key}_episodes"] = len(vals)
    return out


def aggregate(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Means over episodes of ``episode_metrics`` results, for a report table.

    For each of ``success`` (as a rate), ``fixed_strict``, ``misplaced`` and ``energy``: the mean
    over the episodes where it is not None (None when there is none), and ``<key>_episodes``,
    how many episodes that mean is over; likewise under ``by_kind``. ``episodes``: how many
    records there are.
    """
    out = _means(records)
    out["by_kind"] = {k: _means([r["by_kind"][k] for r in records]) for k in KINDS}
    return out
