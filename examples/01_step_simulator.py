"""Step the simulator over Zenoh: a `tidee server` on loopback and a `SimClient`.

Starts `tidee server` as a subprocess listening on a free loopback port, connects a
``SimClient`` to it, resets the first messy configuration of test room LivingRoom 200,
takes a few actions (one of which fails on purpose) and prints what came back. This is
the same wire an agent in another process (or on another machine) uses.

Run:  .venv/bin/python examples/01_step_simulator.py
"""

from __future__ import annotations

import subprocess
import sys

from tidee.launch import free_port
from tidee.protocol.client import SimClient
from tidee.protocol.messages import Action, ActionName, EpisodeSpec

endpoint = f"tcp/127.0.0.1:{free_port()}"
# "tiny" is PyBullet's CPU renderer: no GPU or display needed.
server = subprocess.Popen(
    [sys.executable, "-m", "tidee.cli", "server", "--endpoint", endpoint, "--renderer", "tiny"]
)
try:
    # The client waits until the server is visible on the network (it takes a few seconds to start).
    with SimClient(endpoint=endpoint, connect_timeout=60) as sim:
        obs = sim.reset(EpisodeSpec(room_type="LivingRoom", seed=200, mess_index=0, max_steps=50))
        print(
            f"reset: rgb {obs.rgb.shape} {obs.rgb.dtype}, depth {obs.depth.shape} {obs.depth.dtype}, "
            f"pose (x, y, yaw, pitch) = {tuple(round(v, 2) for v in obs.agent_pose)}, "
            f"steps left {obs.steps_left}"
        )

        actions = [
            Action(ActionName.RotateLeft),
            Action(ActionName.MoveAhead),
            Action(ActionName.LookDown),
            # Nothing is held, so putting down fails: the observation says why.
            Action(ActionName.PutObject, 0.5, 0.7),
        ]
        for action in actions:
            obs = sim.step(action)
            outcome = "ok" if obs.success else f"failed: {obs.error} ({obs.message})"
            print(
                f"step {obs.step}: {action.name.value:<10} {outcome:<45} "
                f"pose {tuple(round(v, 2) for v in obs.agent_pose)}"
            )

        scene = sim.state()  # privileged state, for evaluation only: what the mess-up moved
        print(f"the mess-up moved {len(scene.get('mess', []))} of {len(scene['objects'])} objects")
finally:
    server.terminate()
    server.wait(timeout=30)
