"""tidee eval preferences: the scripted profile and the scoring, on hand-made records."""

from __future__ import annotations

from tidee.agent.evaluation.preference_eval import GROUP_PHRASES, score, script_profile


def _obj(i, t, moved, orig, final, found=True):
    return {
        "id": f"{t}_{i}",
        "type": t,
        "variant": None,
        "moved": moved,
        "found": found,
        "picked": moved,
        "original_parent_type": orig,
        "final_parent_type": final,
    }


def _rec(variant, mug, apple, plate, bowl="Shelf"):
    return {
        "variant": variant,
        "room_type": "Kitchen",
        "seed": 200,
        "mess_index": 0,
        "present_receptacles": ["CounterTop", "DiningTable", "Shelf", "Fridge"],
        "objects": [
            _obj(0, "Mug", True, "Shelf", mug),
            _obj(0, "Apple", True, "Fridge", apple),
            _obj(0, "Plate", True, "Shelf", plate),
            _obj(0, "Bowl", False, "Shelf", bowl),
        ],
    }


MEMBERS = {p: () for p in GROUP_PHRASES}


def test_the_profile_asks_for_another_place_forbids_the_agents_own_and_names_a_group() -> None:
    members = dict(MEMBERS, dishes=("Plate", "Bowl"))
    prof = script_profile(_rec("A", "CounterTop", "CounterTop", "Shelf"), members, seed=0)
    asked, never, group = prof["asked"], prof["never"], prof["group"]
    moved = {"Mug": "Shelf", "Apple": "Fridge", "Plate": "Shelf"}
    assert asked["receptacle"] != moved[asked["category"]] and asked["text"].startswith("the ")
    assert never["category"] != asked["category"] and never["text"].startswith("never put the ")
    assert group is None or (group["text"].startswith("dishes go on the ") and "Plate" in group["unnamed"])
    assert script_profile(_rec("A", "CounterTop", "CounterTop", "Shelf"), members, seed=0) == prof


def test_obeyed_group_and_side_effects_are_counted_per_agent() -> None:
    prof = {
        "asked": {"category": "Mug", "receptacle": "DiningTable"},
        "never": {"category": "Apple", "receptacle": "CounterTop"},
        "group": {"categories": ["Plate"], "unnamed": ["Plate"], "receptacle": "Shelf"},
    }
    key = ("Kitchen", 200, 0)
    without = [_rec("A", "Shelf", "CounterTop", "CounterTop", bowl="Shelf")]
    with_ = [_rec("A", "DiningTable", "Fridge", "Shelf", bowl="CounterTop")]
    m = score(without, with_, {key: prof})["A"]
    assert m["asked"] == {"n": 1, "share": 1.0} and m["never"] == {"n": 1, "share": 1.0}
    assert m["group"] == {"n": 1, "share": 1.0}
    assert m["side"] == {"n": 1, "share": 1.0}  # the bowl, named by nothing, moved
