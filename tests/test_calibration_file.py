"""Calibration file format: round trip, clear errors, resolution checks; the runtime's response LUT."""

from __future__ import annotations

import json

import numpy as np
import pytest

from illuminet.calibration.calibfile import (
    FORMAT_NAME,
    FORMAT_VERSION,
    Calibration,
    CalibrationError,
    CameraCalib,
    StereoCalib,
    load_calibration,
    save_calibration,
)
from illuminet.runtime.physics import linearize, load_response_lut


def _calib() -> Calibration:
    K = np.array([[400.0, 0, 319.5], [0, 401.0, 199.5], [0, 0, 1]])
    left = CameraCalib(640, 400, K, np.array([-0.05, 0.01, 0, 0, 0]), rms_px=0.2)
    right = CameraCalib(640, 400, K.copy(), np.array([-0.04, 0.01, 0, 0, 0]))
    return Calibration(
        {"left": left, "right": right}, StereoCalib("left", "right", np.eye(3), np.array([-0.075, 0, 0]), rms_px=0.3)
    )


def test_round_trip(tmp_path):
    p = save_calibration(_calib(), tmp_path / "c.json")
    d = json.loads(p.read_text())
    assert d["format"] == FORMAT_NAME and d["version"] == FORMAT_VERSION
    assert d["stereo"]["baseline_m"] == pytest.approx(0.075)
    c = load_calibration(p)
    assert c.color_camera == "left"
    assert np.allclose(c.camera("left").K, _calib().camera("left").K)
    assert c.stereo.baseline_m == pytest.approx(0.075)
    assert c.camera("left").rms_px == pytest.approx(0.2)
    intr = c.color.intrinsics()
    assert (intr.fx, intr.width, intr.height) == (400.0, 640, 400)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.pop("format"), "format: expected 'illuminet-calibration'"),
        (lambda d: d.update(version=99), "version: this build reads version 1"),
        (lambda d: d["cameras"]["left"].pop("K"), "missing key 'cameras.left.K'"),
        (lambda d: d["cameras"]["left"].update(K=[[1, 0], [0, 1]]), "cameras.left.K: expected shape (3, 3)"),
        (lambda d: d["cameras"]["left"].update(dist=[0.1, 0.2, 0.3]), "cameras.left.dist: model 'pinhole' takes"),
        (lambda d: d["cameras"]["left"].update(model="orthographic"), "cameras.left.model: expected one of"),
        (lambda d: d["cameras"]["left"].update(width="640"), "cameras.left.width: expected int"),
        (lambda d: d["stereo"].update(right="nope"), "stereo.right names camera 'nope'"),
        (lambda d: d["stereo"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "stereo.R: expected a rotation"),
        (lambda d: d["stereo"].update(baseline_m=0.2), "stereo.baseline_m 0.2 disagrees"),
        # wrong types used to escape as a bare ValueError/TypeError from float() and dict()
        (lambda d: d["cameras"]["left"].update(rms_px="abc"), "cameras.left.rms_px: expected the reprojection RMS"),
        (lambda d: d["cameras"]["left"].update(rms_px=float("nan")), "cameras.left.rms_px: expected"),
        (lambda d: d["stereo"].update(baseline_m="x"), "stereo.baseline_m: expected the baseline"),
        (lambda d: d["stereo"].update(rms_px=[1]), "stereo.rms_px: expected"),
        (lambda d: d.update(meta="ab"), "meta: expected an object"),
        (lambda d: d.update(meta=[1, 2]), "meta: expected an object"),
        (lambda d: d.update(meta=[[1, 2]]), "meta: expected an object"),  # dict() would have taken it
        (lambda d: d.update(color_camera=5), "color_camera: expected the name of one of the cameras"),
        (lambda d: d.update(stereo=5), "stereo: expected an object, got int"),
        # loaded without a word: an optical axis outside the picture, an absurd size, focal length or baseline
        (
            lambda d: d["cameras"]["left"].update(K=[[400, 0, -9000], [0, 400, 200], [0, 0, 1]]),
            "cameras.left.K: principal point (-9000, 200) is outside the 640x400 image",
        ),
        (lambda d: d["cameras"]["left"].update(width=10**30), "cameras.left.width/height: 1000000000000000000000"),
        (
            lambda d: d["cameras"]["left"].update(K=[[1e300, 0, 320], [0, 400, 200], [0, 0, 1]]),
            "cameras.left.K: fx=1e+300 pixels for an image 640 px across",
        ),
        (lambda d: d["stereo"].update(T=[1e300, 0, 0], baseline_m=None), "stereo.T: [1e+300, 0.0, 0.0] is over 100 m"),
    ],
)
def test_bad_file_names_key(tmp_path, mutate, message, recwarn):
    d = _calib().to_dict()
    mutate(d)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(d))
    with pytest.raises(CalibrationError) as e:
        load_calibration(p)
    assert str(p) in str(e.value) and message in str(e.value)
    assert "\n" not in str(e.value)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]  # |1e300| overflowed, a warning


@pytest.mark.timeout(60)  # a pipe given as the file waited for a writer for ever
def test_not_json_and_missing_and_depthai_hint(tmp_path):
    import os

    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "missing.json")
    os.mkfifo(tmp_path / "pipe.json")
    with pytest.raises(CalibrationError, match="pipe.json: not a regular file"):
        load_calibration(tmp_path / "pipe.json")
    p = tmp_path / "x.json"
    p.write_text("{nope")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(p)
    p.write_text(json.dumps({"cameraData": []}))
    with pytest.raises(CalibrationError, match="import-depthai"):
        load_calibration(p)


def test_json_python_refuses_and_an_endless_file_are_calibration_errors(tmp_path):
    # a 5000-digit int made json raise a bare ValueError (a traceback); /dev/zero was read until memory ran out
    from illuminet.calibration.depthai_import import import_depthai

    p = tmp_path / "huge.json"
    p.write_text('{"format": ' + "9" * 5000 + "}")
    for load in (load_calibration, import_depthai):
        with pytest.raises(CalibrationError, match=r"huge.json: not valid JSON: .*4300 digits"):
            load(p)
        with pytest.raises(CalibrationError, match=r"/dev/zero: not a regular file"):
            load("/dev/zero")


def test_other_resolution_refused_or_scaled():
    c = _calib()
    c.check_size(640, 400)
    with pytest.raises(CalibrationError, match=r"calibrated for 640x400, but images are 1280x800 \(same aspect"):
        c.check_size(1280, 800)
    with pytest.raises(CalibrationError, match="different aspect ratio"):
        c.check_size(640, 480)
    s = c.scaled_to(1280, 800)
    K = s.camera("left").K
    assert K[0, 0] == pytest.approx(800.0) and K[1, 1] == pytest.approx(802.0)
    assert K[0, 2] == pytest.approx(639.5) and K[1, 2] == pytest.approx(399.5)  # centre stays the centre
    assert np.allclose(s.camera("left").dist, c.camera("left").dist)
    assert s.stereo.rectification is None and s.stereo.baseline_m == pytest.approx(0.075)
    with pytest.raises(CalibrationError, match="cannot be used for 640x480"):
        c.scaled_to(640, 480)


def test_require_stereo_message():
    c = Calibration({"left": _calib().camera("left")})
    with pytest.raises(CalibrationError, match="has no 'stereo' section"):
        c.require_stereo()


def test_response_lut_load_and_use(tmp_path):
    lut = np.stack([np.linspace(0, 1, 256) ** g for g in (2.0, 2.2, 2.4)], axis=1).astype(np.float32)
    np.save(tmp_path / "r.npy", lut)
    got = load_response_lut(tmp_path / "r.npy")
    img = np.full((2, 2, 3), 128, np.uint8)
    lin = linearize(img, got)
    assert lin[0, 0, 1] == pytest.approx((128 / 255) ** 2.2, rel=1e-5)
    np.save(tmp_path / "bad.npy", lut[:100])
    with pytest.raises(ValueError, match=r"bad.npy: response curve must have shape \(256, 3\)"):
        load_response_lut(tmp_path / "bad.npy")
    np.save(tmp_path / "dec.npy", lut[::-1].copy())
    with pytest.raises(ValueError, match="non-decreasing"):
        load_response_lut(tmp_path / "dec.npy")
    with pytest.raises(ValueError, match="not found"):
        load_response_lut(tmp_path / "none.npy")
    # not a .npy: numpy's message advised unpickling it ("load it unsafely using the `allow_pickle=`"); an .npz
    # archive said "could not convert string to float: 'a'", naming no file
    (tmp_path / "text.npy").write_text("hello")
    with pytest.raises(ValueError, match=r"text\.npy: not a \.npy array; expected a \(256, 3\) response curve") as e:
        load_response_lut(tmp_path / "text.npy")
    assert "pickle" not in str(e.value)
    with open(tmp_path / "z.npy", "wb") as f:
        np.savez(f, a=lut)
    with pytest.raises(ValueError, match=r"z\.npy: an \.npz archive; expected a \(256, 3\) response curve"):
        load_response_lut(tmp_path / "z.npy")
    np.save(tmp_path / "words.npy", np.array([["a"] * 3] * 256))  # text that is no number: the file is named
    with pytest.raises(ValueError, match=r"words\.npy: cannot read response curve: could not convert"):
        load_response_lut(tmp_path / "words.npy")
