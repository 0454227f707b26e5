"""``tidee scene tour``: the server as its own process, a client over Zenoh.

It starts ``tidee server`` on embedded Zenoh (peer mode, loopback), connects a client,
resets a messy room, looks around (one full turn, looking down at each heading), and saves
what it saw plus a top-down render with the moved objects circled. It prints every file it
wrote.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import cv2
import numpy as np

from tidee.launch import free_port
from tidee.protocol.client import SimClient
from tidee.protocol.messages import Action, ActionName, EpisodeSpec


def run_demo(out_dir: str, room_type: str = "LivingRoom", seed: int = 200, mess: int = 0) -> int:
    os.makedirs(out_dir, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = subprocess.Popen([sys.executable, "-m", "tidee.cli", "server", "--endpoint", endpoint])
    print(f"demo: started tidee server (pid {server.pid}) on {endpoint}")
    try:
        with SimClient(endpoint=endpoint, timeout=120, connect_timeout=60) as client:
            t0 = time.perf_counter()
            obs = client.reset(EpisodeSpec(room_type=room_type, seed=seed, mess_index=mess, resolution=480))
            print(f"demo: reset {room_type} seed {seed} mess {mess} in {time.perf_counter() - t0:.1f} s")
            frames = []
            obs = client.step(Action(ActionName.LookDown))
            for k in range(4):
                frames.append(obs.rgb.copy())
                depth = np.clip(obs.depth / 5.0 * 255, 0, 255).astype(np.uint8)
                cv2.imwrite(os.path.join(out_dir, f"view{k}_rgb.png"), obs.rgb[:, :, ::-1])
                cv2.imwrite(
                    os.path.join(out_dir, f"view{k}_depth.png"),
                    cv2.applyColorMap(depth, cv2.COLORMAP_VIRIDIS),
                )
                obs = client.step(Action(ActionName.RotateRight))
            sheet = np.concatenate([np.concatenate(frames[:2], 1), np.concatenate(frames[2:], 1)], 0)
            cv2.imwrite(os.path.join(out_dir, "views.png"), sheet[:, :, ::-1])
            state = client.state()
            moved = [(m["id"], m["original_parent_type"], m["messy_parent_type"]) for m in state["mess"]]
            print(f"demo: {len(state['objects'])} objects; moved out of place (evaluation view):")
            for oid, was, now in moved:
                print(f"  {oid}: {was} -> {now}")
        from tidee.server.render import render_room

        for p in render_room(room_type, seed, mess, out_dir, resolution=480):
            print(p)
        print(f"demo: wrote {out_dir}/views.png (what the agent saw) and the renders above")
        return 0
    finally:
        server.terminate()
        try:
            server.wait(timeout=15)
        except subprocess.TimeoutExpired:
            server.kill()
