"""Plane detection, tracking, labels, anchors and the bad-depth guard, on analytic RGB-D scenes.

The scenes (:class:`illuminet.bench.planes.AnalyticScene`) are ray-cast with exact ground truth and
stereo-like noise (sigma = 3 mm x z^2), holes and 8-bit colour, so every figure here can fail.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from illuminet.bench.planes import AnalyticScene, plane_errors
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.stages.anchor import SYNTHETIC_HEIGHT_M, AnchorStage, object_frame, synthetic_plane
from illuminet.runtime.stages.plane_fit import (
    METHODS,
    DetectParams,
    check_depth,
    detect_planes,
    estimate_up,
    fit_plane_disparity,
    label_planes,
    make_cloud,
)
from illuminet.runtime.stages.planes import PlaneStage


@pytest.fixture(scope="module")
def scene() -> AnalyticScene:
    return AnalyticScene(seed=3)


def _cfg(**planes):
    return apply_overrides(defaults(), [("planes", k, v) for k, v in planes.items()])


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(np.dot(a, b))), -1, 1))))


# ---------------------------------------------------------------------------------------- fitting


def test_disparity_fit_is_exact_on_a_noise_free_plane():
    n_true = np.array([0.1, -0.8, -0.5])
    n_true /= np.linalg.norm(n_true)
    d_true = 1.3
    rng = np.random.default_rng(0)
    rays = np.column_stack([rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.4, 0.4, 500), np.ones(500)])
    z = -d_true / (rays @ n_true)
    n, d = fit_plane_disparity(rays[z > 0], z[z > 0])
    assert _angle(n, n_true) < 1e-6 and abs(d - d_true) < 1e-9
    assert fit_plane_disparity(np.array([[0.0, 0, 1], [0.1, 0, 1], [0.2, 0, 1]]), np.ones(3)) is None  # collinear


@pytest.mark.parametrize("method", METHODS)
def test_each_method_finds_floor_and_table_within_1deg_1cm_at_1_5m(scene, method):
    """Done-when figure: floor at 1.5 m below the camera, table top; normal <= 1 deg, offset <= 1 cm."""
    params = DetectParams.from_config(defaults())
    truth = scene.true_planes()
    for k in range(3):
        f = scene.frame(k)
        fits = detect_planes(make_cloud(f.depth, f.intrinsics), params, method, np.random.default_rng(k))
        errs = plane_errors(fits, truth)
        for label, ang, doff in [e for e in errs[:2]]:  # floor (offset 1.5 m) and table
            assert ang <= 1.0, (method, label, ang)
            assert doff <= 0.01, (method, label, doff)


@pytest.mark.parametrize("method", ["ransac", "region"])
def test_ransac_and_region_also_find_the_wall_at_4m(scene, method):
    f = scene.frame(0)
    fits = detect_planes(make_cloud(f.depth, f.intrinsics), DetectParams.from_config(defaults()), method)
    errs = plane_errors(fits, scene.true_planes())
    assert errs[2] is not None, f"{method} missed the wall"
    assert errs[2][1] < 2.0 and errs[2][2] < 0.03  # 4 m, noise sigma 4.8 cm per point


def test_plane_geometry_area_extent_and_masks(scene):
    stage = PlaneStage(defaults())
    out = stage.process(scene.frame(0))
    planes = out.results["planes"]
    table = [p for p in planes if p.label == "table"][0]
    # the table top is 0.9 m x 0.9 m = 0.81 m^2; holes and hidden parts only remove area
    assert 0.55 < table.area_m2 < 0.85
    assert 0.7 < table.extent_m[0] < 1.0 and 0.7 < table.extent_m[1] < 1.0
    assert table.inlier_mask.shape == (400, 640) and table.inlier_mask.dtype == bool
    kind = scene._kind
    inl = table.inlier_mask & (kind > 0)
    assert (kind[inl] == 2).mean() > 0.97  # the table's inliers really are table pixels
    assert abs(table.distance(table.centroid)) < 0.01
    assert np.allclose(np.linalg.norm(table.axes, axis=1), 1.0) and abs(table.axes[0] @ table.normal) < 1e-3


# ---------------------------------------------------------------------------------------- labels


def test_labels_with_gravity(scene):
    out = PlaneStage(defaults()).process(scene.frame(0))
    labels = sorted(p.label for p in out.results["planes"])
    assert labels == ["floor", "table", "wall"]
    floor = [p for p in out.results["planes"] if p.label == "floor"][0]
    assert _angle(floor.normal, -scene.gravity) < 1.0


def test_labels_without_gravity_use_the_largest_up_facing_plane():
    sc = AnalyticScene(seed=1, gravity=False)
    stage = PlaneStage(defaults())
    out = stage.process(sc.frame(0))
    assert stage.stats()["up_from"] == "largest-up-facing"
    labels = {p.label for p in out.results["planes"]}
    assert {"floor", "table", "wall"} <= labels


def test_estimate_up_fallbacks():
    up, src = estimate_up([], None)
    assert src == "assumed-level" and np.allclose(up, [0, -1, 0])
    up, src = estimate_up([(np.array([0, 0, -1.0]), 5.0), (np.array([0, -0.9, -0.43]), 3.0)], None)
    assert src == "largest-up-facing" and up[1] < -0.8  # floor-like beats the larger frontal wall
    up, src = estimate_up([], np.array([0, 2.0, 0]))
    assert src == "gravity" and np.allclose(up, [0, -1, 0])
    assert label_planes(
        [np.array([0, -1.0, 0]), np.array([0, -1.0, 0]), np.array([0, 0, -1.0])],
        [1.4, 0.7, 3.0],
        np.array([0, -1.0, 0]),
    ) == ["floor", "table", "wall"]


# ---------------------------------------------------------------------------------------- tracking


def test_tracking_keeps_ids_and_detects_only_every_n_frames(scene):
    stage = PlaneStage(_cfg(redetect_every=5, still_px=0.0))  # the tracker itself: fit every frame
    ids = []
    for k in range(11):
        out = stage.process(scene.frame(k))
        ids.append({p.label: p.id for p in out.results["planes"]})
    assert all(i == ids[0] for i in ids), ids
    st = stage.stats()
    assert st["detections"] == 3 and st["tracked_updates"] == 8 and st["tracks_lost"] == 0


def test_smoothing_reduces_frame_to_frame_jitter():
    sc = AnalyticScene(seed=5, depth_noise=0.01, table=False, wall=False)  # noisy, floor only
    jitter = {}
    for s in (0.0, 0.8):
        stage = PlaneStage(_cfg(smoothing=s, redetect_every=100, still_px=0.0))
        offs = [stage.process(sc.frame(k)).results["planes"][0].offset for k in range(12)]
        jitter[s] = np.std(np.diff(offs[2:]))
    assert jitter[0.8] < 0.6 * jitter[0.0], jitter


def test_tracking_follows_a_turning_camera_without_redetecting():
    """The camera pitches down 3 deg per frame: the last frame's planes catch only part of their
    points (a wall 4 m away moves 20 cm), so without predicting the motion nearly every frame lost a
    track and re-detected (8 of 9); with the constant-velocity prediction at most the frames where a
    plane leaves the view do, and the floor stays exact."""
    stage = PlaneStage(_cfg(redetect_every=100))
    for k in range(10):
        sc = AnalyticScene(seed=20 + k, pitch_deg=25.0 + 3.0 * k)
        planes = stage.process(sc.frame(k)).results["planes"]
        floor = plane_errors(planes, sc.true_planes())[0]
        assert floor is not None and floor[1] < 0.5 and floor[2] < 0.005, (k, floor)
    assert stage.stats()["tracks_lost"] <= 3, stage.stats()
    assert stage.stats()["still_frames"] == 0  # a moving camera is fitted every frame


def test_a_still_camera_keeps_its_planes_without_refitting(scene):
    from illuminet.runtime.stages.planes import HOLD_AFTER_FITS

    stage = PlaneStage(_cfg())
    outs = [stage.process(scene.frame(k)).results["planes"] for k in range(24)]
    st = stage.stats()
    # fitted until the temporal filter has settled, then held (the same planes object, not refitted)
    assert all(outs[k] is not outs[k - 1] for k in range(1, HOLD_AFTER_FITS)), st
    assert st["still_frames"] >= 24 - HOLD_AFTER_FITS - 3, st
    assert outs[-1] is outs[-2]
    floor = plane_errors(outs[-1], scene.true_planes())[0]
    assert floor is not None and floor[1] < 0.5 and floor[2] < 0.01
    off = PlaneStage(_cfg(still_px=0.0))
    for k in range(8):
        off.process(scene.frame(k))
    assert off.stats()["still_frames"] == 0 and off.stats()["tracked_updates"] + off.stats()["detections"] == 8


def test_lost_track_triggers_redetection():
    near = AnalyticScene(seed=2, cam_height_m=1.5, table=False, wall=False)
    far = AnalyticScene(seed=2, cam_height_m=1.9, table=False, wall=False)  # the camera was lifted
    stage = PlaneStage(_cfg(redetect_every=100))
    for k in range(3):
        stage.process(near.frame(k))
    out = stage.process(far.frame(3))
    floor = out.results["planes"][0]
    assert stage.stats()["tracks_lost"] == 1 and stage.stats()["detections"] == 2
    assert abs(floor.offset - 1.9) < 0.01


# ---------------------------------------------------------------------------------------- bad depth


def _frame_with_depth(depth, seq=0, size=(640, 400)):
    w, h = size
    return Frame(
        seq=seq,
        t_device_ns=seq,
        t_host_ns=seq,
        color=np.zeros((h, w, 3), np.uint8),
        depth=depth,
        intrinsics=Intrinsics(450, 450, (w - 1) / 2, (h - 1) / 2, w, h),
    )


@pytest.mark.parametrize(
    "kind,depth",
    [
        ("invalid", np.zeros((400, 640), np.float32)),
        ("invalid", np.full((400, 640), np.nan, np.float32)),
        ("units_mm", np.full((400, 640), 1500.0, np.float32)),
        ("units_small", np.full((400, 640), 0.0015, np.float32)),
    ],
)
def test_bad_depth_is_reported_once_and_the_stream_continues(scene, caplog, kind, depth):
    stage = PlaneStage(defaults())
    good = stage.process(scene.frame(0)).results["planes"]
    caplog.set_level(logging.WARNING)
    for k in range(3):
        out = stage.process(_frame_with_depth(depth, seq=k + 1))
        assert out.results["planes"] == good  # the previous planes are kept
    msgs = [r.getMessage() for r in caplog.records if "planes" in r.getMessage()]
    assert len(msgs) == 1, msgs
    assert stage.stats()["bad_depth"] == {kind: 3} and stage.stats()["bad_depth_frames"] == 3
    if kind == "units_mm":
        assert "millimetres" in msgs[0] and "depth_from_mm" in msgs[0]
    out = stage.process(scene.frame(5))  # and recovers on the next good frame
    assert len(out.results["planes"]) == 3


def test_tiny_and_missing_depth_give_empty_planes_before_any_good_frame(caplog):
    stage = PlaneStage(defaults())
    caplog.set_level(logging.WARNING)
    out = stage.process(_frame_with_depth(np.ones((10, 12), np.float32), size=(12, 10)))
    assert out.results["planes"] == ()
    out = stage.process(_frame_with_depth(None))
    assert out.results["planes"] == ()
    assert stage.stats()["bad_depth"] == {"tiny": 1, "no_depth": 1}
    assert "12x10" in caplog.text


def test_some_nan_pixels_are_treated_as_invalid_with_one_warning(scene, caplog):
    f = scene.frame(0)
    d = f.depth.copy()
    d[::7, ::5] = np.nan
    stage = PlaneStage(defaults())
    caplog.set_level(logging.WARNING)
    for k in range(2):
        out = stage.process(f.replace(depth=d, seq=k))
    assert len(out.results["planes"]) == 3
    assert caplog.text.count("NaN/inf") == 1


def test_check_depth_messages():
    assert check_depth(np.full((100, 100), 1.2, np.float32)) is None
    kind, msg = check_depth(np.full((100, 100), 1200.0, np.float32))
    assert kind == "units_mm" and "1200" in msg
    # a replayed depth PNG of 65535s is read as 65.535 m: not "convert millimetres", which it already is
    kind, msg = check_depth(np.full((100, 100), 65535, np.uint16) * np.float32(1e-3))
    assert kind == "units_mm" and "'no depth' seems written as 65535" in msg and "depth_from_mm" not in msg
    # a sparse map (0.5 % valid) is refused as too sparse, not as "all values are 0"
    sparse = np.zeros((200, 200), np.float32)
    sparse.reshape(-1)[::200] = 1.5
    kind, msg = check_depth(sparse)
    assert kind == "invalid" and "all values are 0" not in msg and "under 1 %" in msg, msg
    assert check_depth(np.zeros((100, 100), np.float32))[1].count("all values are 0") == 1


# ---------------------------------------------------------------------------------------- anchor


def _anchor_chain(cfg, frame):
    f = PlaneStage(cfg).process(frame)
    st = AnchorStage(cfg)
    return st, st.process(f)


def _check_frame(T):
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and abs(np.linalg.det(R) - 1) < 1e-9


def test_auto_anchor_stands_on_the_floor_under_the_image_centre(scene):
    st, out = _anchor_chain(defaults(), scene.frame(0))
    a = out.results["anchor"]
    floor = [p for p in out.results["planes"] if p.label == "floor"][0]
    assert a.plane_id == floor.id and not a.synthetic
    _check_frame(a.T_cam_obj)
    assert _angle(a.R[:, 1], floor.normal) < 1e-6 and a.R[:, 1] @ floor.normal > 0
    # the central ray meets the floor 1.5 / sin(35 deg) away
    ray = np.array([0, 0, 1.0])
    hit = floor.intersect(ray)
    assert np.linalg.norm(a.t - hit) < 0.01
    # +Z points towards the camera within the plane
    to_cam = -a.t - (-a.t @ a.R[:, 1]) * a.R[:, 1]
    assert a.R[:, 2] @ to_cam / np.linalg.norm(to_cam) > 0.999
    assert st.stats()["state"] == "plane"


def test_pixel_anchor_on_the_table(scene):
    # a pixel on the table top: project the table centre (world (0, 0.75, 1.6))
    p_c = scene.R_c2w.T @ (np.array([0.0, 0.75, 1.6]) - scene.C)
    u = scene.intr.fx * p_c[0] / p_c[2] + scene.intr.cx
    v = scene.intr.fy * p_c[1] / p_c[2] + scene.intr.cy
    cfg = apply_overrides(defaults(), [("anchor", "mode", "pixel"), ("anchor", "pixel", [float(u), float(v)])])
    _, out = _anchor_chain(cfg, scene.frame(0))
    a = out.results["anchor"]
    table = [p for p in out.results["planes"] if p.label == "table"][0]
    assert a.plane_id == table.id
    assert np.linalg.norm(a.t - p_c) < 0.01


def _project(scene, p_w):
    p_c = scene.R_c2w.T @ (np.asarray(p_w, float) - scene.C)
    return p_c, (scene.intr.fx * p_c[0] / p_c[2] + scene.intr.cx, scene.intr.fy * p_c[1] / p_c[2] + scene.intr.cy)


def test_pixel_anchor_on_a_wall_stands_on_the_floor_at_its_foot(scene, caplog):
    """An object cannot stand on a wall: a pixel on the wall puts it on the floor where the wall meets it
    (the floor under the pixel's ray lies behind the wall), with one warning naming the pixel."""
    _, (u, v) = _project(scene, [1.0, 0.4, scene.wall_dist])  # beside the table, seen above the floor
    assert 0 <= u < 640 and 0 <= v < 400
    cfg = apply_overrides(defaults(), [("anchor", "mode", "pixel"), ("anchor", "pixel", [float(u), float(v)])])
    caplog.set_level(logging.WARNING)
    _, out = _anchor_chain(cfg, scene.frame(0))
    a = out.results["anchor"]
    planes = out.results["planes"]
    floor = [p for p in planes if p.label == "floor"][0]
    assert any(p.label == "wall" for p in planes)
    assert a.plane_id == floor.id and not a.synthetic
    p_w = scene.R_c2w @ a.t + scene.C
    assert p_w[2] < scene.wall_dist  # in front of the wall, where the camera sees it
    assert np.linalg.norm(p_w[[0, 2]] - [1.0, scene.wall_dist]) < 0.4  # at the wall's foot, below the pixel
    assert f"pixel = [{u:g}, {v:g}] lies on a plane labelled wall" in caplog.text


def test_pixel_anchor_on_the_floor_is_unchanged_by_the_support_rule(scene):
    p_c, (u, v) = _project(scene, [-1.0, 0.0, 2.0])  # floor in view, beside the table
    cfg = apply_overrides(defaults(), [("anchor", "mode", "pixel"), ("anchor", "pixel", [float(u), float(v)])])
    st, out = _anchor_chain(cfg, scene.frame(0))
    a = out.results["anchor"]
    floor = [p for p in out.results["planes"] if p.label == "floor"][0]
    assert a.plane_id == floor.id and np.linalg.norm(a.t - p_c) < 0.01
    assert st.stats()["warnings"] == {}


def test_point_anchor_projects_onto_the_nearest_plane(scene):
    p_floor = scene.R_c2w.T @ (np.array([0.4, 0.05, 2.5]) - scene.C)  # 5 cm above the floor
    cfg = apply_overrides(defaults(), [("anchor", "mode", "point"), ("anchor", "point", [float(x) for x in p_floor])])
    _, out = _anchor_chain(cfg, scene.frame(0))
    a = out.results["anchor"]
    floor = [p for p in out.results["planes"] if p.label == "floor"][0]
    assert a.plane_id == floor.id
    assert abs(floor.distance(a.t)) < 1e-9
    assert abs(np.linalg.norm(a.t - p_floor) - 0.05) < 0.01


def test_anchor_does_not_drift_or_spin_over_frames(scene):
    cfg = defaults()
    ps, an = PlaneStage(cfg), AnchorStage(cfg)
    Ts = [an.process(ps.process(scene.frame(k))).results["anchor"].T_cam_obj for k in range(10)]
    for T in Ts[1:]:
        assert np.linalg.norm(T[:3, 3] - Ts[0][:3, 3]) < 0.01
        cosang = (np.trace(Ts[0][:3, :3].T @ T[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cosang, -1, 1))) < 0.5


def test_synthetic_plane_when_no_plane_is_found(caplog):
    caplog.set_level(logging.INFO)
    stage = AnchorStage(defaults())
    f = _frame_with_depth(np.zeros((400, 640), np.float32)).with_result("planes", ())
    g = np.array([0.0, np.cos(np.radians(30)), np.sin(np.radians(30))])  # camera pitched down 30 deg
    out = stage.process(f.replace(gravity=g))
    a = out.results["anchor"]
    assert a.synthetic and a.plane_id == -1
    _check_frame(a.T_cam_obj)
    assert np.allclose(a.R[:, 1], -g)
    assert abs(a.t @ g - SYNTHETIC_HEIGHT_M) < 1e-9  # 1.2 m below the camera along gravity
    st = stage.stats()
    assert st["state"] == "synthetic" and st["synthetic_frames"] == 1
    assert "synthetic floor" in caplog.text
    # without gravity: the camera is assumed level
    plane, origin = synthetic_plane(None)
    assert np.allclose(plane.normal, [0, -1, 0]) and np.allclose(origin, [0, 1.2, 1.5])


def test_object_frame_when_looking_straight_down():
    T = object_frame(np.array([0, 0, -1.0]), np.array([0, 0, 1.0]))
    _check_frame(T)
    assert np.allclose(T[:3, 1], [0, 0, -1]) and np.allclose(T[:3, 2], [0, 1, 0])


@pytest.mark.parametrize("lock", ["camera", "world"])
def test_pixel_outside_the_image_falls_back_to_the_centre_once(scene, caplog, lock):
    cfg = apply_overrides(
        defaults(), [("anchor", "mode", "pixel"), ("anchor", "pixel", [5000, 20]), ("anchor", "lock", lock)]
    )
    ps, an = PlaneStage(cfg), AnchorStage(cfg)
    caplog.set_level(logging.WARNING)
    for k in range(3):
        out = an.process(ps.process(scene.frame(k)))
    floor = [p for p in out.results["planes"] if p.label == "floor"][0]
    assert out.results["anchor"].plane_id == floor.id
    assert caplog.text.count("outside the 640x400 image") == 1
    # camera lock chooses (and checks the pixel) every frame; world lock places the object once
    assert an.stats()["warnings"] == {"pixel_outside": 3 if lock == "camera" else 1}


def test_smoothing_does_not_lag_behind_a_moving_camera():
    """The camera rises 5 mm per frame: plain exponential smoothing at 0.8 would trail by ~2 cm."""
    stage = PlaneStage(_cfg(smoothing=0.8, redetect_every=100))
    errs = []
    for k in range(8):
        h = 1.5 + 0.005 * k
        sc = AnalyticScene(seed=10 + k, cam_height_m=h, table=False, wall=False)
        floor = stage.process(sc.frame(k)).results["planes"][0]
        errs.append(abs(floor.offset - h))
    assert max(errs) < 0.003, errs
    assert stage.stats()["tracks_lost"] == 0
