"""One tidy episode of the paper's agent (TIDEE), in process, and its evaluation record.

``EpisodeRunner`` plays an episode against any transport: here ``InProcessTransport``
(the simulator in this process); a ``SimClient`` would play it against a `tidee server`.
The agent reads only its own observations; ``evaluate=True`` reads the server's
privileged state once the episode is over, to score it: for each object, whether the
mess-up moved it, whether the agent found it and picked it up, and where it ended.

A short episode (60 steps, 25 of them for mapping the room) in a small test room at a
low resolution keeps this to about half a minute on one core; ``tidee eval tidy`` runs
the full 1000-step episodes. Oracle perception (the segmentation mask) needs no detector.

Run:  .venv/bin/python examples/03_agent_episode.py
"""

from __future__ import annotations

from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.runner import EpisodeRunner
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.transport import InProcessTransport

config = AgentConfig(variant="TIDEE", perception="oracle", policy=PolicyConfig(mapping_step_budget=25))
spec = EpisodeSpec(room_type="Bathroom", seed=200, mess_index=0, resolution=128, max_steps=60)

with InProcessTransport(renderer="tiny") as sim:
    runner = EpisodeRunner(config, sim)
    result = runner.run(spec, evaluate=True)

print(
    f"{config.variant} (OOP detector {config.oop!r}): {result.steps} steps, {result.wall_s:.1f} s, "
    f"ended by {result.end_reason}, {result.objects_fixed} objects put away"
)
record = result.record
assert record is not None
print(f"{'object':<16} {'moved':>5} {'found':>5} {'picked':>6}  tidy on -> ended on")
for o in record["objects"]:
    if o["moved"] or o["found"] or o["picked"]:
        print(
            f"{o['id']:<16} {o['moved']!s:>5} {o['found']!s:>5} {o['picked']!s:>6}  "
            f"{o['original_parent_type']} -> {o['final_parent_type']}"
        )
moved = [o for o in record["objects"] if o["moved"]]
print(
    f"found {sum(o['found'] for o in moved)} of {len(moved)} moved objects, "
    f"picked up {sum(o['picked'] for o in record['objects'])} objects"
)
