"""Episode logs: what an agent did, replayable by the viewer, safe against crashes and damage.

A log is a directory::

    LOG/telemetry.tlog   every telemetry message the agent published (and more: see below),
                         as framed, CRC-checked codec frames, append-only
    LOG/events.jsonl     one checksummed JSON object per line: actions, poses, events (append-only)
    LOG/summary.json     the final state and the episode record, with its checksum; written
                         atomically at the end

Every record of every file carries a CRC-32 (``zlib.crc32``), so a reader tells a damaged
record from a good one, skips it, and goes on with the next good one.

``telemetry.tlog``: the magic ``b"TIDEELOG2\\n"``, then records of
``sync b"\\x1eREC" | u32 length | u32 crc32(body) | body`` (little-endian) where ``body`` is
``u8 len(kind) | kind (ASCII) | codec frame``. After a damaged record, or garbage, the reader
resyncs: it scans forward for the next sync marker whose length and CRC check out. Logs of
the previous format (magic ``b"TIDEELOG1\\n"``, no sync marker) are still read; there the
reader resyncs on the codec frame's own magic ``b"TIDE"``.

``events.jsonl``: each line is ``<crc32 as 8 lowercase hex digits> TAB <JSON object>``, the
CRC taken over the JSON text's bytes (ASCII: non-ASCII characters are escaped). Greppable as
text; ``cut -f2- events.jsonl`` gives plain JSON lines. In the previous format the lines were
bare JSON, unchecked.

``summary.json``: indented JSON whose ``"crc32"`` entry is the CRC-32, as 8 hex digits, of the
canonical JSON (sorted keys, no spaces, ASCII) of the other entries. A summary whose
checksum is missing (in the current format) or wrong is treated as absent.

Records are appended and flushed one at a time, so a crash can only leave a torn *last*
record. ``LogReader`` never raises on damaged content: it returns every intact record, counts
the damaged stretches it skipped per file (``LogReader.skipped``) and says what it skipped in
one line (``LogReader.corrupt_message``). Nothing in here imports torch.
"""

from __future__ import annotations

import json
import os
import re
import struct
import tempfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tidee.protocol import codec
from tidee.protocol.codec import ProtocolError

MAGIC = b"TIDEELOG2\n"
MAGIC_V1 = b"TIDEELOG1\n"  # no sync marker, events and summary unchecked
SYNC = b"\x1eREC"
_RECORD = struct.Struct("<4sII")  # sync, length, crc32(body)
_RECORD_V1 = struct.Struct("<II")  # length, crc32(body)
SUMMARY_CRC = "crc32"
TLOG_NAME, EVENTS_NAME, SUMMARY_NAME = "telemetry.tlog", "events.jsonl", "summary.json"
_EVENT_LINE = re.compile(rb"([0-9a-f]{8})\t")


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
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; logs and reports are meant to be read
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


def _summary_crc(entries: dict[str, Any]) -> str:
    """The checksum of a summary: CRC-32 of its canonical JSON (so re-indenting keeps it valid)."""
    canonical = json.dumps(entries, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return f"{zlib.crc32(canonical.encode()):08x}"


class LogWriter:
    """Appends telemetry frames and events to a log directory (created if missing)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        # An earlier run's summary must not make this run look finished if it crashes.
        (self.dir / SUMMARY_NAME).unlink(missing_ok=True)
        self._tlog = open(self.dir / TLOG_NAME, "wb")
        self._tlog.write(MAGIC)
        self._tlog.flush()
        self._events = open(self.dir / EVENTS_NAME, "wb")
        self.closed = False

    def message(self, kind: str, msg: Any, encoding: str = "jpeg") -> None:
        """Append one telemetry message (images compressed by ``encoding`` to keep logs small)."""
        frame = codec.encode(msg, encoding)
        kind_b = kind.encode("ascii")
        if not 0 < len(kind_b) < 256:
            raise ValueError(f"kind must be 1..255 ASCII characters, got {kind!r}")
        body = bytes([len(kind_b)]) + kind_b + frame
        self._tlog.write(_RECORD.pack(SYNC, len(body), zlib.crc32(body)) + body)
        self._tlog.flush()

    def event(self, **fields: Any) -> None:
        """Append one line ``crc32hex TAB json`` to ``events.jsonl``."""
        text = json.dumps(fields, default=_json_default).encode("ascii")  # ensure_ascii: always ASCII
        self._events.write(b"%08x\t%s\n" % (zlib.crc32(text), text))
        self._events.flush()

    def finish(self, summary: dict[str, Any]) -> None:
        """Write ``summary.json`` (with its ``crc32`` entry; one already in ``summary`` is
        replaced) atomically and close the streams."""
        plain = _strict(json.loads(json.dumps(summary, default=_json_default)))  # as a reader will see it
        plain.pop(SUMMARY_CRC, None)
        write_json_atomic(self.dir / SUMMARY_NAME, {**plain, SUMMARY_CRC: _summary_crc(plain)})
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


@dataclass
class Damage:
    """What a reader skipped in one file: stretches of bytes that held no intact record."""

    stretches: int = 0
    nbytes: int = 0
    first: str = ""

    def add(self, why: str, nbytes: int) -> None:
        self.stretches += 1
        self.nbytes += nbytes
        self.first = self.first or why

    def describe(self) -> str:
        plural = "" if self.stretches == 1 else "es"
        return (
            f"skipped {self.stretches} damaged stretch{plural} ({self.nbytes} bytes), the first: {self.first}"
        )


class LogReader:
    """Reads a log directory, skipping damaged records (a crashed agent's torn tail, flipped
    bytes, garbage) and counting what it skipped.

    ``skipped``: damaged stretches skipped per file name by the latest read of each file (a
    stretch is a damaged record, a torn tail or a run of garbage); ``truncated``: whether any
    was skipped; ``corrupt_message``: one line saying what, or ``""``. Raises only when the
    directory is not an episode log (no ``telemetry.tlog``, or one with neither the magic nor
    any intact record)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        self.dir = Path(directory)
        path = self.dir / TLOG_NAME
        if not path.is_file():
            raise FileNotFoundError(f"{self.dir} is not an episode log: no {TLOG_NAME} in it")
        self.damage = {name: Damage() for name in (TLOG_NAME, EVENTS_NAME, SUMMARY_NAME)}
        with open(path, "rb") as f:
            self._data = f.read()
        self.version, self._start, self._header_damage = self._format()

    # --- telemetry.tlog ---------------------------------------------------------------------

    def _format(self) -> tuple[int, int, str]:
        """(format version, offset of the first record, what is wrong with the magic or "");
        a damaged magic is resynced past."""
        data = self._data
        if data.startswith(MAGIC):
            return 2, len(MAGIC), ""
        # A flipped "2" reads "1": an old log's first record cannot start with the sync marker.
        if data.startswith(MAGIC_V1) and data[len(MAGIC_V1) : len(MAGIC_V1) + len(SYNC)] != SYNC:
            return 1, len(MAGIC_V1), ""
        if MAGIC.startswith(data):  # torn while the file was being created: empty
            return 2, len(data), f"truncated file header: {len(data)} of {len(MAGIC)} bytes"
        for version in (2, 1):
            if self._resync(0, version) is not None:
                return version, 0, ""  # the damaged magic is the first stretch skipped
        raise ValueError(
            f"{self.dir / TLOG_NAME} is not an episode log: it does not start with "
            f"{MAGIC!r} and holds no intact record"
        )

    def _record_at(self, pos: int, version: int) -> tuple[bytes, int] | str:
        """The body of the record at ``pos`` and the offset after it, or why there is none."""
        data = self._data
        fmt = _RECORD if version == 2 else _RECORD_V1
        if pos + fmt.size > len(data):
            return f"truncated record header at byte {pos}"
        if version == 2:
            sync, length, crc = _RECORD.unpack_from(data, pos)
            if sync != SYNC:
                return f"no record marker at byte {pos}"
        else:
            length, crc = _RECORD_V1.unpack_from(data, pos)
        start = pos + fmt.size
        if start + length > len(data):
            return f"truncated record at byte {pos}: {len(data) - start} of {length} bytes"
        body = data[start : start + length]
        if zlib.crc32(body) != crc:
            return f"CRC mismatch in the record at byte {pos}"
        return body, start + length

    def _candidates(self, pos: int, version: int) -> Iterator[int]:
        """Offsets at or after ``pos`` where a record may start, in increasing order of the
        marker they are found by."""
        data = self._data
        if version == 2:
            p = data.find(SYNC, pos)
            while p >= 0:
                yield p
                p = data.find(SYNC, p + 1)
            return
        # Old format: a body is ``n | kind (n bytes) | codec frame``, so a record starts
        # 9 + n bytes before a codec magic, where the byte before the kind is n.
        q = data.find(codec.MAGIC, pos)
        while q >= 0:
            for n in range(1, 256):
                start = q - n - 1 - _RECORD_V1.size
                if start < pos:
                    break
                if data[q - n - 1] == n:
                    yield start
            q = data.find(codec.MAGIC, q + 1)

    def _resync(self, pos: int, version: int) -> int | None:
        """The offset of the next intact record at or after ``pos``, or None."""
        for p in self._candidates(pos, version):
            if not isinstance(self._record_at(p, version), str):
                return p
        return None

    def records(self) -> Iterator[tuple[str, bytes]]:
        """``(kind, codec frame)`` of every intact record in the order written, undecoded."""
        damage = self.damage[TLOG_NAME] = Damage()
        data, pos, version = self._data, self._start, self.version
        if self._header_damage:
            damage.add(self._header_damage, len(data))
        while pos < len(data):
            found = self._record_at(pos, version)
            if isinstance(found, str):
                nxt = self._resync(pos + 1, version)
                end = len(data) if nxt is None else nxt
                damage.add(found, end - pos)
                pos = end
                continue
            body, pos = found
            n = body[0] if body else 0
            kind = body[1 : 1 + n]
            if not n or len(kind) < n or not kind.isascii():
                damage.add(f"malformed kind in the record ending at byte {pos}", len(body))
                continue
            yield kind.decode("ascii"), body[1 + n :]

    def messages(self) -> Iterator[tuple[str, Any]]:
        """``(kind, message)`` of every intact record in the order written; damaged ones are
        skipped (``skipped``, ``corrupt_message``)."""
        for kind, frame in self.records():
            try:
                msg = codec.decode(frame)
            except ProtocolError as e:  # intact bytes a codec of this version cannot read
                self.damage[TLOG_NAME].add(f"undecodable {kind!r} record: {e}", len(frame))
                continue
            yield kind, msg

    # --- events.jsonl and summary.json -------------------------------------------------------

    def events(self) -> list[dict[str, Any]]:
        """Every intact line of ``events.jsonl``, in order."""
        damage = self.damage[EVENTS_NAME] = Damage()
        path = self.dir / EVENTS_NAME
        out: list[dict[str, Any]] = []
        if not path.is_file():
            return out
        parse = _checked_event if self.version >= 2 else _unchecked_event
        bad_from: int | None = None  # first line of the current run of damaged lines
        bad_bytes = 0
        lines = path.read_bytes().split(b"\n")
        if lines and not lines[-1]:
            lines.pop()  # the newline ending the last line
        for number, line in enumerate(lines, 1):
            skipped, event = _salvage(line, parse)
            if skipped:
                bad_from = bad_from or number
                bad_bytes += skipped
            if event is not None:
                if bad_from is not None:
                    damage.add(f"line {bad_from} is damaged", bad_bytes)
                    bad_from, bad_bytes = None, 0
                out.append(event)
        if bad_from is not None:
            damage.add(f"line {bad_from} is damaged", bad_bytes)
        return out

    def summary(self) -> dict[str, Any] | None:
        """``summary.json`` without its checksum, or None when the episode did not finish
        (crash, still running) or the file is damaged (then ``skipped`` counts it)."""
        damage = self.damage[SUMMARY_NAME] = Damage()
        path = self.dir / SUMMARY_NAME
        if not path.is_file():
            return None
        raw = path.read_bytes()
        try:
            entries = json.loads(raw.decode("utf-8"))
        except ValueError:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
            damage.add("not valid JSON; treated as absent", len(raw))
            return None
        if not isinstance(entries, dict):
            damage.add("not a JSON object; treated as absent", len(raw))
            return None
        crc = entries.pop(SUMMARY_CRC, None)
        if crc is None and self.version < 2:
            return entries  # an old log: summaries were unchecked
        if crc != _summary_crc(entries):
            damage.add("checksum missing or wrong; treated as absent", len(raw))
            return None
        return entries

    # --- what was skipped ----------------------------------------------------------------------

    @property
    def skipped(self) -> dict[str, int]:
        return {name: d.stretches for name, d in self.damage.items()}

    @property
    def truncated(self) -> bool:
        return any(d.stretches for d in self.damage.values())

    @property
    def corrupt_message(self) -> str:
        return "; ".join(f"{name}: {d.describe()}" for name, d in self.damage.items() if d.stretches)


def _checked_event(line: bytes) -> dict[str, Any] | None:
    """The event of a ``crc32hex TAB json`` line, or None when the line is not one intact."""
    m = _EVENT_LINE.match(line)
    if m is None:
        return None
    text = line[m.end() :]
    if zlib.crc32(text) != int(m.group(1), 16):
        return None
    return _unchecked_event(text)


def _unchecked_event(text: bytes) -> dict[str, Any] | None:
    try:
        event = json.loads(text.decode("utf-8"))
    except ValueError:
        return None
    return event if isinstance(event, dict) else None


def _salvage(
    line: bytes, parse: Callable[[bytes], dict[str, Any] | None]
) -> tuple[int, dict[str, Any] | None]:
    """(bytes skipped, event) for one line: the whole line if it is intact, else the intact
    record that starts after damage within it (a lost newline merges two lines; garbage may
    precede a record), else nothing."""
    event = parse(line)
    if event is not None:
        return 0, event
    if parse is _checked_event:
        for m in _EVENT_LINE.finditer(line, 1):
            event = parse(line[m.start() :])
            if event is not None:
                return m.start(), event
    return len(line) + 1, None
