"""The human judge: Housekeep votes through the name mapping, on hand-made votes and on the
shipped table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tidee.agent.evaluation.human_judge import HOUSEKEEP_DIR, HumanJudge, Votes, human_metrics, human_pairwise

MAPPING = {
    "rooms": {"Kitchen": "kitchen"},
    "objects": {
        "Mug": {"housekeep": "mug", "tier": "exact", "note": ""},
        "Statue": {"housekeep": None, "tier": "none", "note": "no counterpart"},
        "Book": {"housekeep": "book", "tier": "exact", "note": ""},
        "Book/cookbook": {"housekeep": "book", "tier": "close", "note": "a book, not a cookbook"},
    },
    "receptacles": {
        "Kitchen": {
            "Cabinet": {"housekeep": "top_cabinet", "tier": "close", "note": ""},
            "CounterTop": {"housekeep": "counter", "tier": "exact", "note": ""},
            "Floor": {"housekeep": "carpet", "tier": "approximate", "note": "a rug stands in for the floor"},
            "Toilet": {"housekeep": None, "tier": "none", "note": "not in a kitchen"},
        }
    },
}
TABLE = {
    ("kitchen", "top_cabinet", "mug"): Votes(8, 2, 0),
    ("kitchen", "counter", "mug"): Votes(2, 6, 2),
    ("kitchen", "carpet", "mug"): Votes(0, 1, 9),
    ("kitchen", "counter", "book"): Votes(4, 4, 2),
    ("kitchen", "top_cabinet", "book"): Votes(1, 2, 7),
    ("kitchen", "carpet", "book"): Votes(0, 0, 10),
}
PRESENT = ["Cabinet", "CounterTop"]


@pytest.fixture
def judge() -> HumanJudge:
    return HumanJudge(TABLE, MAPPING)


def test_a_placement_is_correct_plausible_and_relative_by_the_votes(judge: HumanJudge) -> None:
    cabinet = judge.judge("Mug", None, "Kitchen", "Cabinet", PRESENT)
    counter = judge.judge("Mug", None, "Kitchen", "CounterTop", PRESENT)
    floor = judge.judge("Mug", None, "Kitchen", "Floor", PRESENT)
    assert (
        cabinet
        and cabinet.correct
        and cabinet.plausible
        and cabinet.relative == 1.0
        and cabinet.tier == "close"
    )
    assert counter and not counter.correct and counter.plausible and counter.relative == 2 / 8
    assert floor and not floor.plausible and floor.relative == 0.0 and floor.tier == "approximate"


def test_unmapped_names_are_not_judged_and_a_held_object_is_wrong(judge: HumanJudge) -> None:
    assert judge.judge("Statue", None, "Kitchen", "CounterTop", PRESENT) is None
    assert judge.judge("Mug", None, "Kitchen", "Toilet", PRESENT) is None
    held = judge.judge("Mug", None, "Kitchen", None, PRESENT)
    assert held and not held.correct and held.relative == 0.0


def test_a_variant_uses_its_own_entry_and_its_looser_tier(judge: HumanJudge) -> None:
    j = judge.judge("Book", "cookbook", "Kitchen", "CounterTop", PRESENT)
    assert j and j.tier == "close" and not j.correct and j.plausible
    assert judge.object_name("Book", "hardcover") == ("book", "exact")


def _record(variant: str, mug_on: str | None, picked: bool = True) -> dict:
    return {
        "variant": variant,
        "room_type": "Kitchen",
        "seed": 200,
        "mess_index": 0,
        "split": "test",
        "present_receptacles": PRESENT,
        "objects": [
            {
                "id": "Mug_0",
                "type": "Mug",
                "variant": None,
                "moved": True,
                "picked": picked,
                "original_parent_type": "Cabinet",
                "final_parent_type": mug_on,
            },
            {
                "id": "Statue_0",
                "type": "Statue",
                "variant": None,
                "moved": True,
                "picked": picked,
                "original_parent_type": "CounterTop",
                "final_parent_type": "Floor",
            },
            {
                "id": "Book_0",
                "type": "Book",
                "variant": "cookbook",
                "moved": False,
                "picked": False,
                "original_parent_type": "CounterTop",
                "final_parent_type": "CounterTop",
            },
        ],
    }


def test_metrics_count_coverage_and_the_tidy_rooms(judge: HumanJudge) -> None:
    m = human_metrics([_record("A", "Cabinet"), _record("B", "Floor")], judge)
    a, b, tidy = m["variants"]["A"], m["variants"]["B"], m["tidy_rooms"]
    assert (a["placements"], a["judged"], a["coverage"], a["correct"]) == (2, 1, 0.5, 1.0)
    assert b["correct"] == 0.0 and b["plausible"] == 0.0 and b["by_tier"]["approximate"] == 1
    # the tidy room once per configuration: mug in the cabinet (correct), cookbook on the counter
    # (plausible, not correct), the statue unjudged
    assert (tidy["placements"], tidy["judged"], tidy["correct"], tidy["plausible"]) == (3, 2, 0.5, 1.0)


def test_pairwise_by_votes_with_a_margin(judge: HumanJudge) -> None:
    recs = [_record("A", "Cabinet"), _record("B", "CounterTop")]
    one = human_pairwise(recs, ["A", "B"], judge=judge)
    assert (one["A"]["B"]["wins"], one["A"]["B"]["n"], one["A"]["B"]["unjudged"]) == (1, 1, 1)
    recs = [_record("A", "CounterTop"), _record("B", "Floor")]  # 2 votes against 0
    assert human_pairwise(recs, ["A", "B"], margin=2, judge=judge)["A"]["B"]["wins"] == 1
    assert human_pairwise(recs, ["A", "B"], margin=3, judge=judge)["A"]["B"]["ties"] == 1


def test_the_shipped_mapping_names_exist_in_the_shipped_table() -> None:
    judge = HumanJudge.load()
    objects = {o for (_, _, o) in judge.table}
    receptacles = {(room, r) for (room, r, _) in judge.table}
    for key, entry in judge.objects.items():
        assert entry["tier"] in ("exact", "close", "approximate", "none"), key
        assert (entry["housekeep"] is None) == (entry["tier"] == "none"), key
        assert entry["housekeep"] is None or entry["housekeep"] in objects, key
    for room_type, entries in judge.receptacles.items():
        for name, entry in entries.items():
            hk = entry["housekeep"]
            assert hk is None or (judge.rooms[room_type], hk) in receptacles, (room_type, name)
    licence = (HOUSEKEEP_DIR / "README.md").read_text()
    assert "Yash Kant" in licence and "MIT" in licence
    assert json.loads((HOUSEKEEP_DIR / "mapping.json").read_text())["rooms"]["LivingRoom"] == "living_room"
    assert Path(HOUSEKEEP_DIR / "housekeep_orr_4rooms.csv").stat().st_size > 800_000
