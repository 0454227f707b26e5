"""Episodes in child processes: N sessions simulate on N cores instead of sharing one GIL.

An :class:`EpisodeProcess` runs a child process (``multiprocessing``, "spawn" context: no
forked Zenoh or GL state; a fresh one after the last died or retired, see Recycling) that hosts
any number of episodes, each under an integer id, and executes ``open`` / ``reset`` / ``step`` /
``state`` / ``close`` sent over a Pipe, one request at a time. Its episodes share one
``SceneLibrary`` (and so its in-memory LRU; the on-disk scene cache is shared by every
process), and a closed real episode is kept for the next ``open`` (PyBullet does not give
back all of a disconnected client's memory). A :class:`RemoteEpisode` is the parent's handle on
one of them: it implements ``EpisodeLike``, so the server holds it exactly as it would hold an
``Episode``. :class:`EpisodeProcesses` is the server's set of them, one per worker thread; the
thread with index *i* is the only one that talks to process *i* (and to its retiring children),
so a pipe is never shared between threads and needs no lock.

Recycling: PyBullet keeps part of every collision mesh it was ever given (the vertices of each
``createCollisionShape(GEOM_MESH, vertices=...)``; neither ``resetSimulation`` nor a disconnect
frees them), so a simulator process grows about 70-150 kB with every reset. A child that has
run ``recycle_after`` resets *retires*: it takes no new episode (the next ``open`` starts a
fresh child beside it), an episode of it that is reset moves to the fresh child (a reset starts
over anyway, from the same deterministic spec, so the frames are the same), and it is stopped
once its last episode is closed or has moved. An episode that is only stepped is never moved:
a live session is not disturbed, its child just lives on until that session resets or ends.

Frames: the server asks for an observation *encoded* (``RemoteEpisode.encoded``: the op, and
the wire form its client asked for). The child encodes it itself (the protocol codec; also the
viewer feed's copy without ground truth when one is wanted) into a shared-memory block it owns
(``multiprocessing.shared_memory``; a bigger one replaces it when a frame does not fit) and
sends only the block's name and the frames' lengths down the pipe; the parent copies the bytes
out before its next request. A 256² frame is 450 KB: through the pipe it took several
round trips of the socket's buffer between the two processes, and a pickle and an encode in the
parent. The parent unlinks a dead child's block; a child unlinks its own when it exits.

Errors: an exception raised in the child is pickled and raised again in the parent with its
type and message (the child's traceback rides along as its ``__cause__``, as in
``concurrent.futures``); one that cannot make the trip becomes a :class:`RemoteEpisodeError`
naming the original type. A child that dies (killed, out of memory, a crash in native code)
makes the next request of each of its episodes raise :class:`EpisodeProcessDied`; a fresh
child is started for the next episode opened, and a ``reset`` of an episode that lived there
reopens it in the new process (as an episode's exception leaves its session usable for a new
reset).

Children ignore SIGINT (a Ctrl-C reaches the whole process group; the parent decides when
they stop) and exit when asked, or when the pipe closes because the parent is gone, so a
killed server leaves no simulator behind once the child's current request is done.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from multiprocessing import shared_memory
from typing import Any

from tidee.protocol.codec import encode
from tidee.protocol.messages import Action, EpisodeSpec, Observation

log = logging.getLogger("tidee.server")

EpisodeMaker = Callable[[], Any]  # picklable (a module-level class or function, or a partial of one)
_CONTEXT = multiprocessing.get_context("spawn")
_STOP_GRACE_S = 5.0
_OPS = ("reset", "step", "begin_unshuffle", "state")
_OBSERVING = ("reset", "step", "begin_unshuffle")  # the ops ``RemoteEpisode.encoded`` may run
MIN_FRAME_AREA = 1 << 20  # bytes: the smallest shared-memory block for encoded frames


class EpisodeProcessDied(RuntimeError):
    """The child process that held an episode is gone; the episode's state went with it."""


class RemoteEpisodeError(RuntimeError):
    """An exception from the child that could not be pickled; the message names its type."""


class _RemoteTraceback(Exception):
    """Carries the child's formatted traceback into the parent's log (as ``__cause__``)."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text

    def __str__(self) -> str:
        return self.text


@dataclass(frozen=True)
class Wire:
    """How the server wants an observation encoded (``tidee.protocol.codec.encode``'s
    ``encoding`` and ``raw_depth``), and whether the viewer feed's copy without ground truth is
    wanted too (a viewer listens and the observation carries ground truth)."""

    encoding: str = "raw"
    raw_depth: str = "f32"
    feed: bool = False


@dataclass(frozen=True)
class EncodedObservation:
    """An observation as the child encoded it: ``frame`` for the client; ``private``: it holds
    ground truth, so the viewer feed gets ``feed`` (the same without it; None when not asked
    for) instead."""

    frame: bytes
    private: bool
    feed: bytes | None = None


@dataclass(frozen=True)
class _Frames:
    """The child's answer to an ``observe``: where the encoded frames lie (block, lengths)."""

    area: str
    lengths: tuple[int, ...]
    private: bool


class _FrameArea:
    """The child's shared memory for encoded frames (module docstring, Frames)."""

    def __init__(self) -> None:
        self.shm: shared_memory.SharedMemory | None = None

    def put(self, obs: Observation, wire: Wire) -> _Frames:
        private = obs.ground_truth is not None
        frames = [encode(obs, wire.encoding, raw_depth=wire.raw_depth)]
        if private and wire.feed:
            frames.append(encode(replace(obs, ground_truth=None), wire.encoding, raw_depth=wire.raw_depth))
        need = sum(len(f) for f in frames)
        if self.shm is None or self.shm.size < need:
            self.close()
            self.shm = shared_memory.SharedMemory(create=True, size=max(MIN_FRAME_AREA, need + need // 4))
        buf, at = self.shm.buf, 0
        assert buf is not None
        for f in frames:
            buf[at : at + len(f)] = f
            at += len(f)
        return _Frames(self.shm.name, tuple(len(f) for f in frames), private)

    def close(self) -> None:
        if self.shm is not None:
            self.shm.close()
            self.shm.unlink()
            self.shm = None


class _FrameReader:
    """The parent's view of one child's frame area: attached by name, re-attached when the child
    replaced it; ``read`` copies the frames out."""

    def __init__(self) -> None:
        self.shm: shared_memory.SharedMemory | None = None

    def read(self, frames: _Frames) -> EncodedObservation:
        if self.shm is None or self.shm.name != frames.area:
            self.close()
            # Attaching registers the name with the resource tracker the child already told (one
            # set of names per tracker): the child's unlink unregisters it for both.
            self.shm = shared_memory.SharedMemory(name=frames.area)
        buf, at, out = self.shm.buf, 0, []
        assert buf is not None
        for n in frames.lengths:
            out.append(bytes(buf[at : at + n]))
            at += n
        return EncodedObservation(out[0], frames.private, out[1] if len(out) > 1 else None)

    def close(self, unlink: bool = False) -> None:
        """Detach; ``unlink``: remove the block too (its child died without doing it)."""
        if self.shm is None:
            return
        self.shm.close()
        if unlink:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass
        self.shm = None


# --- the child ------------------------------------------------------------------------------
def _child_main(
    conn: multiprocessing.connection.Connection, renderer: str, make_episode: EpisodeMaker | None
) -> None:
    """Serve requests from ``conn`` until told to stop (``None``) or the parent goes away."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # PyBullet keeps about 0.3 MB of every client it ever connected, so a real Episode (which
    # starts afresh at every reset, and is only ever opened to be reset) is kept when closed and
    # handed to the next open: spares never outnumber the most episodes this child held at once.
    reuse = make_episode is None
    spares: list[Any] = []
    if make_episode is None:
        from tidee.server.episode import Episode, SceneLibrary

        library = SceneLibrary()

        def make_episode() -> Any:
            return Episode(renderer=renderer, library=library)

    episodes: dict[int, Any] = {}
    frames = _FrameArea()
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            break
        if request is None:
            break
        op, episode_id, args, kwargs = request
        try:
            if op == "open":
                episode = episodes[episode_id] = spares.pop() if spares else make_episode()
                value: Any = getattr(episode, "renderer", renderer)
            elif op == "close":
                episode = episodes.pop(episode_id, None)
                value = None
                if episode is not None and reuse:
                    spares.append(episode)
                elif episode is not None:
                    value = episode.close()
            elif op == "observe":  # args: (Wire, the op, its arguments...)
                wire, op, *args = args
                if op not in _OBSERVING:
                    raise ValueError(f"cannot observe {op!r}; expected one of {_OBSERVING}")
                value = frames.put(getattr(episodes[episode_id], op)(*args, **kwargs), wire)
            elif op in _OPS:
                value = getattr(episodes[episode_id], op)(*args, **kwargs)
            else:
                raise ValueError(f"unknown episode request {op!r}; expected open, close or one of {_OPS}")
            reply: tuple = (True, value)
        except Exception as e:
            reply = (False, _portable(e), traceback.format_exc())
        try:
            conn.send(reply)
        except (BrokenPipeError, EOFError):
            break
        except Exception as e:  # the value would not pickle: say so instead of leaving the parent waiting
            conn.send(
                (
                    False,
                    RemoteEpisodeError(f"cannot send the {op} result to the server: {type(e).__name__}: {e}"),
                    traceback.format_exc(),
                )
            )
    for episode in [*episodes.values(), *spares]:
        try:
            episode.close()
        except Exception:
            pass
    frames.close()


def _portable(e: Exception) -> Exception:
    """``e`` if it survives pickling with its type and message, else a stand-in that names it."""
    try:
        back = pickle.loads(pickle.dumps(e))
        if type(back) is type(e) and str(back) == str(e):
            return e
    except Exception:
        pass
    return RemoteEpisodeError(f"{type(e).__name__}: {e}")


# --- the parent -----------------------------------------------------------------------------
class _Child:
    """One simulator process as the parent sees it: its pipe, the episodes it holds, its resets."""

    def __init__(self, process: Any, conn: multiprocessing.connection.Connection, generation: int) -> None:
        self.process = process
        self.conn = conn
        self.generation = generation
        self.episodes: set[int] = set()
        self.resets = 0
        self.frames = _FrameReader()

    @property
    def alive(self) -> bool:
        return self.process.is_alive()


class EpisodeProcess:
    """Episodes in a child process, started on the first ``open()``, again after it dies or retires.

    Not thread-safe: one thread (the server's worker *i*) talks to it and to every child it runs.
    ``make_episode``: builds an episode in the child (picklable); default: a real ``Episode``
    with ``renderer`` and the child's shared ``SceneLibrary``. ``recycle_after``: resets a child
    runs before it retires (0: never; module docstring, Recycling).
    """

    def __init__(
        self,
        renderer: str = "tiny",
        make_episode: EpisodeMaker | None = None,
        name: str = "tidee-sim",
        recycle_after: int = 0,
    ) -> None:
        if recycle_after < 0:
            raise ValueError(f"recycle_after must be >= 0 (0: never), got {recycle_after}")
        self.renderer = renderer
        self.make_episode = make_episode
        self.name = name
        self.recycle_after = recycle_after
        self.generation = 0  # bumped at every start: episodes of another generation live elsewhere
        self.started = 0  # children started so far (the first, fresh ones after deaths and retirements)
        self._current: _Child | None = None  # the child new episodes go to
        self._retiring: dict[int, _Child] = {}  # generation -> a retired child still holding episodes
        self._ids = itertools.count()
        self._deaths: dict[int, str] = {}  # generation -> how that child ended

    @property
    def pid(self) -> int | None:
        """The pid of the live child that takes new episodes (None before the first start, or once
        it has died or retired)."""
        current = self._current
        return current.process.pid if current is not None and current.alive else None

    @property
    def pids(self) -> list[int]:
        """Every live child: the current one and those retiring."""
        children = [self._current, *self._retiring.values()]
        return [c.process.pid for c in children if c is not None and c.alive]

    @property
    def alive(self) -> bool:
        return self._current is not None and self._current.alive

    def takes(self, generation: int) -> bool:
        """Whether the child of ``generation`` is the live one that takes new episodes."""
        return self.alive and self._current is not None and self._current.generation == generation

    def open(self) -> RemoteEpisode:
        """A new episode in the current child (starting a fresh one if there is none)."""
        if not self.alive:
            self._start()
        child = self._current
        assert child is not None
        episode_id = next(self._ids)
        renderer = self.call(child.generation, "open", episode_id)
        child.episodes.add(episode_id)
        return RemoteEpisode(self, episode_id, child.generation, renderer)

    def call(self, generation: int, op: str, episode_id: int, *args: Any, **kwargs: Any) -> Any:
        """Run ``op`` on an episode in the child of ``generation``; its exception is raised here."""
        child = self._child(generation)
        if child is None:
            raise self._died_error(generation)
        try:
            child.conn.send((op, episode_id, args, kwargs))
            ok, value, *child_traceback = child.conn.recv()
        except (EOFError, OSError):  # BrokenPipeError, ConnectionResetError: the child is gone
            self._reap(child)
            raise self._died_error(generation) from None
        if op == "close":
            child.episodes.discard(episode_id)
            if child.generation in self._retiring and not child.episodes:
                self._stop(child, "retired")
        if not ok:
            value.__cause__ = _RemoteTraceback(child_traceback[0])
            raise value
        if isinstance(value, _Frames):  # copied out before the child's next frame overwrites them
            value = child.frames.read(value)
        if op == "reset" or (op == "observe" and args[1] == "reset"):
            child.resets += 1
            if child is self._current and 0 < self.recycle_after <= child.resets:
                self._retire(child)
        return value

    def stop(self) -> None:
        """Ask every child to close its episodes and exit; terminate one that does not."""
        for child in [*self._retiring.values(), self._current]:
            if child is not None:
                self._stop(child, "was stopped")

    def _child(self, generation: int) -> _Child | None:
        current = self._current
        if current is not None and current.generation == generation:
            return current
        return self._retiring.get(generation)

    def _start(self) -> None:
        if self._current is not None:  # dead: forget it
            self._reap(self._current)
        parent_end, child_end = _CONTEXT.Pipe()
        process = _CONTEXT.Process(
            target=_child_main,
            args=(child_end, self.renderer, self.make_episode),
            name=self.name,
            daemon=True,
        )
        process.start()
        child_end.close()  # else the parent's copy keeps the pipe open and a dead child is never noticed
        self.generation += 1
        self.started += 1
        self._current = _Child(process, parent_end, self.generation)
        log.info("%s: started simulator process pid %d", self.name, process.pid)

    def _retire(self, child: _Child) -> None:
        """``child`` takes no new episode; stopped at once if it holds none, else when its last goes."""
        self._current = None
        if not child.episodes:
            self._stop(child, "retired")
            return
        self._retiring[child.generation] = child
        log.info(
            "%s: simulator process pid %d retires after %d resets; %d episode(s) stay until they "
            "end or reset",
            self.name,
            child.process.pid,
            child.resets,
            len(child.episodes),
        )

    def _stop(self, child: _Child, how: str) -> None:
        """Ask ``child`` to close its episodes and exit; terminate it if it does not."""
        try:
            child.conn.send(None)
        except (OSError, EOFError):
            pass
        process = child.process
        process.join(_STOP_GRACE_S)
        if process.is_alive():
            log.warning(
                "%s (pid %d) did not exit in %.0f s; terminating it", self.name, process.pid, _STOP_GRACE_S
            )
            process.terminate()
            process.join(2.0)
        if process.is_alive():
            process.kill()
            process.join()
        if how == "retired":
            log.info("%s: retired simulator process pid %d stopped", self.name, process.pid)
        self._reap(child, how)

    def _reap(self, child: _Child, stopped: str | None = None) -> None:
        """Forget a dead (or ``stopped``: "was stopped", "retired") child, remembering how it ended."""
        child.conn.close()
        if self._current is child:
            self._current = None
        self._retiring.pop(child.generation, None)
        process = child.process
        process.join(1.0)
        if process.is_alive():  # its pipe broke but it runs on: it can serve nobody now
            process.kill()
            process.join()
        code = process.exitcode
        child.frames.close(unlink=code != 0)  # a child that did not exit cleanly left its block behind
        how = f"killed by {_signal_name(-code)}" if code < 0 else f"exit code {code}"
        self._deaths[child.generation] = f"{self.name} (pid {process.pid}) " + (stopped or f"died: {how}")
        if stopped is None:
            log.error("simulator process %s", self._deaths[child.generation])
        process.close()

    def _died_error(self, generation: int) -> EpisodeProcessDied:
        how = self._deaths.get(generation, f"{self.name} is not running")
        return EpisodeProcessDied(
            f"the simulator process that held this episode is gone ({how}); the "
            f"episode is lost: send reset to start it again in a new process"
        )


class RemoteEpisode:
    """``EpisodeLike`` for an episode that lives in a child of an :class:`EpisodeProcess`."""

    def __init__(self, process: EpisodeProcess, episode_id: int, generation: int, renderer: str) -> None:
        self.process = process
        self.episode_id = episode_id
        self.generation = generation
        self.renderer = renderer
        self.pid = process.pid

    def reset(self, spec: EpisodeSpec, session: str = "local", ground_truth: bool = False) -> Observation:
        if not self.process.takes(self.generation):
            # Its child died or retired: start over in the current one, as a reset starts over anyway.
            self.close()
            self._reopen()
        return self._call("reset", spec, session=session, ground_truth=ground_truth)

    def step(self, action: Action, ground_truth: bool = False) -> Observation:
        return self._call("step", action, ground_truth=ground_truth)

    def begin_unshuffle(self, ground_truth: bool = False) -> Observation:
        return self._call("begin_unshuffle", ground_truth=ground_truth)

    def state(self) -> dict[str, Any]:
        return self._call("state")

    def encoded(self, wire: Wire, op: str, *args: Any, **kwargs: Any) -> EncodedObservation:
        """``op`` (reset, step or begin_unshuffle) with its arguments, its observation encoded by
        the child as ``wire`` says (module docstring, Frames)."""
        if op == "reset" and not self.process.takes(self.generation):
            self.close()
            self._reopen()
        return self._call("observe", wire, op, *args, **kwargs)

    def close(self) -> None:
        try:
            self._call("close")
        except EpisodeProcessDied:
            pass

    def _call(self, op: str, *args: Any, **kwargs: Any) -> Any:
        return self.process.call(self.generation, op, self.episode_id, *args, **kwargs)

    def _reopen(self) -> None:
        fresh = self.process.open()
        self.episode_id, self.generation, self.renderer, self.pid = (
            fresh.episode_id,
            fresh.generation,
            fresh.renderer,
            fresh.pid,
        )


class EpisodeProcesses:
    """The server's child processes: ``open(i)`` makes an episode in process ``i``.

    Processes start lazily, on their first episode, so a server sized for every core costs
    nothing until sessions arrive. ``make_episode`` and ``recycle_after``: see
    :class:`EpisodeProcess` (tests pass a fake episode class here to run the process machinery
    without physics).
    """

    def __init__(
        self,
        processes: int,
        renderer: str = "tiny",
        make_episode: EpisodeMaker | None = None,
        name: str = "tidee-sim",
        recycle_after: int = 0,
    ) -> None:
        if processes < 1:
            raise ValueError(f"processes must be >= 1, got {processes}")
        self.processes = [
            EpisodeProcess(renderer, make_episode, name=f"{name}-{i}", recycle_after=recycle_after)
            for i in range(processes)
        ]

    def __len__(self) -> int:
        return len(self.processes)

    def open(self, index: int) -> RemoteEpisode:
        return self.processes[index].open()

    def stop(self, index: int) -> None:
        self.processes[index].stop()

    @property
    def pids(self) -> list[int | None]:
        """Per slot, the child that takes new episodes (None: none running)."""
        return [p.pid for p in self.processes]


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which a container or taskset narrows)."""
    return len(os.sched_getaffinity(0))
