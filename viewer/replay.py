"""Replay of a saved episode log: the latest message of each kind at or before a step.

The log (``protocol/episode_log.py``) is read once. Raw arrays of maps, memory and search
messages stay zero-copy views of the file's bytes; frames, whose images the log stores as
JPEG, are kept encoded and decoded only when shown, so memory stays near the log's size.

A rearrangement's log holds two phases whose step counts each start at 0: the replay's step
axis puts the unshuffle phase after the walkthrough (its step ``k`` is replay step
``walkthrough's last + 1 + k``); the messages themselves keep the agent's own step.
"""

from __future__ import annotations

import bisect
import dataclasses
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tidee.protocol import codec
from tidee.protocol.episode_log import LogReader
from tidee.protocol.messages import AgentFrame, AgentStatus, EpisodeSummary
from tidee.viewer.phases import unshuffle_began

REPLAYED_KINDS = ("status", "frame", "maps", "memory", "walkthrough", "search", "summary")


@dataclass
class _Track:
    """One kind's messages in step order (a log is written in step order; ties keep the last)."""

    steps: list[int] = field(default_factory=list)
    items: list[Any] = field(default_factory=list)  # messages, or encoded frames (bytes)

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
        count, last = 0, 0
        self.unshuffle_step: int | None = None  # a rearrangement: the replay step its unshuffle begins at
        offset, status = 0, None
        for kind, msg in reader.messages():
            if isinstance(msg, AgentStatus):
                if status is not None and msg.step < status.step:
                    began = unshuffle_began(status, msg)
                    offset = last + 1 if began else 0  # else: a new episode in the same log
                    self.unshuffle_step = offset if began else self.unshuffle_step
                status = msg
            if isinstance(msg, EpisodeSummary):
                step = last  # the episode's end: shown from the last step logged before it
            elif kind in self._tracks and hasattr(msg, "step"):
                step = offset + int(msg.step)
            else:
                continue  # acks and unknown kinds: nothing to show at a step
            item = codec.encode(msg, "jpeg") if isinstance(msg, AgentFrame) else msg
            self._tracks[kind].add(step, item)
            self.session = self.session or getattr(msg, "session", None)
            last = max(last, step)
            count += 1
        if count == 0:
            why = f" ({reader.corrupt_message})" if reader.truncated else ""
            raise ValueError(f"{self.directory}: the log holds no telemetry to replay{why}")
        self.messages = count
        self.summary = reader.summary()  # before the damage report, which counts a damaged summary
        self.truncated, self.corrupt_message = reader.truncated, reader.corrupt_message
        all_steps = [s for t in self._tracks.values() for s in t.steps[:1] + t.steps[-1:]]
        self.first_step, self.last_step = min(all_steps), max(all_steps)
        if not self._tracks["summary"].steps and isinstance(self.summary, dict):
            logged = episode_summary(self.summary.get("summary"))  # a log whose tlog lacks it
            if logged is not None:
                self._tracks["summary"].add(self.last_step, logged)
        statuses = self._tracks["status"]
        self._history = np.array(
            [(s, m.objects_fixed, m.oop_found) for s, m in zip(statuses.steps, statuses.items)],
            dtype=np.float64,
        ).reshape(-1, 3)

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

    def frames(self, first: int, last: int, max_frames: int | None = None) -> Iterator[AgentFrame]:
        """The logged frames with index ``first`` to ``last`` (inclusive, in step order),
        decoded; at most ``max_frames`` of them, evenly spread, the last always among them."""
        idx = np.arange(max(first, 0), min(last, len(self._tracks["frame"].items) - 1) + 1)
        if max_frames is not None and len(idx) > max_frames:
            idx = idx[np.unique(np.linspace(len(idx) - 1, 0, max_frames).round().astype(int))]
        for i in idx:
            yield codec.decode(self._tracks["frame"].items[int(i)])

    def step_of(self, kind: str, index: int) -> int:
        """The replay step of message ``index`` of ``kind``."""
        return self._tracks[kind].steps[index]

    def count(self, kind: str) -> int:
        return len(self._tracks[kind].steps)

    def steps(self, kind: str) -> list[int]:
        """The steps at which the log holds a message of ``kind``."""
        return list(self._tracks[kind].steps)

    def latest_status(self, step: int) -> AgentStatus | None:
        i = self._tracks["status"].index_at(step)
        return None if i is None else self._tracks["status"].items[i]


def episode_summary(record: Any) -> EpisodeSummary | None:
    """An ``EpisodeSummary`` from ``summary.json``'s ``summary`` entry (None when absent or not one)."""
    if not isinstance(record, dict):
        return None
    names = {f.name for f in dataclasses.fields(EpisodeSummary)}
    try:
        return EpisodeSummary(**{k: v for k, v in record.items() if k in names})
    except TypeError:  # a required field is missing: not a summary this viewer knows
        return None
