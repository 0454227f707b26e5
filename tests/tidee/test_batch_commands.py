"""The batch commands on ``tidee.batch``: the same shards and records on the local backend and on
Ray, the same shards for any worker count, and ``--resume`` remaking only a damaged shard.

One local Ray serves the module (starting one costs seconds); the commands run in this process
with tiny inputs. The Ray comparisons are slow: the data commands' in minutes on a busy 2-core
machine, the agent-driven ones (gen search, gen oop-memory, eval search) in more."""

from __future__ import annotations

import gzip
import json
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tidee.cli import main

RAY = str(Path(sys.executable).with_name("ray"))
needs_ray = pytest.mark.skipif(
    shutil.which(RAY) is None, reason="Ray not installed (pip install -e .[cluster])"
)

DETECTION = ["gen", "detection", "--rooms-per-type", "1", "--messes", "0", "--walks", "1"]
DETECTION += ["--frames-per-walk", "1", "--resolution", "32", "--shard-size", "2"]


@pytest.fixture(scope="module")
def local_ray() -> Iterator[Any]:
    """A Ray on this machine with 2 CPUs, which every ``--backend ray`` run here joins."""
    from tidee.batch import connect_ray

    ray, started = connect_ray(None, 2)
    yield ray
    if started:
        ray.shutdown()


def _run(*argv: str) -> None:
    assert main(list(argv)) == 0


def _shards(out: Path) -> dict[str, bytes]:
    manifest = json.loads((out / "manifest.json").read_text())
    return {name: (out / name).read_bytes() for name in manifest["shards"]}


def _cache_entries(root: Path) -> dict[str, Any]:
    return {
        str(p.relative_to(root)): json.loads(gzip.open(p).read()) for p in sorted(root.rglob("*.json.gz"))
    }


def test_gen_detection_gives_the_same_shards_for_any_worker_count_and_resume_remakes_a_damaged_one(
    tmp_path: Path,
) -> None:
    one, two = tmp_path / "one", tmp_path / "two"
    _run(*DETECTION, "--workers", "1", "--out", str(one))
    _run(*DETECTION, "--workers", "2", "--out", str(two))
    shards = _shards(one)
    assert len(shards) == 2 and shards == _shards(two)  # 4 configurations, 2 per shard
    first, second = sorted(shards)
    (two / first).write_bytes(b"damaged")
    stamp = (two / second).stat().st_mtime_ns
    _run(*DETECTION, "--workers", "2", "--resume", "--out", str(two))
    assert _shards(two) == shards and (two / second).stat().st_mtime_ns == stamp  # only the damaged one


@needs_ray
@pytest.mark.slow
def test_gen_detection_stats_and_cache_on_ray_match_local(tmp_path: Path, local_ray: Any) -> None:
    _run(*DETECTION, "--workers", "1", "--out", str(tmp_path / "det_local"))
    _run(*DETECTION, "--workers", "2", "--backend", "ray", "--out", str(tmp_path / "det_ray"))
    assert _shards(tmp_path / "det_local") == _shards(tmp_path / "det_ray")

    stats = ["gen", "stats", "--seeds", "0"]
    _run(*stats, "--out", str(tmp_path / "stats_local.json"))
    _run(*stats, "--workers", "2", "--backend", "ray", "--out", str(tmp_path / "stats_ray.json"))
    local, ray = (json.loads((tmp_path / f"stats_{b}.json").read_text()) for b in ("local", "ray"))
    assert local["counts"] == ray["counts"] and local["counts"]["*"]

    cache = ["gen", "cache", "--split", "val", "--limit", "2"]
    _run(*cache, "--cache-dir", str(tmp_path / "cache_local"))
    _run(*cache, "--workers", "2", "--backend", "ray", "--cache-dir", str(tmp_path / "cache_ray"))
    entries = _cache_entries(tmp_path / "cache_local")
    assert len(entries) >= 3 and entries == _cache_entries(tmp_path / "cache_ray")  # tidy room + 2 messes


def _search_episodes(out: Path) -> list[dict[str, Any]]:
    episodes = json.loads((out / "search.json").read_text())["episodes"]
    return [{k: v for k, v in e.items() if k not in ("wall_s", "retries")} for e in episodes]


@needs_ray
@pytest.mark.slow
def test_the_agent_driven_batch_commands_on_ray_match_local(tmp_path: Path, local_ray: Any) -> None:
    search = ["gen", "search", "--rooms-per-type", "1", "--messes", "0", "--snapshots", "2"]
    search += ["--max-steps", "70"]
    _run(*search, "--workers", "1", "--out", str(tmp_path / "search_local"))
    _run(*search, "--workers", "2", "--backend", "ray", "--out", str(tmp_path / "search_ray"))
    local = {p.name: p.read_bytes() for p in (tmp_path / "search_local").glob("*.npz")}
    assert len(local) == 4
    assert local == {p.name: p.read_bytes() for p in (tmp_path / "search_ray").glob("*.npz")}

    memory = ["gen", "oop-memory", "--rooms-per-type", "1", "--messes", "1", "--resolution", "128"]
    _run(*memory, "--workers", "1", "--out", str(tmp_path / "memory_local"))
    _run(*memory, "--workers", "2", "--backend", "ray", "--out", str(tmp_path / "memory_ray"))
    samples = (tmp_path / "memory_local" / "samples.jsonl").read_bytes()
    assert samples and samples == (tmp_path / "memory_ray" / "samples.jsonl").read_bytes()

    evaluate = ["eval", "search", "--rooms", "1", "--categories-per-room", "2", "--max-steps", "40"]
    _run(*evaluate, "--workers", "2", "--out", str(tmp_path / "eval_local"))
    _run(*evaluate, "--workers", "2", "--backend", "ray", "--out", str(tmp_path / "eval_ray"))
    episodes = _search_episodes(tmp_path / "eval_local")
    assert len(episodes) == 4 and episodes == _search_episodes(tmp_path / "eval_ray")
