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

from tidee.agent.config import AgentProcessConfig
from tidee.agent.runner import EpisodeResult, EpisodeRunner, format_summary
from tidee.agent.telemetry import TelemetryPublisher
from tidee.protocol.client import RemoteError, SimClient
from tidee.protocol.messages import AgentCommand, EpisodeSpec, ErrorCode
from tidee.protocol.zenoh_config import ZenohOpenError, open_session

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
        print(
            f"agent: session {session}, variant {cfg.agent.variant}, perception {cfg.agent.perception}"
            f"{' (ORACLE)' if cfg.agent.perception == 'oracle' else ''}; logs in {cfg.log_dir}",
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
    """Play ``spec``; if its server goes away, wait for it and play the episode again from the start.

    The reset of a re-run opens a new session on the restarted server, and the runner's
    new log writer replaces the aborted run's log (same episode name).
    """
    for attempt in range(MAX_RECONNECTS + 1):
        step["last"] = 0
        try:
            return runner.run(spec, evaluate=cfg.score)
        except (TimeoutError, RemoteError) as e:
            if attempt == MAX_RECONNECTS or cfg.reconnect_timeout <= 0 or not _server_went_away(e):
                raise
            log.debug("episode failed: %s", e)
        print(
            f"agent: server {cfg.server_id!r} went away at step {step['last']}; "
            f"waiting up to {cfg.reconnect_timeout:g} s for it to come back",
            flush=True,
        )
        try:
            client.wait_for_server(cfg.reconnect_timeout)
        except TimeoutError:
            raise TimeoutError(
                f"server {cfg.server_id!r} did not come back within {cfg.reconnect_timeout:g} s"
            ) from None
        print(
            f"agent: server {cfg.server_id!r} is back; running {spec.room_type} seed {spec.seed} "
            f"mess {spec.mess_index} again from the start",
            flush=True,
        )
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
