"""``tidee eval ceiling``: counterfactual learners, the observed judge, the survey; the generator version."""

from __future__ import annotations

import json
from collections import Counter
from typing import Any

import pytest

from tidee.agent.evaluation.ceiling import (
    ceilings,
    counterfactual,
    observed_judge,
    prior_choosers,
    rooms_choosers,
    run_ceiling,
    survey,
)
from tidee.agent.evaluation.judge import judge_score
from tidee.agent.reasoning.rgcn.config import CeilingConfig
from tidee.protocol.vocab import ROOM_TYPES
from tidee.server.catalog import receptacle_weights
from tidee.server.rooms import generate_scene, rooms_version
from tidee.server.world import World

BEDROOM = ["Bed", "SideTable", "Dresser", "Desk"]
COUNTS = {
    ("Bedroom", "Watch", None): Counter(Dresser=6, SideTable=3),
    ("Bedroom", "CellPhone", None): Counter(Bed=5, SideTable=2),
    ("LivingRoom", "Watch", None): Counter(SideTable=4),
}


def _obj(oid: str, final: str) -> dict[str, Any]:
    return {
        "id": oid,
        "type": oid.split("_")[0],
        "variant": None,
        "moved": True,
        "found": True,
        "picked": True,
        "original_parent_type": "SideTable",
        "messy_parent_type": "Floor",
        "final_parent_type": final,
    }


def _records(tidee: dict[str, str], common: dict[str, str]) -> list[dict[str, Any]]:
    def rec(variant: str, finals: dict[str, str]) -> dict[str, Any]:
        return {
            "variant": variant,
            "split": "test",
            "room_type": "Bedroom",
            "seed": 1,
            "mess_index": 0,
            "steps": 10,
            "wall_s": 1.0,
            "present_receptacles": list(BEDROOM),
            "objects": [_obj(k, v) for k, v in finals.items()],
        }

    return [rec("TIDEE", tidee), rec("CommonMemory", common)]


def test_the_priors_the_tests_assume():
    w = receptacle_weights("Watch", None, "Bedroom", BEDROOM)
    assert max(w, key=w.get) == "SideTable" and w["Dresser"] < w["SideTable"]
    c = receptacle_weights("CellPhone", None, "Bedroom", BEDROOM)
    assert max(c, key=c.get) == "SideTable" and c["Bed"] < c["SideTable"]


def test_rooms_learner_follows_the_counts_and_common_memory_pools_them():
    tidee, common = rooms_choosers(COUNTS)
    assert tidee("Bedroom", "Watch", None, BEDROOM) == "Dresser"
    assert common("Bedroom", "Watch", None, BEDROOM) == "SideTable"  # 6 Dresser < 3 + 4 SideTable
    assert tidee("Bedroom", "CellPhone", None, BEDROOM) == "Bed"
    # neither surveyed receptacle present: nothing to go on
    assert tidee("Bedroom", "Watch", None, ["Bed", "Desk"]) is None
    assert common("Bedroom", "Watch", None, ["Bed", "Desk"]) is None
    # a category the survey never saw in this room type falls back on its pooled counts
    assert tidee("Bedroom", "Watch", "nonexistent", BEDROOM) == "SideTable"


def test_ceilings_on_hand_built_episodes():
    # The agents put the watch and the phone on the side table (TIDEE) and on the dresser / bed
    # (CommonMemory).
    records = _records(
        {"Watch_1": "SideTable", "CellPhone_1": "SideTable"}, {"Watch_1": "Dresser", "CellPhone_1": "Bed"}
    )
    out = ceilings({"episodes": records}, COUNTS)
    # the catalog judge prefers the side table for both
    assert (out["report"]["wins"], out["report"]["ties"], out["report"]["losses"]) == (2, 0, 0)
    # a perfect learner of these rooms: watch Dresser vs SideTable (lost), phone Bed vs Bed (tied)
    rl = out["rooms_learner"]
    assert (rl["wins"], rl["ties"], rl["losses"]) == (0, 1, 1) and rl["pref_a"] == pytest.approx(0.25)
    assert rl["mean_judge"]["TIDEE"] == pytest.approx(
        (
            judge_score("Watch", None, "Bedroom", "Dresser", BEDROOM)
            + judge_score("CellPhone", None, "Bedroom", "Bed", BEDROOM)
        )
        / 2
    )
    # a learner of rooms that follow the prior always takes the judge's favourite: it never loses
    pl = out["prior_learner"]
    assert pl["losses"] == 0 and pl["mean_judge"]["TIDEE"] == pytest.approx(1.0)
    # scored by the rooms, the same placements lose both: the side table is the rooms' second choice
    ob = out["observed_judge"]
    assert (ob["wins"], ob["ties"], ob["losses"]) == (0, 0, 2)
    assert ob["mean_judge"]["TIDEE"] == pytest.approx((3 / 6 + 2 / 5) / 2)
    assert ob["mean_judge"]["CommonMemory"] == pytest.approx(1.0)


def test_counterfactual_copies_and_changes_only_picked_objects():
    records = _records({"Watch_1": "SideTable", "CellPhone_1": "SideTable"}, {"Watch_1": "Dresser"})
    records[0]["objects"][1]["picked"] = False
    tidee, _ = prior_choosers()
    out = counterfactual(records, "TIDEE", lambda rt, cat, v, present: "Desk")
    assert [o["final_parent_type"] for o in out[0]["objects"]] == ["Desk", "SideTable"]
    assert records[0]["objects"][0]["final_parent_type"] == "SideTable"  # the input is untouched
    assert tidee("Bedroom", "Watch", None, BEDROOM) == "SideTable"


def test_observed_judge_scores_relative_to_the_most_frequent_present():
    judge = observed_judge(COUNTS)
    assert judge("Watch", None, "Bedroom", "Dresser", BEDROOM) == 1.0
    assert judge("Watch", None, "Bedroom", "SideTable", BEDROOM) == pytest.approx(0.5)
    assert judge("Watch", None, "Bedroom", "SideTable", ["SideTable", "Bed"]) == 1.0  # the dresser is absent
    assert judge("Watch", None, "Bedroom", None, BEDROOM) == 0.0
    assert judge("Pen", None, "Bedroom", "Desk", BEDROOM) == 1.0  # never surveyed: no evidence against it


def test_a_report_without_common_memory_is_refused(tmp_path):
    records = _records({"Watch_1": "SideTable"}, {"Watch_1": "Dresser"})
    path = tmp_path / "report.json"
    path.write_text(json.dumps({"episodes": [records[0]]}))
    with pytest.raises(ValueError, match="CommonMemory"):
        run_ceiling(CeilingConfig((str(tmp_path),), str(tmp_path / "out"), rooms_per_type=1), progress=False)
    with pytest.raises(FileNotFoundError, match="no tidy report"):
        run_ceiling(
            CeilingConfig((str(tmp_path / "missing"),), str(tmp_path / "out"), rooms_per_type=1),
            progress=False,
        )


def test_rooms_version_is_an_explicit_choice():
    assert rooms_version() == 1 and rooms_version(1) == 1 and rooms_version(2) == 2
    with pytest.raises(ValueError, match="version must be one of"):
        rooms_version(3)


def test_version_2_rooms_are_deterministic_and_keep_the_furniture():
    world = World(renderer="tiny")
    try:
        v1 = generate_scene("Bedroom", 10190, world=world)
        assert generate_scene("Bedroom", 10190, world=world, version=1).to_dict() == v1.to_dict()
        v2 = generate_scene("Bedroom", 10190, world=world, version=2)
        again = generate_scene("Bedroom", 10190, world=world, version=2)
    finally:
        world.close()
    assert v2.to_dict() == again.to_dict()
    furniture = lambda s: [(o.id, o.type, o.position) for o in s.objects if not o.pickupable]  # noqa: E731
    assert furniture(v2) == furniture(v1)
    small = [o for o in v2.objects if o.pickupable]
    assert small and [(o.id, o.position) for o in small] != [
        (o.id, o.position) for o in v1.objects if o.pickupable
    ]
    present = sorted({o.type for o in v2.objects if o.receptacle and not o.pickupable})
    for o in small:
        assert receptacle_weights(o.type, o.variant, "Bedroom", present).get(o.parent_type, 0.0) > 0, o


def test_survey_counts_every_object_once_and_a_second_survey_reads_the_scene_cache(tmp_path, monkeypatch):
    from tidee.server import episode, rooms
    from tidee.server.scene_cache import SceneCache

    s = survey(1, version=1, progress=False, cache=SceneCache(tmp_path, version=1))
    assert s["rooms"] == 4 and s["seeds"] == [10185, 10185]
    assert sum(sum(c.values()) for c in s["counts"].values()) == s["objects"] > 0
    assert 0.0 <= s["tv"] <= 1.0 and set(s["tv_by_room_type"]) <= set(ROOM_TYPES)

    def no_physics(*a, **kw):
        raise AssertionError("a cached room was generated again")

    monkeypatch.setattr(rooms, "generate_scene", no_physics)
    monkeypatch.setattr(episode, "generate_scene", no_physics)  # the scene library's own name for it
    again = survey(1, version=1, progress=False, cache=SceneCache(tmp_path, version=1))
    same = ("counts", "objects", "tv", "tv_by_room_type", "objects_per_room")
    assert {k: again[k] for k in same} == {k: s[k] for k in same}
