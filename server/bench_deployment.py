"""``tidee bench deployment``: step latency peer-to-peer vs through a ``tidee router``, side by side.

One ``tidee server`` (one simulator process) is reachable both ways at once: it listens on its own
loopback endpoint, as in peer mode, and is also connected to a ``tidee router`` (a Zenoh config
file adds the router to its connect endpoints). Two clients hold a session each on that server:

* peer-to-peer: a peer whose only link is to the server (gossip off, so it does not reach the
  router through the server's announcements);
* through a router: a Zenoh client of the router, as every process is in compose.yaml.

Both reset the same room and walk the same action sequence, stepped in turn, step by step (the
order rotating each step: ``bench_transport``'s loop), so a change in the load of a shared machine
touches both alike. Reported: median, p90 and max step latency of each, the ratios (target: the
router's median at most 1.2 times the peer's), each client's links, and the load average.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zenoh

from tidee.launch import end_process, free_port, tidee_command
from tidee.protocol.client import SimClient
from tidee.protocol.episode_log import write_atomic, write_json_atomic
from tidee.protocol.zenoh_config import merged_config, tidee_defaults
from tidee.server.bench_sim import spread
from tidee.server.bench_transport import bench_spec, interleaved_latencies

TARGET_RATIO = 1.2  # through a router / peer-to-peer, median step latency
PATHS = ("peer-to-peer", "through a router")


def run_deployment_bench(
    out_path: str,
    steps: int = 200,
    resolution: int = 256,
    renderer: str = "tiny",
    room_type: str = "LivingRoom",
    seed: int = 200,
    mess_index: int = 0,
) -> dict:
    spec = bench_spec(steps, resolution, room_type, seed, mess_index)
    load_before = os.getloadavg()
    links: dict[str, dict[str, int]] = {}
    with _both_ways(renderer, links) as clients:
        ms = interleaved_latencies(clients, spec, steps)
    load_after = os.getloadavg()
    peer, routed = (float(np.median(ms[p])) for p in PATHS)
    ratio = round(routed / peer, 3)
    result = {
        "room": f"{room_type}/{seed} mess {mess_index}",
        "resolution": resolution,
        "renderer": renderer,
        "steps": steps,
        "step_ms": {path: spread(ms[path], 3) for path in PATHS},
        "ratio_median": ratio,
        "ratio_p90": round(float(np.percentile(ms[PATHS[1]], 90) / np.percentile(ms[PATHS[0]], 90)), 3),
        "router_overhead_ms_median": round(routed - peer, 3),
        "target_ratio": TARGET_RATIO,
        "met": ratio <= TARGET_RATIO,
        "links": links,
        "load_avg_before": [round(x, 2) for x in load_before],
        "load_avg_after": [round(x, 2) for x in load_after],
        "machine": f"{platform.machine()} {os.cpu_count()} cores",
    }
    _write(out_path, result)
    return result


@contextlib.contextmanager
def _both_ways(renderer: str, links: dict[str, dict[str, int]]) -> Iterator[dict[str, SimClient]]:
    """A router, one server on it and on its own endpoint, and a client each way (``PATHS``); the
    clients' links go into ``links``. Everything is stopped afterwards, the router last."""
    router_ep, server_ep = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    server_id = f"bench{uuid.uuid4().hex[:6]}"
    tidee = tidee_command()
    with (
        tempfile.TemporaryDirectory(prefix="tidee-bench-deployment-") as tmp,
        contextlib.ExitStack() as stack,
    ):
        also_router = Path(tmp) / "server.json5"  # the server's peer settings, plus a link to the router
        also_router.write_text(json.dumps({"connect": {"endpoints": [router_ep]}}))
        log = stack.enter_context(open(Path(tmp) / "log.txt", "w+b"))
        server = [
            *tidee,
            "server",
            "--endpoint",
            server_ep,
            "--zenoh-config",
            str(also_router),
            "--server-id",
            server_id,
            "--renderer",
            renderer,
            "--processes",
            "1",
            "--max-sessions",
            "2",
        ]
        for argv in ([*tidee, "router", "--listen", router_ep], server):  # ended in reverse order
            proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
            stack.callback(end_process, proc)
        try:
            ways = {  # Zenoh settings, and where SimClient's messages say it connects
                PATHS[0]: (
                    {**tidee_defaults(False, server_ep), "scouting/gossip/enabled": False},
                    {"endpoint": server_ep},
                ),
                PATHS[1]: (tidee_defaults(False, router=router_ep), {"router": router_ep}),
            }
            clients = {}
            for path, (settings, where) in ways.items():
                z = zenoh.open(merged_config(settings))
                stack.callback(z.close)
                clients[path] = stack.enter_context(
                    SimClient(**where, server_id=server_id, zsession=z, connect_timeout=60.0)
                )
                links[path] = {
                    "routers": len(list(z.info.routers_zid())),
                    "peers": len(list(z.info.peers_zid())),
                }
            yield clients
        except BaseException:
            log.seek(0)
            sys.stderr.write(log.read()[-4000:].decode(errors="replace"))
            raise


def _write(out_path: str, result: dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(out_path)) or ".", exist_ok=True)
    write_json_atomic(out_path, result)
    before, after = (" / ".join(f"{x:.2f}" for x in result[k]) for k in ("load_avg_before", "load_avg_after"))
    lines = [
        "# Deployment benchmark (`tidee bench deployment`): peer-to-peer vs through a router",
        "",
        f"One server, {result['room']}, {result['resolution']}² {result['renderer']} renderer, "
        f"{result['steps']} timed steps each way, stepped in turn; {result['machine']}; load average "
        f"(1/5/15 min) {before} before, {after} after.",
        "",
        "| path | client's links | step ms median | p90 | max |",
        "|---|---|---|---|---|",
    ]
    for path in PATHS:
        s, link = result["step_ms"][path], result["links"][path]
        links = f"{link['routers']} router(s), {link['peers']} peer(s)"
        lines.append(f"| {path} | {links} | {s['median']} | {s['p90']} | {s['max']} |")
    verdict = "met" if result["met"] else "not met"
    lines += [
        "",
        f"Through a router / peer-to-peer: median {result['ratio_median']}, p90 {result['ratio_p90']} "
        f"(target ≤ {result['target_ratio']}: {verdict}); the router adds "
        f"{result['router_overhead_ms_median']} ms per step at the median.",
    ]
    write_atomic(os.path.splitext(out_path)[0] + ".md", ("\n".join(lines) + "\n").encode())
