"""A rearrangement's two phases as the viewer tells them apart (pure functions, no viser).

An episode whose ``AgentStatus.episode`` has a ``rearrange_index`` is a 2-phase
rearrangement: its status ``phase`` is ``walkthrough`` while the agent maps the goal room,
and anything else once the unshuffle phase began. The agent's step count starts again at 0
in the unshuffle phase, so a step going back is a new episode only when it is not that switch.
"""

from __future__ import annotations

from typing import Any

WALKTHROUGH, UNSHUFFLE = "walkthrough", "unshuffle"


def rearrangement_phase(status: Any) -> str | None:
    """``walkthrough`` or ``unshuffle`` for a rearrangement's ``AgentStatus``; None for a tidying episode."""
    episode = getattr(status, "episode", None) or {}
    if episode.get("rearrange_index") is None:
        return None
    return WALKTHROUGH if status.phase == WALKTHROUGH else UNSHUFFLE


def unshuffle_began(before: Any, now: Any) -> bool:
    """True when status ``now`` is the unshuffle phase following ``before``'s walkthrough of
    the same episode (where the step count starts again)."""
    return (
        rearrangement_phase(before) == WALKTHROUGH
        and rearrangement_phase(now) == UNSHUFFLE
        and before.episode == now.episode
    )
