"""The pipelined loop ([loop] pipeline = "threads"): same output as serial, threads, bounded queues, latency.

Nothing here is timed: overlap and bounds are shown by counting (a stage waits for another thread's
progress, with a generous timeout only so that a broken pipeline fails instead of hanging).
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time

import numpy as np
import pytest

from illuminet.hw.replay import ReplaySource
from illuminet.runtime.config import ConfigError, apply_overrides, defaults
from illuminet.runtime.frame import Frame
from illuminet.runtime.stage import Sink, Source, Stage
from illuminet.runtime.stream.loop import resolve_pipeline, run_loop

from ._sessions import frames, make_session

WAIT_S = 10.0  # only a safety net against a hang; never reached when the pipeline works


class Front(Stage):
    """A depth-only stage (runs ahead on the worker when pipelined); fails on ``fail_on``."""

    name = "front"

    def __init__(self, fail_on=()):
        self.fail_on = set(fail_on)
        self.threads: set[int] = set()
        self.started: list[int] = []
        self.cond = threading.Condition()
        self.closed = 0

    def process(self, frame):
        with self.cond:
            self.started.append(frame.seq)
            self.cond.notify_all()
        self.threads.add(threading.get_ident())
        if frame.seq in self.fail_on:
            raise ValueError(f"front fails on {frame.seq}")
        return frame.with_result("front", frame.seq * 10)

    def wait_started(self, seq, timeout=WAIT_S) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: seq in self.started, timeout)

    def close(self):
        self.closed += 1


class Bound(Stage):
    """A thread-bound stage (like the renderer): must run on the loop's thread, after ``front``."""

    name = "bound"
    requires = ()
    thread_bound = True

    def __init__(self, fail_on=(), front: Front | None = None, wait_ahead=0):
        self.fail_on = set(fail_on)
        self.front = front
        self.wait_ahead = wait_ahead
        self.threads: set[int] = set()
        self.overlapped: list[bool] = []
        self.ahead: list[int] = []
        self.closed = 0

    def process(self, frame):
        self.threads.add(threading.get_ident())
        if self.front is not None:
            with self.front.cond:
                self.ahead.append(len(self.front.started) - 1 - frame.seq)
        if self.wait_ahead and self.front is not None and frame.seq + 1 < self.wait_ahead:
            # frame k renders only once the front half has started frame k + 1: proof of overlap
            self.overlapped.append(self.front.wait_started(frame.seq + 1))
        if frame.seq in self.fail_on:
            raise KeyError(f"bound fails on {frame.seq}")
        return frame.with_result("bound", (frame.results.get("front"), frame.seq))

    def close(self):
        self.closed += 1


class Collect(Sink):
    name = "collect"

    def __init__(self):
        self.frames: list[Frame] = []
        self.threads: set[int] = set()
        self.closed = False

    def write(self, frame):
        self.threads.add(threading.get_ident())
        self.frames.append(frame)

    def close(self):
        self.closed = True


@pytest.fixture
def session(tmp_path):
    make_session(tmp_path / "s", 12)
    return tmp_path / "s"


def _asap(path, **kw):
    return ReplaySource(path, timing="asap", **kw)


def test_front_stages_run_on_a_worker_thread_and_the_bound_stage_on_the_loop_thread(session):
    front, sink = Front(), Collect()
    bound = Bound(front=front)
    st = run_loop(_asap(session), [front, bound], [sink], pipeline="threads")
    me = threading.get_ident()
    assert bound.threads == {me} and sink.threads == {me}  # GL context and sinks stay on the loop's thread
    assert len(front.threads) == 1 and me not in front.threads
    assert st.pipeline == "threads" and st.depth == 1 and st.to_dict()["pipeline"] == "threads"
    assert [f.seq for f in sink.frames] == list(range(12))  # order kept, nothing dropped
    assert front.closed == bound.closed == 1 and sink.closed


def test_the_front_half_works_on_the_next_frame_while_the_bound_stage_runs(session):
    front = Front()
    bound = Bound(front=front, wait_ahead=12)  # the session's 12 frames
    run_loop(_asap(session), [front, bound], [Collect()], pipeline="threads")
    # every frame but the last: the worker had started frame k + 1 while frame k was being rendered
    assert bound.overlapped == [True] * 11


@pytest.mark.parametrize("depth", [1, 3])
def test_the_worker_runs_at_most_depth_frames_ahead(session, depth):
    front = Front()
    bound = Bound(front=front)
    st = run_loop(_asap(session), [front, bound], [Collect()], pipeline="threads", depth=depth)
    # when the loop thread starts frame k, the worker has started at most k + depth + 1 frames:
    # `depth` finished ones waiting in the hand-off and one in its hands
    assert max(bound.ahead) <= depth + 1 and st.in_flight_max <= depth
    assert st.frames == 12


def test_threads_give_the_serial_results_failures_and_counts(session, caplog):
    out = {}
    for mode in ("serial", "threads"):
        sink = Collect()
        with caplog.at_level(logging.ERROR):
            caplog.clear()
            st = run_loop(_asap(session), [Front(fail_on={2, 3}), Bound(fail_on={5})], [sink], pipeline=mode, depth=2)
        out[mode] = (
            [(f.seq, f.results.get("front"), f.results.get("bound")) for f in sink.frames],
            st.failed_frames,
            dict(st.failures),
            len([r for r in caplog.records if r.levelno == logging.ERROR]),
        )
    assert out["serial"] == out["threads"]
    rows, failed, failures, logged = out["threads"]
    assert rows[3][1] == 10  # front failed on 2 and 3: the last good result (frame 1's) is carried
    assert rows[5][2] == (40, 4)  # the bound stage failed on 5: frame 4's result is carried
    assert failed == 3 and failures == {"stage:front: ValueError": 2, "stage:bound: KeyError": 1} and logged == 2


@pytest.mark.parametrize("where", ["front", "bound"])
def test_strict_raises_from_either_thread_and_closes_everything(session, where):
    front = Front(fail_on={4} if where == "front" else ())
    bound = Bound(fail_on={4} if where == "bound" else ())
    sink, src = Collect(), _asap(session)
    with pytest.raises(ValueError if where == "front" else KeyError, match="fails on 4"):
        run_loop(src, [front, bound], [sink], strict=True, pipeline="threads")
    assert front.closed == 1 and bound.closed == 1 and sink.closed and src._closed
    assert [f.seq for f in sink.frames] == [0, 1, 2, 3]


def test_max_frames_and_stop_with_threads(session):
    st = run_loop(_asap(session, loop=True), [Front(), Bound()], [], max_frames=25, pipeline="threads")
    assert st.frames == 25 and st.end_reason == "max_frames"
    stop = threading.Event()

    class StopAt(Collect):
        def write(self, frame):
            super().write(frame)
            if len(self.frames) == 3:
                stop.set()

    sink = StopAt()
    st = run_loop(_asap(session, loop=True), [Front(), Bound()], [sink], stop_event=stop, pipeline="threads")
    assert st.end_reason == "stopped" and st.frames == 3 and sink.closed


class FastLiveSource(Source):
    """A camera delivering ``n`` frames as fast as it is read (live: the loop's slot drops)."""

    name = "fast-camera"
    live = True

    def __init__(self, n):
        self.frames = frames(n)
        self.delivered = 0
        self.cond = threading.Condition()

    def read(self):
        with self.cond:
            if self.delivered == len(self.frames):
                return None
            f = self.frames[self.delivered].replace(t_host_ns=time.monotonic_ns())
            self.delivered += 1
            self.cond.notify_all()
            return f

    def wait_delivered(self, k):
        with self.cond:
            assert self.cond.wait_for(lambda: self.delivered >= k, WAIT_S), f"camera stuck at {self.delivered}"


class SlowBound(Bound):
    """The renderer, slowness made exact: frame k returns once the camera delivered frame k + ahead."""

    def __init__(self, source, ahead):
        super().__init__()
        self.source, self.ahead = source, ahead

    def process(self, frame):
        self.source.wait_delivered(min(frame.seq + 1 + self.ahead, len(self.source.frames)))
        return super().process(frame)


def test_a_fast_live_camera_never_grows_a_queue_with_threads():
    src, sink = FastLiveSource(200), Collect()
    st = run_loop(src, [Front(), SlowBound(src, ahead=6)], [sink], pipeline="threads")
    seqs = [f.seq for f in sink.frames]
    # every frame was processed, dropped by the newest-frame slot, or was in flight at the end
    assert st.frames + st.dropped <= 200 <= st.frames + st.dropped + 2, st.to_dict()
    assert st.dropped > 100 and st.in_flight_max <= 1  # the hand-off never held more than its depth
    assert all(b > a for a, b in zip(seqs, seqs[1:]))


def test_a_live_synthetic_camera_drops_the_oldest_and_its_queue_stays_bounded():
    """``synthetic://...?live=1``: frames come on the camera's own clock; a slow reader never makes its
    queue (2 frames) or the loop's (1 slot + depth) grow: it makes drops."""
    from illuminet.hw import open_source

    src = open_source("synthetic://lamp?live=1&fps=1000&frames=300&size=64x40", defaults())
    assert src.live and src.queue == 2

    class WaitForCamera(Bound):
        def process(self, frame):  # the loop is at least 20 camera frames behind on every frame
            with src._cond:
                src._cond.wait_for(lambda: src.delivered >= min(frame.seq + 20, 300) or src._finished, WAIT_S)
            return super().process(frame)

    sink = Collect()
    st = run_loop(src, [Front(), WaitForCamera()], [sink], pipeline="threads")
    s = st.source_stats
    assert s["delivered"] == 300 and s["queue_max"] <= 2 and st.in_flight_max <= 1
    # every delivered frame reached the sinks or was dropped (by the camera's queue or the loop's slot)
    assert st.frames + st.dropped + s["dropped"] <= 300 <= st.frames + st.dropped + s["dropped"] + 3
    # the loop is always 20 frames behind: about one frame in 20 is processed (a few more at the end,
    # when the camera has stopped and the frames in the pipeline's hands finish without waiting)
    assert st.frames <= 300 // 20 + 8


def test_replay_at_recorded_timing_says_once_how_to_keep_every_frame(tmp_path, caplog):
    make_session(tmp_path / "fast", 30, fps=200.0)
    src = ReplaySource(tmp_path / "fast", timing="recorded")

    class Behind(Stage):  # frame k returns once the replay has emitted 4 more frames (always behind)
        name = "behind"

        def process(self, frame):
            deadline = time.monotonic() + WAIT_S
            while src._emitted < min(frame.seq + 5, 30) and time.monotonic() < deadline:
                time.sleep(0.001)
            return frame

    with caplog.at_level(logging.WARNING):
        st = run_loop(src, [Behind()], [Collect()])
    assert st.dropped > 0
    advice = [r.getMessage() for r in caplog.records if "--timing asap" in r.getMessage()]
    assert len(advice) == 1 and "slower than the recording" in advice[0]
    # a camera drops by design: no advice
    assert FastLiveSource(1).drop_advice == ""


class StampedSource(Source):
    """Frames whose capture stamp (t_host_ns) is ``offset_ns`` before their arrival, or a fixed value."""

    def __init__(self, n, offset_ns=None, fixed=None):
        self.n, self.i, self.offset_ns, self.fixed = n, 0, offset_ns, fixed

    def read(self):
        if self.i == self.n:
            return None
        f = frames(1)[0].replace(seq=self.i)
        self.i += 1
        t = self.fixed if self.fixed is not None else time.monotonic_ns() - self.offset_ns
        return f.replace(t_host_ns=t)


@pytest.mark.parametrize("mode", ["serial", "threads"])
def test_latency_counts_from_the_capture_stamp_when_it_is_on_the_host_clock(mode):
    # captured 200 ms before it arrived: the latency includes those 200 ms
    st = run_loop(StampedSource(5, offset_ns=200_000_000), [Front(), Bound()], [], pipeline=mode)
    lat = st.to_dict()["steps"]["latency"]
    assert lat["n"] == 5 and lat["median_ms"] >= 200.0
    # a stamp on another clock (0, or in the future) is not used: the arrival counts instead
    for fixed in (0, time.monotonic_ns() + 10**15):
        st = run_loop(StampedSource(5, fixed=fixed), [Front(), Bound()], [], pipeline=mode)
        lat = st.to_dict()["steps"]["latency"]
        assert lat["n"] == 5 and 0.0 <= lat["median_ms"] < 1000.0
    assert st.snapshot()["latency_ms"]["n"] == 5


def test_pipeline_setting():
    stages = [Front(), Bound()]
    assert resolve_pipeline("serial", stages) == "serial" and resolve_pipeline("threads", stages) == "threads"
    assert resolve_pipeline("auto", [Bound()]) == "serial"  # nothing to run ahead of the bound stage
    with pytest.raises(ValueError, match=r"\[loop\] pipeline"):
        resolve_pipeline("fast", stages)
    with pytest.raises(ConfigError, match="pipeline"):
        apply_overrides(defaults(), [("loop", "pipeline", "fast")])
    with pytest.raises(ConfigError, match="depth"):
        apply_overrides(defaults(), [("loop", "depth", 0)])


def test_the_demo_chain_gives_the_same_composites_serial_and_pipelined():
    """The real chain (planes, anchor + odometry, plane light, light estimate with its own 10 Hz worker,
    PRT shading, GL render) on the shipped demo session, replayed asap: byte-identical composites."""
    from illuminet.commands.demo import default_source_url, demo_stages
    from illuminet.hw import open_source
    from illuminet.runtime.scene import COMPOSITE, LIGHT

    class Digest(Sink):
        name = "digest"

        def __init__(self):
            self.rows = []

        def write(self, frame):
            comp = frame.results.get(COMPOSITE.name)
            light = frame.results.get(LIGHT.name)
            self.rows.append(
                (
                    frame.seq,
                    None if comp is None else hashlib.sha1(np.ascontiguousarray(comp).tobytes()).hexdigest(),
                    None if light is None else np.asarray(light.sh9).tobytes(),
                )
            )

    cfg = apply_overrides(defaults(), [("source", "timing", "asap")])
    out = {}
    for mode in ("serial", "threads"):
        sink = Digest()
        st = run_loop(open_source(default_source_url(), cfg), demo_stages(cfg), [sink], max_frames=24, pipeline=mode)
        assert st.frames == 24 and st.failed_frames == 0 and st.pipeline == mode
        out[mode] = sink.rows
    assert all(r[1] is not None for r in out["serial"])  # the object was drawn on every frame
    assert out["serial"] == out["threads"]


def test_the_status_page_and_stats_json_show_latency_cpu_and_pipeline(session):
    """The MJPEG server's /stats.json passes the loop's snapshot through; the page shows the latency."""
    import http.client
    import json

    from illuminet.runtime.stream.loop import LoopStats
    from illuminet.runtime.stream.mjpeg import MjpegSink

    stats = LoopStats()
    run_loop(_asap(session), [Front(), Bound()], [], stats=stats, pipeline="threads")
    with MjpegSink(port=0, stats=stats.snapshot) as sink:
        conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
        conn.request("GET", "/stats.json")
        loop = json.loads(conn.getresponse().read())["loop"]
        conn.request("GET", "/")
        page = conn.getresponse().read().decode()
        conn.close()
    assert loop["latency_ms"]["n"] == 12 and loop["latency_ms"]["p99"] >= loop["latency_ms"]["median"] >= 0
    assert loop["cpu_ms_per_frame"] > 0 and loop["pipeline"] == "threads" and loop["depth"] == 1
    assert "latency_ms" in page and "cpu_ms_per_frame" in page


def test_bench_live_reports_drops_latency_quarters_and_bounded_queues(capsys):
    """`illuminet bench live` end to end on a tiny camera (figures are not judged, only their presence)."""
    import argparse

    from illuminet.bench import live

    assert [q["n"] for q in live.quarters([0.001] * 10)] == [3, 3, 2, 2]
    args = argparse.Namespace(quick=True, fps="100", seconds=3.0, size="96x60", pipeline="threads")
    res = live.run(args, defaults())["100fps-threads"]
    assert res["delivered"] == 300 and res["processed"] + res["dropped_loop"] + res["dropped_camera_queue"] <= 300
    assert res["queues_bounded"] and res["camera_queue_max"] <= 2 and res["handoff_max"] <= 1
    assert len(res["latency_quarters"]) == 4 and res["latency_p99_ms"] >= res["latency_median_ms"] > 0
    assert "per quarter" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="--fps"):
        live.run(argparse.Namespace(quick=True, fps="0", seconds=1.0, size=None, pipeline=None), defaults())
    # --seconds 0 ran the default 10 s per rate instead of being refused like any value outside 0.5..3600
    with pytest.raises(ConfigError, match=r"--seconds: expected 0.5..3600, got 0.0"):
        live.run(argparse.Namespace(quick=False, fps="100", seconds=0.0, size=None, pipeline=None), defaults())


def test_gl_draws_without_the_gil_give_the_same_pictures(monkeypatch):
    """The renderer's draws go through ctypes (the GIL released, runtime/render/nogil.py) on EGL; the
    composites are the bytes moderngl's own calls give."""
    import illuminet.runtime.render.compositor as comp_mod
    import illuminet.runtime.render.shadow as shadow_mod
    from illuminet.commands.demo import default_source_url, demo_stages
    from illuminet.hw import open_source
    from illuminet.runtime.render.gl import get_context
    from illuminet.runtime.render.nogil import gl_nogil
    from illuminet.runtime.scene import COMPOSITE

    get_context()
    if gl_nogil() is None:
        pytest.skip("the GL context is not an EGL one here: moderngl's own calls are used")

    class Keep(Sink):
        name = "keep"

        def __init__(self):
            self.pics = []

        def write(self, frame):
            self.pics.append(hashlib.sha1(frame.results[COMPOSITE.name].tobytes()).hexdigest())

    cfg = apply_overrides(defaults(), [("source", "timing", "asap")])
    out = []
    for off in (False, True):
        if off:
            monkeypatch.setattr(comp_mod, "gl_nogil", lambda: None)
            monkeypatch.setattr(shadow_mod, "gl_nogil", lambda: None)
        keep = Keep()
        run_loop(open_source(default_source_url(), cfg), demo_stages(cfg), [keep], max_frames=8)
        out.append(keep.pics)
    assert len(out[0]) == 8 and out[0] == out[1]
