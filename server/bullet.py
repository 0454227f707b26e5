"""PyBullet, imported without its banner, and a way to silence its C-level prints.

PyBullet writes its build time on import, and the eglRenderer plugin its GL details on
load and unload, straight to the process's stdout and stderr; a user's terminal should show tidee's
own lines only.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator


def _flush_c_stdio() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library handle on this platform
        pass


@contextlib.contextmanager
def quiet_stdio() -> Iterator[None]:
    """Silence C-level writes to stdout and stderr for the duration of the block."""
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = [(fd, os.dup(fd)) for fd in (1, 2)]
    except OSError:  # no usable stdio: nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            for fd, _ in saved:
                os.dup2(null.fileno(), fd)
        yield
    finally:
        _flush_c_stdio()  # C's stdout is block-buffered on a pipe: flush while it still goes to null
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


with quiet_stdio():
    import pybullet as pb  # noqa: E402

__all__ = ["pb", "quiet_stdio"]
