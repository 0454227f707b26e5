"""Vector environments: ``gymnasium.make_vec`` of ``tidee/Tidy-v0`` and ``tidee/Rearrange-v0``,
synchronous and asynchronous, in process and over Zenoh.

Gymnasium 1.x ships no checker for vector envs, so :func:`check_vector_env` does what one would:
the batched spaces are the single env's, every observation is in the batched space, a reset with a
seed gives sub-env i the seed + i, and a sub-env that ends resets on its next step (Gymnasium's
default next-step autoreset) while the others go on. Each sub-env also passes
``gymnasium.utils.env_checker.check_env``."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import tidee.protocol  # noqa: F401  (registers the environments)
from tests.support.fakes import FakeEpisode
from tests.support.net import start_server
from tidee.protocol.gym_env import ACTIONS, RearrangeEnv, TidyEnv
from tidee.protocol.messages import ActionName, EpisodeSpec
from tidee.protocol.transport import InProcessTransport

SPEC = EpisodeSpec(resolution=32, max_steps=3)
ASYNC = {"vector_kwargs": {"context": "spawn"}}  # a forked PyBullet or Zenoh is unsafe
N = 2


def fake_transport() -> InProcessTransport:
    """A fresh fake simulator per sub-env (module-level: the spawned sub-envs unpickle it)."""
    return InProcessTransport(FakeEpisode())


def _actions(names: list[ActionName]) -> dict[str, np.ndarray]:
    return {
        "action": np.array([ACTIONS.index(n) for n in names]),
        "point": np.full((len(names), 2), 0.75, np.float32),
    }


def check_vector_env(envs: gym.vector.VectorEnv, single: gym.Env) -> list[Any]:
    """The checks above; returns what the envs gave, to compare two vector envs."""
    assert envs.num_envs == N
    assert envs.single_observation_space == single.observation_space
    assert envs.single_action_space == single.action_space
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    envs.action_space.seed(0)
    assert envs.action_space.contains(envs.action_space.sample())
    obs, info = envs.reset(seed=5)
    assert envs.observation_space.contains(obs)
    assert list(info["step"]) == [0] * N
    seen = [obs, info["step"].tolist()]
    move, done = ActionName.MoveAhead, ActionName.Done
    # sub-env 0 ends with Done; sub-env 1 walks on
    obs, reward, terminated, truncated, info = envs.step(_actions([done, move]))
    assert envs.observation_space.contains(obs)
    assert terminated.tolist() == [True, False] and truncated.tolist() == [False, False]
    assert reward.tolist() == [0.0, 0.0] and info["step"].tolist() == [1, 1]
    seen += [obs, info["step"].tolist()]
    # next step: sub-env 0 resets (its action ignored), sub-env 1 steps
    obs, reward, terminated, truncated, info = envs.step(_actions([move, move]))
    assert info["step"].tolist() == [0, 2] and not terminated.any() and not truncated.any()
    assert float(obs["pose"][0, 0]) == 0.0 and float(obs["pose"][1, 0]) == 0.5  # 2 MoveAheads of 0.25 m
    seen += [obs, info["step"].tolist()]
    # the step cap truncates sub-env 1
    obs, reward, terminated, truncated, info = envs.step(_actions([move, move]))
    assert truncated.tolist() == [False, True] and info["step"].tolist() == [1, 3]
    seen += [obs, info["step"].tolist()]
    envs.close()
    return seen


def _same(a: list[Any], b: list[Any]) -> bool:
    from gymnasium.utils.env_checker import data_equivalence

    return all(data_equivalence(x, y, exact=True) for x, y in zip(a, b, strict=True))


def test_make_vec_sync_and_async_in_process_pass_the_checks_and_agree() -> None:
    single = TidyEnv(spec=SPEC, transport=fake_transport)
    kw: dict[str, Any] = {"spec": SPEC, "transport": fake_transport}
    sync = gym.make_vec("tidee/Tidy-v0", num_envs=N, vectorization_mode="sync", **kw)
    assert isinstance(sync, gym.vector.SyncVectorEnv)
    for sub in sync.envs:
        check_env(sub.unwrapped)
    seen_sync = check_vector_env(sync, single)
    asynchronous = gym.make_vec("tidee/Tidy-v0", num_envs=N, vectorization_mode="async", **kw, **ASYNC)
    assert isinstance(asynchronous, gym.vector.AsyncVectorEnv)
    assert _same(seen_sync, check_vector_env(asynchronous, single))
    single.close()


def test_vector_reset_seeds_each_sub_env_with_its_own_room() -> None:
    envs = gym.make_vec("tidee/Tidy-v0", num_envs=N, spec=SPEC, transport=fake_transport)
    envs.reset(seed=40)
    assert [sub.unwrapped.transport.episode.spec.seed for sub in envs.envs] == [40, 41]
    envs.close()


def test_a_transport_instance_serves_one_env_at_a_time() -> None:
    with pytest.raises(ValueError, match="pass transport as a function"):
        gym.make_vec("tidee/Tidy-v0", num_envs=N, spec=SPEC, transport=fake_transport())
    shared = fake_transport()
    first = TidyEnv(spec=SPEC, transport=shared)
    with pytest.raises(ValueError, match="already serves another open env"):
        TidyEnv(spec=SPEC, transport=shared)
    first.close()
    TidyEnv(spec=SPEC, transport=shared).close()  # free again once the first env is closed


def test_rearrange_vector_env_goes_from_walkthrough_to_unshuffle() -> None:
    spec = EpisodeSpec(resolution=32, max_steps=3, rearrange_index=1)
    envs = gym.make_vec("tidee/Rearrange-v0", num_envs=N, spec=spec, transport=fake_transport)
    single = RearrangeEnv(spec=spec, transport=fake_transport)
    assert envs.single_observation_space == single.observation_space
    obs, _ = envs.reset(seed=3)
    assert obs["phase"].tolist() == [0, 0] and envs.observation_space.contains(obs)
    obs, _, terminated, truncated, _ = envs.step(_actions([ActionName.Done, ActionName.MoveAhead]))
    assert obs["phase"].tolist() == [1, 0] and not terminated.any() and not truncated.any()
    obs, _, terminated, _, _ = envs.step(_actions([ActionName.Done, ActionName.MoveAhead]))
    assert terminated.tolist() == [True, False]
    envs.close()
    single.close()


def test_real_rooms_in_process_sync_vector_env() -> None:
    pytest.importorskip("pybullet")
    spec = EpisodeSpec(room_type="Bathroom", resolution=32, max_steps=4)
    envs = gym.make_vec("tidee/Tidy-v0", num_envs=N, spec=spec, transport_kwargs={"renderer": "tiny"})
    obs, info = envs.reset(seed=200)
    assert envs.observation_space.contains(obs) and obs["rgb"].shape == (N, 32, 32, 3)
    assert not np.array_equal(obs["rgb"][0], obs["rgb"][1])  # rooms 200 and 201
    obs, *_ = envs.step(_actions([ActionName.RotateLeft, ActionName.LookDown]))
    assert envs.observation_space.contains(obs)
    envs.close()


def test_over_zenoh_one_server_many_sessions_and_sub_envs_spread_over_servers() -> None:
    servers = [start_server(), start_server()]
    try:
        one = {"endpoint": servers[0].config.endpoint, "server_id": servers[0].config.server_id}
        single = TidyEnv(spec=SPEC, transport=fake_transport)
        envs = gym.make_vec(
            "tidee/Tidy-v0", num_envs=N, vectorization_mode="async", spec=SPEC, transport="zenoh",
            transport_kwargs=one, **ASYNC,
        )  # fmt: skip
        seen = check_vector_env(envs, single)
        assert _same(seen, check_vector_env(gym.make_vec("tidee/Tidy-v0", num_envs=N, spec=SPEC,
                                                         transport=fake_transport), single))  # fmt: skip
        assert servers[0].sessions == ()  # every session closed with its sub-env
        # sub-envs spread over servers: one function per sub-env
        spread = gym.vector.AsyncVectorEnv(
            [_zenoh_env_fn(s.config.endpoint, s.config.server_id) for s in servers], context="spawn"
        )
        spread.reset(seed=1)
        assert [len(s.sessions) for s in servers] == [1, 1]
        spread.step(_actions([ActionName.MoveAhead, ActionName.MoveAhead]))
        spread.close()
        single.close()
    finally:
        for s in servers:
            s.stop()


def _zenoh_env_fn(endpoint: str, server_id: str) -> Any:
    def make() -> gym.Env:
        kwargs = {"endpoint": endpoint, "server_id": server_id}
        return gym.make("tidee/Tidy-v0", spec=SPEC, transport="zenoh", transport_kwargs=kwargs)

    return make
