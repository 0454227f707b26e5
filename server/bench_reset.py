"""``tidee gen cache`` and ``tidee bench reset``: settled scenes stored ahead of a run, and
what a reset costs without and with them.

``bench reset`` resets every configuration of a split twice in one run, side by side: cold
(an empty cache directory, so every room is generated and messed up with physics, then
stored) and cached (a new scene library reading that directory, as a new process would).
It writes JSON and Markdown with the median, p90 and max of each, and the machine's load.
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import numpy as np

from tidee.protocol.messages import EpisodeSpec
from tidee.server.bench_sim import spread, write_report
from tidee.server.episode import Episode, SceneLibrary
from tidee.server.scene_cache import SceneCache
from tidee.server.splits import mess_config, num_configs

if TYPE_CHECKING:
    from tidee.batch import BackendConfig

RESET_RESOLUTION = 64  # a reset's cost is the scene, not the first frame: keep the render small


def split_configs(split: str, limit: int | None = None) -> list[tuple[str, int, int]]:
    n = num_configs(split) if limit is None else min(limit, num_configs(split))
    return [(c.room_type, c.seed, c.mess_index) for c in (mess_config(split, i) for i in range(n))]


def reset_times(configs: Iterable[tuple[str, int, int]], cache: SceneCache | None) -> list[float]:
    """Reset one simulator to each (room type, seed, mess index) in turn (generating and storing
    what ``cache`` lacks); the seconds each reset took."""
    library = SceneLibrary(disk=cache)
    ep = Episode(renderer="tiny", library=library)
    times = []
    try:
        for room_type, seed, mess in configs:
            t0 = time.perf_counter()
            ep.reset(
                EpisodeSpec(room_type=room_type, seed=seed, mess_index=mess, resolution=RESET_RESOLUTION)
            )
            times.append(time.perf_counter() - t0)
    finally:
        ep.close()
    return times


def _fill_room(job: tuple[tuple[tuple[str, int, int], ...], str | None]) -> dict[str, Any]:
    """Generate and store one room's configurations (a batch job); their cache files (and the tidy
    room's), by path under the cache's root, so the command's own cache holds them too wherever
    the job ran."""
    configs, directory = job
    cache = SceneCache(directory) if directory else SceneCache()
    reset_times(configs, cache)
    room_type, seed = configs[0][:2]
    paths = [cache.path(room_type, seed, None), *(cache.path(*c) for c in configs)]
    return {
        "files": {str(p.relative_to(cache.root)): p.read_bytes() for p in paths if p.is_file()},
        "configurations": len(configs),
    }


def fill_cache(
    split: str,
    workers: int = 1,
    directory: str | None = None,
    limit: int | None = None,
    backend: BackendConfig | None = None,
    progress: bool = True,
) -> dict:
    """Generate and store every configuration of ``split`` (rooms in order, each room's messes
    in one job so its tidy room is generated once) on local workers or Ray (``tidee.batch``)."""
    from tidee.batch import BackendConfig, run_jobs

    backend = backend or BackendConfig()
    configs = split_configs(split, limit)
    by_room: dict[tuple[str, int], list[tuple[str, int, int]]] = {}
    for c in configs:
        by_room.setdefault(c[:2], []).append(c)
    cache = SceneCache(directory) if directory else SceneCache()
    before = sum(1 for c in configs if cache.path(*c).exists())
    todo = [
        (tuple(chunk), directory)
        for chunk in by_room.values()
        if any(not cache.path(*c).exists() for c in chunk)
    ]
    t0 = time.perf_counter()
    run_jobs(
        todo,
        _fill_room,
        workers=workers,
        renderer=None,
        backend=backend.backend,
        ray_address=backend.ray_address,
        progress=progress,
        desc=f"{split} rooms",
        files_dir=cache.root,
    )
    return {
        "split": split,
        "configurations": len(configs),
        "already_cached": before,
        "generated": len(configs) - before,
        "wall_s": round(time.perf_counter() - t0, 1),
        "directory": str(cache.dir),
    }


def _seconds(xs: list[float]) -> dict[str, float]:
    return {
        "n": len(xs),
        **{f"{k}_s": v for k, v in spread(xs, 4).items()},
        "mean_s": round(float(np.mean(xs)), 4),
    }


def run_reset_bench(out_path: str, split: str = "test", limit: int | None = None) -> dict:
    configs = split_configs(split, limit)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="tidee-reset-bench-") as d:
        cold = reset_times(configs, SceneCache(d))
        cached = reset_times(configs, SceneCache(d))
    slowest = int(np.argmax(cold))
    result = {
        "split": split,
        "configurations": len(configs),
        "renderer": "tiny",
        "resolution": RESET_RESOLUTION,
        "cold": _seconds(cold),
        "cached": _seconds(cached),
        "speedup_median": round(float(np.median(cold) / np.median(cached)), 1),
        "slowest_cold": {"config": list(configs[slowest]), "s": round(cold[slowest], 2)},
        "machine": f"{platform.machine()} {os.cpu_count()} cores",
        "load_avg_1m_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "command": f"tidee bench reset --split {split}"
        + (f" --limit {limit}" if limit else "")
        + f" --out {out_path}",
    }
    write_report(
        out_path, result, "Reset benchmark (`tidee bench reset`): cold (generate + physics) vs cached"
    )
    return result
