"""RoomR's 2-phase rearrangement metrics: oriented-box IoU, pose energy, episode metrics, means.

Every expected value is worked out by hand in the comment next to it. Boxes have their
``position`` at the centre of the bottom face, as the simulator exports them.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest

from tidee.agent.evaluation.rearrange_metrics import (
    aggregate,
    box_corners,
    episode_metrics,
    iou_3d,
    object_kind,
    openness,
    pose_difference_energy,
    pose_iou,
    poses_equal,
    rotation_matrix,
)

R2 = math.sqrt(0.5)
YAW90 = [0.0, 0.0, R2, R2]  # 90 degrees about z
ROLL90 = [R2, 0.0, 0.0, R2]  # 90 degrees about x
IDENTITY = [0.0, 0.0, 0.0, 1.0]


def yaw(deg: float) -> list[float]:
    h = math.radians(deg) / 2
    return [0.0, 0.0, math.sin(h), math.cos(h)]


def item(
    oid: str = "Mug_1",
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0),
    size: tuple[float, float, float] = (1.0, 1.0, 1.0),
    orn: list[float] | None = None,
    **kw: Any,
) -> dict[str, Any]:
    """A pickupable object, shaped like an ``Episode.object_states()`` entry."""
    d: dict[str, Any] = {
        "id": oid,
        "type": oid.split("_")[0],
        "variant": None,
        "pickupable": True,
        "receptacle": False,
        "openable": False,
        "is_open": False,
        "parent": "Floor",
        "parent_type": "Floor",
        "position": list(pos),
        "orientation": list(orn or IDENTITY),
        "size": list(size),
    }
    d.update(kw)
    return d


def door(oid: str = "Fridge_1", is_open: bool = False, **kw: Any) -> dict[str, Any]:
    """An openable piece of furniture."""
    return item(oid, (2.0, 2.0, 0.0), (0.8, 0.7, 1.8), pickupable=False, openable=True, is_open=is_open, **kw)


def furniture(oid: str = "Table_1", pos: tuple[float, float, float] = (3.0, 0.0, 0.0)) -> dict[str, Any]:
    return item(oid, pos, (1.2, 0.8, 0.75), pickupable=False, receptacle=True)


def moved(
    obj: dict[str, Any], dx: float = 0.0, dy: float = 0.0, dz: float = 0.0, **kw: Any
) -> dict[str, Any]:
    x, y, z = obj["position"]
    return {**obj, "position": [x + dx, y + dy, z + dz], **kw}


# ---------------------------------------------------------------- boxes and IoU


def test_box_corners_bottom_centre_and_yaw() -> None:
    # A 2 x 1 x 0.5 box at (1, 2, 3) turned 90 degrees about z: its long side now runs along y,
    # so x spans 1 +- 0.5, y spans 2 +- 1, and z runs from the bottom face at 3 up to 3.5.
    c = box_corners(item(pos=(1.0, 2.0, 3.0), size=(2.0, 1.0, 0.5), orn=YAW90))
    assert c.shape == (8, 3)
    np.testing.assert_allclose(c.min(0), [0.5, 1.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(c.max(0), [1.5, 3.0, 3.5], atol=1e-12)


def test_box_corners_tilt_turns_about_the_bottom_centre() -> None:
    # 90 degrees about x maps local (x, y, z) to (x, -z, y): the unit cube's z in [0, 1] becomes
    # y in [-1, 0] and its y in [-0.5, 0.5] becomes z in [-0.5, 0.5].
    c = box_corners(item(orn=ROLL90))
    np.testing.assert_allclose(c.min(0), [-0.5, -1.0, -0.5], atol=1e-12)
    np.testing.assert_allclose(c.max(0), [0.5, 0.0, 0.5], atol=1e-12)


def test_rotation_matrix_normalises_the_quaternion() -> None:
    # (0, 0, 2, 2) is 90 degrees about z scaled by 2*sqrt(2): x goes to y.
    np.testing.assert_allclose(rotation_matrix([0, 0, 2, 2]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    with pytest.raises(ValueError):
        rotation_matrix([0, 0, 0, 0])


def test_iou_identical_boxes_is_one() -> None:
    a = item(pos=(0.3, -1.2, 0.7), size=(0.2, 0.4, 0.1), orn=yaw(33))
    assert iou_3d(a, dict(a)) == pytest.approx(1.0, abs=1e-9)


def test_iou_disjoint_and_touching_boxes_is_zero() -> None:
    # Centres 2 m apart along x with 1 m boxes: a 1 m gap. Then 1 m apart: the faces touch
    # (a flat intersection of volume 0).
    a = item()
    assert iou_3d(a, item(pos=(2.0, 0.0, 0.0))) == 0.0
    assert iou_3d(a, item(pos=(1.0, 0.0, 0.0))) == pytest.approx(0.0, abs=1e-9)
    # Apart only vertically: one cube on top of the other, 0.5 m gap.
    assert iou_3d(a, item(pos=(0.0, 0.0, 1.5))) == 0.0


def test_iou_unit_box_shifted_by_half_its_width() -> None:
    # Overlap 0.5 x 1 x 1 = 0.5; union 1 + 1 - 0.5 = 1.5; IoU = 0.5 / 1.5 = 1/3.
    assert iou_3d(item(), item(pos=(0.5, 0.0, 0.0))) == pytest.approx(1 / 3, abs=1e-9)


def test_iou_box_inside_a_box() -> None:
    # A 0.5 m cube inside the unit cube: intersection 0.125, union 1; IoU = 0.125.
    assert iou_3d(item(), item(pos=(0.1, -0.1, 0.2), size=(0.5, 0.5, 0.5))) == pytest.approx(0.125, abs=1e-9)


def test_iou_yaw_90_square_and_oblong() -> None:
    # Square in x-y (1 x 1 x 1): turning it 90 degrees about z maps the box onto itself: IoU 1.
    assert iou_3d(item(), item(orn=YAW90)) == pytest.approx(1.0, abs=1e-9)
    # 2 x 1 x 1, turned 90 degrees: x in [-1, 1], y in [-0.5, 0.5] against x in [-0.5, 0.5],
    # y in [-1, 1]: overlap 1 x 1 x 1 = 1; union 2 + 2 - 1 = 3; IoU 1/3.
    assert iou_3d(item(size=(2, 1, 1)), item(size=(2, 1, 1), orn=YAW90)) == pytest.approx(1 / 3, abs=1e-9)


def test_iou_yaw_45_unit_cube() -> None:
    # A unit square and the same square turned 45 degrees overlap in a regular octagon: the
    # turned square pokes (sqrt2/2 - 1/2) past each side in a right triangle of area
    # (sqrt2/2 - 1/2)^2 = (3 - 2 sqrt2)/4, four of them: overlap = 1 - (3 - 2 sqrt2) = 2 sqrt2 - 2.
    # IoU = (2 sqrt2 - 2) / (2 - (2 sqrt2 - 2)) = 2(sqrt2 - 1) / (2 sqrt2 (sqrt2 - 1)) = 1/sqrt2.
    assert iou_3d(item(), item(orn=yaw(45))) == pytest.approx(1 / math.sqrt(2), abs=1e-9)


def test_iou_tilted_90_about_x() -> None:
    # Tilted cube: x in [-0.5, 0.5], y in [-1, 0], z in [-0.5, 0.5] (see the corners test);
    # against x in [-0.5, 0.5], y in [-0.5, 0.5], z in [0, 1]: overlap 1 x 0.5 x 0.5 = 0.25;
    # union 2 - 0.25 = 1.75; IoU = 1/7.
    assert iou_3d(item(), item(orn=ROLL90)) == pytest.approx(1 / 7, abs=1e-9)


def _inside(obj: dict[str, Any], pts: np.ndarray) -> np.ndarray:
    rot = rotation_matrix(obj["orientation"])
    local = (pts - np.asarray(obj["position"])) @ rot
    half = np.asarray(obj["size"]) / 2
    return (np.abs(local[:, :2]) <= half[:2]).all(1) & (local[:, 2] >= 0) & (local[:, 2] <= 2 * half[2])


def test_iou_arbitrary_tilt_matches_monte_carlo() -> None:
    # No closed form for two boxes tilted about skew axes: count 400k uniform points in the
    # axis-aligned hull of both boxes (standard error of the estimate about 0.002).
    q = np.array([0.3, -0.2, 0.4, 0.85])
    a = item(size=(0.6, 0.4, 0.3))
    b = item(pos=(0.1, 0.05, -0.05), size=(0.5, 0.5, 0.25), orn=list(q / np.linalg.norm(q)))
    corners = np.vstack([box_corners(a), box_corners(b)])
    rng = np.random.default_rng(0)
    pts = rng.uniform(corners.min(0), corners.max(0), size=(400_000, 3))
    ia, ib = _inside(a, pts), _inside(b, pts)
    estimate = (ia & ib).sum() / (ia | ib).sum()
    assert 0.1 < estimate < 0.9  # a real partial overlap
    assert iou_3d(a, b) == pytest.approx(estimate, abs=0.01)


def test_iou_is_symmetric() -> None:
    a = item(size=(0.6, 0.4, 0.3), orn=yaw(20))
    b = item(pos=(0.2, 0.1, 0.05), size=(0.5, 0.5, 0.25), orn=[0.1, 0.2, 0.0, 0.97])
    assert iou_3d(a, b) == pytest.approx(iou_3d(b, a), abs=1e-9)


# ---------------------------------------------------------------- kinds and openness


def test_kinds() -> None:
    assert object_kind(item()) == "pickupable"
    assert object_kind(item(openable=True)) == "pickupable"  # pickupable wins
    assert object_kind(door()) == "openable"
    assert object_kind(furniture()) is None


def test_openness_from_is_open_or_explicit_value() -> None:
    assert openness(door(is_open=True)) == 1.0
    assert openness(door(is_open=False)) == 0.0
    assert openness(door(is_open=True, openness=0.7)) == 0.7


# ---------------------------------------------------------------- energy and pose equality


def test_energy_zero_in_place() -> None:
    g = item(pos=(1.0, 2.0, 0.75), size=(0.1, 0.1, 0.12), orn=yaw(30))
    assert pose_difference_energy(g, dict(g)) == 0.0
    assert poses_equal(g, dict(g))


def test_energy_iou_part_for_a_partial_overlap() -> None:
    # Shifted half its width: IoU 1/3 < 0.5, so energy = 0.5 * (1 - (1/3) / 0.5) + 0 = 1/6.
    g = item()
    assert pose_difference_energy(g, moved(g, dx=0.5)) == pytest.approx(1 / 6, abs=1e-9)
    assert not poses_equal(g, moved(g, dx=0.5))


def test_energy_zero_above_the_iou_threshold() -> None:
    # Shifted a quarter: overlap 0.75, union 1.25, IoU 0.6 >= 0.5: energy 0 and equal.
    g = item()
    assert pose_difference_energy(g, moved(g, dx=0.25)) == 0.0
    assert poses_equal(g, moved(g, dx=0.25))


def test_energy_position_barrier_for_far_moves() -> None:
    # A 0.2 m cube moved 1 m along x: no overlap (IoU part 0.5 * 1); the nearest corners are
    # 1 - 0.2 = 0.8 m apart, so the position part is 0.5 * 0.8 / 2.0 = 0.2: energy 0.7.
    g = item(size=(0.2, 0.2, 0.2))
    assert pose_difference_energy(g, moved(g, dx=1.0)) == pytest.approx(0.7, abs=1e-9)
    # Moved 3 m: corners 2.8 m apart, past the 2 m barrier: position part 0.5, energy 1.
    assert pose_difference_energy(g, moved(g, dx=3.0)) == pytest.approx(1.0, abs=1e-12)
    # Moved diagonally by (0.6, 0.8, 0): nearest corners (0.4, 0.6, 0) apart, |.| = sqrt(0.52);
    # energy = 0.5 + 0.5 * sqrt(0.52) / 2.
    assert pose_difference_energy(g, moved(g, dx=0.6, dy=0.8)) == pytest.approx(
        0.5 + 0.25 * math.sqrt(0.52), abs=1e-9
    )


def test_near_identical_pose_counts_as_iou_one() -> None:
    # A 2 cm cube moved 9 mm: the boxes' true IoU is (0.011 / 0.029) ~ 0.379 < 0.5, but the
    # positions are under 1 cm apart and the orientations under 10 degrees: IoU 1, in place.
    g = item(size=(0.02, 0.02, 0.02))
    near = moved(g, dx=0.009, orientation=yaw(9))
    assert iou_3d(g, moved(g, dx=0.009)) == pytest.approx(0.011 / 0.029, abs=1e-9)
    assert pose_iou(g, near) == 1.0
    assert pose_difference_energy(g, near) == 0.0
    # 11 mm, or 15 degrees: the real IoU again, under 0.5: misplaced.
    assert pose_difference_energy(g, moved(g, dx=0.011)) > 0
    assert pose_difference_energy(g, moved(g, dx=0.009, orientation=yaw(15))) > 0


def test_held_object_is_misplaced() -> None:
    # Held: at the agent's x, y and z = -5. Its box is 5 m under the floor: no overlap, corners
    # more than 2 m from the goal's: energy 0.5 + 0.5 = 1.
    g = item(pos=(1.0, 1.0, 0.75), size=(0.1, 0.1, 0.1))
    held = moved(g, dx=0.3, dz=-5.75)
    assert held["position"][2] == pytest.approx(-5.0)
    assert pose_difference_energy(g, held) == pytest.approx(1.0)
    assert not poses_equal(g, held)


def test_openable_open_vs_closed() -> None:
    # Goal closed (0.0), now open (1.0): difference 1 > 0.2: energy 1, not equal.
    assert pose_difference_energy(door(is_open=False), door(is_open=True)) == 1.0
    assert not poses_equal(door(is_open=False), door(is_open=True))
    assert pose_difference_energy(door(is_open=True), door(is_open=True)) == 0.0
    # Openable furniture is compared by openness only: moving it changes nothing.
    assert pose_difference_energy(door(), moved(door(), dx=2.0)) == 0.0


def test_openable_within_tolerance() -> None:
    # Goal open (1.0), now 0.9 open: difference 0.1 <= 0.2: in place. 0.75: 0.25 > 0.2: misplaced.
    assert pose_difference_energy(door(is_open=True), door(is_open=True, openness=0.9)) == 0.0
    assert poses_equal(door(is_open=True), door(is_open=True, openness=0.9))
    assert pose_difference_energy(door(is_open=True), door(is_open=True, openness=0.75)) == 1.0
    assert not poses_equal(door(is_open=True), door(is_open=True, openness=0.75))


def test_missing_object_energy_one() -> None:
    assert pose_difference_energy(item(), None) == 1.0
    assert pose_difference_energy(door(), None) == 1.0
    assert not poses_equal(item(), None)


def test_unscored_object_raises() -> None:
    with pytest.raises(ValueError, match="neither pickupable nor openable"):
        pose_difference_energy(furniture(), furniture())
    with pytest.raises(ValueError):
        poses_equal(furniture(), furniture())


# ---------------------------------------------------------------- episode metrics


def small(oid: str, x: float) -> dict[str, Any]:
    """A 0.2 m cube on the floor at (x, 0)."""
    return item(oid, (x, 0.0, 0.0), (0.2, 0.2, 0.2))


GOAL6 = [small(f"Obj_{i}", float(i)) for i in range(6)]  # Obj_0 .. Obj_5, 1 m apart


def far(obj: dict[str, Any]) -> dict[str, Any]:
    """Moved 3 m along y: energy 1 (see the barrier test)."""
    return moved(obj, dy=3.0)


def states(far_ids: set[int]) -> list[dict[str, Any]]:
    return [far(o) if i in far_ids else dict(o) for i, o in enumerate(GOAL6)]


def test_episode_two_of_four_fixed() -> None:
    # 6 objects, 4 shuffled (energy 1 each): start_misplaced 4, start_energy 4. The agent puts
    # back Obj_0 and Obj_1: end_misplaced 2, fixed 2, newly 0. FixedStrict = 2/4 = 0.5;
    # Misplaced = 2/4 = 0.5; Energy = 2/4 = 0.5; not a success.
    m = episode_metrics(GOAL6, states({0, 1, 2, 3}), states({2, 3}))
    assert m["start_misplaced"] == 4 and m["end_misplaced"] == 2
    assert m["fixed"] == 2 and m["newly_misplaced"] == 0
    assert m["prop_fixed"] == pytest.approx(0.5)
    assert m["fixed_strict"] == pytest.approx(0.5)
    assert m["misplaced"] == pytest.approx(0.5)
    assert m["start_energy"] == pytest.approx(4.0) and m["end_energy"] == pytest.approx(2.0)
    assert m["energy"] == pytest.approx(0.5)
    assert m["success"] is False
    assert m["objects_scored"] == 6


def test_episode_newly_misplaced_zeroes_fixed_strict() -> None:
    # As above, and the agent also knocks Obj_5 (in place at the start) 3 m away: end_misplaced
    # 3, newly 1, fixed still 2. prop_fixed = 0.5 but FixedStrict = 0; Misplaced = 3/4;
    # Energy = 3/4.
    m = episode_metrics(GOAL6, states({0, 1, 2, 3}), states({2, 3, 5}))
    assert m["newly_misplaced"] == 1 and m["fixed"] == 2 and m["end_misplaced"] == 3
    assert m["prop_fixed"] == pytest.approx(0.5)
    assert m["fixed_strict"] == 0.0
    assert m["misplaced"] == pytest.approx(0.75)
    assert m["energy"] == pytest.approx(0.75)
    rows = {r["id"]: r for r in m["objects"]}
    assert rows["Obj_5"]["misplaced_start"] is False and rows["Obj_5"]["misplaced_end"] is True


def test_episode_success_only_when_everything_is_in_place() -> None:
    # All four back: success, FixedStrict 1, Misplaced 0/4 = 0, Energy 0/4 = 0.
    m = episode_metrics(GOAL6, states({0, 1, 2, 3}), states(set()))
    assert m["success"] is True
    assert m["fixed_strict"] == 1.0 and m["misplaced"] == 0.0 and m["energy"] == 0.0
    # Obj_3 only half back (a 0.2 m cube 0.1 m off: IoU 1/3, energy 1/6 > 0): no success;
    # Misplaced 1/4; Energy (1/6) / 4 = 1/24; FixedStrict 3/4.
    end = states(set())
    end[3] = moved(GOAL6[3], dx=0.1)
    m = episode_metrics(GOAL6, states({0, 1, 2, 3}), end)
    assert m["success"] is False
    assert m["end_misplaced"] == 1
    assert m["misplaced"] == pytest.approx(0.25)
    assert m["energy"] == pytest.approx(1 / 24)
    assert m["fixed_strict"] == pytest.approx(0.75)


def test_episode_by_kind_split_ignores_furniture() -> None:
    # Goal: 2 pickupables (Cup_1, Cup_2), 2 openables (Fridge_1 and Cabinet_1, closed), a table.
    # Start: Cup_1 far (1), Fridge_1 open (1); the table also moved, but tables are not scored.
    # End: Cup_1 back, Fridge_1 still open, Cabinet_1 newly opened.
    #   all: start 2, end 2, fixed 1, newly 1: prop_fixed 1/2, FixedStrict 0, Misplaced 2/2 = 1,
    #        Energy 2/2 = 1.
    #   pickupable: start 1, end 0, fixed 1: FixedStrict 1, Misplaced 0, Energy 0, success.
    #   openable: start 1, end 2, fixed 0, newly 1: FixedStrict 0, Misplaced 2, Energy 2.
    cup1, cup2 = small("Cup_1", 0.0), small("Cup_2", 1.0)
    fridge, cabinet, table = door("Fridge_1"), door("Cabinet_1"), furniture()
    goal = [cup1, cup2, fridge, cabinet, table]
    start = [far(cup1), cup2, door("Fridge_1", True), cabinet, moved(table, dx=1.0)]
    end = [cup1, cup2, door("Fridge_1", True), door("Cabinet_1", True), moved(table, dx=1.0)]
    m = episode_metrics(goal, start, end)
    assert m["objects_scored"] == 4
    assert sorted(r["id"] for r in m["objects"]) == ["Cabinet_1", "Cup_1", "Cup_2", "Fridge_1"]
    assert (m["start_misplaced"], m["end_misplaced"], m["fixed"], m["newly_misplaced"]) == (2, 2, 1, 1)
    assert m["prop_fixed"] == pytest.approx(0.5) and m["fixed_strict"] == 0.0
    assert m["misplaced"] == pytest.approx(1.0) and m["energy"] == pytest.approx(1.0)
    p, o = m["by_kind"]["pickupable"], m["by_kind"]["openable"]
    assert (p["objects_scored"], o["objects_scored"]) == (2, 2)
    assert p["success"] is True and p["fixed_strict"] == 1.0 and p["misplaced"] == 0.0 and p["energy"] == 0.0
    assert o["success"] is False and o["fixed_strict"] == 0.0
    assert o["misplaced"] == pytest.approx(2.0) and o["energy"] == pytest.approx(2.0)
    assert {r["id"]: r["kind"] for r in m["objects"]}["Fridge_1"] == "openable"


def test_episode_missing_objects_count_as_misplaced() -> None:
    # Obj_2 absent from the end list (energy 1, misplaced) although it was in place at the
    # start: newly misplaced, FixedStrict 0. Obj_0 absent from the start list: misplaced at
    # the start (energy 1), present and in place at the end: fixed.
    start = states(set())[1:]
    end = [o for o in states(set()) if o["id"] != "Obj_2"]
    m = episode_metrics(GOAL6, start, end)
    rows = {r["id"]: r for r in m["objects"]}
    assert (
        rows["Obj_2"]["missing_end"] and rows["Obj_2"]["misplaced_end"] and rows["Obj_2"]["energy_end"] == 1.0
    )
    assert rows["Obj_0"]["missing_start"] and rows["Obj_0"]["energy_start"] == 1.0
    assert (m["start_misplaced"], m["end_misplaced"], m["fixed"], m["newly_misplaced"]) == (1, 1, 1, 1)
    assert m["fixed_strict"] == 0.0 and m["misplaced"] == 1.0


def test_episode_held_object_at_the_end_is_misplaced() -> None:
    # Obj_0 was shuffled and is still in the agent's hand at the end (z = -5): not fixed.
    end = states(set())
    end[0] = moved(GOAL6[0], dx=0.5, dz=-5.0)
    m = episode_metrics(GOAL6, states({0}), end)
    assert m["end_misplaced"] == 1 and m["fixed"] == 0
    assert m["fixed_strict"] == 0.0 and m["misplaced"] == 1.0 and m["energy"] == pytest.approx(1.0)


def test_episode_objects_not_in_the_goal_are_ignored() -> None:
    extra = small("Stray_1", 9.0)
    m = episode_metrics(GOAL6, [*states({0}), extra], [*states(set()), far(extra)])
    assert m["objects_scored"] == 6 and m["end_misplaced"] == 0 and m["success"] is True


def test_episode_zero_denominators() -> None:
    # Nothing shuffled, nothing touched: prop_fixed and FixedStrict 1 (RoomR), Misplaced and
    # Energy undefined (None: no misplaced object, no energy at the start), success.
    m = episode_metrics(GOAL6, states(set()), states(set()))
    assert m["prop_fixed"] == 1.0 and m["fixed_strict"] == 1.0
    assert m["misplaced"] is None and m["energy"] is None
    assert m["success"] is True
    # Nothing shuffled, the agent knocks one away: FixedStrict 0, ratios still None, no success.
    m = episode_metrics(GOAL6, states(set()), states({4}))
    assert m["fixed_strict"] == 0.0 and m["prop_fixed"] == 1.0 and m["newly_misplaced"] == 1
    assert m["misplaced"] is None and m["energy"] is None
    assert m["success"] is False


def test_episode_kind_with_nothing_misplaced_at_start() -> None:
    # Only a pickupable was shuffled; the openables were all in place at the start.
    goal = [small("Cup_1", 0.0), door("Fridge_1")]
    m = episode_metrics(goal, [far(goal[0]), goal[1]], goal)
    o = m["by_kind"]["openable"]
    assert o["start_misplaced"] == 0 and o["fixed_strict"] == 1.0 and o["prop_fixed"] == 1.0
    assert o["misplaced"] is None and o["energy"] is None and o["success"] is True
    assert m["misplaced"] == 0.0 and m["energy"] == 0.0
    # A kind with no objects at all reads the same.
    n = episode_metrics([small("Cup_1", 0.0)], [far(small("Cup_1", 0.0))], [small("Cup_1", 0.0)])
    assert n["by_kind"]["openable"]["objects_scored"] == 0
    assert n["by_kind"]["openable"]["misplaced"] is None and n["by_kind"]["openable"]["fixed_strict"] == 1.0


def test_episode_metrics_json_round_trip() -> None:
    # Plain Python types only (a numpy bool or float64 would not survive json.dumps unchanged).
    m = episode_metrics(GOAL6, states({0, 1, 2, 3}), states({2, 3, 5}))
    assert json.loads(json.dumps(m)) == m
    assert type(m["success"]) is bool and type(m["objects"][0]["misplaced_end"]) is bool
    assert type(m["start_misplaced"]) is int and type(m["energy"]) is float


def test_episode_duplicate_ids_rejected() -> None:
    with pytest.raises(ValueError, match="twice"):
        episode_metrics(GOAL6, [*states(set()), GOAL6[0]], states(set()))


# ---------------------------------------------------------------- aggregate


def test_aggregate_means_over_defined_episodes() -> None:
    # r1: FS 0.5, Misplaced 0.5, Energy 0.5, no success. r2: FS 1, Misplaced 0, Energy 0, success.
    # r3 (nothing shuffled): FS 1, Misplaced / Energy None, success.
    # success 2/3; FS (0.5 + 1 + 1)/3 = 5/6; Misplaced (0.5 + 0)/2 = 0.25 over 2; Energy 0.25 over 2.
    r1 = episode_metrics(GOAL6, states({0, 1, 2, 3}), states({2, 3}))
    r2 = episode_metrics(GOAL6, states({0, 1, 2, 3}), states(set()))
    r3 = episode_metrics(GOAL6, states(set()), states(set()))
    a = aggregate([r1, r2, r3])
    assert a["episodes"] == 3
    assert a["success"] == pytest.approx(2 / 3)
    assert a["fixed_strict"] == pytest.approx(5 / 6)
    assert a["misplaced"] == pytest.approx(0.25) and a["misplaced_episodes"] == 2
    assert a["energy"] == pytest.approx(0.25) and a["energy_episodes"] == 2
    assert a["success_episodes"] == 3
    # All objects are pickupable: the same by kind; no openable ever misplaced: its ratios None,
    # FixedStrict 1 and success 1 in every episode.
    assert a["by_kind"]["pickupable"]["fixed_strict"] == pytest.approx(5 / 6)
    assert (
        a["by_kind"]["openable"]["misplaced"] is None and a["by_kind"]["openable"]["misplaced_episodes"] == 0
    )
    assert a["by_kind"]["openable"]["fixed_strict"] == 1.0 and a["by_kind"]["openable"]["success"] == 1.0
    json.dumps(a)


def test_aggregate_of_nothing() -> None:
    a = aggregate([])
    assert a["episodes"] == 0
    assert all(a[k] is None for k in ("success", "fixed_strict", "misplaced", "energy"))
    assert a["by_kind"]["pickupable"]["episodes"] == 0
