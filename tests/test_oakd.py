"""OAK-D source: everything that runs without a device, through DepthAI's own host-side classes.

* URL options; calibration parsing of the real OAK-D Pro AF calibration file (checked against the
  scale-and-centre-crop computed here from the JSON itself);
* a host-only DepthAI pipeline: the same Sync node and non-blocking queue the live source uses, fed
  with ``dai.ImgFrame`` messages built on the host, converted to ``Frame``;
* IMU packets built on the host -> gravity in colour-camera axes.
Tests that need a device are marked ``hardware``.
"""

from __future__ import annotations

import copy
import datetime
import json
import logging
import os
import time

import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from illuminet.hw import oakd  # noqa: E402
from illuminet.runtime.config import defaults  # noqa: E402
from illuminet.runtime.frame import Intrinsics  # noqa: E402
from illuminet.runtime.stage import EndOfStream  # noqa: E402

CALIB = "calibration/oakd_pro_af_calib_18443010F116631200.json"


def test_telemetry_is_off():
    assert os.environ["DEPTHAI_TELEMETRY"] == "0"


def test_crash_dump_upload_is_off_unless_the_user_asked(tmp_path):
    """libdepthaicore uploads a firmware crash dump to Luxonis unless DEPTHAI_CRASHDUMP=0: importing the
    OAK-D source (and the CLI) sets it, in a fresh interpreter; a value the user set is kept."""
    import subprocess
    import sys

    code = (
        "import os, illuminet.hw.oakd, illuminet.cli; "
        "print(os.environ['DEPTHAI_CRASHDUMP'], os.environ['DEPTHAI_DISABLE_CRASHDUMP_COLLECTION'])"
    )
    env = {k: v for k, v in os.environ.items() if "CRASHDUMP" not in k}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.stdout.splitlines()[-1].split() == ["0", "1"], out.stderr
    env["DEPTHAI_CRASHDUMP"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.stdout.splitlines()[-1].split() == [str(tmp_path), "1"], out.stderr


def test_parse_url_defaults_and_options():
    o = oakd.parse_url("oakd://")
    assert o.device == "" and o.size == (640, 400) and o.queue == 2 and o.fps == 30
    assert o.sync_threshold == datetime.timedelta(milliseconds=500 / 30)
    o = oakd.parse_url(
        "oakd://18443010F116631200?fps=15&size=1280x800&queue=1&imu=0&preset=high_detail"
        "&mono=1280x800&exposure_us=8000&iso=400&reconnect=0"
    )
    assert o.device == "18443010F116631200" and o.fps == 15 and o.size == (1280, 800)
    assert o.queue == 1 and o.imu is False and o.preset == "high_detail" and o.mono_size == (1280, 800)
    assert (o.exposure_us, o.iso, o.reconnect) == (8000, 400, False)
    assert oakd.parse_url("oakd://192.168.1.44").device == "192.168.1.44"


@pytest.mark.parametrize(
    "url, msg",
    [
        ("oakd://?queue=9", "queue=9: expected 1..4"),
        ("oakd://?size=640", "expected WIDTHxHEIGHT"),
        ("oakd://?fps=fast", "expected a number"),
        ("oakd://?color=1", "unknown parameter 'color'"),
        ("oakd://?preset=magic", "preset='magic'"),
        ("oakd://?exposure_us=1000", "needs both exposure_us and iso"),
        ("oakd://?imu=maybe", "expected 0/1"),
        # accepted before, then a 13 s device search (and values the camera would reject)
        ("oakd://?sync_ms=-1", "sync_ms=-1: expected >= 0"),
        ("oakd://?exposure_us=-5&iso=-5", "expected an integer in 0..33000"),
        ("oakd://?exposure_us=100&iso=50", "iso=50: expected 100..1600"),
        ("oakd://?imu_rate=99999999", "expected an integer in 1..1000"),
    ],
)
def test_parse_url_refuses_bad_values(url, msg):
    with pytest.raises(ValueError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        oakd.parse_url(url)


@pytest.mark.shared_data
def test_intrinsics_from_real_calibration_match_scale_and_crop(shared_data):
    path = shared_data / CALIB
    calib = oakd.load_calibration_file(str(path))
    raw = json.loads(path.read_text())
    cam_a = dict(raw["cameraData"])[0]  # socket 0 = CAM_A, the colour camera
    K, W, H = np.asarray(cam_a["intrinsicMatrix"]), cam_a["width"], cam_a["height"]
    for w, h in [(640, 400), (640, 360), (1280, 800), (W, H)]:
        intr = oakd.intrinsics_from_calibration(calib, w, h)
        # Camera.requestOutput's CROP mode: scale to cover the output, then crop the centre
        s = max(w / W, h / H)
        assert intr.fx == pytest.approx(K[0, 0] * s, rel=1e-5)
        assert intr.fy == pytest.approx(K[1, 1] * s, rel=1e-5)
        assert intr.cx == pytest.approx(K[0, 2] * s - (W * s - w) / 2, abs=0.02)
        assert intr.cy == pytest.approx(K[1, 2] * s - (H * s - h) / 2, abs=0.02)
        assert (intr.width, intr.height) == (w, h)
        assert intr.dist == pytest.approx(tuple(cam_a["distortionCoeff"][:8]), rel=1e-6)
        # DepthAI's own ImgTransformation of the calibrated mode cropped and scaled the same way agrees
        crop_w, crop_h = round(w / s), round(h / s)
        tr = _transformation(K, (W, H), ((W - crop_w) // 2, (H - crop_h) // 2, crop_w, crop_h), (w, h))
        assert oakd.intrinsics_disagreement(oakd.intrinsics_from_transformation(tr, w, h), intr) < 0.002
    assert oakd.intrinsics_from_calibration(calib, 640, 400, undistorted=True).dist == ()
    # the two mono cameras are there as well (1280x800 sensors, fx ~ 800)
    left = oakd.intrinsics_from_calibration(calib, 1280, 800, socket=oakd.LEFT_SOCKET)
    assert 700 < left.fx < 900


@pytest.mark.shared_data
def test_imu_rotation_from_calibration(shared_data, tmp_path):
    path = shared_data / CALIB
    # this factory calibration has no IMU extrinsics: no rotation rather than a guess
    assert oakd.imu_rotation_from_calibration(oakd.load_calibration_file(str(path))) is None
    raw = json.loads(path.read_text())
    R = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    with_imu = copy.deepcopy(raw)
    with_imu["imuExtrinsics"].update(rotationMatrix=R, toCameraSocket=0)
    p = tmp_path / "with_imu.json"
    p.write_text(json.dumps(with_imu))
    got = oakd.imu_rotation_from_calibration(oakd.load_calibration_file(str(p)))
    np.testing.assert_allclose(got, R, atol=1e-6)


def test_calibration_file_errors(tmp_path):
    with pytest.raises(oakd.OakdError, match="not found"):
        oakd.load_calibration_file(str(tmp_path / "nope.json"))


def _img(i: int, w=64, h=40, exposure_us=8000, iso=400, ct=5600):
    """A colour ImgFrame built on the host, as the device would send it (BGR interleaved)."""
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 200  # red
    rgb[..., 1] = i
    rgb[..., 2] = 10
    f = dai.ImgFrame()
    f.setCvFrame(np.ascontiguousarray(rgb[..., ::-1]), dai.ImgFrame.Type.BGR888i)
    ts = datetime.timedelta(seconds=10, microseconds=i * 33_333)
    f.setTimestamp(ts)
    f.setTimestampDevice(ts)
    f.setSequenceNum(i)
    cam = f.cam
    cam.exposureTimeUs, cam.sensitivityIso, cam.wbColorTemp = exposure_us, iso, ct
    f.cam = cam
    return f


def _depth(i: int, w=64, h=40, mm=1500):
    d = dai.ImgFrame()
    a = np.full((h, w), mm, np.uint16)
    a[0, 0] = 0  # an invalid pixel
    d.setFrame(a)
    d.setType(dai.ImgFrame.Type.RAW16)
    d.setWidth(w)
    d.setHeight(h)
    ts = datetime.timedelta(seconds=10, microseconds=i * 33_333)
    d.setTimestamp(ts)
    d.setTimestampDevice(ts)
    d.setSequenceNum(i)
    return d


def test_host_only_pipeline_sync_queue_keeps_newest_and_converts():
    """The live source's host side (Sync node + non-blocking queue + converter) in a host-only pipeline."""
    opts = oakd.parse_url("oakd://?fps=30&queue=2&size=64x40")
    intr = Intrinsics(50.0, 50.0, 32.0, 20.0, 64, 40)
    pipeline = dai.Pipeline(False)  # no device
    sync, queue = oakd.build_sync(pipeline, opts)
    qc = sync.inputs["color"].createInputQueue()
    qd = sync.inputs["depth"].createInputQueue()
    conv = oakd.FrameConverter(intr)
    pipeline.start()
    try:
        # first one frame, read at once
        qc.send(_img(0))
        qd.send(_depth(0))
        g = queue.get(datetime.timedelta(seconds=5))
        assert g is not None
        f0 = conv.convert(g)
        # then 6 frames while "the loop is busy": the queue (2) keeps only the newest
        for i in range(1, 7):
            qc.send(_img(i))
            qd.send(_depth(i))
        time.sleep(0.5)
        groups = queue.tryGetAll()
    finally:
        pipeline.stop()
    assert 1 <= len(groups) <= 2
    f = conv.convert(groups[-1])
    assert f0.color.shape == (40, 64, 3) and f0.color.dtype == np.uint8
    assert tuple(f0.color[5, 5]) == (200, 0, 10)  # RGB order, not BGR
    assert f.color[5, 5, 1] == 6  # the newest frame
    assert f.depth.dtype == np.float32 and f.depth[5, 5] == pytest.approx(1.5) and f.depth[0, 0] == 0
    assert f.t_device_ns == (10 * 1_000_000 + 6 * 33_333) * 1000
    assert f.t_host_ns == f.t_device_ns  # host-built frames carry the same host timestamp
    assert f.exposure.exposure_us == pytest.approx(8000) and f.exposure.iso == 400
    assert f.exposure.color_temperature_k == 5600 and f.exposure.known
    assert f.intrinsics == intr
    assert conv.dropped == 5  # device sequence jumped from 0 to 6


def test_converter_scales_depth_and_intrinsics_and_reports_unknown_exposure():
    intr = Intrinsics(100.0, 100.0, 63.5, 39.5, 128, 80)
    g = dai.MessageGroup()
    g["color"] = _img(3, exposure_us=0, iso=0, ct=0)
    g["depth"] = _depth(3, w=32, h=20, mm=800)
    f = oakd.FrameConverter(intr).convert(g)
    assert f.depth.shape == (40, 64) and f.depth[20, 30] == pytest.approx(0.8)
    assert f.intrinsics.width == 64 and f.intrinsics.fx == pytest.approx(50.0)
    assert f.exposure.exposure_us is None and f.exposure.iso is None and not f.exposure.known
    bad = dai.MessageGroup()
    bad["color"] = _img(4)
    with pytest.raises(ValueError, match="lacks"):
        oakd.FrameConverter(intr).convert(bad)


def _imu(t_s: float, acc):
    d = dai.IMUData()
    p = dai.IMUPacket()
    a = p.acceleroMeter
    a.x, a.y, a.z = acc
    ts = a.tsDevice
    ts.sec, ts.nsec = int(t_s), int(round((t_s % 1) * 1e9))
    a.tsDevice = ts
    p.acceleroMeter = a
    d.packets = [p]
    return d


def test_device_imu_gives_gravity_in_colour_camera_axes():
    from illuminet.hw.serial_imu import ImuMatcher

    # an IMU whose x axis points along the camera's y (down): R maps IMU x -> camera y
    R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    conv = oakd.FrameConverter(Intrinsics(50, 50, 32, 20, 64, 40), imu=ImuMatcher(max_skew_ms=20, rotation=R))
    for k in range(20):  # held still: the accelerometer reads +9.81 along IMU -x (up in the camera)
        conv.add_imu(_imu(10 + k * 0.01, (-9.81, 0.0, 0.0)))
    g = dai.MessageGroup()
    g["color"] = _img(3)
    g["depth"] = _depth(3)
    f = conv.convert(g)
    assert f.imu and f.gravity is not None
    np.testing.assert_allclose(f.gravity, [0, 1, 0], atol=1e-5)  # down = camera +y
    assert f.imu[0].accel == pytest.approx((0.0, -9.81, 0.0), abs=1e-5)


def test_td_to_ns():
    assert oakd.td_to_ns(datetime.timedelta(days=1, seconds=2, microseconds=3)) == (86402 * 10**6 + 3) * 1000


def test_open_url_uses_config_and_list_devices_runs():
    src = oakd.open_url("oakd://?reconnect=0", defaults())
    assert src.live and src.reconnect is False and src.name == "oakd"
    assert oakd.open_url("oakd://", defaults()).reconnect is True
    assert isinstance(oakd.list_devices(), list)


def test_no_device_gives_a_clear_error(monkeypatch):
    if oakd.list_devices():
        pytest.skip("an OAK device is connected")
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "500")  # ms; DepthAI's default search takes ~10 s
    src = oakd.open_url("oakd://NOSUCHDEVICE0000?reconnect=0", defaults())
    with pytest.raises(oakd.OakdError, match="cannot open OAK device NOSUCHDEVICE0000.*udev"):
        src.open()
    src.close()


def test_lost_device_reconnects_with_backoff_until_closed(monkeypatch):
    """With reconnect on, a device that cannot be opened is retried with growing delays; close() ends it."""
    import threading

    if oakd.list_devices():
        pytest.skip("an OAK device is connected")
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "200")
    src = oakd.open_url("oakd://NOSUCHDEVICE0000", defaults())
    src.BACKOFF_START_S = 0.1
    delays = []
    orig_wait = src._stop.wait

    def wait(t):
        delays.append(t)
        return orig_wait(t)

    src._stop.wait = wait
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("frame", src.read()))
    t.start()
    deadline = time.time() + 20
    while src.reconnects < 3 and time.time() < deadline:
        time.sleep(0.05)
    src.close()
    t.join(10)
    assert not t.is_alive() and out["frame"] is None
    assert src.reconnects >= 3 and delays[:3] == [0.1, 0.2, 0.4]


@pytest.mark.hardware
def test_live_device_frames():
    if not oakd.list_devices():
        pytest.skip("no OAK device connected")
    with oakd.open_url("oakd://?fps=15", defaults()) as src:
        frames = [src.read() for _ in range(10)]
        st = src.stats()
        source = src._last_converter.intrinsics_source
    f = frames[-1]
    # v3 frames carry their own camera matrix, and depth aligned to colour carries the same one
    assert source == "frame" and st["misaligned_depth"] == 0
    assert f.color.shape == (400, 640, 3) and f.depth.shape == (400, 640)
    assert (f.depth > 0).mean() > 0.3
    assert all(b.t_device_ns > a.t_device_ns for a, b in zip(frames, frames[1:]))
    assert f.exposure.known


class _HostRig:
    """Connects OakdSource to a host-only DepthAI pipeline (Sync node + queue) that the test feeds."""

    def __init__(self):
        self.sessions = []
        self.inputs = None

    def connect(self, opts):
        pipeline = dai.Pipeline(False)
        sync, queue = oakd.build_sync(pipeline, opts)
        self.inputs = (sync.inputs["color"].createInputQueue(), sync.inputs["depth"].createInputQueue())
        pipeline.start()
        s = oakd.OakdSession(
            pipeline=pipeline,
            queues={"sync_queue": queue, "imu_queue": None},
            converter=oakd.FrameConverter(Intrinsics(50, 50, 32, 20, 64, 40)),
            device_id=f"host-rig-{len(self.sessions)}",
        )
        self.sessions.append(s)
        return s

    def send(self, i, depth_tr=None):
        qc, qd = self.inputs
        qc.send(_img(i))
        d = _depth(i)
        if depth_tr is not None:
            d.setTransformation(depth_tr)
        qd.send(d)


def test_source_reads_newest_and_reconnects_after_a_stall():
    rig = _HostRig()
    opts = oakd.parse_url("oakd://?size=64x40&queue=2&timeout_s=0.5")
    src = oakd.OakdSource(opts, reconnect=True, connect=rig.connect)
    src.BACKOFF_START_S = 0.05
    # the first session's depth carries another camera matrix than its colour (fx 70, not 50)
    wrong = dai.ImgTransformation(64, 40, [[70.0, 0.0, 32.0], [0.0, 70.0, 20.0], [0.0, 0.0, 1.0]])
    with src:
        rig.send(0, wrong)
        f0 = src.read()
        for i in range(1, 6):  # the loop was busy: 5 frames arrive before the next read
            rig.send(i, wrong)
        time.sleep(0.3)
        f1 = src.read()
        assert (f0.seq, f1.seq) == (0, 1) and f1.color[5, 5, 1] == 5  # the newest
        # the device stalls: after timeout_s the source reconnects and goes on with the new session
        out = {}
        import threading

        t = threading.Thread(target=lambda: out.setdefault("f", src.read()))
        t.start()
        deadline = time.time() + 5
        while len(rig.sessions) < 2 and time.time() < deadline:
            time.sleep(0.02)
        time.sleep(0.1)
        rig.send(10)
        t.join(5)
        assert out["f"].color[5, 5, 1] == 10 and out["f"].seq == 2
        st = src.stats()
    assert st["reconnects"] == 1 and st["device"] == "host-rig-1" and st["dropped"] >= 3
    assert st["misaligned_depth"] == 2  # counted in the first session, kept over the reconnection


def test_source_without_reconnect_ends_with_a_clear_error():
    rig = _HostRig()
    opts = oakd.parse_url("oakd://?size=64x40&timeout_s=0.3&reconnect=0")
    src = oakd.OakdSource(opts, reconnect=True, connect=rig.connect)
    with src:
        rig.send(0)
        assert src.read() is not None
        with pytest.raises(EndOfStream, match="lost: no frame from OAK host-rig-0 for 0.3 s"):
            src.read()


def _transformation(K_sensor, sensor, crop, size, dist=(0.1, -0.2, 0.0, 0.0, 0.05)):
    """An ImgTransformation as the Camera node attaches it: the calibration at the sensor mode, a crop, a scale."""
    tr = dai.ImgTransformation(
        *sensor, [list(map(float, r)) for r in K_sensor], dai.CameraModel.Perspective, list(dist)
    )
    x, y, w, h = crop
    tr.addCrop(x, y, w, h)
    tr.addScale(size[0] / w, size[1] / h)
    return tr


def _frame_with(tr, i=0, w=640, h=400):
    f = _img(i, w=w, h=h)
    f.setTransformation(tr)
    return f


def test_intrinsics_come_from_the_frames_transformation_and_a_mismatch_is_reported_once(caplog):
    # calibrated at 1920x1080 (16:9); a 640x400 output via the calibration's scale-and-crop
    K1080 = np.array([[1578.0, 0, 987.3], [0, 1576.0, 552.1], [0, 0, 1]])
    s = max(640 / 1920, 400 / 1080)
    calib = Intrinsics(
        K1080[0, 0] * s, K1080[1, 1] * s, 987.3 * s - (1920 * s - 640) / 2, 552.1 * s, 640, 400, (0.1, -0.2, 0, 0, 0.05)
    )
    # ... but the camera picked the 4:3 sensor mode 4056x3040 (the 1080p image is its 3840x2160 centre, halved)
    # and cropped 16:10 from it: a wider view, so a shorter focal length than the calibration path says
    K_full = K1080.copy()
    K_full[:2] *= 2.0
    K_full[0, 2] += (4056 - 3840) / 2
    K_full[1, 2] += (3040 - 2160) / 2
    crop_h = 4056 * 400 // 640
    tr = _transformation(K_full, (4056, 3040), (0, (3040 - crop_h) // 2, 4056, crop_h), (640, 400))
    want = np.asarray(tr.getIntrinsicMatrix())
    assert want[0, 0] == pytest.approx(K_full[0, 0] * 640 / 4056, rel=1e-4)
    conv = oakd.FrameConverter(calib)
    caplog.set_level(logging.WARNING, logger="illuminet.hw.oakd")
    frames = []
    for i in range(3):
        g = dai.MessageGroup()
        g["color"] = _frame_with(tr, i)
        g["depth"] = _depth(i, w=640, h=400)
        frames.append(conv.convert(g))
    f = frames[-1]
    assert (f.intrinsics.fx, f.intrinsics.fy) == pytest.approx((want[0, 0], want[1, 1]), rel=1e-5)
    assert (f.intrinsics.cx, f.intrinsics.cy) == pytest.approx((want[0, 2], want[1, 2]), abs=1e-3)
    assert (f.intrinsics.width, f.intrinsics.height) == (640, 400)
    assert f.intrinsics.dist == calib.dist  # distortion does not change with crop and scale
    assert conv.intrinsics_source == "frame"
    assert oakd.intrinsics_disagreement(f.intrinsics, calib) > 0.05
    warnings = [r for r in caplog.records if "intrinsics" in r.getMessage()]
    assert len(warnings) == 1 and "differ from the calibration" in warnings[0].getMessage()

    # a frame whose transformation agrees with the calibration (the 1080p mode, cropped to 16:10): no warning
    caplog.clear()
    crop_w = round(1080 * 640 / 400)
    agree = _transformation(K1080, (1920, 1080), ((1920 - crop_w) // 2, 0, crop_w, 1080), (640, 400))
    conv2 = oakd.FrameConverter(calib)
    g = dai.MessageGroup()
    g["color"] = _frame_with(agree)
    g["depth"] = _depth(0, w=640, h=400)
    f2 = conv2.convert(g)
    assert conv2.intrinsics_source == "frame"
    assert oakd.intrinsics_disagreement(f2.intrinsics, calib) < 0.01
    assert not [r for r in caplog.records if "intrinsics" in r.getMessage()]

    # a frame built on the host carries no transformation: the calibration's intrinsics
    g = dai.MessageGroup()
    g["color"] = _img(0, w=640, h=400)
    g["depth"] = _depth(0, w=640, h=400)
    assert conv2.convert(g).intrinsics == calib and conv2.intrinsics_source == "calibration"


def test_depth_with_another_camera_matrix_than_its_colour_is_reported_once(caplog):
    """Depth aligned to colour must carry the colour frame's camera matrix (StereoDepth aligned to the
    calibration's idea of the crop while the Camera node took another sensor mode must be noticed)."""
    K1080 = np.array([[1578.0, 0, 987.3], [0, 1576.0, 552.1], [0, 0, 1]])
    K_full = K1080.copy()
    K_full[:2] *= 2.0
    K_full[0, 2] += 108
    K_full[1, 2] += 440
    crop_h = 4056 * 400 // 640
    colour_tr = _transformation(K_full, (4056, 3040), (0, (3040 - crop_h) // 2, 4056, crop_h), (640, 400))
    crop_w = round(1080 * 640 / 400)
    other_tr = _transformation(K1080, (1920, 1080), ((1920 - crop_w) // 2, 0, crop_w, 1080), (320, 200))
    same_tr = _transformation(K_full, (4056, 3040), (0, (3040 - crop_h) // 2, 4056, crop_h), (320, 200))
    calib = oakd.intrinsics_from_transformation(colour_tr, 640, 400)
    caplog.set_level(logging.WARNING, logger="illuminet.hw.oakd")

    def group(i, depth_tr):
        g = dai.MessageGroup()
        g["color"] = _frame_with(colour_tr, i)
        d = _depth(i, w=320, h=200)  # depth at half the size: compared after scaling
        d.setTransformation(depth_tr)
        g["depth"] = d
        return g

    conv = oakd.FrameConverter(calib)
    f = conv.convert(group(0, same_tr))
    assert conv.misaligned_depth == 0 and f.depth.shape == (400, 640)
    for i in range(1, 4):
        f = conv.convert(group(i, other_tr))  # the stream goes on
    assert f.depth.shape == (400, 640)
    assert conv.misaligned_depth == 3
    warnings = [r.getMessage() for r in caplog.records if "not aligned" in r.getMessage()]
    assert len(warnings) == 1 and "misaligned_depth" in warnings[0]
