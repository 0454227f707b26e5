"""``tidee bench transport``: step latency in-process vs over Zenoh on loopback.

The same room and the same action sequence run on an ``Episode`` in this process and
through ``tidee server``s in separate processes (the honest measurement: real sockets,
encode + send + decode both ways), one server per way depth travels under ``raw``
(``TIDEE_WIRE_DEPTH`` in its environment): ``f32`` (float32 metres, exact: the default)
and ``mm`` (uint16 millimetres, ``raw-depth-mm``: half the depth bytes, 1 mm precision).
The three are stepped in turn, step by step (the order rotating each step), so a change in
the load of a shared machine touches all of them alike. The figure of merit is the ratio of
median step latencies; median / p90 / max of each are reported side by side, with the
codec's own cost per depth form on one rendered frame and the machine's load average.
"""

from __future__ import annotations

import contextlib
import os
import platform
import subprocess
import time
import uuid
from collections.abc import Iterator

import numpy as np

from tidee.launch import free_port, tidee_command
from tidee.protocol.client import SimClient
from tidee.protocol.codec import RAW_DEPTH_FORMS, WIRE_DEPTH_ENV, decode, encode
from tidee.protocol.messages import Action, EpisodeSpec, Observation
from tidee.protocol.transport import InProcessTransport, SimTransport
from tidee.server.bench_sim import ACTIONS, spread, write_report

WARMUP_STEPS = 10


def bench_spec(steps: int, resolution: int, room_type: str, seed: int, mess_index: int = 0) -> EpisodeSpec:
    """The episode a step benchmark walks: long enough for its warm-up and ``steps`` timed steps."""
    return EpisodeSpec(
        room_type=room_type,
        seed=seed,
        mess_index=mess_index,
        resolution=resolution,
        max_steps=steps + WARMUP_STEPS + 10,
    )


def server_command(endpoint: str, server_id: str, renderer: str, *flags: str) -> list[str]:
    """``tidee server`` on ``endpoint`` as a subprocess's command line, with more ``flags``."""
    return tidee_command(
        "server", "--endpoint", endpoint, "--server-id", server_id, "--renderer", renderer, *flags
    )


def run_transport_bench(
    resolution: int,
    steps: int,
    out_path: str,
    renderer: str = "auto",
    room_type: str = "LivingRoom",
    seed: int = 200,
) -> dict:
    spec = bench_spec(steps, resolution, room_type, seed)
    load_before = os.getloadavg()
    with contextlib.ExitStack() as stack:
        inproc = stack.enter_context(InProcessTransport(renderer=renderer))
        renderer_used = getattr(inproc.episode, "renderer", renderer)
        transports: dict[str, SimTransport] = {"inproc": inproc}
        for form in RAW_DEPTH_FORMS:
            transports[form] = stack.enter_context(_server_client(renderer_used, form))
        ms = interleaved_latencies(transports, spec, steps)
        frame = inproc.reset(spec)
    load_after = os.getloadavg()
    inproc_ms, zenoh_ms = ms["inproc"], {form: ms[form] for form in RAW_DEPTH_FORMS}
    inproc_median = float(np.median(inproc_ms))
    result: dict = {
        "resolution": resolution,
        "steps": steps,
        "renderer": renderer_used,
        "room": f"{room_type}/{seed}",
        "encoding": "raw",
        "inproc_step_ms": spread(inproc_ms, 3),
    }
    for form in RAW_DEPTH_FORMS:
        median = float(np.median(zenoh_ms[form]))
        result[f"zenoh_{form}_step_ms"] = spread(zenoh_ms[form], 3)
        result[f"ratio_{form}"] = round(median / inproc_median, 3)
        result[f"overhead_ms_{form}"] = round(median - inproc_median, 3)
    result["ratio"] = result["ratio_f32"]  # what a default server and SimClient get
    result.update(codec_costs(frame))
    result["load_1min_before_after"] = [round(load_before[0], 2), round(load_after[0], 2)]
    result["load_1_5_15_after"] = [round(x, 2) for x in load_after]
    result["machine"] = f"{platform.machine()} {os.cpu_count()} cores"
    write_report(
        out_path, result, "Transport benchmark (`tidee bench transport`): in-process vs Zenoh loopback"
    )
    return result


def codec_costs(obs: Observation, repeats: int = 200) -> dict:
    """Frame bytes, encode and decode microseconds (median) and the worst depth error of each
    raw depth form on one rendered observation; float16 (not a wire form) for comparison."""
    depth = np.asarray(obs.depth)
    seen = np.isfinite(depth) & (depth > 0)
    out: dict = {}
    for form in RAW_DEPTH_FORMS:
        frame = encode(obs, raw_depth=form)
        back = decode(frame)
        out[f"codec_{form}"] = {
            "frame_kib": round(len(frame) / 1024, 1),
            "encode_us": _median_us(lambda f=form: encode(obs, raw_depth=f), repeats),
            "decode_us": _median_us(lambda fr=frame: decode(fr), repeats),
            "max_depth_err_mm": round(float(np.abs(back.depth[seen] - depth[seen]).max(initial=0)) * 1000, 3),
        }
    half = depth.astype("<f2")
    out["codec_f16_not_used"] = {
        "depth_kib": round(half.nbytes / 1024, 1),
        "convert_us": _median_us(lambda: depth.astype("<f2"), repeats),
        "back_us": _median_us(lambda: half.astype(np.float32), repeats),
        "max_depth_err_mm": round(
            float(np.abs(half.astype(np.float32)[seen] - depth[seen]).max(initial=0)) * 1000, 3
        ),
    }
    return out


def _median_us(fn, repeats: int) -> float:  # type: ignore[no-untyped-def]
    fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return round(float(np.median(samples)) * 1e6, 1)


@contextlib.contextmanager
def _server_client(renderer: str, form: str) -> Iterator[SimClient]:
    """A client of a fresh server process that sends depth as ``form``; the server stops after."""
    endpoint, server_id = loopback_endpoint(), f"bench{uuid.uuid4().hex[:6]}"
    server = subprocess.Popen(
        server_command(endpoint, server_id, renderer, "--max-sessions", "1"),
        env={**os.environ, WIRE_DEPTH_ENV: form},
    )
    try:
        with SimClient(endpoint=endpoint, server_id=server_id, connect_timeout=60.0) as client:
            yield client
    finally:
        server.terminate()
        server.wait(timeout=30)


def interleaved_latencies(
    transports: dict[str, SimTransport], spec: EpisodeSpec, steps: int
) -> dict[str, list[float]]:
    """Milliseconds per step (the caller's wall clock) of each transport over the shared action
    sequence, stepping them in turn (rotating which goes first)."""
    names = list(transports)
    for t in transports.values():
        t.reset(spec)
        for k in range(WARMUP_STEPS):
            t.step(Action(ACTIONS[k % len(ACTIONS)]))
        t.reset(spec)
    out: dict[str, list[float]] = {name: [] for name in names}
    for k in range(steps):
        action = Action(ACTIONS[k % len(ACTIONS)])
        for i in range(len(names)):
            name = names[(k + i) % len(names)]
            t0 = time.perf_counter()
            transports[name].step(action)
            out[name].append((time.perf_counter() - t0) * 1000)
    return out


def loopback_endpoint() -> str:
    """A TCP endpoint on a free loopback port."""
    return f"tcp/127.0.0.1:{free_port()}"
