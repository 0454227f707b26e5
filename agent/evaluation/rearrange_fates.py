"""Where a rearrangement's score goes: the fate of each object the shuffle changed.

Scored after an episode (evaluation only: it reads the server's goal, start and end states),
from what the agent remembered and did. Each pickupable misplaced at the start of the
unshuffle phase gets the first of these that applies, in the order the agent's pipeline
meets them:

==================  ============================================================================
fixed               in place at the end (IoU > 0.5 with its goal box)
missed_walkthrough  no walkthrough track of its class within ``NEAR_M`` of its goal place
missed_unshuffle    no unshuffle track of its class within ``NEAR_M`` of its shuffled place
glimpsed            tracked in both phases, but one of the tracks was seen fewer than
                    ``min_obs`` times (too few to say that something moved)
not_believed        tracked in both phases, never believed moved
not_picked          believed moved, never picked up
not_put             picked up, never put down (dropped or still held at the end)
put_off             put down, not in place: ``position_cm`` (x, y distance of the box bottoms),
                    ``height_cm``, ``yaw_deg`` (folded to [0, 90]: a box turned half way round
                    is the same box) and ``iou`` say by how much
==================  ============================================================================

Every pickupable row also says how far the shuffle moved it (``moved_cm``, box centre to box
centre) and what held it in the goal state and after the shuffle (``goal_on``, ``start_on``: the
receptacle's type, or Floor). An openable that changed is ``fixed``, ``not_believed`` or
``not_restored``. An object in place at the start and misplaced at the end (what makes
FixedStrict 0) is ``newly`` misplaced: ``picked`` (the agent took it for moved), ``believed``
(an openable it took for toggled) or ``disturbed`` (knocked while it walked, put or opened
something). A put-down object also says
where its put's (x, y) error came from: ``estimate_cm`` (the point the agent aimed the put at,
from the goal place) and ``landed_cm`` (where the object came to rest, from that point).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from tidee.agent.evaluation.rearrange_metrics import pose_iou, rotation_matrix
from tidee.agent.mapping.geometry import start_to_world_xy

NEAR_M = 0.5  # a track this close (x, y) to an object's box centre saw it
PICKUPABLE_FATES = (
    "fixed",
    "missed_walkthrough",
    "missed_unshuffle",
    "glimpsed",
    "not_believed",
    "not_picked",
    "not_put",
    "put_off",
)
OPENABLE_FATES = ("fixed", "not_believed", "not_restored")

Track = tuple[str, Sequence[float], int]  # (label, start-frame centroid, detections merged)


def box_centre(obj: Mapping[str, Any]) -> np.ndarray:
    """World centre of an object's oriented box (``position`` is its bottom face's centre)."""
    half_up = np.array([0.0, 0.0, float(obj["size"][2]) / 2])
    return np.asarray(obj["position"], float) + rotation_matrix(obj["orientation"]) @ half_up


def best_track(obj: Mapping[str, Any], tracks: Iterable[Track], start: Mapping[str, float]) -> int | None:
    """The most-observed track of ``obj``'s class within ``NEAR_M`` (x, y) of its box centre:
    its observation count, or None when there is none."""
    centre = box_centre(obj)
    counts = [
        n
        for label, c, n in tracks
        if label == obj["type"] and float(np.linalg.norm(start_to_world_xy(start, c) - centre[:2])) <= NEAR_M
    ]
    return max(counts) if counts else None


def yaw_deg(q: Sequence[float]) -> float:
    """The heading (degrees) of an orientation's x axis."""
    r = rotation_matrix(q)
    return math.degrees(math.atan2(r[1, 0], r[0, 0]))


def folded_yaw_gap(a: Sequence[float], b: Sequence[float]) -> float:
    """The heading difference of two orientations, folded to [0, 90] degrees."""
    d = abs((yaw_deg(a) - yaw_deg(b) + 180.0) % 360.0 - 180.0)
    return min(d, 180.0 - d)


def _no_counts() -> dict[str, dict[str, int]]:
    return {
        "pickupable": dict.fromkeys(PICKUPABLE_FATES, 0),
        "openable": dict.fromkeys(OPENABLE_FATES, 0),
        "newly": {"picked": 0, "believed": 0, "disturbed": 0},
    }


def change_fates(
    metrics: Mapping[str, Any],
    goal: Sequence[Mapping[str, Any]],
    start: Sequence[Mapping[str, Any]],
    end: Sequence[Mapping[str, Any]],
    frame: Mapping[str, float],
    walkthrough: Sequence[Track],
    unshuffle: Sequence[Track],
    believed: set[str],
    picked: set[str],
    put: set[str],
    min_obs: int,
    aims: Mapping[str, Sequence[float]] | None = None,
) -> dict[str, Any]:
    """The fate of every changed object of one episode (module docstring) and the newly
    misplaced ones. ``metrics``: ``episode_metrics`` of the episode; ``frame``: the start pose
    in the world; ``walkthrough`` / ``unshuffle``: the agent's tracks as it compared the phases;
    ``believed``: ids of the objects its beliefs were about; ``picked`` / ``put``: ids it picked
    up / put down; ``aims``: per id put down, the world point (x, y) the agent aimed the put at.
    Returns ``changes`` (one row per changed object), ``newly`` (one per newly
    misplaced object) and ``counts`` ({kind: {fate: n}}, newly misplaced under ``newly``)."""
    g = {o["id"]: o for o in goal}
    s = {o["id"]: o for o in start}
    e = {o["id"]: o for o in end}
    changes: list[dict[str, Any]] = []
    newly: list[dict[str, Any]] = []
    for row in metrics["objects"]:
        oid, kind = row["id"], row["kind"]
        if not row["misplaced_start"]:
            if row["misplaced_end"]:
                cause = "picked" if oid in picked else "believed" if oid in believed else "disturbed"
                newly.append({"id": oid, "type": row["type"], "cause": cause})
            continue
        out: dict[str, Any] = {"id": oid, "type": row["type"], "kind": kind}
        if kind == "pickupable":  # what held it in the goal state and after the shuffle
            out["goal_on"] = g[oid].get("parent_type") if oid in g else None
            out["start_on"] = s[oid].get("parent_type") if oid in s else None
        if kind == "pickupable" and oid in s:
            out["moved_cm"] = round(100 * float(np.linalg.norm(box_centre(g[oid]) - box_centre(s[oid]))), 1)
        if not row["misplaced_end"]:
            out["fate"] = "fixed"
        elif kind == "openable":
            out["fate"] = "not_restored" if oid in believed else "not_believed"
        elif oid in believed:
            out["fate"] = "not_picked" if oid not in picked else "not_put" if oid not in put else "put_off"
        else:
            seen_then = best_track(g[oid], walkthrough, frame)
            seen_now = best_track(s[oid], unshuffle, frame) if oid in s else None
            if seen_then is None:
                out["fate"] = "missed_walkthrough"
            elif seen_now is None:
                out["fate"] = "missed_unshuffle"
            elif min(seen_then, seen_now) < min_obs:
                out["fate"] = "glimpsed"
            else:
                out["fate"] = "not_believed"
        if out["fate"] == "put_off" and oid in e:
            a, b = g[oid], e[oid]
            out["position_cm"] = round(
                100 * float(np.linalg.norm(np.subtract(a["position"][:2], b["position"][:2]))), 1
            )
            out["height_cm"] = round(100 * (float(b["position"][2]) - float(a["position"][2])), 1)
            out["yaw_deg"] = round(folded_yaw_gap(a["orientation"], b["orientation"]), 1)
            out["iou"] = round(pose_iou(a, b), 3)
        aim = (aims or {}).get(oid)
        if aim is not None and oid in e and out["fate"] in ("put_off", "fixed"):
            # the put's x-y error, split: the remembered place's, and where it came to rest from there
            target = np.asarray(aim[:2])
            out["estimate_cm"] = round(
                100 * float(np.linalg.norm(target - np.asarray(g[oid]["position"][:2]))), 1
            )
            out["landed_cm"] = round(
                100 * float(np.linalg.norm(np.asarray(e[oid]["position"][:2]) - target)), 1
            )
        changes.append(out)
    counts = _no_counts()
    for c in changes:
        counts[c["kind"]][c["fate"]] += 1
    for n in newly:
        counts["newly"][n["cause"]] += 1
    return {"changes": changes, "newly": newly, "counts": counts}


def sum_counts(fates: Iterable[Mapping[str, Any]]) -> dict[str, dict[str, int]]:
    """``counts`` summed over episodes (records without fates are skipped)."""
    total = _no_counts()
    for f in fates:
        for kind, counts in f["counts"].items():
            for fate, n in counts.items():
                total[kind][fate] += int(n)
    return total
