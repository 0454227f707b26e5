"""Run a batch of jobs on local worker processes or on Ray actors, records in job order.

Every batch command (``tidee eval tidy|rearrange|preferences|search``, ``tidee gen ...``)
describes its work as jobs (any picklable object: an episode, a room configuration, a group of
them) and gives a module-level ``run_one(job) -> record`` (a JSON-serialisable dict).
:func:`run_jobs` runs every job once:

* ``backend="local"``: in this process when ``workers`` is 1, else in ``workers`` spawned
  processes; a free worker takes the next job.
* ``backend="ray"``: one Ray actor per worker, on a local Ray started for the run
  (``ray_address`` None, ``num_cpus=workers``) or on a running cluster (``ray.init(address=...)``);
  a free actor takes the next job.

Each worker (process or actor) keeps a context across its jobs: its simulator and the models it
loaded (:func:`worker_state`, set up by :func:`init_worker`), so the same jobs give the same
records on either backend. A worker that dies mid-job (killed, out of memory, a node lost) is
replaced and its job runs again on another worker, up to ``max_retries`` times; each record
carries ``retries``. An exception raised by ``run_one`` is not retried: it ends the run, as it
would in one process. ``cost``: an estimate of each job's run time; jobs start longest first,
so that a long one does not start last and hold the run while the other workers idle. A local
worker whose command was killed ends within ``PARENT_CHECK_S`` instead of finishing its job.

``out_jsonl``: each record is appended as it finishes, one line ``<crc32 8 hex> TAB <JSON>``
(the episode log's format) holding the job's key and its record, flushed and synced. With
``resume``, jobs whose key already has an intact line are not run again: their stored records
are returned. A torn or damaged line (a crash mid-write) is ignored and dropped from the file.
A job's key is its ``key()`` method, or the ``key`` function given to :func:`run_jobs`.

``files_dir``: a job that makes files (data shards, cached scenes) returns them in its record
as ``"files": {relative path: bytes}``; this process writes them under ``files_dir`` (atomically)
as the job finishes and keeps ``{relative path: sha256}`` in the record. So the files land where
the command runs whichever machine made them, and with ``resume`` a stored record counts only
while each of its files is there with that digest (a missing or damaged file is made again).
:func:`npz_bytes` makes an ``.npz`` whose bytes depend only on its arrays.

Ray is optional (``pip install -e .[cluster]``) and imported only by a ``backend="ray"`` run.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import multiprocessing as mp
import os
import pickle
import socket
import sys
import tempfile
import threading
import time
import traceback
import zlib
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Literal, TypeVar

from tidee.options import option
from tidee.threads import threads_per_process

Backend = Literal["local", "ray"]
BACKENDS: tuple[Backend, ...] = ("local", "ray")
INSTALL_RAY = "pip install -e '.[cluster]'"
J = TypeVar("J")
Record = dict[str, Any]


# --- the options every batch command shares --------------------------------------------------


@dataclass
class BackendConfig:
    """Where a batch command's jobs run (a field ``batch`` of its config: one declaration)."""

    backend: Backend = option(
        "local",
        "local: worker processes on this machine | ray: one Ray actor per worker "
        "(needs pip install -e '.[cluster]')",
    )
    ray_address: str | None = option(
        None, "a running Ray cluster's HOST:PORT for --backend ray (default: start Ray on this machine)"
    )

    def __post_init__(self) -> None:
        if self.ray_address is not None and self.backend != "ray":
            raise ValueError("--ray-address is for --backend ray")


@dataclass
class BatchConfig(BackendConfig):
    """Where a batch command's jobs run, and whether it goes on from an interrupted run (for
    commands whose output is one record or file per job)."""

    resume: bool = option(
        False,
        "go on from an interrupted run: the jobs whose records and files OUT already holds intact "
        "are not run again",
    )


# --- the worker context ----------------------------------------------------------------------

_WORKER: dict[str, Any] = {}  # this process's simulator ("transport") and loaded models ("models")


def worker_state() -> dict[str, Any]:
    """This process's worker context: a dict kept across every job the process runs.

    ``"transport"``: its simulator (set by :func:`init_worker`); ``"models"``: loaded agent models
    by key (``tidee.agent.runner.worker_models``); a command may keep more of its own under other keys.
    """
    return _WORKER


def init_worker(renderer: str | None, threads: int) -> None:
    """Set up a worker: its share of the cores (``tidee.threads``) and its own simulator
    (none when ``renderer`` is None: jobs that need no simulator; one it has is kept)."""
    from tidee.threads import use_threads

    use_threads(threads)
    if renderer is not None and "transport" not in _WORKER:
        from tidee.protocol.transport import InProcessTransport

        _WORKER["transport"] = InProcessTransport(renderer=renderer)
    _WORKER["ready"] = True


def worker_transport(renderer: str) -> Any:
    """This worker's simulator; opened now when no :func:`init_worker` ran in this process."""
    transport = _WORKER.get("transport")
    if transport is None:
        from tidee.protocol.transport import InProcessTransport

        transport = _WORKER["transport"] = InProcessTransport(renderer=renderer)
    return transport


# --- keys and the records file ---------------------------------------------------------------


def job_key(job: Any) -> str:
    """A job's key for ``out_jsonl`` and ``resume``: its ``key()`` method, as text."""
    key = getattr(job, "key", None)
    if not callable(key):
        raise TypeError(f"{type(job).__name__} has no key() method: give run_jobs key=")
    return str(key())


def config_digest(config: Any, skip: Sequence[str] = ()) -> str:
    """10 hex digits of a config dataclass's fields but ``skip``: part of a job's key, so that a
    resumed run with other settings runs the job again instead of keeping a stale record."""
    from dataclasses import asdict

    fields = {k: v for k, v in asdict(config).items() if k not in skip}
    return hashlib.sha1(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:10]


def _json_default(x: Any) -> Any:
    if hasattr(x, "tolist"):
        return x.tolist()
    if hasattr(x, "item"):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


def record_line(key: str, record: Record) -> bytes:
    """One line of a records file: ``crc32hex TAB {"key": ..., "record": ...}`` and a newline."""
    text = json.dumps({"key": key, "record": record}, default=_json_default).encode("ascii")
    return b"%08x\t%s\n" % (zlib.crc32(text), text)


def _parse_line(line: bytes) -> tuple[str, Record] | None:
    crc, sep, text = line.partition(b"\t")
    if not sep or len(crc) != 8:
        return None
    try:
        if int(crc, 16) != zlib.crc32(text):
            return None
        entry = json.loads(text)
    except ValueError:
        return None
    if not isinstance(entry, dict) or not isinstance(entry.get("record"), dict):
        return None
    return str(entry.get("key")), entry["record"]


def read_records(path: str | os.PathLike) -> dict[str, Record]:
    """Every intact record of a records file by key (the last one where a key repeats); a torn
    or damaged line is skipped. An absent file has none."""
    path = Path(path)
    if not path.is_file():
        return {}
    out: dict[str, Record] = {}
    for line in path.read_bytes().split(b"\n"):
        parsed = _parse_line(line)
        if parsed is not None:
            out[parsed[0]] = parsed[1]
    return out


def stored_jobs(jobs: Sequence[Any], path: str | os.PathLike) -> int:
    """How many of ``jobs`` already have an intact record in ``path``: what ``resume`` will
    take from it instead of running (for a report's notes)."""
    stored = read_records(path)
    return sum(job_key(j) in stored for j in jobs)


class _RecordsFile:
    """``out_jsonl`` while a run appends to it (whole lines, flushed and synced)."""

    def __init__(self, path: Path, stored: dict[str, Record]) -> None:
        from tidee.protocol.episode_log import write_atomic

        path.parent.mkdir(parents=True, exist_ok=True)
        # Rewritten first: a fresh run starts empty; a resumed one keeps only its intact lines, so
        # that a torn last line cannot swallow the next record appended after it.
        write_atomic(path, b"".join(record_line(k, r) for k, r in stored.items()))
        self._f = open(path, "ab")  # closed by close()

    def append(self, key: str, record: Record) -> None:
        self._f.write(record_line(key, record))
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.close()


# --- errors ----------------------------------------------------------------------------------


class WorkerLost(ChildProcessError):
    """A job's workers died more than ``max_retries`` times (an OSError: the CLI says it in a line)."""


class _RemoteTraceback(Exception):
    def __init__(self, text: str) -> None:
        self.text = text

    def __str__(self) -> str:
        return self.text


def _too_many_deaths(job: Any, key: Callable[[Any], str] | None, deaths: int, why: str) -> WorkerLost:
    try:
        name = (key or job_key)(job)
    except TypeError:
        name = repr(job)[:120]
    return WorkerLost(
        f"job {name}: its worker died {deaths} times ({why}); giving up "
        "(finished records are kept: run again with --resume)"
    )


# --- the runner ------------------------------------------------------------------------------


def run_jobs(
    jobs: Sequence[J],
    run_one: Callable[[J], Record],
    *,
    workers: int,
    renderer: str | None,
    backend: Backend = "local",
    ray_address: str | None = None,
    progress: bool = True,
    out_jsonl: str | os.PathLike | None = None,
    resume: bool = False,
    max_retries: int = 2,
    key: Callable[[J], str] | None = None,
    desc: str = "episodes",
    files_dir: str | os.PathLike | None = None,
    cost: Callable[[J], float] | None = None,
) -> list[Record]:
    """Every job's record (``run_one(job)`` plus ``retries``), in job order (see the module doc).

    ``run_one`` must be a module-level function (it is pickled to the workers). ``renderer``:
    the simulator each worker opens (None: none). ``key``: a job's key (default: its ``key()`` method),
    needed only with ``out_jsonl``. ``files_dir``: where the files a record carries are written.
    ``cost``: each job's estimated run time; the most costly start first.
    """
    from tqdm import tqdm

    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if max_retries < 0:
        raise ValueError(f"max_retries must be >= 0, got {max_retries}")
    if resume and out_jsonl is None:
        raise ValueError("resume needs out_jsonl (the records file to resume from)")
    keyf: Callable[[Any], str] = key or job_key
    keys = [keyf(j) for j in jobs] if out_jsonl is not None else []
    records: list[Record | None] = [None] * len(jobs)
    stored: dict[str, Record] = read_records(out_jsonl) if out_jsonl is not None and resume else {}
    if files_dir is not None:  # a record whose files are gone or damaged is not done
        stored = {k: r for k, r in stored.items() if files_intact(files_dir, r)}
    for i, k in enumerate(keys):
        if k in stored:
            records[i] = stored[k]
    todo = [i for i, r in enumerate(records) if r is None]
    if cost is not None:  # longest first (stable: equal estimates keep the job order)
        estimates = {i: float(cost(jobs[i])) for i in todo}
        todo.sort(key=lambda i: -estimates[i])
    # Ray first: an unreachable cluster is refused before a bar or a file is touched
    ray: Any = None
    connected = False
    if backend == "ray" and todo:
        ray, connected = connect_ray(ray_address, workers)
    sink: _RecordsFile | None = None
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc=desc, disable=not progress)

    def done(i: int, record: Record, retries: int) -> None:
        record = dict(record, retries=retries)
        if files_dir is not None and "files" in record:
            record["files"] = write_files(files_dir, record["files"])
        records[i] = record
        if sink is not None:
            sink.append(keys[i], record)
        bar.update()

    try:
        if out_jsonl is not None:
            sink = _RecordsFile(Path(out_jsonl), stored)
        if not todo:
            pass
        elif backend == "ray":
            _run_ray(ray, jobs, todo, run_one, done, workers, renderer, ray_address is None, max_retries, key)
        elif workers <= 1:
            if "ready" not in _WORKER:
                init_worker(renderer, threads_per_process(1))
            for i in todo:
                done(i, run_one(jobs[i]), 0)
        else:
            _run_local_pool(jobs, todo, run_one, done, workers, renderer, max_retries, key)
    finally:
        bar.close()
        if sink is not None:
            sink.close()
        if connected:
            ray.shutdown()
    return [r for r in records if r is not None]


# --- files a job makes -----------------------------------------------------------------------


def _relative(name: str) -> Path:
    path = Path(name)
    if path.is_absolute() or ".." in path.parts or not path.parts:
        raise ValueError(f"a job's file must be a relative path inside the output folder, got {name!r}")
    return path


def write_files(root: str | os.PathLike, files: Mapping[str, bytes]) -> dict[str, str]:
    """Write ``files`` (relative path: bytes) under ``root``, each atomically; their sha256 by path."""
    from tidee.protocol.episode_log import write_atomic

    digests = {}
    for name, data in files.items():
        path = Path(root) / _relative(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, data)
        digests[name] = hashlib.sha256(data).hexdigest()
    return digests


def files_intact(root: str | os.PathLike, record: Record) -> bool:
    """Whether each file a stored record names (``"files": {path: sha256}``) is under ``root`` with
    that digest (a record without files is intact)."""
    files = record.get("files") or {}
    if not isinstance(files, dict):
        return False
    for name, digest in files.items():
        try:
            data = (Path(root) / _relative(name)).read_bytes()
        except (OSError, ValueError):
            return False
        if hashlib.sha256(data).hexdigest() != digest:
            return False
    return True


def npz_bytes(arrays: Mapping[str, Any]) -> bytes:
    """``arrays`` as the bytes of a compressed ``.npz``. numpy writes each member through
    ``ZipFile.open``, which stamps 1980-01-01 rather than the time, so the bytes depend only on
    the arrays: the same shard is the same file whichever worker or backend made it."""
    import numpy as np

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# --- local worker processes ------------------------------------------------------------------


PARENT_CHECK_S = 1.0  # how often a local worker looks whether its parent is still there


def _exit_with(parent: int) -> None:
    """End this process (at once, from a daemon thread) when ``parent`` is no longer its parent: a
    killed or crashed ``tidee`` command leaves no worker finishing an episode nobody will read."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_S)
    os._exit(0)


def _local_worker(
    conn: Connection,
    run_one: Callable[[Any], Record],
    renderer: str | None,
    threads: int,
    parent: int | None = None,
) -> None:
    """A worker process: set up once, then run the jobs it is sent until told to stop, or until
    ``parent`` (a pid) is gone."""
    if parent is not None:
        threading.Thread(target=_exit_with, args=(parent,), daemon=True, name="parent-watch").start()
    init_worker(renderer, threads)
    while True:
        try:
            msg = conn.recv()
        except EOFError:  # the parent is gone
            return
        if msg is None:
            return
        i, job = msg
        try:
            reply: tuple[int, bool, Any] = (i, True, run_one(job))
        except Exception as e:
            tb = traceback.format_exc()
            try:
                pickle.dumps(e)
                error: BaseException = e
            except Exception:
                error = RuntimeError(f"{type(e).__name__}: {e}")
            reply = (i, False, (error, tb))
        try:
            conn.send(reply)
        except OSError:  # the parent is gone (BrokenPipeError)
            return


class _Proc:
    def __init__(
        self, ctx: Any, run_one: Callable[[Any], Record], renderer: str | None, threads: int
    ) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(
            target=_local_worker,
            args=(child, run_one, renderer, threads, os.getpid()),
            name="tidee-eval-worker",
        )
        self.process.start()
        child.close()
        self.job: int | None = None

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=5)
        self.conn.close()


def _run_local_pool(
    jobs: Sequence[Any],
    todo: list[int],
    run_one: Callable[[Any], Record],
    done: Callable[[int, Record, int], None],
    workers: int,
    renderer: str | None,
    max_retries: int,
    key: Callable[[Any], str] | None,
) -> None:
    ctx = mp.get_context("spawn")
    threads = threads_per_process(workers)
    pending = deque(todo)
    deaths = dict.fromkeys(todo, 0)
    procs = [_Proc(ctx, run_one, renderer, threads) for _ in range(min(workers, len(todo)))]
    try:
        while True:
            for p in procs:  # a free worker takes the next job
                if p.job is None and pending:
                    p.job = pending.popleft()
                    p.conn.send((p.job, jobs[p.job]))
            busy = [p for p in procs if p.job is not None]
            if not busy:
                return
            ready = set(wait([p.conn for p in busy] + [p.process.sentinel for p in busy]))
            for p in busy:
                if p.conn not in ready and p.process.sentinel not in ready:
                    continue
                i = p.job
                assert i is not None
                try:
                    reply = p.conn.recv() if p.conn.poll() else None
                except (EOFError, OSError):
                    reply = None
                if reply is None:  # the process died mid-job: replace it, run the job again
                    p.process.join(timeout=5)
                    p.conn.close()
                    deaths[i] += 1
                    if deaths[i] > max_retries:
                        raise _too_many_deaths(jobs[i], key, deaths[i], f"exit code {p.process.exitcode}")
                    procs[procs.index(p)] = _Proc(ctx, run_one, renderer, threads)
                    pending.appendleft(i)
                    continue
                p.job = None
                _, ok, value = reply
                if not ok:
                    error, tb = value
                    raise error from _RemoteTraceback(tb)
                done(i, value, deaths[i])
    finally:
        for p in procs:
            if p.process.is_alive() or not p.conn.closed:
                p.stop()


# --- Ray actors ------------------------------------------------------------------------------


class _RayWorker:
    """A Ray actor: a worker context (simulator, models) kept across the jobs it runs."""

    def __init__(self, run_one: Callable[[Any], Record], renderer: str | None, threads: int) -> None:
        init_worker(renderer, threads)
        self._run_one = run_one

    def run(self, job: Any) -> Record:
        return self._run_one(job)


def import_ray() -> Any:
    """The ``ray`` module, or a one-line ValueError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ValueError(f"--backend ray needs Ray, which is not installed: {INSTALL_RAY}") from None
    return ray


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Refuse a HOST:PORT (or ray://HOST:PORT) nothing listens on, in one line and seconds."""
    where = address.split("://", 1)[-1]
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit():
        return  # "auto", "local", a name Ray resolves itself
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except OSError as e:
        raise ConnectionError(
            f"--ray-address {address}: no Ray cluster reachable ({e.strerror or e}); "
            "start one with `ray start --head` or check the address"
        ) from None


def connect_ray(address: str | None, workers: int) -> tuple[Any, bool]:
    """``ray`` connected to ``address`` (None: a new local Ray with ``workers`` CPUs).

    Returns the module and whether this call connected it (and so should shut it down)."""
    import logging

    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if address is None:
        # "local": a fresh instance even where another Ray runs on this machine
        ray.init(
            address="local",
            num_cpus=workers,
            include_dashboard=False,
            logging_level=logging.WARNING,
            object_store_memory=200 * 1024 * 1024,
        )
        return ray, True
    _check_reachable(address)
    try:
        with _stderr_held():
            ray.init(address=address, logging_level=logging.WARNING)
    except Exception as e:  # Ray's own errors (ConnectionError, RuntimeError, ...) in one line
        raise ConnectionError(f"--ray-address {address}: cannot join the Ray cluster: {_why(e)}") from None
    return ray, True


@contextlib.contextmanager
def _stderr_held() -> Iterator[None]:
    """Hold what is written to this process's stderr (file descriptor 2, so Ray's C++ core too)
    and let it through only if the block succeeds: while Ray retries a cluster that refuses it
    (e.g. one that wants a token) its core warns every second; the error we raise says why."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        ok = False
        try:
            yield
            ok = True
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            if ok:
                held.seek(0)
                os.write(2, held.read())


def _why(e: BaseException) -> str:
    """Why Ray refused, in one line (a token-authenticated cluster says what to set)."""
    chain: list[str] = []
    cur: BaseException | None = e
    while cur is not None and len(chain) < 5:
        chain.append(f"{type(cur).__name__}: {cur}")
        cur = cur.__cause__ or cur.__context__
    text = "\n".join(chain)
    if "AuthenticationError" in text or "InvalidAuthToken" in text:
        return (
            "it asks for its token: set RAY_AUTH_MODE=token and RAY_AUTH_TOKEN "
            "(or ~/.ray/auth_token) as on its nodes"
        )
    first = str(e).strip().splitlines()
    return first[0] if first else type(e).__name__


def _run_ray(
    ray: Any,
    jobs: Sequence[Any],
    todo: list[int],
    run_one: Callable[[Any], Record],
    done: Callable[[int, Record, int], None],
    workers: int,
    renderer: str | None,
    local: bool,
    max_retries: int,
    key: Callable[[Any], str] | None,
) -> None:
    # On a Ray started here the workers share this machine's cores as local processes would; on
    # a cluster each actor holds one CPU of its node.
    threads = threads_per_process(workers) if local else 1
    actor_cls = ray.remote(num_cpus=1, max_restarts=0)(_RayWorker)
    pending = deque(todo)
    deaths = dict.fromkeys(todo, 0)
    actors = [actor_cls.remote(run_one, renderer, threads) for _ in range(min(workers, len(todo)))]
    idle = list(actors)
    running: dict[Any, tuple[Any, int]] = {}  # ObjectRef -> (actor, job index)
    try:
        while pending or running:
            while idle and pending:  # a free actor takes the next job
                actor, i = idle.pop(0), pending.popleft()
                running[actor.run.remote(jobs[i])] = (actor, i)
            ready, _ = ray.wait(list(running), num_returns=1)
            for ref in ready:
                actor, i = running.pop(ref)
                try:
                    record = ray.get(ref)
                except ray.exceptions.RayActorError as e:  # the actor died: a new one, the job again
                    deaths[i] += 1
                    ray.kill(actor)
                    actors.remove(actor)
                    if deaths[i] > max_retries:
                        why = str(e).strip().splitlines()[0] if str(e).strip() else "actor died"
                        raise _too_many_deaths(jobs[i], key, deaths[i], why) from None
                    replacement = actor_cls.remote(run_one, renderer, threads)
                    actors.append(replacement)
                    idle.append(replacement)
                    pending.appendleft(i)
                    continue
                except ray.exceptions.RayTaskError as e:  # run_one raised: as it would in one process
                    raise e.as_instanceof_cause() from None
                idle.append(actor)
                done(i, record, deaths[i])
    finally:
        for actor in actors:
            try:
                ray.kill(actor)
            except Exception:  # already gone
                pass


__all__ = [
    "BACKENDS",
    "Backend",
    "BackendConfig",
    "BatchConfig",
    "WorkerLost",
    "config_digest",
    "connect_ray",
    "files_intact",
    "import_ray",
    "init_worker",
    "job_key",
    "npz_bytes",
    "read_records",
    "record_line",
    "run_jobs",
    "worker_state",
    "worker_transport",
    "write_files",
]
