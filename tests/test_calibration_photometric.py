"""Photometric calibration: response curve from a synthetic bracket, exposure/WB normalisation."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from illuminet.calibration.calibfile import CalibrationError
from illuminet.calibration.photometric import (
    REFERENCE,
    calibrate_response,
    exposure_factor,
    exposure_time_from_name,
    exposure_times_from_names,
    normalize_exposure,
    save_response_lut,
    undo_white_balance,
)
from illuminet.runtime.frame import Exposure
from illuminet.runtime.physics import linearize, load_response_lut

TIMES = [1 / 400, 1 / 200, 1 / 100, 1 / 50, 1 / 25, 1 / 12.5, 1 / 6.25]


def _bracket(gamma=(2.0, 2.2, 2.5), seed=0):
    """A static scene with radiance over ~2 decades, through a per-channel power-law camera."""
    rng = np.random.default_rng(seed)
    rad = np.exp(rng.uniform(np.log(0.02), np.log(3.0), (120, 160, 1))) * np.array([0.8, 1.0, 1.2])
    rad = cv2.GaussianBlur(rad.astype(np.float32), (0, 0), 3)
    imgs = []
    for t in TIMES:
        lin = np.clip(rad * t * 20, 0, 1)
        code = np.stack([lin[..., c] ** (1 / gamma[c]) for c in range(3)], -1) * 255
        code = np.clip(np.rint(code + rng.normal(0, 0.5, code.shape)), 0, 255).astype(np.uint8)
        imgs.append(np.ascontiguousarray(code[..., ::-1]))  # BGR, as files are read
    return imgs


def test_response_curve_recovers_camera_gamma(tmp_path):
    gamma = (2.0, 2.2, 2.5)
    lut = calibrate_response(_bracket(gamma), TIMES)
    assert lut.shape == (256, 3) and lut.dtype == np.float32
    assert np.all(np.diff(lut, axis=0) >= 0) and np.allclose(lut[255], 1.0) and np.all(lut[0] == 0)
    codes = np.arange(40, 231)
    for c in range(3):
        true = (codes / 255.0) ** gamma[c]
        err = np.abs(lut[codes, c] - true).max()
        print(f"channel {c}: gamma {gamma[c]}, max abs error {err:.4f} over codes 40..230")
        assert err < 0.05
    p = save_response_lut(lut, tmp_path / "resp")
    assert p.suffix == ".npy"
    back = load_response_lut(p)  # what the runtime reads
    img = np.full((1, 1, 3), 128, np.uint8)
    assert linearize(img, back)[0, 0, 1] == pytest.approx(lut[128, 1])


def test_bracket_errors():
    imgs = _bracket()
    with pytest.raises(CalibrationError, match="at least 3 exposures"):
        calibrate_response(imgs[:2], TIMES[:2])
    with pytest.raises(CalibrationError, match="span only 2.0x"):
        calibrate_response(imgs[:3], [0.01, 0.015, 0.02])
    with pytest.raises(CalibrationError, match="different sizes"):
        calibrate_response([imgs[0], imgs[1][:50], imgs[2]], TIMES[:3])


def test_exposure_times_from_names_and_json(tmp_path):
    assert exposure_time_from_name("img_10ms.png") == pytest.approx(0.01)
    assert exposure_time_from_name("e2500us.jpg") == pytest.approx(0.0025)
    assert exposure_time_from_name("shot_0.004s.png") == pytest.approx(0.004)
    assert exposure_time_from_name("bracket_1-250.png") == pytest.approx(0.004)
    assert exposure_time_from_name("IMG_0001.png") is None
    files = [tmp_path / "a.png", tmp_path / "b.png"]
    with pytest.raises(CalibrationError, match="a.png: exposure time unknown"):
        exposure_times_from_names(files)
    (tmp_path / "exposures.json").write_text(json.dumps({"a.png": 0.01, "b": 0.02}))
    assert exposure_times_from_names(files) == [0.01, 0.02]


def test_exposure_and_white_balance_normalisation():
    lin = np.full((2, 2, 3), 0.2, np.float32)
    # twice the reference exposure time: values halve; ISO 200 at half time: unchanged
    out, known = normalize_exposure(lin, Exposure(exposure_us=20_000, iso=100), undo_wb=False)
    assert known and np.allclose(out, 0.1)
    assert exposure_factor(Exposure(exposure_us=5_000, iso=200)) == pytest.approx(1.0)
    out, known = normalize_exposure(lin, Exposure())
    assert not known and np.allclose(out, lin)
    # the camera boosted red x2 (AWB under a blue-ish light): undoing it restores the light's colour
    wb = undo_white_balance(np.array([[[0.4, 0.2, 0.2]]], np.float32), (2.0, 1.0, 1.0))
    assert np.allclose(wb, [0.2, 0.2, 0.2])
    out, _ = normalize_exposure(
        np.array([[[0.4, 0.2, 0.2]]], np.float32),
        Exposure(exposure_us=REFERENCE.exposure_us, iso=100, wb_gains=(4.0, 2.0, 2.0)),
    )
    assert np.allclose(out, [0.2, 0.2, 0.2])
    with pytest.raises(ValueError, match="wb_gains must be 3 positive numbers"):
        undo_white_balance(lin, (1.0, 0.0, 1.0))


def test_photometric_cli(tmp_path, capsys):
    from illuminet.calibration.calibfile import Calibration, CameraCalib, save_calibration
    from illuminet.cli import main

    bracket = tmp_path / "bracket"
    bracket.mkdir()
    for img, t in zip(_bracket(), TIMES):
        cv2.imwrite(str(bracket / f"shot_{t * 1e6:.0f}us.png"), img)
    cal = save_calibration(Calibration({"left": CameraCalib(160, 120, np.eye(3), np.zeros(5))}), tmp_path / "c.json")
    out = tmp_path / "resp.npy"
    assert main(["calibrate", "photometric", str(bracket), "-o", str(out), "--calibration", str(cal)]) == 0
    assert "7 exposures" in capsys.readouterr().out
    lut = load_response_lut(out)
    assert abs(lut[128, 1] - (128 / 255) ** 2.2) < 0.03
    from illuminet.calibration.calibfile import load_calibration

    assert load_calibration(cal).response_lut_path() == out.resolve()
    (bracket / "unnamed.png").write_bytes((bracket / "shot_2500us.png").read_bytes())
    assert main(["calibrate", "photometric", str(bracket), "-o", str(out)]) == 2
    assert "unnamed.png: exposure time unknown" in capsys.readouterr().err
