"""Several tidee rooms at once as a Gymnasium vector environment: `gymnasium.make_vec`.

Each sub-env holds its own simulator, here in its own process (``vectorization_mode="async"``;
``"sync"`` steps them one after another in this process). ``reset(seed=s)`` plays rooms s, s+1,
...; a sub-env whose episode ends resets on its next step, so the batch keeps going. Against
running servers, ``transport="zenoh"`` with ``transport_kwargs={"endpoint": ...}`` gives each
sub-env its own session.

Run:  .venv/bin/python examples/06_vector_env.py
"""

from __future__ import annotations

import gymnasium
import numpy as np

import tidee  # noqa: F401  (registers tidee/Tidy-v0)
from tidee.protocol.gym_env import ACTIONS
from tidee.protocol.messages import ActionName, EpisodeSpec

if __name__ == "__main__":  # the sub-env processes import this file: only the parent runs it
    envs = gymnasium.make_vec(
        "tidee/Tidy-v0",
        num_envs=2,
        vectorization_mode="async",
        vector_kwargs={"context": "spawn"},  # a forked PyBullet is unsafe
        spec=EpisodeSpec(room_type="Bathroom", resolution=64, max_steps=3),
        transport_kwargs={"renderer": "tiny"},
    )
    obs, info = envs.reset(seed=200)  # Bathroom 200 and Bathroom 201: two test rooms
    print(f"reset: rgb {obs['rgb'].shape}, rooms differ: {not np.array_equal(obs['rgb'][0], obs['rgb'][1])}")
    turn = ACTIONS.index(ActionName.RotateLeft)
    for _ in range(4):
        action = {"action": np.full(2, turn), "point": np.zeros((2, 2), np.float32)}
        obs, reward, terminated, truncated, info = envs.step(action)
        print(f"steps {info['step'].tolist()}, truncated {truncated.tolist()}")  # the cap is 3 steps
    envs.close()
