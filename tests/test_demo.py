"""``illuminet demo``: the whole pipeline on the built-in scene writes a video, a still and its figures."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from illuminet.cli import main

pytestmark = pytest.mark.gl


@pytest.fixture(autouse=True)
def _gl(gl):  # the demo renders: needs the EGL context (skips where there is none)
    yield


def test_demo_writes_video_still_and_reports(tmp_path, capsys):
    out = tmp_path / "demo.mp4"
    src = "synthetic://indoor?seed=0&frames=4&size=640x400&path=orbit"
    rc = main(["demo", "--frames", "4", "--out", str(out), "--source", src, "--strict"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert out.is_file() and out.stat().st_size > 1000
    still = tmp_path / "demo_still.png"
    assert still.is_file()
    # the video holds the frames, at the source's size
    cap = cv2.VideoCapture(str(out))  # reading back the demo's own file, not a camera (tests may; hw/ owns cameras)
    n = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        assert img.shape == (400, 640, 3)
        n += 1
    cap.release()
    assert n == 4
    av = pytest.importorskip("av", reason="PyAV writes the demo's H.264 MP4")
    with av.open(str(out)) as c:  # H.264 in yuv420p: what browsers play (tests/test_browser.py plays one)
        cc = c.streams.video[0].codec_context
        assert (cc.name, cc.pix_fmt) == ("h264", "yuv420p")
    # what it reports: per-stage timing, the shading that drove the object, peak memory
    for stage in ("stage:planes", "stage:plane_light", "stage:shading", "stage:render"):
        assert stage in text
    assert "shading: " in text and any(w in text for w in ("radiance transfer", "learned model", "baseline"))
    assert "peak resident memory:" in text
    assert "failed frames 0" in text


def test_demo_composites_the_object_into_the_picture(tmp_path, capsys):
    pngs = tmp_path / "png"
    src = "synthetic://indoor?seed=0&frames=2&size=640x400"
    rc = main(
        [
            "demo",
            "--frames",
            "2",
            "--no-video",
            "--png-dir",
            str(pngs),
            "--source",
            src,
            "--still",
            str(tmp_path / "s.png"),
            "--strict",
        ]
    )
    assert rc == 0, capsys.readouterr().out
    files = sorted(pngs.glob("*.png"))
    assert len(files) == 2
    # the same source without the renderer: the pictures must differ where the object stands
    from illuminet.hw import open_source

    with open_source(src) as s:
        raw = s.read().color
    out = cv2.imread(str(files[0]))[:, :, ::-1]
    diff = np.abs(out.astype(int) - raw.astype(int)).max(axis=-1)
    changed = diff > 8
    assert 200 < changed.sum() < 0.3 * changed.size, changed.sum()


def test_a_source_shorter_than_frames_still_gives_a_still(tmp_path, capsys):
    """The still is the middle of --frames (frame 45 of 90); a 3-frame source never got there, and the
    demo wrote no still and said nothing. Its last frame is the still now, and the report says so."""
    still = tmp_path / "s.png"
    src = "synthetic://indoor?seed=0&frames=3&size=320x200"
    rc = main(["demo", "--no-video", "--source", src, "--still", str(still), "--strict"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert cv2.imread(str(still)).shape == (200, 320, 3)
    assert f"still: {still} (the last frame, 2: the source ended first)" in text


def test_a_demo_stopped_by_ctrl_c_says_so_at_its_still(tmp_path, capsys, monkeypatch):
    """Ctrl-C before the middle frame: the last frame is the still, and the report said 'the source
    ended first', which it did not (the user stopped the run)."""
    import signal

    from illuminet.commands.demo import StillSink

    write = StillSink.write

    def write_then_ctrl_c(self, frame):
        write(self, frame)
        if self.frames == 2:
            signal.raise_signal(signal.SIGINT)  # the loop's handler: stop after this frame

    monkeypatch.setattr(StillSink, "write", write_then_ctrl_c)
    still = tmp_path / "s.png"
    src = "synthetic://indoor?seed=0&frames=20&size=320x200"
    rc = main(["demo", "--no-video", "--source", src, "--frames", "20", "--still", str(still)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "ended: stopped" in text, text
    assert f"still: {still} (the last frame, 1: the run was stopped first)" in text, text


@pytest.mark.parametrize("name", ["st.xyz", "folder"])
def test_a_still_that_cannot_be_written_is_refused_before_the_run(tmp_path, capsys, name):
    (tmp_path / "folder").mkdir()
    src = "synthetic://indoor?frames=2&size=64x48"
    rc = main(["demo", "--source", src, "--no-video", "--still", str(tmp_path / name)])
    err = capsys.readouterr().err
    assert rc == 2 and f"--still {tmp_path / name}: expected an image file path" in err, err


@pytest.mark.parametrize("flag", ["--still", "--out", "--png-dir"])
def test_an_output_under_a_file_is_refused_before_the_run(tmp_path, capsys, flag):
    """The still's (and the video's) folder is made when missing; under a file it cannot be: the
    still failed only after the run, the video with a bare '[Errno 17] File exists', and the PNG
    folder said the file 'is not a writable folder'."""
    notes = tmp_path / "notes.txt"
    notes.write_text("x")
    target = notes / {"--still": "s.png", "--out": "v.mp4", "--png-dir": "frames"}[flag]
    src = "synthetic://indoor?frames=2&size=64x48"
    rc = main(["demo", "--source", src, flag, str(target)] + (["--no-video"] if flag != "--out" else []))
    cap = capsys.readouterr()
    assert rc == 2, cap.out + cap.err
    assert f"{notes} is a file, not a folder; choose another path" in cap.err, cap.err
    if flag != "--png-dir":
        assert f"{flag} {target}: cannot create its folder: " in cap.err, cap.err
    assert "demo: source" not in cap.out + cap.err  # refused before anything ran


def test_demo_frames_and_live_config():
    from illuminet.cli import build_parser
    from illuminet.commands.demo import demo_config, demo_frames
    from illuminet.runtime.config import defaults

    args = build_parser().parse_args(["demo"])
    assert demo_frames(args) == 90 and demo_config(args, defaults()).source.timing == "asap"
    args = build_parser().parse_args(
        ["demo", "--mjpeg", "--port", "0", "--estimates", "e.jsonl", "--viewer-model", "builtin:bowl"]
    )
    cfg = demo_config(args, defaults())
    # serving: real time, until Ctrl-C
    assert demo_frames(args) == 0 and cfg.source.timing == "recorded" and cfg.source.max_frames == 0
    assert cfg.output.mjpeg and cfg.output.port == 0 and cfg.output.estimates == "e.jsonl"
    assert cfg.output.viewer_model == "builtin:bowl"
    assert demo_frames(build_parser().parse_args(["demo", "--mjpeg", "--frames", "5"])) == 5


def test_demo_rejects_bad_arguments(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "x.mp4"), "--no-video"]) == 2  # --out was ignored silently
    assert "--no-video writes none; drop one of them" in capsys.readouterr().err
    assert main(["demo", "--frames", "0"]) == 2
    assert "--frames must be at least 1" in capsys.readouterr().err
    rc = main(["demo", "--frames", "1", "--source", "nope://x", "--no-video", "--still", ""])
    assert rc == 2  # a malformed or unknown source URL is a usage mistake, as for `run` (was 1 here)
    assert "nope" in capsys.readouterr().err
    # an empty value read as none: the demo ran (and wrote out/demo.mp4) or replayed the built-in session
    for flag in ("--out", "--source", "--make-default-session"):
        assert main(["demo", "--frames", "1", flag, " ", "--still", ""]) == 2
        assert f"illuminet demo: {flag} ' ' is empty; expected " in capsys.readouterr().err


def test_demo_missing_session_is_one_line(tmp_path, capsys):
    """A replay of a folder that is not a session fails with one line naming it, not a report of 0 frames."""
    missing = tmp_path / "no_such_session"
    rc = main(["demo", "--source", f"replay://{missing}", "--no-video", "--still", ""])
    assert rc == 1
    cap = capsys.readouterr()
    assert f"{missing}: not a session folder" in cap.err
    assert "0 frames" not in cap.out and "step " not in cap.out
