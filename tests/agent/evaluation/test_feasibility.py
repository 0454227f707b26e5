"""The preference evaluation's check that the simulator can carry out a placement, on a real room."""

from __future__ import annotations

from tidee.agent.evaluation.feasibility import PlacementCheck


def test_a_box_too_big_for_the_side_table_does_not_fit_but_goes_on_the_bed() -> None:
    with PlacementCheck() as check:
        room = check.room("Bedroom", 204, 2)  # Box_0 is 48 x 36 cm; the side table's top 40 x 34
        box = next(o for o in room.check.scene("Bedroom", 204, 2).objects if o.type == "Box")
        assert room("Box", "SideTable") is False
        assert room("Box", "Bed") is True
        assert room("Box", "Floor") is True
        assert room(("Box",), "SideTable") is False  # a one-category group is the category
        assert room("Box", "Toaster") is False  # no such receptacle in the room
        again = check.scene("Bedroom", 204, 2).by_id()[box.id]  # each check starts from the mess
        assert again.parent_type == box.parent_type and again.position == box.position
