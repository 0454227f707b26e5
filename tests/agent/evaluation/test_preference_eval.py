"""tidee eval preferences: the scripted profile and the scoring, on hand-made records."""

from __future__ import annotations

from tidee.agent.evaluation.preference_eval import (
    GROUP_PHRASES,
    _markdown,
    score,
    script_profile,
    side_effect_list,
)


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


def test_a_preference_the_simulator_cannot_carry_out_is_not_asked() -> None:
    members = dict(MEMBERS, dishes=("Plate", "Bowl"))
    rec = _rec("A", "CounterTop", "CounterTop", "Shelf")
    calls = []

    def nowhere(cats, r):
        calls.append((cats, r))
        return False

    prof = script_profile(rec, members, seed=0, fits=nowhere)
    assert prof["asked"] is None and prof["group"] is None and prof["never"] is not None
    kinds = {u["kind"] for u in prof["unfit"]}
    assert kinds == {"asked", "dishes"} and len(prof["unfit"]) == len(calls)
    assert (("Plate", "Bowl"), "CounterTop") in calls  # a group is checked with all its members at once

    def counter_only(cats, r):
        return r == "CounterTop"

    prof = script_profile(rec, members, seed=0, fits=counter_only)
    assert prof["group"]["receptacle"] == "CounterTop"
    assert prof["asked"] is None or prof["asked"]["receptacle"] == "CounterTop"
    assert all(u["receptacle"] != "CounterTop" for u in prof["unfit"])


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
    assert m["found"] == m["picked"] == {"n": 1, "share": 1.0}
    assert m["side"] == {"n": 1, "share": 1.0}  # the bowl, named by nothing, moved
    assert m["side_worse"] == {"n": 1, "share": 0.0}  # shelf to counter top: plausible both
    assert m["side_rerun"] == {"n": 0, "share": None}  # no reseeded run
    # a second run without preferences under another seed: the bowl ends where it did, on the
    # same objects (the named ones are left out of both shares)
    reseeded = [_rec("A", "CounterTop", "CounterTop", "Shelf", bowl="Shelf")]
    m = score(without, with_, {key: prof}, reseeded)["A"]
    assert m["side"] == {"n": 1, "share": 1.0} and m["side_rerun"] == {"n": 1, "share": 0.0}
    moved_again = [_rec("A", "CounterTop", "CounterTop", "Shelf", bowl="Floor")]
    m = score(without, with_, {key: prof}, moved_again)["A"]
    assert m["side_rerun"] == m["side_rerun_worse"] == {"n": 1, "share": 1.0}  # a bowl on the floor
    on_floor = [_rec("A", "DiningTable", "Fridge", "Shelf", bowl="Floor")]
    assert score(without, on_floor, {key: prof})["A"]["side_worse"] == {"n": 1, "share": 1.0}
    assert score(on_floor, with_, {key: prof})["A"]["side_worse"] == {"n": 1, "share": 0.0}  # better


def test_the_report_lists_every_side_effect_object_by_object() -> None:
    prof = {
        "asked": {"category": "Mug", "receptacle": "DiningTable"},
        "never": None,
        "group": {"categories": ["Plate"], "unnamed": ["Plate"], "receptacle": "Shelf"},
    }
    key = ("Kitchen", 200, 0)
    without = [_rec("A", "Shelf", "CounterTop", "CounterTop", bowl="Shelf")]
    # the apple (named by nothing here) stays; the bowl goes to the floor: a side effect for the worse
    with_ = [_rec("A", "DiningTable", "CounterTop", "Shelf", bowl="Floor")]
    effects = side_effect_list(without, with_, {key: prof})
    assert effects == [
        {
            "variant": "A",
            "configuration": "Kitchen_200_mess0",
            "object": "Bowl_0",
            "without": "Shelf",
            "with": "Floor",
            "moved_by_mess": False,
            "worse": True,
        }
    ]
    m = score(without, with_, {key: prof})["A"]
    assert m["side"] == {"n": 2, "share": 0.5}  # the same one of the two others the shares count
    report = {
        "config": {"configurations": 1, "split": "test", "perception": "learned", "oop": "visual"},
        "metrics": {"A": m},
        "side_effects": effects,
        "groups": {},
        "command": "tidee eval preferences",
    }
    md = _markdown(report)
    assert "| A | Kitchen_200_mess0 | Bowl_0 | Shelf | Floor | no | yes |" in md
    assert "| 50.0 % (1 of 2) |" in md  # the count beside the share: 10 of 496 is not "2.0 %" of a 2 % target


def test_keep_logs_gives_each_half_of_the_eval_its_own_log_folder(tmp_path, monkeypatch) -> None:
    from tidee.agent.evaluation import preference_eval
    from tidee.agent.evaluation.config import PreferenceEvalConfig
    from tidee.agent.reasoning import preferences

    seen = []

    def run_jobs(jobs, workers, renderer, progress, **_batch):
        seen.append([(j.log_dir, j.agent.preferences, j.agent.seed) for j in jobs])
        return [
            dict(
                _rec(j.agent.variant, "CounterTop", "CounterTop", "Shelf"),
                room_type=j.spec.room_type,
                seed=j.spec.seed,
                mess_index=j.spec.mess_index,
            )
            for j in jobs
        ]

    monkeypatch.setattr(preference_eval, "run_jobs", run_jobs)
    monkeypatch.setattr(preferences, "group_members", lambda phrase: ())

    class Anywhere:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def room(self, *key):
            return lambda cats, r: True

    monkeypatch.setattr(preference_eval, "placement_check", Anywhere)
    for keep, reseed in ((False, False), (True, True)):
        seen.clear()
        out = tmp_path / str(keep)
        cfg = PreferenceEvalConfig(
            out=out, episodes=2, variants=("CommonMemory",), keep_logs=keep, reseeded=reseed, progress=False
        )
        result = preference_eval.run_preference_eval(cfg)
        assert len(seen) == (3 if reseed else 2)
        without, with_ = seen[:2]
        assert all(p is None for _, p, _ in without) and all(p for _, p, _ in with_)
        halves = ("without", "with", "reseeded") if keep else ()
        for jobs, half in zip(seen, halves, strict=False):
            assert {d for d, _, _ in jobs} == {out / "logs" / half}
        if not keep:
            assert {d for jobs in seen for d, _, _ in jobs} == {None}
        if reseed:  # the same episodes, no profile, every agent seed moved by the offset
            again = seen[2]
            assert all(p is None for _, p, _ in again)
            assert [s for _, _, s in again] == [s + preference_eval.RESEED_OFFSET for _, _, s in without]
        m = result["metrics"]["CommonMemory"]
        assert m["asked"]["n"] == 2 and (out / "preferences.md").exists()
        assert (m["side_rerun"]["n"] > 0) == reseed
