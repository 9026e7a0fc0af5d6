"""Freed memory given back to the system: the trimmer's pace, and that a trim returns what a
freed array held."""

import sys

import numpy as np
import pytest

from shared.memory import Trimmer, release_free_memory, resident_mb


def test_the_trimmer_trims_at_most_every_period():
    now = [0.0]
    t = Trimmer(every_s=30.0, clock=lambda: now[0])
    calls = []
    for step in range(0, 100, 5):  # every 5 s for 95 s
        now[0] = float(step)
        calls.append(t.maybe())
    assert [i * 5 for i, c in enumerate(calls) if c] == [30, 60, 90]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc")
def test_a_trim_returns_freed_heap_pages_the_heap_keeps():
    """Once a 2 MB block was freed, glibc serves blocks up to 2 MB from its heap; freed while a
    later one still holds the heap's top, they stay resident (76 MB measured) until trimmed."""
    big = np.ones(2_000_000 // 8)
    del big
    before = resident_mb()
    blocks = [np.ones(100_000) for _ in range(100)]  # 800 kB each: 80 MB
    last = blocks[-1]
    del blocks
    kept = resident_mb()
    assert release_free_memory()
    after = resident_mb()
    assert kept - before > 60  # freed, yet resident
    assert after - before < 10, (before, kept, after)  # given back
    assert last.sum() == 100_000
