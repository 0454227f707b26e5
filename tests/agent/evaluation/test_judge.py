"""The simulated judge, tidy metrics, the pairwise preference table and the written report."""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import pytest
from scipy.stats import binomtest

from tidee.agent.evaluation import (
    AI2THOR_PLACEMENT,
    MESSY_PLACEMENT,
    judge_score,
    pairwise_table,
    plausible,
    prefer,
    reference_records,
    variant_metrics,
    with_references,
    write_report,
)
from tidee.server.catalog import PRIORS

KITCHEN = ["CounterTop", "Fridge", "Sink", "Cabinet", "DiningTable"]


def obj(
    oid: str,
    final: str | None,
    *,
    moved: bool = True,
    found: bool | None = None,
    picked: bool | None = None,
    original: str = "CounterTop",
    messy: str = "Floor",
    variant: str | None = None,
) -> dict[str, Any]:
    """One object entry; found/picked default to moved."""
    return {
        "id": oid,
        "type": oid.split("_")[0],
        "variant": variant,
        "moved": moved,
        "found": moved if found is None else found,
        "picked": moved if picked is None else picked,
        "original_parent_type": original,
        "messy_parent_type": messy if moved else original,
        "final_parent_type": final,
    }


def record(
    variant: str,
    seed: int,
    objects: list[dict[str, Any]],
    *,
    steps: int = 100,
    wall_s: float = 2.0,
    perception: str = "oracle",
    mess_index: int = 0,
) -> dict[str, Any]:
    return {
        "variant": variant,
        "perception": perception,
        "split": "test",
        "room_type": "Kitchen",
        "seed": seed,
        "mess_index": mess_index,
        "steps": steps,
        "wall_s": wall_s,
        "end_reason": "no_oop_found",
        "present_receptacles": list(KITCHEN),
        "objects": objects,
    }


# ------------------------------------------------------------------------- judge


def test_priors_used_by_the_tests_are_as_assumed():
    mug = PRIORS["Mug"]["*"]["Kitchen"]
    apple = PRIORS["Apple"]["*"]["Kitchen"]
    assert max(mug, key=mug.get) == "CounterTop" and "Floor" not in mug
    assert max(apple, key=apple.get) == "CounterTop" and "Floor" not in apple


def test_judge_score_orders_placements_by_prior():
    top = judge_score("Mug", None, "Kitchen", "CounterTop", KITCHEN)
    cab = judge_score("Mug", None, "Kitchen", "Cabinet", KITCHEN)
    floor = judge_score("Mug", None, "Kitchen", "Floor", KITCHEN)
    mug = PRIORS["Mug"]["*"]["Kitchen"]
    assert top == 1.0
    assert cab == pytest.approx(mug["Cabinet"] / mug["CounterTop"])
    assert floor == 0.0
    assert top > cab > floor
    assert judge_score("Mug", None, "Kitchen", None, KITCHEN) == 0.0
    # a receptacle missing from the room has no weight there
    assert judge_score("Mug", None, "Kitchen", "Microwave", KITCHEN) == 0.0
    # the max is taken over the receptacles present
    assert judge_score("Mug", None, "Kitchen", "Cabinet", ["Cabinet", "Sink"]) == 1.0
    assert plausible("Mug", None, "Kitchen", "CounterTop", KITCHEN)
    assert plausible("Mug", None, "Kitchen", "Sink", KITCHEN)
    assert not plausible("Mug", None, "Kitchen", "Floor", KITCHEN)
    assert not plausible("Mug", None, "Kitchen", None, KITCHEN)
    # weight > 0 but below 0.1 x max: scores low, is implausible
    micro = judge_score("Mug", None, "Kitchen", "Microwave", KITCHEN + ["Microwave"])
    assert micro == pytest.approx(mug["Microwave"] / mug["CounterTop"]) and 0 < micro < 0.1
    assert not plausible("Mug", None, "Kitchen", "Microwave", KITCHEN + ["Microwave"])


def test_judge_score_uses_variant_priors():
    cook = PRIORS["Book"]["cookbook"]["Kitchen"]
    assert judge_score("Book", "cookbook", "Kitchen", "Shelf", None) == 1.0
    assert judge_score("Book", "cookbook", "Kitchen", "CounterTop", None) == pytest.approx(
        cook["CounterTop"] / cook["Shelf"]
    )


def test_prefer():
    assert prefer(0.9, 0.2) == 1.0
    assert prefer(0.2, 0.9) == 0.0
    assert prefer(0.5, 0.5) == 0.5
    assert prefer(0.5, 0.5 + 1e-9) == 0.5
    with pytest.raises(ValueError, match="eps"):
        prefer(1, 0, eps=-1)


def test_reference_records():
    rec = record(
        "A",
        1,
        [
            obj("Mug_1", "Sink", original="Cabinet", messy="Floor"),
            obj("Apple_1", "Floor", moved=False, picked=True, original="Fridge"),
        ],
        steps=50,
    )
    before = copy.deepcopy(rec)
    refs = reference_records(rec)
    assert rec == before  # not mutated
    assert set(refs) == {AI2THOR_PLACEMENT, MESSY_PLACEMENT}
    ai2, messy = refs[AI2THOR_PLACEMENT], refs[MESSY_PLACEMENT]
    assert ai2["variant"] == AI2THOR_PLACEMENT and messy["variant"] == MESSY_PLACEMENT
    for r in (ai2, messy):
        assert r["steps"] == 0 and r["wall_s"] == 0
        assert (r["room_type"], r["seed"], r["mess_index"], r["split"]) == ("Kitchen", 1, 0, "test")
        assert [(o["found"], o["picked"]) for o in r["objects"]] == [(True, True), (False, False)]
    assert [o["final_parent_type"] for o in ai2["objects"]] == ["Cabinet", "Fridge"]
    assert [o["final_parent_type"] for o in messy["objects"]] == ["Floor", "Fridge"]
    bad = copy.deepcopy(rec)
    del bad["objects"][0]["messy_parent_type"]
    with pytest.raises(ValueError, match="messy_parent_type"):
        reference_records(bad)


# ----------------------------------------------------------------------- metrics


def _metric_records() -> list[dict[str, Any]]:
    return [
        record(
            "A",
            1,
            [
                obj("Mug_1", "CounterTop"),  # plausible
                obj("Apple_1", "Floor", found=False, picked=False),  # left on the floor
                obj("Mug_2", "Cabinet", moved=False, picked=True),
            ],
            steps=100,
            wall_s=4.0,
        ),
        record("A", 2, [obj("Mug_1", "Cabinet"), obj("Apple_1", "Fridge")], steps=300, wall_s=6.0),
        record(
            "B",
            1,
            [
                obj("Mug_1", "Floor", found=True, picked=False),
                obj("Apple_1", "Floor", found=False, picked=False),
            ],
            steps=10,
            wall_s=1.0,
        ),
    ]


def test_variant_metrics_exact():
    m = variant_metrics(_metric_records())
    assert list(m) == ["A", "B"]
    a, b = m["A"], m["B"]
    assert a["episodes"] == 2 and (a["moved"], a["found"], a["picked"]) == (4, 3, 4)
    assert a["object_success"] == pytest.approx(3 / 4)
    assert a["episode_success"] == pytest.approx(1 / 2)
    assert a["found_rate"] == pytest.approx(3 / 4)
    assert a["false_pick_rate"] == pytest.approx(1 / 4)
    mug, apple = PRIORS["Mug"]["*"]["Kitchen"], PRIORS["Apple"]["*"]["Kitchen"]
    expected = (1.0 + 0.0 + mug["Cabinet"] / mug["CounterTop"] + apple["Fridge"] / apple["CounterTop"]) / 4
    assert a["mean_judge_score"] == pytest.approx(expected)
    assert a["steps_mean"] == 200 and a["wall_s_mean"] == 5.0
    assert b["object_success"] == 0 and b["episode_success"] == 0
    assert b["found_rate"] == pytest.approx(1 / 2)
    assert b["false_pick_rate"] == 0.0 and b["picked"] == 0  # nothing picked: 0 by definition


def test_variant_metrics_missing_keys_are_named():
    recs = _metric_records()
    del recs[1]["steps"]
    with pytest.raises(ValueError, match=r"record 1 .*variant 'A'.*missing key 'steps'"):
        variant_metrics(recs)
    recs = _metric_records()
    del recs[2]["objects"][1]["found"]
    with pytest.raises(ValueError, match=r"record 2 .*object 1 \('Apple_1'\) is missing key 'found'"):
        variant_metrics(recs)
    recs = _metric_records()
    recs[0]["objects"][0]["type"] = "Sofa"  # no placement prior
    with pytest.raises(ValueError, match="cannot be judged"):
        variant_metrics(recs)


# ---------------------------------------------------------------------- pairwise


def _pair_records() -> list[dict[str, Any]]:
    return [
        record(
            "A",
            1,
            [
                obj("Mug_1", "CounterTop"),
                obj("Apple_1", "Fridge"),
                obj("Mug_2", "CounterTop"),  # picked by A only
                obj("Mug_3", "Floor", moved=False, picked=True),
            ],
        ),  # not moved
        record(
            "B",
            1,
            [
                obj("Mug_1", "Floor"),
                obj("Apple_1", "Fridge"),
                obj("Mug_2", "Floor", found=False, picked=False),
                obj("Mug_3", "CounterTop", moved=False, picked=True),
            ],
        ),
        record("A", 2, [obj("Mug_1", "Cabinet"), obj("Apple_1", "CounterTop")]),
        record("B", 2, [obj("Mug_1", "CounterTop"), obj("Apple_1", "Floor")]),
        record("A", 3, [obj("Mug_1", "CounterTop")]),  # B did not run seed 3
    ]


def test_pairwise_counts_ties_and_exclusions():
    t = pairwise_table(_pair_records(), ["A", "B"])
    assert list(t) == ["A", "B"] and list(t["A"]) == ["B"]
    ab, ba = t["A"]["B"], t["B"]["A"]
    assert (ab["n"], ab["wins"], ab["ties"], ab["losses"]) == (4, 2, 1, 1)
    assert ab["pref_a"] == pytest.approx(0.625)
    assert (ba["wins"], ba["ties"], ba["losses"]) == (1, 1, 2)
    assert ba["pref_a"] == pytest.approx(0.375)
    assert ab["p_value"] == pytest.approx(binomtest(2, 3, 0.5).pvalue)
    assert ab["configurations"] == 2
    # what decided it: seed 1's Mug_1 (CounterTop over Floor) and seed 2's Apple_1 won, seed 2's Mug_1 lost
    assert ab["decided"] == [
        {"type": "Apple", "a": "CounterTop", "b": "Floor", "winner": "A", "n": 1},
        {"type": "Mug", "a": "CounterTop", "b": "Floor", "winner": "A", "n": 1},
        {"type": "Mug", "a": "Cabinet", "b": "CounterTop", "winner": "B", "n": 1},
    ]


def test_pairwise_p_value_matches_scipy():
    recs = []
    for seed in range(10):
        win = seed < 9
        a_mug, b_mug = ("CounterTop", "Floor") if win else ("Floor", "CounterTop")
        recs.append(record("A", seed, [obj("Mug_1", a_mug), obj("Apple_1", "Fridge")]))
        recs.append(record("B", seed, [obj("Mug_1", b_mug), obj("Apple_1", "Fridge")]))
    c = pairwise_table(recs)["A"]["B"]
    assert (c["n"], c["wins"], c["ties"], c["losses"]) == (20, 9, 10, 1)
    assert c["pref_a"] == pytest.approx((9 + 5) / 20)
    assert c["p_value"] == pytest.approx(binomtest(9, 10, 0.5, alternative="two-sided").pvalue)
    assert c["p_value"] < 0.05


def test_pairwise_reference_rows():
    recs = with_references(_pair_records())
    assert len(recs) == 5 + 2 * 3  # one pair per configuration
    t = pairwise_table(recs, ["A", "B"])
    assert list(t) == ["A", "B", AI2THOR_PLACEMENT, MESSY_PLACEMENT]
    ref = t[AI2THOR_PLACEMENT][MESSY_PLACEMENT]
    # every moved object: originals are CounterTop (the top prior), messy parents the Floor (no weight)
    assert (ref["n"], ref["wins"], ref["ties"], ref["losses"]) == (6, 6, 0, 0)
    assert ref["pref_a"] == 1.0
    assert t[MESSY_PLACEMENT][AI2THOR_PLACEMENT]["pref_a"] == 0.0
    # against an agent, only the moved objects that agent picked count
    assert t["B"][AI2THOR_PLACEMENT]["n"] == 4
    assert t["A"][MESSY_PLACEMENT]["n"] == 6
    # references are included even when not named
    assert AI2THOR_PLACEMENT in pairwise_table(recs)
    assert with_references(recs) == recs  # idempotent


def test_pairwise_errors():
    recs = _pair_records()
    with pytest.raises(ValueError, match="no records for variant"):
        pairwise_table(recs, ["A", "C"])
    dup = recs + [copy.deepcopy(recs[0])]
    with pytest.raises(ValueError, match="repeats the configuration"):
        pairwise_table(dup)


# ------------------------------------------------------------------------ report


def test_write_report(tmp_path):
    recs = with_references(_pair_records())
    notes = ["3 configurations, hand-built for the test"]
    rep = write_report(recs, tmp_path / "out", "Tidy test", notes)
    out = tmp_path / "out"
    names = sorted(p.name for p in out.iterdir())
    assert names == ["metrics.png", "pairwise.png", "report.json", "report.md"]  # no temp files left
    for png in ("metrics.png", "pairwise.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads((out / "report.json").read_text())
    assert data == json.loads(json.dumps(rep))
    assert set(data["metrics"]) == {"A", "B", AI2THOR_PLACEMENT, MESSY_PLACEMENT}
    assert data["pairwise"]["A"]["B"]["n"] == 4
    assert len(data["episodes"]) == len(recs)
    required = {"type", "variant", "moved", "found", "picked", "original_parent_type", "final_parent_type"}
    for ep in data["episodes"]:
        assert ep["objects"]
        for o in ep["objects"]:
            assert required <= set(o)
            assert 0.0 <= o["judge_score"] <= 1.0 and isinstance(o["plausible"], bool)
    assert notes[0] in data["notes"]
    md = (out / "report.md").read_text()
    assert md.startswith("# Tidy test")
    assert "| Variant | Episodes | Object success | Episode success | Found rate |" in md
    assert "| A \\ B | A | B | AI2THORPlacement | MessyPlacement |" in md
    p = binomtest(2, 3).pvalue
    assert f"| A | — | 62.5% (n=4, p={p:.2f}) |" in md
    assert "## What decided the judge: A against the other agents" in md
    assert "- **A vs B**: 2 won, 1 lost, 1 tied." in md
    assert "  - won: Apple CounterTop vs Floor ×1; Mug CounterTop vs Floor ×1" in md
    assert "  - lost: Mug Cabinet vs CounterTop ×1" in md
    assert "simulated" in md and "placement priors" in md
    assert "Perception was oracle" in md
    assert notes[0] in md
    assert not math.isnan(data["metrics"]["A"]["object_success"])


def test_write_report_mixed_perception_and_empty(tmp_path):
    recs = _metric_records()
    recs[2]["perception"] = "learned"
    rep = write_report(recs, tmp_path, "Mixed", [])
    assert any("not oracle" in n and "B: learned" in n for n in rep["notes"])
    with pytest.raises(ValueError, match="no episode records"):
        write_report([], tmp_path / "empty", "Empty", [])


# ------------------------------------------------------------------------ merging


def test_merged_reports_equal_one_run_of_both_variants(tmp_path):
    """A's episodes from one run, B's from another (gzipped as under docs/): the merged report
    has the metrics and pairwise cells of a report of all the records at once."""
    import gzip

    from tidee.agent.evaluation.report import merge_reports

    recs = _pair_records()
    write_report(
        with_references([r for r in recs if r["variant"] == "A"]),
        tmp_path / "a",
        "A run",
        ["command: tidee eval tidy --variants A"],
    )
    write_report(with_references([r for r in recs if r["variant"] == "B"]), tmp_path / "b", "B run", [])
    b_json = tmp_path / "b" / "report.json"
    (tmp_path / "b" / "report.json.gz").write_bytes(gzip.compress(b_json.read_bytes()))
    b_json.unlink()
    whole = write_report(with_references(recs), tmp_path / "whole", "whole")
    merged = merge_reports(
        [tmp_path / "a", tmp_path / "b"], tmp_path / "m", command="tidee eval tidy-merge ..."
    )
    assert merged["metrics"] == whole["metrics"] and merged["pairwise"] == whole["pairwise"]
    assert merged["pairwise"]["A"]["B"]["pref_a"] == pytest.approx(0.625)
    assert any(
        n.startswith(f"{tmp_path / 'a'} (A): command: tidee eval tidy --variants A") for n in merged["notes"]
    )
    assert "command: tidee eval tidy-merge ..." in merged["notes"]
    # only the named variants; a variant from two sources is refused, naming both
    only_a = merge_reports([tmp_path / "whole"], tmp_path / "m2", variants=["A"])
    assert set(only_a["metrics"]) == {"A", AI2THOR_PLACEMENT, MESSY_PLACEMENT}
    with pytest.raises(ValueError, match=r"'A' is in both .*a and .*whole"):
        merge_reports([tmp_path / "a", tmp_path / "whole"], tmp_path / "m3")
    picked = merge_reports(
        [tmp_path / "a", (tmp_path / "whole", ["B"])], tmp_path / "m3"
    )  # A from a, B from whole
    assert picked["pairwise"] == whole["pairwise"]
    with pytest.raises(ValueError, match=r"no records of \['C'\] in .*whole"):
        merge_reports([(tmp_path / "whole", ["C"])], tmp_path / "m3")
    with pytest.raises(ValueError, match=r"no records of \['C'\]"):
        merge_reports([tmp_path / "a"], tmp_path / "m4", variants=["A", "C"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no report.json"):
        merge_reports([tmp_path / "empty"], tmp_path / "m6")
    (tmp_path / "odd.json").write_text(json.dumps({"episodes": [["not", "a", "record"]]}))
    with pytest.raises(ValueError, match="episode 0 is not a record"):
        merge_reports([tmp_path / "odd.json"], tmp_path / "m7")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a readable tidy report"):
        merge_reports([tmp_path / "bad.json"], tmp_path / "m7")


def test_tidy_merge_command_takes_named_variants_from_each_source(tmp_path, capsys):
    from tidee.cli import main

    recs = _pair_records()
    write_report(with_references(recs), tmp_path / "run1", "run 1")
    write_report(with_references(recs), tmp_path / "run2", "run 2")
    assert (
        main(
            [
                "eval",
                "tidy-merge",
                "--from",
                f"{tmp_path / 'run1'}=A,{tmp_path / 'run2'}=B",
                "--out",
                str(tmp_path / "m"),
            ]
        )
        == 0
    )
    data = json.loads((tmp_path / "m" / "report.json").read_text())
    assert data["pairwise"]["A"]["B"]["pref_a"] == pytest.approx(0.625)
    assert (
        f"command: tidee eval tidy-merge --from {tmp_path / 'run1'}=A,"
        in (tmp_path / "m" / "report.md").read_text()
    )
    assert (
        main(
            [
                "eval",
                "tidy-merge",
                "--from",
                f"{tmp_path / 'run1'},{tmp_path / 'run2'}",
                "--out",
                str(tmp_path / "m2"),
            ]
        )
        == 2
    )
    assert "'A' is in both" in capsys.readouterr().err
