"""Episode logs under damage: every record checksummed, readers that never raise, skip what is
damaged, resync after it and count it.

The fuzz test damages each file of a small real log (flipped bytes, truncation, inserted
garbage; seeded) and checks that every intact record comes back, in order, that nothing
damaged comes back as valid, and that the damage is counted. ``pytest -s`` prints its figures.
"""

from __future__ import annotations

import json
import random
import shutil
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from tidee.protocol import codec
from tidee.protocol.episode_log import (
    EVENTS_NAME,
    MAGIC,
    MAGIC_V1,
    SUMMARY_NAME,
    TLOG_NAME,
    LogReader,
    LogWriter,
)
from tidee.protocol.messages import AgentStatus, CommandAck, ReceptaclePrediction

SEED = 20240611
CASES_PER_OPERATION = 70  # x 5 operations x 3 files = 1050 cases


def _status(step: int) -> AgentStatus:
    return AgentStatus(
        session="s",
        step=step,
        phase="mapping",
        episode={"room_type": "Kitchen"},
        pose=(0.1 * step, 0.0, 0.0, 30.0),
        predictions=[ReceptaclePrediction("Desk", 0.5)],
        trajectory=np.zeros((step % 4 + 1, 2), np.float32),
    )


SUMMARY = {
    "steps": 12,
    "session": "s",
    "record": {"objects": [{"name": "Mug", "found": True}], "score": 0.25},
}


def _write_log(directory: Path) -> tuple[list[tuple[str, bytes]], list[dict]]:
    """A small log of 12 steps; returns its telemetry records (kind, frame) and its events."""
    records, events = [], []
    with LogWriter(directory) as w:
        for step in range(12):
            msgs = [("status", _status(step))]
            if step % 3 == 0:
                msgs.append(("ack", CommandAck(session="s", command_id=f"c{step}", kind="pause", ok=True)))
            for kind, msg in msgs:
                w.message(kind, msg)
                records.append((kind, codec.encode(msg, "jpeg")))
            event = {"kind": "action", "step": step, "action": "MoveAhead", "pose": [0.1 * step, 0.0, 30.0]}
            w.event(**event)
            events.append(event)
        w.finish(SUMMARY)
    return records, events


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> tuple[Path, list[tuple[str, bytes]], list[dict]]:
    directory = tmp_path_factory.mktemp("log") / "ep"
    records, events = _write_log(directory)
    return directory, records, events


def _tlog_spans(records: list[tuple[str, bytes]]) -> list[tuple[int, int]]:
    """Where each record lies in ``telemetry.tlog``: sync + header (12 bytes) + body."""
    spans, pos = [], len(MAGIC)
    for kind, frame in records:
        end = pos + 12 + 1 + len(kind) + len(frame)
        spans.append((pos, end))
        pos = end
    return spans


def _line_spans(data: bytes) -> list[tuple[int, int]]:
    spans, pos = [], 0
    for line in data.splitlines(keepends=True):
        spans.append((pos, pos + len(line)))
        pos += len(line)
    return spans


# --- the formats ---------------------------------------------------------------------------------


def test_every_record_of_every_file_carries_a_checksum(pristine) -> None:
    directory, records, events = pristine
    data = (directory / TLOG_NAME).read_bytes()
    assert data.startswith(MAGIC)
    for (start, end), (kind, frame) in zip(_tlog_spans(records), records):
        sync, length, crc = struct.unpack_from("<4sII", data, start)
        body = data[start + 12 : end]
        assert sync == b"\x1eREC" and length == len(body) and crc == zlib.crc32(body)
        assert body == bytes([len(kind)]) + kind.encode() + frame
    lines = (directory / EVENTS_NAME).read_bytes().splitlines()
    assert len(lines) == len(events)
    for line, event in zip(lines, events):
        crc, text = line.split(b"\t", 1)
        assert int(crc, 16) == zlib.crc32(text) and json.loads(text) == event
    stored = json.loads((directory / SUMMARY_NAME).read_text())
    canonical = json.dumps(SUMMARY, sort_keys=True, separators=(",", ":"))
    assert stored == {**SUMMARY, "crc32": f"{zlib.crc32(canonical.encode()):08x}"}
    r = LogReader(directory)
    assert list(r.records()) == records and r.events() == events and r.summary() == SUMMARY
    assert not r.truncated and r.corrupt_message == ""
    assert r.skipped == {TLOG_NAME: 0, EVENTS_NAME: 0, SUMMARY_NAME: 0}


def test_finish_replaces_a_checksum_already_in_the_summary(tmp_path) -> None:
    with LogWriter(tmp_path) as w:  # a summary read back from another log, say
        w.finish({"steps": 3, "loss": float("nan"), "mean": np.float32(0.5), "crc32": "00000000"})
    r = LogReader(tmp_path)
    assert r.summary() == {"steps": 3, "loss": None, "mean": 0.5} and not r.truncated


def test_a_bad_summary_checksum_means_no_summary_and_says_so(tmp_path) -> None:
    with LogWriter(tmp_path) as w:
        w.finish({"steps": 3})
    path = tmp_path / SUMMARY_NAME
    path.write_text(path.read_text().replace('"steps": 3', '"steps": 4'))
    r = LogReader(tmp_path)
    assert r.summary() is None and r.skipped[SUMMARY_NAME] == 1
    assert r.corrupt_message.startswith(f"{SUMMARY_NAME}: skipped 1 damaged stretch")
    assert "\n" not in r.corrupt_message


def test_old_logs_without_sync_markers_or_checksums_are_read_and_resynced(tmp_path) -> None:
    records = [("status", codec.encode(_status(step), "raw")) for step in range(6)]
    blob, spans = bytearray(MAGIC_V1), []
    for kind, frame in records:
        body = bytes([len(kind)]) + kind.encode() + frame
        spans.append(len(blob))
        blob += struct.pack("<II", len(body), zlib.crc32(body)) + body
    (tmp_path / TLOG_NAME).write_bytes(bytes(blob))
    (tmp_path / EVENTS_NAME).write_text('{"step": 0}\n{"step": 1}\n')
    (tmp_path / SUMMARY_NAME).write_text('{"steps": 6}\n')
    r = LogReader(tmp_path)
    assert r.version == 1 and list(r.records()) == records
    assert r.events() == [{"step": 0}, {"step": 1}] and r.summary() == {"steps": 6} and not r.truncated
    blob[spans[2] + 20] ^= 0x40  # damage the third record
    (tmp_path / TLOG_NAME).write_bytes(bytes(blob))
    r = LogReader(tmp_path)
    assert list(r.records()) == records[:2] + records[3:] and r.skipped[TLOG_NAME] == 1
    assert [m.step for _, m in r.messages()] == [0, 1, 3, 4, 5]


def test_a_directory_that_is_no_log_is_refused(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="no telemetry.tlog"):
        LogReader(tmp_path)
    (tmp_path / TLOG_NAME).write_bytes(b"not a log at all, just text\n" * 10)
    with pytest.raises(ValueError, match="not an episode log"):
        LogReader(tmp_path)


# --- the fuzz test -------------------------------------------------------------------------------

OPERATIONS = ("flip", "flip3", "truncate", "insert", "insert_at_boundary")


@dataclass
class Figures:
    cases: int = 0
    damaged: int = 0  # cases whose damage left bytes of no intact record (expected to be counted)
    detected: int = 0  # ... and the reader counted them
    after_damage: int = 0  # cases with intact records after the damage
    resynced: int = 0  # ... all of which were read back
    false_accepts: int = 0  # a record returned that is not one written, or out of order
    lost_intact: int = 0  # an intact record not returned
    miscounted: int = 0  # damage counted where there was none
    by_file: dict = field(default_factory=dict)


def _damage(
    data: bytes, op: str, spans: list[tuple[int, int]], rng: random.Random, header: int
) -> tuple[bytes, set[int], int, bool]:
    """(damaged bytes, indices of records damaged, first damaged offset, whether the damaged
    file holds bytes of no intact record). ``header``: bytes before the first record."""

    def hit(lo: int, hi: int) -> set[int]:  # records overlapping [lo, hi)
        return {i for i, (s, e) in enumerate(spans) if s < hi and lo < e}

    if op in ("flip", "flip3"):
        positions = [rng.randrange(len(data)) for _ in range(1 if op == "flip" else 3)]
        out = bytearray(data)
        for p in positions:
            out[p] ^= rng.randrange(1, 256)
        damaged = set().union(*(hit(p, p + 1) for p in positions))
        return bytes(out), damaged, min(positions), True
    if op == "truncate":
        p = rng.randrange(len(data))
        lost = hit(p, len(data))
        torn = {i for i in lost if spans[i][0] < p}  # records of which a prefix is left
        return data[:p], lost, p, bool(torn) or p < header
    garbage = rng.randbytes(rng.randrange(1, 65))
    if op == "insert":
        p = rng.randrange(len(data) + 1)
        damaged = {i for i, (s, e) in enumerate(spans) if s < p < e}
    else:
        p = rng.choice([s for s, _ in spans] + [len(data)])
        damaged = set()
    return data[:p] + garbage + data[p:], damaged, p, True


def _check(returned: list, written: list, damaged: set[int], figures: Figures, where: str) -> None:
    """Every returned record is a written one, in order; every undamaged one is returned."""
    indices = []
    for item in returned:
        matches = [i for i, w in enumerate(written) if w == item]
        if not matches:
            figures.false_accepts += 1
            continue
        indices.append(matches[0])
    if indices != sorted(set(indices)):
        figures.false_accepts += 1
    missing = set(range(len(written))) - damaged - set(indices)
    if missing:
        figures.lost_intact += 1
        raise AssertionError(f"{where}: intact records {sorted(missing)} not read back")


def test_fuzz_damaged_logs_are_read_without_error_resynced_and_counted(pristine, tmp_path) -> None:
    source, records, events = pristine
    assert len(set(records)) == len(records)  # distinct, so each returned one is identifiable
    rng = random.Random(SEED)
    figures = Figures()
    files = {name: (source / name).read_bytes() for name in (TLOG_NAME, EVENTS_NAME, SUMMARY_NAME)}
    spans = {
        TLOG_NAME: _tlog_spans(records),
        EVENTS_NAME: _line_spans(files[EVENTS_NAME]),
        SUMMARY_NAME: [(0, len(files[SUMMARY_NAME]))],
    }
    assert spans[TLOG_NAME][-1][1] == len(files[TLOG_NAME])
    headers = {TLOG_NAME: len(MAGIC), EVENTS_NAME: 0, SUMMARY_NAME: 0}
    directory = tmp_path / "ep"
    shutil.copytree(source, directory)
    for name, data in files.items():
        for op in OPERATIONS:
            for case in range(CASES_PER_OPERATION):
                damaged_data, damaged, first, expect_count = _damage(
                    data, op, spans[name], rng, headers[name]
                )
                if name == EVENTS_NAME and op == "truncate":
                    # a line cut only of its newline is intact: its checksum covers the JSON text
                    damaged -= {i for i, (s, e) in enumerate(spans[name]) if len(damaged_data) == e - 1}
                    expect_count = any(s < len(damaged_data) < e - 1 for s, e in spans[name])
                (directory / name).write_bytes(damaged_data)
                where = f"{name} {op} case {case}"
                r = LogReader(directory)
                got_records = list(r.records())
                list(r.messages())  # decoding never raises either
                got_events = r.events()
                got_summary = r.summary()
                if name == TLOG_NAME:
                    _check(got_records, records, damaged, figures, where)
                    after = [i for i, (s, _) in enumerate(spans[name]) if s > first and i not in damaged]
                    returned = {records.index(x) for x in got_records if x in records}
                else:
                    assert got_records == records, where
                if name == EVENTS_NAME:
                    _check(got_events, events, damaged, figures, where)
                    after = [i for i, (s, _) in enumerate(spans[name]) if s > first and i not in damaged]
                    returned = {events.index(x) for x in got_events if x in events}
                else:
                    assert got_events == events, where
                if name == SUMMARY_NAME:
                    assert got_summary in (None, SUMMARY), where
                    if got_summary != SUMMARY and got_summary is not None:
                        figures.false_accepts += 1
                    expect_count = got_summary is None  # a damaged summary is absent, and counted
                    after, returned = [], set()
                else:
                    assert got_summary == SUMMARY, where
                figures.cases += 1
                figures.damaged += expect_count
                counted = r.skipped[name] > 0
                figures.detected += expect_count and counted
                figures.miscounted += counted and not expect_count
                assert counted == expect_count, f"{where}: skipped {r.skipped}, expected {expect_count}"
                assert all(v == 0 for k, v in r.skipped.items() if k != name), where
                assert (r.corrupt_message != "") == counted and "\n" not in r.corrupt_message, where
                figures.after_damage += bool(after)
                if after and set(after) <= returned:
                    figures.resynced += 1
                    figures.by_file[name] = figures.by_file.get(name, 0) + 1
        (directory / name).write_bytes(data)
    print(f"\nfuzz: {figures}")
    assert figures.cases >= 500
    assert figures.false_accepts == 0 and figures.lost_intact == 0 and figures.miscounted == 0
    assert figures.detected == figures.damaged and figures.resynced == figures.after_damage
