"""Stereo calibration on synthetic board views, and host stereo depth on a synthetic scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import Calibration, CalibrationError, CameraCalib, StereoCalib
from illuminet.calibration.charuco import BoardDetector
from illuminet.calibration.intrinsics import calibrate_intrinsics
from illuminet.calibration.stereo import HostStereo, calibrate_stereo
from illuminet.calibration.synthview import (
    board_plane,
    board_poses,
    degrade,
    depth_error,
    pixel_rays,
    render,
    stereo_scene,
)

SPEC = BoardSpec(9, 6, 30.0, 22.0, "DICT_4X4_50")


@pytest.fixture(scope="module")
def scene():
    return stereo_scene(640, 400)


def test_stereo_calibration_synthetic_baseline_within_1_percent():
    K = np.array([[450.0, 0, 322.3], [0, 451.0, 197.6], [0, 0, 1]])
    left = CameraCalib(640, 400, K, np.array([-0.1, 0.04, 0.0003, -0.0002, 0.0]))
    K2 = K.copy()
    K2[0, 2] += 5
    right = CameraCalib(640, 400, K2, np.array([-0.09, 0.03, -0.0002, 0.0001, 0.0]))
    R = cv2.Rodrigues(np.array([0.003, -0.012, 0.004]))[0]
    T = np.array([-0.075, 0.0005, 0.0012])
    plane = board_plane(SPEC)
    det = BoardDetector(SPEC)
    rl = pixel_rays(left.scaled_to(1280, 800))
    rr = pixel_rays(right.scaled_to(1280, 800))
    dl, dr = [], []
    for k, (Rb, tb) in enumerate(board_poses(SPEC, 12, seed=11, distance=(0.45, 0.7), shift=(0.08, 0.06))):
        il, _ = render(left, Rb, tb, [plane], background=128, rays=rl)
        ir, _ = render(right, R @ Rb, R @ tb + T, [plane], background=128, rays=rr)
        dl.append(det.detect(degrade(il, 0.7, 2.0, 2 * k), f"left_{k:02d}.png"))
        dr.append(det.detect(degrade(ir, 0.7, 2.0, 2 * k + 1), f"right_{k:02d}.png"))
    cl = calibrate_intrinsics([d for d in dl if len(d)], SPEC).camera
    cr = calibrate_intrinsics([d for d in dr if len(d)], SPEC).camera
    res = calibrate_stereo(dl, dr, SPEC, cl, cr)
    err = abs(res.stereo.baseline_m / 0.075 - 1)
    ang = np.degrees(np.linalg.norm(cv2.Rodrigues(res.stereo.R.T @ R)[0]))
    print(
        f"stereo: baseline {1000 * res.stereo.baseline_m:.2f} mm (error {100 * err:.3f} %), "
        f"rotation error {ang:.3f} deg, "
        f"rms {res.rms_px:.3f} px"
    )
    assert err < 0.01
    assert ang < 0.2
    assert res.rms_px < 0.5
    assert res.stereo.rectification is not None  # horizontal pair: rectification stored


def test_host_stereo_depth_on_synthetic_pair(scene):
    hs = HostStereo(scene.calibration)
    rgb, depth = hs.compute(scene.left, scene.right)
    assert rgb.shape == (400, 640, 3) and rgb.dtype == np.uint8
    assert depth.shape == (400, 640) and depth.dtype == np.float32
    assert np.all(depth >= 0) and np.all(np.isfinite(depth))
    truth = scene.depth_rectified(hs.rectification.R1, hs.rectification.P1)
    err = depth_error(depth, truth)
    print(f"host stereo error: {err}")
    assert err["median_rel"] < 0.03
    assert err["bad_5pct"] < 0.10
    assert err["valid"] > 0.6
    i = hs.intrinsics
    assert (i.width, i.height, i.dist) == (640, 400, ())
    assert i.fx == pytest.approx(hs.rectification.P1[0, 0])


def test_host_stereo_other_resolution(scene):
    # same aspect ratio: rescaled; the images must then have that size
    hs = HostStereo(scene.calibration, image_size=(320, 200))
    small_l = cv2.resize(scene.left, (320, 200), interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(scene.right, (320, 200), interpolation=cv2.INTER_AREA)
    _, depth = hs.compute(small_l, small_r)
    assert depth.shape == (200, 320) and (depth > 0).mean() > 0.5
    with pytest.raises(CalibrationError, match="cannot be used for 640x480"):
        HostStereo(scene.calibration, image_size=(640, 480))
    with pytest.raises(CalibrationError, match=r"left image is 320x200, but the stereo calibration is for 640x400"):
        HostStereo(scene.calibration).compute(small_l, small_r)


def test_host_stereo_refuses_bad_pairs(scene):
    c = scene.calibration
    L, R = c.camera("left"), c.camera("right")
    swapped = Calibration({"left": L, "right": R}, StereoCalib("left", "right", np.eye(3), np.array([0.075, 0, 0])))
    with pytest.raises(CalibrationError, match="left and right are swapped"):
        HostStereo(swapped)
    vertical = Calibration({"left": L, "right": R}, StereoCalib("left", "right", np.eye(3), np.array([0.0, -0.04, 0])))
    with pytest.raises(CalibrationError, match="mostly vertical"):
        HostStereo(vertical)
    with pytest.raises(CalibrationError, match="no 'stereo' section"):
        HostStereo(Calibration({"left": L}))


def test_too_few_stereo_pairs(scene):
    det = BoardDetector(SPEC)
    cam = scene.calibration.camera("left")
    img, _ = render(cam, *board_poses(SPEC, 1, 3, distance=(0.5, 0.6))[0], [board_plane(SPEC)], background=128)
    d = det.detect(img, "left_00.png")
    d2 = det.detect(img, "right_00.png")
    with pytest.raises(CalibrationError, match=r"too few stereo pairs: 1 pair\(s\)"):
        calibrate_stereo([d], [d2], SPEC, cam, cam)


def test_host_stereo_fisheye_and_grey_input():
    scene = stereo_scene(640, 400, fx=260.0, fisheye=True, seed=4)
    # full-resolution matching: the wide-angle rectified focal length (~203 px) leaves the 3 m wall
    # only ~5 px of disparity, too few at half resolution (median error 3.5 % there, 1.5 % here)
    hs = HostStereo(scene.calibration, scale=1.0)
    gl = cv2.cvtColor(scene.left, cv2.COLOR_BGR2GRAY)
    gr = cv2.cvtColor(scene.right, cv2.COLOR_BGR2GRAY)
    rgb, depth = hs.compute(gl, gr)  # mono stereo cameras deliver grey images
    assert rgb.shape == (400, 640, 3)
    err = depth_error(depth, scene.depth_rectified(hs.rectification.R1, hs.rectification.P1))
    print(f"fisheye host stereo error: {err}")
    assert err["median_rel"] < 0.03 and err["valid"] > 0.5
