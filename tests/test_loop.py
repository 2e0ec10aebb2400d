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
from illuminet.runtime.stage import Sink, Stage
from illuminet.runtime.stream.loop import LoopStats, run_loop
from illuminet.runtime.stream.session import SessionReader
from illuminet.runtime.stream.sinks import NullSink

from ._sessions import make_session, spawn, wait_for_lines


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
    assert list(d["steps"]) == ["source", "stage:level", "sink:collect", "total"]
    assert d["steps"]["stage:level"]["n"] == 10 and d["steps"]["total"]["median_ms"] > 0
    assert sink.closed


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


def test_live_source_keeps_newest_frame_and_counts_drops(tmp_path):
    """A live source at 200 fps into a 25 ms stage: the loop skips frames instead of lagging behind."""
    make_session(tmp_path / "fast", 60, fps=200.0)
    sink = Collect()
    src = ReplaySource(tmp_path / "fast", timing="recorded")
    assert src.live
    st = run_loop(src, [SeqStage(delay_s=0.025)], [sink])
    seqs = [f.seq for f in sink.frames]
    assert st.dropped > 20, st.to_dict()
    assert st.frames + st.dropped <= 60
    assert st.frames + st.dropped >= 58  # at most the frame in hand at the end is neither
    assert all(b > a for a, b in zip(seqs, seqs[1:]))
    assert seqs[-1] >= 58  # the newest frames are the ones processed
    # the same session replayed asap drops nothing
    st2 = run_loop(ReplaySource(tmp_path / "fast", timing="asap"), [SeqStage(delay_s=0.002)], [NullSink()])
    assert st2.dropped == 0 and st2.frames == 60


def test_max_frames_and_stop_event(session):
    st = run_loop(_asap(session, loop=True), [], [], max_frames=25)
    assert st.frames == 25 and st.end_reason == "max_frames"
    stop = threading.Event()
    sink = Collect()
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    st = run_loop(ReplaySource(session, timing="recorded", loop=True), [], [sink], stop_event=stop)
    elapsed = time.monotonic() - t0
    assert st.end_reason == "stopped" and elapsed < 2.0 and sink.closed
    assert 3 <= st.frames <= 30 * elapsed + 2  # a 30 fps recording, played at its pace until stopped


def test_stop_does_not_wait_for_a_slow_live_source(tmp_path):
    make_session(tmp_path / "slow", 3, fps=0.5)  # the replay sleeps 2 s between frames
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    t0 = time.monotonic()
    st = run_loop(ReplaySource(tmp_path / "slow", timing="recorded"), [], [], stop_event=stop)
    assert st.frames == 1 and st.end_reason == "stopped"
    assert time.monotonic() - t0 < 1.5


def test_snapshot_is_thread_safe_and_on_stats_is_called(session):
    stats = LoopStats()
    polled, reports = [], []
    done = threading.Event()

    def poll():
        while not done.is_set():
            polled.append(stats.snapshot())
    t = threading.Thread(target=poll)
    t.start()
    try:
        run_loop(_asap(session, loop=True), [SeqStage(delay_s=0.002)], [NullSink()], max_frames=150,
                 stats=stats, on_stats=reports.append, stats_interval_s=0.05)
    finally:
        done.set()
        t.join()
    assert len(polled) > 5
    last = stats.snapshot()
    assert last["frames"] == 150 and last["running"] is False and last["fps"] > 0 and last["fps_recent"] > 0
    assert set(last["stages_ms"]) == {"source", "stage:level", "sink:null", "total"}
    assert last["stages_ms"]["stage:level"] >= 2.0
    assert len(reports) >= 2 and reports[-1]["frames"] == 150
    assert all(a["frames"] <= b["frames"] for a, b in zip(polled, polled[1:]))
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
