"""Centroid relations (language paragraph) and oriented-box relations (Memex graph)."""

from __future__ import annotations

import math

import pytest

from tidee.agent.reasoning.relations import (
    FLOOR,
    Box3D,
    ObjectRef,
    box_relations,
    centroid_relations,
    closest_to,
    next_to,
    relation_paragraph,
    supported_by,
    words,
)


def rec(oid: str, label: str, centroid, box_min=None, box_max=None) -> ObjectRef:
    return ObjectRef(oid, label, centroid, box_min, box_max, receptacle=True)


# ----------------------------------------------------------------------------- words
@pytest.mark.parametrize(
    "label, expected",
    [
        ("SideTable", "side table"),
        ("TVStand", "tv stand"),
        ("CD", "cd"),
        ("AlarmClock", "alarm clock"),
        ("Floor", "floor"),
        ("Mug", "mug"),
        ("CounterTop", "counter top"),
        ("RemoteControl", "remote control"),
        ("Side_Table", "side table"),
    ],
)
def test_words(label: str, expected: str) -> None:
    assert words(label) == expected


def test_words_rejects_empty() -> None:
    with pytest.raises(ValueError, match="no words"):
        words("__")


# ----------------------------------------------------------------------------- supported_by
def test_mug_above_table_centroid_is_supported_by_table() -> None:
    table = rec("t", "DiningTable", (1.0, 0.0, 0.375))
    shelf = rec("s", "Shelf", (3.0, 3.0, 0.5))  # below the mug too, but far
    cabinet = rec("c", "Cabinet", (1.0, 0.2, 1.6))  # above: never a support
    chair = ObjectRef("ch", "Chair", (1.0, -0.3, 0.45))  # not a receptacle
    mug = ObjectRef("m", "Mug", (1.1, 0.1, 0.8))
    assert supported_by(mug, [shelf, cabinet, chair, table, mug]) is table


def test_low_object_with_nothing_under_it_is_on_the_floor() -> None:
    table = rec("t", "DiningTable", (1.0, 0.0, 0.375), (0.4, -0.4, 0.0), (1.6, 0.4, 0.75))
    ball = ObjectRef("b", "BasketBall", (3.0, 0.0, 0.05))
    assert supported_by(ball, [table]) == FLOOR
    # Under the table (the table's box contains its x, y, but the top is above): floor.
    under = ObjectRef("u", "BasketBall", (1.0, 0.0, 0.12))
    assert supported_by(under, [table]) == FLOOR
    # Nothing below at all: floor as well.
    high = ObjectRef("h", "Book", (3.0, 0.0, 0.9))
    assert supported_by(high, [rec("c", "Cabinet", (3.0, 0.0, 1.6))]) == FLOOR
    assert supported_by(high, []) == FLOOR


def test_box_contained_object_picks_highest_surface() -> None:
    # A low TV stand top at 0.12 m: an object at 0.15 m is on it, not on the floor.
    stand = rec("st", "TVStand", (0.0, 0.0, 0.06), (-0.5, -0.2, 0.0), (0.5, 0.2, 0.12))
    cd = ObjectRef("cd", "CD", (0.1, 0.05, 0.15))
    assert supported_by(cd, [stand]) is stand
    # A tray on a table: the higher surface wins although the table is nearer (centroid).
    table = rec("t", "DiningTable", (2.0, 0.0, 0.6), (1.4, -0.4, 0.0), (2.6, 0.4, 0.75))
    tray = rec("tr", "Tray", (2.3, 0.3, 0.765), (2.1, 0.15, 0.75), (2.5, 0.45, 0.78))
    apple = ObjectRef("a", "Apple", (2.35, 0.36, 0.82))
    assert supported_by(apple, [table, tray]) is tray
    # Just inside the tray's edge (y = 0.15) it is on the tray; well outside the tray's
    # footprint (but within a wide margin) the table under it explains the apple better.
    assert supported_by(ObjectRef("a2", "Apple", (2.35, 0.16, 0.82)), [table, tray]) is tray
    assert supported_by(ObjectRef("a3", "Apple", (2.35, -0.2, 0.82)), [table, tray], xy_margin_m=0.7) is table
    # Only the tray is a candidate: the margin still lets a partial box catch the apple.
    assert supported_by(ObjectRef("a5", "Apple", (2.35, 0.06, 0.82)), [tray]) is tray
    # A tall bottle (bottom 0.76) beside a microwave whose top (0.95) is below its centroid:
    # its box bottom says it stands on the table, not on the microwave.
    micro = rec("m", "Microwave", (2.3, -0.2, 0.85), (2.1, -0.35, 0.75), (2.5, -0.05, 0.95))
    bottle = ObjectRef("bo", "WineBottle", (2.3, -0.1, 1.0), (2.26, -0.14, 0.76), (2.34, -0.06, 1.2))
    assert supported_by(bottle, [table, micro]) is table
    assert supported_by(ObjectRef("a4", "Apple", (2.0, 0.0, 0.8)), [table, tray]) is table
    # Inside a shelf unit (its top is above the object): the smallest containing box.
    shelf = rec("sh", "Shelf", (5.0, 0.0, 0.9), (4.6, -0.2, 0.0), (5.4, 0.2, 1.8))
    room_thing = rec("big", "Cabinet", (5.0, 0.0, 1.0), (4.0, -1.0, 0.0), (6.0, 1.0, 2.0))
    book = ObjectRef("bk", "Book", (5.0, 0.0, 1.0))
    assert supported_by(book, [room_thing, shelf]) is shelf


def test_low_shelf_and_walled_container() -> None:
    # A remote on a coffee table's magazine shelf (9 cm up, under the top): the coffee
    # table, not the floor; the same remote lying on the floor under the table: the floor.
    table = rec("ct", "CoffeeTable", (0.0, 0.0, 0.22), (-0.6, -0.3, 0.0), (0.6, 0.3, 0.45))
    on_shelf = ObjectRef("r", "RemoteControl", (0.1, 0.0, 0.11), (0.0, -0.02, 0.095), (0.2, 0.02, 0.125))
    assert supported_by(on_shelf, [table]) is table
    on_floor = ObjectRef("r2", "RemoteControl", (0.1, 0.0, 0.015), (0.0, -0.02, 0.0), (0.2, 0.02, 0.03))
    assert supported_by(on_floor, [table]) == FLOOR
    # Off the floor but beside the table's footprint (the shelf rule does not grow it): floor band.
    beside = ObjectRef("r3", "RemoteControl", (0.65, 0.0, 0.11), (0.6, -0.02, 0.095), (0.7, 0.02, 0.125))
    assert supported_by(beside, [table]) == FLOOR
    # Of two boxes holding it, the smaller: a bathtub's floor, not the room-sized thing around it.
    tub = rec("tb", "Bathtub", (2.0, 0.0, 0.28), (1.2, -0.4, 0.0), (2.8, 0.4, 0.56))
    big = rec("big", "Cabinet", (2.0, 0.0, 1.0), (0.0, -2.0, 0.0), (4.0, 2.0, 2.0))
    bottle = ObjectRef("sb", "SprayBottle", (2.1, 0.1, 0.2), (2.05, 0.05, 0.12), (2.15, 0.15, 0.28))
    assert supported_by(bottle, [big, tub]) is tub
    # A dumbbell thrown into a box lies on the box's floor, 1 cm up: in the box (walled),
    # while under an open table at that height it is on the floor.
    box = rec("bx", "Box", (3.0, 0.0, 0.15), (2.8, -0.15, 0.0), (3.2, 0.15, 0.3))
    bell = ObjectRef("db", "Dumbbell", (3.0, 0.0, 0.05), (2.9, -0.04, 0.01), (3.1, 0.04, 0.09))
    assert supported_by(bell, [box]) is box
    assert (
        supported_by(
            ObjectRef("db2", "Dumbbell", (0.1, 0.0, 0.05), (0.0, -0.04, 0.01), (0.2, 0.04, 0.09)), [table]
        )
        == FLOOR
    )


def test_supported_by_excludes_the_target_itself() -> None:
    plate = ObjectRef("p", "Plate", (0.0, 0.0, 0.8), (-0.1, -0.1, 0.79), (0.1, 0.1, 0.81), receptacle=True)
    assert supported_by(plate, [plate]) == FLOOR


# ----------------------------------------------------------------------------- next_to, closest_to
def test_next_to_threshold_and_order() -> None:
    target = ObjectRef("x", "Pillow", (0.0, 0.0, 0.5))
    near = rec("a", "SideTable", (0.9, 0.0, 0.5))
    far = rec("b", "Sofa", (1.1, 0.0, 0.5))
    nearer = rec("c", "Bed", (0.0, 0.5, 0.5))
    small = ObjectRef("d", "Mug", (0.1, 0.0, 0.5))
    assert next_to(target, [far, near, small, nearer]) == [nearer, near]
    assert next_to(target, [far, near, small, nearer], d=1.5) == [nearer, near, far]
    assert next_to(target, [far, near, small, nearer], d=0.3, receptacles_only=False) == [small]
    with pytest.raises(ValueError, match="threshold"):
        next_to(target, [], d=0.0)
    assert closest_to(target, [far, near, small, nearer]) is small
    assert closest_to(target, [far, near, nearer]) is None
    assert closest_to(target, [far, near, nearer], include_receptacles=True) is nearer


# ----------------------------------------------------------------------------- paragraph
def small_bedroom() -> tuple[ObjectRef, list[ObjectRef]]:
    side_table = rec("st", "SideTable", (0.0, 0.0, 0.3), (-0.25, -0.25, 0.0), (0.25, 0.25, 0.6))
    bed = rec("bed", "Bed", (2.5, 0.0, 0.3), (1.5, -1.0, 0.0), (3.5, 1.0, 0.6))
    pillow = ObjectRef("p", "Pillow", (0.05, 0.0, 0.7))
    mug = ObjectRef("m", "Mug", (0.2, 0.1, 0.65))
    clock = ObjectRef("c", "AlarmClock", (-0.15, -0.1, 0.65))
    return pillow, [bed, side_table, mug, clock, pillow]


def test_relation_paragraph_exact() -> None:
    pillow, others = small_bedroom()
    assert relation_paragraph(pillow, others) == (
        "The pillow is next to the side table. The pillow is supported by the side table. "
        "The pillow is closest to the mug."
    )
    assert centroid_relations(pillow, others) == [
        ("next_to", "SideTable"),
        ("supported_by", "SideTable"),
        ("closest_to", "Mug"),
    ]
    # A larger threshold adds the bed after the side table (ordered by distance).
    assert relation_paragraph(pillow, others, d=3.0) == (
        "The pillow is next to the side table. The pillow is next to the bed. "
        "The pillow is supported by the side table. The pillow is closest to the mug."
    )


def test_relation_paragraph_floor_and_no_neighbours() -> None:
    cd = ObjectRef("cd", "CD", (4.0, 4.0, 0.01))
    stand = rec("tv", "TVStand", (0.0, 0.0, 0.3))
    assert relation_paragraph(cd, [stand, cd]) == "The cd is supported by the floor."


# ----------------------------------------------------------------------------- box relations
def test_book_on_table() -> None:
    table = Box3D((0.0, 0.0, 0.375), (1.2, 0.8, 0.75))
    book = Box3D((0.1, 0.0, 0.77), (0.2, 0.15, 0.04), yaw=0.3)
    rels = set(box_relations([("DiningTable", table), ("Book", book)]))
    assert (1, "supported_by", 0) in rels and (1, "above", 0) in rels
    assert (0, "below", 1) in rels
    assert (0, "supported_by", 1) not in rels
    assert not any(r in ("next_to", "facing", "aligned_with") for _, r, _ in rels)
    # Floating 0.3 m over the table: above but not supported.
    lamp = Box3D((0.1, 0.0, 1.2), (0.2, 0.2, 0.2))
    rels = set(box_relations([("DiningTable", table), ("Lamp", lamp)]))
    assert (1, "above", 0) in rels and (1, "supported_by", 0) not in rels
    # Beside the table at the same height: next to, not above.
    box = Box3D((0.9, 0.0, 0.2), (0.3, 0.3, 0.4))
    rels = set(box_relations([("DiningTable", table), ("Box", box)]))
    assert rels == {(0, "next_to", 1), (1, "next_to", 0)}


def test_chair_facing_table() -> None:
    table = Box3D((0.0, 0.0, 0.375), (1.2, 0.8, 0.75))
    chair = Box3D((0.0, -0.8, 0.45), (0.45, 0.45, 0.9), yaw=0.0)  # front = +y, the table
    turned = Box3D((0.0, -0.8, 0.45), (0.45, 0.45, 0.9), yaw=math.pi)  # front = -y
    rels = box_relations([("DiningTable", table), ("Chair", chair)])
    assert (1, "facing", 0) in rels
    assert (0, "facing", 1) not in rels  # a dining table has no front
    assert (1, "next_to", 0) in rels
    assert (1, "facing", 0) not in box_relations([("DiningTable", table), ("Chair", turned)])
    # A non-facing class in the same pose does not face anything.
    assert (1, "facing", 0) not in box_relations([("DiningTable", table), ("Stool", chair)])
    # A TV faces a sofa 1.8 m in front of it, not one 2.5 m away.
    tv = Box3D((0.0, 0.0, 1.0), (1.0, 0.1, 0.6), yaw=math.pi / 2)  # front = -x
    sofa_near = Box3D((-1.8, 0.0, 0.4), (2.0, 0.9, 0.8), yaw=-math.pi / 2)
    sofa_far = Box3D((-2.5 - 0.45, 0.0, 0.4), (2.0, 0.9, 0.8), yaw=-math.pi / 2)
    assert (0, "facing", 1) in box_relations([("Television", tv), ("Sofa", sofa_near)])
    assert (0, "facing", 1) not in box_relations([("Television", tv), ("Sofa", sofa_far)])
    # The sofa (front = +x) faces the TV back.
    assert (1, "facing", 0) in box_relations([("Television", tv), ("Sofa", sofa_near)])


def test_two_aligned_cabinets() -> None:
    a = Box3D((0.0, 2.0, 0.45), (0.6, 0.5, 0.9))
    b = Box3D((0.6, 2.0, 0.45), (0.6, 0.5, 0.9))  # side by side, touching
    perpendicular = Box3D((-0.55, 2.0, 0.45), (0.5, 0.4, 0.9), yaw=math.pi / 2)
    skew = Box3D((0.3, 1.0, 0.45), (0.6, 0.5, 0.9), yaw=math.radians(30))
    offset = Box3D((1.25, 2.3, 0.45), (0.6, 0.5, 0.9))  # shifted back 0.3 m
    far = Box3D((3.0, 2.0, 0.45), (0.6, 0.5, 0.9))  # coplanar but 2.1 m away
    rels = set(
        box_relations(
            [
                ("Cabinet", a),
                ("Cabinet", b),
                ("Cabinet", perpendicular),
                ("Cabinet", skew),
                ("Cabinet", offset),
                ("Cabinet", far),
            ]
        )
    )
    assert {(0, "aligned_with", 1), (1, "aligned_with", 0)} <= rels
    assert (0, "next_to", 1) in rels
    assert (0, "aligned_with", 2) in rels  # perpendicular, coplanar
    assert (0, "aligned_with", 3) not in rels and (3, "aligned_with", 0) not in rels
    assert (1, "aligned_with", 4) in rels  # side faces x = 0.9, 0.95
    assert (0, "aligned_with", 4) not in rels  # nothing within 0.1 m
    assert (0, "aligned_with", 5) not in rels and (1, "aligned_with", 5) not in rels


def test_box_relations_order_is_deterministic() -> None:
    table = Box3D((0.0, 0.0, 0.375), (1.2, 0.8, 0.75))
    book = Box3D((0.1, 0.0, 0.77), (0.2, 0.15, 0.04))
    chair = Box3D((0.0, -0.8, 0.45), (0.45, 0.45, 0.9))
    boxes = [("DiningTable", table), ("Book", book), ("Chair", chair)]
    rels = box_relations(boxes)
    assert rels == sorted(rels, key=lambda r: (r[0], r[2]))
    assert rels == box_relations(boxes)


def test_invalid_inputs() -> None:
    with pytest.raises(ValueError, match="size"):
        Box3D((0, 0, 0), (1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="both"):
        ObjectRef("a", "Mug", (0, 0, 0), box_min=(0, 0, 0))
    with pytest.raises(ValueError, match="exceeds"):
        ObjectRef("a", "Mug", (0, 0, 0), (1, 0, 0), (0, 1, 1))
    with pytest.raises(ValueError, match="centroid"):
        ObjectRef("a", "Mug", (0, 0))
