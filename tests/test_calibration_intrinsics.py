"""Intrinsic calibration on synthetic renders of a board with known intrinsics, and its input errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import CalibrationError, CameraCalib
from illuminet.calibration.charuco import BoardDetector, detect_files
from illuminet.calibration.intrinsics import calibrate_intrinsics, evaluate_intrinsics
from illuminet.calibration.synthview import board_plane, board_poses, degrade, pixel_rays, render

SPEC = BoardSpec(9, 6, 30.0, 22.0, "DICT_4X4_50")
PINHOLE = CameraCalib(
    640, 400, np.array([[450.0, 0, 322.3], [0, 451.0, 197.6], [0, 0, 1]]), np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0])
)
FISHEYE = CameraCalib(
    640,
    400,
    np.array([[300.0, 0, 322.3], [0, 300.5, 197.6], [0, 0, 1]]),
    np.array([-0.02, -0.008, 0.008, -0.004]),
    "fisheye",
)


def _views(cam: CameraCalib, n: int, seed: int = 0, distance=(0.35, 0.6)) -> list:
    """Board rendered through ``cam`` at random poses, blurred (sigma 0.7 px) and noisy (2 levels)."""
    plane = board_plane(SPEC)
    rays = pixel_rays(cam.scaled_to(2 * cam.width, 2 * cam.height))
    det = BoardDetector(SPEC)
    out = []
    for k, (R, t) in enumerate(board_poses(SPEC, n, seed, distance=distance)):
        img, _ = render(cam, R, t, [plane], background=128, rays=rays)
        out.append(det.detect(degrade(img, 0.7, 2.0, seed * 100 + k), f"view_{k:02d}.png"))
    return out


def test_pinhole_synthetic_meets_targets():
    dets = _views(PINHOLE, 12)
    assert sum(len(d) > 0 for d in dets) >= 10
    r = calibrate_intrinsics(dets, SPEC, "pinhole")
    fx_err = abs(r.camera.K[0, 0] / PINHOLE.K[0, 0] - 1)
    fy_err = abs(r.camera.K[1, 1] / PINHOLE.K[1, 1] - 1)
    print(f"pinhole: fx error {100 * fx_err:.3f} %, fy error {100 * fy_err:.3f} %, rms {r.rms_px:.3f} px")
    assert fx_err < 0.005 and fy_err < 0.005
    assert r.rms_px <= 0.3
    assert abs(r.camera.K[0, 2] - PINHOLE.K[0, 2]) < 3 and abs(r.camera.K[1, 2] - PINHOLE.K[1, 2]) < 3
    # the true intrinsics explain the same detections about as well (poses re-solved)
    assert evaluate_intrinsics(dets, SPEC, PINHOLE).rms_px <= 0.3


def test_fisheye_synthetic_meets_targets():
    dets = _views(FISHEYE, 12, seed=1, distance=(0.19, 0.33))
    r = calibrate_intrinsics(dets, SPEC, "fisheye")
    fx_err = abs(r.camera.K[0, 0] / FISHEYE.K[0, 0] - 1)
    print(f"fisheye: fx error {100 * fx_err:.3f} %, rms {r.rms_px:.3f} px")
    assert r.camera.model == "fisheye" and len(r.camera.dist) == 4
    assert fx_err < 0.005
    assert r.rms_px <= 0.3


def test_fisheye_fixed_distortion_recovers_focal():
    dets = _views(FISHEYE, 3, seed=2, distance=(0.19, 0.3))
    guess = CameraCalib(
        640, 400, FISHEYE.K * np.array([[1.03, 1, 1], [1, 1.03, 1], [1, 1, 1]]), FISHEYE.dist, "fisheye"
    )
    r = calibrate_intrinsics(dets, SPEC, "fisheye", guess=guess, fix=("principal_point", "distortion"))
    assert np.allclose(r.camera.dist, FISHEYE.dist)
    assert abs(r.camera.K[0, 0] / FISHEYE.K[0, 0] - 1) < 0.005


def test_too_few_views():
    dets = _views(PINHOLE, 2, seed=3)
    with pytest.raises(CalibrationError, match=r"too few views: 2 usable view\(s\).*need at least 4"):
        calibrate_intrinsics(dets, SPEC, "pinhole")


def test_fix_needs_guess_and_known_names():
    dets = _views(PINHOLE, 1, seed=4)
    with pytest.raises(CalibrationError, match="needs starting intrinsics"):
        calibrate_intrinsics(dets, SPEC, fix=["focal"])
    with pytest.raises(CalibrationError, match="unknown parameter group"):
        calibrate_intrinsics(dets, SPEC, fix=["everything"])


def test_no_board_found_names_files_and_dictionary(tmp_path):
    img, _ = render(PINHOLE, *board_poses(SPEC, 1, 5)[0], [board_plane(SPEC)], background=128)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((400, 640, 3), 128, np.uint8))
    wrong = BoardSpec(9, 6, 30.0, 22.0, "DICT_5X5_100")
    with pytest.raises(CalibrationError) as e:
        detect_files([tmp_path], wrong)
    msg = str(e.value)
    assert "board not found in any of 2 image(s)" in msg and "a.png" in msg
    assert "markers were found with DICT_4X4_" in msg  # suggests the family the markers really come from
    with pytest.raises(CalibrationError, match="blank.png"):
        detect_files([tmp_path], SPEC, require_all=True)
    assert len(detect_files([tmp_path], SPEC)) == 1  # without require_all the blank view is skipped


def test_mixed_image_sizes(tmp_path):
    img, _ = render(PINHOLE, *board_poses(SPEC, 1, 6)[0], [board_plane(SPEC)], background=128)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "b.png"), cv2.resize(img, (320, 200)))
    with pytest.raises(CalibrationError, match=r"images have different sizes \(640x400: a.png; 320x200: b.png\)"):
        detect_files([tmp_path], SPEC)


def test_guess_of_other_resolution_refused():
    dets = _views(PINHOLE, 1, seed=7)
    guess = PINHOLE.scaled_to(1280, 800)
    with pytest.raises(CalibrationError, match="starting intrinsics are for 1280x800, the images are 640x400"):
        calibrate_intrinsics(dets, SPEC, guess=guess, fix=["distortion"])
