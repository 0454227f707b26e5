"""Settled scenes on disk, so a reset loads a room instead of re-running its physics.

Generating a room and messing it up runs PyBullet's physics until everything settles
(about 2 s a configuration, up to a minute for a few). The result is deterministic, so
it is stored once, as JSON, and every later reset of that configuration, in any process,
loads it in a few milliseconds.

Entries are keyed by (room type, seed, mess index) under a *generator fingerprint*: a
digest of the generator's version, the source of every module and data file that shapes
a scene (``server/*.py``, the catalog), and the PyBullet and NumPy versions. Any change to
them picks a new fingerprint, so a stale scene is never loaded; old fingerprints'
folders can be deleted. Each file carries the sha256 of its scene; a file that fails the
check is ignored (and regenerated). Writes are atomic, so concurrent workers may fill the
same cache.

The cache lives in ``$XDG_CACHE_HOME/tidee/scenes`` (``~/.cache/tidee/scenes``), or the
directory given to :class:`SceneCache`.
"""

from __future__ import annotations

import contextlib
import functools
import gzip
import hashlib
import json
import logging
import os
from importlib import metadata
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_SERVER_DIR = Path(__file__).resolve().parent
# What shapes a scene: the catalog, the generator, the mess-up, the world's bodies and physics.
_SCENE_SOURCES = ("bullet.py", "meshes.py", "messup.py", "rooms.py", "scene.py", "shuffle.py", "world.py")


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "tidee" / "scenes"


@functools.cache
def generator_fingerprint(version: int) -> str:
    """A digest of everything that decides what a generated (and messed-up) scene is."""
    h = hashlib.sha256(f"rooms v{version}".encode())
    catalog = _SERVER_DIR / "catalog"
    files = [_SERVER_DIR / name for name in _SCENE_SOURCES]
    files += sorted(
        p for p in catalog.rglob("*") if p.suffix in (".py", ".json") and "__pycache__" not in p.parts
    )
    for p in files:
        h.update(str(p.relative_to(_SERVER_DIR)).encode())
        h.update(p.read_bytes())
    for dist in ("pybullet", "numpy"):
        try:
            h.update(f"{dist}={metadata.version(dist)}".encode())
        except metadata.PackageNotFoundError:  # pragma: no cover - both are dependencies
            h.update(f"{dist}=?".encode())
    return h.hexdigest()[:16]


def _digest(scene: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(scene, sort_keys=True).encode()).hexdigest()


class SceneCache:
    """Scene dicts on disk under one generator fingerprint."""

    def __init__(self, directory: str | os.PathLike[str] | None = None, version: int = 1) -> None:
        self.root = Path(directory) if directory is not None else default_cache_dir()
        self.version = version
        self.fingerprint = generator_fingerprint(version)
        self.dir = self.root / self.fingerprint
        self.hits = 0
        self.misses = 0

    def path(self, room_type: str, seed: int, mess_index: int | str | None) -> Path:
        """``mess_index``: a messy configuration, None for the tidy room, or a tag such as
        ``"shuffle3"`` for another kind of state of the room."""
        if isinstance(mess_index, str):
            if not mess_index.isalnum():
                raise ValueError(f"a scene tag must be letters and digits, got {mess_index!r}")
            mess = mess_index
        else:
            mess = "tidy" if mess_index is None else f"mess{int(mess_index)}"
        return self.dir / f"{room_type}_{int(seed)}_{mess}.json.gz"

    def load(self, room_type: str, seed: int, mess_index: int | str | None) -> dict[str, Any] | None:
        """The stored scene, or None when absent or damaged (a damaged file is removed)."""
        path = self.path(room_type, seed, mess_index)
        try:
            with gzip.open(path, "rt") as f:
                entry = json.load(f)
            scene = entry["scene"]
            ok = entry.get("sha256") == _digest(scene) and entry.get("key") == [
                room_type,
                int(seed),
                mess_index,
            ]
        except (FileNotFoundError, NotADirectoryError):
            self.misses += 1
            return None
        except (OSError, EOFError, ValueError, KeyError, TypeError) as e:
            ok, scene = False, None
            log.warning("scene cache: %s is unreadable (%s); regenerating it", path, e)
        if not ok:
            log.warning("scene cache: %s failed its checksum; regenerating it", path)
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)
            self.misses += 1
            return None
        self.hits += 1
        return scene

    def store(self, room_type: str, seed: int, mess_index: int | str | None, scene: dict[str, Any]) -> None:
        """Write atomically; a cache that cannot be written (read-only disk) only costs speed."""
        path = self.path(room_type, seed, mess_index)
        entry = {
            "key": [room_type, int(seed), mess_index],
            "fingerprint": self.fingerprint,
            "sha256": _digest(scene),
            "scene": scene,
        }
        tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with gzip.open(tmp, "wt", compresslevel=5) as f:
                json.dump(entry, f)
            os.replace(tmp, path)
        except OSError as e:
            log.warning("scene cache: cannot write %s (%s); scenes will be regenerated", path, e)
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)


__all__ = ["SceneCache", "default_cache_dir", "generator_fingerprint"]
