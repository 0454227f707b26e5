"""Name -> factory registries: placement models (agent variants), OOP detectors, the gym env."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import pytest

from tidee.agent.config import AGENT_VARIANTS, AgentConfig
from tidee.agent.reasoning.oop import OOP_DETECTORS, RelationStatsOOP, make_oop, register_oop_detector
from tidee.agent.reasoning.placement import PLACEMENT_MODELS, CommonMemory, make_placement, register_placement


@pytest.fixture(autouse=True)
def restore_registries() -> Iterator[None]:
    """Registrations made by a test do not outlive it."""
    placement, oop = dict(PLACEMENT_MODELS), dict(OOP_DETECTORS)
    yield
    PLACEMENT_MODELS.clear()
    PLACEMENT_MODELS.update(placement)
    OOP_DETECTORS.clear()
    OOP_DETECTORS.update(oop)


class FirstInMemory:
    """Ranks the receptacle classes in memory in the order they were first seen."""

    name = "FirstInMemory"

    def predict(self, obj, memory, room_type):
        return [(o.label, 1.0) for o in memory if o.label != obj.label]


class NothingOutOfPlace:
    name = "nothing"

    def score_all(self, targets, objects, room_type):
        return {t.id: 0.0 for t in targets}


def test_the_paper_variants_and_detectors_are_registered_in_order() -> None:
    assert AGENT_VARIANTS == ("TIDEE", "WithoutMemex", "3DSmntMap2Place", "CommonMemory", "RandomReceptacle")
    assert tuple(PLACEMENT_MODELS) == AGENT_VARIANTS
    searching = [name for name, entry in PLACEMENT_MODELS.items() if entry.search]
    assert searching == ["TIDEE", "WithoutMemex", "3DSmntMap2Place"]
    assert tuple(OOP_DETECTORS) == ("relation_stats", "visual", "language", "fused")
    assert isinstance(make_placement("CommonMemory")[0], CommonMemory)
    assert isinstance(make_oop("relation_stats"), RelationStatsOOP)


def test_a_registered_placement_model_is_a_selectable_variant() -> None:
    with pytest.raises(ValueError, match="unknown variant 'FirstInMemory'"):
        AgentConfig(variant="FirstInMemory", perception="oracle")
    assert register_placement("FirstInMemory")(FirstInMemory) is FirstInMemory  # the decorator returns it
    cfg = AgentConfig(variant="FirstInMemory", perception="oracle")
    placement, searcher = make_placement(cfg.variant)
    assert isinstance(placement, FirstInMemory) and searcher is None
    assert "FirstInMemory" not in AGENT_VARIANTS  # the paper's variants stay the paper's


def test_a_registered_oop_detector_is_selectable() -> None:
    register_oop_detector("nothing")(NothingOutOfPlace)
    cfg = AgentConfig(variant="CommonMemory", perception="oracle", oop="nothing")
    assert isinstance(make_oop(cfg.oop), NothingOutOfPlace)


def test_the_runner_builds_registered_parts() -> None:
    from tidee.agent.runner import EpisodeRunner

    register_placement("FirstInMemory")(FirstInMemory)
    register_oop_detector("nothing")(NothingOutOfPlace)
    runner = EpisodeRunner(
        AgentConfig(variant="FirstInMemory", perception="oracle", oop="nothing"), transport=None
    )  # type: ignore[arg-type]
    assert isinstance(runner.placement, FirstInMemory) and runner.searcher is None
    assert isinstance(runner.oop, NothingOutOfPlace)


def test_unknown_names_list_the_registered_ones() -> None:
    registered = r"TIDEE, WithoutMemex, 3DSmntMap2Place, CommonMemory, RandomReceptacle"
    with pytest.raises(ValueError, match=rf"unknown variant 'Tidy'; registered: {registered} \(register_"):
        AgentConfig(variant="Tidy")
    with pytest.raises(ValueError, match="unknown variant 'Tidy'; registered: TIDEE"):
        make_placement("Tidy")
    with pytest.raises(ValueError, match="reference row"):
        AgentConfig(variant="MessyPlacement")
    with pytest.raises(
        ValueError,
        match=r"unknown OOP detector 'bert'; registered: relation_stats, visual, "
        r"language, fused \(register_oop_detector",
    ):
        AgentConfig(perception="oracle", oop="bert")
    with pytest.raises(ValueError, match="unknown OOP detector 'bert'"):
        make_oop("bert")


def test_a_name_is_registered_once() -> None:
    with pytest.raises(ValueError, match="placement model 'TIDEE' is already registered"):
        register_placement("TIDEE")(FirstInMemory)
    with pytest.raises(ValueError, match="OOP detector 'visual' is already registered"):
        register_oop_detector("visual")(NothingOutOfPlace)
    with pytest.raises(ValueError, match="'auto'"):
        register_oop_detector("auto")(NothingOutOfPlace)
    register_placement("FirstInMemory")(FirstInMemory)
    with pytest.raises(ValueError, match="already registered"):
        register_placement("FirstInMemory")(FirstInMemory)
    assert PLACEMENT_MODELS["TIDEE"].factory is not FirstInMemory  # a refused registration changes nothing


def test_import_tidee_registers_the_gym_env_without_torch_or_pybullet() -> None:
    code = (
        "import sys, gymnasium, tidee\n"
        "spec = gymnasium.spec('tidee/Tidy-v0')\n"
        "assert spec.entry_point == 'tidee.protocol.gym_env:TidyEnv', spec.entry_point\n"
        "heavy = [m for m in ('torch', 'pybullet', 'zenoh') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
        "print('ok')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr


def test_each_choice_of_a_set_is_one_table_that_also_builds_it() -> None:
    """The explorers and perception modes the CLI offers are exactly the ones with a factory."""
    from tidee.agent.config import EXPLORERS
    from tidee.agent.perception import PERCEPTION_MODES, PERCEPTIONS
    from tidee.agent.policy.tidy import EXPLORER_GOALS

    assert tuple(EXPLORER_GOALS) == EXPLORERS
    assert tuple(PERCEPTION_MODES) == PERCEPTIONS
    with pytest.raises(ValueError, match="unknown perception 'sonar'; choose one of"):
        from tidee.agent.perception import make_perception

        make_perception("sonar")
