"""tidee.batch.run_jobs: local processes and Ray actors give the same records in job order; resume
skips finished jobs; a worker that dies mid-job is replaced and its job retried; torn lines in
the records file are ignored; ``tidee eval tidy --backend ray`` (local Ray and a two-node
cluster on loopback) matches the local backend."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tidee.batch import (
    WorkerLost,
    files_intact,
    npz_bytes,
    read_records,
    record_line,
    run_jobs,
    worker_state,
    write_files,
)

REPO = Path(__file__).resolve().parents[2]
TIDEE = str(Path(sys.executable).with_name("tidee"))
RAY = str(Path(sys.executable).with_name("ray"))
needs_ray = pytest.mark.skipif(
    shutil.which(RAY) is None, reason="Ray not installed (pip install -e .[cluster])"
)


@dataclass(frozen=True)
class Sq:
    """A job for a trivial ``run_one``: no simulator."""

    n: int
    calls: str | None = None  # a folder: each call leaves a file there (calls counted across processes)
    die_once: str | None = None  # a marker file: the first attempt creates it and kills its worker
    die_always: bool = False
    fail: bool = False

    def key(self) -> str:
        return f"sq/{self.n}"


def square(job: Sq) -> dict[str, Any]:
    if job.calls:
        Path(job.calls, f"{job.n}-{os.getpid()}-{time.time_ns()}").touch()
    if job.die_always:
        os._exit(3)
    if job.die_once and not os.path.exists(job.die_once):
        Path(job.die_once).touch()
        os._exit(3)
    if job.fail:
        raise ValueError(f"job {job.n} refuses")
    state = worker_state()
    state["jobs"] = state.get("jobs", 0) + 1  # the context lives across a worker's jobs
    return {"n": job.n, "square": job.n * job.n, "wall_s": time.time()}


def _run(jobs: list[Sq], **kw: Any) -> list[dict[str, Any]]:
    kw.setdefault("workers", 2)
    return run_jobs(jobs, square, renderer=None, progress=False, **kw)


def _calls(folder: Path) -> list[int]:
    return sorted(int(p.name.split("-")[0]) for p in folder.iterdir())


def _same(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> bool:
    strip = lambda rs: [{k: v for k, v in r.items() if k not in ("wall_s", "timing_ms")} for r in rs]
    return strip(a) == strip(b)


# --- the runner with a trivial run_one -------------------------------------------------------


def test_records_come_back_in_job_order_with_retries_and_the_same_for_any_worker_count() -> None:
    jobs = [Sq(n) for n in range(7)]
    one, two = _run(jobs, workers=1), _run(jobs, workers=3)
    assert [r["n"] for r in two] == list(range(7))
    assert all(r["retries"] == 0 and r["square"] == r["n"] ** 2 for r in two)
    assert _same(one, two)


def test_resume_skips_the_jobs_the_file_holds(tmp_path: Path) -> None:
    calls, out = tmp_path / "calls", tmp_path / "episodes.jsonl"
    calls.mkdir()
    first = _run([Sq(n, str(calls)) for n in range(3)], out_jsonl=out)
    assert _calls(calls) == [0, 1, 2] and len(read_records(out)) == 3
    for p in calls.iterdir():
        p.unlink()
    both = _run([Sq(n, str(calls)) for n in range(5)], out_jsonl=out, resume=True)
    assert _calls(calls) == [3, 4]  # only the new jobs ran
    assert both[:3] == first  # the stored records, as they were
    assert [r["n"] for r in both] == list(range(5)) and set(read_records(out)) == {
        f"sq/{n}" for n in range(5)
    }
    again = _run([Sq(n, str(calls)) for n in range(2)], out_jsonl=out)  # no --resume: a fresh file
    assert set(read_records(out)) == {"sq/0", "sq/1"} and [r["n"] for r in again] == [0, 1]


def test_a_torn_or_damaged_line_is_ignored_and_its_job_runs_again(tmp_path: Path) -> None:
    calls, out = tmp_path / "calls", tmp_path / "episodes.jsonl"
    calls.mkdir()
    good = record_line("sq/0", {"n": 0, "square": 0, "retries": 0})
    damaged = record_line("sq/1", {"n": 1, "square": 1, "retries": 0}).replace(b'"square": 1', b'"square": 7')
    torn = record_line("sq/2", {"n": 2, "square": 4, "retries": 0})[:-9]  # a crash mid-write
    out.write_bytes(good + damaged + torn)
    assert set(read_records(out)) == {"sq/0"}
    recs = _run([Sq(n, str(calls)) for n in range(3)], workers=1, out_jsonl=out, resume=True)
    assert _calls(calls) == [1, 2] and [r["square"] for r in recs] == [0, 1, 4]
    lines = out.read_bytes().splitlines()
    assert len(lines) == 3 and set(read_records(out)) == {"sq/0", "sq/1", "sq/2"}  # the torn line is gone


def test_a_worker_killed_mid_job_is_replaced_and_its_job_retried(tmp_path: Path) -> None:
    out = tmp_path / "episodes.jsonl"
    jobs = [Sq(n, die_once=str(tmp_path / "died") if n == 2 else None) for n in range(5)]
    recs = _run(jobs, out_jsonl=out)
    assert [r["retries"] for r in recs] == [0, 0, 1, 0, 0]
    assert [r["square"] for r in recs] == [n * n for n in range(5)]
    assert read_records(out)["sq/2"]["retries"] == 1


def test_a_job_whose_worker_always_dies_gives_up_after_max_retries(tmp_path: Path) -> None:
    calls = tmp_path / "calls"
    calls.mkdir()
    with pytest.raises(WorkerLost, match=r"job sq/1: its worker died 2 times"):
        _run([Sq(0), Sq(1, str(calls), die_always=True)], max_retries=1)
    assert _calls(calls) == [1, 1]


def test_workers_end_soon_after_their_command_is_killed(tmp_path: Path) -> None:
    pids = tmp_path / "pids"
    script = f"""
import sys
sys.path.insert(0, {str(REPO)!r})
from tests.support.jobs import mark_and_sleep
from tidee.batch import run_jobs
jobs = [({str(pids)!r}, n, 60.0) for n in range(2)]
run_jobs(jobs, mark_and_sleep, workers=2, renderer=None, progress=False)
"""
    pids.mkdir()
    parent = subprocess.Popen([sys.executable, "-c", script], cwd=REPO)
    try:
        deadline = time.monotonic() + 60
        while len(list(pids.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        workers = [int(p.name.split("-")[1]) for p in pids.iterdir()]
        assert len(workers) == 2, "the workers never started their jobs"
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 10  # each was 60 s from the end of its job
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by init) is not running
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_an_exception_in_run_one_ends_the_run_as_in_one_process() -> None:
    with pytest.raises(ValueError, match="job 1 refuses"):
        _run([Sq(0), Sq(1, fail=True), Sq(2)])


def test_a_key_function_serves_jobs_without_a_key_method(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    recs = run_jobs(
        [3, 4], _cube, workers=1, renderer=None, progress=False, out_jsonl=out, key=lambda n: f"cube/{n}"
    )
    assert [r["cube"] for r in recs] == [27, 64] and set(read_records(out)) == {"cube/3", "cube/4"}
    with pytest.raises(TypeError, match="no key"):
        run_jobs([3], _cube, workers=1, renderer=None, progress=False, out_jsonl=out)


def _cube(n: int) -> dict[str, Any]:
    return {"cube": n**3}


def test_the_costliest_jobs_start_first_and_records_stay_in_job_order(tmp_path: Path) -> None:
    calls = tmp_path / "calls"
    calls.mkdir()
    jobs = [Sq(n, str(calls)) for n in (2, 0, 5, 3)]
    recs = _run(jobs, workers=1, cost=lambda j: j.n)
    started = [
        int(p.name.split("-")[0]) for p in sorted(calls.iterdir(), key=lambda p: int(p.name.split("-")[2]))
    ]
    assert started == [5, 3, 2, 0] and [r["n"] for r in recs] == [2, 0, 5, 3]


def _file_job(n: int) -> dict[str, Any]:
    return {"files": {f"part/{n}.bin": bytes([n]) * (n + 1)}, "n": n}


def test_a_jobs_files_are_written_here_and_a_damaged_one_is_made_again_on_resume(tmp_path: Path) -> None:
    out, records = tmp_path / "out", tmp_path / "out" / "jobs.jsonl"
    run = lambda resume: run_jobs(  # noqa: E731
        [0, 1, 2],
        _file_job,
        workers=2,
        renderer=None,
        progress=False,
        out_jsonl=records,
        key=lambda n: f"f/{n}",
        files_dir=out,
        resume=resume,
    )
    first = run(False)
    assert (out / "part" / "2.bin").read_bytes() == b"\x02\x02\x02"
    assert [r["files"] for r in first] == [
        {f"part/{n}.bin": hashlib.sha256(bytes([n]) * (n + 1)).hexdigest()} for n in range(3)
    ]
    assert files_intact(out, first[1])
    (out / "part" / "1.bin").write_bytes(b"damaged")
    (out / "part" / "2.bin").unlink()
    stamp = (out / "part" / "0.bin").stat().st_mtime_ns
    again = run(True)
    assert again == first and (out / "part" / "1.bin").read_bytes() == b"\x01\x01"
    assert (out / "part" / "2.bin").exists() and (out / "part" / "0.bin").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="relative path inside"):
        write_files(out, {"../escape.bin": b"x"})


def test_npz_bytes_depend_only_on_the_arrays() -> None:
    import io

    import numpy as np

    arrays = {"a": np.arange(12, dtype=np.int16).reshape(3, 4), "s": "Kitchen"}
    one = npz_bytes(arrays)
    time.sleep(1.1)  # a writer that stamped the time would differ now
    assert npz_bytes(arrays) == one
    with np.load(io.BytesIO(one)) as z:
        assert np.array_equal(z["a"], arrays["a"]) and str(z["s"]) == "Kitchen"


def test_importing_tidee_and_building_the_cli_loads_no_ray() -> None:
    code = (
        "import sys, tidee, tidee.cli\n"
        "tidee.cli.build_parser()\n"
        "import tidee.batch, tidee.agent.evaluation.tidy_eval\n"
        "assert 'ray' not in sys.modules, 'ray imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_backend_ray_without_ray_says_how_to_install_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from tidee.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as if not installed
    rc = main(["eval", "tidy", "--out", str(tmp_path / "o"), "--episodes", "1", "--backend", "ray"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and len(err.splitlines()) == 1 and "pip install -e '.[cluster]'" in err


# --- Ray -------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@needs_ray
def test_an_unreachable_ray_address_is_one_line_and_quick(tmp_path: Path) -> None:
    t0 = time.monotonic()
    r = subprocess.run(
        [
            TIDEE,
            "eval",
            "tidy",
            "--out",
            str(tmp_path / "o"),
            "--episodes",
            "1",
            "--variants",
            "RandomReceptacle",
        ]
        + ["--backend", "ray", "--ray-address", f"127.0.0.1:{_free_port()}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and time.monotonic() - t0 < 30
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and "--ray-address" in err[0] and "Traceback" not in r.stderr, r.stderr


@needs_ray
@pytest.mark.slow
def test_ray_actors_give_the_local_records_and_retry_a_killed_one(tmp_path: Path) -> None:
    jobs = [Sq(n, die_once=str(tmp_path / "died") if n == 3 else None) for n in range(6)]
    ray_recs = _run(jobs, backend="ray")
    assert [r["retries"] for r in ray_recs] == [0, 0, 0, 1, 0, 0]
    local = _run([Sq(n) for n in range(6)])
    assert _same([dict(r, retries=0) for r in ray_recs], local)
    with pytest.raises(ValueError, match="job 1 refuses"):
        _run([Sq(0), Sq(1, fail=True)], backend="ray")


# --- tidee eval tidy -------------------------------------------------------------------------

EVAL = ["--episodes", "2", "--variants", "RandomReceptacle", "--perception", "oracle"]
EVAL += ["--resolution", "64", "--max-steps", "60", "--workers", "2"]


def _eval(out: Path, *extra: str, env: dict[str, str] | None = None) -> list[dict[str, Any]]:
    r = subprocess.run(
        [TIDEE, "eval", "tidy", "--out", str(out), *EVAL, *extra],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    stored = read_records(out / "episodes.jsonl")
    episodes = [e for e in report["episodes"] if e["variant"] == "RandomReceptacle"]
    assert len(episodes) == 2 and len(stored) == 2
    return episodes


@needs_ray
@pytest.mark.slow
def test_eval_tidy_on_ray_matches_local_and_resumes(tmp_path: Path) -> None:
    local = _eval(tmp_path / "local")
    on_ray = _eval(tmp_path / "ray", "--backend", "ray")
    assert _same(local, on_ray)
    t0 = time.monotonic()
    resumed = _eval(tmp_path / "ray", "--resume")  # every episode stored: none runs again
    assert _same(local, resumed) and "2 episodes resumed" in (tmp_path / "ray" / "report.md").read_text()
    assert time.monotonic() - t0 < 60


@pytest.fixture
def ray_cluster() -> Iterator[tuple[str, dict[str, str]]]:
    """A two-node Ray cluster on loopback (one CPU each) with token authentication: its address
    and the environment a driver joins it with. Stopped by the ids of what it started."""
    if shutil.which(RAY) is None:
        pytest.skip("Ray not installed (pip install -e .[cluster])")
    temp = tempfile.mkdtemp(prefix="tdr")  # short: Ray's socket paths must fit 107 bytes
    port = _free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus", "1", "--block", "--object-store-memory", str(100 * 1024 * 1024)]
    env = dict(
        os.environ, RAY_USAGE_STATS_ENABLED="0", RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32)
    )
    nodes: list[subprocess.Popen[bytes]] = []
    try:
        head = [RAY, "start", "--head", "--port", str(port), "--node-ip-address", "127.0.0.1"]
        head += ["--include-dashboard=false", "--temp-dir", temp, "--disable-usage-stats", *common]
        nodes.append(_start(head, env, temp))
        _wait_for(address, nodes[0])
        worker = [RAY, "start", "--address", address, "--node-ip-address", "127.0.0.1", *common]
        nodes.append(_start(worker, env, temp))
        _wait_for_nodes(address, 2, env)
        yield address, env
    finally:
        for p in reversed(nodes):
            _stop(p)
        _kill_leftovers(temp)
        shutil.rmtree(temp, ignore_errors=True)


def _start(cmd: list[str], env: dict[str, str], temp: str) -> subprocess.Popen[bytes]:
    log = open(Path(temp) / f"start-{len(os.listdir(temp))}.log", "wb")  # noqa: SIM115
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _wait_for(address: str, head: subprocess.Popen[bytes], timeout: float = 90) -> None:
    host, port = address.rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert head.poll() is None, "ray start --head exited"
        try:
            with socket.create_connection((host, int(port)), timeout=1):
                return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"no Ray head at {address} after {timeout} s")


def _wait_for_nodes(address: str, n: int, env: dict[str, str], timeout: float = 120) -> None:
    code = (
        "import ray, sys, logging\n"
        f"ray.init(address={address!r}, logging_level=logging.WARNING)\n"
        "print(sum(1 for x in ray.nodes() if x['Alive']))\n"
        "ray.shutdown()\n"
    )
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
        if r.returncode == 0 and r.stdout.strip().splitlines()[-1:] == [str(n)]:
            return
        time.sleep(1)
    raise AssertionError(f"the Ray cluster at {address} did not reach {n} nodes")


def _stop(p: subprocess.Popen[bytes]) -> None:
    """SIGTERM to a ``ray start --block``: it stops the Ray processes it started; then its group."""
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)
    try:
        os.killpg(p.pid, 9)  # the session start_new_session made for this node: its leftovers only
    except (ProcessLookupError, PermissionError):
        pass


def _kill_leftovers(temp: str) -> None:
    """Any process whose command line names this cluster's temp dir (ours alone), by pid."""
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = Path("/proc", pid, "cmdline").read_bytes()
        except OSError:
            continue
        if temp.encode() in cmd and int(pid) != os.getpid():
            try:
                os.kill(int(pid), 9)
            except OSError:
                pass


@pytest.mark.slow
def test_eval_tidy_on_a_two_node_ray_cluster_matches_local(
    tmp_path: Path, ray_cluster: tuple[str, dict[str, str]]
) -> None:
    address, env = ray_cluster
    on_cluster = _eval(tmp_path / "cluster", "--backend", "ray", "--ray-address", address, env=env)
    local = _eval(tmp_path / "local")
    assert _same(local, on_cluster)
    assert "--backend ray" in (tmp_path / "cluster" / "report.md").read_text()
    no_token = {k: v for k, v in env.items() if not k.startswith("RAY_AUTH")}
    t0 = time.monotonic()
    r = subprocess.run(
        [
            TIDEE,
            "eval",
            "tidy",
            "--out",
            str(tmp_path / "x"),
            *EVAL,
            "--backend",
            "ray",
            "--ray-address",
            address,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env=no_token,
    )
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode != 0 and time.monotonic() - t0 < 45, r.stderr
    assert len(err) == 1 and "RAY_AUTH_MODE=token" in err[0], r.stderr
