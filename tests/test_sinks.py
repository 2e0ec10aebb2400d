"""Output sinks: real video files, PNG sequences, the session recorder, build_sinks from the config."""

from __future__ import annotations

import logging
import os
import time

import cv2
import numpy as np
import pytest

from illuminet.hw.replay import ReplaySource
from illuminet.pipeline import build_sinks
from illuminet.runtime.config import ConfigError, apply_overrides, defaults
from illuminet.runtime.stage import Stage
from illuminet.runtime.stream.loop import run_loop
from illuminet.runtime.stream.session import SessionReader
from illuminet.runtime.stream.sinks import (
    NullSink,
    PngSequenceSink,
    SessionRecorderSink,
    SinkError,
    VideoSink,
    output_picture,
    pyav_available,
)

from ._sessions import H, W, frames, same_frame


class Composite(Stage):
    """Writes an inverted picture as results['composite'] (what a renderer does)."""

    name = "composite"

    def process(self, frame):
        return frame.with_result("composite", 255 - frame.color)


def _count_video(path):
    cap = cv2.VideoCapture(str(path))
    n, first = 0, None
    while True:
        ok, img = cap.read()
        if not ok:
            break
        first = img if first is None else first
        n += 1
    cap.release()
    return n, first


@pytest.mark.parametrize("ext", [".mp4", ".avi"])
def test_video_file_is_playable_with_all_frames(tmp_path, ext):
    fs = frames(12, w=160, h=120)
    sink = VideoSink(tmp_path / f"out{ext}", fps=30)
    with sink:
        for f in fs:
            sink.write(f)
    # .mp4: H.264 through PyAV when it is installed (the project's dependency), else OpenCV's mp4v
    assert sink.codec in (("h264",) if ext == ".mp4" and pyav_available() else ("mp4v", "avc1", "MJPG", "XVID"))
    n, first = _count_video(tmp_path / f"out{ext}")
    assert n == 12
    # lossy, but the picture is the frame's (RGB written as BGR correctly: mean colour per channel close)
    assert np.allclose(first[..., ::-1].reshape(-1, 3).mean(0), fs[0].color.reshape(-1, 3).mean(0), atol=6)
    assert not list(tmp_path.glob(".*probe*")), "the open() probe file is removed"


def test_mp4_is_h264_yuv420p_through_pyav_with_odd_sizes_padded(tmp_path):
    av = pytest.importorskip("av", reason="PyAV (pip install av) writes the H.264 MP4")
    fs = frames(7, w=161, h=121)
    sink = VideoSink(tmp_path / "o.mp4", fps=25)
    with sink:
        for f in fs:
            sink.write(f)
    assert sink.backend == "pyav" and sink.stats() == {"frames": 7, "codec": "h264", "backend": "pyav"}
    with av.open(str(tmp_path / "o.mp4")) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == "h264" and s.codec_context.pix_fmt == "yuv420p"
        assert (s.width, s.height) == (162, 122) and s.average_rate == 25
        decoded = [fr.to_ndarray(format="rgb24") for fr in c.decode(s)]
    assert len(decoded) == 7
    # the picture survives (lossy): mean colour per channel close to the frame's, incl. the repeated edge
    assert np.allclose(decoded[3][:121, :161].reshape(-1, 3).mean(0), fs[3].color.reshape(-1, 3).mean(0), atol=6)
    assert not list(tmp_path.glob(".*probe*"))


def test_video_backend_choice(tmp_path):
    assert VideoSink(tmp_path / "a.avi").backend == "opencv"  # MJPG in an AVI: OpenCV
    assert VideoSink(tmp_path / "a.mp4", codecs=("mp4v",)).backend == "opencv"  # FourCCs are OpenCV's
    assert VideoSink(tmp_path / "a.mp4", backend="opencv").backend == "opencv"
    with pytest.raises(SinkError, match="PyAV backend writes H.264 into"):
        VideoSink(tmp_path / "a.avi", backend="pyav")
    with pytest.raises(SinkError, match="backend must be auto, pyav or opencv"):
        VideoSink(tmp_path / "a.mp4", backend="ffmpeg")


def test_video_codec_fallback(tmp_path):
    sink = VideoSink(tmp_path / "x.mp4", codecs=("NOPE", "mp4v"))
    with sink:
        for f in frames(3, w=160, h=120):
            sink.write(f)
    assert sink.codec == "mp4v" and _count_video(tmp_path / "x.mp4")[0] == 3


def test_video_errors_are_clear(tmp_path):
    with pytest.raises(SinkError, match=r"unknown extension '.gif'"):
        VideoSink(tmp_path / "x.gif")
    with pytest.raises(SinkError, match="does not exist"):
        VideoSink(tmp_path / "no" / "x.mp4").open()
    with pytest.raises(SinkError, match=r"could not open a writer with codec\(s\) NOPE"):
        VideoSink(tmp_path / "x.mp4", codecs=("NOPE",)).open()
    sink = VideoSink(tmp_path / "x.mp4")
    with sink:
        sink.write(frames(1, w=160, h=120)[0])
        with pytest.raises(SinkError, match="frame 0 is 64x48, the video is 160x120"):
            sink.write(frames(1)[0])


def test_png_sequence_writes_the_composite_exactly(tmp_path):
    fs = frames(3)
    sink = PngSequenceSink(tmp_path / "png")
    stage = Composite()
    with sink:
        for f in fs:
            sink.write(stage.process(f))
    files = sorted((tmp_path / "png").glob("*.png"))
    assert [p.name for p in files] == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]
    img = cv2.imread(str(files[1]), cv2.IMREAD_COLOR)[..., ::-1]
    assert np.array_equal(img, 255 - fs[1].color)


def test_png_sequence_never_overwrites_a_frame_when_seq_repeats(tmp_path):
    # a replayed session whose seq repeats (only its timestamps must increase): 6 frames left 1 PNG
    fs = [f.replace(seq=s) for f, s in zip(frames(6), [5, 5, 5, 6, 2, 3])]
    with PngSequenceSink(tmp_path / "p") as sink:
        for f in fs:
            sink.write(f)
    names = sorted(p.name for p in (tmp_path / "p").iterdir())
    assert names == [
        "frame_000002_r3.png",
        "frame_000003_r3.png",
        "frame_000005.png",
        "frame_000005_r1.png",
        "frame_000005_r2.png",
        "frame_000006_r2.png",
    ]


def test_png_sequence_says_when_its_folder_holds_an_earlier_runs_frames(tmp_path, caplog):
    """A --png-dir reused after a longer run kept that run's extra frames among this run's, unannounced."""
    caplog.set_level(logging.WARNING)
    with PngSequenceSink(tmp_path / "p") as sink:
        for f in frames(5):
            sink.write(f)
    assert "earlier run" not in caplog.text
    with PngSequenceSink(tmp_path / "p") as sink:
        for f in frames(2):
            sink.write(f)
    assert "already holds 5 frame_*.png from an earlier run" in caplog.text
    assert len(list((tmp_path / "p").glob("frame_*.png"))) == 5  # nothing deleted


def test_png_sequence_without_composite_writes_the_camera_picture(tmp_path):
    f = frames(1)[0]
    with PngSequenceSink(tmp_path / "png") as sink:
        sink.write(f)
    assert np.array_equal(cv2.imread(str(tmp_path / "png" / "frame_000000.png"))[..., ::-1], f.color)


def test_bad_composite_is_refused():
    f = frames(1)[0].with_result("composite", np.zeros((4, 4), np.float32))
    with pytest.raises(SinkError, match=r"results\['composite'\] must be an HxWx3 uint8 RGB image"):
        output_picture(f)


def test_an_opencv_video_on_a_full_disk_is_a_sink_failure_not_silence(tmp_path, monkeypatch):
    # cv2.VideoWriter.write reports nothing: on a full disk FFmpeg printed "Failed to write frame" and the
    # run exited 0 with no sink failure, the video cut short
    import collections
    import shutil

    (tmp_path / "v.avi").symlink_to("/dev/full")  # a file that never grows
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**6, 10**6, 0))
    sink = VideoSink(tmp_path / "v.avi", fps=30)
    sink.open()
    fs = frames(4, w=160, h=120)
    sink.write(fs[0])  # one write that does not grow the file may be FFmpeg's buffer
    with pytest.raises(SinkError, match=r"v.avi: the disk is full \(0 bytes free in .*\); OpenCV's writer cannot"):
        sink.write(fs[1])
    with pytest.raises(SinkError, match=r"the disk is full .*the file's end, its index, may be missing"):
        sink.close()


def test_a_video_that_grows_is_not_taken_for_a_full_disk(tmp_path, monkeypatch):
    import collections
    import shutil

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**6, 10**6, 10**9))
    sink = VideoSink(tmp_path / "v.avi", fps=30)
    with sink:
        for f in frames(6, w=160, h=120):
            sink.write(f)
    assert _count_video(tmp_path / "v.avi")[0] == 6


def test_a_recorder_that_cannot_finalise_names_the_session_and_what_replays(tmp_path, monkeypatch):
    # a full disk at close: the run's last line was "illuminet: [Errno 28] No space left on device"
    import errno

    from illuminet.runtime.stream.session import SessionWriter

    rec = SessionRecorderSink(tmp_path / "rec", fsync=False)
    rec.open()
    rec.write(frames(1)[0])

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(SessionWriter, "close", full)
    with pytest.raises(SinkError, match=r"rec: cannot finalise the manifest: No space left on device; the 1 frames"):
        rec.close()
    empty = SessionRecorderSink(tmp_path / "empty", fsync=False)
    empty.open()  # no frame: no manifest yet, so the message must not promise a replay
    with pytest.raises(SinkError, match=r"empty: cannot finalise the manifest: .*no manifest was written"):
        empty.close()
    monkeypatch.undo()
    assert len(SessionReader(tmp_path / "rec")) == 1  # the committed frame replays


def test_recorder_records_input_frames_not_results(tmp_path):
    fs = frames(20)
    # three encoders finish out of order; the writer must still commit in frame order
    rec = SessionRecorderSink(tmp_path / "rec", source="test://x", fsync=False, encoders=3)
    run_loop(ReplaySource(_session(tmp_path, fs), timing="asap"), [Composite()], [rec])
    r = SessionReader(tmp_path / "rec", strict=True)
    assert r.finalized and len(r) == 20 and rec.frames == 20
    for a, b in zip(fs, r):
        assert same_frame(a, b)  # the camera input, not the inverted composite


def _session(tmp_path, fs):
    from illuminet.runtime.stream.session import SessionWriter

    with SessionWriter(tmp_path / "src") as w:
        for f in fs:
            w.append(f)
    return tmp_path / "src"


def test_recorder_errors_reach_the_loop(tmp_path):
    fs = frames(3)
    rec = SessionRecorderSink(tmp_path / "rec")
    rec.open()
    rec.write(fs[1])
    rec.write(fs[0])  # timestamp goes back: the writer thread fails on it
    deadline = time.monotonic() + 5
    while rec._error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(SinkError, match="does not increase"):
        rec.write(fs[2])
    rec.close()
    assert len(SessionReader(tmp_path / "rec", strict=True)) == 1
    with pytest.raises(Exception, match="already contains a session"):
        SessionRecorderSink(tmp_path / "rec").open()


def test_recorder_frames_that_fail_while_the_queue_drains_fail_the_close(tmp_path):
    """Frames that failed after the loop's last write() were only logged at close: a recording that lost
    its last queued frames (a disk full while draining) ended with exit status 0."""
    fs = frames(3)
    rec = SessionRecorderSink(tmp_path / "rec", fsync=False)
    rec.open()
    rec.write(fs[2])
    rec.write(fs[0])  # timestamp goes back: the writer thread fails on it, after the last write()
    with pytest.raises(SinkError, match=r"rec: 1 frame\(s\) queued at the end were not recorded: .*does not increase"):
        rec.close()
    assert rec.stats() == {"frames": 1, "lost": 1}
    assert len(SessionReader(tmp_path / "rec", strict=True)) == 1  # finalised all the same


def test_null_sink_counts():
    s = NullSink()
    for f in frames(3):
        s.write(f)
    assert s.stats() == {"frames": 3}


def test_build_sinks_from_config(tmp_path):
    assert build_sinks(defaults()) == []
    cfg = apply_overrides(
        defaults(),
        [
            ("output", "video", str(tmp_path / "a.mp4")),
            ("output", "png_dir", str(tmp_path / "p")),
            ("output", "record", str(tmp_path / "r")),
            ("output", "record_color", "raw"),
            ("output", "fps", 12.0),
        ],
    )
    sinks = build_sinks(cfg, source_url="replay://x")
    kinds = {type(s) for s in sinks}
    assert kinds == {VideoSink, PngSequenceSink, SessionRecorderSink}
    video = next(s for s in sinks if isinstance(s, VideoSink))
    rec = next(s for s in sinks if isinstance(s, SessionRecorderSink))
    assert video.fps == 12.0 and rec._writer_args["color"] == "raw" and rec._writer_args["source"] == "replay://x"
    # the schema refuses the range itself, before any sink is built
    with pytest.raises(ConfigError, match=r"record_jpeg_quality: expected int in 1..100, got int 0"):
        apply_overrides(cfg, [("output", "record_jpeg_quality", 0)])


def test_mjpeg_status_page_shows_the_loop_snapshot(tmp_path):
    """build_sinks wires LoopStats.snapshot into the MJPEG server; a real HTTP client reads both."""
    import json as _json
    import threading
    import urllib.request

    from illuminet.runtime.stream.loop import LoopStats

    src_path = _session(tmp_path, frames(5))
    cfg = apply_overrides(defaults(), [("output", "mjpeg", True), ("output", "port", 0)])
    stats = LoopStats()
    (sink,) = build_sinks(cfg, stats=stats.snapshot)
    stop = threading.Event()
    src = ReplaySource(src_path, timing="recorded", loop=True)
    t = threading.Thread(
        target=run_loop, args=(src, [Composite()], [sink]), kwargs={"stats": stats, "stop_event": stop}
    )
    t.start()
    try:
        deadline = time.monotonic() + 10
        while (sink._server is None or stats.frames < 5) and time.monotonic() < deadline:
            time.sleep(0.02)
        with urllib.request.urlopen(f"http://127.0.0.1:{sink.port}/stats.json", timeout=5) as r:
            page = _json.loads(r.read())
        with urllib.request.urlopen(f"http://127.0.0.1:{sink.port}/stream.mjpg", timeout=5) as r:
            head = r.read(20000)
    finally:
        stop.set()
        t.join(timeout=10)
    loop = page["loop"]
    assert loop["running"] is True and loop["frames"] >= 5 and "stage:composite" in loop["stages_ms"]
    assert loop["dropped"] >= 0 and "fps_recent" in loop
    start = head.index(b"\xff\xd8")
    jpg = cv2.imdecode(np.frombuffer(head[start : head.index(b"\xff\xd9", start) + 2], np.uint8), cv2.IMREAD_COLOR)
    assert jpg.shape == (H, W, 3)


def test_build_sinks_estimates_and_viewer_model(tmp_path):
    from illuminet.runtime.stream.mjpeg import MjpegSink
    from illuminet.runtime.stream.sinks import EstimateSink

    cfg = apply_overrides(
        defaults(),
        [("output", "estimates", str(tmp_path / "e.jsonl")), ("output", "mjpeg", True), ("output", "port", 0)],
    )
    est, mj = build_sinks(cfg)
    assert isinstance(est, EstimateSink) and est.path == str(tmp_path / "e.jsonl")
    assert isinstance(mj, MjpegSink) and mj.viewer_model == "builtin:vase"  # the [model] bundle's object
    bad = apply_overrides(cfg, [("output", "viewer_model", str(tmp_path / "nope.glb"))])
    with pytest.raises(ConfigError, match=r"\[output\] viewer_model = .*nope.glb.*no such file"):
        build_sinks(bad)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device that is always full)")
def test_png_sequence_on_a_full_disk_is_one_error_without_libpng_lines(tmp_path, capfd):
    """`--png-dir` on a full disk: libpng printed "libpng error: Write Error" three times straight to
    descriptor 2 above the one line. Now the error says why (ENOSPC) and nothing else is printed."""
    (tmp_path / "p").mkdir()
    os.symlink("/dev/full", tmp_path / "p" / "frame_000000.png")  # writes to it fail: no space left
    with PngSequenceSink(tmp_path / "p") as sink:
        with pytest.raises(SinkError, match=r"cannot write .*frame_000000.png: No space left on device"):
            sink.write(frames(1)[0])
    out, err = capfd.readouterr()
    assert "libpng" not in err and "libpng" not in out, err
