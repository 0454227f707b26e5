"""Rearrangement configurations and the two-phase episode: in process, over Zenoh, as a gym env."""

from __future__ import annotations

import socket
import uuid

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tidee.protocol  # noqa: F401  (registers tidee/Rearrange-v0)
from tests.support.fakes import FakeEpisode
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.messages import Action, ActionName, EpisodeSpec, ErrorCode
from tidee.protocol.transport import InProcessTransport
from tidee.server.episode import Episode, SceneLibrary
from tidee.server.scene_cache import SceneCache
from tidee.server.service import ServerConfig, SimServer
from tidee.server.shuffle import MOVED, TOGGLED

CONFIGS = [("Kitchen", 201, 1), ("LivingRoom", 200, 0), ("Bathroom", 204, 3)]
SPEC = EpisodeSpec(room_type="Kitchen", seed=201, rearrange_index=1, resolution=32, walkthrough_steps=5)


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> SceneLibrary:
    return SceneLibrary(disk=SceneCache(tmp_path_factory.mktemp("scenes")))


@pytest.fixture
def episode(library: SceneLibrary):
    ep = Episode(renderer="tiny", library=library)
    yield ep
    ep.close()


def _by_id(objects: list[dict]) -> dict[str, dict]:
    return {o["id"]: o for o in objects}


@pytest.mark.parametrize(("room_type", "seed", "index"), CONFIGS)
def test_shuffle_moves_what_its_record_says_and_nothing_else(
    library: SceneLibrary, episode: Episode, room_type: str, seed: int, index: int
) -> None:
    pair = library.rearrangement(episode.world, room_type, seed, index)
    goal, shuffled = pair.goal.by_id(), pair.shuffled.by_id()
    moved = {m.id for m in pair.shuffled.mess}
    assert MOVED[0] <= len(moved) <= MOVED[1]
    assert len(pair.toggled()) <= TOGGLED[1]
    for oid, o in shuffled.items():
        g = goal[oid]
        shift = float(np.linalg.norm(np.subtract(o.position, g.position)))
        if oid in moved:
            assert o.parent != g.parent or shift >= 0.3, oid
        elif o.pickupable:
            assert o.parent == g.parent and shift < 0.02, (oid, shift)
        if o.openable and not o.pickupable:
            assert (o.is_open != g.is_open) == (oid in pair.toggled())


def test_configurations_are_deterministic_and_cached(tmp_path, episode: Episode) -> None:
    fresh = SceneLibrary(disk=None).rearrangement(episode.world, "Kitchen", 201, 1)
    cache = SceneCache(tmp_path)
    SceneLibrary(disk=cache).rearrangement(episode.world, "Kitchen", 201, 1)
    assert cache.path("Kitchen", 201, "shuffle1").exists() and cache.path("Kitchen", 201, "goal1").exists()
    warm = SceneCache(tmp_path)
    loaded = SceneLibrary(disk=warm).rearrangement(episode.world, "Kitchen", 201, 1)
    assert warm.misses == 0 and warm.hits == 2
    assert loaded.goal.to_dict() == fresh.goal.to_dict()
    assert loaded.shuffled.to_dict() == fresh.shuffled.to_dict()
    other = SceneLibrary(disk=None).rearrangement(episode.world, "Kitchen", 201, 2)
    assert other.shuffled.to_dict() != fresh.shuffled.to_dict()


def test_walkthrough_refuses_interaction_then_unshuffle_starts_at_the_same_pose(episode: Episode) -> None:
    first = episode.reset(SPEC)
    assert first.phase == "walkthrough" and first.steps_left == SPEC.walkthrough_steps
    goal = _by_id(episode.state()["objects"])
    for name in (ActionName.PickupObject, ActionName.OpenObject, ActionName.PutObject):
        obs = episode.step(Action(name, 0.5, 0.6))
        assert not obs.success and obs.error == "walkthrough" and "walkthrough" in obs.message
    assert _by_id(episode.state()["objects"]) == goal  # nothing touched
    obs = episode.step(Action(ActionName.MoveAhead))
    assert obs.phase == "walkthrough"
    obs = episode.step(Action(ActionName.RotateLeft))
    assert obs.done and obs.steps_left == 0  # the walkthrough's own cap (5)
    unshuffle = episode.begin_unshuffle()
    assert unshuffle.phase == "unshuffle" and not unshuffle.done and unshuffle.step == 0
    assert unshuffle.steps_left == SPEC.max_steps
    assert unshuffle.agent_pose == first.agent_pose == (0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(unshuffle.camera_pose, first.camera_pose)
    state = episode.state()
    assert state["phase"] == "unshuffle"
    assert any(
        o["parent"] != goal[o["id"]]["parent"] or o["position"] != goal[o["id"]]["position"]
        for o in state["objects"]
        if o["pickupable"]
    )
    with pytest.raises(ValueError, match="already begun"):
        episode.begin_unshuffle()
    episode.reset(EpisodeSpec(room_type="Kitchen", seed=201, mess_index=0, resolution=32))
    with pytest.raises(ValueError, match="not a rearrangement"):
        episode.begin_unshuffle()


def test_a_spec_is_either_a_mess_or_a_rearrangement() -> None:
    with pytest.raises(ValueError, match="not both"):
        EpisodeSpec(seed=200, mess_index=0, rearrange_index=0)


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def test_phases_over_zenoh_and_bad_requests_leave_the_session_usable(library: SceneLibrary) -> None:
    endpoint = _free_endpoint()
    config = ServerConfig(endpoint=endpoint, server_id=f"r{uuid.uuid4().hex[:8]}", workers=1)
    with SimServer(config, lambda: Episode(renderer="tiny", library=library)):
        with SimClient(endpoint=endpoint, server_id=config.server_id, timeout=120) as client:
            with pytest.raises(RemoteError) as bad_index:
                client.reset(EpisodeSpec(room_type="Kitchen", seed=201, rearrange_index=99, resolution=32))
            assert bad_index.value.code == ErrorCode.invalid_field
            assert "spec.rearrange_index" in bad_index.value.message and "0-4" in bad_index.value.message
            client.reset(EpisodeSpec(room_type="Kitchen", seed=201, mess_index=0, resolution=32))
            with pytest.raises(RemoteError, match="not a rearrangement") as early:
                client.begin_unshuffle()
            assert early.value.code == ErrorCode.invalid_field
            obs = client.reset(SPEC)
            assert obs.phase == "walkthrough"
            assert client.step(Action(ActionName.PickupObject, 0.5, 0.5)).error == "walkthrough"
            obs = client.begin_unshuffle()
            assert obs.phase == "unshuffle" and obs.step == 0
            with pytest.raises(RemoteError, match="already begun"):
                client.begin_unshuffle()
            assert client.step(Action(ActionName.RotateLeft)).success  # still usable
            assert client.state()["phase"] == "unshuffle"


def _env(library: SceneLibrary) -> gym.Env:
    transport = InProcessTransport(Episode(renderer="tiny", library=library))
    return gym.make("tidee/Rearrange-v0", spec=SPEC, transport=transport)


def test_rearrange_env_passes_check_env() -> None:
    # The fake episode: check_env resets with random room seeds, which a real one would generate.
    env = gym.make("tidee/Rearrange-v0", spec=SPEC, transport=InProcessTransport(FakeEpisode()))
    check_env(env.unwrapped)  # it closes the env


def test_rearrange_env_switches_phase_on_done(library: SceneLibrary) -> None:
    env = _env(library)
    try:
        obs, _ = env.reset(seed=201)
        assert obs["phase"] == 0
        done = {"action": list(ActionName).index(ActionName.Done), "point": np.zeros(2, np.float32)}
        obs, _, terminated, truncated, info = env.step(done)
        assert obs["phase"] == 1 and not terminated and not truncated and info["step"] == 0
        obs, _, terminated, _, _ = env.step(done)
        assert terminated and obs["phase"] == 1
    finally:
        env.close()
