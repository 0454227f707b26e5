"""The agent's non-learned modules: oracle perception, statistics, OOP, placement, logs, telemetry."""

from __future__ import annotations

import numpy as np
import pytest

from tests.support.fixtures import spec, table_room
from tidee.agent.classes import CLASSES, PICKUPABLE, RECEPTACLES
from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.evaluation.tidy_eval import select_configs
from tidee.agent.mapping.memory import ObjectMemory
from tidee.agent.perception import make_perception
from tidee.agent.reasoning.oop import RelationStatsOOP, support_label
from tidee.agent.reasoning.placement import CommonMemory
from tidee.agent.reasoning.stats import PlacementStats, build_stats
from tidee.agent.telemetry import RateLimiter
from tidee.protocol.episode_log import LogReader, LogWriter
from tidee.protocol.messages import AgentStatus, ReceptaclePrediction
from tidee.protocol.vocab import ROOM_TYPES


def _memory_with(*entries: tuple[str, tuple, tuple, tuple]) -> ObjectMemory:
    mem = ObjectMemory()
    for label, c, lo, hi in entries:
        mem.add_or_merge(label, 1.0, np.array(c, float), np.array(lo, float), np.array(hi, float), step=0)
    return mem


def test_class_list_is_the_catalog_minus_structure() -> None:
    assert "Floor" not in CLASSES and "Wall" not in CLASSES
    assert {"Mug", "DiningTable", "Fridge", "AlarmClock"} <= set(CLASSES)
    assert "Mug" in PICKUPABLE and "DiningTable" in RECEPTACLES and "Mug" not in RECEPTACLES


def test_oracle_perception_sees_the_table_mug_and_fridge() -> None:
    from tidee.server.episode import Episode

    ep = Episode(renderer="tiny")
    try:
        obs = ep.load(table_room(), spec(128), agent_xy=(2.0, 0.6), yaw_deg=90.0, ground_truth=True)
        obs = ep.step(
            __import__("tidee.protocol.messages", fromlist=["Action"]).Action("LookDown"), ground_truth=True
        )
    finally:
        ep.close()
    dets = make_perception("oracle").detect(obs)
    by_label = {d.label: d for d in dets}
    assert {"DiningTable", "Mug"} <= set(by_label), sorted(by_label)
    mug, table = by_label["Mug"], by_label["DiningTable"]
    assert mug.source == "oracle" and mug.score == 1.0 and mug.mask.sum() > 0
    x0, y0, x1, y1 = mug.box
    assert 0 <= x0 < x1 <= 128 and 0 <= y0 < y1 <= 128
    # The mug stands on the table: its box is inside the table's columns and above its bottom.
    assert table.box[0] <= x0 and x1 <= table.box[2] and y1 <= table.box[3]
    # Without ground truth the oracle refuses, saying why.
    obs.ground_truth = None
    with pytest.raises(ValueError, match="ground truth"):
        make_perception("oracle").detect(obs)


def test_bad_agent_configurations_say_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="needs --perception learned"):
        AgentConfig(perception="oracle", oop="visual")
    with pytest.raises(ValueError, match="unknown variant"):
        AgentConfig(variant="Tidy")
    with pytest.raises(ValueError, match="oop_threshold"):
        PolicyConfig(oop_threshold=0.0)
    with pytest.raises(ValueError, match="needs --perception learned"):
        AgentConfig(perception="oracle", detection_threshold=0.2)
    with pytest.raises(ValueError, match=r"must be in \(0, 1\), got 1.5"):
        AgentConfig(detection_threshold=1.5)
    with pytest.raises(ValueError, match="learned perception only"):
        make_perception("oracle", threshold=0.2)
    with pytest.raises(ValueError, match="needs --perception learned"):
        AgentConfig(perception="oracle", detector="tiny+egl")
    with pytest.raises(ValueError, match="detector must be one of"):
        AgentConfig(detector="egl")
    with pytest.raises(ValueError, match="cannot run with --detector tiny\\+egl"):
        AgentConfig(detector="tiny+egl", oop="fused")
    with pytest.raises(ValueError, match="oracle perception has none"):
        make_perception("oracle", detector="tiny+egl")
    with pytest.raises(ValueError, match="unknown detector 'egl'"):
        make_perception("learned", detector="egl")


def test_shipped_statistics_come_from_training_rooms_only() -> None:
    stats = PlacementStats.load()
    assert stats.meta["split"] == "train"
    assert stats.meta["rooms"] >= 80
    # Mugs rest on tables and counters in training rooms, never on the floor.
    mug = stats.table("Mug", "Kitchen")
    assert sum(mug.values()) >= 5 and mug.get("Floor", 0) == 0
    with pytest.raises(ValueError, match="val/test"):
        build_stats([0, 200])


def test_relation_stats_oop_flags_a_mug_on_the_floor_not_on_the_counter() -> None:
    oop = RelationStatsOOP()
    mem = _memory_with(
        ("CounterTop", (1.0, 0.0, 0.45), (0.5, -0.3, 0.0), (1.5, 0.3, 0.9)),
        ("Mug", (1.0, 0.1, 0.95), (0.95, 0.05, 0.9), (1.05, 0.15, 1.0)),  # on the counter
        ("Mug", (-1.5, 1.0, 0.05), (-1.55, 0.95, 0.0), (-1.45, 1.05, 0.1)),  # on the floor
    )
    objs = list(mem)
    on_counter, on_floor = objs[1], objs[2]
    assert support_label(on_counter, objs) == "CounterTop"
    assert support_label(on_floor, objs) == "Floor"
    probs = oop.score_all([on_counter, on_floor], objs, "Kitchen")
    assert probs[on_counter.id] < 0.5
    assert probs[on_floor.id] == pytest.approx(1.0)


def test_common_memory_ranks_by_training_frequency_whatever_the_room() -> None:
    stats = PlacementStats.load()
    mem = _memory_with(("Mug", (0, 0, 0.05), (0, 0, 0), (0.1, 0.1, 0.1)))
    ranked = CommonMemory(stats).predict(next(iter(mem)), mem, "Bedroom")
    assert ranked and abs(sum(p for _, p in ranked) - 1.0) < 0.05
    table = stats.table("Mug")
    assert ranked[0][0] == max(table, key=table.get)
    assert [p for _, p in ranked] == sorted((p for _, p in ranked), reverse=True)
    # Category only: the same ranking in every room type.
    assert ranked == CommonMemory(stats).predict(next(iter(mem)), mem, "Kitchen")


def test_select_configs_spreads_over_room_types() -> None:
    configs = select_configs("test", 8)
    assert len(configs) == 8
    assert {c.room_type for c in configs} == set(ROOM_TYPES)
    assert all(c.seed in range(200, 205) for c in configs)
    assert len(select_configs("test", None)) == 100


def test_rate_limiter_keeps_to_its_rate() -> None:
    now = [0.0]
    lim = RateLimiter({"maps": 4.0}, clock=lambda: now[0])
    sent = 0
    for _ in range(100):  # 10 s at 10 Hz offered
        sent += lim.due("maps")
        now[0] += 0.1
    assert 38 <= sent <= 41


def _status(step: int) -> AgentStatus:
    return AgentStatus(
        session="s",
        step=step,
        phase="mapping",
        episode={"room_type": "Kitchen"},
        pose=(0.1 * step, 0.0, 0.0, 30.0),
        predictions=[ReceptaclePrediction("Desk", 0.5)],
        trajectory=np.zeros((step + 1, 2), np.float32),
    )


def test_episode_log_round_trip_and_truncated_tail(tmp_path) -> None:
    with LogWriter(tmp_path / "ep") as w:
        for step in range(5):
            w.message("status", _status(step))
            w.event(kind="action", step=step, action="MoveAhead")
    r = LogReader(tmp_path / "ep")
    msgs = list(r.messages())
    assert [m.step for _, m in msgs] == [0, 1, 2, 3, 4] and not r.truncated
    assert r.summary() is None  # never finished: no summary
    assert len(r.events()) == 5
    # A crash mid-write leaves a torn last record: the reader keeps the complete ones.
    path = tmp_path / "ep" / "telemetry.tlog"
    path.write_bytes(path.read_bytes()[:-7])
    r2 = LogReader(tmp_path / "ep")
    assert [m.step for _, m in r2.messages()] == [0, 1, 2, 3] and r2.truncated
    assert "truncated" in r2.corrupt_message


def test_a_rerun_into_the_same_log_directory_never_shows_the_earlier_runs_summary(tmp_path) -> None:
    with LogWriter(tmp_path / "ep") as w:
        w.finish({"steps": 5})
    assert LogReader(tmp_path / "ep").summary() == {"steps": 5}
    with LogWriter(tmp_path / "ep") as w:  # the rerun crashes before finishing
        w.message("status", _status(0))
    assert LogReader(tmp_path / "ep").summary() is None


def test_an_agent_plays_mess_0_unless_a_mess_or_a_rearrangement_is_asked_for(monkeypatch) -> None:
    import tidee.launch
    from tidee import cli
    from tidee.agent.config import AgentProcessConfig
    from tidee.options import from_args

    def spec(*argv: str):
        return from_args(AgentProcessConfig, cli.build_parser().parse_args(["agent", *argv])).spec

    assert (spec().mess_index, spec().rearrange_index) == (0, None)
    assert spec("--mess-index", "3").mess_index == 3
    assert (spec("--rearrange-index", "2").mess_index, spec("--rearrange-index", "2").rearrange_index) == (
        None,
        2,
    )
    with pytest.raises(ValueError, match="not both"):
        spec("--mess-index", "1", "--rearrange-index", "2")
    seen = {}
    monkeypatch.setattr(tidee.launch, "run_all", lambda cfg: seen.setdefault("cfg", cfg) and 0)
    args = cli.build_parser().parse_args(["run", "--rearrange-index", "1", "--unmatched", "commonsense"])
    args.func(args)  # a live rearrangement: the agent gets the index and no mess
    fwd = seen["cfg"].agent_args
    assert fwd[fwd.index("--rearrange-index") + 1] == "1" and "--mess-index" not in fwd
    assert fwd[fwd.index("--unmatched") + 1] == "commonsense"
    assert spec(*fwd).rearrange_index == 1


def test_tidee_run_forwards_agent_options(monkeypatch) -> None:
    import tidee.launch
    from tidee import cli
    from tidee.agent.config import AgentProcessConfig
    from tidee.options import from_args

    seen = {}
    monkeypatch.setattr(tidee.launch, "run_all", lambda cfg: seen.setdefault("cfg", cfg) and 0)
    args = cli.build_parser().parse_args(
        [
            "run",
            "--variant",
            "RandomReceptacle",
            "--pose-noise",
            "--seed",
            "201",
            "--linger",
            "0",
            "--detection-threshold",
            "0.2",
        ]
    )
    args.func(args)
    fwd = seen["cfg"].agent_args
    assert fwd[fwd.index("--variant") + 1] == "RandomReceptacle" and "--pose-noise" in fwd
    assert fwd[fwd.index("--seed") + 1] == "201" and "--server-id" not in fwd and "--depth-noise" not in fwd
    assert fwd[fwd.index("--detection-threshold") + 1] == "0.2"
    agent = from_args(AgentProcessConfig, cli.build_parser().parse_args(["agent", *fwd]))
    assert agent.agent.detection_threshold == 0.2 and agent.agent.variant == "RandomReceptacle"
    assert agent.spec.seed == 201 and agent.spec.pose_noise
    assert (
        cli.build_parser()
        .parse_args(["eval", "tidy", "--out", "x", "--detection-threshold", "0.25"])
        .detection_threshold
        == 0.25
    )


def test_the_agent_side_asks_for_the_renderer_its_detector_was_trained_on() -> None:
    import tidee.launch
    from tidee import cli
    from tidee.agent.perception import TRAINED_RENDERER

    assert tidee.launch.RunConfig().renderer == TRAINED_RENDERER
    parser = cli.build_parser()
    assert parser.parse_args(["run"]).renderer == TRAINED_RENDERER
    assert parser.parse_args(["eval", "tidy", "--out", "x"]).renderer == TRAINED_RENDERER
    assert parser.parse_args(["server"]).renderer == TRAINED_RENDERER  # a server started alone matches it too
    from tidee.server.service import ServerConfig

    assert ServerConfig().renderer == TRAINED_RENDERER


def test_a_preference_on_the_command_channel_retrains_the_language_oop_head() -> None:
    from tidee.agent.config import AgentConfig
    from tidee.agent.runner import EpisodeRunner

    runner = EpisodeRunner(AgentConfig(perception="oracle", oop="language"), transport=None)  # type: ignore[arg-type]
    clf = runner.oop.classifier
    para = ["The alarm clock is supported by the desk."]
    before = float(clf.predict(para)[0])
    ok, msg = runner._apply_preference("the alarm clock on the desk is out of place")
    after = float(clf.predict(para)[0])
    assert ok and "learned" in msg
    assert after > before and after >= 0.7, (before, after)
    ok, msg = runner._apply_preference("I want my zzz on the qqq")
    assert not ok and "could not use" in msg


def test_the_detection_threshold_reaches_the_learned_detector() -> None:
    from tidee.agent.perception import AGENT_THRESHOLD

    assert make_perception("learned").threshold == AGENT_THRESHOLD
    assert make_perception("learned", threshold=0.2).threshold == 0.2


def test_the_detector_option_picks_the_weights_the_agent_loads() -> None:
    from tidee.agent.learning import WEIGHTS_DIR
    from tidee.agent.runner import AgentModels

    default = make_perception("learned")
    both = make_perception("learned", detector="tiny+egl")
    assert default.path == WEIGHTS_DIR / "detector.pt"
    assert both.path == WEIGHTS_DIR / "detector_tiny_egl.pt"
    assert both.sha256 != default.sha256
    assert both.reclassifier_manifest["weights"] == "reclassifier_tiny_egl.pt"
    # its own fusion, chosen on the validation rooms for this pair
    assert (both.alpha, both.beta, both.gate) == tuple(
        both.reclassifier_manifest["metrics"]["fusion"][k] for k in ("alpha", "beta", "gate")
    )
    # agents with different detectors never share loaded models in a batch worker
    assert AgentModels.key_of(AgentConfig()) != AgentModels.key_of(AgentConfig(detector="tiny+egl"))
