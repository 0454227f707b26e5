"""Settled scenes on disk: the same episodes bit for bit, checksums, fingerprints."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from tidee.protocol.messages import Action, ActionName, EpisodeSpec
from tidee.server.episode import Episode, SceneLibrary
from tidee.server.scene_cache import SceneCache, generator_fingerprint

SPEC = EpisodeSpec(room_type="Bathroom", seed=201, mess_index=2, resolution=64, max_steps=20)
ACTIONS = [ActionName.RotateRight, ActionName.MoveAhead, ActionName.LookDown, ActionName.RotateLeft]


def _play(library: SceneLibrary) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
    ep = Episode(renderer="tiny", library=library)
    try:
        obs = [ep.reset(SPEC)]
        obs += [ep.step(Action(a)) for a in ACTIONS]
        state = ep.state()
    finally:
        ep.close()
    return [(o.rgb, o.depth, o.agent_pose) for o in obs], state


def test_a_cached_scene_plays_the_same_episode_bit_for_bit(tmp_path) -> None:
    cache = SceneCache(tmp_path)
    fresh, fresh_state = _play(SceneLibrary(disk=None))  # no disk cache at all
    filled, _ = _play(SceneLibrary(disk=cache))  # generates and stores
    assert cache.path(SPEC.room_type, SPEC.seed, SPEC.mess_index).exists()
    assert cache.path(SPEC.room_type, SPEC.seed, None).exists()  # the tidy room too
    warm_cache = SceneCache(tmp_path)
    loaded, loaded_state = _play(SceneLibrary(disk=warm_cache))  # a new process would do this
    assert warm_cache.hits == 1 and warm_cache.misses == 0
    for a, b, c in zip(fresh, filled, loaded):
        for x, y, z in zip(a, b, c):
            assert np.array_equal(np.asarray(x), np.asarray(y)) and np.array_equal(
                np.asarray(x), np.asarray(z)
            )
    assert json.dumps(fresh_state, sort_keys=True) == json.dumps(loaded_state, sort_keys=True)


def test_a_damaged_entry_is_ignored_and_regenerated(tmp_path) -> None:
    cache = SceneCache(tmp_path)
    scene = {"format_version": 1, "objects": [{"id": "Mug_1", "position": [0.5, 1.25, 0.9]}]}
    cache.store("Kitchen", 3, 7, scene)
    assert cache.load("Kitchen", 3, 7) == scene
    path = cache.path("Kitchen", 3, 7)
    entry = json.loads(gzip.open(path, "rt").read())
    entry["scene"]["objects"][0]["position"][2] = 0.95  # a flipped value: checksum fails
    with gzip.open(path, "wt") as f:
        json.dump(entry, f)
    assert cache.load("Kitchen", 3, 7) is None and not path.exists()
    path.write_bytes(b"\x1f\x8b not gzip")  # a torn file
    assert cache.load("Kitchen", 3, 7) is None
    assert cache.load("Kitchen", 3, 8) is None and cache.misses == 3


def test_the_fingerprint_follows_the_generator_version() -> None:
    assert generator_fingerprint(1) != generator_fingerprint(2)
    assert SceneCache(version=1).dir != SceneCache(version=2).dir


def test_an_unwritable_cache_only_costs_speed(tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    cache = SceneCache(blocker)
    cache.store("Kitchen", 3, None, {"a": 1})  # logs, does not raise
    assert cache.load("Kitchen", 3, None) is None


@pytest.mark.parametrize("mess", [None, 0])
def test_the_library_prefers_memory_then_disk(tmp_path, mess) -> None:
    from tidee.server.world import World

    cache = SceneCache(tmp_path)
    lib = SceneLibrary(disk=cache)
    world = World(renderer="tiny")
    try:
        lib.scene(world, "Kitchen", 202, mess)
        lib.scene(world, "Kitchen", 202, mess)  # from memory: the disk is not asked again
        assert cache.hits == 0
        lib2 = SceneLibrary(disk=SceneCache(tmp_path))
        lib2.scene(world, "Kitchen", 202, mess)
        assert lib2.disk().hits == 1
    finally:
        world.close()
