"""Every bad argument or environment ends in one line naming what was wrong, a non-zero exit and no traceback.

Each case runs ``tidee`` as a user would (a subprocess, loopback only). ``{busy}`` is a port something
already listens on, ``{free}`` one nothing listens on, ``{tmp}`` a scratch directory.
"""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest

from tests.support import REPO as SUPPORT_REPO
from tidee import launch
from tidee.launch import free_port

REPO = SUPPORT_REPO
ROOM = ["--room-type", "Kitchen", "--seed", "1"]

# (argv, a substring the message must contain)
CASES: list[tuple[list[str], str]] = [
    # the command line itself
    (["nosuchcommand"], "invalid choice: 'nosuchcommand'"),
    (["server", "--no-such-flag"], "unrecognized arguments: --no-such-flag"),
    (["server", "--renderer", "vulkan"], "argument --renderer: invalid choice"),
    (["agent", "--room-type", "Garage"], "argument --room-type: invalid choice"),
    (["eval", "tidy"], "--out"),  # a required flag left out
    # numbers out of range
    (["server", "--max-sessions", "0"], "argument --max-sessions: expected an integer >= 1"),
    (["server", "--processes", "-1"], "argument --processes: expected an integer >= 0"),
    (["agent", "--seed", "-1"], "argument --seed: expected an integer >= 0"),
    (["agent", "--seed", "abc"], "argument --seed: expected an integer >= 0, got 'abc'"),
    (["agent", "--mess-index", "-1"], "argument --mess-index"),
    (["agent", "--seed", "200", "--mess-index", "7"], "configurations 0-4"),
    (["agent", "--resolution", "5000"], "argument --resolution: expected an image side in pixels in 16-1024"),
    (["agent", "--max-steps", "0"], "argument --max-steps"),
    (["agent", "--threads", "-2"], "argument --threads"),
    (["agent", "--connect-timeout", "-1"], "argument --connect-timeout"),
    (["run", "--episodes", "0"], "argument --episodes"),
    (["run", "--linger", "-1"], "argument --linger"),
    (["scene", "render", *ROOM, "--out", "{tmp}/r", "--resolution", "0"], "argument --resolution"),
    (["scene", "render", *ROOM, "--out", "{tmp}/r", "--resolution", "5000"], "argument --resolution"),
    (
        ["scene", "export", "--room-type", "Kitchen", "--seed", "-3", "--out", "{tmp}/x.json"],
        "argument --seed",
    ),
    (["eval", "tidy", "--out", "{tmp}/o", "--workers", "0"], "argument --workers"),
    (["eval", "tidy", "--out", "{tmp}/o", "--episodes", "-5"], "argument --episodes"),
    (["bench", "sim", "--steps", "-1"], "argument --steps"),
    (["gen", "cache", "--workers", "0"], "argument --workers"),
    (["gen", "stats", "--seeds", "a-b"], "--seeds 'a-b'"),
    (["viewer", "--rate", "0"], "argument --rate"),
    (["viewer", "--window", "10x10"], "--window 10x10"),
    # ports
    (["run", "--port", "0"], "argument --port: expected a TCP port in 1-65535, got 0"),
    (["run", "--port", "70000"], "argument --port: expected a TCP port in 1-65535, got 70000"),
    (["run", "--port", "99999"], "argument --port"),
    (["viewer", "--port", "-1"], "argument --port"),
    (["viewer", "--port", "70000"], "argument --port"),
    (["viewer", "--port", "{busy}"], "port {busy} on 127.0.0.1 is already in use"),
    (["run", "--port", "{busy}"], "port {busy} on 127.0.0.1 is already in use"),
    (["server", "--endpoint", "tcp/127.0.0.1:{busy}"], "--endpoint tcp/127.0.0.1:{busy}: port {busy}"),
    # hosts
    (["viewer", "--host", "256.1.1.1"], "argument --host: '256.1.1.1' is not an IPv4 address"),
    (["viewer", "--host", "no such host"], "argument --host"),
    (["run", "--host", "256.1.1.1"], "argument --host"),
    (["viewer", "--host", "192.0.2.1", "--port", "0"], "cannot listen on 192.0.2.1"),  # not this machine's
    # Zenoh endpoints
    (
        ["server", "--endpoint", "notanendpoint"],
        "argument --endpoint: 'notanendpoint' is not a Zenoh endpoint",
    ),
    (["server", "--endpoint", "tcp/127.0.0.1:99999"], "port 99999 is not in 1-65535"),
    (
        ["agent", "--endpoint", "tcp/127.0.0.1"],
        "argument --endpoint: 'tcp/127.0.0.1': the address must be HOST:PORT",
    ),
    (["viewer", "--endpoint", "smoke/127.0.0.1:7447"], "unknown protocol 'smoke'"),
    (["agent", "--router", "tcp/256.1.1.1:7447"], "argument --router"),
    (
        ["server", "--router", "tcp/127.0.0.1:{free}"],
        "--router tcp/127.0.0.1:{free}: Zenoh could not connect",
    ),
    (["viewer", "--router", "tcp/127.0.0.1:{free}", "--port", "0"], "--router tcp/127.0.0.1:{free}"),
    (["agent", "--router", "tcp/127.0.0.1:{free}"], "--router tcp/127.0.0.1:{free}: Zenoh could not connect"),
    (
        ["agent", "--router", "tcp/127.0.0.1:{free}", "--server-id", "auto"],
        "--router tcp/127.0.0.1:{free}: Zenoh could not connect to it",
    ),
    (
        ["agent", "--endpoint", "tcp/127.0.0.1:{free}", "--server-id", "auto", "--connect-timeout", "1"],
        "no live tidee server at tcp/127.0.0.1:{free} within 1 s (start one with: tidee server --endpoint",
    ),
    (
        ["agent", "--server-id", "no.dots"],
        "server_id must be 1-128 characters of [A-Za-z0-9_-], got 'no.dots'",
    ),
    (["agent", "--session", "a/b"], "session must be 1-128 characters of [A-Za-z0-9_-], got 'a/b'"),
    (["server", "--server-id", "auto"], "server_id 'auto' is reserved"),
    (
        ["agent", "--endpoint", "tcp/127.0.0.1:{free}", "--connect-timeout", "1"],
        "no tidee server 'sim0' at tcp/127.0.0.1:{free} within 1 s (start one with: tidee server --endpoint",
    ),
    # paths
    (
        ["eval", "tidy", "--out", "/dev/null/x"],
        "argument --out: cannot create '/dev/null/x': /dev/null is a file",
    ),
    (["scene", "export", *ROOM, "--out", "{tmp}/a_file/x.json"], "argument --out"),
    (["agent", "--log-dir", "/dev/null/runs"], "argument --log-dir"),
    (["viewer", "--replay", "{tmp}/no_such_log"], "--replay"),
    (["viewer", "--screenshot", "/dev/null/x.png", "--replay", "{tmp}"], "argument --screenshot"),
    (["eval", "tidy-merge", "--from", "{tmp}/no_such_report", "--out", "{tmp}/m"], "no_such_report"),
    (
        ["eval", "compare", "--before", "{tmp}/no_such_report", "--after", "{tmp}", "--out", "{tmp}/c"],
        "tidee eval compare: error: {tmp}/no_such_report: no such report directory or file",
    ),
    # Zenoh config files: missing, unparsable, refused by Zenoh when read or when used
    (["server", "--zenoh-config", "{tmp}/no_such.json5"], "--zenoh-config {tmp}/no_such.json5: no such file"),
    (
        ["agent", "--zenoh-config", "{tmp}/bad.json5"],
        "--zenoh-config {tmp}/bad.json5: Zenoh cannot read it: line 1",
    ),
    (["viewer", "--port", "0", "--zenoh-config", "{tmp}/unknown_key.json5"], "unknown field `nosuchkey`"),
    (["router", "--zenoh-config", "{tmp}/a_file"], "--zenoh-config {tmp}/a_file: Zenoh cannot read it"),
    (["run", "--no-viewer", "--zenoh-config", "{tmp}/no_such.json5"], "{tmp}/no_such.json5: no such file"),
    (
        ["server", "--router", "tls/127.0.0.1:{free}", "--zenoh-config", "{tmp}/not_pem.json5"],
        "transport/link/tls/root_ca_certificate: '{tmp}/a_file' is not a PEM file",
    ),
    (
        ["router", "--listen", "tcp/127.0.0.1:{free}", "--zenoh-config", "{tmp}/tls_only.json5"],
        "Zenoh could not start the router: Unsupported protocol: tcp",
    ),
    (
        ["agent", "--router", "tls/127.0.0.1:{free}", "--zenoh-config", "{tmp}/tls_only.json5"],
        "--router tls/127.0.0.1:{free} with --zenoh-config {tmp}/tls_only.json5: Zenoh could not connect",
    ),
    (["router", "--listen", "tcp/127.0.0.1:{busy}"], "--listen tcp/127.0.0.1:{busy}: port {busy}"),
    (
        ["router", "--listen", "tcp/127.0.0.1"],
        "argument --listen: 'tcp/127.0.0.1': the address must be HOST:PORT",
    ),
]


CONCURRENT = 3  # invocations at a time: most of each is Python start-up


@pytest.fixture(scope="module")
def places(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    tmp = tmp_path_factory.mktemp("cli_errors")
    (tmp / "a_file").write_text("not a directory")
    (tmp / "bad.json5").write_text('{ mode: "client" scouting: }')
    (tmp / "unknown_key.json5").write_text("{ nosuchkey: 1 }")
    (tmp / "not_pem.json5").write_text('{ transport: { link: { tls: { root_ca_certificate: "a_file" } } } }')
    (tmp / "tls_only.json5").write_text('{ transport: { link: { protocols: ["tls"] } } }')
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        yield {"busy": str(busy.getsockname()[1]), "free": str(free_port()), "tmp": str(tmp)}


@pytest.fixture(scope="module")
def results(places: dict[str, str]) -> dict[int, subprocess.CompletedProcess]:
    """Every case run once, a few at a time (the table would take minutes one after another)."""
    with ThreadPoolExecutor(CONCURRENT) as pool:
        futures = {
            i: pool.submit(_tidee, [a.format(**places) for a in argv]) for i, (argv, _) in enumerate(CASES)
        }
        return {i: f.result() for i, f in futures.items()}


def _tidee(argv: list[str], timeout: float = 30) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tidee.cli", *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


@pytest.mark.parametrize("case", range(len(CASES)), ids=[" ".join(a) for a, _ in CASES])
def test_a_bad_invocation_is_refused_in_one_line(
    case: int, places: dict[str, str], results: dict[int, subprocess.CompletedProcess]
) -> None:
    expected = CASES[case][1]
    r = results[case]
    output = r.stdout + r.stderr
    assert r.returncode != 0, output
    assert "Traceback" not in output, output
    errors = [ln for ln in r.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1, output
    assert expected.format(**places) in errors[0], output


@pytest.mark.parametrize("server_id", ["sim0", "auto"])
def test_an_agent_whose_router_is_unreachable_says_so_within_10_s(
    places: dict[str, str], server_id: str
) -> None:
    router = f"tcp/127.0.0.1:{places['free']}"
    start = time.monotonic()
    r = _tidee(["agent", "--router", router, "--server-id", server_id])
    took = time.monotonic() - start
    assert r.returncode == 1 and "Traceback" not in r.stderr + r.stdout, r.stderr
    assert r.stderr.startswith(f"agent: error: --router {router}: Zenoh could not connect to it: ")
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert took < 10, f"{took:.1f} s"


def test_the_table_covers_at_least_thirty_cases() -> None:
    assert len(CASES) >= 30


def test_a_bad_zenoh_config_from_the_environment_names_the_variable(places: dict[str, str]) -> None:
    env = {**os.environ, "TIDEE_ZENOH_CONFIG": f"{places['tmp']}/no_such.json5"}
    r = subprocess.run(
        [sys.executable, "-m", "tidee.cli", "agent"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
        stdin=subprocess.DEVNULL,
        env=env,
    )
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip() == f"tidee: error: TIDEE_ZENOH_CONFIG={places['tmp']}/no_such.json5: no such file"


def test_tidee_run_stops_when_the_server_dies_at_start_up(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """A child that exits while the agent runs ends ``tidee run`` at once, non-zero, naming the child."""

    def fake(*args: str) -> list[str]:
        exit_code = 3 if args[0] == "server" else None  # the server dies; the agent would wait for it
        code = (
            f"import sys; sys.exit({exit_code})"
            if exit_code
            else "import signal, time; signal.signal(signal.SIGINT, signal.SIG_DFL); time.sleep(30)"
        )
        return [sys.executable, "-c", code]

    monkeypatch.setattr(launch, "tidee_command", fake)
    rc = launch.run_all(launch.RunConfig(viewer=False, linger=0))
    assert rc == 1
    assert "run: error: the server exited with status 3" in capsys.readouterr().err


def test_a_negative_start_seed_is_an_invalid_field_naming_it() -> None:
    from tidee.protocol.codec import ProtocolError, decode, encode
    from tidee.protocol.messages import EpisodeSpec, ErrorCode, ResetRequest

    with pytest.raises(ValueError, match="start_seed must be >= 0"):
        EpisodeSpec(start_seed=-1)
    prefix = struct.Struct("<4sHI")  # magic, version, header length (protocol/README.md)
    frame = encode(ResetRequest("s1", EpisodeSpec(start_seed=1)))
    magic, version, header_len = prefix.unpack_from(frame)
    header = json.loads(frame[prefix.size : prefix.size + header_len])
    header["fields"]["spec"]["start_seed"] = -1
    raw = json.dumps(header).encode()
    bad = prefix.pack(magic, version, len(raw)) + raw + frame[prefix.size + header_len :]
    with pytest.raises(ProtocolError) as info:
        decode(bad)
    assert info.value.code == ErrorCode.invalid_field and "start_seed must be >= 0" in info.value.message
