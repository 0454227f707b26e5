"""The shipped secure deployment (deploy/secure/) does what its README says, on loopback.

One module-wide deployment, made here from the shipped files: a CA and per-role certificates
(``deploy/secure/make_certs.sh`` into a temporary folder, beside copies of the role files), a
``tidee router`` with ``router.json5`` (mutual TLS, access control, default deny) and a real
``tidee server`` with ``server.json5``. An honest agent (the ``agent`` certificate) runs a real
episode through ``SimClient`` and publishes telemetry; hostile clients then try, each try bounded
by a timeout, what their certificate may not do, and each is refused while the honest one works:

* a certificate the CA did not sign, no certificate, or plain TCP: no connection at all;
* a ``guest`` certificate (the CA's, a common name no rule names) and the ``viewer`` one: cannot
  reset, step or close the honest session;
* ``agent``, ``viewer``, ``guest``: cannot read ``state`` (only ``evaluator`` can), not even
  through a wildcard query;
* ``agent``, ``evaluator``, ``guest``: hear no telemetry and no observations (only ``viewer`` does),
  not even through a ``**`` subscriber; ``guest`` and ``viewer`` cannot publish telemetry;
* ``agent``, ``evaluator``, ``guest``: cannot put agent commands (only ``viewer`` can);
* ``guest``, ``viewer``, ``agent``: cannot serve the sim (a queryable on the server's keys or its
  info key, a server liveliness token): only the server's replies reach clients;
* ``viewer``, ``guest``: cannot ask the servers how full they are (``--server-id auto``, which the
  honest agent uses); ``agent`` and ``evaluator`` can.

The router and the server run exactly as ``deploy/secure/compose.yaml`` declares them
(tests/support/deployment.py says how its addresses, ports and paths become this test's).
"""

from __future__ import annotations

import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from tests.support import REPO
from tests.support.deployment import SECURE_COMPOSE, load_compose, loopback_argv
from tests.support.net import wait_until
from tidee.agent.telemetry import TelemetryPublisher
from tidee.launch import free_port
from tidee.protocol import keys
from tidee.protocol.client import SimClient
from tidee.protocol.codec import decode, encode
from tidee.protocol.discovery import ask_servers
from tidee.protocol.messages import (
    Action,
    ActionName,
    AgentCommand,
    CloseReply,
    CloseRequest,
    EpisodeSpec,
    ResetRequest,
    StateRequest,
    StepRequest,
)
from tidee.protocol.zenoh_config import ZenohOpenError, open_session

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")

SECURE = REPO / "deploy" / "secure"
ROLES = ("server", "agent", "viewer", "evaluator", "guest")  # guest: signed by the CA, in no rule
SERVER_ID = "sim0"
START_S = 60.0  # a process (router, server) is up within this
REFUSED_S = 2.0  # a request nobody may answer: Zenoh's query timeout
HEAR_S = 1.0  # after the viewer heard something, how long the others get to hear it too
SPEC = EpisodeSpec(room_type="Kitchen", seed=200, mess_index=0, resolution=64, max_steps=50)


@dataclass
class Deployment:
    folder: Path  # the role files, certs/ beside them
    router: str  # the endpoint clients connect to
    sessions: list[zenoh.Session] = field(default_factory=list)

    def config(self, role: str) -> str:
        return str(self.folder / f"{role}.json5")

    def open(self, role: str) -> zenoh.Session:
        """A Zenoh session with ``role``'s certificate (closed at the end of the module)."""
        z = open_session(False, router=self.router, zenoh_config=self.config(role))
        self.sessions.append(z)
        return z


@dataclass
class Honest:
    client: SimClient
    publisher: TelemetryPublisher
    z: zenoh.Session
    steps: int = 0


def _make_certs(folder: Path, roles: tuple[str, ...]) -> None:
    subprocess.run(
        ["sh", str(SECURE / "make_certs.sh"), str(folder)],
        env={**os.environ, "ROLES": " ".join(roles)},
        check=True,
        capture_output=True,
        timeout=60,
    )


def _role_file(folder: Path, role: str, text: str) -> None:
    (folder / f"{role}.json5").write_text(text)


def _lines(proc: subprocess.Popen) -> queue.Queue[str]:
    """The process's stdout, line by line, read on a thread (so every wait can have a timeout)."""
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line.rstrip("\n"))

    threading.Thread(target=read, daemon=True).start()
    return lines


def _wait_for_line(lines: queue.Queue[str], prefix: str, timeout: float, anywhere: bool = False) -> str:
    """The first line starting with ``prefix`` (``anywhere``: holding it, as in a log line)."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=left)
        except queue.Empty:
            break
        if line.startswith(prefix) or (anywhere and prefix in line):
            return line
    raise AssertionError(f"no line {'holding' if anywhere else 'starting'} {prefix!r} within {timeout} s")


def _stop(proc: subprocess.Popen, sig: int, grace: float = 30.0) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)
        raise AssertionError(f"{proc.args[3]} did not stop within {grace} s of signal {sig}") from None


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    folder = tmp_path_factory.mktemp("secure")
    for f in SECURE.glob("*.json5"):
        shutil.copy(f, folder)
    _make_certs(folder / "certs", ROLES)
    agent_file = (folder / "agent.json5").read_text()
    _role_file(folder, "guest", agent_file.replace("certs/agent.", "certs/guest."))
    _make_certs(folder / "rogue", ("agent",))  # another CA's certificate, with the agent's name
    _role_file(folder, "rogue", agent_file.replace("certs/agent.", "rogue/agent."))
    no_cert = agent_file.replace('connect_private_key: "certs/agent.key",', "").replace(
        'connect_certificate: "certs/agent.pem",', ""
    )
    _role_file(folder, "no_cert", no_cert.replace("enable_mtls: true", "enable_mtls: false"))

    port = free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("TIDEE_ZENOH_CONFIG", None)
    tidee = [sys.executable, "-m", "tidee.cli"]
    # The router and a server exactly as deploy/secure/compose.yaml runs them, on loopback
    # (tests/support/deployment.py: the router's port, /secure -> this folder).
    services = load_compose(SECURE_COMPOSE)["services"]

    def command(service: str) -> list[str]:
        argv = services[service]["command"]
        return loopback_argv(argv, ports={7447: port}, paths={"/secure": folder}, service_host="localhost")

    router = subprocess.Popen(
        [*tidee, *command("router")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        cwd=REPO,
    )
    router_lines = _lines(router)
    server = None
    dep = Deployment(folder, f"tls/localhost:{port}")
    try:
        _wait_for_line(router_lines, "router: ready", START_S)
        assert command("server0") == [
            "server", "--router", dep.router, "--zenoh-config", dep.config("server"),
            "--renderer", "tiny", "--server-id", SERVER_ID,
        ]  # fmt: skip
        server = subprocess.Popen(
            [*tidee, *command("server0")],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
            cwd=REPO,
        )
        # up before any test: the teardown's SIGINT must meet a running server, not its imports
        _wait_for_line(_lines(server), f"tidee server {SERVER_ID!r} ready", START_S, anywhere=True)
        yield dep
    finally:
        for z in dep.sessions:
            z.close()
        if server is not None:
            assert _stop(server, signal.SIGINT) == 0
        assert _stop(router, signal.SIGTERM, grace=15) == 0, "the router ends cleanly on SIGTERM"
        _wait_for_line(router_lines, "router: stopped", 5)


@pytest.fixture(scope="module")
def honest(deployment: Deployment) -> Iterator[Honest]:
    """The honest agent: a real episode on the server, telemetry on one Zenoh session."""
    z = deployment.open("agent")
    client = SimClient(  # as the compose file's agents: it asks the servers and takes the one there is
        router=deployment.router,
        server_id="auto",
        zsession=z,
        timeout=60.0,
        connect_timeout=START_S,
        zenoh_config=deployment.config("agent"),
    )
    assert client.server_id == SERVER_ID
    publisher = TelemetryPublisher(z, client.session_id)
    agent = Honest(client, publisher, z)
    obs = client.reset(SPEC)
    assert obs.step == 0 and obs.rgb.shape == (64, 64, 3)
    yield agent
    publisher.close()
    client.close()


def _step(agent: Honest) -> None:
    obs = agent.client.step(Action(ActionName.RotateLeft))
    agent.steps += 1
    assert obs.step == agent.steps and obs.success, "the honest session kept its own steps"


def _answers(z: zenoh.Session, key: str, payload: bytes = b"") -> list[bytes]:
    """The ok replies to a query, waiting at most REFUSED_S."""
    return [
        r.ok.payload.to_bytes() for r in z.get(key, payload=payload, timeout=REFUSED_S) if r.ok is not None
    ]


# --- the honest path ------------------------------------------------------------------------


def test_the_honest_agent_runs_its_episode_and_the_evaluator_reads_its_state(
    deployment: Deployment, honest: Honest
) -> None:
    for _ in range(3):
        _step(honest)
    evaluator = deployment.open("evaluator")
    key = keys.sim_op(SERVER_ID, honest.client.session_id, "state")
    (reply,) = _answers(evaluator, key, encode(StateRequest(honest.client.session_id)))
    assert decode(reply).scene["objects"], "the evaluator reads the scene state"


# --- no connection without a certificate of the CA ------------------------------------------


@pytest.mark.parametrize("who", ["no_cert", "rogue", "plain_tcp"])
def test_a_client_without_a_certificate_of_the_ca_cannot_connect(deployment: Deployment, who: str) -> None:
    start = time.monotonic()
    with pytest.raises(ZenohOpenError, match="Zenoh could not connect"):
        if who == "plain_tcp":
            open_session(False, router=deployment.router.replace("tls/localhost", "tcp/127.0.0.1"))
        else:
            open_session(False, router=deployment.router, zenoh_config=deployment.config(who))
    assert time.monotonic() - start < 15


# --- refused: the sim's requests ------------------------------------------------------------


@pytest.mark.parametrize("role", ["guest", "viewer"])
def test_other_roles_cannot_reset_step_or_close_the_honest_session(
    deployment: Deployment, honest: Honest, role: str
) -> None:
    hostile = deployment.open(role)
    session = honest.client.session_id
    requests = {
        "step": StepRequest(session, Action(ActionName.MoveAhead)),
        "reset": ResetRequest(session, SPEC),
        "close": CloseRequest(session),
    }
    for op, request in requests.items():
        assert _answers(hostile, keys.sim_op(SERVER_ID, session, op), encode(request)) == [], op
    with pytest.raises((PermissionError, TimeoutError)):  # SimClient with the honest id: its reset
        SimClient(
            router=deployment.router,
            server_id=SERVER_ID,
            session=session,
            timeout=REFUSED_S,
            connect_timeout=REFUSED_S,
            zenoh_config=deployment.config(role),
        ).reset(SPEC)
    _step(honest)  # the episode goes on where it was: not reset, not stepped, not closed


def test_only_the_evaluator_reads_the_scene_state(deployment: Deployment, honest: Honest) -> None:
    session = honest.client.session_id
    request = encode(StateRequest(session))
    with pytest.raises((PermissionError, TimeoutError)):
        honest.client.state()
    for role in ("agent", "viewer", "guest"):
        z = deployment.open(role)
        assert _answers(z, keys.sim_op(SERVER_ID, session, "state"), request) == [], role
        for wildcard in (f"tidee/sim/{SERVER_ID}/session/{session}/*", "tidee/**"):
            assert _answers(z, wildcard, request) == [], f"{role}: {wildcard}"
    evaluator = deployment.open("evaluator")
    assert len(_answers(evaluator, keys.sim_op(SERVER_ID, session, "state"), request)) == 1
    _step(honest)


def test_agents_may_ask_the_servers_how_full_they_are_and_no_one_else(
    deployment: Deployment, honest: Honest
) -> None:
    session = honest.client.session_id
    for role in ("agent", "evaluator"):
        (info,) = ask_servers(deployment.open(role), session, timeout=REFUSED_S)
        assert info.server_id == SERVER_ID and info.sessions >= 1 and info.holds_session, role
    for role in ("viewer", "guest"):
        assert ask_servers(deployment.open(role), session, timeout=REFUSED_S) == [], role


# --- refused: telemetry, observations, commands ---------------------------------------------


def test_only_viewers_hear_telemetry_and_observations(deployment: Deployment, honest: Honest) -> None:
    session = honest.client.session_id
    heard: dict[str, list[tuple[str, bytes]]] = {}
    for role in ("viewer", "agent", "evaluator", "guest"):
        z = deployment.open(role)
        got = heard.setdefault(role, [])
        for key in (keys.agent_telemetry_wildcard(), keys.observations_wildcard(), "**"):
            z.declare_subscriber(key, lambda s, got=got: got.append((str(s.key_expr), s.payload.to_bytes())))
    forgers = {role: deployment.open(role) for role in ("guest", "viewer")}  # (agent roles may: limitations)
    time.sleep(0.5)  # the subscribers' declarations reach the publishers
    for role, z in forgers.items():  # pretend to be the agent: only agent roles publish telemetry
        z.put(keys.agent_telemetry(session, "ack"), f"forged by {role}".encode())
    honest.publisher.ack("c0", "pause", True, "the honest agent's telemetry")
    _step(honest)  # the server publishes the observation to viewers
    telemetry, observation = keys.agent_telemetry(session, "ack"), keys.observations(SERVER_ID, session)
    viewer = heard["viewer"]
    assert wait_until(lambda: {telemetry, observation} <= {k for k, _ in viewer}, timeout=10), viewer
    time.sleep(HEAR_S)
    assert [p for k, p in viewer if k == telemetry and b"forged" in p] == [], (
        "forged telemetry reached a viewer"
    )
    for role in ("agent", "evaluator", "guest"):
        assert heard[role] == [], f"{role} heard {heard[role]}"


def test_only_viewers_command_agents(deployment: Deployment, honest: Honest) -> None:
    session = honest.client.session_id
    honest.publisher.commands()  # start from an empty inbox
    for role in ("guest", "agent", "evaluator"):
        deployment.open(role).put(keys.agent_cmd(session), encode(AgentCommand("pause", f"from-{role}")))
    deployment.open("viewer").put(keys.agent_cmd(session), encode(AgentCommand("pause", "from-viewer")))
    received: list = []
    assert wait_until(lambda: received.extend(honest.publisher.commands()) or bool(received), timeout=10)
    time.sleep(HEAR_S)
    received += honest.publisher.commands()
    assert [c.command_id for c in received] == ["from-viewer"]


# --- refused: serving the sim ---------------------------------------------------------------


def test_only_the_server_serves_the_sim(deployment: Deployment, honest: Honest) -> None:
    fakes = []
    for role in ("guest", "viewer", "agent"):
        z = deployment.open(role)
        for server_id in (SERVER_ID, "evil"):
            fakes.append(
                z.declare_queryable(keys.sim_op_wildcard(server_id), lambda q: q.reply(q.key_expr, b"FAKE"))
            )
        fakes.append(z.liveliness().declare_token(keys.alive_server("evil")))
        fakes.append(z.declare_queryable(keys.server_info("evil"), lambda q: q.reply(q.key_expr, b"FAKE")))
    time.sleep(0.5)
    evaluator = deployment.open("evaluator")
    assert [i.server_id for i in ask_servers(evaluator, timeout=REFUSED_S)] == [SERVER_ID]
    probe = f"probe-{os.getpid()}"  # closing a session the server does not hold changes nothing
    replies = _answers(evaluator, keys.sim_op(SERVER_ID, probe, "close"), encode(CloseRequest(probe)))
    assert [decode(r) for r in replies] == [CloseReply(probe, closed=False)], "one reply: the server's"
    assert _answers(evaluator, keys.sim_op("evil", probe, "close"), encode(CloseRequest(probe))) == []
    with pytest.raises(TimeoutError, match="no tidee server 'evil'"):
        SimClient(
            router=deployment.router,
            server_id="evil",
            connect_timeout=REFUSED_S,
            zenoh_config=deployment.config("evaluator"),
        )
    _step(honest)  # still answered by the real server
