"""``tidee agent``: the agent as its own process, talking to a server over Zenoh.

It opens one Zenoh session, uses it for the simulator client (reset/step) and for the
telemetry publisher (viewers), and plays episodes: the one given on the command line,
then, with ``--serve``, whatever a viewer asks for (``new_episode`` commands) until
interrupted. Episode logs go to ``--log-dir``.
"""

from __future__ import annotations

import logging
import signal
import sys
import time
import uuid
from typing import TYPE_CHECKING

from tidee.agent.config import AgentProcessConfig
from tidee.agent.perception import DETECTOR_SETS
from tidee.agent.telemetry import TelemetryPublisher
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.messages import AgentCommand, EpisodeSpec, ErrorCode
from tidee.protocol.zenoh_config import ZenohOpenError, open_session

if TYPE_CHECKING:
    from tidee.agent.runner import EpisodeResult, EpisodeRunner

log = logging.getLogger("tidee.agent")

MAX_RECONNECTS = 3  # re-runs of one episode after its server went away


def run_agent_process(cfg: AgentProcessConfig) -> int:
    session = cfg.session or f"agent-{uuid.uuid4().hex[:8]}"
    stop = {"flag": False}

    def _sigterm(*_: object) -> None:
        stop["flag"] = True
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _sigterm)
    try:
        z = open_session(False, cfg.endpoint, cfg.router, cfg.zenoh_config)
    except ZenohOpenError as e:  # a bad endpoint, an unreachable router
        print(f"agent: error: {e}", file=sys.stderr, flush=True)
        return 1
    # The episode loop (torch, the models) loads only once Zenoh is up: a wrong endpoint is told in seconds.
    from tidee.agent.runner import EpisodeRunner, format_summary

    publisher = None
    try:
        client = SimClient(
            cfg.endpoint,
            cfg.router,
            server_id=cfg.server_id,
            session=session,
            timeout=120.0,
            zsession=z,
            connect_timeout=cfg.connect_timeout,
            zenoh_config=cfg.zenoh_config,
        )
        publisher = TelemetryPublisher(z, session)
        step = {"last": 0}  # the episode's last step, for the "went away" line

        def _on_step(n: int) -> None:
            step["last"] = n

        runner = EpisodeRunner(
            cfg.agent, client, session=session, publisher=publisher, log_dir=cfg.log_dir, on_step=_on_step
        )
        chosen = " (chosen: the live server with the most room)" if client.auto else ""
        print(
            f"agent: session {session} on server {client.server_id!r}{chosen}, variant {cfg.agent.variant}, "
            f"perception {cfg.agent.perception}{' (ORACLE)' if cfg.agent.perception == 'oracle' else ''}"
            f"{'' if cfg.agent.detector == DETECTOR_SETS[0] else f', detector {cfg.agent.detector}'}; "
            f"logs in {cfg.log_dir}",
            flush=True,
        )
        queue: list[EpisodeSpec] = []
        base = cfg.spec
        for k in range(cfg.episodes):
            mess = None if base.mess_index is None else base.mess_index + k
            queue.append(EpisodeSpec(**{**base.__dict__, "mess_index": mess}))
        while not stop["flag"]:
            if not queue:
                if not cfg.serve:
                    break
                cmd = _wait_for_new_episode(publisher)
                queue.append(_spec_from(cmd, base))
            spec = queue.pop(0)
            res = _run_until_done(runner, client, spec, cfg, step)
            assert res.summary is not None
            print(f"agent: {format_summary(res.summary)}", flush=True)
            if res.aborted_by is not None:
                queue.insert(0, _spec_from(res.aborted_by, base))
        client.close()
        return 0
    except KeyboardInterrupt:
        print("agent: stopped (the episode in progress is not scored)", flush=True)
        return 0 if stop["flag"] else 130
    except (TimeoutError, RemoteError) as e:  # the server went away, or refused the episode
        print(f"agent: error: {e}", file=sys.stderr, flush=True)
        return 1
    finally:
        if publisher is not None:
            publisher.close()
        z.close()


def _run_until_done(
    runner: EpisodeRunner, client: SimClient, spec: EpisodeSpec, cfg: AgentProcessConfig, step: dict[str, int]
) -> EpisodeResult:
    """Play ``spec``; if its server goes away, play the episode again from the start: on another
    live server when the agent chose its server (``--server-id auto``), else on the same one once
    it is back. Either wait is bounded by ``--reconnect-timeout``.

    The reset of a re-run opens a new session there, and the runner's new log writer replaces
    the aborted run's log (same episode name).
    """
    for attempt in range(MAX_RECONNECTS + 1):
        step["last"] = 0
        try:
            return runner.run(spec, evaluate=cfg.score)
        except (TimeoutError, RemoteError) as e:
            if attempt == MAX_RECONNECTS or cfg.reconnect_timeout <= 0 or not _server_went_away(e):
                raise
            log.debug("episode failed: %s", e)
            # A server that still answers but did not answer us: the last resort, not the first.
            avoid = {client.server_id} if isinstance(e, TimeoutError) else set()
        gone, again = client.server_id, f"{spec.room_type} seed {spec.seed} mess {spec.mess_index}"
        if client.auto:
            print(
                f"agent: server {gone!r} went away at step {step['last']}; moving to another live server "
                f"(waiting up to {cfg.reconnect_timeout:g} s for one with room)",
                flush=True,
            )
            try:
                client.choose_server(cfg.reconnect_timeout, avoid=avoid)
            except TimeoutError as e:
                raise TimeoutError(f"after server {gone!r} went away: {e}") from None
            print(f"agent: on server {client.server_id!r}; running {again} again from the start", flush=True)
            continue
        print(
            f"agent: server {gone!r} went away at step {step['last']}; "
            f"waiting up to {cfg.reconnect_timeout:g} s for it to come back",
            flush=True,
        )
        try:
            client.wait_for_server(cfg.reconnect_timeout)
        except TimeoutError:
            raise TimeoutError(
                f"server {gone!r} did not come back within {cfg.reconnect_timeout:g} s"
            ) from None
        print(f"agent: server {gone!r} is back; running {again} again from the start", flush=True)
    raise AssertionError("unreachable")


def _server_went_away(e: Exception) -> bool:
    """No reply at all, or a server that no longer knows our session (it restarted)."""
    return isinstance(e, TimeoutError) or (isinstance(e, RemoteError) and e.code == ErrorCode.unknown_session)


def _spec_from(cmd: AgentCommand, base: EpisodeSpec) -> EpisodeSpec:
    return EpisodeSpec(
        **{
            **base.__dict__,
            "room_type": cmd.room_type or base.room_type,
            "seed": base.seed if cmd.seed is None else cmd.seed,
            "mess_index": cmd.mess_index,
        }
    )


def _wait_for_new_episode(publisher: TelemetryPublisher) -> AgentCommand:
    """Idle until a viewer asks for an episode; other commands are acknowledged."""
    while True:
        for cmd in publisher.commands():
            if isinstance(cmd, str):
                log.warning(cmd)
                continue
            if cmd.kind == "new_episode":
                publisher.ack(cmd.command_id, cmd.kind, True, "starting")
                return cmd
            ok = cmd.kind in ("pause", "resume", "step")  # harmless while idle; a preference needs an episode
            publisher.ack(
                cmd.command_id,
                cmd.kind,
                ok,
                "idle: no episode is running" if ok else "no episode is running; start one first",
            )
        time.sleep(0.1)
