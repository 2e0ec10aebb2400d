"""Hand the C heap's free pages back to the operating system now and then, on a long-running stream.

Why: a stream allocates and frees frame-sized buffers (decoded pictures, depth, GL read-backs,
JPEG encodes) every frame, from several threads. glibc keeps what is freed inside its heaps for
reuse, and over an hour the free space scattered between blocks still in use grows: the fourteenth
wave's 30-minute soaks (``illuminet bench soak``) measured the heap *in use* flat but the resident
size rising +0.11 to +0.19 MB/min, all of it free space inside glibc's heaps (docs/runtime.md,
"Fourteenth wave"). On a 4 GB board running a kiosk for days that is memory no one uses.

``malloc_trim(0)`` (glibc) returns every whole free page inside every arena to the system
(``madvise(MADV_DONTNEED)``), not only the top of the main heap as glibc does by itself.
:class:`HeapTrimmer` calls it from the loop thread every ``[loop] trim_memory_s`` seconds, after
a frame has gone to the sinks; what it costs (milliseconds per call) and what it gave back are in
its :meth:`~HeapTrimmer.stats`. Where the C library is not glibc (musl, macOS) there is nothing to
call and the trimmer does nothing (``available`` is False).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import time

log = logging.getLogger(__name__)


def glibc_function(name: str, restype, argtypes: list):
    """The C library's function ``name`` with its types set, or None (another C library, an older
    glibc without it). Used here for ``malloc_trim`` and by ``illuminet bench soak`` for ``mallinfo2``."""
    try:
        lib = ctypes.util.find_library("c")
        fn = getattr(ctypes.CDLL(lib), name) if lib else None
    except (OSError, AttributeError):
        return None
    if fn is not None:
        fn.restype = restype
        fn.argtypes = argtypes
    return fn


_MALLOC_TRIM = glibc_function("malloc_trim", ctypes.c_int, [ctypes.c_size_t])
try:
    _PAGE = os.sysconf("SC_PAGE_SIZE")
except (AttributeError, ValueError, OSError):  # pragma: no cover - not POSIX
    _PAGE = 4096


def _rss_kb() -> int:
    """Resident set size now, kB (Linux ``/proc/self/statm``); 0 where it cannot be read."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * (_PAGE // 1024)
    except (OSError, ValueError, IndexError):
        return 0


class HeapTrimmer:
    """Calls ``malloc_trim(0)`` at most every ``interval_s`` seconds (0 = never).

    :meth:`maybe` is cheap when it is not yet time (one clock read); call it once per frame.
    """

    def __init__(self, interval_s: float) -> None:
        self.interval_s = float(interval_s)
        self.available = _MALLOC_TRIM is not None
        self.enabled = self.available and self.interval_s > 0
        self._next = time.monotonic() + self.interval_s
        self.calls = 0
        self.ms: list[float] = []  # cost of each call (the last 64)
        self.released_mb = 0.0  # RSS before minus after, summed (what the calls gave back)

    def maybe(self) -> bool:
        """Trim if ``interval_s`` has passed since the last trim (or the start); True if it trimmed."""
        if not self.enabled:
            return False
        now = time.monotonic()
        if now < self._next:
            return False
        self.trim()
        self._next = time.monotonic() + self.interval_s
        return True

    def trim(self) -> None:
        """One ``malloc_trim(0)`` now (nothing without glibc)."""
        if _MALLOC_TRIM is None:
            return
        before = _rss_kb()
        t0 = time.perf_counter()
        _MALLOC_TRIM(0)
        dt = (time.perf_counter() - t0) * 1e3
        after = _rss_kb()
        self.calls += 1
        self.ms = (self.ms + [dt])[-64:]
        self.released_mb += max(0, before - after) / 1024.0
        log.debug("malloc_trim: %.1f ms, RSS %.1f -> %.1f MB", dt, before / 1024.0, after / 1024.0)

    def stats(self) -> dict:
        ms = sorted(self.ms)
        return {
            "interval_s": self.interval_s,
            "available": self.available,
            "calls": self.calls,
            "median_ms": round(ms[len(ms) // 2], 2) if ms else 0.0,
            "max_ms": round(ms[-1], 2) if ms else 0.0,
            "released_mb": round(self.released_mb, 1),
        }
