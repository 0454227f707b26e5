"""How an agent reaches an episode: over Zenoh, or in this process.

Both transports have the same five methods (``SimTransport``), so agent code, the gym
env and evaluation never care which one they hold. The in-process transport imports
``tidee.server`` (and so pybullet) only when it builds an episode itself.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from tidee.protocol.client import SimClient
from tidee.protocol.messages import Action, EpisodeSpec, Observation


@runtime_checkable
class SimTransport(Protocol):
    def reset(self, spec: EpisodeSpec, ground_truth: bool = False) -> Observation: ...

    def step(self, action: Action, ground_truth: bool = False) -> Observation: ...

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation: ...

    def state(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class EpisodeLike(Protocol):
    """What the server and the in-process transport need of an episode
    (``tidee.server.episode.Episode``; tests use a fake)."""

    def reset(self, spec: EpisodeSpec, session: str = ..., ground_truth: bool = False) -> Observation: ...

    def step(self, action: Action, ground_truth: bool = False) -> Observation: ...

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation: ...

    def state(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


# SimClient already is a SimTransport over Zenoh; the name says what it is used as.
ZenohTransport = SimClient


class InProcessTransport:
    """Calls an episode directly: no serialisation, no sockets (tests, batch evaluation)."""

    def __init__(
        self, episode: EpisodeLike | None = None, renderer: str = "auto", session: str = "local"
    ) -> None:
        if episode is None:
            from tidee.server.episode import Episode  # pybullet: only when needed

            episode = Episode(renderer=renderer)
        self.episode: EpisodeLike | None = episode
        self.session_id = session

    def reset(self, spec: EpisodeSpec, ground_truth: bool = False) -> Observation:
        return self._episode().reset(spec, session=self.session_id, ground_truth=ground_truth)

    def step(self, action: Action, ground_truth: bool = False) -> Observation:
        return self._episode().step(action, ground_truth=ground_truth)

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation:
        """A rearrangement: end the walkthrough, start the unshuffle phase."""
        return self._episode().begin_unshuffle(ground_truth=ground_truth)

    def state(self) -> dict[str, Any]:
        return self._episode().state()

    def close(self) -> None:
        episode, self.episode = self.episode, None
        if episode is not None:
            episode.close()

    def __enter__(self) -> InProcessTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _episode(self) -> EpisodeLike:
        if self.episode is None:
            raise RuntimeError("the transport is closed")
        return self.episode


def send_step(
    transport: SimTransport, action: Action, ground_truth: bool = False
) -> Callable[[], Observation]:
    """Start a step; the returned function waits for its observation. Over Zenoh the request
    leaves at once, so the agent can spend the server's time on its own work (telemetry, logs);
    in process the step runs when its observation is asked for."""
    send = getattr(transport, "send_step", None)
    if send is not None:
        return send(action, ground_truth)
    return functools.partial(transport.step, action, ground_truth=ground_truth)


def make_transport(kind: str, **kwargs: Any) -> SimTransport:
    """``"inproc"``: ``InProcessTransport(**kwargs)``; ``"zenoh"``: ``SimClient(**kwargs)``."""
    if kind == "inproc":
        return InProcessTransport(**kwargs)
    if kind == "zenoh":
        return SimClient(**kwargs)
    raise ValueError(f"transport must be 'inproc' or 'zenoh', got {kind!r}")
