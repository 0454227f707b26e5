"""The soak benchmark's memory figure: peaks of whole saw teeth, early against late."""

from __future__ import annotations

import pytest

from tidee.server.bench_soak import growth_window, soak_rooms, soak_summary


def saw(sessions: int, period: int, base: float, rise: float, drift: float = 0.0) -> list[float]:
    """A simulator process replaced every ``period`` sessions, growing ``rise`` MB a session."""
    return [base + drift * i + rise * (i % period) for i in range(sessions)]


def test_flat_teeth_are_no_growth_wherever_warm_up_ends() -> None:
    for offset in range(0, 50, 7):  # warm-up ends anywhere in a tooth
        totals = saw(1000 + offset, 50, 200.0, 0.1)[offset:]
        r = soak_summary(totals, warmup=100, window=growth_window(len(totals), 100, 50))
        assert r["growth_after_warmup_pct"] == 0.0
        assert r["rss_after_warmup_mb"]["max"] == pytest.approx(204.9)


def test_growing_teeth_and_a_plain_leak_count() -> None:
    growing = saw(1000, 50, 200.0, 0.1, drift=0.02)  # each tooth 1 MB higher than the one before
    r = soak_summary(growing, warmup=100, window=growth_window(1000, 100, 50))
    early, late = 200 + 0.02 * 199 + 4.9, 200 + 0.02 * 999 + 4.9  # the last session of each window
    assert r["growth_after_warmup_pct"] == pytest.approx(100 * (late - early) / early, abs=0.01)
    leak = [200.0 + 0.076 * i for i in range(1000)]  # never recycled: 76 kB a session
    r = soak_summary(leak, warmup=100, window=growth_window(1000, 100, 0))
    assert r["growth_after_warmup_pct"] > 25


def test_the_window_holds_two_teeth_but_never_more_than_half_of_the_run() -> None:
    assert growth_window(1000, 100, 50) == 100
    assert growth_window(300, 30, 50) == 100
    assert growth_window(300, 30, 0) == 30
    assert growth_window(120, 12, 100) == 54


def test_rooms_are_distinct_and_bounded() -> None:
    rooms = soak_rooms(200)
    assert len(set(rooms)) == 200 and rooms[0] == ("Kitchen", 10_000)
    with pytest.raises(ValueError, match="distinct rooms"):
        soak_rooms(10**6)
