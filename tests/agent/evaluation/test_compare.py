"""``tidee eval compare``: two runs of one evaluation, episode by episode."""

from __future__ import annotations

import gzip
import json

import pytest

from tidee.agent.evaluation.compare import compare_reports, format_markdown, write_comparison


def _object(oid, moved, picked, plausible, final):
    # a book in a bedroom: plausible on the shelf, bed or dresser, not on the floor (the judge
    # decides from the receptacle; the flag is what the report stored beside it)
    return {
        "id": oid,
        "type": "Book",
        "variant": None,
        "moved": moved,
        "found": picked,
        "picked": picked,
        "original_parent_type": "Shelf",
        "messy_parent_type": "Floor" if moved else "Shelf",
        "final_parent_type": final if plausible else "Floor",
        "plausible": plausible,
    }


def _tidy_episode(variant, seed, plausible, steps=300, picked_unmoved=0, final="Shelf"):
    objects = [_object(f"Book_{i}", True, True, i < plausible, final) for i in range(3)]
    objects += [_object(f"Book_{i + 3}", False, i < picked_unmoved, True, "Shelf") for i in range(2)]
    return {
        "variant": variant,
        "room_type": "Bedroom",
        "seed": seed,
        "mess_index": 0,
        "steps": steps,
        "wall_s": 10.0,
        "present_receptacles": ["Bed", "Dresser", "Floor", "Shelf"],
        "objects": objects,
    }


def _write(path, episodes, command, gz=False):
    path.mkdir(parents=True)
    text = json.dumps({"episodes": episodes, "notes": [f"command: {command}"]}).encode()
    (path / ("report.json.gz" if gz else "report.json")).write_bytes(gzip.compress(text) if gz else text)
    return path


def test_tidy_episodes_are_matched_by_agent_and_configuration(tmp_path):
    before = _write(
        tmp_path / "a",
        [
            _tidy_episode("TIDEE", 200, 2),
            _tidy_episode("TIDEE", 201, 3),
            _tidy_episode("TIDEE", 202, 1),
            _tidy_episode("TIDEE", 203, 1),
            _tidy_episode("CommonMemory", 200, 1),
            _tidy_episode("TIDEE", 204, 0),
        ],
        "tidee eval tidy --out a",
        gz=True,
    )
    after = _write(
        tmp_path / "b",
        [
            _tidy_episode("TIDEE", 200, 3),  # better
            _tidy_episode("TIDEE", 201, 2, picked_unmoved=1),  # worse
            _tidy_episode("TIDEE", 202, 1, steps=280),  # same score, another course
            _tidy_episode("TIDEE", 203, 1),  # identical
            _tidy_episode("CommonMemory", 200, 1, final="Bed"),  # same score, other end states
        ],
        "tidee eval tidy --out b",
    )
    result = compare_reports(before, after)
    assert result["kind"] == "tidy"
    tidee, common = result["rows"]["TIDEE"], result["rows"]["CommonMemory"]
    assert tidee["episodes"] == 4 and tidee["identical"] == 1
    assert [c["episode"] for c in tidee["better"]] == ["Bedroom 200 mess 0"]
    assert tidee["better"][0]["before"] == [2.0] and tidee["better"][0]["after"] == [3.0]
    assert [c["episode"] for c in tidee["worse"]] == ["Bedroom 201 mess 0"]
    assert tidee["same_score_other_course"][0]["steps"] == [300, 280]
    # over the 4 episodes both ran: 7 then 7 of 12 moved objects plausible; one false pick after
    assert tidee["metric_before"] == {"object_success_pct": 58.3, "moved_objects": 12.0, "false_picks": 0.0}
    assert tidee["metric_after"] == {"object_success_pct": 58.3, "moved_objects": 12.0, "false_picks": 1.0}
    assert len(common["same_score_other_course"]) == 1 and common["identical"] == 0
    assert result["only_in_one"] == {"before": ["Bedroom 204 mess 0 [TIDEE]"], "after": []}
    md = format_markdown(result)
    assert "| TIDEE | 4 | 1 | 1 | 1 | 1 | 58.3 → 58.3 | 12 → 12 | 0 → 1 |" in md
    assert "- before: `tidee eval tidy --out a`" in md and "Only in before (1)" in md
    out = write_comparison(result, tmp_path / "c")
    assert (
        out.read_text() == md and json.loads((tmp_path / "c" / "compare.json").read_text())["kind"] == "tidy"
    )


def _rearrange_episode(row, seed, fixed_strict, energy, steps=400):
    objects = [{"id": "Pen_0", "misplaced_end": fixed_strict < 1, "energy_end": energy}]
    metrics = {
        "fixed_strict": fixed_strict,
        "success": fixed_strict == 1.0,
        "misplaced": None,
        "energy": energy,
        "objects": objects,
        "by_kind": {k: {"fixed_strict": None} for k in ("pickupable", "openable")},
    }
    return {
        "row": row,
        "room_type": "Kitchen",
        "seed": seed,
        "rearrange_index": 1,
        "steps": steps,
        "rearrange": metrics,
    }


def test_rearrangement_episodes_rank_by_fixed_strict_then_energy(tmp_path):
    before = _write(
        tmp_path / "a",
        [_rearrange_episode("clean", 200, 0.5, 0.4), _rearrange_episode("clean", 201, 0.0, 0.9)],
        "tidee eval rearrange",
    )
    after = _write(
        tmp_path / "b",
        [_rearrange_episode("clean", 200, 0.5, 0.3), _rearrange_episode("clean", 201, 0.0, 1.0)],
        "tidee eval rearrange",
    )
    row = compare_reports(before, after)["rows"]["clean"]
    assert [c["episode"] for c in row["better"]] == ["Kitchen 200 rearrangement 1"]  # less energy left
    assert [c["episode"] for c in row["worse"]] == ["Kitchen 201 rearrangement 1"]
    assert row["metric_before"] == {"fixed_strict_pct": 25.0, "success_pct": 0.0, "energy_pct": 65.0}
    assert row["metric_after"] == {"fixed_strict_pct": 25.0, "success_pct": 0.0, "energy_pct": 65.0}


def test_reports_that_cannot_be_compared_are_refused_in_one_line(tmp_path):
    tidy = _write(tmp_path / "t", [_tidy_episode("TIDEE", 200, 2)], "t")
    rearrange = _write(tmp_path / "r", [_rearrange_episode("clean", 200, 0.5, 0.4)], "r")
    other = _write(tmp_path / "o", [_tidy_episode("TIDEE", 300, 2)], "o")
    with pytest.raises(
        ValueError, match="is a tidy report and .* a rearrange report: compare like with like"
    ):
        compare_reports(tidy, rearrange)
    with pytest.raises(ValueError, match="share no episode"):
        compare_reports(tidy, other)
    empty = _write(tmp_path / "e", [], "e")
    with pytest.raises(ValueError, match="has no episodes"):
        compare_reports(empty, tidy)
    dup = _write(tmp_path / "d", [_tidy_episode("TIDEE", 200, 2)] * 2, "d")
    with pytest.raises(ValueError, match="two episodes of"):
        compare_reports(dup, tidy)


def test_a_condition_row_keeps_the_report_name_and_reference_rows_name_their_condition(tmp_path):
    agent = dict(_tidy_episode("TIDEE +est. depth", 200, 1), condition="est-depth")
    reference = dict(_tidy_episode("AI2THORPlacement", 200, 3), condition="est-depth")
    clean = _tidy_episode("AI2THORPlacement", 200, 3)
    report = _write(tmp_path / "a", [agent, reference, clean], "tidee eval tidy --conditions clean,est-depth")
    rows = compare_reports(report, report)["rows"]
    assert sorted(rows) == ["AI2THORPlacement", "AI2THORPlacement (est-depth)", "TIDEE +est. depth"]
    assert all(r["identical"] == 1 for r in rows.values())
