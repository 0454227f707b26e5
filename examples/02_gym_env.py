"""A tidee episode as a Gymnasium environment: `gymnasium.make("tidee/Tidy-v0")`.

``import tidee`` registers the environment. With ``transport="inproc"`` the simulator runs
in this process (no server); ``transport="zenoh"`` with ``transport_kwargs={"endpoint": ...}``
talks to a `tidee server` instead. Actions are ``{"action": index into ACTIONS, "point":
normalised pixel (x, y)}``; the reward is always 0 (tidying is scored after the episode).

Run:  .venv/bin/python examples/02_gym_env.py
"""

from __future__ import annotations

import gymnasium
import numpy as np

import tidee  # noqa: F401  (registers tidee/Tidy-v0)
from tidee.protocol.gym_env import ACTIONS
from tidee.protocol.messages import EpisodeSpec

env = gymnasium.make(
    "tidee/Tidy-v0",
    spec=EpisodeSpec(room_type="Kitchen", mess_index=0, max_steps=20),
    transport="inproc",
    transport_kwargs={"renderer": "tiny"},
)
print("action space:", env.action_space)
print("observation space:", env.observation_space)

obs, info = env.reset(seed=200)  # room seed 200: a test room
env.action_space.seed(0)  # the random actions below are reproducible too
print(f"reset: rgb {obs['rgb'].shape}, depth {obs['depth'].shape}, pose {obs['pose']}")
# Random actions, all but Done (which would end the episode at once).
not_done = np.array([a.value != "Done" for a in ACTIONS], np.int8)
for _ in range(8):
    action = env.action_space.sample(mask={"action": not_done, "point": None})
    obs, reward, terminated, truncated, info = env.step(action)
    name = ACTIONS[action["action"]].value
    outcome = "ok" if info["success"] else f"failed: {info['error']}"
    print(f"step {info['step']}: {name:<12} reward {reward} {outcome:<22} pose {obs['pose'].round(2)}")
    if terminated or truncated:
        print("episode over:", "Done called" if terminated else "step cap")
        break
env.close()
