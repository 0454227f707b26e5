"""The command line as a user meets it: refusals in one line, quiet start-up, Ctrl-C, the demo."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.support import REPO as SUPPORT_REPO
from tidee import cli
from tidee.launch import free_port
from tidee.server.splits import check_mess_index, messes_per_room

REPO = SUPPORT_REPO


def _tidee(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tidee.cli", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def test_messy_configuration_ranges_follow_the_splits() -> None:
    assert messes_per_room(200) == 5 and messes_per_room(100) == 10 and messes_per_room(3) == 100
    assert messes_per_room(10_500) == 100 and messes_per_room(5_000) is None
    check_mess_index(200, 4)
    check_mess_index(5_000, 10**6)  # outside every split: any index
    check_mess_index(200, None)  # the tidy room
    with pytest.raises(
        ValueError,
        match=r"mess_index 5 is out of range: test room seed 200 has messy "
        r"configurations 0-4",
    ):
        check_mess_index(200, 5)


@pytest.mark.parametrize(
    "args",
    [
        ["run", "--no-viewer", "--mess-index", "999999"],
        ["agent", "--seed", "101", "--mess-index", "10"],
        ["run", "--no-viewer", "--mess-index", "3", "--episodes", "3"],
        [
            "scene",
            "export",
            "--room-type",
            "Kitchen",
            "--seed",
            "200",
            "--mess-index",
            "5",
            "--out",
            "x.json",
        ],
    ],
)
def test_an_out_of_range_mess_index_is_refused_in_one_line_before_anything_starts(args: list[str]) -> None:
    t0 = time.monotonic()
    r = _tidee(*args)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "--mess-index" in lines[0] or "mess_index" in lines[0]
    assert "configurations 0-" in lines[0] and r.stdout == ""
    assert time.monotonic() - t0 < 30  # refused up front, not after starting a server


def test_one_flag_name_for_the_messy_configuration() -> None:
    parser = cli.build_parser()
    for argv in (
        ["run"],
        ["demo"],
        ["agent"],
        ["scene", "render", "--room-type", "Kitchen", "--seed", "1", "--out", "o"],
        ["scene", "export", "--room-type", "Kitchen", "--seed", "1", "--out", "o"],
        ["scene", "tour"],
    ):
        ns = parser.parse_args(argv)
        assert hasattr(ns, "mess_index") and not hasattr(ns, "mess"), argv


def test_demo_is_run_on_the_demo_room_and_make_demo_calls_it() -> None:
    parser = cli.build_parser()
    demo, run = vars(parser.parse_args(["demo"])), vars(parser.parse_args(["run"]))
    assert demo.pop("command") == "demo" and run.pop("command") == "run"
    demo.pop("func"), run.pop("func")  # two closures over the same config and command function
    assert demo == run and (demo["room_type"], demo["seed"]) == ("LivingRoom", 200)
    from tidee.agent.config import LiveRunConfig
    from tidee.options import from_args

    assert from_args(LiveRunConfig, parser.parse_args(["demo"])).agent.spec.mess_index == 0
    make_demo = (REPO / "Makefile").read_text().split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    assert "tidee demo" in make_demo


def test_the_simulator_starts_without_printing_anything() -> None:
    code = (
        "from tidee.server.world import World\n"
        "w = World(renderer='auto'); w.close()\n"
        "w = World(renderer='tiny'); w.close()\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == "" and r.stderr == "", (r.stdout, r.stderr)


def _no_process_in_group(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    return False


def test_ctrl_c_stops_server_agent_and_viewer_cleanly(tmp_path) -> None:
    """Ctrl-C in a terminal: SIGINT to the whole foreground group; every process ends, no traceback."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tidee.cli",
            "run",
            "--max-steps",
            "300",
            "--port",
            str(free_port()),
            "--log-dir",
            str(tmp_path),
            "--linger",
            "0",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    out: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            out.append(line)
            if line.startswith("agent: session"):  # the episode is under way
                break
        assert any(ln.startswith("agent: session") for ln in out), "".join(out)
        time.sleep(2.0)
        os.killpg(proc.pid, signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        out.append(rest)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = "".join(out)
    assert proc.returncode == 130, text
    assert "Traceback" not in text and "run: interrupted" in text, text
    assert "agent: stopped" in text or "tidee agent: interrupted" in text, text
    deadline = time.monotonic() + 10
    while not _no_process_in_group(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _no_process_in_group(proc.pid), "a child of tidee run outlived it"
