"""The Gymnasium environment over both transports."""

from __future__ import annotations

import socket
import uuid
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tidee.protocol  # noqa: F401  (registers tidee/Tidy-v0)
from tests.support.fakes import FakeEpisode
from tidee.protocol.gym_env import ACTIONS, TidyEnv, to_action
from tidee.protocol.messages import Action, ActionName, EpisodeSpec
from tidee.protocol.transport import InProcessTransport, SimTransport
from tidee.server.service import ServerConfig, SimServer

SPEC = EpisodeSpec(resolution=32, max_steps=5)


def fake_env(**kwargs: Any) -> gym.Env:
    return gym.make("tidee/Tidy-v0", spec=SPEC, transport=InProcessTransport(FakeEpisode()), **kwargs)


def test_check_env_in_process() -> None:
    env = fake_env()
    check_env(env.unwrapped)
    env.close()


def test_check_env_over_zenoh() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    config = ServerConfig(endpoint=endpoint, server_id=f"g{uuid.uuid4().hex[:8]}")
    server = SimServer(config, FakeEpisode).start()
    try:
        env = gym.make(
            "tidee/Tidy-v0",
            spec=SPEC,
            transport="zenoh",
            transport_kwargs={"endpoint": endpoint, "server_id": server.config.server_id},
        )
        check_env(env.unwrapped)
        env.close()
        assert server.sessions == ()
    finally:
        server.stop()


def test_transports_are_sim_transports() -> None:
    assert isinstance(InProcessTransport(FakeEpisode()), SimTransport)


def test_spaces_and_episode_end() -> None:
    env = fake_env(render_mode="rgb_array")
    obs, info = env.reset(seed=7)
    assert env.observation_space.contains(obs) and info["step"] == 0 and info["steps_left"] == 5
    assert env.action_space["action"].n == len(ActionName) == 13
    assert env.render().shape == (32, 32, 3)
    move = {"action": ACTIONS.index(ActionName.MoveAhead), "point": np.zeros(2, np.float32)}
    for _ in range(4):
        obs, reward, terminated, truncated, info = env.step(move)
        assert reward == 0.0 and not terminated and not truncated
    _, _, terminated, truncated, _ = env.step(move)
    assert truncated and not terminated  # the step cap
    env.reset(seed=7)
    done = {"action": ACTIONS.index(ActionName.Done), "point": np.zeros(2, np.float32)}
    _, _, terminated, truncated, _ = env.step(done)
    assert terminated and not truncated
    env.close()


def test_seed_selects_the_room_and_options_change_the_spec() -> None:
    episode = FakeEpisode()
    env = TidyEnv(spec=SPEC, transport=InProcessTransport(episode))
    env.reset(seed=11, options={"room_type": "Kitchen", "mess_index": 2})
    assert episode.spec is not None
    assert (episode.spec.seed, episode.spec.room_type, episode.spec.mess_index) == (11, "Kitchen", 2)
    with pytest.raises(ValueError, match="resolution"):
        env.reset(options={"resolution": 64})
    env.close()


def test_to_action() -> None:
    pick = ACTIONS.index(ActionName.PickupObject)
    assert to_action({"action": pick, "point": np.array([0.25, 1.0], np.float32)}) == Action(
        ActionName.PickupObject, 0.25, 1.0
    )
    assert to_action({"action": 0, "point": np.array([0.5, 0.5])}) == Action(ACTIONS[0])


def test_real_episode_in_process() -> None:
    pytest.importorskip("pybullet")
    env = gym.make(
        "tidee/Tidy-v0",
        spec=EpisodeSpec(room_type="Bedroom", seed=2, resolution=32),
        transport_kwargs={"renderer": "tiny"},
    )
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_send_step_runs_in_process_when_asked_and_over_zenoh_at_once() -> None:
    from tests.support.net import wait_until
    from tidee.protocol.client import SimClient
    from tidee.protocol.transport import send_step

    episode = FakeEpisode()
    transport = InProcessTransport(episode)
    transport.reset(SPEC)
    observe = send_step(transport, Action(ActionName.MoveAhead))
    assert episode.steps == 0  # in process: the step runs when its observation is asked for
    assert observe().step == 1 and episode.steps == 1
    made: list[FakeEpisode] = []

    def factory() -> FakeEpisode:
        made.append(FakeEpisode())
        return made[-1]

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    server = SimServer(ServerConfig(endpoint=endpoint, server_id=f"s{uuid.uuid4().hex[:8]}"), factory).start()
    try:
        with SimClient(endpoint, server_id=server.config.server_id, timeout=30, connect_timeout=30) as client:
            client.reset(SPEC)
            observe = send_step(client, Action(ActionName.MoveAhead))
            # over Zenoh the request leaves at once: the server steps before anyone waits for it
            assert wait_until(lambda: any(e.steps == 1 for e in made), timeout=10.0)
            obs = observe()
            assert obs.step == 1 and obs.success
            assert client.step(Action(ActionName.MoveAhead)).step == 2
    finally:
        server.stop()
