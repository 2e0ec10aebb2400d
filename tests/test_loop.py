"""The streaming loop: failures, strict mode, flow limiting, stop/signals, statistics."""

from __future__ import annotations

import json
import logging
import signal
import threading
import time

import numpy as np
import pytest

from illuminet.hw.replay import ReplaySource
from illuminet.runtime.stage import Sink, Source, Stage
from illuminet.runtime.stream.loop import LoopStats, run_loop
from illuminet.runtime.stream.session import SessionReader
from illuminet.runtime.stream.sinks import NullSink

from ._sessions import frames, make_session, spawn, wait_for_lines


class SeqStage(Stage):
    """Adds results['level'] = seq * 10; raises on the frames listed in ``fail_on``."""

    name = "level"

    def __init__(self, fail_on=(), error=ValueError, delay_s=0.0):
        self.fail_on = set(fail_on)
        self.error = error
        self.delay_s = delay_s
        self.opened = self.closed = 0

    def open(self):
        self.opened += 1

    def close(self):
        self.closed += 1

    def process(self, frame):
        if self.delay_s:
            time.sleep(self.delay_s)
        if frame.seq in self.fail_on:
            raise self.error(f"no plane in frame {frame.seq}")
        return frame.with_result("level", frame.seq * 10)


class Collect(Sink):
    name = "collect"

    def __init__(self, fail_on=()):
        self.frames = []
        self.fail_on = set(fail_on)
        self.closed = False

    def write(self, frame):
        if frame.seq in self.fail_on:
            raise OSError(f"disk full at {frame.seq}")
        self.frames.append(frame)

    def close(self):
        self.closed = True


@pytest.fixture
def session(tmp_path):
    make_session(tmp_path / "s", 10)
    return tmp_path / "s"


def _asap(path, **kw):
    return ReplaySource(path, timing="asap", **kw)


def test_all_frames_flow_through_with_timing(session):
    sink = Collect()
    st = run_loop(_asap(session), [SeqStage()], [sink])
    assert [f.results["level"] for f in sink.frames] == [k * 10 for k in range(10)]
    d = st.to_dict()
    assert d["frames"] == 10 and d["dropped"] == 0 and d["failed_frames"] == 0 and d["end_reason"] == "end of stream"
    assert list(d["steps"]) == ["source", "stage:level", "latency", "sink:collect", "total"]
    assert d["steps"]["stage:level"]["n"] == 10 and d["steps"]["total"]["median_ms"] > 0
    assert d["steps"]["latency"]["n"] == 10 and d["steps"]["latency"]["median_ms"] > 0
    assert sink.closed


class BusyStage(Stage):
    """Spends ``busy_s`` of CPU on every frame."""

    name = "busy"

    def __init__(self, busy_s):
        self.busy_s = busy_s

    def process(self, frame):
        t0 = time.thread_time()
        x = 0
        while time.thread_time() - t0 < self.busy_s:
            x += 1
        return frame.with_result("busy", x)


@pytest.mark.parametrize("pipeline", ["serial", "threads"])
def test_each_stage_is_charged_its_own_cpu_time_not_its_waits(session, pipeline):
    # a stage that sleeps 20 ms a frame costs no CPU; one that computes 20 ms costs 20 ms
    st = run_loop(_asap(session), [SeqStage(delay_s=0.02), BusyStage(0.02)], [NullSink()], pipeline=pipeline)
    assert st.frames == 10
    assert min(st.samples["stage:level"].values) >= 0.02
    assert st.stage_cpu_s["level"] < 0.05  # 10 frames: ~0 CPU, against >= 0.2 s of wall time
    assert 0.2 <= st.stage_cpu_s["busy"] < 0.4
    assert 20 <= st.to_dict()["stage_cpu_ms_per_frame"]["busy"] < 40


def test_failing_frame_is_counted_stream_goes_on_with_last_good_result(session, caplog):
    sink = Collect()
    stage = SeqStage(fail_on={3, 4, 7})
    with caplog.at_level(logging.ERROR):
        st = run_loop(_asap(session), [stage], [sink])
    assert len(sink.frames) == 10  # the failing frames still reach the outputs
    assert [f.results["level"] for f in sink.frames] == [0, 10, 20, 20, 20, 50, 60, 60, 80, 90]
    assert st.failed_frames == 3 and st.failures == {"stage:level: ValueError": 3}
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1, "logged once per kind"
    assert "no plane in frame 3" in errors[0].getMessage() and "--strict" in errors[0].getMessage()
    assert stage.opened == 1 and stage.closed == 1
    assert "failure stage:level: ValueError: 3x" in st.format_stats()


def test_each_error_kind_is_logged_once(session, caplog):
    class Two(SeqStage):
        def process(self, frame):
            if frame.seq in (1, 2):
                raise ValueError("a")
            if frame.seq in (5, 6):
                raise KeyError("b")
            return frame

    with caplog.at_level(logging.ERROR):
        st = run_loop(_asap(session), [Two()], [])
    assert st.failures == {"stage:level: ValueError": 2, "stage:level: KeyError": 2}
    assert len([r for r in caplog.records if r.levelno == logging.ERROR]) == 2


def test_first_frame_failing_has_no_last_good_result(session):
    sink = Collect()
    run_loop(_asap(session), [SeqStage(fail_on={0})], [sink])
    assert "level" not in sink.frames[0].results and sink.frames[1].results["level"] == 10


def test_strict_raises_and_still_closes_everything(session):
    sink, stage = Collect(), SeqStage(fail_on={2})
    src = _asap(session)
    with pytest.raises(ValueError, match="no plane in frame 2"):
        run_loop(src, [stage], [sink], strict=True)
    assert sink.closed and stage.closed == 1 and src._closed


def test_stage_returning_no_frame_is_a_failure(session):
    class Bad(Stage):
        name = "bad"

        def process(self, frame):
            return None

    with pytest.raises(TypeError, match="returned NoneType, expected a Frame"):
        run_loop(_asap(session), [Bad()], [], strict=True)
    assert run_loop(_asap(session), [Bad()], []).failed_frames == 10


def test_sink_failure_is_counted(session):
    sink, other = Collect(fail_on={1, 2}), Collect()
    st = run_loop(_asap(session), [], [sink, other])
    assert st.sink_failures == 2 and st.failed_frames == 0
    assert len(sink.frames) == 8 and len(other.frames) == 10  # other outputs unaffected
    with pytest.raises(OSError, match="disk full at 1"):
        run_loop(_asap(session), [], [Collect(fail_on={1})], strict=True)


class FastLiveSource(Source):
    """A camera that delivers ``n`` frames as fast as the reader thread asks (live: flow-limited)."""

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
            f = self.frames[self.delivered]
            self.delivered += 1
            self.cond.notify_all()
            return f

    def wait_delivered(self, k, timeout=5.0):
        with self.cond:
            assert self.cond.wait_for(lambda: self.delivered >= k, timeout), f"camera stuck at {self.delivered}"


class WaitForCamera(Stage):
    """A slow stage, slowness made exact: on frame k it returns only once the camera has delivered
    frame k + ``ahead`` (or its last frame), so the loop is always behind by that many frames."""

    name = "slow"

    def __init__(self, source, ahead):
        self.source, self.ahead = source, ahead

    def process(self, frame):
        self.source.wait_delivered(min(frame.seq + 1 + self.ahead, len(self.source.frames)))
        return frame


def test_live_source_keeps_newest_frame_and_counts_drops(session):
    """A live camera faster than a stage: the loop skips frames instead of lagging behind."""
    assert ReplaySource(session, timing="recorded").live  # a replay at its recorded pace is live too
    src, sink = FastLiveSource(60), Collect()
    st = run_loop(src, [WaitForCamera(src, ahead=5)], [sink])
    seqs = [f.seq for f in sink.frames]
    assert st.frames + st.dropped == 60, st.to_dict()  # every frame was either processed or dropped
    assert st.dropped >= 4 * (st.frames - 1)  # the 5 delivered during each stage call but the newest
    assert all(b > a for a, b in zip(seqs, seqs[1:]))
    assert seqs[-1] == 59  # the newest frame is the one processed
    # a non-live source (replay asap) is read in the loop's thread: nothing is dropped
    st2 = run_loop(_asap(session), [SeqStage(delay_s=0.002)], [NullSink()])
    assert st2.dropped == 0 and st2.frames == 10


class StopAt(Collect):
    """A sink that sets ``stop`` once it has written ``n`` frames (the stop request of a user)."""

    def __init__(self, stop, n):
        super().__init__()
        self.stop, self.n = stop, n

    def write(self, frame):
        super().write(frame)
        if len(self.frames) == self.n:
            self.stop.set()


def test_max_frames_and_stop_event(session):
    st = run_loop(_asap(session, loop=True), [], [], max_frames=25)
    assert st.frames == 25 and st.end_reason == "max_frames"
    # a stop request ends the stream after the frame in hand, on a live (recorded-pace) source too
    stop = threading.Event()
    sink = StopAt(stop, 3)
    st = run_loop(ReplaySource(session, timing="recorded", loop=True), [], [sink], stop_event=stop)
    assert st.end_reason == "stopped" and st.frames == 3 and sink.closed


def test_stop_does_not_wait_for_a_slow_live_source(tmp_path):
    make_session(tmp_path / "slow", 3, fps=0.5)  # the replay sleeps 2 s between frames
    stop = threading.Event()
    t0 = time.monotonic()
    # stop as soon as the first frame is out: the reader thread is then asleep until the next one
    st = run_loop(ReplaySource(tmp_path / "slow", timing="recorded"), [], [StopAt(stop, 1)], stop_event=stop)
    assert st.frames == 1 and st.end_reason == "stopped"
    assert time.monotonic() - t0 < 1.5  # not the 2 s the source would take to give the next frame


def test_snapshot_is_thread_safe_and_on_stats_is_called(session):
    """Another thread reads the live statistics while the loop runs: every 10th frame the sink hands
    the turn to a reader thread and waits until it has taken its snapshot (no polling, no sleeps)."""
    stats = LoopStats()
    polled, reports = [], []
    turn, taken, done = threading.Event(), threading.Event(), threading.Event()

    def reader():
        while True:
            turn.wait(5.0)
            turn.clear()
            if done.is_set():
                return
            polled.append(stats.snapshot())
            taken.set()

    class HandOver(NullSink):
        def write(self, frame):
            if frame.seq % 10 == 9:
                turn.set()
                assert taken.wait(5.0), "the reader thread did not take its snapshot"
                taken.clear()

    t = threading.Thread(target=reader)
    t.start()
    try:
        run_loop(
            _asap(session, loop=True),
            [SeqStage(delay_s=0.002)],
            [HandOver()],
            max_frames=60,
            stats=stats,
            on_stats=reports.append,
            stats_interval_s=0.0,
        )
    finally:
        done.set()
        turn.set()
        t.join()
    # each snapshot was taken from the other thread while the loop ran, inside frame 10k + 9's sink
    assert [p["frames"] for p in polled] == [9, 19, 29, 39, 49, 59] and all(p["running"] for p in polled)
    last = stats.snapshot()
    assert last["frames"] == 60 and last["running"] is False and last["fps"] > 0 and last["fps_recent"] > 0
    assert set(last["stages_ms"]) == {"source", "stage:level", "sink:null", "total"}
    assert last["stages_ms"]["stage:level"] >= 2.0
    # latency (capture -> sinks) includes at least the stage's 2 ms; CPU time per frame is counted
    assert last["latency_ms"]["n"] == 60 and last["latency_ms"]["median"] >= 2.0
    assert last["latency_ms"]["p99"] >= last["latency_ms"]["median"] and last["cpu_ms_per_frame"] > 0
    # stats_interval_s = 0: on_stats after every frame, and once more at the end
    assert len(reports) == 61 and [r["frames"] for r in reports[:60]] == list(range(1, 61))
    assert reports[-1]["frames"] == 60 and reports[-1]["running"] is False
    json.loads(json.dumps(last))


def test_failing_stats_callback_does_not_stop_the_stream(session, caplog):
    def bad(snapshot):
        raise RuntimeError("status page gone")

    with caplog.at_level(logging.ERROR):
        st = run_loop(_asap(session), [], [], on_stats=bad, stats_interval_s=0.0)
    assert st.frames == 10 and "status page gone" in caplog.text
    with pytest.raises(RuntimeError, match="status page gone"):
        run_loop(_asap(session), [], [], on_stats=bad, stats_interval_s=0.0, strict=True)


def test_to_json_and_table(session):
    st = run_loop(_asap(session), [SeqStage()], [NullSink()])
    d = json.loads(st.to_json())
    assert d["frames"] == 10 and set(d["steps"]["total"]) == {"n", "median_ms", "p99_ms", "max_ms"}
    table = st.format_stats()
    for row in ("source", "stage:level", "sink:null", "total", "median ms", "p99 ms", "10 frames in"):
        assert row in table


def test_runs_outside_the_main_thread_without_signal_handlers(session):
    before = signal.getsignal(signal.SIGTERM)
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("st", run_loop(_asap(session), [], [])))
    t.start()
    t.join()
    assert out["st"].frames == 10 and signal.getsignal(signal.SIGTERM) is before


def test_a_second_signal_while_the_front_thread_finishes_still_records_why_the_run_ended(session):
    # threads: the stop joins the front thread (up to 10 s); a second Ctrl-C there raised
    # KeyboardInterrupt before the statistics were closed: "ended: " was blank and running stayed True
    stop = threading.Event()

    class SlowToFinish(Stage):
        name = "slow"

        def process(self, frame):
            if frame.seq == 2:
                stop.set()  # the first Ctrl-C
                time.sleep(0.5)  # the loop thread is now joining this thread
                signal.raise_signal(signal.SIGINT)  # the second one
                time.sleep(1.0)
            return frame

    st = LoopStats()
    with pytest.raises(KeyboardInterrupt):
        run_loop(_asap(session), [SlowToFinish()], [Collect()], pipeline="threads", stop_event=stop, stats=st)
    assert st.end_reason == "interrupted" and not st.running
    assert json.loads(st.to_json())["end_reason"] == "interrupted"


def test_signal_handlers_are_restored(session):
    before = signal.getsignal(signal.SIGINT)
    run_loop(_asap(session), [], [])
    assert signal.getsignal(signal.SIGINT) is before


def test_sink_that_cannot_open_closes_what_was_opened(session):
    class NoOpen(Sink):
        name = "noopen"

        def open(self):
            raise OSError("cannot open output")

        def write(self, frame):
            pass

    stage, src = SeqStage(), _asap(session)
    with pytest.raises(OSError, match="cannot open output"):
        run_loop(src, [stage], [NoOpen()])
    assert stage.closed == 1 and src._closed


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_to_a_recording_subprocess_finalises_it(tmp_path, sig):
    make_session(tmp_path / "src", 10, fps=60.0)
    out = tmp_path / "rec"
    proc = spawn(["-m", "illuminet", "record", f"replay://{tmp_path}/src?timing=recorded&loop=1", str(out)])
    try:
        wait_for_lines(out / "frames.jsonl", 8, proc)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    r = SessionReader(out, strict=True)  # finalised, no problem at all
    assert r.finalized and r.manifest["frame_count"] == len(r) >= 8
    assert "ended: stopped" in stdout and "sink:record" in stdout
    seqs = [f.seq for f in r]
    assert all(b > a for a, b in zip(seqs, seqs[1:]))
    src = list(SessionReader(tmp_path / "src"))
    for f in r:  # what was recorded is what the source gave (the loop restarts with seq + 10)
        assert np.array_equal(f.color, src[f.seq % 10].color)


class Fragmenter(Stage):
    """Leaves the C heap full of holes: 64 KB blocks (inside glibc's heap, under its mmap threshold),
    every other one freed, the rest kept until close."""

    name = "fragment"

    def __init__(self):
        self.kept = []

    def process(self, frame):
        blocks = [bytearray(64 * 1024) for _ in range(200)]
        self.kept.extend(blocks[::2])
        time.sleep(0.02)
        return frame

    def close(self):
        self.kept.clear()


def test_the_heap_trimmer_hands_free_pages_back_between_frames(session):
    from illuminet.runtime.stream import memtrim

    if memtrim._MALLOC_TRIM is None:
        pytest.skip("not glibc: there is no malloc_trim to call")
    st = run_loop(_asap(session), [Fragmenter()], [NullSink()], trim_memory_s=0.05)
    mt = st.to_dict()["memory_trim"]
    assert mt["available"] and mt["calls"] >= 2, mt
    # 10 frames x 100 freed 64 KB blocks: tens of MB of whole free pages between the kept blocks
    assert mt["released_mb"] > 10, mt
    assert "memory trim:" in st.format_stats()
    off = run_loop(_asap(session), [Fragmenter()], [NullSink()])  # the API's default: never
    assert off.to_dict()["memory_trim"]["calls"] == 0


class OpenCVThreads(Stage):
    name = "opencv_threads"

    def __init__(self):
        self.seen = set()

    def process(self, frame):
        import cv2

        self.seen.add(cv2.getNumThreads())
        return frame


@pytest.mark.parametrize("pipeline", ["serial", "threads"])
def test_the_loop_sets_opencvs_thread_count_while_it_runs_and_restores_it(session, pipeline):
    """``[loop] opencv_threads`` (default 1): OpenCV's workers spinning between the frames' small calls
    cost CPU on a 2-core board; the loop sets the count for its run and puts the old one back."""
    import cv2

    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(2)
        probe = OpenCVThreads()
        run_loop(_asap(session), [probe], [NullSink()], pipeline=pipeline)
        assert probe.seen == {1} and cv2.getNumThreads() == 2
        probe = OpenCVThreads()
        run_loop(_asap(session), [probe], [NullSink()], pipeline=pipeline, opencv_threads=0)  # OpenCV's own
        assert probe.seen == {2} and cv2.getNumThreads() == 2
        with pytest.raises(ValueError, match="opencv_threads"):
            run_loop(_asap(session), [OpenCVThreads()], [NullSink()], opencv_threads=-1)
    finally:
        cv2.setNumThreads(before)
