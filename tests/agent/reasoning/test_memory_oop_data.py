"""OOP samples from the agent's own object memory (`tidee gen oop-memory`)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.reasoning.language_oop import memory_data as mem
from tidee.agent.reasoning.language_oop.config import MemoryGenConfig


def _track(i: int, label: str, xyz: tuple[float, float, float]) -> TrackedObject:
    c = np.array(xyz, float)
    return TrackedObject(id=i, label=label, score=1.0, centroid=c, box_min=c - 0.05, box_max=c + 0.05)


def test_tracks_match_objects_of_their_class_one_to_one_in_the_world_frame() -> None:
    # start frame: origin at (2, 1), yawed 90 degrees (start x axis = world y axis)
    start = {"x": 2.0, "y": 1.0, "yaw_deg": 90.0}
    objects = [
        {"id": "Mug_0", "type": "Mug", "centroid": [2.0, 2.0, 0.9]},  # start (1, 0)
        {"id": "Mug_1", "type": "Mug", "centroid": [2.0, 2.3, 0.9]},  # start (1.3, 0)
        {"id": "Bowl_0", "type": "Bowl", "centroid": [1.0, 1.0, 0.9]},
    ]  # start (0, 1)
    tracks = [
        _track(1, "Mug", (1.05, 0.0, 0.9)),
        _track(2, "Mug", (1.1, 0.0, 0.9)),
        _track(3, "Bowl", (0.0, 1.0, 0.9)),
        _track(4, "Mug", (0.0, 1.0, 0.9)),
    ]
    m = mem.match_tracks(tracks, objects, start)
    assert m[1]["id"] == "Mug_0"  # the nearest pair first
    assert m[2]["id"] == "Mug_1"  # one to one: the second mug track takes the other mug
    assert m[3]["id"] == "Bowl_0"
    assert 4 not in m  # a mug track where only a bowl is: no match


def test_memory_samples_are_labelled_by_the_mess_up() -> None:
    from tidee.protocol.transport import InProcessTransport

    t = InProcessTransport(renderer="tiny")
    try:
        rows = mem.config_memory_samples(t, "Bathroom", 0, 0, resolution=96, max_steps=150)
        moved = {m["id"] for m in t.state()["mess"]}
    finally:
        t.close()
    assert rows, "the agent mapped a bathroom and tracked no pickupable object"
    for r in rows:
        assert r["label"] == int(r["object"] in moved), r
        assert r["object"].split("_")[0] == r["category"]
        assert r["paragraph"].startswith("The ")
    assert any(r["label"] == 1 for r in rows) and any(r["label"] == 0 for r in rows)


def test_loading_refuses_the_wrong_split_and_names_a_bad_line(tmp_path) -> None:
    (tmp_path / "meta.json").write_text(json.dumps({"split": "test"}))
    (tmp_path / "samples.jsonl").write_text('{"paragraph": "x", "label": 0}\nnot json\n')
    with pytest.raises(ValueError, match="'test' samples; this needs 'train'"):
        mem.load_memory_samples(tmp_path, split="train")
    with pytest.raises(ValueError, match="line 2 is not JSON"):
        mem.load_memory_samples(tmp_path, split="test")
    with pytest.raises(FileNotFoundError, match="tidee gen oop-memory"):
        mem.load_memory_samples(tmp_path / "missing")


def test_generation_refuses_messes_the_split_does_not_have(tmp_path) -> None:
    with pytest.raises(ValueError, match="test rooms have messes 0-4"):
        MemoryGenConfig(out=str(tmp_path), split="test", rooms_per_type=1, messes=6)


def test_the_fused_head_refuses_memory_samples_without_detector_features(tmp_path) -> None:
    pytest.importorskip("torch")
    from tidee.agent.reasoning.language_oop.fused_train import add_memory_samples

    (tmp_path / "meta.json").write_text(json.dumps({"split": "train", "perception": "oracle"}))
    (tmp_path / "samples.jsonl").write_text("")
    with pytest.raises(ValueError, match="--perception learned"):
        add_memory_samples(
            {"paragraphs": [], "features": np.zeros((0, 64)), "labels": [], "categories": [], "rooms": []},
            tmp_path,
        )
    (tmp_path / "meta.json").write_text(json.dumps({"split": "train", "perception": "learned"}))
    (tmp_path / "samples.jsonl").write_text(
        json.dumps(
            {
                "paragraph": "The mug is supported by the floor.",
                "label": 1,
                "category": "Mug",
                "room_type": "Kitchen",
                "config": "Kitchen:60:0",
                "object": "Mug_0",
                "snapshot": 0,
                "feature": [0.5] * 64,
            }
        )
        + "\n"
    )
    samples: dict[str, Any] = {
        "paragraphs": ["p"],
        "features": np.zeros((1, 64), np.float32),
        "labels": [0],
        "categories": ["Cup"],
        "rooms": ["Kitchen:61:0:3"],
    }
    meta = add_memory_samples(samples, tmp_path)
    assert meta["perception"] == "learned"
    assert samples["labels"] == [0, 1] and samples["features"].shape == (2, 64)
    assert samples["features"][1, 0] == pytest.approx(0.5) and samples["rooms"][1] == "Kitchen:60:0"
