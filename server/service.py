"""The Zenoh simulation server: many concurrent episodes, one per session id.

Threads: the queryable and the client-liveliness subscriber deliver into Zenoh FIFO
channels; one dispatcher thread per channel only turns each item into a job on a worker
queue (no decoding, no simulation, no Zenoh calls); worker threads do everything else. The
info queryable (``tidee/sim/{server}/info``: how full the server is, for clients choosing one;
``tidee.protocol.discovery``) is answered by its own dispatcher thread, which never waits on an
episode. No
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
reset starts them again in a fresh child) and the other sessions carry on. A child that has
run ``ServerConfig.recycle_after`` resets is replaced by a fresh one without disturbing a live
session (``tidee.server.workers``, Recycling): PyBullet leaks a little memory at every reset. A server given
its own ``episode_factory`` (a test's fake, an ``Episode`` in this process) runs the
episodes in ``ServerConfig.workers`` threads of this process instead; pass an
``EpisodeProcesses`` to run a factory of your own in child processes.

Robustness: every request is decoded strictly; a bad one gets an ``ErrorReply`` saying
what was wrong; an exception inside an episode becomes ``ErrorReply(internal)`` and the
session stays usable (its next reset starts afresh). A request's size is checked before its
payload is copied out of Zenoh, so an oversized one costs no Python memory. Sessions are
freed on ``close``, when their client's liveliness token disappears, when they have had no
request for ``ServerConfig.idle_timeout_s`` (a reaper thread; the session's next step or
state says it was reclaimed and why), or when the server stops.

Quota and ownership: one client holds at most ``ServerConfig.max_sessions_per_client`` sessions,
and only the client that opened a session may reset, step, advance or close it: another client
naming the same session id is refused by name (``invalid_field``), and the first plays on.
Zenoh does not tell a queryable who sent a query, so a client is what the query says it is
(``client_of``): the Zenoh session id in the query's ``source_info`` (``SimClient`` sends
its own; clients that share a Zenoh session share a quota), else the session id up to its
last ``-`` (``agent7-0``, ``agent7-1`` are one client), else the session id alone. Both
keep well-behaved but careless clients apart; they are no defence against a client that lies,
which only ``max_sessions``, the idle timeout and a router's access control bound.

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
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from tidee.protocol import keys
from tidee.protocol.codec import ProtocolError, decode, encode, wire_depth
from tidee.protocol.messages import (
    CloseReply,
    CloseRequest,
    ErrorCode,
    ErrorReply,
    Observation,
    PhaseRequest,
    ResetRequest,
    ServerInfo,
    ServerInfoRequest,
    StateReply,
    StateRequest,
    StepRequest,
)
from tidee.protocol.transport import EpisodeLike
from tidee.protocol.zenoh_config import make_config
from tidee.server.config import ServerConfig
from tidee.server.splits import check_mess_index
from tidee.server.workers import EncodedObservation, EpisodeProcesses, RemoteEpisode, Wire

log = logging.getLogger("tidee.server")

REQUEST_TYPES: dict[str, type] = {
    "reset": ResetRequest,
    "step": StepRequest,
    "phase": PhaseRequest,
    "state": StateRequest,
    "close": CloseRequest,
}
INBOX_CAPACITY = 1024  # queries or liveliness events waiting for a dispatcher
DEPARTED_MEMORY = 4096  # how many vanished or reclaimed session ids are remembered
REAPER_PERIOD_S = 5.0  # the idle reaper looks this often (at timeout/4 for short timeouts)


def client_of(query: zenoh.Query, session: str) -> str:
    """Who sent ``query`` for ``session``, as far as the query says (module docstring, Quota)."""
    source = query.source_info
    if source is not None:
        return f"zenoh session {source.source_id.zid}"
    prefix, dash, _ = session.rpartition("-")
    return f"session prefix {prefix!r}" if dash and prefix else f"session {session!r}"


@dataclass
class _Job:
    session: str | None  # None when the key did not parse
    op: str  # reset | step | state | close | gone (client token deleted) | idle
    query: zenoh.Query | None = None
    payload: bytes = b""
    refusal: ProtocolError | None = None  # decided on receipt (a bad key, an oversized payload)
    client: str = ""


@dataclass
class _Pin:
    worker: int  # the worker (and so the child process) that serves the session
    pending: int = 0  # its jobs queued or running


@dataclass
class _Session:
    worker: int
    client: str  # client_of() its first reset
    episode: EpisodeLike | None  # None while the episode is being built
    token: Any = None  # liveliness: tidee/alive/session/{server}/{session}
    publisher: zenoh.Publisher | None = None
    last_request: float = dataclasses.field(default_factory=time.monotonic)  # receipt or answer
    reclaiming: bool = False  # an idle job is queued for it


class SimServer:
    """Serve episodes over Zenoh until ``stop()``.

    ``episode_factory``: None (default) runs real ``tidee.server.episode.Episode``s in
    ``config.process_count()`` child processes; an ``EpisodeProcesses`` runs its own episodes
    in its processes; any other callable builds an episode on the session's worker thread,
    in this process (``config.workers`` threads). The server stops the processes it uses.
    """

    def __init__(
        self,
        config: ServerConfig,
        episode_factory: Callable[[], EpisodeLike] | EpisodeProcesses | None = None,
    ) -> None:
        self.config = config
        if episode_factory is None:
            episode_factory = EpisodeProcesses(
                config.process_count(),
                config.renderer,
                name=f"tidee-sim-{config.server_id}",
                recycle_after=config.recycle_after,
            )
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
        self._lock = threading.Lock()  # guards _sessions, _announced, _departed, _reclaimed, _pins, _load
        # Sessions whose client token is up here: a client that chose this server declares it before
        # its first reset, so a second client choosing at the same moment counts it (ServerInfo).
        self._announced: set[str] = set()
        # Sessions whose client's token went away: a request the client sent just before it
        # vanished must not create a session nobody will ever free.
        self._departed: OrderedDict[str, None] = OrderedDict()
        # Sessions the idle reaper freed, with the message their next request gets.
        self._reclaimed: OrderedDict[str, str] = OrderedDict()
        self._stopping = threading.Event()
        self._reaper: threading.Thread | None = None
        # Which worker serves a session: set by its first job, kept while it lives or has jobs queued.
        self._pins: dict[str, _Pin] = {}
        self._load = [0] * workers  # pinned sessions per worker
        self._queues: list[queue.SimpleQueue[_Job | None]] = [queue.SimpleQueue() for _ in range(workers)]
        self._workers = [
            threading.Thread(target=self._work, args=(i,), name=f"tidee-sim-worker-{i}", daemon=True)
            for i in range(workers)
        ]
        self._z: zenoh.Session | None = None
        self._inbound: list[Any] = []  # queryable + liveliness subscriber
        self._dispatchers: list[threading.Thread] = []
        self._server_token: Any = None
        self._handlers: dict[str, Callable[[Any, str], Any]] = {
            "reset": self._reset,
            "step": self._step,
            "phase": self._phase,
            "state": self._state,
            "close": self._close,
        }

    # --- lifecycle ----------------------------------------------------------------------
    def start(self) -> SimServer:
        cfg = self.config
        self._z = zenoh.open(make_config(True, cfg.endpoint, cfg.router, cfg.zenoh_config))
        for worker in self._workers:
            worker.start()
        queries = self._z.declare_queryable(
            keys.sim_op_wildcard(cfg.server_id), zenoh.handlers.FifoChannel(INBOX_CAPACITY)
        )
        clients = self._z.liveliness().declare_subscriber(
            keys.alive_clients_wildcard(cfg.server_id),
            zenoh.handlers.FifoChannel(INBOX_CAPACITY),
            history=True,
        )
        info = self._z.declare_queryable(
            keys.server_info(cfg.server_id), zenoh.handlers.FifoChannel(INBOX_CAPACITY)
        )
        self._inbound = [queries, clients, info]
        self._dispatchers = [
            threading.Thread(
                target=self._dispatch, args=(queries, self._on_query), daemon=True, name="tidee-sim-queries"
            ),
            threading.Thread(
                target=self._dispatch,
                args=(clients, self._on_client_liveliness),
                daemon=True,
                name="tidee-sim-clients",
            ),
            # Answered on its own thread: a client choosing a server never waits behind an episode.
            threading.Thread(
                target=self._dispatch, args=(info, self._on_info), daemon=True, name="tidee-sim-info"
            ),
        ]
        for dispatcher in self._dispatchers:
            dispatcher.start()
        self._stopping.clear()
        if cfg.idle_timeout_s > 0:
            self._reaper = threading.Thread(target=self._reap_idle, daemon=True, name="tidee-sim-reaper")
            self._reaper.start()
        # Declared last: a client that sees this token can already reach the queryable.
        self._server_token = self._z.liveliness().declare_token(keys.alive_server(cfg.server_id))
        where = "a simulator process each" if self.processes is not None else "episodes in this process"
        log.info(
            "tidee server %r ready: max %d sessions, %d worker(s), %s",
            cfg.server_id,
            cfg.max_sessions,
            len(self._workers),
            where,
        )
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
        self._stopping.set()
        if self._reaper is not None:
            self._reaper.join()
            self._reaper = None
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
        # The size first: an oversized payload is never copied out of Zenoh's buffers.
        size, limit = (len(query.payload) if query.payload is not None else 0), self.config.max_request_bytes
        refusal, payload = None, b""
        if size > limit:
            refusal = ProtocolError(
                ErrorCode.oversized,
                f"request is {size} bytes, the limit is {limit} "
                f"(max_request_bytes); requests carry no arrays",
            )
        elif query.payload is not None:
            payload = query.payload.to_bytes()
        try:
            _, session, op = keys.parse_sim_op(key)
        except ValueError as e:
            refusal = ProtocolError(ErrorCode.malformed, str(e))
            self._queues[0].put(_Job(None, "invalid", query, refusal=refusal))
            return
        job = _Job(session, op, query, payload, refusal, client_of(query, session))
        self._route(session, touch=True).put(job)

    def _on_info(self, query: zenoh.Query) -> None:
        """A client choosing a server: how full this one is, and whether it holds the asked session."""
        try:
            size = len(query.payload) if query.payload is not None else 0
            if size > self.config.max_request_bytes:
                raise ProtocolError(ErrorCode.oversized, f"info request is {size} bytes")
            payload = query.payload.to_bytes() if query.payload is not None else b""
            request = decode(payload, max_bytes=self.config.max_request_bytes, expected=ServerInfoRequest)
            with self._lock:  # held, being opened, or announced by another client's token
                holds = request.session is not None and request.session in self._sessions
                coming = self._announced.difference(self._sessions, [request.session])
                held = len(self._sessions) + len(coming)
            reply = encode(ServerInfo(self.config.server_id, held, self.config.max_sessions, holds))
            query.reply(keys.server_info(self.config.server_id), reply)
        except ProtocolError as e:
            query.reply_err(encode(ErrorReply(e.code, e.message)))
        finally:
            query.drop()

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
                self._announced.discard(session)
                self._departed[session] = None
                while len(self._departed) > DEPARTED_MEMORY:
                    self._departed.popitem(last=False)
            else:  # a (new) client declared this session id
                self._departed.pop(session, None)
                if len(self._announced) < DEPARTED_MEMORY:  # bounded whatever clients declare
                    self._announced.add(session)
        if gone:
            self._route(session).put(_Job(session, "gone"))

    def _route(self, session: str, touch: bool = False) -> queue.SimpleQueue[_Job | None]:
        """The queue of the session's worker: its pinned one, else the least loaded (pinned now).

        ``touch``: a request arrived for it, so it is not idle.
        """
        with self._lock:
            entry = self._sessions.get(session)
            if touch and entry is not None:
                entry.last_request = time.monotonic()
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
            entry = self._sessions.get(session)
            if entry is not None:  # idle from the end of its last request, however long that took
                entry.last_request = time.monotonic()
            if pin.pending == 0 and entry is None:
                del self._pins[session]
                self._load[pin.worker] -= 1

    # --- workers ------------------------------------------------------------------------
    def _work(self, index: int) -> None:
        q = self._queues[index]
        while (job := q.get()) is not None:
            if job.op == "gone":
                if self._free(job.session):  # type: ignore[arg-type]
                    log.info("session %s: client gone, freed", job.session)
            elif job.op == "idle":
                self._reclaim(job.session)  # type: ignore[arg-type]
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
            reply = self._handlers[job.op](request, job.client)
        except ProtocolError as e:
            reply = ErrorReply(e.code, e.message, job.session)
        except Exception as e:  # an episode's bug must not take the server or other sessions down
            log.exception("session %s: %s failed", job.session, job.op)
            reply = ErrorReply(ErrorCode.internal, f"{job.op} failed: {type(e).__name__}: {e}", job.session)
        self._send(job, reply, encoding)

    def _parse(self, job: _Job) -> Any:
        if job.refusal is not None:
            raise job.refusal
        request = decode(job.payload, max_bytes=self.config.max_request_bytes, expected=REQUEST_TYPES[job.op])
        if request.session != job.session:
            raise ProtocolError(
                ErrorCode.invalid_field,
                f"field 'session' is {request.session!r} but the key names session {job.session!r}",
            )
        return request

    def _send(self, job: _Job, reply: Any, encoding: str) -> None:
        query = job.query
        assert query is not None
        try:
            raw_depth = "f32"
            try:
                # Depth under raw: float32, or uint16 mm with TIDEE_WIRE_DEPTH=mm (codec.wire_depth).
                raw_depth = wire_depth()
                # One join into bytes, one copy into Zenoh (ZBytes cannot wrap a Python buffer);
                # the reply and the feed then share that ZBytes (put/reply take a reference).
                frame = (
                    reply.frame
                    if isinstance(reply, EncodedObservation)
                    else encode(reply, encoding, raw_depth=raw_depth)
                )
                payload = zenoh.ZBytes(frame)
            except Exception as e:  # e.g. an episode returned a depth map of the wrong dtype
                log.exception("session %s: cannot encode the %s reply", job.session, job.op)
                reply = ErrorReply(ErrorCode.internal, f"cannot encode the reply: {e}", job.session)
                payload = zenoh.ZBytes(encode(reply))
            if isinstance(reply, ErrorReply):
                query.reply_err(payload)
            else:
                query.reply(query.key_expr, payload)  # congestion control: the query's (BLOCK)
            if isinstance(reply, (Observation, EncodedObservation)):
                self._publish(job.session, reply, payload, encoding, raw_depth)  # type: ignore[arg-type]
        except Exception:
            log.exception("session %s: could not reply to %s", job.session, job.op)
        finally:
            query.drop()  # sends the final answer now rather than when Python collects the query

    def _feed(self, session: str) -> Any:
        """The session's viewer-feed publisher (None when it has none)."""
        with self._lock:
            entry = self._sessions.get(session)
        return None if entry is None else entry.publisher

    @staticmethod
    def _listened(publisher: Any) -> bool:
        status: Any = publisher.matching_status  # a MatchingStatus (zenoh's stubs say bool)
        return bool(status.matching)

    def _publish(
        self,
        session: str,
        obs: Observation | EncodedObservation,
        frame: zenoh.ZBytes,
        encoding: str,
        raw_depth: str = "f32",
    ) -> None:
        """The viewer feed: the same frame, minus any privileged ground truth (encoded here, or
        by the child that made it when a viewer listened then; none when no viewer listens)."""
        publisher = self._feed(session)
        if publisher is None:
            return
        if isinstance(obs, EncodedObservation) and obs.private:
            if obs.feed is None:
                return
            frame = zenoh.ZBytes(obs.feed)
        elif isinstance(obs, Observation) and obs.ground_truth is not None:
            if not self._listened(publisher):
                return  # no viewer listens: spare the second encode (and its copies)
            stripped = dataclasses.replace(obs, ground_truth=None)
            frame = zenoh.ZBytes(encode(stripped, encoding, raw_depth=raw_depth))
        publisher.put(frame)

    # --- requests (on the session's worker) ----------------------------------------------
    # Each takes the request and its client (client_of): a reset may open a session for it, and
    # only the client that opened a session may reset, step, advance or close it (state is read
    # by evaluators too; a router's access control decides who may ask).
    def _observe(
        self, request: Any, episode: EpisodeLike, op: str, *args: Any, **kwargs: Any
    ) -> Observation | EncodedObservation:
        """``op`` on the episode; one in a child process encodes its observation there, in the
        form the request asked for (``tidee.server.workers``, Frames)."""
        kwargs["ground_truth"] = request.ground_truth
        if not isinstance(episode, RemoteEpisode):
            return getattr(episode, op)(*args, **kwargs)
        wire = Wire(
            request.encoding,
            wire_depth(),
            feed=request.ground_truth and self._viewer_listens(request.session),
        )
        return episode.encoded(wire, op, *args, **kwargs)

    def _viewer_listens(self, session: str) -> bool:
        publisher = self._feed(session)
        return publisher is not None and self._listened(publisher)

    def _reset(self, request: ResetRequest, client: str) -> Observation | EncodedObservation:
        for name in ("mess_index", "rearrange_index"):
            try:
                check_mess_index(request.spec.seed, getattr(request.spec, name))
            except ValueError as e:
                raise ProtocolError(ErrorCode.invalid_field, f"field 'spec.{name}': {e}") from None
        episode = self._episode(request.session, client, create=True)
        return self._observe(request, episode, "reset", request.spec, session=request.session)

    def _step(self, request: StepRequest, client: str) -> Observation | EncodedObservation:
        episode = self._episode(request.session, client)
        return self._observe(request, episode, "step", request.action)

    def _phase(self, request: PhaseRequest, client: str) -> Observation | EncodedObservation:
        episode = self._episode(request.session, client)
        try:
            return self._observe(request, episode, "begin_unshuffle")
        except ValueError as e:  # not a rearrangement, or the unshuffle already begun
            raise ProtocolError(ErrorCode.invalid_field, f"field 'phase': {e}") from None

    def _state(self, request: StateRequest, client: str) -> StateReply:
        return StateReply(request.session, self._episode(request.session).state())

    def _close(self, request: CloseRequest, client: str) -> CloseReply:
        with self._lock:
            entry = self._sessions.get(request.session)
            if entry is not None:
                self._check_owner(request.session, entry, client)
        closed = self._free(request.session)
        if closed:
            log.info("session %s: closed by its client", request.session)
        return CloseReply(request.session, closed)

    # --- sessions -------------------------------------------------------------------------
    def _check_owner(self, session: str, entry: _Session, client: str) -> None:
        """Refuse, by name, a client other than the one that opened ``session``."""
        if entry.client != client:
            raise ProtocolError(
                ErrorCode.invalid_field,
                f"field 'session': session {session!r} is held by another client on server "
                f"{self.config.server_id!r}; use another session id (tidee agent --session)",
            )

    def _episode(self, session: str, client: str | None = None, create: bool = False) -> EpisodeLike:
        """The session's episode. ``client``: who asks; when given, only the session's own client
        gets it. ``create``: open the session for ``client`` if there is none (a reset)."""
        cfg = self.config
        create_for = client if create else None
        if create_for is not None and session in self._departed:
            self._readmit_if_alive(session)
        with self._lock:
            entry = self._sessions.get(session)
            if entry is not None and client is not None:
                self._check_owner(session, entry, client)
            if entry is None and create_for is not None:
                if session in self._departed:
                    raise ProtocolError(
                        ErrorCode.unknown_session, f"the client of session {session!r} has disconnected"
                    )
                if len(self._sessions) >= cfg.max_sessions:
                    raise ProtocolError(
                        ErrorCode.server_busy,
                        f"server {cfg.server_id!r} holds {len(self._sessions)} sessions, its "
                        f"maximum (max_sessions); close one or start another server",
                    )
                held = sum(1 for other in self._sessions.values() if other.client == create_for)
                if held >= cfg.max_sessions_per_client:
                    raise ProtocolError(
                        ErrorCode.server_busy,
                        f"{create_for} holds {held} sessions on server {cfg.server_id!r}, its quota "
                        f"(max_sessions_per_client={cfg.max_sessions_per_client}); close one of them first",
                    )
                self._reclaimed.pop(session, None)  # a reset starts afresh, as after a close
                worker = self._pins[session].worker
                entry = self._sessions[session] = _Session(worker, create_for, episode=None)  # reserve a slot
            reclaimed = self._reclaimed.get(session) if entry is None else None
        if reclaimed is not None:
            raise ProtocolError(ErrorCode.unknown_session, reclaimed)
        if entry is None:
            raise ProtocolError(
                ErrorCode.unknown_session,
                f"no session {session!r} on server {cfg.server_id!r}: send reset first (or it was closed)",
            )
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
            entry.publisher = self._z.declare_publisher(
                keys.observations(server_id, session), congestion_control=zenoh.CongestionControl.DROP
            )
            log.info(
                "session %s: opened (%d held), renderer %s",
                session,
                len(self.sessions),
                getattr(entry.episode, "renderer", "?"),
            )
        return entry.episode

    def _readmit_if_alive(self, session: str) -> None:
        """Forget that ``session``'s client left if a client token for it is declared now: a new
        client may reuse the id, and its reset can arrive before the server sees its token."""
        assert self._z is not None
        replies = self._z.liveliness().get(keys.alive_client(self.config.server_id, session), timeout=1.0)
        if any(reply.ok is not None for reply in replies):
            with self._lock:
                self._departed.pop(session, None)

    def _reap_idle(self) -> None:
        """Reaper thread: queue an ``idle`` job for each session idle past the timeout."""
        timeout = self.config.idle_timeout_s
        while not self._stopping.wait(min(timeout / 4, REAPER_PERIOD_S)):
            now = time.monotonic()
            with self._lock:
                idle = [
                    session
                    for session, entry in self._sessions.items()
                    if entry.episode is not None
                    and not entry.reclaiming
                    and now - entry.last_request >= timeout
                    and self._pins[session].pending == 0
                ]
                for session in idle:
                    self._sessions[session].reclaiming = True
            for session in idle:  # on the session's worker: only that thread touches its episode
                self._route(session).put(_Job(session, "idle"))

    def _reclaim(self, session: str) -> None:
        """Free ``session`` if it is still idle (a request may have come since the reaper looked)."""
        timeout = self.config.idle_timeout_s
        with self._lock:
            entry = self._sessions.get(session)
            if entry is None:
                return
            entry.reclaiming = False
            idle_s = time.monotonic() - entry.last_request
            if idle_s < timeout:
                return
            self._reclaimed[session] = (
                f"session {session!r} was reclaimed after {timeout:g} s idle "
                f"(idle_timeout_s on server {self.config.server_id!r}); "
                f"send reset to start a new episode"
            )
            while len(self._reclaimed) > DEPARTED_MEMORY:
                self._reclaimed.popitem(last=False)
        if self._free(session):
            log.info("session %s: reclaimed after %.0f s without a request", session, idle_s)

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


def serve(
    config: ServerConfig, episode_factory: Callable[[], EpisodeLike] | EpisodeProcesses | None = None
) -> None:
    """Run a server until SIGINT or SIGTERM, then shut it down cleanly."""
    from tidee.launch import wait_for_signal

    server = SimServer(config, episode_factory).start()
    try:
        wait_for_signal()
    finally:
        server.stop()
