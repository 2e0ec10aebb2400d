"""Timing statistics shared by the streaming loop and the benchmarks: medians and p99, never means."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


class Samples:
    """Durations (seconds) of one named step; summarised as median / p99 in milliseconds.

    Keeps the last ``keep`` durations in a ring of float64 allocated (and written) up front: an
    endless live run's statistics take the same memory from the first frame to the last (a list of
    Python floats grew by ~32 bytes per step and frame, ~0.3 MB/min at 15 fps: ``bench soak``).
    """

    def __init__(self, name: str, keep: int = 100_000):
        self.name = name
        self._keep = int(keep)
        self._ring = np.full(self._keep, np.nan)  # full(): the pages are touched now, not as the ring fills
        self._n = 0  # durations added in all

    def add(self, seconds: float) -> None:
        self._ring[self._n % self._keep] = seconds
        self._n += 1

    @property
    def _values(self) -> np.ndarray:
        """The kept durations in the order they were added (oldest first)."""
        if self._n <= self._keep:
            return self._ring[: self._n].copy()
        i = self._n % self._keep
        return np.concatenate([self._ring[i:], self._ring[:i]])

    @contextmanager
    def time(self) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(time.perf_counter() - t0)

    def __len__(self) -> int:
        return min(self._n, self._keep)

    @property
    def values(self) -> list[float]:
        """The durations kept, in the order they were added (a copy)."""
        return list(self._values)

    def summary(self) -> dict[str, float]:
        """``{"n", "median_ms", "p99_ms", "max_ms"}`` over the kept durations (zeros when empty)."""
        if not self._n:
            return {"n": 0, "median_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0}
        a = self._ring[: len(self)] * 1e3
        return {
            "n": int(a.size),
            "median_ms": float(np.median(a)),
            "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()),
        }


def measure(fn, repeat: int, warmup: int = 3) -> dict[str, float]:
    """Call ``fn()`` ``warmup`` times untimed, then ``repeat`` times; return :meth:`Samples.summary`."""
    for _ in range(warmup):
        fn()
    s = Samples("measure")
    for _ in range(repeat):
        with s.time():
            fn()
    return s.summary()
