"""replay:// source: timing modes, looping, URL/config handling, damaged sessions."""

from __future__ import annotations

import time

import numpy as np
import pytest

from illuminet.hw import SourceError, open_source
from illuminet.hw.replay import ReplaySource, open_url
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.stage import EndOfStream

from ._sessions import make_session, same_frame


def _read_all(src, limit=1000):
    out, times = [], []
    with src:
        while len(out) < limit:
            f = src.read()
            if f is None:
                break
            times.append(time.monotonic())
            out.append(f)
    return out, times


def test_asap_returns_every_frame_in_order_and_is_not_live(tmp_path):
    fs = make_session(tmp_path / "s", 12)
    src = ReplaySource(tmp_path / "s", timing="asap")
    assert not src.live
    got, _ = _read_all(src)
    assert len(got) == 12 and all(same_frame(a, b) for a, b in zip(fs, got))
    assert src.stats()["frames"] == 12 and src.stats()["corrupt"] == 0


def test_recorded_timing_follows_timestamps_and_asap_is_faster(tmp_path):
    make_session(tmp_path / "s", 10, fps=20.0)  # 50 ms apart: 450 ms from first to last
    src = ReplaySource(tmp_path / "s", timing="recorded")
    assert src.live  # recorded timing behaves like a camera for the loop's flow limiter
    got, times = _read_all(src)
    rel = np.array(times) - times[0]
    expected = np.array([(f.t_device_ns - got[0].t_device_ns) * 1e-9 for f in got])
    assert np.allclose(expected, np.arange(10) * 0.05)
    # never early (it sleeps until the timestamp), late only by scheduling noise on a busy machine
    assert np.all(rel >= expected - 0.002), rel - expected
    assert np.median(rel - expected) < 0.05, rel - expected
    assert rel[-1] < 0.45 + 0.3
    _, t_asap = _read_all(ReplaySource(tmp_path / "s", timing="asap"))
    assert t_asap[-1] - t_asap[0] < 0.5 * rel[-1]


def test_loop_restarts_with_increasing_seq_and_time(tmp_path):
    fs = make_session(tmp_path / "s", 5)
    got, _ = _read_all(ReplaySource(tmp_path / "s", timing="asap", loop=True, max_frames=13))
    assert len(got) == 13
    seqs = [f.seq for f in got]
    ts = [f.t_device_ns for f in got]
    assert seqs == list(range(13))
    assert all(b > a for a, b in zip(ts, ts[1:]))
    period = fs[1].t_device_ns - fs[0].t_device_ns
    assert all(b - a == period for a, b in zip(ts, ts[1:]))  # the restart keeps the frame rate
    for k in range(13):
        assert np.array_equal(got[k].color, fs[k % 5].color)


def test_max_frames_without_loop(tmp_path):
    make_session(tmp_path / "s", 8)
    got, _ = _read_all(ReplaySource(tmp_path / "s", timing="asap", max_frames=3))
    assert [f.seq for f in got] == [0, 1, 2]


def test_close_interrupts_a_recorded_wait(tmp_path):
    import threading

    make_session(tmp_path / "s", 3, fps=0.5)  # 2 s between frames
    src = ReplaySource(tmp_path / "s", timing="recorded")
    src.open()
    assert src.read() is not None
    threading.Timer(0.1, src.close).start()
    t0 = time.monotonic()
    assert src.read() is None
    assert time.monotonic() - t0 < 1.0


def test_url_query_overrides_config(tmp_path, monkeypatch):
    make_session(tmp_path / "s", 4)
    cfg = apply_overrides(
        defaults(), [("source", "timing", "asap"), ("source", "loop", True), ("source", "max_frames", 7)]
    )
    src = open_source(f"replay://{tmp_path}/s", cfg)
    assert isinstance(src, ReplaySource)
    assert (src.timing, src.loop, src.max_frames) == ("asap", True, 7)
    src = open_url(f"replay://{tmp_path}/s?timing=recorded&loop=0&max_frames=2", cfg)
    assert (src.timing, src.loop, src.max_frames) == ("recorded", False, 2)
    monkeypatch.chdir(tmp_path)  # relative paths: replay://s
    got, _ = _read_all(open_source("replay://s?timing=asap", defaults()))
    assert len(got) == 4


def test_a_home_relative_session_path_is_expanded(tmp_path, monkeypatch):
    """No shell expands ~ inside a URL: `replay://~/sessions/s` was looked for in a folder named '~'
    ('~/sessions/s: not a session folder'), and `run --video ~/...` beside it worked."""
    from illuminet.hw.replay import session_folder

    make_session(tmp_path / "sessions" / "s", 3)
    monkeypatch.setenv("HOME", str(tmp_path))
    got, _ = _read_all(open_source("replay://~/sessions/s?timing=asap", defaults()))
    assert len(got) == 3
    assert session_folder("replay://~/sessions/s") == tmp_path / "sessions" / "s"  # output checks see it too


@pytest.mark.parametrize(
    "query, expect",
    [
        ("timing=fast", r"timing='fast': expected one of recorded, asap"),
        ("loop=maybe", r"loop='maybe': expected 0/1"),
        ("max_frames=-1", r"max_frames='-1': expected an integer >= 0"),
        ("speed=2", r"unknown parameter 'speed'; known: timing, loop, max_frames"),
    ],
)
def test_bad_url_queries_are_named(tmp_path, query, expect):
    with pytest.raises(SourceError, match=expect):
        open_url(f"replay://{tmp_path}?{query}", defaults())


def test_missing_session_is_a_clear_source_error(tmp_path):
    src = open_source(f"replay://{tmp_path}/nope", defaults())
    with pytest.raises(SourceError, match="not a session folder"):
        src.open()
    with pytest.raises(SourceError, match="no session path"):
        open_url("replay://", defaults())


def test_corrupt_frame_is_skipped_and_counted(tmp_path, caplog):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000002.color.png"
    p.write_bytes(b"\x89PNG" + b"\0" * (p.stat().st_size - 4))  # same size, undecodable
    src = ReplaySource(tmp_path / "s", timing="asap")
    got, _ = _read_all(src)
    assert [f.seq for f in got] == [0, 1, 3, 4, 5]
    assert src.stats()["corrupt"] == 1
    assert "000002.color.png is not a decodable PNG" in caplog.text


def test_file_that_cannot_be_read_is_skipped(tmp_path, caplog):
    make_session(tmp_path / "s", 4)
    src = ReplaySource(tmp_path / "s", timing="asap", workers=1)
    with src:
        first = src.read()
        # after validation, frame 3's colour becomes unreadable (here: a folder, an OSError as root too)
        p = tmp_path / "s" / "frames" / "000003.color.png"
        p.unlink()
        p.mkdir()
        rest = []
        while (f := src.read()) is not None:
            rest.append(f)
    assert [first.seq] + [f.seq for f in rest] == [0, 1, 2] and src.stats()["corrupt"] == 1
    assert "cannot read" in caplog.text and "000003.color.png" in caplog.text


def test_session_with_nothing_intact(tmp_path):
    make_session(tmp_path / "s", 2)
    for p in (tmp_path / "s" / "frames").glob("*.color.png"):
        p.unlink()
    with pytest.raises(SourceError, match="no intact frame to replay.*missing file"):
        ReplaySource(tmp_path / "s").open()


def test_every_frame_unreadable_ends_with_an_error(tmp_path):
    make_session(tmp_path / "s", 3)
    for p in (tmp_path / "s" / "frames").glob("*.depth.png"):
        p.write_bytes(b"\0" * p.stat().st_size)
    src = ReplaySource(tmp_path / "s", timing="asap", loop=True)
    with src, pytest.raises(EndOfStream, match="every frame of the session is unreadable"):
        for _ in range(10):
            src.read()


def test_strict_config_refuses_a_damaged_session(tmp_path):
    make_session(tmp_path / "s", 4)
    (tmp_path / "s" / "frames" / "000001.depth.png").unlink()
    cfg = apply_overrides(defaults(), [("logging", "strict", True)])
    with pytest.raises(SourceError, match="invalid session"):
        open_source(f"replay://{tmp_path}/s", cfg).open()


def test_a_looped_replay_warns_once_per_damaged_frame_and_counts_every_skip(tmp_path, caplog):
    # `illuminet demo --mjpeg` and `--loop` replay until Ctrl-C: the same damaged frame logged a
    # warning on every round, a line a second for as long as the stream ran
    make_session(tmp_path / "s", 4)
    p = tmp_path / "s" / "frames" / "000002.color.png"
    p.write_bytes(b"\x89PNG" + b"\0" * (p.stat().st_size - 4))  # same size, undecodable
    src = ReplaySource(tmp_path / "s", timing="asap", loop=True)
    with caplog.at_level("DEBUG", logger="illuminet.hw.replay"), src:
        got = [src.read() for _ in range(15)]  # five rounds of the three intact frames
    assert [f.seq % 4 for f in got] == [0, 1, 3] * 5
    assert src.stats()["corrupt"] >= 4  # every skip is counted
    warnings = [r for r in caplog.records if r.levelname == "WARNING" and "000002.color.png" in r.getMessage()]
    assert len(warnings) == 1
