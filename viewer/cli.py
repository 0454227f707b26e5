"""``tidee viewer``: argument parsing only (viser is imported when the command runs).

The options are the fields of ``tidee.viewer.config.ViewerCommandConfig``; its ``EXCLUSIVE`` pairs
(``--endpoint``/``--router``, ``--read-only``/``--token``) become argparse mutually exclusive
groups, so giving both is refused in one line.
"""

from __future__ import annotations

import argparse

from tidee.options import add_command
from tidee.viewer.config import ViewerCommandConfig

HELP = "the live web viewer (viser): watch and steer agents in a browser"


def register(sub: argparse._SubParsersAction) -> None:
    add_command(sub, "viewer", ViewerCommandConfig, run, HELP, exclusive=ViewerCommandConfig.EXCLUSIVE)


def run(config: ViewerCommandConfig) -> int:
    if config.annotated and not config.screenshot:
        raise SystemExit("tidee viewer: --annotated needs --screenshot PNG (and --replay LOGDIR)")
    if config.screenshot:
        if not config.viewer.replay:
            raise SystemExit("tidee viewer: --screenshot needs --replay LOGDIR")
        from tidee.viewer.screenshot import screenshot_replay

        step = screenshot_replay(
            config.viewer.replay,
            config.screenshot,
            at=config.at,
            annotated_png=config.annotated,
            size=config.window,
        )
        also = f" and {config.annotated}" if config.annotated else ""
        print(f"viewer: {config.screenshot}{also} (step {step} of {config.viewer.replay})")
        return 0
    import zenoh

    from tidee.protocol.zenoh_config import open_error
    from tidee.viewer.app import serve

    try:
        serve(config.viewer)
    except zenoh.ZError as e:  # opening the live feed's session: an unreachable router
        raise open_error(e, False, config.viewer.endpoint, config.viewer.router) from None
    return 0
