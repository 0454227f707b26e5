"""A stand-in for ``tidee.server.episode.Episode``: same API, no physics, instant.

Observations are deterministic functions of (spec.seed, step, action history), so the
gym env checker's determinism checks hold, and tests can tell sessions apart.
"""

from __future__ import annotations

import zlib

import numpy as np

from tidee.protocol.messages import Action, ActionError, ActionName, EpisodeSpec, GroundTruth, Observation


class FakeEpisode:
    """Moves change ``agent_pose``; ``PickupObject`` at x < 0.5 fails; ``Done`` ends it.

    ``fail_on``: an action name whose step raises ``RuntimeError`` (to test that the
    server survives an exception inside an episode).
    """

    def __init__(self, renderer: str = "auto", fail_on: str | None = None) -> None:
        self.renderer = renderer
        self.fail_on = fail_on
        self.spec: EpisodeSpec | None = None
        self.session = ""
        self.steps = 0
        self.done = False
        self.history = 0
        self.pose = [0.0, 0.0, 0.0, 0.0]
        self.closed = False
        self.phase: str | None = None  # a rearrangement's: walkthrough, then unshuffle

    def reset(self, spec: EpisodeSpec, session: str = "local", ground_truth: bool = False) -> Observation:
        self.spec, self.session = spec, session
        self.steps, self.done, self.history = 0, False, spec.seed
        self.pose = [0.0, 0.0, 0.0, 0.0]
        self.phase = None if spec.rearrange_index is None else "walkthrough"
        return self._observe(None, True, None, "", ground_truth)

    def step(self, action: Action, ground_truth: bool = False) -> Observation:
        if self.spec is None:
            raise RuntimeError("step() before reset()")
        name = ActionName(action.name)
        if name.value == self.fail_on:
            raise RuntimeError(f"fake failure on {name.value}")
        if self.done:
            return self._observe(
                name.value, False, ActionError.episode_over, "the episode is over", ground_truth
            )
        self.steps += 1
        self.history = zlib.crc32(f"{self.history}:{name.value}:{action.x}:{action.y}".encode())
        ok, err = True, None
        if name == ActionName.MoveAhead:
            self.pose[0] += 0.25
        elif name == ActionName.RotateLeft:
            self.pose[2] = (self.pose[2] + 90.0 + 180) % 360 - 180
        elif name == ActionName.PickupObject and action.x is not None and action.x < 0.5:
            ok, err = False, ActionError.nothing_there
        if name == ActionName.Done or self.steps >= self._cap():
            self.done = True
        return self._observe(name.value, ok, err, "" if ok else "fake: nothing at that pixel", ground_truth)

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation:
        """A rearrangement's second phase: the same room (the fake has no shuffle), steps from 0."""
        if self.spec is None:
            raise RuntimeError("begin_unshuffle() before reset()")
        if self.phase is None:
            raise ValueError("this is not a rearrangement episode: reset with spec.rearrange_index first")
        if self.phase != "walkthrough":
            raise ValueError("the unshuffle phase has already begun")
        self.steps, self.done, self.phase = 0, False, "unshuffle"
        self.pose = [0.0, 0.0, 0.0, 0.0]
        return self._observe(None, True, None, "", ground_truth)

    def state(self) -> dict:
        if self.spec is None:
            raise RuntimeError("state() before reset()")
        return {
            "room_type": self.spec.room_type,
            "seed": self.spec.seed,
            "steps": self.steps,
            "objects": [{"id": "Mug_0", "type": "Mug", "position": [1.0, 2.0, 0.8]}],
        }

    def close(self) -> None:
        self.closed = True

    def _cap(self) -> int:
        assert self.spec is not None
        return self.spec.walkthrough_steps if self.phase == "walkthrough" else self.spec.max_steps

    def _observe(
        self, last: str | None, ok: bool, err: ActionError | None, msg: str, ground_truth: bool
    ) -> Observation:
        assert self.spec is not None
        r = self.spec.resolution
        rng = np.random.default_rng(self.history)
        gt = None
        if ground_truth:
            gt = GroundTruth(
                instance_seg=rng.integers(-1, 3, (r, r), dtype=np.int32),
                objects=[{"id": "Mug_0", "type": "Mug", "moved": False}],
            )
        return Observation(
            session=self.session,
            step=self.steps,
            rgb=rng.integers(0, 256, (r, r, 3), dtype=np.uint8),
            depth=rng.uniform(0.1, 5.0, (r, r)).astype(np.float32),
            camera_pose=np.eye(4),
            agent_pose=(self.pose[0], self.pose[1], self.pose[2], self.pose[3]),
            intrinsics=np.array([[r / 2, 0, (r - 1) / 2], [0, r / 2, (r - 1) / 2], [0, 0, 1.0]]),
            last_action=last,
            success=ok,
            error=err.value if err else None,
            message=msg,
            done=self.done,
            steps_left=max(self._cap() - self.steps, 0),
            ground_truth=gt,
            phase=self.phase,
        )
