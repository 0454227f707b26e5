"""``tidee/Tidy-v0``: a tidee episode as a Gymnasium environment.

Actions: ``{"action": Discrete(13), "point": Box(0, 1, (2,))}``: the action index is into
``ACTIONS`` (the order of ``ActionName``); ``point`` is the normalised pixel (x, y) and
only matters for the pixel actions (pick, put, open, close).
Observations: ``{"rgb": HxWx3 uint8, "depth": HxW float32 metres, "pose": (x, y, yaw_deg,
pitch_deg) float32 in the start frame}``; everything else of the ``Observation``
(success, error, held object, camera pose, intrinsics, ground truth) is in ``info``.
Reward is always 0: tidying is scored at the end by evaluation, not per step.
``terminated`` when the agent calls Done; ``truncated`` when the step cap ends the episode.
``reset(seed=s)`` plays room seed ``s``; without a seed, the env's RNG draws one.

``transport``: ``"inproc"`` (a simulator in this process), ``"zenoh"`` (a session on a running
server; ``transport_kwargs`` go to ``SimClient``), a ``SimTransport``, or a function that makes
one. Each env holds its own simulator session, so vector environments work as Gymnasium makes
them: ``gymnasium.make_vec("tidee/Tidy-v0", num_envs=N, vectorization_mode="sync" | "async")``
(one simulator or Zenoh session per sub-env; ``vector_kwargs={"context": "spawn"}`` for async:
a forked PyBullet or Zenoh is unsafe). ``reset(seed=s)`` on the vector env plays rooms s, s+1, ...,
and a finished sub-env resets on its next step (Gymnasium's default autoreset). A transport
*instance* can serve one env at a time: give a function instead for several (sub-envs of one
``make_vec`` call share its keyword arguments).

``tidee/Rearrange-v0`` (``RearrangeEnv``): a 2-phase rearrangement. ``reset`` starts the
walkthrough of the goal state (the spec's ``rearrange_index``, default 0); ``Done`` there,
or the walkthrough's step cap, switches to the unshuffle phase (the shuffled room, the agent
back at its start pose; not terminated); ``Done`` in the unshuffle phase terminates. The
observation gains ``phase`` (0 walkthrough, 1 unshuffle); interactions during the
walkthrough fail with error ``walkthrough``.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from tidee.protocol.messages import (
    PIXEL_ACTIONS,
    REARRANGE_PHASES,
    Action,
    ActionName,
    EpisodeSpec,
    Observation,
)
from tidee.protocol.transport import SimTransport, make_transport

ACTIONS: tuple[ActionName, ...] = tuple(ActionName)
_MAX_SEED = 2**31 - 1
# Generous finite bounds (rooms are under 10 m; the renderer's far plane is 20 m).
MAX_DEPTH_M = 100.0
POSE_LOW = np.array([-100.0, -100.0, -180.0, -90.0], np.float32)
POSE_HIGH = -POSE_LOW
# Transports held by an open env: an instance given to several (make_vec passes one set of keyword
# arguments to every sub-env) would interleave their episodes, so the second is refused.
_HELD: weakref.WeakSet[Any] = weakref.WeakSet()


class TidyEnv(gym.Env[dict[str, np.ndarray], dict[str, Any]]):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        spec: EpisodeSpec | None = None,
        transport: str | SimTransport | Callable[[], SimTransport] = "inproc",
        transport_kwargs: dict[str, Any] | None = None,
        ground_truth: bool = False,
        render_mode: str | None = None,
    ) -> None:
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        self.episode_spec = spec or EpisodeSpec()
        self.ground_truth = ground_truth
        self.render_mode = render_mode
        self.transport: SimTransport = _own_transport(transport, transport_kwargs)
        r = self.episode_spec.resolution
        self.action_space = spaces.Dict(
            {
                "action": spaces.Discrete(len(ACTIONS)),
                "point": spaces.Box(0.0, 1.0, (2,), np.float32),
            }
        )
        # gymnasium types spaces.Dict as Space[dict[str, Space]] (its subspaces), not as the
        # space of the dicts of samples it holds.
        self.observation_space = spaces.Dict(  # type: ignore[assignment]
            {
                "rgb": spaces.Box(0, 255, (r, r, 3), np.uint8),
                "depth": spaces.Box(0.0, MAX_DEPTH_M, (r, r), np.float32),
                "pose": spaces.Box(POSE_LOW, POSE_HIGH, (4,), np.float32),
            }
        )
        self._last: Observation | None = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``options``: EpisodeSpec fields to change for this episode (not ``resolution``)."""
        super().reset(seed=seed)
        changes = dict(options or {})
        if changes.get("resolution", self.episode_spec.resolution) != self.episode_spec.resolution:
            raise ValueError("resolution fixes the observation space; make a new env to change it")
        room_seed = seed if seed is not None else int(self.np_random.integers(_MAX_SEED))
        spec = dataclasses.replace(self.episode_spec, **{"seed": room_seed, **changes})
        self._last = self.transport.reset(spec, ground_truth=self.ground_truth)
        return self._observation(self._last), self._info(self._last)

    def step(self, action: dict[str, Any]) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        self._last = obs = self.transport.step(to_action(action), ground_truth=self.ground_truth)
        terminated = obs.done and obs.last_action == ActionName.Done.value
        return self._observation(obs), 0.0, terminated, obs.done and not terminated, self._info(obs)

    def render(self) -> np.ndarray | None:
        if self.render_mode == "rgb_array" and self._last is not None:
            return self._last.rgb
        return None

    def close(self) -> None:
        _HELD.discard(self.transport)
        self.transport.close()
        super().close()

    @staticmethod
    def _observation(obs: Observation) -> dict[str, np.ndarray]:
        return {"rgb": obs.rgb, "depth": obs.depth, "pose": np.asarray(obs.agent_pose, np.float32)}

    @staticmethod
    def _info(obs: Observation) -> dict[str, Any]:
        info = {
            f.name: getattr(obs, f.name)
            for f in dataclasses.fields(obs)
            if f.name not in ("rgb", "depth", "agent_pose", "ground_truth")
        }
        if obs.ground_truth is not None:
            info["ground_truth"] = obs.ground_truth
        return info


class RearrangeEnv(TidyEnv):
    """``tidee/Rearrange-v0``: the walkthrough, then the unshuffle phase (module docstring)."""

    def __init__(self, spec: EpisodeSpec | None = None, **kwargs: Any) -> None:
        spec = spec or EpisodeSpec()
        if spec.rearrange_index is None:
            spec = dataclasses.replace(spec, rearrange_index=0)
        super().__init__(spec, **kwargs)
        self.observation_space = spaces.Dict(  # type: ignore[assignment]
            {**self.observation_space.spaces, "phase": spaces.Discrete(len(REARRANGE_PHASES))}  # type: ignore[attr-defined]
        )

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``options``: EpisodeSpec fields to change (``rearrange_index`` picks the configuration)."""
        options = dict(options or {})
        if options.get("rearrange_index", 0) is None:
            raise ValueError("rearrange_index must be a configuration index, not None")
        return super().reset(seed=seed, options=options)

    def step(self, action: dict[str, Any]) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        assert self._last is not None
        if self._last.phase == "walkthrough" and (terminated or truncated):
            self._last = first = self.transport.begin_unshuffle(ground_truth=self.ground_truth)
            return self._observation(first), 0.0, False, False, self._info(first)
        return obs, reward, terminated, truncated, info

    @staticmethod
    def _observation(obs: Observation) -> dict[str, np.ndarray]:
        out = TidyEnv._observation(obs)
        out["phase"] = np.int64(REARRANGE_PHASES.index(obs.phase or "unshuffle"))  # type: ignore[assignment]
        return out


def _own_transport(
    transport: str | SimTransport | Callable[[], SimTransport], kwargs: dict[str, Any] | None
) -> SimTransport:
    """The env's own transport: made from a name or a function, or an instance no open env holds."""
    if isinstance(transport, str):
        made = make_transport(transport, **(kwargs or {}))
    elif isinstance(transport, SimTransport):
        if transport in _HELD:
            raise ValueError(
                "this transport already serves another open env (make_vec gives every sub-env the "
                "same arguments): pass transport as a function that makes one, or a name"
            )
        made = transport
    elif callable(transport):
        made = transport()
    else:
        raise TypeError(
            f"transport must be a name, a SimTransport or a function, got {type(transport).__name__}"
        )
    _HELD.add(made)
    return made


def to_action(action: dict[str, Any]) -> Action:
    """A gym action (``{"action": index, "point": (x, y)}``) as a protocol ``Action``."""
    name = ACTIONS[int(action["action"])]
    if name in PIXEL_ACTIONS:
        x, y = np.clip(np.asarray(action["point"], np.float64), 0.0, 1.0)
        return Action(name, float(x), float(y))
    return Action(name)
