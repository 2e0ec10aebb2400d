"""V4L2 stereo source without a camera: URL rules, side-by-side splitting, and the whole source driven
by a capture backend that plays recorded numpy frames (the same interface OpenCV's V4L2 capture has),
with real host stereo depth from a calibration file."""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest

from illuminet.hw import v4l2
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.stage import EndOfStream

W, H = 320, 200
F, B, Z = 300.0, 0.06, 1.0  # focal px, baseline m, plane depth m -> disparity 18 px
DISP = int(round(F * B / Z))


class RecordedCapture:
    """A CaptureBackend playing numpy frames: ``None`` entries are failed grabs (a stalled device)."""

    def __init__(self, name, frames, timestamps=None, opens_fail=0):
        self.name = name
        self.frames = list(frames)
        self.timestamps = list(timestamps) if timestamps is not None else [None] * len(self.frames)
        self.i = -1
        self.opened = 0
        self.closed = 0
        self.opens_fail = opens_fail

    def open(self):
        if self.opens_fail > 0:
            self.opens_fail -= 1
            raise v4l2.V4l2Error(f"{self.name} not there yet")
        self.opened += 1

    def grab(self):
        self.i += 1
        return self.i < len(self.frames) and self.frames[self.i] is not None

    def retrieve(self):
        return self.frames[self.i], self.timestamps[self.i]

    def close(self):
        self.closed += 1


def _texture(seed=0):
    rng = np.random.default_rng(seed)
    t = rng.integers(0, 256, (H, W + DISP, 3), dtype=np.uint8)
    return cv2.GaussianBlur(t, (3, 3), 0)


def _pair(seed=0):
    """Rectified pair of a textured fronto-parallel plane at Z: right(x) = left(x + d)."""
    t = _texture(seed)
    left = np.ascontiguousarray(t[:, :W])
    right = np.ascontiguousarray(t[:, DISP : DISP + W])
    return left, right


@pytest.fixture(scope="module")
def calib_file(tmp_path_factory):
    K = [[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]]
    d = {
        "format": "illuminet-calibration",
        "version": 1,
        "cameras": {
            "left": {"width": W, "height": H, "model": "pinhole", "K": K, "dist": [0, 0, 0, 0, 0]},
            "right": {"width": W, "height": H, "model": "pinhole", "K": K, "dist": [0, 0, 0, 0, 0]},
        },
        "stereo": {"left": "left", "right": "right", "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [-B, 0, 0]},
    }
    p = tmp_path_factory.mktemp("calib") / "rig.json"
    p.write_text(json.dumps(d))
    return str(p)


def test_parse_url():
    o = v4l2.parse_url("v4l2:///dev/video0?stereo=sbs&size=2560x720&fps=30&fourcc=mjpg&swap=1&calib=a.json")
    assert (o.device, o.stereo, o.size, o.fps, o.fourcc, o.swap, o.calib) == (
        "/dev/video0",
        "sbs",
        (2560, 720),
        30.0,
        "MJPG",
        True,
        "a.json",
    )
    o = v4l2.parse_url("v4l2:///dev/video0?right=/dev/video2")
    assert o.stereo == "pair" and o.right == "/dev/video2"
    assert v4l2.parse_url("v4l2:///dev/video4").stereo == ""


@pytest.mark.parametrize(
    "url, msg",
    [
        ("v4l2://", "no device"),
        ("v4l2:///dev/video0?stereo=3d", "stereo='3d'"),
        ("v4l2:///dev/video0?stereo=pair", "needs right="),
        ("v4l2:///dev/video0?stereo=sbs&right=/dev/video2", "contradicts"),
        ("v4l2:///dev/video0?size=big", "WIDTHxHEIGHT"),
        ("v4l2:///dev/video0?gain=3", "unknown parameter 'gain'"),
        ("v4l2:///dev/video0?fourcc=MJPEG", "four characters"),
    ],
)
def test_parse_url_refuses(url, msg):
    with pytest.raises(ValueError, match=msg):
        v4l2.parse_url(url)


def test_mono_camera_is_refused_with_the_reason():
    expect = r"names a single \(mono\) camera \(no \?stereo= or \?right=\): depth is required"
    with pytest.raises(v4l2.V4l2Error, match=expect):
        v4l2.open_url("v4l2:///dev/video0", defaults())


def test_stereo_without_calibration_is_refused(tmp_path):
    with pytest.raises(v4l2.V4l2Error, match="needs the stereo pair's calibration file"):
        v4l2.open_url("v4l2:///dev/video0?stereo=sbs", defaults())
    with pytest.raises(v4l2.V4l2Error, match="not found"):
        v4l2.open_url(f"v4l2:///dev/video0?stereo=sbs&calib={tmp_path}/none.json", defaults())
    # a folder (or a device) was also "not found": the user looked for a file that is there
    with pytest.raises(v4l2.V4l2Error, match=r"calibration file .* is not a file \(a folder or a device\?\)"):
        v4l2.open_url(f"v4l2:///dev/video0?stereo=sbs&calib={tmp_path}", defaults())


def test_open_url_takes_calibration_from_config(tmp_path):
    p = tmp_path / "c.json"
    p.write_text("{}")
    cfg = apply_overrides(defaults(), [("source", "calibration", str(p)), ("source", "reconnect", False)])
    src = v4l2.open_url("v4l2:///dev/video7?right=/dev/video9&size=640x400", cfg)
    assert src.calib_path == str(p) and src.reconnect is False and src.live
    assert src.grabber.left.name == "/dev/video7" and src.grabber.right.name == "/dev/video9"


def test_split_sbs():
    img = np.zeros((4, 6, 3), np.uint8)
    img[:, 3:] = 9
    left, right = v4l2.split_sbs(img)
    assert left.shape == right.shape == (4, 3, 3) and left.max() == 0 and right.min() == 9
    left, right = v4l2.split_sbs(img, swap=True)
    assert left.min() == 9
    with pytest.raises(ValueError, match="odd"):
        v4l2.split_sbs(np.zeros((4, 5), np.uint8))


def test_sbs_source_gives_rgbd_with_host_stereo_depth(calib_file):
    frames, ts = [], []
    for i in range(4):
        left, right = _pair(i)
        frames.append(np.hstack([left, right]))
        ts.append(1_000_000_000 + i * 33_333_333)
    ts[3] += 2 * 33_333_333  # two frames the driver delivered and nobody grabbed
    cap = RecordedCapture("/dev/video0", frames, ts)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), calib_file, reconnect=False)
    with src:
        out = [src.read() for _ in range(4)]
        with pytest.raises(EndOfStream, match="lost"):  # the recording ends = the device stops delivering
            src.read()
    f = out[0]
    assert f.color.shape == (H, W, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (H, W) and f.depth.dtype == np.float32
    core = f.depth[40:160, 100:300]
    valid = core[core > 0]
    assert valid.size > 0.8 * core.size
    assert np.median(valid) == pytest.approx(Z, rel=0.05)
    assert f.intrinsics.width == W and f.intrinsics.dist == ()
    # colour is RGB (OpenCV delivers BGR): the rectified left image's channels are reversed
    lb = frames[0][:, :W]
    assert np.abs(f.color[100, 150].astype(int) - lb[100, 150, ::-1].astype(int)).max() <= 40
    assert [x.t_device_ns for x in out] == ts
    assert [x.seq for x in out] == [0, 1, 2, 3]
    assert src.stats()["dropped"] == 2


def test_two_device_pair_and_bad_frames_are_skipped(calib_file):
    pairs = [_pair(i) for i in range(3)]
    lefts = [p[0] for p in pairs]
    rights = [p[1] for p in pairs]
    rights[1] = rights[1][:100]  # a corrupt frame: wrong size
    lc, rc = RecordedCapture("/dev/video0", lefts), RecordedCapture("/dev/video2", rights)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(lc, rc), calib_file, reconnect=False)
    with src:
        a = src.read()
        b = src.read()  # frame 1 is skipped, frame 2 comes
    assert src.stats()["bad_frames"] == 1
    assert a.seq == 0 and b.seq == 1
    assert np.median(b.depth[b.depth > 0]) == pytest.approx(Z, rel=0.05)
    assert lc.closed == rc.closed == 1


def test_a_calibration_that_does_not_fit_the_camera_is_an_error_not_endless_bad_frames(calib_file, tmp_path):
    """A calibration of another aspect ratio (or without a stereo pair) fails on every frame alike: the
    first frame ends the stream with one error naming the file and the size; before, every frame was
    skipped as 'bad' with a warning, forever on a live camera."""
    frames = [np.zeros((240, 2 * W, 3), np.uint8)] * 50  # 320x240 per eye: 4:3, calibrated 320x200 (16:10)
    cap = RecordedCapture("/dev/video0", frames)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), calib_file, reconnect=False)
    with src, pytest.raises(v4l2.V4l2Error, match=r"rig.json cannot be used for its 320x240 images: .*aspect"):
        src.read()
    assert cap.i == 0 and src.stats()["bad_frames"] == 0
    mono = tmp_path / "mono.json"
    d = json.loads(open(calib_file).read())
    del d["stereo"]
    mono.write_text(json.dumps(d))
    left, right = _pair(0)
    cap = RecordedCapture("/dev/video0", [np.hstack([left, right])] * 5)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), str(mono), reconnect=False)
    with src, pytest.raises(v4l2.V4l2Error, match="has no 'stereo' section"):
        src.read()


def test_one_odd_sized_frame_after_good_ones_is_skipped(calib_file):
    left, right = _pair(0)
    good = np.hstack([left, right])
    frames = [good, np.zeros((240, 2 * W, 3), np.uint8), good]
    src = v4l2.V4l2Source(v4l2.StereoGrabber(RecordedCapture("/dev/video0", frames)), calib_file, reconnect=False)
    with src:
        assert src.read().seq == 0
        assert src.read().seq == 1  # the 320x240 frame in between is skipped
    assert src.stats()["bad_frames"] == 1


def test_frames_that_are_all_bad_end_the_stream_with_the_reason(calib_file):
    """Two cameras of different sizes fail every frame alike: after max_bad_frames in a row, one error
    with the reason, instead of a warning per frame forever."""
    lefts = [_pair(0)[0]] * 40
    rights = [np.zeros((H // 2, W, 3), np.uint8)] * 40
    grabber = v4l2.StereoGrabber(RecordedCapture("/dev/video0", lefts), RecordedCapture("/dev/video2", rights))
    src = v4l2.V4l2Source(grabber, calib_file, reconnect=False)  # max_bad_frames=30
    with src, pytest.raises(v4l2.V4l2Error, match="30 frames in a row could not be used: .*set the same size="):
        src.read()
    assert src.stats()["bad_frames"] == 30


def test_lost_device_reconnects_with_backoff(calib_file):
    left, right = _pair(0)
    sbs = np.hstack([left, right])

    class Flaky(RecordedCapture):
        """Delivers 1 frame, then nothing (unplugged); reopening fails twice, then it works again."""

        def open(self):
            super().open()
            if self.opened == 2:  # second session: after the reconnect
                self.frames, self.i = [sbs, sbs], -1

    cap = Flaky("/dev/video0", [sbs] + [None] * 3)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), calib_file, reconnect=True, max_failures=3)
    src.BACKOFF_START_S = 0.01

    orig_open, failed = cap.open, []

    def failing_open():
        if cap.opened == 1 and len(failed) < 2:  # the first two reopen attempts fail
            failed.append(1)
            raise v4l2.V4l2Error("no such device")
        orig_open()

    cap.open = failing_open
    with src:
        assert src.read() is not None
        assert src.read() is not None  # after losing the device and reopening it
    assert src.reconnects == 3 and cap.opened == 2


def test_close_interrupts_a_reconnect(calib_file):
    cap = RecordedCapture("/dev/video0", [], opens_fail=0)
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), calib_file, reconnect=True, max_failures=1)
    src.open()
    cap.opens_fail = 10**6  # never comes back
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("f", src.read()))
    t.start()
    time.sleep(0.8)
    src.close()
    t.join(5)
    assert not t.is_alive() and out["f"] is None and src.reconnects >= 1


def test_list_devices_reads_dev_and_sysfs():
    for d in v4l2.list_devices():
        assert d["device"].startswith("/dev/video") and set(d) == {"device", "name", "index"}


def test_missing_device_is_named():
    with pytest.raises(v4l2.V4l2Error, match="/dev/video-none does not exist"):
        v4l2.OpenCvCapture("/dev/video-none").open()


@pytest.mark.hardware
def test_real_sbs_camera(tmp_path):
    devs = v4l2.list_devices()
    if not devs:
        pytest.skip("no V4L2 device")
    cap = v4l2.OpenCvCapture(devs[0]["device"])
    cap.open()
    try:
        assert cap.grab()
        img, _ = cap.retrieve()
        assert img is not None and img.ndim == 3
    finally:
        cap.close()


def test_close_during_a_stalled_grab_never_releases_the_device_under_it(calib_file):
    """OpenCV's V4L2 grab can block for 10 s on a stalled camera; releasing the capture meanwhile frees
    the buffers it uses (a crash at exit). close() waits a moment, then leaves the release to the
    reading thread, which does it as soon as its grab returns."""
    left, right = _pair(0)
    sbs = np.hstack([left, right])
    in_grab, go = threading.Event(), threading.Event()
    events = []

    class Stalls(RecordedCapture):
        def grab(self):
            if self.i >= 0:  # the second grab stalls until released by the test
                in_grab.set()
                go.wait(10)
                events.append("grab returned")
            return super().grab()

        def close(self):
            events.append("close")
            super().close()

    cap = Stalls("/dev/video0", [sbs, sbs])
    src = v4l2.V4l2Source(v4l2.StereoGrabber(cap), calib_file, reconnect=False)
    src.CLOSE_WAIT_S = 0.2
    src.open()
    assert src.read() is not None
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("f", src.read()))
    t.start()
    assert in_grab.wait(5)
    t0 = time.monotonic()
    src.close()
    assert time.monotonic() - t0 < 2 and events == []  # close() returned without touching the device
    go.set()
    t.join(5)
    assert not t.is_alive() and out["f"] is None
    assert events == ["grab returned", "close"] and cap.closed == 1
