"""tidee's live web viewer (viser): watch and steer agents in a browser.

``run_viewer(ViewerConfig(...))`` starts one in this process and returns a handle with
``.url`` and ``.stop()``; ``tidee viewer`` runs one until Ctrl-C. The names below are
imported on first use, so ``import tidee.viewer`` (and ``tidee --help``) stay light.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ViewerConfig", "ViewerHandle", "run_viewer", "serve"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from tidee.viewer import app

        return getattr(app, name)
    raise AttributeError(f"module 'tidee.viewer' has no attribute {name!r}")
