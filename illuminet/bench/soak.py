"""``illuminet bench soak --minutes N``: does the process grow while it streams for a long time?

Runs what ``illuminet demo --mjpeg`` runs -- the built-in default session replayed in real time
(recorded timing), looped, through the whole pipeline (planes -> anchor -> plane light -> light
estimate -> shading -> render) into the MJPEG server -- with two real HTTP clients attached for the
whole run: one reads the MJPEG stream (``/stream.mjpg``, parsing every part, as a browser's network
layer does), one the lighting estimate as Server-Sent Events (``/estimates``). Every second the
process's resident memory (``VmRSS`` of ``/proc/self/status``) is sampled, and, where the C library
is glibc (>= 2.33), its heap (``mallinfo2``: bytes in use, and bytes free inside the heap).

Printed: the RSS slope in MB per minute after a warm-up (a least-squares line through the samples
after the first 20 % of the run, at most 2 minutes: imports, the bundle, caches and the first
frames' buffers settle there), and the drift between the medians of the first and the last fifth of
those samples (robust to the allocator returning and re-taking ~10 MB at a time, which dominates a
short run's slope); the rise of the RSS's floor in each third of the fitted run (a leak rises alike
in each; an allocator settling to its high-water mark, in steps that thin out:
:func:`rise_by_thirds`); RSS at the start of the fit, at the end and its peak; with glibc, where a growth
lives: the slopes of the heap in use (a leak of C or Python allocations), of the free bytes inside
the heap (fragmentation: freed blocks the allocator cannot give back) and of the rest of the RSS
(libraries, the GL driver's own mappings, thread stacks); frames
processed; failures (failed frames, sink failures, client errors and reconnects); the per-frame
loop time (median, p99); frames and events the clients received. Target: a slope <= 0.1 MB/min over
30 minutes (the default). A short run's slope is noisy (allocator and page-cache effects of a few
MB weigh more over a few minutes): quote the 30-minute figure.

Only named runs execute it (``illuminet bench soak``): ``illuminet bench`` without names skips it.
Nothing is read from ../shared/data.
"""

from __future__ import annotations

import argparse
import ctypes
import http.client
import math
import resource
import sys
import threading
import time

import numpy as np

from illuminet.runtime.config import apply_overrides
from illuminet.runtime.errors import ConfigError
from illuminet.runtime.stream.memtrim import glibc_function

SLOPE_TARGET_MB_PER_MIN = 0.1
DEFAULT_MINUTES = 30.0
#: share of the run, and most seconds, before the slope's fit starts
WARMUP_SHARE, WARMUP_MAX_S = 0.2, 120.0


def rss_mb() -> float:
    """Resident memory of this process now, MB (``VmRSS``); the peak (``ru_maxrss``) where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / (1024.0 * 1024.0)


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (every field a ``size_t``)."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


#: glibc's ``mallinfo2`` function, or None (another C library, or glibc < 2.33)
_MALLINFO2 = glibc_function("mallinfo2", _MallInfo2, [])


def heap_mb() -> tuple[float, float, float] | None:
    """glibc's heap now, MB: (in use, free inside the heap, the heap's total: sbrk'd arenas + mmapped
    blocks), summed over every arena; None where glibc's ``mallinfo2`` is not available."""
    if _MALLINFO2 is None:
        return None
    m = _MALLINFO2()
    mib = 1024.0 * 1024.0
    return (m.uordblks + m.hblkhd) / mib, m.fordblks / mib, (m.arena + m.hblkhd) / mib


def slope_mb_per_min(t_s: np.ndarray, mb: np.ndarray) -> float:
    """Least-squares slope of ``mb`` over ``t_s``, in MB per minute (NaN with fewer than 3 samples)."""
    if len(t_s) < 3 or np.ptp(t_s) <= 0:
        return float("nan")
    return float(np.polyfit(np.asarray(t_s) / 60.0, np.asarray(mb), 1)[0])


def rise_by_thirds(t_s: np.ndarray, mb: np.ndarray) -> list[float]:
    """How much ``mb`` rose in each third of the run, MB per minute: the change of its *floor* (the
    lowest sample in the first and in the last sixth of the third, so the allocator's swings and the
    frames in flight do not count) across the third. A leak rises by the same amount in every third; an
    allocator settling to its high-water mark (rare coincident peaks, each arena keeping its largest
    size) rises in steps that thin out. NaN where a third has fewer than 6 samples."""
    t_s, mb = np.asarray(t_s, np.float64), np.asarray(mb, np.float64)
    out = []
    for part in np.array_split(np.arange(len(t_s)), 3):
        if len(part) < 6:
            out.append(float("nan"))
            continue
        sixths = np.array_split(part, 6)
        a, b = sixths[0], sixths[-1]
        dt = (np.median(t_s[b]) - np.median(t_s[a])) / 60.0
        out.append(float((mb[b].min() - mb[a].min()) / dt) if dt > 0 else float("nan"))
    return out


class _Client(threading.Thread):
    """A real HTTP client on ``path`` for the whole run; reconnects if the server drops it (counted)."""

    def __init__(self, port: int, path: str, stop: threading.Event):
        super().__init__(daemon=True, name=f"soak-client{path}")
        self.port, self.path = port, path
        self.items = 0
        self.bytes = 0
        self.errors = 0
        self.last_error = ""
        self.stop = stop  # the run's end: the server closing the stream then is no error

    def run(self) -> None:
        from illuminet.bench.mjpeg import read_part
        from illuminet.runtime.stream.mjpeg import BOUNDARY

        marker = f"--{BOUNDARY}".encode()
        while not self.stop.is_set():
            conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
            try:
                conn.request("GET", self.path)
                resp = conn.getresponse()
                if resp.status != 200:
                    raise OSError(f"HTTP {resp.status}")
                while not self.stop.is_set():
                    line = resp.fp.readline()
                    if not line:
                        raise OSError("the server closed the stream")
                    if self.path == "/estimates":
                        if line.startswith(b"data: "):
                            self.items += 1
                            self.bytes += len(line)
                        continue
                    if line.strip() != marker:
                        continue
                    self.bytes += read_part(resp.fp)
                    self.items += 1
            except (OSError, http.client.HTTPException, ValueError) as e:
                if self.stop.is_set():
                    break
                self.errors += 1
                self.last_error = f"{type(e).__name__}: {e}"
                self.stop.wait(0.5)
            finally:
                conn.close()


def check_args(args: argparse.Namespace, cfg) -> float:
    """``--minutes`` (the default when not given); ``illuminet bench`` calls it before any benchmark
    runs, also when soak is not named (a bad --minutes was then silently ignored)."""
    minutes = getattr(args, "minutes", None)
    if minutes is None:
        minutes = 0.5 if getattr(args, "quick", False) else DEFAULT_MINUTES
    if not (isinstance(minutes, (int, float)) and math.isfinite(minutes) and minutes > 0):
        raise ConfigError(f"bench soak --minutes: expected a finite number of minutes > 0, got {minutes!r}")
    return float(minutes)


def run(args: argparse.Namespace, cfg) -> dict:
    from illuminet.commands.demo import default_source_url, demo_stages
    from illuminet.hw import open_source
    from illuminet.runtime.stream.loop import LoopStats, run_loop
    from illuminet.runtime.stream.mjpeg import MjpegSink

    minutes = check_args(args, cfg)
    duration = float(minutes) * 60.0
    # the demo session in real time, looped: the pace of a camera, for as long as asked
    cfg = apply_overrides(cfg, [("source", "timing", "recorded"), ("source", "loop", True)])
    url = default_source_url()
    stats = LoopStats()
    source = open_source(url, cfg)
    stages = demo_stages(cfg)
    sink = MjpegSink("127.0.0.1", 0, stats=stats.snapshot, viewer_model="builtin:vase")
    sink.open()  # before the loop, so the clients connect first; run_loop's open is then a no-op
    samples: list[tuple[float, float]] = []
    heap: list[tuple[float, float, float, float]] = []  # (t, in use, free inside, RSS outside the heap)
    stop = threading.Event()
    clients = [_Client(sink.port, "/stream.mjpg", stop), _Client(sink.port, "/estimates", stop)]
    for c in clients:
        c.start()
    t0 = time.monotonic()
    interval = min(1.0, max(0.05, duration / 200))

    def sample() -> None:
        while True:
            t_s, rss = time.monotonic() - t0, rss_mb()
            samples.append((t_s, rss))
            h = heap_mb()
            if h is not None:
                heap.append((t_s, h[0], h[1], rss - h[2]))
            if stop.wait(interval) or time.monotonic() - t0 >= duration:
                stop.set()
                return

    sampler = threading.Thread(target=sample, name="soak-rss", daemon=True)
    sampler.start()
    print(
        f"soak: {url} in real time, looped, whole pipeline -> MJPEG server with a stream client and an "
        f"estimate client, for {minutes:g} min; RSS sampled every {interval:g} s"
    )
    sys.stdout.flush()
    try:
        run_loop(
            source,
            stages,
            [sink],
            stop_event=stop,
            stats=stats,
            install_signals=False,
            trim_memory_s=float(cfg.loop.trim_memory_s),
            opencv_threads=int(cfg.loop.opencv_threads),
        )
    finally:
        stop.set()
        sink.close()
        for c in clients:
            c.join(5)
        sampler.join(5)

    t = np.array([s[0] for s in samples])
    mb = np.array([s[1] for s in samples])
    warmup = min(WARMUP_SHARE * duration, WARMUP_MAX_S)
    fit = t >= warmup
    slope = slope_mb_per_min(t[fit], mb[fit])
    d = stats.to_dict()
    total = d["steps"].get("total", {"median_ms": 0.0, "p99_ms": 0.0})
    client_errors = sum(c.errors for c in clients)
    failures = int(d["failed_frames"]) + int(d["sink_failures"]) + client_errors
    print(stats.format_stats())
    for st in stages:  # where the object stood: the crop's framebuffers grow with it (a memory step)
        if st.name in ("anchor", "render"):
            print(f"  {st.name}: " + ", ".join(f"{k}={v}" for k, v in st.stats().items() if k != "odometry"))
    print(
        f"frames: {d['frames']} in {t[-1] if len(t) else 0:.0f} s; per-frame loop time median "
        f"{total['median_ms']:.1f} ms, p99 {total['p99_ms']:.1f} ms"
    )
    print(
        f"clients: {clients[0].items} MJPEG frames ({clients[0].bytes / 1e6:.1f} MB), {clients[1].items} estimate "
        f"events; client errors/reconnects {client_errors}"
        + (f" (last: {'; '.join(c.last_error for c in clients if c.last_error)})" if client_errors else "")
    )
    print(
        f"failures: {failures} (failed frames {d['failed_frames']}, sink failures {d['sink_failures']}, "
        f"client errors {client_errors})"
    )
    fit_from = float(mb[fit][0]) if fit.any() else float("nan")
    print(
        f"RSS: {fit_from:.1f} MB after the {warmup:.0f} s warm-up, {float(mb[-1]) if len(mb) else 0:.1f} MB at the "
        f"end, peak {float(mb.max()) if len(mb) else 0:.1f} MB; {int(fit.sum())} samples fitted"
    )
    # a figure robust to the allocator's swings (glibc returning and re-taking ~10 MB at a time): the
    # change between the medians of the first and the last fifth of the fitted samples, per minute
    fm, ft = mb[fit], t[fit]
    k = max(1, len(fm) // 5)
    drift = (
        float((np.median(fm[-k:]) - np.median(fm[:k])) / ((np.median(ft[-k:]) - np.median(ft[:k])) / 60.0))
        if len(fm) >= 10
        else float("nan")
    )
    print(f"RSS drift: {drift:+.3f} MB/min between the medians of the first and last fifth after warm-up")
    thirds = rise_by_thirds(ft, fm)
    print(
        "RSS floor's rise by third of the run after warm-up: "
        + ", ".join(f"{v:+.3f}" for v in thirds)
        + " MB/min (a leak rises alike in each; an allocator settling to its high-water mark, less and less)"
    )
    heap_slopes = heap_thirds = None
    if heap:
        ht = np.array(heap)
        hf = ht[:, 0] >= warmup
        heap_slopes = {
            k: slope_mb_per_min(ht[hf, 0], ht[hf, i]) for i, k in enumerate(("in_use", "free", "outside"), start=1)
        }
        print(
            f"where (glibc heap, slope after warm-up, MB/min): in use {heap_slopes['in_use']:+.3f} (a leak), free "
            f"inside the heap {heap_slopes['free']:+.3f} (fragmentation), RSS outside the heap "
            f"{heap_slopes['outside']:+.3f} (libraries, GL driver, stacks); in use {ht[-1, 1]:.1f} MB, free "
            f"{ht[-1, 2]:.1f} MB at the end"
        )
        heap_thirds = rise_by_thirds(ht[hf, 0], ht[hf, 1])
        print("heap in use, its floor's rise by third: " + ", ".join(f"{v:+.3f}" for v in heap_thirds) + " MB/min")
    verdict = "met" if slope <= SLOPE_TARGET_MB_PER_MIN else ("NOT met" if math.isfinite(slope) else "no figure")
    note = "" if minutes >= DEFAULT_MINUTES else f" (a {minutes:g}-minute run: noisy; the target is over 30 min)"
    print(f"RSS slope: {slope:+.3f} MB/min after warm-up; target <= {SLOPE_TARGET_MB_PER_MIN} MB/min: {verdict}{note}")
    return {
        "minutes": float(minutes),
        "source": url,
        "frames": d["frames"],
        "failures": failures,
        "failed_frames": d["failed_frames"],
        "sink_failures": d["sink_failures"],
        "client_errors": client_errors,
        "client_mjpeg_frames": clients[0].items,
        "client_estimate_events": clients[1].items,
        "frame_median_ms": total["median_ms"],
        "frame_p99_ms": total["p99_ms"],
        "rss_slope_mb_per_min": slope,
        "rss_drift_mb_per_min": drift,
        "rss_floor_rise_by_third_mb_per_min": thirds,
        "rss_after_warmup_mb": fit_from,
        "rss_end_mb": float(mb[-1]) if len(mb) else float("nan"),
        "rss_peak_mb": float(mb.max()) if len(mb) else float("nan"),
        "warmup_s": warmup,
        "heap_slopes_mb_per_min": heap_slopes,
        "heap_in_use_floor_rise_by_third_mb_per_min": heap_thirds,
        "heap_samples": [[round(float(v), 2) for v in h] for h in heap],  # (t s, in use, free, outside) MB
        "rss_samples": [[round(float(a), 2), round(float(b), 2)] for a, b in samples],
        "target_mb_per_min": SLOPE_TARGET_MB_PER_MIN,
    }
