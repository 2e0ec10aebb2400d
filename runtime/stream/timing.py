"""Timing statistics shared by the streaming loop and the benchmarks: medians and p99, never means."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


class Samples:
    """Durations (seconds) of one named step; summarised as median / p99 in milliseconds."""

    def __init__(self, name: str, keep: int = 100_000):
        self.name = name
        self._keep = keep
        self._values: list[float] = []

    def add(self, seconds: float) -> None:
        if len(self._values) >= self._keep:  # bounded memory for endless live runs
            del self._values[: self._keep // 2]
        self._values.append(seconds)

    @contextmanager
    def time(self) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(time.perf_counter() - t0)

    def __len__(self) -> int:
        return len(self._values)

    @property
    def values(self) -> list[float]:
        """The durations kept, in the order they were added (a copy)."""
        return list(self._values)

    def summary(self) -> dict[str, float]:
        """``{"n", "median_ms", "p99_ms", "max_ms"}`` (zeros when empty)."""
        if not self._values:
            return {"n": 0, "median_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0}
        a = np.asarray(self._values) * 1e3
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
