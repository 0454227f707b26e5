"""The Zenoh simulation server: many concurrent episodes, one per session id.

Threads: the queryable and the client-liveliness subscriber deliver into Zenoh FIFO
channels; one dispatcher thread per channel only turns each item into a job on a worker
queue (no decoding, no simulation, no Zenoh calls); worker threads do everything else. No
Python callback runs on Zenoh's threads, and a process that forgets ``stop()`` still exits
(Zenoh's Python callbacks run on non-daemon threads that would keep it alive). A new
session goes to the worker holding the fewest sessions and stays pinned to it for its life,
so its requests run in order and its episode is only ever touched by one thread.

Processes: PyBullet holds the GIL, so threads alone would simulate every session on one
core. By default the episodes live in child processes (``tidee.server.workers``): worker
thread *i* owns child process *i* and is the only thread that talks to it, and the server
holds a proxy per episode. ``ServerConfig.processes`` sets how many (0: one per available
core, never more than ``max_sessions``); each starts with its first session, so N sessions
run on min(N, processes) cores. A child that dies fails its sessions' next request (a
reset starts them again in a fresh child) and the other sessions carry on. A server given
its own ``episode_factory`` (a test's fake, an ``Episode`` in this process) runs the
episodes in ``ServerConfig.workers`` threads of this process instead; pass an
``EpisodeProcesses`` to run a factory of your own in child processes.

Robustness: every request is decoded strictly; a bad one gets an ``ErrorReply`` saying
what was wrong; an exception inside an episode becomes ``ErrorReply(internal)`` and the
session stays usable (its next reset starts afresh). Sessions are freed on ``close``,
when their client's liveliness token disappears, or when the server stops.

Congestion: replies travel with the query's congestion control, which ``SimClient`` sets
to ``BLOCK`` (the agent must get every frame; Zenoh 1.x ignores a reply's own setting);
the viewer feed (``tidee/sim/{server}/obs/{session}``) is published with ``DROP``, so a
slow viewer loses frames instead of stalling the simulation. Viewers should subscribe
with a ``RingChannel`` (latest wins).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable

import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode
from tidee.protocol.messages import (CloseReply, CloseRequest, ErrorCode, ErrorReply, Observation,
                                     ResetRequest, StateReply, StateRequest, StepRequest)
from tidee.protocol.transport import EpisodeLike
from tidee.protocol.zenoh_config import make_config
from tidee.server.splits import check_mess_index
from tidee.server.workers import EpisodeProcesses, available_cores

log = logging.getLogger("tidee.server")

REQUEST_TYPES: dict[str, type] = {"reset": ResetRequest, "step": StepRequest, "state": StateRequest,
                                  "close": CloseRequest}
RENDERERS = ("auto", "egl", "tiny")
INBOX_CAPACITY = 1024                  # queries or liveliness events waiting for a dispatcher
DEPARTED_MEMORY = 4096                 # how many vanished clients' session ids are remembered


@dataclass
class ServerConfig:
    endpoint: str | None = None        # listen here (default: TIDEE_ZENOH_ENDPOINT, else loopback:7447)
    router: str | None = None          # or: client mode through this Zenoh router (TIDEE_ZENOH_ROUTER)
    max_sessions: int = 16
    renderer: str = "tiny"             # auto | egl | tiny; tiny: the frames the shipped detector was trained on
    server_id: str = "sim0"
    processes: int = 0                 # child processes running episodes; 0: one per available core
    workers: int = 1                   # threads running episodes when a factory is given (module docstring)
    max_request_bytes: int = 1 << 20   # requests carry no arrays

    def __post_init__(self) -> None:
        keys.check_id("server_id", self.server_id)
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        for name in ("max_sessions", "workers", "max_request_bytes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if int(self.processes) < 0:
            raise ValueError(f"processes must be >= 0 (0: one per available core), got {self.processes}")

    def process_count(self) -> int:
        """How many child processes the default episodes run in."""
        return min(self.processes or available_cores(), self.max_sessions)


@dataclass
class _Job:
    session: str | None                # None when the key did not parse
    op: str                            # reset | step | state | close | gone (client token deleted)
    query: zenoh.Query | None = None
    payload: bytes = b""
    key_error: str | None = None


@dataclass
class _Pin:
    worker: int                        # the worker (and so the child process) that serves the session
    pending: int = 0                   # its jobs queued or running


@dataclass
class _Session:
    worker: int
    episode: EpisodeLike | None        # None while the episode is being built
    token: Any = None                  # liveliness: tidee/alive/session/{server}/{session}
    publisher: zenoh.Publisher | None = None


class SimServer:
    """Serve episodes over Zenoh until ``stop()``.

    ``episode_factory``: None (default) runs real ``tidee.server.episode.Episode``s in
    ``config.process_count()`` child processes; an ``EpisodeProcesses`` runs its own episodes
    in its processes; any other callable builds an episode on the session's worker thread,
    in this process (``config.workers`` threads). The server stops the processes it uses.
    """

    def __init__(self, config: ServerConfig,
                 episode_factory: Callable[[], EpisodeLike] | EpisodeProcesses | None = None) -> None:
        self.config = config
        if episode_factory is None:
            episode_factory = EpisodeProcesses(config.process_count(), config.renderer,
                                               name=f"tidee-sim-{config.server_id}")
        self.processes: EpisodeProcesses | None = None
        if isinstance(episode_factory, EpisodeProcesses):
            self.processes = episode_factory
            self._open: Callable[[int], EpisodeLike] = episode_factory.open
            workers = len(episode_factory)
        else:
            factory = episode_factory
            self._open = lambda worker: factory()
            workers = config.workers
        self._sessions: dict[str, _Session] = {}
        self._lock = threading.Lock()              # guards _sessions, _departed, _pins and _load
        # Sessions whose client's token went away: a request the client sent just before it
        # vanished must not create a session nobody will ever free.
        self._departed: OrderedDict[str, None] = OrderedDict()
        # Which worker serves a session: set by its first job, kept while it lives or has jobs queued.
        self._pins: dict[str, _Pin] = {}
        self._load = [0] * workers                 # pinned sessions per worker
        self._queues: list[queue.SimpleQueue[_Job | None]] = [
            queue.SimpleQueue() for _ in range(workers)]
        self._workers = [threading.Thread(target=self._work, args=(i,), name=f"tidee-sim-worker-{i}",
                                          daemon=True) for i in range(workers)]
        self._z: zenoh.Session | None = None
        self._inbound: list[Any] = []              # queryable + liveliness subscriber
        self._dispatchers: list[threading.Thread] = []
        self._server_token: Any = None
        self._handlers: dict[str, Callable[[Any], Any]] = {
            "reset": self._reset, "step": self._step, "state": self._state, "close": self._close}

    # --- lifecycle ----------------------------------------------------------------------
    def start(self) -> SimServer:
        cfg = self.config
        self._z = zenoh.open(make_config(listen=True, endpoint=cfg.endpoint, router=cfg.router))
        for worker in self._workers:
            worker.start()
        queries = self._z.declare_queryable(keys.sim_op_wildcard(cfg.server_id),
                                            zenoh.handlers.FifoChannel(INBOX_CAPACITY))
        clients = self._z.liveliness().declare_subscriber(keys.alive_clients_wildcard(cfg.server_id),
                                                          zenoh.handlers.FifoChannel(INBOX_CAPACITY),
                                                          history=True)
        self._inbound = [queries, clients]
        self._dispatchers = [
            threading.Thread(target=self._dispatch, args=(queries, self._on_query), daemon=True,
                             name="tidee-sim-queries"),
            threading.Thread(target=self._dispatch, args=(clients, self._on_client_liveliness), daemon=True,
                             name="tidee-sim-clients")]
        for dispatcher in self._dispatchers:
            dispatcher.start()
        # Declared last: a client that sees this token can already reach the queryable.
        self._server_token = self._z.liveliness().declare_token(keys.alive_server(cfg.server_id))
        where = "a simulator process each" if self.processes is not None else "episodes in this process"
        log.info("tidee server %r ready: max %d sessions, %d worker(s), %s", cfg.server_id, cfg.max_sessions,
                 len(self._workers), where)
        return self

    def stop(self) -> None:
        """Stop taking requests, finish queued ones, free every session, leave Zenoh."""
        if self._z is None:
            return
        for decl in self._inbound:
            decl.undeclare()  # closes its channel: the dispatcher's loop ends
        for dispatcher in self._dispatchers:
            dispatcher.join()
        self._inbound, self._dispatchers = [], []
        for q in self._queues:
            q.put(None)
        for worker in self._workers:
            worker.join()
        self._server_token.undeclare()
        self._z.close()
        self._z = None
        log.info("tidee server %r stopped", self.config.server_id)

    def __enter__(self) -> SimServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def sessions(self) -> tuple[str, ...]:
        """Ids of the sessions this server holds now."""
        with self._lock:
            return tuple(self._sessions)

    # --- dispatchers: enqueue only --------------------------------------------------------
    @staticmethod
    def _dispatch(channel: Any, handle: Callable[[Any], None]) -> None:
        for item in channel:  # until the queryable or subscriber is undeclared
            try:
                handle(item)
            except Exception:  # keep dispatching whatever one item did
                log.exception("dropped an inbound item")

    def _on_query(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            _, session, op = keys.parse_sim_op(key)
        except ValueError as e:
            self._queues[0].put(_Job(None, "invalid", query, payload, key_error=str(e)))
            return
        self._route(session).put(_Job(session, op, query, payload))

    def _on_client_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            _, _, session = keys.parse_alive(str(sample.key_expr))
        except ValueError:
            return
        if session is None:
            return
        gone = sample.kind == zenoh.SampleKind.DELETE
        with self._lock:
            if gone:
                self._departed[session] = None
                while len(self._departed) > DEPARTED_MEMORY:
                    self._departed.popitem(last=False)
            else:  # a (new) client declared this session id
                self._departed.pop(session, None)
        if gone:
            self._route(session).put(_Job(session, "gone"))

    def _route(self, session: str) -> queue.SimpleQueue[_Job | None]:
        """The queue of the session's worker: its pinned one, else the least loaded (pinned now)."""
        with self._lock:
            pin = self._pins.get(session)
            if pin is None:
                worker = min(range(len(self._load)), key=self._load.__getitem__)
                pin = self._pins[session] = _Pin(worker)
                self._load[worker] += 1
            pin.pending += 1
        return self._queues[pin.worker]

    def _job_done(self, session: str) -> None:
        """Unpin a session that has no episode and no job left (closed, refused, never opened)."""
        with self._lock:
            pin = self._pins[session]
            pin.pending -= 1
            if pin.pending == 0 and session not in self._sessions:
                del self._pins[session]
                self._load[pin.worker] -= 1

    # --- workers ------------------------------------------------------------------------
    def _work(self, index: int) -> None:
        q = self._queues[index]
        while (job := q.get()) is not None:
            if job.op == "gone":
                if self._free(job.session):  # type: ignore[arg-type]
                    log.info("session %s: client gone, freed", job.session)
            else:
                self._answer(job)
            if job.session is not None:
                self._job_done(job.session)
        with self._lock:  # stopping: free the sessions this worker owns, then its simulator process
            mine = [session for session, entry in self._sessions.items() if entry.worker == index]
        for session in mine:
            self._free(session)
        if self.processes is not None:
            self.processes.stop(index)

    def _answer(self, job: _Job) -> None:
        assert job.query is not None
        encoding = "raw"
        try:
            request = self._parse(job)
            encoding = getattr(request, "encoding", "raw")
            reply = self._handlers[job.op](request)
        except ProtocolError as e:
            reply = ErrorReply(e.code, e.message, job.session)
        except Exception as e:  # an episode's bug must not take the server or other sessions down
            log.exception("session %s: %s failed", job.session, job.op)
            reply = ErrorReply(ErrorCode.internal, f"{job.op} failed: {type(e).__name__}: {e}", job.session)
        self._send(job, reply, encoding)

    def _parse(self, job: _Job) -> Any:
        if job.key_error is not None:
            raise ProtocolError(ErrorCode.malformed, job.key_error)
        request = decode(job.payload, max_bytes=self.config.max_request_bytes, expected=REQUEST_TYPES[job.op])
        if request.session != job.session:
            raise ProtocolError(ErrorCode.invalid_field, f"field 'session' is {request.session!r} but "
                                                         f"the key names session {job.session!r}")
        return request

    def _send(self, job: _Job, reply: Any, encoding: str) -> None:
        query = job.query
        assert query is not None
        try:
            try:
                payload = zenoh.ZBytes(encode(reply, encoding))  # converted once: reply and feed share it
            except Exception as e:  # e.g. an episode returned a depth map of the wrong dtype
                log.exception("session %s: cannot encode the %s reply", job.session, job.op)
                reply = ErrorReply(ErrorCode.internal, f"cannot encode the reply: {e}", job.session)
                payload = zenoh.ZBytes(encode(reply))
            if isinstance(reply, ErrorReply):
                query.reply_err(payload)
            else:
                query.reply(query.key_expr, payload)  # congestion control: the query's (BLOCK)
            if isinstance(reply, Observation):
                self._publish(job.session, reply, payload, encoding)  # type: ignore[arg-type]
        except Exception:
            log.exception("session %s: could not reply to %s", job.session, job.op)
        finally:
            query.drop()  # sends the final answer now rather than when Python collects the query

    def _publish(self, session: str, obs: Observation, frame: zenoh.ZBytes, encoding: str) -> None:
        """The viewer feed: the same frame, minus any privileged ground truth."""
        with self._lock:
            entry = self._sessions.get(session)
        if entry is None or entry.publisher is None:
            return
        if obs.ground_truth is not None:
            frame = zenoh.ZBytes(encode(dataclasses.replace(obs, ground_truth=None), encoding))
        entry.publisher.put(frame)

    # --- requests (on the session's worker) ----------------------------------------------
    def _reset(self, request: ResetRequest) -> Observation:
        try:
            check_mess_index(request.spec.seed, request.spec.mess_index)
        except ValueError as e:
            raise ProtocolError(ErrorCode.invalid_field, f"field 'spec.mess_index': {e}") from None
        episode = self._episode(request.session, create=True)
        return episode.reset(request.spec, session=request.session, ground_truth=request.ground_truth)

    def _step(self, request: StepRequest) -> Observation:
        return self._episode(request.session).step(request.action, ground_truth=request.ground_truth)

    def _state(self, request: StateRequest) -> StateReply:
        return StateReply(request.session, self._episode(request.session).state())

    def _close(self, request: CloseRequest) -> CloseReply:
        closed = self._free(request.session)
        if closed:
            log.info("session %s: closed by its client", request.session)
        return CloseReply(request.session, closed)

    # --- sessions -------------------------------------------------------------------------
    def _episode(self, session: str, create: bool = False) -> EpisodeLike:
        with self._lock:
            entry = self._sessions.get(session)
            if entry is None and create:
                if session in self._departed:
                    raise ProtocolError(ErrorCode.unknown_session,
                                        f"the client of session {session!r} has disconnected")
                if len(self._sessions) >= self.config.max_sessions:
                    raise ProtocolError(
                        ErrorCode.server_busy,
                        f"server {self.config.server_id!r} holds {len(self._sessions)} sessions, its "
                        f"maximum (max_sessions); close one or start another server")
                worker = self._pins[session].worker
                entry = self._sessions[session] = _Session(worker, episode=None)  # reserve the slot
        if entry is None:
            raise ProtocolError(ErrorCode.unknown_session,
                                f"no session {session!r} on server {self.config.server_id!r}: "
                                f"send reset first (or it was closed)")
        if entry.episode is None:
            try:
                entry.episode = self._open(entry.worker)
            except BaseException:
                with self._lock:
                    self._sessions.pop(session, None)
                raise
            assert self._z is not None
            server_id = self.config.server_id
            entry.token = self._z.liveliness().declare_token(keys.alive_session(server_id, session))
            entry.publisher = self._z.declare_publisher(keys.observations(server_id, session),
                                                        congestion_control=zenoh.CongestionControl.DROP)
            log.info("session %s: opened (%d held)", session, len(self.sessions))
        return entry.episode

    def _free(self, session: str) -> bool:
        """Close and forget ``session``; False if there was no such session."""
        with self._lock:
            entry = self._sessions.pop(session, None)
        if entry is None:
            return False
        releases = [decl.undeclare for decl in (entry.publisher, entry.token) if decl is not None]
        if entry.episode is not None:
            releases.append(entry.episode.close)
        for release in releases:
            try:
                release()
            except Exception:
                log.exception("session %s: error while freeing it", session)
        return True


def serve(config: ServerConfig,
          episode_factory: Callable[[], EpisodeLike] | EpisodeProcesses | None = None) -> None:
    """Run a server until SIGINT or SIGTERM, then shut it down cleanly."""
    from tidee.launch import wait_for_signal

    server = SimServer(config, episode_factory).start()
    try:
        wait_for_signal()
    finally:
        server.stop()
