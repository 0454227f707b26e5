"""The eval's scheduling estimate: an episode's cost is its room's object count from the scene cache."""

from __future__ import annotations

from pathlib import Path

import pytest

from tidee.agent.evaluation import tidy_eval
from tidee.protocol.messages import EpisodeSpec
from tidee.server.scene_cache import SceneCache


def test_an_episode_costs_its_rooms_objects_and_an_uncached_room_more_than_any(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    tidy_eval._room_cost.cache_clear()
    small = EpisodeSpec(room_type="Bathroom", seed=201, mess_index=3)
    big = EpisodeSpec(room_type="Kitchen", seed=201, mess_index=0)
    SceneCache().store("Bathroom", 201, None, {"objects": [{"id": i} for i in range(30)]})
    SceneCache().store("Kitchen", 201, None, {"objects": [{"id": i} for i in range(50)]})
    assert tidy_eval.episode_cost(small) == 30.0 and tidy_eval.episode_cost(big) == 50.0
    assert tidy_eval.episode_cost(EpisodeSpec(room_type="Bedroom", seed=202)) == tidy_eval.UNCACHED_COST
    assert tidy_eval.UNCACHED_COST > 50
    tidy_eval._room_cost.cache_clear()
