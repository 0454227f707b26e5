"""Your own out-of-place (OOP) detector: register it by name, select it with ``AgentConfig.oop``.

An OOP detector scores the objects the agent tracks with P(out of place); the agent
picks up those at or above ``PolicyConfig.oop_threshold`` (0.5). The toy below says that
whatever lies on the floor is out of place, and nothing else is. It reads what each
object rests on from the agent's own 3D estimates (``support_labels``), as the shipped
statistics-based detector does. ``register_oop_detector`` adds it to ``OOP_DETECTORS``,
the table configuration validation and ``EpisodeRunner`` read.

Run:  .venv/bin/python examples/05_custom_oop_detector.py
"""

from __future__ import annotations

from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.mapping.memory import TrackedObject
from tidee.agent.reasoning.oop import OOP_DETECTORS, register_oop_detector, support_labels
from tidee.agent.runner import EpisodeRunner
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.transport import InProcessTransport


@register_oop_detector("on_the_floor")
class OnTheFloor:
    name = "on_the_floor"

    def score_all(
        self, targets: list[TrackedObject], objects: list[TrackedObject], room_type: str
    ) -> dict[int, float]:
        support = support_labels(targets, objects)
        return {t.id: 0.9 if support[t.id] == "Floor" else 0.1 for t in targets}


print("registered OOP detectors:", ", ".join(OOP_DETECTORS))
config = AgentConfig(
    variant="CommonMemory",
    perception="oracle",
    oop="on_the_floor",
    policy=PolicyConfig(mapping_step_budget=25),
)
spec = EpisodeSpec(room_type="Bathroom", seed=200, mess_index=0, resolution=128, max_steps=60)
with InProcessTransport(renderer="tiny") as sim:
    result = EpisodeRunner(config, sim).run(spec, evaluate=True)

record = result.record
assert record is not None
print(f"OOP detector {record['oop']}: {result.steps} steps, {result.objects_fixed} objects put away")
for o in record["objects"]:
    if o["moved"] or o["found"] or o["picked"]:
        print(
            f"  {o['id']:<14} lay on {o['messy_parent_type']:<8} moved={o['moved']!s:<5} "
            f"found={o['found']!s:<5} picked={o['picked']}"
        )
