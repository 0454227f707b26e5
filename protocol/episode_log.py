"""Episode logs: what an agent did, replayable by the viewer, safe against crashes.

A log is a directory::

    LOG/telemetry.tlog   every telemetry message the agent published (and more: see below),
                         as length-prefixed, CRC-checked codec frames, append-only
    LOG/events.jsonl     one JSON object per line: actions, poses, events (append-only)
    LOG/summary.json     the final state and the episode record; written atomically at the end

``telemetry.tlog`` layout: the magic ``b"TIDEELOG1\\n"``, then records of
``u32 length | u32 crc32(body) | body`` (little-endian) where ``body`` is
``u8 len(kind) | kind (ASCII) | codec frame``. Records are appended and flushed one at a
time, so a crash can only leave a truncated *last* record; the reader stops there and
reports it (``LogReader.truncated``) instead of failing. Nothing in here imports torch.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tidee.protocol import codec
from tidee.protocol.codec import ProtocolError

MAGIC = b"TIDEELOG1\n"
_RECORD = struct.Struct("<II")
TLOG_NAME, EVENTS_NAME, SUMMARY_NAME = "telemetry.tlog", "events.jsonl", "summary.json"


def write_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``:
    readers see the old file or the new one, never half of it. The file is world-readable."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)                   # mkstemp makes 0600; logs and reports are meant to be read
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """``write_atomic`` of ``data`` as strict, indented JSON (numpy values become plain
    numbers, NaN becomes null)."""
    write_atomic(path, (json.dumps(_strict(data), indent=1, default=_json_default) + "\n").encode())


def _strict(x: Any) -> Any:
    if isinstance(x, float) and x != x:
        return None
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    return x


def _json_default(x: Any) -> Any:
    if hasattr(x, "tolist"):
        return x.tolist()
    if hasattr(x, "item"):
        return x.item()
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


class LogWriter:
    """Appends telemetry frames and events to a log directory (created if missing)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        # An earlier run's summary must not make this run look finished if it crashes.
        (self.dir / SUMMARY_NAME).unlink(missing_ok=True)
        self._tlog = open(self.dir / TLOG_NAME, "wb")
        self._tlog.write(MAGIC)
        self._events = open(self.dir / EVENTS_NAME, "w")
        self.closed = False

    def message(self, kind: str, msg: Any, encoding: str = "jpeg") -> None:
        """Append one telemetry message (images compressed by ``encoding`` to keep logs small)."""
        frame = codec.encode(msg, encoding)
        kind_b = kind.encode("ascii")
        if not 0 < len(kind_b) < 256:
            raise ValueError(f"kind must be 1..255 ASCII characters, got {kind!r}")
        body = bytes([len(kind_b)]) + kind_b + frame
        self._tlog.write(_RECORD.pack(len(body), zlib.crc32(body)) + body)
        self._tlog.flush()

    def event(self, **fields: Any) -> None:
        self._events.write(json.dumps(fields, default=_json_default) + "\n")
        self._events.flush()

    def finish(self, summary: dict[str, Any]) -> None:
        """Write ``summary.json`` atomically and close the streams."""
        write_json_atomic(self.dir / SUMMARY_NAME, summary)
        self.close()

    def close(self) -> None:
        if not self.closed:
            self._tlog.close()
            self._events.close()
            self.closed = True

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LogReader:
    """Reads a log directory; tolerant of a truncated last record (a crashed agent)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        self.dir = Path(directory)
        path = self.dir / TLOG_NAME
        if not path.is_file():
            raise FileNotFoundError(f"{self.dir} is not an episode log: no {TLOG_NAME} in it")
        self.truncated = False
        self.corrupt_message = ""
        with open(path, "rb") as f:
            self._data = f.read()
        if not self._data.startswith(MAGIC):
            raise ValueError(f"{path} does not start with the episode-log magic {MAGIC!r}")

    def messages(self) -> Iterator[tuple[str, Any]]:
        """``(kind, message)`` in the order written; stops at the first damaged record."""
        data, pos = self._data, len(MAGIC)
        while pos < len(data):
            if pos + _RECORD.size > len(data):
                self._stop(f"truncated record header at byte {pos}")
                return
            length, crc = _RECORD.unpack_from(data, pos)
            body = data[pos + _RECORD.size: pos + _RECORD.size + length]
            if len(body) < length:
                self._stop(f"truncated record at byte {pos}: {len(body)} of {length} bytes")
                return
            if zlib.crc32(body) != crc:
                self._stop(f"CRC mismatch in the record at byte {pos}")
                return
            n = body[0]
            kind = body[1:1 + n].decode("ascii", "replace")
            try:
                msg = codec.decode(body[1 + n:])
            except ProtocolError as e:
                self._stop(f"undecodable record at byte {pos}: {e}")
                return
            yield kind, msg
            pos += _RECORD.size + length

    def _stop(self, why: str) -> None:
        self.truncated, self.corrupt_message = True, why

    def events(self) -> list[dict[str, Any]]:
        """Every complete line of ``events.jsonl`` (a torn last line is skipped)."""
        path = self.dir / EVENTS_NAME
        out: list[dict[str, Any]] = []
        if path.is_file():
            for line in path.read_text().splitlines():
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    self._stop(f"torn line in {EVENTS_NAME}")
                    break
        return out

    def summary(self) -> dict[str, Any] | None:
        """``summary.json``, or None when the episode did not finish (crash, still running)."""
        path = self.dir / SUMMARY_NAME
        return json.loads(path.read_text()) if path.is_file() else None
