"""``tidee bench transport``: step latency in-process vs over Zenoh on loopback.

The same room and the same action sequence run twice: on an ``Episode`` in this process,
then through a ``tidee server`` in a separate process (the honest measurement: two
processes, real sockets, encode + send + decode both ways). The figure of merit is the
ratio of median step latencies.
"""

from __future__ import annotations

import os
import platform
import socket
import subprocess
import sys
import time
import uuid

import numpy as np

from tidee.protocol.client import SimClient
from tidee.protocol.messages import Action, EpisodeSpec
from tidee.protocol.transport import InProcessTransport, SimTransport
from tidee.server.bench_sim import ACTIONS, write_report

WARMUP_STEPS = 10


def run_transport_bench(
    resolution: int,
    steps: int,
    out_path: str,
    renderer: str = "auto",
    room_type: str = "LivingRoom",
    seed: int = 200,
) -> dict:
    spec = EpisodeSpec(
        room_type=room_type,
        seed=seed,
        mess_index=0,
        resolution=resolution,
        max_steps=steps + WARMUP_STEPS + 10,
    )
    with InProcessTransport(renderer=renderer) as inproc:
        renderer_used = getattr(inproc.episode, "renderer", renderer)
        inproc_ms = _step_latencies(inproc, spec, steps)
    endpoint, server_id = _free_loopback_endpoint(), f"bench{uuid.uuid4().hex[:6]}"
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tidee.cli",
            "server",
            "--endpoint",
            endpoint,
            "--server-id",
            server_id,
            "--renderer",
            renderer_used,
            "--max-sessions",
            "1",
        ]
    )
    try:
        with SimClient(endpoint=endpoint, server_id=server_id, connect_timeout=60.0) as client:
            zenoh_ms = _step_latencies(client, spec, steps)
    finally:
        server.terminate()
        server.wait(timeout=30)
    inproc_median, zenoh_median = float(np.median(inproc_ms)), float(np.median(zenoh_ms))
    frame_kib = resolution * resolution * (3 + 4) / 1024
    result = {
        "resolution": resolution,
        "steps": steps,
        "renderer": renderer_used,
        "room": f"{room_type}/{seed}",
        "inproc_step_ms_median": round(inproc_median, 3),
        "zenoh_step_ms_median": round(zenoh_median, 3),
        "ratio": round(zenoh_median / inproc_median, 3),
        "zenoh_overhead_ms_median": round(zenoh_median - inproc_median, 3),
        "inproc_step_ms_p90": round(float(np.percentile(inproc_ms, 90)), 3),
        "zenoh_step_ms_p90": round(float(np.percentile(zenoh_ms, 90)), 3),
        "observation_kib": round(frame_kib, 1),
        "encoding": "raw",
        "machine": f"{platform.machine()} {os.cpu_count()} cores",
    }
    write_report(
        out_path, result, "Transport benchmark (`tidee bench transport`): in-process vs Zenoh loopback"
    )
    return result


def _step_latencies(transport: SimTransport, spec: EpisodeSpec, steps: int) -> list[float]:
    """Milliseconds per step (the caller's wall clock) over the shared action sequence."""
    transport.reset(spec)
    for k in range(WARMUP_STEPS):
        transport.step(Action(ACTIONS[k % len(ACTIONS)]))
    transport.reset(spec)
    out = []
    for k in range(steps):
        t = time.perf_counter()
        transport.step(Action(ACTIONS[k % len(ACTIONS)]))
        out.append((time.perf_counter() - t) * 1000)
    return out


def _free_loopback_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"
