"""One short tidy episode end to end over Zenoh: server, agent, telemetry, log, evaluation record."""

from __future__ import annotations

import threading
import uuid

import pytest
import zenoh

from tests.support.net import free_endpoint, wait_until
from tidee.agent.config import AgentConfig, PolicyConfig
from tidee.agent.runner import LOG_EVERY, EpisodeRunner, format_summary
from tidee.agent.telemetry import TelemetryPublisher
from tidee.protocol import codec, keys
from tidee.protocol.client import SimClient
from tidee.protocol.episode_log import LogReader
from tidee.protocol.messages import Action, AgentCommand, EpisodeSpec
from tidee.protocol.zenoh_config import make_config
from tidee.server.service import ServerConfig, SimServer

# A small test room at a small resolution keeps this under a minute on 2 cores.
SPEC = EpisodeSpec(room_type="Bathroom", seed=200, mess_index=0, resolution=96, max_steps=260)


@pytest.fixture
def real_server():
    from tidee.server.episode import Episode

    cfg = ServerConfig(endpoint=free_endpoint(), server_id=f"t{uuid.uuid4().hex[:8]}", max_sessions=2)
    srv = SimServer(cfg, lambda: Episode(renderer="tiny")).start()
    yield srv
    srv.stop()


def test_tidy_episode_over_zenoh_with_telemetry_and_log(real_server: SimServer, tmp_path) -> None:
    endpoint, server_id = real_server.config.endpoint, real_server.config.server_id
    agent_z = zenoh.open(make_config(False, endpoint))
    viewer_z = zenoh.open(make_config(False, endpoint))
    session = "e2e"
    received: dict[str, list] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        _, kind = keys.parse_agent_telemetry(str(sample.key_expr))
        with lock:
            received.setdefault(kind, []).append(codec.decode(sample.payload.to_bytes()))

    sub = viewer_z.declare_subscriber(keys.agent_telemetry_wildcard(session), on_sample)
    cmd_pub = viewer_z.declare_publisher(keys.agent_cmd(session))
    try:
        client = SimClient(
            endpoint, server_id=server_id, session=session, zsession=agent_z, timeout=60, connect_timeout=30
        )
        publisher = TelemetryPublisher(agent_z, session)
        cfg = AgentConfig(
            variant="CommonMemory", perception="oracle", policy=PolicyConfig(mapping_step_budget=120)
        )
        runner = EpisodeRunner(cfg, client, session=session, publisher=publisher, log_dir=tmp_path)
        # A viewer's preference arrives mid-episode and is acknowledged.
        sent = {"done": False}

        def on_step(step: int) -> None:
            if step == 5 and not sent["done"]:
                cmd_pub.put(
                    codec.encode(
                        AgentCommand(
                            kind="preference", command_id="p1", text="I want my towel on the towel holder"
                        )
                    )
                )
                sent["done"] = True

        runner.on_step = on_step
        result = runner.run(SPEC, evaluate=True, episode_name="ep")
        client.step(Action("Done"))
        client.close()
        publisher.close()
    finally:
        sub.undeclare()
        cmd_pub.undeclare()
        viewer_z.close()
        agent_z.close()

    # The episode ran to a decision, not into the step cap's wall.
    assert 20 < result.steps <= SPEC.max_steps
    rec = result.record
    assert rec is not None and rec["perception"] == "oracle"
    moved = [o for o in rec["objects"] if o["moved"]]
    assert len(moved) >= 3
    # With oracle perception the agent finds and puts away at least one moved object.
    assert any(o["found"] for o in moved), moved
    assert result.objects_fixed >= 1
    for o in rec["objects"]:
        assert set(o) >= {
            "type",
            "variant",
            "moved",
            "found",
            "picked",
            "original_parent_type",
            "final_parent_type",
        }
    # Telemetry reached a subscriber: every step's status, and maps, memory, frames.
    assert wait_until(lambda: "ack" in received, timeout=5.0), sorted(received)
    assert {"status", "maps", "memory", "frame"} <= set(received)
    steps = [m.step for m in received["status"]]
    assert steps == sorted(steps) and len(steps) >= result.steps // 2
    assert received["ack"][0].command_id == "p1" and received["ack"][0].ok
    maps = received["maps"][-1]
    assert (maps.occupancy == 2).sum() > 100 and len(maps.points) > 100
    assert len(received["memory"][-1].objects) >= 5
    # The log replays: every status in order, and a summary with the record.
    log = LogReader(tmp_path / "ep")
    kinds = [k for k, _ in log.messages()]
    assert kinds.count("status") == result.steps + 1 and not log.truncated
    # Frames, maps and memory: every LOG_EVERY-th step and the last, however often viewers got them.
    bulky = [(k, m.step) for k, m in log.messages() if k in ("frame", "maps", "memory")]
    assert {k for k, _ in bulky} == {"frame", "maps", "memory"}
    assert all(step % LOG_EVERY == 0 or step == result.steps for _, step in bulky), bulky
    # every such step's frame: the log's cadence is its own, not the viewers' rate-limited one
    frame_steps = [step for k, step in bulky if k == "frame"]
    assert frame_steps == sorted({*range(0, result.steps + 1, LOG_EVERY), result.steps}), frame_steps
    summary = log.summary()
    assert summary is not None and summary["record"]["objects"] == rec["objects"]
    # The end-of-episode summary: counted from the record, sent to viewers, logged, and in summary.json.
    s = result.summary
    assert s is not None and s.moved == len(moved) and s.found == sum(o["found"] for o in moved)
    assert s.plausible is not None and 0 <= s.plausible <= s.moved and s.put_away == result.objects_fixed
    assert s.false_picks == sum(o["picked"] and not o["moved"] for o in rec["objects"])
    assert s.steps == result.steps and s.replay == f"tidee viewer --replay {tmp_path / 'ep'}"
    assert summary["summary"]["moved"] == s.moved and summary["summary"]["replay"] == s.replay
    assert wait_until(lambda: "summary" in received, timeout=5.0)
    assert received["summary"][-1].found == s.found and "summary" in kinds
    line = format_summary(s)
    assert (
        f"moved {s.moved}, found {s.found}, put away {s.put_away}, plausible {s.plausible}/{s.moved}" in line
    )
    assert line.endswith(f"Replay: {s.replay}")
    assert any(e["kind"] == "preference" for e in log.events())
