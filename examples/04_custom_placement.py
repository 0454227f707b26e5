"""Your own placement policy: register it by name, then select it with ``AgentConfig.variant``.

A placement model answers "where does this object belong?" with receptacle classes,
best first; the agent tries them in that order (those it has already mapped first). The
toy below sends every object to the receptacle it has mapped nearest to where it found
the object: "tidy" as "put it on something close by". ``register_placement`` adds it to
the same registry as the paper's variants (``PLACEMENT_MODELS``), so configuration
validation, ``EpisodeRunner`` and the episode record all accept its name.

Run:  .venv/bin/python examples/04_custom_placement.py
"""

from __future__ import annotations

import numpy as np

from tidee.agent.classes import PLACEABLE_RECEPTACLES
from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.mapping.memory import ObjectMemory, TrackedObject
from tidee.agent.reasoning.placement import PLACEMENT_MODELS, register_placement
from tidee.agent.runner import EpisodeRunner
from tidee.protocol.messages import EpisodeSpec
from tidee.protocol.transport import InProcessTransport


@register_placement("NearestReceptacle")
class NearestReceptacle:
    name = "NearestReceptacle"

    def predict(self, obj: TrackedObject, memory: ObjectMemory, room_type: str) -> list[tuple[str, float]]:
        distance: dict[str, float] = {}  # receptacle class -> its nearest mapped instance (metres)
        for other in memory:
            if other.label in PLACEABLE_RECEPTACLES:
                d = float(np.linalg.norm(other.xy - obj.xy))
                distance[other.label] = min(d, distance.get(other.label, np.inf))
        weight = {label: 1.0 / (1.0 + d) for label, d in distance.items()}
        total = sum(weight.values())
        return sorted(((label, w / total) for label, w in weight.items()), key=lambda lw: -lw[1])


print("registered placement models:", ", ".join(PLACEMENT_MODELS))
# relation_stats: the statistics-based OOP detector, no learned model to load.
config = AgentConfig(
    variant="NearestReceptacle",
    perception="oracle",
    oop="relation_stats",
    policy=PolicyConfig(mapping_step_budget=25),
)
spec = EpisodeSpec(room_type="Bathroom", seed=200, mess_index=0, resolution=128, max_steps=60)
with InProcessTransport(renderer="tiny") as sim:
    result = EpisodeRunner(config, sim).run(spec, evaluate=True)

assert result.record is not None
print(f"{result.record['variant']}: {result.steps} steps, {result.objects_fixed} objects put away")
for o in result.record["objects"]:
    if o["picked"]:
        print(
            f"  picked {o['id']:<14} found on {o['messy_parent_type']:<10} "
            f"put on {o['final_parent_type']:<10} (tidy on {o['original_parent_type']})"
        )
