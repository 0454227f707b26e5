"""ObjectMemory: merging by label and distance, weighted averages, ids."""

from __future__ import annotations

import numpy as np
import pytest

from tidee.agent.mapping.memory import ObjectMemory

BOX = (np.zeros(3), np.ones(3))


def add(mem: ObjectMemory, label: str, c, score: float = 1.0, step: int = 0, **kw):
    c = np.asarray(c, float)
    return mem.add_or_merge(label, score, c, c - 0.1, c + 0.1, step, **kw)


def test_same_label_within_merge_distance_merges() -> None:
    mem = ObjectMemory(merge_distance=1.0)
    a = add(mem, "Mug", [1.0, 2.0, 0.9], step=3)
    b = add(mem, "Mug", [1.6, 2.0, 0.9], step=7)
    assert b is a and len(mem) == 1
    assert a.n_obs == 2 and a.first_seen == 3 and a.last_seen == 7


def test_a_label_can_have_its_own_merge_distance() -> None:
    mem = ObjectMemory(merge_distance=1.0, label_merge={"Apple": 0.25})
    a = add(mem, "Apple", [1.0, 2.0, 0.9])
    b = add(mem, "Apple", [1.4, 2.0, 0.9])  # two apples 40 cm apart on one counter
    c = add(mem, "Apple", [1.1, 2.0, 0.9])
    assert b is not a and c is a and len(mem.of_label("Apple")) == 2
    d = add(mem, "Cabinet", [0.0, 0.0, 0.4])
    assert add(mem, "Cabinet", [0.6, 0.0, 0.4]) is d  # other labels: merge_distance
    with pytest.raises(ValueError, match="label_merge distances must be > 0"):
        ObjectMemory(label_merge={"Apple": 0.0})


def test_different_label_or_far_makes_new_entries() -> None:
    mem = ObjectMemory(merge_distance=1.0)
    a = add(mem, "Mug", [0.0, 0.0, 0.9])
    b = add(mem, "Cup", [0.0, 0.0, 0.9])
    c = add(mem, "Mug", [1.01, 0.0, 0.9])
    assert len({a.id, b.id, c.id}) == 3 and len(mem) == 3
    assert [o.id for o in mem.of_label("Mug")] == [a.id, c.id]
    assert mem.labels() == ["Cup", "Mug"]


def test_merges_into_the_nearest_same_label_entry() -> None:
    mem = ObjectMemory(merge_distance=1.0)
    a = add(mem, "Mug", [0.0, 0.0, 0.0])
    b = add(mem, "Mug", [1.5, 0.0, 0.0])
    hit = add(mem, "Mug", [1.0, 0.0, 0.0])  # 1.0 from a, 0.5 from b
    assert hit is b and a.n_obs == 1 and b.n_obs == 2


def test_score_weighted_running_averages() -> None:
    mem = ObjectMemory()
    o = mem.add_or_merge(
        "Book",
        0.2,
        np.array([0.0, 0.0, 0.0]),
        np.array([-1.0, -1, -1]),
        np.array([1.0, 1, 1]),
        0,
        oop_prob=0.2,
    )
    mem.add_or_merge(
        "Book",
        0.6,
        np.array([0.4, 0.0, 0.0]),
        np.array([-0.6, -1, -1]),
        np.array([1.4, 1, 1]),
        1,
        oop_prob=None,
    )
    mem.add_or_merge(
        "Book",
        0.2,
        np.array([0.0, 0.8, 0.0]),
        np.array([-1.0, -0.2, -1]),
        np.array([1.0, 1.8, 1]),
        2,
        oop_prob=0.6,
        feature=np.array([1.0, 2.0], np.float32),
    )
    # weights 0.2, 0.6, 0.2 over a total of 1.0
    np.testing.assert_allclose(o.centroid, [0.24, 0.16, 0.0], atol=1e-12)
    np.testing.assert_allclose(o.box_min, [-0.76, -0.84, -1.0], atol=1e-12)
    np.testing.assert_allclose(o.box_max, [1.24, 1.16, 1.0], atol=1e-12)
    assert o.score == pytest.approx(0.6) and o.n_obs == 3
    assert o.oop_prob == pytest.approx(0.4)  # mean of the non-None 0.2 and 0.6
    np.testing.assert_array_equal(o.feature, [1.0, 2.0])


def test_latest_feature_kept_when_later_is_none() -> None:
    mem = ObjectMemory()
    o = add(mem, "Mug", [0, 0, 0], feature=np.array([3.0]))
    add(mem, "Mug", [0, 0, 0.1], feature=None)
    np.testing.assert_array_equal(o.feature, [3.0])
    assert o.oop_prob is None


def test_ids_not_reused_after_removal() -> None:
    mem = ObjectMemory()
    a = add(mem, "Mug", [0, 0, 0])
    b = add(mem, "Mug", [5, 0, 0])
    removed = mem.remove(b.id)
    assert removed is b and mem.get(b.id) is None and b.id not in mem
    c = add(mem, "Mug", [5, 0, 0])
    assert c.id not in (a.id, b.id) and c.id > b.id
    with pytest.raises(KeyError, match="no tracked object with id"):
        mem.remove(b.id)
    mem.clear()
    assert len(mem) == 0 and list(mem) == []


def test_nearest_and_iteration_order() -> None:
    mem = ObjectMemory()
    add(mem, "Mug", [0, 0, 0.9])
    far = add(mem, "Mug", [3, 3, 0.1])
    add(mem, "Plate", [3.1, 3.1, 0.1])
    assert mem.nearest("Mug", (2.5, 2.5)) is far
    assert mem.nearest("Bowl", (0, 0)) is None
    assert [o.id for o in mem] == [0, 1, 2]


def test_rejects_bad_input() -> None:
    mem = ObjectMemory()
    with pytest.raises(ValueError, match="centroid must have 3"):
        mem.add_or_merge("Mug", 0.5, np.zeros(2), *BOX, 0)
    with pytest.raises(ValueError, match="exceeds box_max"):
        mem.add_or_merge("Mug", 0.5, np.zeros(3), np.ones(3), np.zeros(3), 0)
    with pytest.raises(ValueError, match="score must be in"):
        mem.add_or_merge("Mug", 1.5, np.zeros(3), *BOX, 0)
    with pytest.raises(ValueError, match="merge_distance"):
        ObjectMemory(merge_distance=0)
