"""``tidee bench fuzz``: hostile requests against a real server; does it always answer, and clearly?

A ``tidee server`` subprocess (real episodes in a simulator process, TinyRenderer) gets
``cases`` requests over Zenoh on loopback, drawn reproducibly from ``seed`` (the same seed
gives the same requests, whatever the server answers). Every op (reset, step, phase, state,
close) is sent valid, and broken in one way per case (the *family*):

- ``valid``: unchanged; these keep a few fuzz sessions alive, so the broken requests meet
  sessions in every state (none yet, walking, over, in a rearrangement's walkthrough, closed);
- ``bytes``: truncated, bytes flipped or inserted, random bytes, trailing garbage, sent twice;
- ``prefix``: a wrong magic, protocol version or header length;
- ``type``: one field, at any depth, set to a value of another type (null, bools, huge or
  negative integers, NaN and infinities, empty, long or odd strings, lists, objects);
- ``range``: one to three fields set to boundary values of their own type (resolutions
  15/16/1024/1025, mess indices past the split's range, seeds outside every split, pixels just
  outside [0, 1], unknown room types...);
- ``structure``: a field deleted or added, another message type, a header that is not an
  object, another op's request;
- ``key``: a session in the key other than the payload's, an unknown op, odd session ids;
- ``deep``: JSON nested 100,000 levels deep;
- ``oversized``: a request past the server's ``max_request_bytes``.

Each reply is counted by the code it carries (``ok`` or the ``ErrorReply`` code). A request
with no reply within ``reply_timeout_s`` is a *hang*, a server process that exits is a *crash*
(it is started again and the run goes on), a simulator process that dies shows in the server's
log, and an ``internal`` error is a server bug: each is listed with its case. After every
``batch`` cases an honest client runs a short episode and must get exactly the frames it got
before the fuzzing began. The targets: 0 crashes, 0 hangs, 0 ``internal`` errors, every
honest episode unchanged.

Valid boundary values reach a bounded set of rooms (a few seeds and configurations of the
two fuzz rooms); the first reset of each generates it into the scene cache, as any client's
would.
"""

from __future__ import annotations

import json
import os
import platform
import random
import struct
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from tidee.launch import end_process, free_port
from tidee.protocol import keys
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.codec import MAGIC, ProtocolError, decode, encode
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.protocol.messages import (
    PIXEL_ACTIONS,
    PROTOCOL_VERSION,
    Action,
    ActionName,
    CloseRequest,
    EpisodeSpec,
    ErrorReply,
    Observation,
    PhaseRequest,
    ResetRequest,
    StateRequest,
    StepRequest,
)
from tidee.protocol.vocab import ROOM_TYPES
from tidee.protocol.zenoh_config import make_config
from tidee.server.bench_sim import spread
from tidee.server.config import FuzzBenchConfig, ServerConfig
from tidee.server.workers import available_cores

FAMILIES: dict[str, float] = {  # family -> weight
    "valid": 20,
    "bytes": 14,
    "prefix": 7,
    "type": 24,
    "range": 14,
    "structure": 10,
    "key": 7,
    "deep": 2,
    "oversized": 2,
}
OPS = keys.SESSION_OPS
FUZZ_SESSIONS = ("fuzz-0", "fuzz-1", "fuzz-2")  # one client by their prefix: within its quota of 4
# The two kinds of episode the fuzz sessions run: a messy test room, and a rearrangement (phase works).
SPECS = (
    EpisodeSpec(room_type="LivingRoom", seed=200, mess_index=0, resolution=32, max_steps=30),
    EpisodeSpec(
        room_type="Kitchen", seed=200, rearrange_index=0, resolution=32, max_steps=30, walkthrough_steps=5
    ),
)
HONEST_SPEC = EpisodeSpec(room_type="LivingRoom", seed=200, mess_index=0, resolution=32, max_steps=10)
HONEST_ACTIONS = (ActionName.RotateLeft, ActionName.MoveAhead, ActionName.LookDown)
PREFIX = struct.Struct("<4sHI")  # the codec's frame prefix: magic, version, header length
DEEP_LEVELS = 100_000
ZENOH_TIMEOUT = b"Timeout"  # what Zenoh itself answers when a query's time runs out
TARGETS = {"crashes": 0, "hangs": 0, "internal": 0, "honest_failures": 0}

# Values of the wrong type for any field (JSON can carry all of them: NaN and infinities as
# Python's json writes them, a lone surrogate as its escape).
HOSTILE: tuple[Any, ...] = (
    None, True, False, 0, -1, 1, 2**31, 2**53 + 1, 2**63 - 1, 2**63, -(2**63) - 1, 2**64, 10**30,
    0.5, -0.0, 1e308, 5e-324, float("nan"), float("inf"), float("-inf"),
    "", "x", "0", "1.5", "null", "\u0000", "\ud800", "é\u202e", "A" * 100_000,
    [], [1], [[[]]], {}, {"a": 1}, {"name": "MoveAhead"},
)  # fmt: skip
# Boundary values of each field's own type, by field name.
RANGES: dict[str, tuple[Any, ...]] = {
    "room_type": (*ROOM_TYPES, "Garage", "kitchen", ""),
    "seed": (0, 1, 204, 205, 10_000, 2**63 - 1, -1, 2**63),
    "mess_index": (None, 0, 4, 5, 99, -1, 2**63),
    "rearrange_index": (None, 0, 4, 5, -1),
    "resolution": (15, 16, 1024, 1025, 0, -16),
    "camera_height": (0.19, 0.2, 2.0, 2.01, 0.0, -1.0),
    "max_steps": (0, 1, 100_000, 100_001, -1),
    "walkthrough_steps": (0, 1, 100_000, 100_001),
    "start_seed": (None, 0, 1, 2**63 - 1, -1),
    "pose_noise": (True, False),
    "depth_noise": (True, False),
    "name": (*(a.value for a in ActionName), "Fly", "moveahead", ""),
    "x": (None, 0, 1, 0.0, 1.0, 0.5, -1e-9, 1.000001, 5e-324),
    "y": (None, 0, 1, 0.5, -1e-9, 1.000001),
    "ground_truth": (True, False),
    "encoding": ("raw", "jpeg", "png", "gif", "RAW", ""),
    "phase": ("unshuffle", "walkthrough", "UNSHUFFLE", ""),
    "protocol_version": (0, PROTOCOL_VERSION, PROTOCOL_VERSION + 1, 65535),
    "session": ("fuzz-0", "fuzz-1", "", "a" * 129, "bad/id", "ünï", "fuzz 0"),
}
ODD_SESSION_IDS = ("a" * 128, "x", "-", "_", "A-b_9", "fuzz-9")  # valid key chunks
BAD_KEY_CHUNKS = ("a" * 129, "no.dots", "ünï", "a~b", "@x", "%20")  # no Zenoh wildcard characters


@dataclass
class Case:
    index: int
    family: str
    op: str
    key: str
    payload: bytes
    what: str  # the mutation, in words


@dataclass
class Tally:
    by_family: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    by_op: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    totals: Counter = field(default_factory=Counter)
    internal: list[dict] = field(default_factory=list)
    hangs: list[dict] = field(default_factory=list)
    crashes: list[dict] = field(default_factory=list)
    honest_failures: list[dict] = field(default_factory=list)
    honest_checks: int = 0
    reply_ms: list[float] = field(default_factory=list)

    def count(self, case: Case, outcome: str) -> None:
        self.by_family[case.family][outcome] += 1
        self.by_op[case.op][outcome] += 1
        self.totals[outcome] += 1


# --- the cases --------------------------------------------------------------------------------
class CaseMaker:
    """The case stream of one seed: case *i* depends only on the seed and *i*'s predecessors."""

    def __init__(self, seed: int, server_id: str, max_request_bytes: int) -> None:
        self.rng = random.Random(seed)
        self.server_id = server_id
        self.max_request_bytes = max_request_bytes
        self.index = 0
        families = list(FAMILIES)
        self._families, self._weights = families, [FAMILIES[f] for f in families]

    def next(self) -> Case:
        rng = self.rng
        family = rng.choices(self._families, self._weights)[0]
        op = rng.choice(OPS)
        session = rng.choice(FUZZ_SESSIONS)
        header = self.valid_header(op, session)
        key = keys.sim_op(self.server_id, session, op)
        what = "valid"
        if family == "valid":
            payload = frame(header)
        elif family == "bytes":
            payload, what = self.mutate_bytes(frame(header))
        elif family == "prefix":
            payload, what = self.mutate_prefix(header)
        elif family == "type":
            what, payload = self.mutate_field(header, hostile=True), frame(header)
        elif family == "range":  # one to three fields: boundary values meet each other
            changes = [self.mutate_field(header, hostile=False) for _ in range(rng.randint(1, 3))]
            what, payload = "; ".join(changes), frame(header)
        elif family == "structure":
            payload, what = self.mutate_structure(header, op, session)
        elif family == "key":
            key, payload, what = self.mutate_key(header, op)
        elif family == "deep":
            payload, what = self.deep(header)
        else:  # oversized
            extra = self.max_request_bytes + rng.randint(1, 1 << 16)
            payload, what = frame(header) + b" " * extra, f"{extra} bytes of padding"
        case = Case(self.index, family, op, key, payload, what)
        self.index += 1
        return case

    def valid_header(self, op: str, session: str) -> dict:
        rng = self.rng
        ground_truth = rng.random() < 0.2
        encoding = rng.choice(("raw", "raw", "png", "jpeg"))
        message: Any
        if op == "reset":
            message = ResetRequest(session, rng.choice(SPECS), ground_truth, encoding)
        elif op == "step":
            name = rng.choice(list(ActionName))
            xy = (rng.random(), rng.random()) if name in PIXEL_ACTIONS else (None, None)
            message = StepRequest(session, Action(name, *xy), ground_truth, encoding)
        elif op == "phase":
            message = PhaseRequest(session, "unshuffle", ground_truth, encoding)
        elif op == "state":
            message = StateRequest(session)
        else:
            message = CloseRequest(session)
        return header_of(encode(message))

    def mutate_bytes(self, data: bytes) -> tuple[bytes, str]:
        rng = self.rng
        kind = rng.choice(("truncate", "flip", "insert", "random", "trailing", "twice", "empty"))
        if kind == "truncate":
            cut = rng.randrange(len(data))
            return data[:cut], f"truncated to {cut} of {len(data)} bytes"
        if kind == "flip":
            out = bytearray(data)
            spots = [rng.randrange(len(out)) for _ in range(rng.randint(1, 8))]
            for i in spots:
                out[i] ^= rng.randint(1, 255)
            return bytes(out), f"bytes flipped at {sorted(spots)}"
        if kind == "insert":
            at, junk = rng.randrange(len(data) + 1), rng.randbytes(rng.randint(1, 16))
            return data[:at] + junk + data[at:], f"{len(junk)} bytes inserted at {at}"
        if kind == "random":
            return rng.randbytes(rng.randint(1, 256)), "random bytes"
        if kind == "trailing":
            return data + rng.randbytes(rng.randint(1, 64)), "trailing garbage"
        if kind == "twice":
            return data + data, "the frame twice"
        return b"", "empty"

    def mutate_prefix(self, header: dict) -> tuple[bytes, str]:
        rng = self.rng
        body = json.dumps(header, separators=(",", ":")).encode()
        kind = rng.choice(("magic", "version", "length"))
        if kind == "magic":
            magic = rng.choice((b"TIDF", b"\0\0\0\0", b"HTTP", rng.randbytes(4)))
            return PREFIX.pack(magic, PROTOCOL_VERSION, len(body)) + body, f"magic {magic!r}"
        if kind == "version":
            version = rng.choice((0, PROTOCOL_VERSION + 1, 65535))
            return PREFIX.pack(MAGIC, version, len(body)) + body, f"version {version}"
        length = rng.choice((0, 1, len(body) - 1, len(body) + 1, 2**31, 2**32 - 1))
        return PREFIX.pack(MAGIC, PROTOCOL_VERSION, length) + body, f"header length {length} of {len(body)}"

    def mutate_field(self, header: dict, hostile: bool) -> str:
        rng = self.rng
        paths = list(field_paths(header["fields"]))
        if not hostile:
            paths = [p for p in paths if p[-1] in RANGES] or paths
        path = rng.choice(paths)
        value = rng.choice(HOSTILE if hostile or path[-1] not in RANGES else RANGES[path[-1]])
        parent = header["fields"]
        for part in path[:-1]:
            parent = parent[part]
        parent[path[-1]] = value
        shown = repr(value) if len(repr(value)) < 40 else f"{type(value).__name__} of {len(value)}"
        return f"{'.'.join(path)} = {shown}"

    def mutate_structure(self, header: dict, op: str, session: str) -> tuple[bytes, str]:
        rng = self.rng
        kind = rng.choice(("delete", "add", "type", "header", "fields", "other_op"))
        if kind == "delete":
            path = rng.choice(list(field_paths(header["fields"])))
            parent = header["fields"]
            for part in path[:-1]:
                parent = parent[part]
            del parent[path[-1]]
            return frame(header), f"{'.'.join(path)} deleted"
        if kind == "add":
            dicts = [header["fields"], *(v for v in header["fields"].values() if isinstance(v, dict))]
            target = rng.choice(dicts)
            target[rng.choice(("extra", "Session", "__class__", "type"))] = rng.choice(HOSTILE[:12])
            return frame(header), "an unknown field added"
        if kind == "type":
            name = rng.choice(("Observation", "ErrorReply", "AgentCommand", "Teleport", "", 7, None))
            header["type"] = name
            return frame(header), f"message type {name!r}"
        if kind == "header":
            shape = rng.choice(([header], "text", 42, None, {"type": header["type"]}, {**header, "x": 1}))
            return frame(shape), f"header {type(shape).__name__}"
        if kind == "fields":
            header["fields"] = rng.choice(([1, 2], "fields", None, 3.5))
            return frame(header), f"fields {header['fields']!r}"
        other = rng.choice([o for o in OPS if o != op])
        return frame(self.valid_header(other, session)), f"a {other} request"

    def mutate_key(self, header: dict, op: str) -> tuple[str, bytes, str]:
        rng = self.rng
        base = f"{keys.ROOT}/sim/{self.server_id}/session"
        kind = rng.choice(("mismatch", "odd_id", "bad_id", "op", "extra_chunk"))
        session = header["fields"].get("session", "fuzz-0")
        if kind == "mismatch":
            other = rng.choice([s for s in FUZZ_SESSIONS if s != session])
            return f"{base}/{other}/{op}", frame(header), f"key session {other}, payload {session}"
        if kind == "odd_id":
            odd = rng.choice(ODD_SESSION_IDS)
            header["fields"]["session"] = odd
            return f"{base}/{odd}/{op}", frame(header), f"session id {odd[:20]!r}"
        if kind == "bad_id":
            bad = rng.choice(BAD_KEY_CHUNKS)
            return f"{base}/{bad}/{op}", frame(header), f"key session {bad[:20]!r}"
        if kind == "op":
            wrong = rng.choice(("teleport", "Step", "resets", "_"))
            return f"{base}/{session}/{wrong}", frame(header), f"op {wrong!r}"
        return f"{base}/{session}/{op}/more", frame(header), "an extra key chunk"

    def deep(self, header: dict) -> tuple[bytes, str]:
        path = self.rng.choice(list(field_paths(header["fields"])))
        parent = header["fields"]
        for part in path[:-1]:
            parent = parent[part]
        parent[path[-1]] = "@DEEP@"
        text = json.dumps(header, separators=(",", ":"))
        opener, closer = self.rng.choice((("[", "]"), ('{"a":', "}")))
        text = text.replace('"@DEEP@"', opener * DEEP_LEVELS + "1" + closer * DEEP_LEVELS)
        return frame_text(text), f"{'.'.join(path)} nested {DEEP_LEVELS} deep"


def header_of(data: bytes) -> dict:
    _, _, length = PREFIX.unpack_from(data)
    return json.loads(data[PREFIX.size : PREFIX.size + length])


def frame(header: Any) -> bytes:
    """A request frame around ``header`` (requests carry no arrays): NaN stays NaN, as sent."""
    return frame_text(json.dumps(header, separators=(",", ":")))


def frame_text(text: str) -> bytes:
    body = text.encode("utf-8", "surrogatepass")
    return PREFIX.pack(MAGIC, PROTOCOL_VERSION, len(body)) + body


def field_paths(obj: dict, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every field's path in a header's fields, nested ones included (depth first)."""
    out = []
    for name, value in obj.items():
        out.append((*prefix, name))
        if isinstance(value, dict):
            out += field_paths(value, (*prefix, name))
    return out


# --- the run ----------------------------------------------------------------------------------
class FuzzServer:
    """A ``tidee server`` subprocess and a Zenoh session to it; started again after a crash."""

    def __init__(self, cfg: FuzzBenchConfig) -> None:
        self.cfg = cfg
        self.server_id = f"fuzz{uuid.uuid4().hex[:6]}"
        self.log = tempfile.TemporaryFile()
        self.starts = 0
        self.proc: subprocess.Popen | None = None
        self.z: zenoh.Session | None = None
        self.endpoint = ""

    def start(self, tries: int = 3, wait_s: float = 120.0) -> None:
        """Start the server and wait until it serves. A server that exits before it serves
        (its port taken between ``free_port`` and its bind) is started again on another port,
        up to ``tries`` times; one that neither serves nor exits within ``wait_s`` is an error."""
        self.starts += 1
        for _ in range(tries):
            self.endpoint = f"tcp/127.0.0.1:{free_port()}"
            command = [sys.executable, "-m", "tidee.cli", "server", "--endpoint", self.endpoint]
            command += ["--server-id", self.server_id, "--processes", str(self.cfg.processes)]
            command += ["--renderer", "tiny"]
            self.proc = subprocess.Popen(command, stdout=self.log, stderr=subprocess.STDOUT)
            deadline = time.monotonic() + wait_s
            while not self.crashed:
                try:
                    with self.honest_client("probe", connect_timeout=5.0):  # waits until it serves
                        pass
                except TimeoutError:
                    if time.monotonic() > deadline:
                        raise TimeoutError(
                            f"tidee server {self.server_id!r} at {self.endpoint} did not serve within "
                            f"{wait_s:g} s; its log ends: {self.log_text()[-500:]!r}"
                        ) from None
                    continue
                self.z = zenoh.open(make_config(False, self.endpoint))
                return
        raise RuntimeError(
            f"tidee server exited before it served, {tries} times; its log ends: {self.log_text()[-500:]!r}"
        )

    def honest_client(self, name: str, connect_timeout: float = 120.0) -> SimClient:
        return SimClient(
            endpoint=self.endpoint,
            server_id=self.server_id,
            session=f"honest-{name}",
            timeout=self.cfg.reply_timeout_s,
            connect_timeout=connect_timeout,
        )

    @property
    def crashed(self) -> bool:
        return self.proc is not None and self.proc.poll() is not None

    def stop(self) -> None:
        if self.z is not None:
            self.z.close()
            self.z = None
        if self.proc is not None:
            end_process(self.proc)

    def log_text(self) -> str:
        self.log.seek(0)
        return self.log.read().decode(errors="replace")


def send(z: zenoh.Session, case: Case, timeout: float) -> tuple[str, Any, float]:
    """(outcome, decoded reply or None, ms): ok, an error code, ``hang`` (no reply to a key the
    server listens on), ``unrouted`` (no reply to a key it does not listen on: Zenoh delivers
    the request to nobody) or ``undecodable``."""
    t0 = time.perf_counter()
    try:
        reply = z.get(case.key, payload=case.payload, timeout=timeout).recv()
    except zenoh.ZError:  # the query ended without a reply
        routed = zenoh.KeyExpr(keys.sim_op_wildcard(case.key.split("/")[2])).intersects(case.key)
        return ("hang" if routed else "unrouted"), None, 1000 * (time.perf_counter() - t0)
    ms = 1000 * (time.perf_counter() - t0)
    sample = reply.ok if reply.ok is not None else reply.err
    data = sample.payload.to_bytes()  # type: ignore[union-attr]
    if reply.ok is None and data == ZENOH_TIMEOUT:
        return "hang", None, ms
    try:
        msg = decode(data)
    except ProtocolError:
        return "undecodable", None, ms
    return (msg.code.value if isinstance(msg, ErrorReply) else "ok"), msg, ms


def honest_episode(server: FuzzServer, name: str) -> list[Observation]:
    with server.honest_client(name) as client:
        frames = [client.reset(HONEST_SPEC)]
        frames += [client.step(Action(a)) for a in HONEST_ACTIONS]
    return frames


def same_frames(a: list[Observation], b: list[Observation]) -> str:
    """'' if the two episodes saw the same thing, else what differed first."""
    for i, (x, y) in enumerate(zip(a, b)):
        for name in ("rgb", "depth", "camera_pose"):
            if not np.array_equal(getattr(x, name), getattr(y, name)):
                return f"frame {i}: {name} differs"
        if (x.step, x.agent_pose, x.success, x.error) != (y.step, y.agent_pose, y.success, y.error):
            return f"frame {i}: step/pose/outcome differ"
    return "" if len(a) == len(b) else "a different number of frames"


def fuzz_command(cfg: FuzzBenchConfig) -> str:
    return (
        f"tidee bench fuzz --cases {cfg.cases} --seed {cfg.seed} --batch {cfg.batch} "
        f"--reply-timeout {cfg.reply_timeout_s:g} --processes {cfg.processes}"
    )


def run_fuzz_bench(cfg: FuzzBenchConfig, out_path: Path | None = None) -> dict:
    """Run the cases of ``cfg.seed`` against a fresh server; the report (written to ``out_path``)."""
    server = FuzzServer(cfg)
    tally = Tally()
    load_before, loads = os.getloadavg(), []
    max_request_bytes = ServerConfig().max_request_bytes
    maker = CaseMaker(cfg.seed, server.server_id, max_request_bytes)
    start = time.monotonic()
    server.start()
    try:
        reference = honest_episode(server, "reference")
        opened: set[str] = set()  # sessions outside the fuzz pool a case opened: closed at each batch end
        for i in range(cfg.cases):
            case = maker.next()
            assert server.z is not None
            outcome, reply, ms = send(server.z, case, cfg.reply_timeout_s)
            tally.reply_ms.append(ms)
            if server.crashed:
                tally.crashes.append({**describe(case), "log": server.log_text()[-2000:]})
                outcome = "crash"
                server.stop()
                server.start()
            tally.count(case, outcome)
            if outcome == "internal":
                tally.internal.append({**describe(case), "message": reply.message})
            elif outcome == "hang":
                tally.hangs.append(describe(case))
            elif outcome == "ok" and case.op == "reset" and isinstance(reply, Observation):
                if reply.session not in FUZZ_SESSIONS:
                    opened.add(reply.session)
            if (i + 1) % cfg.batch == 0 or i + 1 == cfg.cases:
                for session in sorted(opened):
                    send(server.z, close_case(server.server_id, session), cfg.reply_timeout_s)
                opened.clear()
                tally.honest_checks += 1
                try:
                    failure = same_frames(reference, honest_episode(server, f"{i + 1}"))
                except (RemoteError, TimeoutError) as e:
                    failure = f"{type(e).__name__}: {e}"
                if failure:
                    tally.honest_failures.append({"after_case": i, "failure": failure})
                loads.append(os.getloadavg()[0])
    finally:
        server.stop()
    log = server.log_text()
    result = {
        "command": fuzz_command(cfg),
        "cases": cfg.cases,
        "seed": cfg.seed,
        "batch": cfg.batch,
        "reply_timeout_s": cfg.reply_timeout_s,
        "processes": cfg.processes,
        "families": FAMILIES,
        "totals": dict(sorted(tally.totals.items())),
        "crashes": len(tally.crashes),
        "hangs": len(tally.hangs),
        "internal": len(tally.internal),
        "simulator_deaths": log.count("died: "),
        "honest_checks": tally.honest_checks,
        "honest_failures": len(tally.honest_failures),
        "targets": TARGETS,
        "targets_met": all(
            v == 0
            for v in (len(tally.crashes), len(tally.hangs), len(tally.internal), len(tally.honest_failures))
        ),
        "by_family": {k: dict(sorted(v.items())) for k, v in sorted(tally.by_family.items())},
        "by_op": {k: dict(sorted(v.items())) for k, v in sorted(tally.by_op.items())},
        "reply_ms": spread(tally.reply_ms, 1),
        "server_starts": server.starts,
        "wall_s": round(time.monotonic() - start, 1),
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        "load_1min_during": spread(loads or [os.getloadavg()[0]]),
        "machine": f"{platform.machine()} {os.cpu_count()} cores, {available_cores()} available",
        "internal_cases": tally.internal[:50],
        "hang_cases": tally.hangs[:50],
        "crash_cases": tally.crashes[:10],
        "honest_failure_cases": tally.honest_failures[:50],
    }
    if out_path is not None:
        write_fuzz_report(out_path, result)
    return result


def close_case(server_id: str, session: str) -> Case:
    key = keys.sim_op(server_id, session, "close")
    return Case(-1, "cleanup", "close", key, encode(CloseRequest(session)), "close")


def describe(case: Case) -> dict:
    return {
        "case": case.index,
        "family": case.family,
        "op": case.op,
        "key": case.key,
        "what": case.what,
        "payload_head": case.payload[:200].hex(),
        "payload_bytes": len(case.payload),
    }


def write_fuzz_report(out_path: Path, r: dict) -> None:
    out_path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(str(out_path), r)
    outcomes = sorted({o for counts in r["by_family"].values() for o in counts})
    lines = [
        "# Fuzz benchmark (`tidee bench fuzz`)",
        "",
        f"`{r['command']}`: {r['cases']} requests to a real `tidee server` over Zenoh on loopback "
        f"({r['processes']} simulator process(es)); an honest episode checked after every {r['batch']}; "
        f"{r['machine']}; {r['wall_s']} s; load average (1/5/15 min) "
        f"{' / '.join(f'{x:.2f}' for x in r['load_avg_before'])} before, "
        f"{' / '.join(f'{x:.2f}' for x in r['load_avg_after'])} after; 1-minute load during the run: "
        f"median {r['load_1min_during']['median']}, max {r['load_1min_during']['max']}.",
        "",
        "| | count | target |",
        "|---|---|---|",
        f"| crashes (server process exited) | {r['crashes']} | 0 |",
        f"| hangs (no reply within {r['reply_timeout_s']:g} s) | {r['hangs']} | 0 |",
        f"| `internal` errors | {r['internal']} | 0 |",
        f"| simulator processes that died | {r['simulator_deaths']} | 0 |",
        f"| honest episodes with other frames | {r['honest_failures']} of {r['honest_checks']} | 0 |",
        "",
        f"Reply time (ms): median {r['reply_ms']['median']}, p90 {r['reply_ms']['p90']}, "
        f"max {r['reply_ms']['max']}.",
        "",
        "Replies by family (rows) and outcome (columns):",
        "",
        "| family | " + " | ".join(outcomes) + " | all |",
        "|---|" + "---|" * (len(outcomes) + 1),
    ]
    for family, counts in r["by_family"].items():
        lines.append(
            f"| {family} | "
            + " | ".join(str(counts.get(o, 0)) for o in outcomes)
            + f" | {sum(counts.values())} |"
        )
    lines.append("| all | " + " | ".join(str(r["totals"].get(o, 0)) for o in outcomes) + f" | {r['cases']} |")
    for title, key in (("`internal` errors", "internal_cases"), ("Hangs", "hang_cases")):
        if r[key]:
            lines += ["", f"{title} (first {len(r[key])}):", ""]
            lines += [
                f"- case {c['case']} ({c['family']}, {c['op']}): {c['what']}: {c.get('message', '')}"
                for c in r[key]
            ]
    write_atomic(os.path.splitext(str(out_path))[0] + ".md", ("\n".join(lines) + "\n").encode())
