"""Replay of a saved episode log: the latest message of each kind at or before a step.

The log (``protocol/episode_log.py``) is read once. Raw arrays of maps, memory and search
messages stay zero-copy views of the file's bytes; frames, whose images the log stores as
JPEG, are kept encoded and decoded only when shown, so memory stays near the log's size.
"""

from __future__ import annotations

import bisect
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tidee.protocol import codec
from tidee.protocol.episode_log import LogReader
from tidee.protocol.messages import AgentFrame, AgentStatus

REPLAYED_KINDS = ("status", "frame", "maps", "memory", "search")


@dataclass
class _Track:
    """One kind's messages in step order (a log is written in step order; ties keep the last)."""

    steps: list[int] = field(default_factory=list)
    items: list[Any] = field(default_factory=list)     # messages, or encoded frames (bytes)

    def add(self, step: int, item: Any) -> None:
        if self.steps and step < self.steps[-1]:
            # an out-of-order record (a new episode in the same log): keep the order by step
            at = bisect.bisect_right(self.steps, step)
            self.steps.insert(at, step)
            self.items.insert(at, item)
        else:
            self.steps.append(step)
            self.items.append(item)

    def index_at(self, step: int) -> int | None:
        i = bisect.bisect_right(self.steps, step) - 1
        return i if i >= 0 else None


class ReplayLog:
    """All telemetry of one log directory, indexed by step."""

    def __init__(self, directory: str | os.PathLike) -> None:
        reader = LogReader(directory)
        self.directory = str(directory)
        self._tracks: dict[str, _Track] = {kind: _Track() for kind in REPLAYED_KINDS}
        self.session: str | None = None
        count = 0
        for kind, msg in reader.messages():
            if kind not in self._tracks or not hasattr(msg, "step"):
                continue  # acks and unknown kinds: nothing to show at a step
            item = codec.encode(msg, "jpeg") if isinstance(msg, AgentFrame) else msg
            self._tracks[kind].add(int(msg.step), item)
            self.session = self.session or getattr(msg, "session", None)
            count += 1
        if count == 0:
            why = f" ({reader.corrupt_message})" if reader.truncated else ""
            raise ValueError(f"{self.directory}: the log holds no telemetry to replay{why}")
        self.messages = count
        self.truncated, self.corrupt_message = reader.truncated, reader.corrupt_message
        self.summary = reader.summary()
        all_steps = [s for t in self._tracks.values() for s in t.steps[:1] + t.steps[-1:]]
        self.first_step, self.last_step = min(all_steps), max(all_steps)
        status = self._tracks["status"]
        self._history = np.array([(m.step, m.objects_fixed, m.oop_found) for m in status.items],
                                 dtype=np.float64).reshape(-1, 3)

    def at(self, step: int) -> dict[str, Any]:
        """The latest message of each kind at or before ``step`` (kinds with none are absent)."""
        out: dict[str, Any] = {}
        for kind, track in self._tracks.items():
            i = track.index_at(step)
            if i is None:
                continue
            item = track.items[i]
            out[kind] = codec.decode(item) if isinstance(item, bytes) else item
        return out

    def index_at(self, kind: str, step: int) -> int | None:
        """Which message of ``kind`` is current at ``step`` (to skip redrawing an unchanged one)."""
        return self._tracks[kind].index_at(step)

    def history(self, step: int, max_points: int = 400) -> np.ndarray:
        """``K x 3`` (step, objects fixed, OOP found) up to ``step``, at most ``max_points`` rows."""
        rows = self._history[self._history[:, 0] <= step] if len(self._history) else self._history
        if len(rows) > max_points:
            rows = rows[np.linspace(0, len(rows) - 1, max_points).astype(int)]
        return rows

    def count(self, kind: str) -> int:
        return len(self._tracks[kind].steps)

    def steps(self, kind: str) -> list[int]:
        """The steps at which the log holds a message of ``kind``."""
        return list(self._tracks[kind].steps)

    def latest_status(self, step: int) -> AgentStatus | None:
        i = self._tracks["status"].index_at(step)
        return None if i is None else self._tracks["status"].items[i]
