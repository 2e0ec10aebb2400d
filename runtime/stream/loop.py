"""The streaming loop: source -> stages -> sinks, with timing, flow limiting, failures and signals.

This module owns how frames move through the pipeline (DESIGN.md §1; docs/runtime.md "Pipeline and
latency")::

    serial (one thread):
    live source ──read──▶ [reader thread] ──▶ newest-frame slot ──▶ stages ──▶ sinks
                                              (one frame; a newer one
                                               replaces it: counted drop)
    non-live source (replay asap, synthetic) ──read in the loop thread──▶ stages ──▶ sinks
                                              (nothing dropped)

    threads ([loop] pipeline = "threads", or "auto" with >= 4 CPUs: AUTO_THREADS_MIN_CPUS):
    source ──▶ [front thread] stages before the first thread-bound one ──▶ hand-off ──▶ [loop thread]
               (planes, anchor, plane_light, light, shading:                  (depth     render (GL) ──▶ sinks
                frame N+1 while the loop thread renders frame N)               frames)

* **Pipelining**: the stage chain is cut before its first ``thread_bound`` stage (the renderer: its GL
  context stays on the thread that opened it). The stages in front of the cut run on one worker
  thread, frame N+1 while the loop thread renders and writes frame N; the hand-off between them holds
  at most ``depth`` frames, and the worker takes a new frame only when the hand-off has room, so
  nothing queues up. Each stage still runs on one thread and sees every frame once, in order, through
  the same :class:`~illuminet.runtime.stage.StageChain` (one failure policy), so a replay ``asap``
  gives the same output frame for frame as the serial loop. The worker also takes a frame only so
  early that its half is done just before the loop thread is free (:meth:`_Loop._pace`): a finished
  frame does not wait in the hand-off while a live camera's newer frames arrive.
* **Flow limiting** (after MediaPipe's ``FlowLimiterCalculator``): when ``source.live`` is true a
  reader thread keeps reading at the source's pace and parks the frame in a one-slot mailbox. If the
  loop has not taken the previous frame yet, the older one is discarded and counted as dropped, so the
  loop always works on the newest picture and latency does not build up behind a slow stage.
* **Latency**: per frame, from its capture (``Frame.t_host_ns``, the host's monotonic clock, when it
  is plausible: not after the frame reached the loop and at most a second before) or else its
  arrival (when ``read()`` returned) to the moment the finished frame is handed to the sinks; the
  ``latency`` row of the statistics (median, p99), and ``latency_ms`` in the live snapshot.
* **Failures**: a stage that raises on a frame marks that frame failed; the failure is counted, logged
  once per (stage, error type) with what to do, and the frame continues with the *last good* results
  of that stage (e.g. the previous lighting), so the output never flickers to nothing. Sink failures
  are counted the same way. ``strict=True`` (tests) re-raises instead.
* **Signals**: SIGINT/SIGTERM set the stop event (handlers are installed only when the loop runs in the
  main thread); the loop finishes the current frame and closes sinks first, so recordings are
  finalised. A second signal interrupts immediately.
* **Timing**: :class:`LoopStats` holds a :class:`~illuminet.runtime.stream.timing.Samples` per step
  (``source``, ``stage:<name>``, ``sink:<name>``, ``total``, ``latency``); :meth:`LoopStats.format_stats`
  prints the median/p99 table, :meth:`LoopStats.to_json` gives the same as JSON, and
  :meth:`LoopStats.snapshot` gives thread-safe live figures (fps, drops, failures, latency, CPU per
  frame, recent per-step medians) for status pages.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import signal
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from illuminet.runtime.errors import OutputClosed
from illuminet.runtime.frame import Frame
from illuminet.runtime.stage import EndOfStream, Sink, Source, Stage, StageChain
from illuminet.runtime.stream.memtrim import HeapTrimmer
from illuminet.runtime.stream.timing import Samples

log = logging.getLogger(__name__)

#: how many recent durations per step the live snapshot uses (a few seconds at camera rates)
RECENT = 120


class LoopStats:
    """Counters and per-step timing of one loop run; safe to read from other threads.

    Attributes
    ----------
    frames : int
        Frames that went through the stages and sinks.
    dropped : int
        Frames a live source delivered that the loop skipped because a newer one arrived first.
    failed_frames : int
        Frames on which at least one stage raised (they still reached the sinks).
    failures : collections.Counter
        ``"stage:<name>: <ErrorType>"`` / ``"sink:<name>: <ErrorType>"`` -> count.
    sink_failures : int
        Sink writes that raised.
    end_reason : str
        ``"end of stream"``, ``"max_frames"``, ``"stopped"`` (signal / stop event) or an error.
    pipeline : str
        ``"serial"`` or ``"threads"`` (what the loop ran; ``[loop] pipeline``), with ``depth``.
    in_flight_max : int
        Most frames that ever waited in the pipelined loop's hand-off (never more than ``depth``).
    stage_cpu_s : dict
        Stage name -> CPU seconds the loop's threads spent in it over the run (thread CPU time: what a
        stage costs, without the waits its wall time includes). Work a stage hands to its own
        threads (the light estimate's worker, a decoder pool, the GL driver) is counted by the stage
        that owns it, if at all (the light stage's ``cpu_ms`` in its stats; the replay's ``decode_cpu_ms``).
    memory_trim : dict
        The heap trimmer's counters (``[loop] trim_memory_s``; :class:`~illuminet.runtime.stream.memtrim.HeapTrimmer`).
    sinks : dict
        Sink name -> its own counters (``stats()``) once the sinks are closed, e.g. the estimates
        sink's ``dropped_lines`` for a pipe reader that did not keep up.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.samples: dict[str, Samples] = {}
        self._recent: dict[str, collections.deque] = {}
        self._frame_times: collections.deque = collections.deque(maxlen=RECENT)
        self.frames = 0
        self.dropped = 0
        self.failed_frames = 0
        self.sink_failures = 0
        self.failures: collections.Counter = collections.Counter()
        self.source_stats: dict[str, Any] = {}
        self.end_reason = ""
        self.running = False
        self.pipeline = "serial"
        self.depth = 0
        self.in_flight_max = 0
        self._t_start: float | None = None
        self._t_end: float | None = None
        self._cpu_start: float | None = None
        self._cpu_end: float | None = None
        self.stage_cpu_s: dict[str, float] = {}
        self.memory_trim: dict[str, Any] = {}
        self.sinks: dict[str, dict[str, Any]] = {}

    # -- recording (called by the loop)

    def _step(self, name: str) -> None:
        if name not in self.samples:
            self.samples[name] = Samples(name)
            self._recent[name] = collections.deque(maxlen=RECENT)

    def add(self, name: str, seconds: float) -> None:
        """Add one duration of step ``name`` (created on first use; table order = first-use order)."""
        with self._lock:
            self._step(name)
            self.samples[name].add(seconds)
            self._recent[name].append(seconds)

    def add_cpu(self, name: str, seconds: float) -> None:
        """Add the thread CPU time stage ``name`` took on one frame (:attr:`stage_cpu_s`)."""
        with self._lock:
            self.stage_cpu_s[name] = self.stage_cpu_s.get(name, 0.0) + seconds

    def start(self) -> None:
        with self._lock:
            self._t_start = time.perf_counter()
            self._cpu_start = time.process_time()
            self.running = True

    def stop(self, reason: str) -> None:
        with self._lock:
            self._t_end = time.perf_counter()
            self._cpu_end = time.process_time()
            self.running = False
            self.end_reason = reason

    def set_pipeline(self, mode: str, depth: int) -> None:
        with self._lock:
            self.pipeline, self.depth = mode, int(depth)

    def note_in_flight(self, n: int) -> None:
        with self._lock:
            self.in_flight_max = max(self.in_flight_max, int(n))

    def frame_done(self) -> None:
        with self._lock:
            self.frames += 1
            self._frame_times.append(time.perf_counter())

    def count_failure(self, key: str, frame_failed: bool) -> None:
        with self._lock:
            self.failures[key] += 1
            if key.startswith("sink:"):
                self.sink_failures += 1
            if frame_failed:
                self.failed_frames += 1

    def set_dropped(self, n: int) -> None:
        with self._lock:
            self.dropped = n

    def set_source_stats(self, d: dict[str, Any]) -> None:
        with self._lock:
            self.source_stats = dict(d)

    def set_memory_trim(self, d: dict[str, Any]) -> None:
        with self._lock:
            self.memory_trim = dict(d)

    def set_sink_stats(self, d: dict[str, dict[str, Any]]) -> None:
        with self._lock:
            self.sinks = {k: dict(v) for k, v in d.items()}

    # -- reading

    @property
    def elapsed_s(self) -> float:
        if self._t_start is None:
            return 0.0
        end = self._t_end if self._t_end is not None else time.perf_counter()
        return end - self._t_start

    @property
    def cpu_s(self) -> float:
        """CPU time of the whole process (every thread: decoders, GL, workers) while the loop ran."""
        if self._cpu_start is None:
            return 0.0
        end = self._cpu_end if self._cpu_end is not None else time.process_time()
        return end - self._cpu_start

    def cpu_ms_per_frame(self) -> float:
        """:attr:`cpu_s` per processed frame, milliseconds (0 before the first frame)."""
        return self.cpu_s / self.frames * 1e3 if self.frames else 0.0

    def snapshot(self) -> dict[str, Any]:
        """Live figures for status pages: thread-safe, cheap (recent window only).

        Returns
        -------
        dict
            ``running``, ``frames``, ``fps`` (over the run), ``fps_recent`` (last ~120 frames),
            ``dropped``, ``failed_frames``, ``sink_failures``, ``elapsed_s``, ``source`` (the source's
            own counters), ``pipeline`` and ``depth``, ``cpu_ms_per_frame`` (process CPU time per
            frame over the run), ``latency_ms``: ``{"median", "p99", "n"}`` of the capture-to-sinks
            latency over the recent window (None before the first frame), ``stages_ms``: step ->
            median milliseconds over the recent window (the latency apart).
        """
        with self._lock:
            recent = {k: list(v) for k, v in self._recent.items()}
            ft = list(self._frame_times)
            out = {
                "running": self.running,
                "frames": self.frames,
                "dropped": self.dropped,
                "failed_frames": self.failed_frames,
                "sink_failures": self.sink_failures,
                "source": dict(self.source_stats),
                "end_reason": self.end_reason,
                "pipeline": self.pipeline,
                "depth": self.depth,
            }
        el = self.elapsed_s
        out["elapsed_s"] = round(el, 3)
        out["fps"] = round(out["frames"] / el, 2) if el > 0 else 0.0
        out["fps_recent"] = round((len(ft) - 1) / (ft[-1] - ft[0]), 2) if len(ft) > 1 and ft[-1] > ft[0] else 0.0
        out["cpu_ms_per_frame"] = round(self.cpu_ms_per_frame(), 3)
        lat = recent.get("latency")
        out["latency_ms"] = (
            {
                "median": round(float(np.median(lat)) * 1e3, 3),
                "p99": round(float(np.percentile(lat, 99)) * 1e3, 3),
                "n": len(lat),
            }
            if lat
            else None
        )
        out["stages_ms"] = {k: round(float(np.median(v)) * 1e3, 3) for k, v in recent.items() if v and k != "latency"}
        return out

    def to_dict(self) -> dict[str, Any]:
        """Everything: counters, ``cpu_ms_per_frame`` (and ``stage_cpu_ms_per_frame``: each stage's
        thread CPU time per frame), the pipeline mode, and each step's ``n``,
        ``median_ms``, ``p99_ms``, ``max_ms`` (``steps["latency"]``: capture to sinks)."""
        with self._lock:
            steps = {k: s.summary() for k, s in self.samples.items()}
            d = {
                "frames": self.frames,
                "dropped": self.dropped,
                "failed_frames": self.failed_frames,
                "sink_failures": self.sink_failures,
                "failures": dict(self.failures),
                "source": dict(self.source_stats),
                "end_reason": self.end_reason,
                "pipeline": self.pipeline,
                "depth": self.depth,
                "in_flight_max": self.in_flight_max,
                "memory_trim": dict(self.memory_trim),
                "sinks": {k: dict(v) for k, v in self.sinks.items()},
                "stage_cpu_ms_per_frame": {
                    k: v / self.frames * 1e3 if self.frames else 0.0 for k, v in self.stage_cpu_s.items()
                },
            }
        el = self.elapsed_s
        d["elapsed_s"] = el
        d["fps"] = d["frames"] / el if el > 0 else 0.0
        d["cpu_s"] = self.cpu_s
        d["cpu_ms_per_frame"] = self.cpu_ms_per_frame()
        d["steps"] = steps
        return d

    def to_json(self, indent: int | None = 2) -> str:
        """:meth:`to_dict` as a JSON string."""
        return json.dumps(self.to_dict(), indent=indent)

    def format_stats(self) -> str:
        """The end-of-run table: one row per step with n, median, p99 and max in milliseconds."""
        d = self.to_dict()
        width = max([len("step")] + [len(k) for k in d["steps"]])
        rows = [f"{'step':<{width}}  {'n':>7}  {'median ms':>9}  {'p99 ms':>8}  {'max ms':>8}"]
        for k, s in d["steps"].items():
            rows.append(f"{k:<{width}}  {s['n']:>7d}  {s['median_ms']:>9.2f}  {s['p99_ms']:>8.2f}  {s['max_ms']:>8.2f}")
        rows.append(
            f"{d['frames']} frames in {d['elapsed_s']:.2f} s ({d['fps']:.1f} fps); dropped {d['dropped']}; "
            f"failed frames {d['failed_frames']}; sink failures {d['sink_failures']}; ended: {d['end_reason']}"
        )
        lat = d["steps"].get("latency")
        pipe = d["pipeline"] + (f" (depth {d['depth']})" if d["pipeline"] == "threads" else "")
        rows.append(
            (f"latency capture -> sinks: median {lat['median_ms']:.1f} ms, p99 {lat['p99_ms']:.1f} ms; " if lat else "")
            + f"CPU {d['cpu_ms_per_frame']:.1f} ms per frame (process); pipeline {pipe}"
        )
        for k, n in sorted(d["failures"].items()):
            rows.append(f"  failure {k}: {n}x")
        mt = d["memory_trim"]
        if mt.get("calls"):
            rows.append(
                f"  memory trim: {mt['calls']} calls (every {mt['interval_s']:g} s), median {mt['median_ms']:.1f} ms, "
                f"max {mt['max_ms']:.1f} ms, gave back {mt['released_mb']:.1f} MB"
            )
        for name, st in d["sinks"].items():
            if st.get("dropped_lines"):
                rows.append(f"  sink {name}: dropped_lines={st['dropped_lines']} (its reader did not keep up)")
        if d["source"]:
            rows.append("  source: " + ", ".join(f"{k}={v}" for k, v in d["source"].items()))
        return "\n".join(rows)


#: a source's capture stamp (``Frame.t_host_ns``) counts for the latency when it is at most this much
#: older than the frame's arrival in the loop (else the arrival counts: a stamp on another clock)
CAPTURE_STAMP_WINDOW_NS = 1_000_000_000


class _NewestFrameSlot:
    """One-frame mailbox between the reader thread and the loop: a newer frame replaces an untaken one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: tuple[Frame, int] | None = None
        self._done = False
        self._error: BaseException | None = None
        self.dropped = 0
        self.delivered = 0  # frames put (taken + dropped + at most one waiting)

    def put(self, frame: Frame, t_arrival_ns: int) -> None:
        with self._cond:
            if self._item is not None:
                self.dropped += 1  # the loop fell behind: the older frame is never processed
            self._item = (frame, t_arrival_ns)
            self.delivered += 1
            self._cond.notify()

    def finish(self, error: BaseException | None = None) -> None:
        with self._cond:
            self._done = True
            self._error = error
            self._cond.notify()

    def take(self, timeout: float) -> tuple[tuple[Frame, int] | None, bool, BaseException | None]:
        """((frame, arrival ns) or None, stream finished, error). Waits at most ``timeout`` s for a frame."""
        with self._cond:
            if self._item is None and not self._done:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item, (self._done and item is None), self._error

    def __len__(self) -> int:
        with self._cond:
            return int(self._item is not None)


def _reader(source: Source, slot: _NewestFrameSlot, stats: LoopStats, stop: threading.Event) -> None:
    try:
        while not stop.is_set():
            t0 = time.perf_counter()
            f = source.read()
            stats.add("source", time.perf_counter() - t0)
            if f is None:
                break
            slot.put(f, time.monotonic_ns())
        slot.finish()
    except BaseException as e:  # handed to the loop thread, which decides (EndOfStream, strict...)
        slot.finish(e)


class _Item:
    """A frame on its way through the loop, with when it was taken and when it arrived."""

    __slots__ = ("frame", "t_taken", "t_arrival_ns", "events")

    def __init__(self, frame: Frame, t_taken: float, t_arrival_ns: int, events: list | None = None) -> None:
        self.frame = frame
        self.t_taken = t_taken  # perf_counter when the loop took it (the start of its ``total``)
        self.t_arrival_ns = t_arrival_ns  # monotonic ns when read() returned it
        self.events = events or []


class _End:
    """Hand-off marker: the front thread saw the stream end (``reason``) or failed (``error``)."""

    __slots__ = ("reason", "error")

    def __init__(self, reason: str = "", error: BaseException | None = None) -> None:
        self.reason, self.error = reason, error


class _HandOff:
    """Bounded FIFO between the front thread and the loop thread (at most ``depth`` frames).

    The producer reserves room (:meth:`wait_room`) *before* it takes a frame from the source, so a
    frame is never read while the loop thread is more than ``depth`` frames behind, and ``put``
    never blocks: the hand-off cannot grow, whatever the source's pace.
    """

    def __init__(self, depth: int) -> None:
        self.depth = max(1, int(depth))
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.max_len = 0

    def wait_room(self, stop: threading.Event) -> bool:
        """Block until fewer than ``depth`` frames wait; False when ``stop`` is set first."""
        with self._cond:
            while len(self._q) >= self.depth:
                if stop.is_set():
                    return False
                self._cond.wait(0.05)
            return not stop.is_set()

    def put(self, item: Any) -> None:
        with self._cond:
            self._q.append(item)
            self.max_len = max(self.max_len, sum(isinstance(x, _Item) for x in self._q))
            self._cond.notify_all()

    def take(self, timeout: float) -> Any:
        """The oldest item, or None when none arrived within ``timeout`` seconds."""
        with self._cond:
            if not self._q:
                self._cond.wait(timeout)
            if not self._q:
                return None
            item = self._q.popleft()
            self._cond.notify_all()
            return item

    def __len__(self) -> int:
        with self._cond:
            return len(self._q)


#: set by the handler of :func:`remember_early_interrupt`: a Ctrl-C came before any loop's handlers
_early_interrupt = threading.Event()


def remember_early_interrupt() -> None:
    """Make SIGINT raise KeyboardInterrupt as usual *and* remember it, until a loop installs its handlers.

    For the command line's start-up (imports, models, GL): a library that catches ``BaseException``
    around its imports (trimesh does, for each optional dependency) swallowed the KeyboardInterrupt
    of a Ctrl-C pressed then, and the run went on as if nothing had been pressed (a camera until a
    second Ctrl-C). The next loop to start sees the flag and stops before its first frame, closing
    its outputs. Main thread only; a SIGINT that is ignored (``SIG_IGN``) stays ignored.
    """
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return

    def handler(signum, frame):
        _early_interrupt.set()
        signal.default_int_handler(signum, frame)

    signal.signal(signal.SIGINT, handler)


@contextlib.contextmanager
def _signals_stop(stop: threading.Event, enabled: bool):
    """SIGINT/SIGTERM -> ``stop`` while the loop runs (main thread only); restore handlers after."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        if stop.is_set():  # second signal: the user really wants out now
            raise KeyboardInterrupt
        log.info(
            "%s received: stopping after this frame and finalising outputs (again to abort)",
            signal.Signals(signum).name,
        )
        stop.set()

    previous = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        previous[s] = signal.signal(s, handler)
    if _early_interrupt.is_set():  # a Ctrl-C during start-up that a library swallowed
        _early_interrupt.clear()
        log.info("SIGINT received during start-up: stopping before the first frame and finalising outputs")
        stop.set()
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


@contextlib.contextmanager
def signals_held():
    """SIGINT/SIGTERM are noted, not acted on, in the block (main thread only; handlers restored
    after). Around a command's run and its final reports: :func:`run_loop` installs its own handlers
    while it runs and puts these back when it returns, so a signal in the cleanup after it (the
    statistics file being written) no longer kills the process half-way (default SIGTERM) or raises
    in the middle of a write (default SIGINT). The cleanup is short and ends the process anyway."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        # before run_loop's handlers are in (a short window): its loop sees this and stops at once
        _early_interrupt.set()
        log.info("%s received: finishing the statistics and reports, then exiting", signal.Signals(signum).name)

    previous = {}
    for s in (signal.SIGINT, signal.SIGTERM):
        previous[s] = signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _early_interrupt.clear()  # one in the cleanup after the loop is for no later loop


def loop_options(loop_cfg: Any) -> dict[str, Any]:
    """:func:`run_loop`'s keyword arguments from a configuration's ``[loop]`` section (``cfg.loop``): what
    the ``run`` and ``demo`` commands pass alike, so a new ``[loop]`` key reaches both."""
    return {
        "pipeline": loop_cfg.pipeline,
        "depth": loop_cfg.depth,
        "trim_memory_s": loop_cfg.trim_memory_s,
        "opencv_threads": loop_cfg.opencv_threads,
    }


def _name(component: Any, fallback: str) -> str:
    return getattr(component, "name", None) or fallback


class _FailureLog:
    """Logs the first failure of each kind in full (with advice), later ones only at debug level."""

    def __init__(self) -> None:
        self.seen: set[str] = set()

    def report(self, key: str, frame: Frame | None, err: BaseException, what_next: str) -> None:
        where = f"frame {frame.seq}" if frame is not None else "before the first frame"
        if key in self.seen:
            log.debug("%s failed again on %s: %s", key, where, err)
            return
        self.seen.add(key)
        log.error(
            "%s failed on %s: %s: %s. %s This is logged once per kind; the count is in the final "
            "statistics. To stop at the first failure with a traceback use --strict ([logging] strict = true); "
            "--log-level debug logs every occurrence.",
            key.split(": ")[0],
            where,
            type(err).__name__,
            err,
            what_next,
        )

    def report_skip(self, key: str, frame: Frame) -> None:
        """A stage skipped because a result it requires is missing (its producer failed)."""
        if key in self.seen:
            return
        self.seen.add(key)
        stage, _, what = key.partition(": ")
        log.warning(
            "%s skipped on frame %d: %s (its producer failed on this frame and had no earlier result); "
            "the frame goes on with this stage's last good result. Logged once per kind.",
            stage,
            frame.seq,
            what,
        )


class _StreamEnded(Exception):
    """The source has no more frames (``reason`` says why); raised by :meth:`_Loop.next_frame`."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


#: ``[loop] pipeline`` values: "auto" (threads with AUTO_THREADS_MIN_CPUS or more CPUs), "serial", "threads"
PIPELINES = ("auto", "serial", "threads")


#: ``[loop] pipeline = "auto"`` threads from this many CPUs: on 2 cores with a software rasteriser
#: (llvmpipe's own threads) the front thread and the renderer fight over the cores and the pipelined loop
#: was slower than the serial one (``illuminet bench demo``: x0.91 fps, latency p99 95 vs 50 ms)
AUTO_THREADS_MIN_CPUS = 4


def resolve_pipeline(mode: str, stages: Sequence[Stage]) -> str:
    """``"serial"`` or ``"threads"`` for ``[loop] pipeline = mode`` and this chain.

    ``auto`` pipelines with :data:`AUTO_THREADS_MIN_CPUS` or more CPUs and a stage to run ahead
    (some stage before the first thread-bound one); ``threads`` always pipelines (with no such
    stage the worker only reads the source while the loop thread runs the rest).
    """
    import os

    if mode not in PIPELINES:
        raise ValueError(f"[loop] pipeline: expected one of {', '.join(PIPELINES)}, got {mode!r}")
    if mode != "auto":
        return mode
    front = _split_index(stages)
    return "threads" if (os.cpu_count() or 1) >= AUTO_THREADS_MIN_CPUS and front > 0 else "serial"


def _split_index(stages: Sequence[Stage]) -> int:
    """Index of the first thread-bound stage (the end of the chain when there is none)."""
    for k, st in enumerate(stages):
        if getattr(st, "thread_bound", False):
            return k
    return len(stages)


class _Loop:
    """One run of :func:`run_loop`: its components, its state, and one method per step of a frame."""

    def __init__(
        self,
        source: Source,
        stages: Sequence[Stage],
        sinks: Sequence[Sink],
        *,
        strict: bool,
        max_frames: int,
        stop: threading.Event,
        on_stats: Callable[[dict[str, Any]], None] | None,
        stats: LoopStats,
        stats_interval_s: float,
        pipeline: str = "serial",
        depth: int = 1,
        trim_memory_s: float = 0.0,
        opencv_threads: int = 1,
    ) -> None:
        if int(opencv_threads) < 0:
            raise ValueError(f"[loop] opencv_threads: expected an int >= 0, got {opencv_threads!r}")
        self.opencv_threads = int(opencv_threads)
        self.source = source
        self.stages = list(stages)
        self.sinks = list(sinks)
        self.sink_names = [_name(s, f"sink{i}") for i, s in enumerate(sinks)]
        self.strict = strict
        self.max_frames = max_frames
        self.stop = stop
        self.stop_reason: str | None = None  # why a sink asked the loop to end (OutputClosed)
        self.on_stats = on_stats
        self.stats = stats
        self.stats_interval_s = stats_interval_s
        self.failures = _FailureLog()
        self.chain = StageChain(stages, strict=strict, source=source)  # checks the wiring before anything opens
        self.mode = resolve_pipeline(pipeline, self.stages)
        if int(depth) < 1:
            raise ValueError(f"[loop] depth: expected an int >= 1, got {depth!r}")
        self.depth = int(depth)
        self.split = _split_index(self.stages) if self.mode == "threads" else len(self.stages)
        stats.set_pipeline(self.mode, self.depth if self.mode == "threads" else 0)
        self.reader_stop = threading.Event()
        self.reader: threading.Thread | None = None
        self.slot: _NewestFrameSlot | None = None  # set for a live source (flow limiting)
        self.handoff: _HandOff | None = None  # set when pipelined
        self.front: threading.Thread | None = None
        self.front_stop = threading.Event()
        self.current: Frame | None = None  # the frame being processed, for messages
        self.reason = "end of stream"
        self.next_report = time.perf_counter() + stats_interval_s
        self.trimmer = HeapTrimmer(trim_memory_s)
        # pacing of a live source's front thread (:meth:`_pace`): recent durations of both halves
        self._t_back_start: float | None = None
        self._ema_back = 0.0
        self._ema_front = 0.0
        self._drop_logged = False

    # -- opening and closing

    def open(self, stack: contextlib.ExitStack) -> None:
        """Open the source, the stages and the sinks on ``stack``, and prepare the reader of a live source.

        The close order is the reverse: sinks, stages, front thread join, reader stop, source, last
        reader join. The reader thread may be blocked inside read() (waiting for a camera, or replay
        sleeping until a timestamp): it gets a moment to notice the stop, then closing the source
        unblocks it.
        """
        if self.opencv_threads > 0:
            import cv2

            # OpenCV's own worker threads, for the whole process while the loop runs (restored last)
            stack.callback(cv2.setNumThreads, cv2.getNumThreads())
            cv2.setNumThreads(self.opencv_threads)
        stack.callback(self._join_reader)
        stack.enter_context(self.source)
        stack.callback(self._stop_reader)
        stack.callback(self._stop_front)  # before the stages close: no stage closes under the worker
        for st in self.stages:
            stack.enter_context(st)
        for sk in self.sinks:
            stack.enter_context(sk)
        if getattr(self.source, "live", False):
            self.slot = _NewestFrameSlot()
            self.reader = threading.Thread(
                target=_reader,
                args=(self.source, self.slot, self.stats, self.reader_stop),
                name="illuminet-source-reader",
                daemon=True,
            )
        if self.mode == "threads":
            self.handoff = _HandOff(self.depth)
            self.front = threading.Thread(target=self._front_worker, name="illuminet-pipeline-front", daemon=True)

    def _stop_reader(self) -> None:
        self.reader_stop.set()
        if self.reader is not None:
            self.reader.join(timeout=0.5)

    def _join_reader(self) -> None:
        if self.reader is not None:
            self.reader.join(timeout=2.0)
            if self.reader.is_alive():
                log.warning(
                    "source %r did not return from read() within 2 s of being closed", _name(self.source, "source")
                )

    def _stop_front(self) -> None:
        self.front_stop.set()
        if self.front is not None and self.front.ident is not None:
            self.front.join(timeout=10.0)
            if self.front.is_alive():
                log.warning("the pipeline's front thread did not finish its frame within 10 s of the stop")

    # -- running

    def run(self) -> None:
        """Process frames until the stream ends, ``max_frames`` or a stop; the reason goes into the stats."""
        self.stats.start()
        if self.reader is not None:
            self.reader.start()
        if self.front is not None:
            self.front.start()
        try:
            self.reason = self._frames() if self.front is None else self._frames_pipelined()
        except BaseException as e:
            self.reason = f"error: {type(e).__name__}: {e}" if not isinstance(e, KeyboardInterrupt) else "interrupted"
            raise
        finally:
            try:
                self._stop_front()
            except KeyboardInterrupt:  # a second Ctrl-C while the front thread finishes its frame
                self.reason = "interrupted"
                raise
            finally:
                self.stats.stop(self.reason)
                try:
                    self.report()
                except Exception:  # strict: a failing stats callback must not hide the real outcome
                    log.exception("stats callback failed")

    def _frames(self) -> str:
        """The frame loop (serial); returns why it ended."""
        while True:
            if self.stop.is_set():
                return self.stop_reason or "stopped"
            if self.max_frames and self.stats.frames >= self.max_frames:
                return "max_frames"
            try:
                item = self.next_frame()
            except _StreamEnded as e:
                return e.reason
            if item is not None:  # None: a live source had nothing new yet; check the stop flags again
                frame, events = self.chain.run(item.frame, on_time=self._stage_time, on_cpu=self.stats.add_cpu)
                self.finish(item, frame, events)
            self._maybe_report()

    def _frames_pipelined(self) -> str:
        """The loop thread's half of the pipelined loop: the thread-bound stages and the sinks."""
        assert self.handoff is not None
        while True:
            if self.stop.is_set():
                return self.stop_reason or "stopped"
            if self.max_frames and self.stats.frames >= self.max_frames:
                return "max_frames"
            item = self.handoff.take(timeout=0.1)
            if isinstance(item, _End):
                if item.error is not None:
                    raise item.error
                return item.reason
            if item is not None:
                t0 = time.perf_counter()
                self._t_back_start = t0
                frame, events = self.chain.run(
                    item.frame, on_time=self._stage_time, on_cpu=self.stats.add_cpu, start=self.split
                )
                self.finish(item, frame, item.events + events)
                self._ema_back = _ema(self._ema_back, time.perf_counter() - t0)
            self._maybe_report()

    def _front_worker(self) -> None:
        """The front thread: take frames (only when the hand-off has room) and run the stages before the cut."""
        assert self.handoff is not None
        handoff, taken = self.handoff, 0
        try:
            while not (self.stop.is_set() or self.front_stop.is_set()):
                if not handoff.wait_room(self.front_stop):
                    return
                if self.max_frames and taken >= self.max_frames:
                    handoff.put(_End("max_frames"))
                    return
                self._pace()
                try:
                    item = self.next_frame()
                except _StreamEnded as e:
                    handoff.put(_End(e.reason))
                    return
                if item is None:
                    continue
                taken += 1
                t0 = time.perf_counter()
                item.frame, item.events = self.chain.run(
                    item.frame, on_time=self._stage_time, on_cpu=self.stats.add_cpu, stop=self.split
                )
                self._ema_front = _ema(self._ema_front, time.perf_counter() - t0)
                handoff.put(item)
                self.stats.note_in_flight(handoff.max_len)
        except BaseException as e:  # re-raised on the loop thread (strict, or a source error)
            handoff.put(_End(error=e))

    def _pace(self) -> None:
        """Start the next frame so that its front half is done just before the loop thread frees.

        The front half of a frame takes ~``ema_front``, the loop thread's half ~``ema_back``; when the
        latter is longer, taking a frame at once would leave it finished and waiting in the hand-off
        (a live camera's newer frames meanwhile dropped): the latency would be two back halves
        instead of one front and one back half. Taking it later costs no frame rate (the worker
        would wait for the hand-off anyway); a margin of a tenth of the back half (and 0.5 ms)
        absorbs the jitter of the estimates. The output does not depend on it: frames and their
        order are the same, only when the worker takes them changes.
        """
        if self._t_back_start is None:
            return
        margin = 0.1 * self._ema_back + 5e-4
        wait = self._t_back_start + self._ema_back - self._ema_front - margin - time.perf_counter()
        if wait > 0:
            self.front_stop.wait(min(wait, 0.05))

    def next_frame(self) -> _Item | None:
        """The next frame, when it was taken (the start of its ``total`` time) and when it arrived.

        A live source's frame comes from the newest-frame slot (None when none arrived within
        0.1 s); any other source is read here. Raises :class:`_StreamEnded` at the end of the
        stream (or an :class:`~illuminet.runtime.stage.EndOfStream` error, which is logged), and
        re-raises any other error of the source.
        """
        if self.slot is not None:
            got, finished, err = self.slot.take(timeout=0.1)
            if err is not None and got is None:
                if isinstance(err, EndOfStream):
                    log.error("source ended: %s", err)
                    raise _StreamEnded(f"source error: {err}")
                raise err
            if finished:
                raise _StreamEnded("end of stream")
            if got is None:
                return None
            if self.slot.dropped and not self._drop_logged:
                self._drop_logged = True
                advice = getattr(self.source, "drop_advice", "")
                if advice:
                    log.warning("%s (logged once; the count is in the statistics as 'dropped')", advice)
            return _Item(got[0], time.perf_counter(), got[1])
        t_frame = time.perf_counter()
        try:
            frame = self.source.read()
        except EndOfStream as e:
            log.error("source ended: %s", e)
            raise _StreamEnded(f"source error: {e}") from None
        self.stats.add("source", time.perf_counter() - t_frame)
        if frame is None:
            raise _StreamEnded("end of stream")
        return _Item(frame, t_frame, time.monotonic_ns())

    def finish(self, item: _Item, frame: Frame, events: list) -> None:
        """Count the frame's stage events, measure its latency, hand it to the sinks, time it."""
        self.count_events(frame, events)
        t_out = time.monotonic_ns()
        t_cap = frame.t_host_ns
        if not (isinstance(t_cap, int) and 0 <= item.t_arrival_ns - t_cap <= CAPTURE_STAMP_WINDOW_NS):
            t_cap = item.t_arrival_ns  # no capture stamp on this clock: from the arrival
        self.stats.add("latency", max(0, t_out - t_cap) * 1e-9)
        self.write_sinks(frame)
        self.stats.add("total", time.perf_counter() - item.t_taken)
        self.stats.frame_done()

    def _maybe_report(self) -> None:
        self.trimmer.maybe()  # between frames, on the loop thread (memtrim.py)
        if time.perf_counter() >= self.next_report:
            self.report()
            self.next_report = time.perf_counter() + self.stats_interval_s

    def run_stages(self, frame: Frame) -> Frame:
        """The stages (StageChain: the one failure / missing-input policy); failures and skips counted and logged."""
        self.current = frame
        frame, events = self.chain.run(frame, on_time=self._stage_time, on_cpu=self.stats.add_cpu)
        self.count_events(frame, events)
        return frame

    def count_events(self, frame: Frame, events: list) -> None:
        """Count and log (once per kind) the failures and skips of one frame's stages."""
        self.current = frame
        counted = False
        for ev in events:
            failed = ev.kind == "failed"
            self.stats.count_failure(ev.key, frame_failed=failed and not counted)
            counted = counted or failed
            if failed:
                self.failures.report(ev.key, frame, ev.error, "The frame goes on with this stage's last good result.")
            else:
                self.failures.report_skip(ev.key, frame)

    def _stage_time(self, name: str, seconds: float) -> None:
        self.stats.add(f"stage:{name}", seconds)

    def write_sinks(self, frame: Frame) -> None:
        """Every sink gets the frame; a failing sink is counted and logged (raised when strict)."""
        for sk, name in zip(self.sinks, self.sink_names):
            t0 = time.perf_counter()
            try:
                sk.write(frame)
            except OutputClosed as e:  # its reader has gone: the run ends here, not a failure
                if self.stop_reason is None:
                    self.stop_reason = str(e)
                    log.info("%s", e)
                self.stop.set()
            except Exception as e:
                if self.strict:
                    raise
                key = f"sink:{name}: {type(e).__name__}"
                self.stats.count_failure(key, frame_failed=False)
                self.failures.report(key, frame, e, "This frame is missing from that output.")
            finally:
                self.stats.add(f"sink:{name}", time.perf_counter() - t0)

    def report(self) -> None:
        """Refresh the source's counters and the drops, and hand a snapshot to ``on_stats``."""
        try:
            self.stats.set_source_stats(self.source.stats())
            self.stats.set_memory_trim(self.trimmer.stats())
            if self.slot is not None:
                self.stats.set_dropped(self.slot.dropped)
            if self.on_stats is not None:
                self.on_stats(self.stats.snapshot())
        except Exception as e:  # statistics must never stop the stream
            if self.strict:
                raise
            self.failures.report(f"stats: {type(e).__name__}", self.current, e, "Statistics may be stale.")


def _ema(prev: float, x: float, a: float = 0.2) -> float:
    return x if prev == 0.0 else (1.0 - a) * prev + a * x


def run_loop(
    source: Source,
    stages: Sequence[Stage],
    sinks: Sequence[Sink],
    *,
    strict: bool = False,
    max_frames: int = 0,
    stop_event: threading.Event | None = None,
    on_stats: Callable[[dict[str, Any]], None] | None = None,
    stats: LoopStats | None = None,
    stats_interval_s: float = 1.0,
    install_signals: bool = True,
    pipeline: str = "serial",
    depth: int = 1,
    trim_memory_s: float = 0.0,
    opencv_threads: int = 1,
) -> LoopStats:
    """Run ``source`` through ``stages`` into ``sinks`` until the stream ends or a stop is requested.

    Opens the source, the stages and the sinks (in that order) and always closes them in reverse
    order -- sinks first, so recordings and videos are finalised even after an error or a signal.

    Parameters
    ----------
    source : Source
        Unopened source; ``source.live`` selects flow limiting (newest frame wins, drops counted).
    stages : sequence of Stage
        Applied in order; each returns a new frame with its results added.
    sinks : sequence of Sink
        Each gets every processed frame.
    strict : bool
        Re-raise the first stage or sink failure instead of counting it (tests).
    max_frames : int
        Stop after this many processed frames (0 = no limit).
    stop_event : threading.Event, optional
        Set it (from any thread) to stop after the current frame. SIGINT/SIGTERM set it too.
    on_stats : callable, optional
        Called with :meth:`LoopStats.snapshot` every ``stats_interval_s`` seconds and at the end.
    stats : LoopStats, optional
        Use this object (e.g. created earlier so a status page can poll its ``snapshot``).
    install_signals : bool
        Install SIGINT/SIGTERM handlers (only effective in the main thread).
    pipeline : {"serial", "threads", "auto"}
        ``[loop] pipeline``: one thread, or the stages before the first thread-bound one (the
        renderer) on a worker thread one frame ahead (module docstring); ``auto`` pipelines with
        :data:`AUTO_THREADS_MIN_CPUS` (4) or more CPUs. The output is the same either way.
    depth : int
        Pipelined: most frames finished by the worker and waiting for the loop thread (``[loop] depth``).
    trim_memory_s : float
        ``[loop] trim_memory_s``: every this many seconds, between frames, hand the C heap's free
        pages back to the system (:mod:`~illuminet.runtime.stream.memtrim`; 0 = never).
    opencv_threads : int
        ``[loop] opencv_threads``: OpenCV's thread count (``cv2.setNumThreads``, process-wide) while
        the loop runs, restored after; 0 = leave OpenCV's default (one per CPU). The default 1: the
        frames' images are small, and OpenCV's workers spinning between calls cost ~0.8 ms of CPU a
        frame on 2 cores for no gain (the loop's own threads fill the cores); the output is the same.

    Returns
    -------
    LoopStats
        Counters and timing; ``format_stats()`` for the table, ``to_json()`` for JSON.

    Raises
    ------
    Exception
        With ``strict=True`` the first failure; always: errors of ``open``/``read`` other than
        :class:`~illuminet.runtime.stage.EndOfStream` (which ends the stream with a logged error).
    """
    stats = stats if stats is not None else LoopStats()
    loop = _Loop(
        source,
        stages,
        sinks,
        strict=strict,
        max_frames=max_frames,
        stop=stop_event if stop_event is not None else threading.Event(),
        on_stats=on_stats,
        stats=stats,
        stats_interval_s=stats_interval_s,
        pipeline=pipeline,
        depth=depth,
        trim_memory_s=trim_memory_s,
        opencv_threads=opencv_threads,
    )
    # signal handlers stay installed until everything is closed: a SIGTERM during finalisation must
    # not kill the process with the default handler half-way through closing a recording
    with _signals_stop(loop.stop, install_signals), contextlib.ExitStack() as stack:
        loop.open(stack)
        loop.run()
    # after close: the source's final counters (e.g. frames it dropped itself), and the sinks'
    try:
        stats.set_source_stats(source.stats())
    except Exception:  # pragma: no cover
        pass
    sink_stats = {}
    for sk, name in zip(loop.sinks, loop.sink_names):
        try:
            sink_stats[name] = sk.stats() if hasattr(sk, "stats") else {}
        except Exception:  # a sink's counters must not hide the run's outcome
            pass
    stats.set_sink_stats(sink_stats)
    return stats
