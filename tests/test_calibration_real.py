"""Real data: DepthAI calibration import, and the ChArUco frames of the fisheye rig against its own file.

The rig's images (../shared/data/calibration/charuco_fisheye_rig) are 3 nearly identical views per
camera of a ChArUco board shown on a monitor: 13x8 squares, DICT_4X4 markers (ids 0..51), the
pre-4.6 ("legacy") layout, markers 3/4 of a square, and squares displayed 0.972 times as high as wide
(found by fitting; with square squares the factory intrinsics leave ~4 px RMS, with 0.9718 ~0.27 px).
Three views of one pose cannot determine a fisheye model, so the comparison holds the factory
distortion (and principal point) and estimates the focal length, and compares the stereo pose.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import CalibrationError, load_calibration, save_calibration
from illuminet.calibration.charuco import detect_files
from illuminet.calibration.depthai_import import import_depthai, parse_depthai
from illuminet.calibration.intrinsics import calibrate_intrinsics, evaluate_intrinsics
from illuminet.calibration.stereo import HostStereo, calibrate_stereo

pytestmark = pytest.mark.shared_data

RIG_BOARD = BoardSpec(13, 8, 20.0, 15.0, "DICT_4X4_1000", legacy=True, aspect=0.9718)
CAMS = {"left": "CAM_B", "right": "CAM_C", "vertical": "CAM_D"}


@pytest.fixture(scope="module")
def rig(shared_data):
    root = shared_data / "calibration" / "charuco_fisheye_rig"
    calib = import_depthai(root / "calib_sensor_07.json")
    dets = {c: detect_files([root / "charuco_on_monitor" / c], RIG_BOARD, require_all=True) for c in CAMS}
    return calib, dets


def test_import_oakd_pro(shared_data, tmp_path):
    c = import_depthai(shared_data / "calibration" / "oakd_pro_af_calib_18443010F116631200.json")
    assert set(c.cameras) == {"CAM_A", "CAM_B", "CAM_C"}
    assert c.camera("CAM_A").size == (1920, 1080) and c.camera("CAM_B").size == (1280, 800)
    assert c.camera("CAM_B").model == "pinhole" and len(c.camera("CAM_B").dist) == 14
    assert (c.stereo.left, c.stereo.right) == ("CAM_B", "CAM_C")
    assert c.stereo.baseline_m == pytest.approx(0.0845, abs=2e-4)
    assert c.stereo.T[0] < 0  # right camera to the right
    # round trip through our format, and host stereo rectification from it at 640x400
    p = save_calibration(c, tmp_path / "oak.json")
    back = load_calibration(p)
    hs = HostStereo(back, image_size=(640, 400))
    assert hs.intrinsics.width == 640 and 350 < hs.intrinsics.fx < 450
    assert hs.baseline_m == pytest.approx(0.0845, abs=5e-4)


def test_import_fisheye_rig(rig):
    calib, _ = rig
    assert all(cam.model == "fisheye" and len(cam.dist) == 4 for cam in calib.cameras.values())
    assert (calib.stereo.left, calib.stereo.right) == ("CAM_B", "CAM_C")
    # the file stores CAM_C -> CAM_B (+10.01 cm); the import inverts it
    assert calib.stereo.T[0] == pytest.approx(-0.10015, abs=2e-4)


def test_import_errors(tmp_path):
    with pytest.raises(CalibrationError, match="missing key 'cameraData'"):
        parse_depthai({"version": 7}, "x.json")
    with pytest.raises(CalibrationError, match=r"cameraData\[0\]: missing key 'intrinsicMatrix'"):
        parse_depthai({"cameraData": [[1, {"width": 10, "height": 10, "distortionCoeff": []}]]}, "x.json")
    with pytest.raises(CalibrationError, match="cameraType: expected 0 .* or 1"):
        parse_depthai(
            {
                "cameraData": [
                    [
                        1,
                        {
                            "width": 10,
                            "height": 10,
                            "intrinsicMatrix": np.eye(3).tolist(),
                            "distortionCoeff": [0] * 14,
                            "cameraType": 5,
                        },
                    ]
                ]
            },
            "x.json",
        )
    p = tmp_path / "d.json"
    p.write_text("[1, 2")
    with pytest.raises(CalibrationError, match="d.json: not valid JSON"):
        import_depthai(p)


def test_board_found_in_every_frame(rig):
    _, dets = rig
    for cam, ds in dets.items():
        assert len(ds) == 3, cam
        assert all(len(d) >= 80 for d in ds), [(cam, len(d)) for d in ds]  # 84 inner corners on the board


def test_factory_intrinsics_fit_and_identify_cameras(rig):
    calib, dets = rig
    for folder, sock in CAMS.items():
        own = evaluate_intrinsics(dets[folder], RIG_BOARD, calib.camera(sock)).rms_px
        others = [
            evaluate_intrinsics(dets[folder], RIG_BOARD, calib.camera(s)).rms_px for s in CAMS.values() if s != sock
        ]
        print(f"{folder}: factory {sock} RMS {own:.3f} px; other cameras' intrinsics {[round(o, 3) for o in others]}")
        assert own < 0.35
        assert own < min(others)  # the folder names match the sockets


def test_focal_length_vs_factory(rig):
    calib, dets = rig
    for folder, sock in CAMS.items():
        ref = calib.camera(sock)
        r = calibrate_intrinsics(dets[folder], RIG_BOARD, "fisheye", guess=ref, fix=("principal_point", "distortion"))
        rel = r.camera.K[0, 0] / ref.K[0, 0] - 1
        print(
            f"{folder}: fx {r.camera.K[0, 0]:.2f} vs factory {ref.K[0, 0]:.2f} ({100 * rel:+.2f} %), "
            f"rms {r.rms_px:.3f} px"
        )
        assert abs(rel) < 0.01
        assert r.rms_px < 0.35


def test_stereo_pose_vs_factory(rig):
    calib, dets = rig
    res = calibrate_stereo(
        dets["left"], dets["right"], RIG_BOARD, calib.camera("CAM_B"), calib.camera("CAM_C"), min_pairs=1
    )
    ang = np.degrees(np.linalg.norm(cv2.Rodrigues(res.stereo.R.T @ calib.stereo.R)[0]))
    t_ours = res.stereo.T / np.linalg.norm(res.stereo.T)
    t_ref = calib.stereo.T / np.linalg.norm(calib.stereo.T)
    dir_deg = np.degrees(np.arccos(np.clip(t_ours @ t_ref, -1, 1)))
    square_mm = RIG_BOARD.square_mm * calib.stereo.baseline_m / res.stereo.baseline_m
    print(
        f"stereo vs factory: rotation differs {ang:.3f} deg, baseline direction {dir_deg:.3f} deg, "
        f"implied displayed square {square_mm:.1f} mm, rms {res.rms_px:.3f} px"
    )
    assert ang < 0.2 and dir_deg < 0.5
    assert res.rms_px < 0.4


def test_host_stereo_on_real_fisheye_pair(shared_data, rig):
    """HostStereo (fisheye rectification) on the rig's real left/right frames at 960x600: depth on
    the monitor agrees with the board plane found by PnP. The board's displayed size is not known
    independently: 87.9 mm squares is what the factory baseline implies (test above), so this checks
    the rectification/matching/depth chain, not the absolute scale."""
    calib, _ = rig
    root = shared_data / "calibration" / "charuco_fisheye_rig" / "charuco_on_monitor"
    left = cv2.imread(str(root / "left" / "left_p0_1.png"))
    right = cv2.imread(str(root / "right" / "right_p0_1.png"))
    spec = BoardSpec(13, 8, 87.9, 87.9 * 0.75, "DICT_4X4_1000", legacy=True, aspect=0.9718)
    from illuminet.calibration.charuco import BoardDetector
    from illuminet.calibration.intrinsics import board_pose

    rv, tv, _ = board_pose(BoardDetector(spec).detect(left), spec, calib.camera("CAM_B"))
    size = (960, 600)
    hs = HostStereo(calib, image_size=size, min_depth_m=0.4)
    _, depth = hs.compute(
        cv2.resize(left, size, interpolation=cv2.INTER_AREA), cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    )
    R1, P1 = hs.rectification.R1, hs.rectification.P1
    Rb = cv2.Rodrigues(rv)[0]
    n, p0 = R1 @ Rb[:, 2], R1 @ tv
    xs, ys = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    rays = np.stack([(xs - P1[0, 2]) / P1[0, 0], (ys - P1[1, 2]) / P1[1, 1], np.ones(xs.shape)], -1)
    z_true = (p0 @ n) / (rays @ n)
    pc = (R1 @ (Rb @ spec.corner_points().T + tv[:, None])).T
    uv = (P1[:3, :3] @ pc.T).T
    hull = cv2.convexHull((uv[:, :2] / uv[:, 2:]).astype(np.float32)).astype(np.int32)
    mask = np.zeros(depth.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    ok = (mask > 0) & (depth > 0)
    rel = np.abs(depth[ok] - z_true[ok]) / z_true[ok]
    print(
        f"real fisheye pair: board at {np.median(z_true[mask > 0]):.3f} m, "
        f"{100 * ok.sum() / mask.sum():.1f} % valid, "
        f"depth error median {100 * np.median(rel):.2f} %, p90 {100 * np.percentile(rel, 90):.2f} %"
    )
    assert ok.sum() / mask.sum() > 0.8
    assert np.median(rel) < 0.03
