"""Mess-up statistics: five objects really out of place, nothing else moved, deterministic."""

from __future__ import annotations

import pytest

from tidee.server.catalog import is_plausible
from tidee.server.episode import SceneLibrary
from tidee.server.world import World


@pytest.fixture(scope="module")
def world():
    w = World(renderer="tiny")
    yield w
    w.close()


@pytest.mark.parametrize("room_type,seed", [("Kitchen", 200), ("Bedroom", 201), ("Bathroom", 202)])
def test_messup_moves_objects_out_of_place(world, room_type, seed):
    lib = SceneLibrary()
    tidy = lib.scene(world, room_type, seed, None)
    messy = lib.scene(world, room_type, seed, 0)
    assert 3 <= len(messy.mess) <= 5, [m.id for m in messy.mess]
    present = sorted({o.type for o in tidy.objects if o.receptacle and not o.pickupable})
    tidy_by_id, messy_by_id = tidy.by_id(), messy.by_id()
    moved = {m.id for m in messy.mess}
    for m in messy.mess:
        o = messy_by_id[m.id]
        assert o.parent == m.messy_parent and o.parent_type == m.messy_parent_type
        assert m.original_parent == tidy_by_id[m.id].parent
        assert m.messy_parent != m.original_parent
        assert not is_plausible(o.type, o.variant, room_type, o.parent_type, present), (o.id, o.parent_type)
        assert m.how in ("drop", "throw")
    for oid, o in tidy_by_id.items():
        if o.pickupable and oid not in moved:
            assert messy_by_id[oid].parent == o.parent, f"{oid} was disturbed"


def test_messup_is_deterministic_and_varies_by_index(world):
    a = SceneLibrary().scene(world, "LivingRoom", 200, 1)
    b = SceneLibrary().scene(world, "LivingRoom", 200, 1)
    c = SceneLibrary().scene(world, "LivingRoom", 200, 2)
    assert [m.id for m in a.mess] == [m.id for m in b.mess]
    assert a.to_dict() == b.to_dict()
    assert [m.id for m in a.mess] != [m.id for m in c.mess] or a.to_dict() != c.to_dict()


def test_throw_and_drop_both_occur(world):
    hows = set()
    lib = SceneLibrary()
    for k in range(3):
        hows |= {m.how for m in lib.scene(world, "LivingRoom", 201, k).mess}
    assert hows == {"drop", "throw"}
