"""Where a rearrangement's score goes: each changed object's fate, by hand-built episodes."""

from __future__ import annotations

import math
from typing import Any

import pytest

from tidee.agent.evaluation.rearrange_fates import change_fates, folded_yaw_gap, sum_counts
from tidee.agent.evaluation.rearrange_metrics import episode_metrics

FRAME = {"x": 1.0, "y": 2.0, "yaw_deg": 90.0}  # start frame: x_world = 1 - y_start, y_world = 2 + x_start


def yaw(deg: float) -> list[float]:
    h = math.radians(deg) / 2
    return [0.0, 0.0, math.sin(h), math.cos(h)]


def thing(oid: str, x: float, y: float, heading: float = 0.0, **kw: Any) -> dict[str, Any]:
    """A 10 x 4 x 6 cm pickupable on the floor at world (x, y)."""
    d = {
        "id": oid,
        "type": oid.split("_")[0],
        "pickupable": True,
        "openable": False,
        "is_open": False,
        "position": [x, y, 0.0],
        "orientation": yaw(heading),
        "size": [0.10, 0.04, 0.06],
    }
    d.update(kw)
    return d


def door(oid: str, is_open: bool) -> dict[str, Any]:
    return {
        "id": oid,
        "type": oid.split("_")[0],
        "pickupable": False,
        "openable": True,
        "is_open": is_open,
        "position": [3.0, 3.0, 0.0],
        "orientation": yaw(0.0),
        "size": [0.5, 0.5, 0.8],
    }


def start_frame(x: float, y: float, z: float = 0.03) -> list[float]:
    """The start-frame point of world (x, y): the inverse of FRAME."""
    return [y - 2.0, 1.0 - x, z]


def fates(goal, start, end, walk, now, believed=(), picked=(), put=(), aims=None):
    metrics = episode_metrics(goal, start, end)
    return change_fates(
        metrics, goal, start, end, FRAME, walk, now, set(believed), set(picked), set(put), 2, aims
    )


def test_each_changed_object_gets_the_first_fate_on_the_way() -> None:
    ids = ["Apple_0", "Book_0", "Cup_0", "Pen_0", "Mug_0", "Key_0", "Fork_0", "Vase_0"]
    goal = [thing(oid, 0.5 * k, 0.0) for k, oid in enumerate(ids)]
    start = [thing(oid, 0.5 * k, 1.0) for k, oid in enumerate(ids)]  # every one moved 1 m north
    end = [dict(o) for o in start]
    end[0] = thing("Apple_0", 0.0, 0.0)  # put back in place: fixed
    end[7] = thing("Vase_0", 3.5, 0.03, heading=60.0)  # put back 3 cm off, turned 60 degrees: put off
    walk = [(o["type"], start_frame(*o["position"][:2]), 5) for o in goal[2:]]  # Apple, Book unseen
    walk += [(goal[0]["type"], start_frame(0.0, 0.0), 5)]
    now = [(o["type"], start_frame(*o["position"][:2]), 5) for o in start if o["id"] != "Cup_0"]
    now = [(label, c, 1 if label == "Pen" else n) for label, c, n in now]  # Pen seen once now
    out = fates(
        goal,
        start,
        end,
        walk,
        now,
        believed={"Key_0", "Fork_0", "Vase_0"},
        picked={"Fork_0", "Vase_0"},
        put={"Vase_0"},
        aims={"Vase_0": [3.51, 0.0]},
    )
    by_id = {c["id"]: c for c in out["changes"]}
    assert {k: by_id[k]["fate"] for k in ids} == {
        "Apple_0": "fixed",  # in place at the end, whatever the agent saw
        "Book_0": "missed_walkthrough",
        "Cup_0": "missed_unshuffle",
        "Pen_0": "glimpsed",
        "Mug_0": "not_believed",
        "Key_0": "not_picked",
        "Fork_0": "not_put",
        "Vase_0": "put_off",
    }
    vase = by_id["Vase_0"]
    assert vase["moved_cm"] == pytest.approx(100.0)
    assert vase["position_cm"] == pytest.approx(3.0) and vase["yaw_deg"] == pytest.approx(60.0)
    assert 0.0 < vase["iou"] < 0.5
    # aimed 1 cm off the goal, came to rest 3.2 cm from there
    assert vase["estimate_cm"] == pytest.approx(1.0)
    assert vase["landed_cm"] == pytest.approx(math.hypot(0.01, 0.03) * 100, abs=0.05)
    assert out["counts"]["pickupable"]["not_believed"] == 1 and out["newly"] == []


def test_openables_and_the_newly_misplaced() -> None:
    goal = [door("Fridge_0", False), door("Cabinet_0", False), door("Drawer_0", True)]
    goal += [thing("Mug_0", 0.0, 0.0), thing("Pen_0", 1.0, 0.0)]
    start = [door("Fridge_0", True), door("Cabinet_0", True), door("Drawer_0", True)]
    start += [thing("Mug_0", 0.0, 0.0), thing("Pen_0", 1.0, 0.0)]
    end = [door("Fridge_0", False), door("Cabinet_0", True), door("Drawer_0", False)]
    end += [thing("Mug_0", 0.5, 0.5), thing("Pen_0", 1.0, 0.2)]
    out = fates(goal, start, end, [], [], believed={"Cabinet_0", "Drawer_0"}, picked={"Mug_0"})
    assert [(c["id"], c["fate"]) for c in out["changes"]] == [
        ("Cabinet_0", "not_restored"),
        ("Fridge_0", "fixed"),
    ]
    assert sorted((n["id"], n["cause"]) for n in out["newly"]) == [
        ("Drawer_0", "believed"),  # closed on a false belief
        ("Mug_0", "picked"),
        ("Pen_0", "disturbed"),
    ]
    total = sum_counts([out, out])
    assert total["openable"] == {"fixed": 2, "not_believed": 0, "not_restored": 2}
    assert total["newly"] == {"picked": 2, "believed": 2, "disturbed": 2}


@pytest.mark.parametrize("a, b, gap", [(0, 10, 10), (0, 170, 10), (0, 180, 0), (30, -60, 90), (-45, 45, 90)])
def test_a_box_turned_half_way_round_is_the_same_box(a: float, b: float, gap: float) -> None:
    assert folded_yaw_gap(yaw(a), yaw(b)) == pytest.approx(gap, abs=1e-6)


def test_the_moved_objects_are_counted_by_what_held_them() -> None:
    from tidee.agent.evaluation.rearrange_eval import by_receptacle, receptacles_markdown

    ids = ["Apple_0", "Soap_0", "Soap_1"]
    goal = [thing("Apple_0", 0.0, 0.0, parent_type="Sink")]
    goal += [thing(oid, 1.0 + k, 0.0, parent_type="Bathtub") for k, oid in enumerate(ids[1:])]
    start = [
        thing(oid, 0.5 * k, 1.0, parent_type="GarbageCan" if k else "Floor") for k, oid in enumerate(ids)
    ]
    end = [thing("Apple_0", 0.0, 0.0, parent_type="Sink")] + [dict(o) for o in start[1:]]
    walk = [(o["type"], start_frame(*o["position"][:2]), 5) for o in goal[:2]]  # Soap_1's place unseen
    out = fates(goal, start, end, walk, [])
    by_id = {c["id"]: c for c in out["changes"]}
    assert (by_id["Apple_0"]["goal_on"], by_id["Apple_0"]["start_on"]) == ("Sink", "Floor")
    table = by_receptacle(out["changes"])
    assert table["goal_on"] == {
        "Sink": {"n": 1, "fixed": 1},
        # Soap_0: a Soap track lies at its goal place, none at its shuffled one; Soap_1: none at its goal
        "Bathtub": {"n": 2, "missed_unshuffle": 1, "missed_walkthrough": 1},
    }
    assert table["start_on"] == {
        "Floor": {"n": 1, "fixed": 1},
        "GarbageCan": {"n": 2, "missed_unshuffle": 1, "missed_walkthrough": 1},
    }
    md = receptacles_markdown({"clean": {"by_receptacle": table}, "oracle": {"by_receptacle": table}})
    assert "| goal: Bathtub | 2 | 0 / 1 / 1 | 0 / 1 / 1 |" in md
    assert "| shuffled: GarbageCan | 2 | 0 / 1 / 1 | 0 / 1 / 1 |" in md
    assert receptacles_markdown({"clean": {"by_receptacle": {"goal_on": {}, "start_on": {}}}}) == []
