"""The deployment that compose.yaml declares, run for real on loopback.

compose.yaml runs a ``tidee router``, two ``tidee server``s, two ``tidee agent``s that choose their
server (``--server-id auto``) and a ``tidee viewer``. These tests run those commands as written
there, changed only as tests/support/deployment.py says: addresses to loopback, ports to free ones,
container paths to temporary folders, and the agents' episode size from the compose variables
TIDEE_RESOLUTION and TIDEE_MAX_STEPS (small here).

* The compose files' shape: services, images, dependencies, published ports (loopback by default),
  each command accepted by tidee's own parser; deploy/secure/compose.yaml is compose.yaml plus
  each role's TLS configuration.
* Failover (fast): the router and both servers from compose.yaml; two clients named as the
  compose agents play real short episodes through the agent's own failover loop
  (``tidee.agent.process._run_until_done``), a scripted walk standing in for the models. One
  server is killed (SIGKILL) mid-episode; its client ends the episode on the other.
* The whole deployment (slow): router, both servers, both agents (learned perception) and the
  viewer from compose.yaml. The agents take one server each; the server of the first is killed
  mid-episode; that agent says so in one line, moves to the other server and finishes its
  episode there; the other agent finishes undisturbed; the viewer serves its page, and both
  agents' telemetry crosses the router.
"""

from __future__ import annotations

import re
import signal
import subprocess
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.support.deployment import COMPOSE, SECURE_COMPOSE, interpolate, load_compose, loopback_argv
from tests.support.net import wait_until
from tests.support.processes import OutputLines, kill_group, start_tidee
from tidee.agent.config import AgentProcessConfig
from tidee.agent.process import _run_until_done
from tidee.cli import build_parser
from tidee.launch import RouterConfig, free_port
from tidee.options import from_args
from tidee.protocol import codec, keys
from tidee.protocol.client import SimClient
from tidee.protocol.discovery import ask_servers
from tidee.protocol.messages import Action, ActionName, AgentStatus, EpisodeSpec
from tidee.protocol.zenoh_config import open_session
from tidee.server.config import ServerConfig
from tidee.viewer.config import ViewerCommandConfig

SERVERS, AGENTS = ("server0", "server1"), ("agent0", "agent1")
SERVER_OF = {"sim0": "server0", "sim1": "server1"}  # compose's server ids and their services
ROUTER_PORT, VIEWER_PORT = 7447, 8080  # compose's; the tests stand free loopback ports in for them
CONFIGS: dict[str, type] = {
    "router": RouterConfig,
    "server": ServerConfig,
    "agent": AgentProcessConfig,
    "viewer": ViewerCommandConfig,
}
START_S = 90.0  # a process is up within this, on a loaded 2-core machine
SMALL = {"TIDEE_RESOLUTION": "64", "TIDEE_MAX_STEPS": "40"}  # the agents' episodes, in the slow test


@dataclass
class Loopback:
    """compose.yaml's commands with this test's stand-ins."""

    tmp: Path
    ports: dict[int, int] = field(
        default_factory=lambda: {ROUTER_PORT: free_port(), VIEWER_PORT: free_port()}
    )
    env: dict[str, str] = field(default_factory=dict)

    @property
    def router(self) -> str:
        return f"tcp/127.0.0.1:{self.ports[ROUTER_PORT]}"

    def argv(self, service: str, compose: Path = COMPOSE) -> list[str]:
        command = load_compose(compose)["services"][service]["command"]
        return loopback_argv(command, self.ports, {"/runs": self.tmp / "runs"}, self.env)


def _config(argv: list[str]) -> Any:
    """What tidee makes of ``argv``: the command's config, as ``tidee`` itself would build it."""
    return from_args(CONFIGS[argv[0]], build_parser().parse_args(argv))


# --- the compose files --------------------------------------------------------------------------


def test_compose_declares_a_router_two_servers_two_choosing_agents_and_a_viewer(tmp_path: Path) -> None:
    services = load_compose()["services"]
    assert set(services) == {"router", *SERVERS, *AGENTS, "viewer"}
    for name, service in services.items():
        assert service["build"] == "." and service["restart"] == "unless-stopped", name
        assert service["command"][0] == ("server" if name in SERVERS else name.rstrip("01")), name
    # Only the router and the viewer publish a port, each on the host's loopback unless told otherwise.
    published = {name: s["ports"] for name, s in services.items() if "ports" in s}
    assert published == {
        "router": [f"${{TIDEE_ROUTER_BIND:-127.0.0.1}}:{ROUTER_PORT}:{ROUTER_PORT}"],
        "viewer": [f"127.0.0.1:{VIEWER_PORT}:{VIEWER_PORT}"],
    }
    assert interpolate(published["router"][0], {}) == f"127.0.0.1:{ROUTER_PORT}:{ROUTER_PORT}"
    assert {name: s.get("depends_on") for name, s in services.items()} == {
        "router": None,
        **dict.fromkeys((*SERVERS, "viewer"), ["router"]),
        **dict.fromkeys(AGENTS, ["router", *SERVERS]),
    }
    # Inside compose every process dials the router by its service name, at the port it listens on.
    raw = {name: s["command"] for name, s in services.items()}
    assert raw["router"] == ["router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}"]
    for name in (*SERVERS, *AGENTS, "viewer"):
        assert raw[name][1:3] == ["--router", f"tcp/router:{ROUTER_PORT}"], name
    # Each command is one tidee accepts, and says what the deployment needs.
    here = Loopback(tmp_path)
    cfg = {name: _config(here.argv(name)) for name in services}
    assert cfg["router"].listen == (here.router,)
    assert [cfg[s].server_id for s in SERVERS] == ["sim0", "sim1"]
    assert all(cfg[s].router == here.router and cfg[s].renderer == "tiny" for s in SERVERS)
    for agent in AGENTS:
        a = cfg[agent]
        assert (a.server_id, a.session, a.serve, a.router) == ("auto", agent, True, here.router)
        assert a.log_dir == tmp_path / "runs" / agent, "each agent logs to its own folder of the volume"
        assert services[agent]["volumes"] == ["runs:/runs"]
        assert (a.spec.resolution, a.spec.max_steps) == (256, 1000), "compose's defaults"
    assert load_compose()["volumes"] == {"runs": None}
    viewer = cfg["viewer"].viewer
    assert (viewer.router, viewer.host, viewer.port) == (here.router, "127.0.0.1", here.ports[VIEWER_PORT])
    small = Loopback(tmp_path, env=SMALL)
    assert _config(small.argv("agent0")).spec.resolution == 64, "TIDEE_RESOLUTION reaches the agents"


ROLES = {"router": "router", **dict.fromkeys(SERVERS, "server"), **dict.fromkeys(AGENTS, "evaluator")}


def test_the_secure_compose_is_compose_yaml_over_tls_with_each_roles_certificate() -> None:
    plain, secure = load_compose()["services"], load_compose(SECURE_COMPOSE)["services"]
    assert set(secure) == set(plain)
    assert load_compose(SECURE_COMPOSE)["volumes"] == load_compose()["volumes"]
    for name, service in secure.items():
        role = ROLES.get(name, name)
        command = list(service["command"])
        at = command.index("--zenoh-config")
        assert command.pop(at + 1) == f"/secure/{role}.json5" and command.pop(at) == "--zenoh-config", name
        assert [arg.replace("tls/", "tcp/") for arg in command] == plain[name]["command"], name
        assert service["build"] == "../.." and service["restart"] == "unless-stopped", name
        assert service.get("ports") == plain[name].get("ports"), name
        assert service.get("depends_on") == plain[name].get("depends_on"), name
        mounts = [f"./{role}.json5:/secure/{role}.json5:ro"] + [
            f"./certs/{f}:/secure/certs/{f}:ro" for f in ("ca.pem", f"{role}.pem", f"{role}.key")
        ]
        assert service["volumes"] == mounts + plain[name].get("volumes", []), name
        assert (SECURE_COMPOSE.parent / f"{role}.json5").is_file(), name


# --- running it ---------------------------------------------------------------------------------


@dataclass
class Deployment:
    here: Loopback
    procs: dict[str, subprocess.Popen]
    out: dict[str, OutputLines]
    z: zenoh.Session  # this test's own client of the router

    def start(self, service: str) -> None:
        self.procs[service] = start_tidee(*self.here.argv(service), env=self.here.env)
        self.out[service] = OutputLines(self.procs[service])


@pytest.fixture
def deployment(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Deployment]:
    """compose.yaml's router and servers, up and answering; the rest is each test's to start."""
    here = Loopback(tmp_path, env=getattr(request, "param", {}))
    dep = Deployment(here, {}, {}, None)  # type: ignore[arg-type]
    try:
        for service in ("router", *SERVERS):
            dep.start(service)
            if service == "router":
                dep.out["router"].wait_for("router: ready", time.monotonic() + START_S)
        dep.z = open_session(False, router=here.router)
        assert wait_until(lambda: len(ask_servers(dep.z)) == 2, timeout=START_S), {
            s: dep.out[s].text for s in SERVERS
        }
        yield dep
    finally:
        for name in reversed(list(dep.procs)):  # agents and viewer first, the router last
            kill_group(dep.procs[name], signal.SIGTERM if name != "router" else signal.SIGINT)
        if dep.z is not None:
            dep.z.close()


class _Walk:
    """The agent's episode loop without its models: reset, then ``steps`` turns."""

    def __init__(self, client: SimClient, steps: int, on_step: Any) -> None:
        self.client, self.steps, self.on_step = client, steps, on_step
        self.servers: list[str] = []  # where each run of the episode went

    def run(self, spec: EpisodeSpec, evaluate: bool = False) -> int:
        self.servers.append(self.client.server_id)
        obs = self.client.reset(spec)
        for _ in range(self.steps):
            obs = self.client.step(Action(ActionName.RotateLeft))
            self.on_step(self, obs.step)
        return obs.step


@pytest.mark.timeout(300)
def test_a_killed_servers_client_finishes_its_episode_on_the_other(
    deployment: Deployment, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = EpisodeSpec(room_type="LivingRoom", seed=200, mess_index=0, resolution=32, max_steps=50)
    cfg = AgentProcessConfig(spec=spec, reconnect_timeout=60.0, score=False)
    clients: list[SimClient] = []
    for name in AGENTS:  # one after the other, as compose's agents start: the first counts once it chose
        assert wait_until(lambda: sum(i.sessions for i in ask_servers(deployment.z)) == len(clients), 10)
        clients.append(
            SimClient(
                router=deployment.here.router,
                server_id="auto",
                session=name,
                timeout=60.0,
                connect_timeout=30.0,
            )
        )
    assert clients[0].server_id != clients[1].server_id, "the second client took the other server"
    victim = clients[0].server_id
    steps = [{"last": 0}, {"last": 0}]
    killed = threading.Event()

    def on_step(walk: _Walk, step: int) -> None:
        k = walks.index(walk)
        steps[k]["last"] = step
        if k == 0 and step == 3 and not killed.is_set():  # mid-episode, no goodbye
            kill_group(deployment.procs[SERVER_OF[victim]])
            killed.set()

    walks = [_Walk(c, 10, on_step) for c in clients]
    results: dict[int, Any] = {}

    def play(k: int) -> None:
        try:
            results[k] = _run_until_done(walks[k], clients[k], spec, cfg, steps[k])  # type: ignore[arg-type]
        except BaseException as e:  # surfaced below
            results[k] = e

    threads = [threading.Thread(target=play, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=240)
    assert results == {0: 10, 1: 10}, results
    survivor = clients[1].server_id
    assert walks[0].servers == [victim, survivor] and walks[1].servers == [survivor]
    assert clients[0].server_id == survivor
    assert capsys.readouterr().out.splitlines() == [
        f"agent: server {victim!r} went away at step 3; moving to another live server "
        "(waiting up to 60 s for one with room)",
        f"agent: on server {survivor!r}; running LivingRoom seed 200 mess 0 again from the start",
    ]
    assert [i.server_id for i in ask_servers(deployment.z)] == [survivor]
    for c in clients:
        c.close()


def _status_steps(z: zenoh.Session, sessions: tuple[str, ...]) -> dict[str, list[int]]:
    """Every status step each agent publishes, as a viewer hears them through the router."""
    heard: dict[str, list[int]] = {s: [] for s in sessions}

    def on_sample(sample: zenoh.Sample) -> None:
        status = codec.decode(sample.payload.to_bytes(), expected=AgentStatus)
        heard[status.session].append(status.step)

    for s in sessions:
        z.declare_subscriber(keys.agent_telemetry(s, "status"), on_sample)
    return heard


_ON_SERVER = re.compile(r"^agent: session (\w+) on server '(\w+)' \(chosen")


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("deployment", [SMALL], indirect=True)
def test_the_whole_deployment_with_a_server_killed_mid_episode(
    deployment: Deployment, tmp_path: Path
) -> None:
    deadline = time.monotonic() + 780
    dep = deployment
    heard = _status_steps(dep.z, AGENTS)
    dep.start("viewer")
    dep.start("agent0")
    first = _ON_SERVER.match(dep.out["agent0"].wait_for("agent: session agent0 on server", deadline))
    dep.start("agent1")  # after the first chose: its client token already counts on that server
    second = _ON_SERVER.match(dep.out["agent1"].wait_for("agent: session agent1 on server", deadline))
    assert first and second, (dep.out["agent0"].text, dep.out["agent1"].text)
    victim, survivor = first.group(2), second.group(2)
    assert victim != survivor, "each agent took its own server"

    assert wait_until(lambda: max(heard["agent0"], default=0) >= 3, timeout=deadline - time.monotonic())
    kill_group(dep.procs[SERVER_OF[victim]])  # mid-episode, no goodbye

    out = dep.out["agent0"]
    gone = out.wait_for("went away", deadline)
    assert re.fullmatch(
        rf"agent: server '{victim}' went away at step \d+; moving to another live server "
        r"\(waiting up to 60 s for one with room\)",
        gone,
    ), gone
    moved = out.wait_for("again from the start", deadline)
    assert moved == f"agent: on server '{survivor}'; running LivingRoom seed 200 mess 0 again from the start"
    for agent in AGENTS:
        summary = dep.out[agent].wait_for("agent: LivingRoom seed 200 mess 0: moved", deadline)
        log = tmp_path / "runs" / agent / "LivingRoom_200_mess0"
        assert summary.endswith(f". Replay: tidee viewer --replay {log}"), summary
        assert (log / "summary.json").is_file(), f"{agent}: the finished run's log"
    assert all(heard[a] for a in AGENTS), "both agents' telemetry crossed the router"
    restarts = [b < a for a, b in zip(heard["agent0"], heard["agent0"][1:])]
    assert any(restarts), f"agent0's telemetry shows its episode starting over: {heard['agent0']}"

    url = dep.out["viewer"].wait_for("viewer: http://", deadline).split()[1]
    with urllib.request.urlopen(url, timeout=30) as page:
        assert page.status == 200

    for name in (*AGENTS, "viewer", SERVER_OF[survivor]):  # each ends cleanly when asked
        dep.procs[name].send_signal(signal.SIGTERM)
        assert dep.procs[name].wait(timeout=60) == 0, dep.out[name].text
    for name, lines in dep.out.items():
        assert "Traceback" not in lines.text, f"{name}:\n{lines.text}"
