"""Relight API and CLI on a synthetic RGB-D view of a floor lit from the right."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from illuminet.cli import main
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import depth_to_mm
from illuminet.runtime.relight import relight

from ._learn_helpers import floor_rgbd
from .conftest import relight_argv

NPZ_KEYS = {
    "vertices",
    "normals",
    "faces",
    "radiance",
    "irradiance",
    "proxy_irradiance",
    "oi",
    "T_cam_obj",
    "exposure_scale",
    "dominant_dir",
    "dominant_share",
    "method",
    "bundle",
    "plane_observed",
    "format",
}


def test_relight_places_object_on_the_floor():
    color, depth, K = floor_rgbd()
    res = relight(color, depth, K, (160, 130), defaults(), bundle="builtin:vase")
    # the anchor lies on the floor under the anchor pixel; +Y of the object is the floor normal
    t = res.T_cam_obj[:3, 3]
    u = K.fx * t[0] / t[2] + K.cx
    v = K.fy * t[1] / t[2] + K.cy
    assert abs(u - 160) < 2 and abs(v - 130) < 2
    up = res.T_cam_obj[:3, 1]
    want = np.array([0, -np.cos(np.deg2rad(50)), -np.sin(np.deg2rad(50))])
    assert np.degrees(np.arccos(np.clip(up @ want, -1, 1))) < 3
    assert res.vertices.shape == res.normals.shape == res.radiance.shape
    assert np.isfinite(res.radiance).all() and (res.radiance >= 0).all()
    assert res.plane_observed > 0.2


def test_relight_radiance_matches_the_floor_it_stands_on():
    """What the scene fixes: an unoccluded up-facing white surface beside the floor receives the floor's
    irradiance, so its radiance (image units) is the floor's linear pixel / the floor's albedo. Checked on
    the learned chain, whose input is that floor alone (the default PRT shading also sees the lamp's
    falloff: the rim, nearer the lamp, is brighter than the floor; test_light_estimate covers it)."""
    cfg = apply_overrides(defaults(), [("model", "shading", "model")])
    color, depth, K = floor_rgbd()
    res = relight(color, depth, K, (160, 130), cfg, bundle="builtin:vase")
    R, t = res.T_cam_obj[:3, :3], res.T_cam_obj[:3, 3]
    v_obj, n_obj = (res.vertices - t) @ R, res.normals @ R  # back into the object frame (+Y up)
    # floor_rgbd paints the floor 0.15 * (1 + 0.8 x) * (1, 0.95, 0.85) in linear units (x: camera metres)
    floor = 0.15 * (1.0 + 0.8 * t[0]) * np.array([1.0, 0.95, 0.85])
    expected = floor / cfg.plane_light.assumed_albedo  # ~ (0.30, 0.29, 0.26)
    # the vase's rim: the top 5 mm, facing up, nothing of the object above it
    rim = (v_obj[:, 1] > v_obj[:, 1].max() - 0.005) & (n_obj[:, 1] > 0.95)
    assert rim.sum() >= 20
    # tolerance 15 %: the learned chain's own error (measured here: -1 %, +2 %, +8 % per channel) plus
    # the lamp's gradient over the rim's width (0.8/m x +-8.5 cm = +-7 %, which a rim average mostly
    # cancels); a missing or doubled exposure or albedo factor (x 0.8, x 2) fails it
    np.testing.assert_allclose(res.radiance[rim].mean(0), expected, rtol=0.15)
    # the base stands on the floor, which hides everything below it: no light (allow 3 % of the top)
    base = (v_obj[:, 1] < 0.002) & (n_obj[:, 1] < -0.95)
    assert base.sum() >= 20 and (res.radiance[base].mean(0) < 0.03 * expected).all()
    # the floor brightens towards +x (a lamp on the right; the plane grid's right edge is (1 + 0.4) /
    # (1 - 0.4) = 2.3x brighter than its left edge): right-facing sides get at least twice the light
    side = np.abs(n_obj[:, 1]) < 0.2
    right, left = res.radiance[side & (n_obj[:, 0] > 0.8)].mean(), res.radiance[side & (n_obj[:, 0] < -0.8)].mean()
    assert right > 2.0 * left, (right, left)


def test_relight_cli_writes_documented_npz(tmp_path):
    color, depth, K = floor_rgbd()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth))
    (tmp_path / "k.json").write_text(json.dumps({"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}))
    out = tmp_path / "r.npz"
    rc = main(
        [
            "relight",
            "--color",
            str(tmp_path / "c.png"),
            "--depth",
            str(tmp_path / "d.png"),
            "--intrinsics",
            str(tmp_path / "k.json"),
            "--anchor",
            "160,130",
            "--bundle",
            "builtin:bowl",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    z = np.load(out, allow_pickle=False)
    assert NPZ_KEYS <= set(z.files)
    assert z["faces"].max() < len(z["vertices"])
    assert str(z["method"]) == "prt"  # the default: the bundle's PRT lit by the light estimate
    assert LIGHT_KEYS <= set(z.files)


def test_relight_cli_errors(tmp_path, capsys):
    color, depth, K = floor_rgbd()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth)[:-10])
    args = [
        "relight",
        "--color",
        str(tmp_path / "c.png"),
        "--depth",
        str(tmp_path / "d.png"),
        "--intrinsics",
        "256,256,160,100",
        "--anchor",
        "160,130",
        "--out",
        str(tmp_path / "r.npz"),
    ]
    assert main(args) == 2
    assert "must be aligned to colour" in capsys.readouterr().err
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth))
    args[args.index("--anchor") + 1] = "900,130"
    assert main(args) == 2
    assert "outside the 320x200 image" in capsys.readouterr().err
    args[args.index("--intrinsics") + 1] = "256,256"
    assert main(args) == 2
    assert "--intrinsics: expected 4" in capsys.readouterr().err


LIGHT_KEYS = {"sh9", "sh9_radiance", "primary_dir", "primary_rgb", "primary_pos", "light_frame"}


def test_relight_npz_carries_the_light_estimate_when_the_chain_makes_one(tmp_path, monkeypatch):
    import illuminet.runtime.relight as R
    from illuminet.runtime.scene import LIGHT, PLANE_LIGHT, LightEstimate
    from illuminet.runtime.stage import Stage

    sh = np.zeros((9, 3))
    sh[0] = [1.0, 0.9, 0.8]
    d = np.array([0.6, 0.8, 0.0])
    est = LightEstimate(sh9=sh, primary_dir=d, primary_rgb=np.array([2.0, 1.9, 1.7]))

    class _GivenEstimate(Stage):  # stands where the light-estimate stage goes: a fixed, constructed estimate
        name = "light"
        requires = (PLANE_LIGHT,)
        provides = (LIGHT,)

        def process(self, frame):
            return frame.with_result(LIGHT, est)

    color, depth, K = floor_rgbd()
    no_light = apply_overrides(defaults(), [("light", "enabled", False)])
    plain = relight(color, depth, K, (160, 130), no_light, bundle="builtin:vase")
    plain.save(tmp_path / "plain.npz")
    assert not LIGHT_KEYS & set(np.load(tmp_path / "plain.npz").files)  # no estimate, no light fields

    stages = R.lighting_stages
    monkeypatch.setattr(R, "lighting_stages", lambda cfg, lut=None: stages(cfg, lut) + [_GivenEstimate()])
    res = relight(color, depth, K, (160, 130), no_light, bundle="builtin:vase")
    assert res.method == "prt"  # auto: the bundle's PRT shades from the estimate
    assert np.allclose(res.dominant_dir, res.T_cam_obj[:3, :3] @ d, atol=1e-5)
    res.save(tmp_path / "r.npz")
    z = np.load(tmp_path / "r.npz", allow_pickle=False)
    assert NPZ_KEYS | LIGHT_KEYS <= set(z.files)
    assert np.allclose(z["sh9"], sh) and np.allclose(z["sh9_radiance"], est.radiance_sh9())
    assert np.allclose(z["primary_dir"], d) and np.allclose(z["primary_rgb"], est.primary_rgb)
    assert z["primary_pos"].shape == (3,) and np.isnan(z["primary_pos"]).all()
    assert str(z["light_frame"]).startswith("object: anchor-centred, +Y up")
    assert np.allclose(z["radiance"], z["irradiance"] / np.pi * float(z["exposure_scale"]), rtol=1e-5)


def test_relight_prt_mode_without_an_estimate_says_so():
    import pytest

    from illuminet.runtime.config import apply_overrides

    color, depth, K = floor_rgbd()
    cfg = apply_overrides(defaults(), [("model", "shading", "prt"), ("light", "enabled", False)])
    with pytest.raises(ValueError, match='"prt" needs a light estimate'):
        relight(color, depth, K, (160, 130), cfg, bundle="builtin:vase")


# ------------------------------------------------------------- user mistakes: one line, exit 2, no work


def _small_inputs(tmp_path):
    """The tester's 64x48 grey image, depth 2 m everywhere (uint16 mm PNG), and accepted variants (the
    mistaken ones are in tests/test_hostile_input.py, BAD_RELIGHT)."""
    cv2.imwrite(str(tmp_path / "c.png"), np.full((48, 64, 3), 128, np.uint8))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((48, 64), 2000, np.uint16))
    np.save(tmp_path / "metres.npy", np.full((48, 64), 2.0, np.float32))
    (tmp_path / "metres.npy").rename(tmp_path / "UPPER.NPY")
    (tmp_path / "K_1280.json").write_text(
        json.dumps({"fx": 1200, "fy": 1200, "cx": 640, "cy": 480} | {"width": 1280, "height": 960})
    )


def _small_argv(tmp_path, **change):
    return relight_argv(tmp_path, {"--" + k: v for k, v in change.items()})


def test_relight_cli_accepts_upper_case_npy_proportional_intrinsics_and_exposure(tmp_path, capsys):
    _small_inputs(tmp_path)
    assert main(_small_argv(tmp_path, depth="{tmp}/UPPER.NPY")) == 0, capsys.readouterr().err
    base = dict(np.load(tmp_path / "r.npz"))
    # calibrated at 1280x960 (fx 1200), used on 64x48: the same camera, scaled by 1/20 (fx 60)
    assert main(_small_argv(tmp_path, intrinsics="{tmp}/K_1280.json", exposure="8000,400")) == 0
    scaled = dict(np.load(tmp_path / "r.npz"))
    assert np.allclose(scaled["T_cam_obj"][:3, 3], base["T_cam_obj"][:3, 3], atol=0.02)
    assert float(scaled["exposure_scale"]) == pytest.approx(8000e-6 * 4)  # the metadata was used


def test_relight_cli_takes_the_intrinsics_of_a_calibration_file(tmp_path, capsys):
    """`illuminet calibrate` (and DepthAI) write the camera's K into a calibration file; relight refused it as
    "expected a JSON object with fx, fy, cx, cy ..., got no fx, fy, cx, cy", so a user copied numbers by hand.
    FILE[:CAMERA] now gives that camera's K (default: the file's colour camera), scaled as a JSON's is."""
    _small_inputs(tmp_path)
    assert main(_small_argv(tmp_path, intrinsics="{tmp}/K_1280.json")) == 0
    scaled = dict(np.load(tmp_path / "r.npz"))

    def cam(w, h, f):
        K = [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]
        return {"width": w, "height": h, "model": "pinhole", "K": K, "dist": [0, 0, 0, 0]}

    cameras = {"rgb": cam(1280, 960, 1200), "mono": cam(1280, 800, 800)}
    calib = {"format": "illuminet-calibration", "version": 1, "cameras": cameras, "color_camera": "mono"}
    (tmp_path / "rig.json").write_text(json.dumps(calib))
    capsys.readouterr()
    assert main(_small_argv(tmp_path, intrinsics="{tmp}/rig.json:rgb")) == 0, capsys.readouterr().err
    np.testing.assert_allclose(dict(np.load(tmp_path / "r.npz"))["T_cam_obj"], scaled["T_cam_obj"], atol=1e-9)
    # the default camera (mono, 16:10) does not fit the 4:3 image: one line naming the cameras to choose from
    assert main(_small_argv(tmp_path, intrinsics="{tmp}/rig.json")) == 2
    err = capsys.readouterr().err
    assert "camera mono is 1280x800" in err and "rig.json:CAMERA, one of mono, rgb" in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert main(_small_argv(tmp_path, intrinsics="{tmp}/rig.json:nope")) == 2
    err = capsys.readouterr().err
    assert "no camera 'nope'" in err and len(err.strip().splitlines()) == 1, err


def test_relight_names_its_anchor_pixel_not_a_configuration_key(caplog):
    """`illuminet relight --anchor 320,40` on a wall warned "[anchor] pixel = [320, 40] lies on a plane labelled
    wall ...": a configuration key the user never set. Relight's warning names its own argument."""
    import logging

    from illuminet.hw import open_source

    with open_source("synthetic://lamp?seed=3&frames=1&size=640x400") as src:
        f = src.read()
    caplog.set_level(logging.WARNING)
    relight(f.color, f.depth, f.intrinsics, (320, 40), defaults(), bundle="builtin:vase")
    assert "anchor pixel = [320, 40] lies on a plane labelled wall" in caplog.text
    assert "[anchor] pixel" not in caplog.text


def test_relight_cli_reads_a_uint16_npy_as_millimetres_like_a_png(tmp_path, capsys):
    """uint16 depth is millimetres in a 16-bit PNG and in the Python API; a uint16 .npy was read as metres
    and refused as "millimetres: ... or give uint16 millimetres", which it was."""
    _small_inputs(tmp_path)
    np.save(tmp_path / "mm.npy", np.full((48, 64), 2000, np.uint16))
    assert main(_small_argv(tmp_path)) == 0
    png = dict(np.load(tmp_path / "r.npz"))
    assert main(_small_argv(tmp_path, depth="{tmp}/mm.npy")) == 0, capsys.readouterr().err
    npy = dict(np.load(tmp_path / "r.npz"))
    np.testing.assert_allclose(npy["T_cam_obj"], png["T_cam_obj"], atol=1e-6)


def test_relight_reads_a_jpeg_as_stored_whatever_its_exif_orientation(tmp_path, capsys):
    """OpenCV turns a JPEG by its EXIF orientation; the depth and intrinsics describe the stored pixels, so a
    phone photo tagged "rotate 90" was refused as not aligned with its depth (a square one lit turned)."""
    import struct

    _small_inputs(tmp_path)
    cv2.imwrite(str(tmp_path / "c.jpg"), np.full((48, 64, 3), 128, np.uint8))
    jpg = (tmp_path / "c.jpg").read_bytes()
    ifd = struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, 6, 0) + struct.pack("<I", 0)  # Orientation 6
    exif = b"Exif\x00\x00" + b"II*\x00" + struct.pack("<I", 8) + ifd
    (tmp_path / "rot.jpg").write_bytes(jpg[:2] + b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif + jpg[2:])
    assert main(_small_argv(tmp_path, color="{tmp}/c.jpg")) == 0
    plain = dict(np.load(tmp_path / "r.npz"))
    assert main(_small_argv(tmp_path, color="{tmp}/rot.jpg")) == 0, capsys.readouterr().err
    np.testing.assert_allclose(dict(np.load(tmp_path / "r.npz"))["radiance"], plain["radiance"])


def test_relight_leaves_the_previous_npz_when_a_write_fails(tmp_path, capsys, monkeypatch):
    """A full disk mid-write left a truncated npz in place of the previous result."""
    import errno

    _small_inputs(tmp_path)
    assert main(_small_argv(tmp_path)) == 0
    before = (tmp_path / "r.npz").read_bytes()

    def fill_the_disk(path, **arrays):
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 half an npz")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", fill_the_disk)
    capsys.readouterr()
    assert main(_small_argv(tmp_path)) == 1
    err = capsys.readouterr().err
    assert "cannot write" in err and "No space left on device" in err and len(err.strip().splitlines()) == 1, err
    assert (tmp_path / "r.npz").read_bytes() == before
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_relight_cli_names_the_npz_numpy_actually_writes(tmp_path, capsys):
    _small_inputs(tmp_path)
    capsys.readouterr()
    assert main(_small_argv(tmp_path, out="{tmp}/r.out")) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "r.out.npz").is_file() and not (tmp_path / "r.out").exists()
    assert out.startswith(f"wrote {tmp_path / 'r.out.npz'}: ")


def test_relight_runtime_refuses_bad_exposure_depth_and_intrinsics():
    from illuminet.runtime.frame import Exposure, Intrinsics

    color, depth, K = floor_rgbd()
    cfg = defaults()
    with pytest.raises(ValueError, match="exposure: the exposure time must be a finite number"):
        relight(color, depth, K, (160, 130), cfg, exposure=Exposure(exposure_us=float("inf"), iso=100.0))
    with pytest.raises(ValueError, match="exposure: expected an Exposure"):
        relight(color, depth, K, (160, 130), cfg, exposure=(8000, 400))
    with pytest.raises(ValueError, match="depth: median depth .* looks like millimetres"):
        relight(color, depth * 1000, K, (160, 130), cfg)
    with pytest.raises(ValueError, match=r"depth: no valid depth: .*\(64000 zero \(invalid\)\)"):
        relight(color, np.zeros_like(depth), K, (160, 130), cfg)
    with pytest.raises(ValueError, match="intrinsics: fx must be a number in pixels, got True"):
        relight(color, depth, Intrinsics(True, K.fy, K.cx, K.cy, K.width, K.height), (160, 130), cfg)
    with pytest.raises(ValueError, match="made for a 640x200 image but the colour image is 320x200"):
        relight(color, depth, Intrinsics(K.fx, K.fy, K.cx, K.cy, 640, 200), (160, 130), cfg)
    # the planes stage refused these with a warning; the error then blamed the plane under the anchor
    with pytest.raises(ValueError, match="depth: depth median is 0.0013 m: too small for a room"):
        relight(color, depth / 1000, K, (160, 130), cfg)
    with pytest.raises(ValueError, match="depth: depth map is 16x10; expected at least 32x24"):
        relight(color[:10, :16], depth[:10, :16], Intrinsics(16, 16, 8, 5, 16, 10), (8, 6), cfg)
    # a plane in full view but 20 m off (beyond the planes' 0.1-15 m) was "no real plane observed"
    with pytest.raises(ValueError, match=r"depth: 100 % of the valid depths lie outside 0.1-15 m.*median 20 m"):
        relight(color, np.full_like(depth, 20.0), K, (160, 130), cfg)
    with pytest.raises(ValueError, match="intrinsics: principal point cx=-5000, cy=99.5 is outside the 320x200"):
        relight(color, depth, Intrinsics(K.fx, K.fy, -5000.0, K.cy, K.width, K.height), (160, 130), cfg)


def test_relight_says_when_precision_has_no_effect(tmp_path, capsys):
    """`--precision fp32` picks the learned model's ONNX chain; with the default physical shading it was
    silently ignored."""
    _small_inputs(tmp_path)
    capsys.readouterr()
    assert main(_small_argv(tmp_path, precision="fp32")) == 0
    out, err = capsys.readouterr()
    assert "method prt" in out and "--precision fp32 applies to the learned model" in err, (out, err)
    assert main(_small_argv(tmp_path)) == 0
    assert "--precision" not in capsys.readouterr().err


def test_relight_names_an_overexposed_plane_under_the_anchor():
    """A floor whose pixels are all clipped is seen but measures no light: the message says so (it
    said "no real plane observed"; the white plate of the real OAK-D recordings is 45-67 % clipped)."""
    color, depth, K = floor_rgbd()
    with pytest.raises(ValueError, match=r"overexposed: 100 % of the pixels around it are clipped"):
        relight(np.full_like(color, 255), depth, K, (160, 130), defaults(), bundle="builtin:vase")


def test_a_png_cut_short_is_one_line_without_libpng_s_own(tmp_path, capfd):
    """libpng writes 'libpng error: Read Error' straight to file descriptor 2, past OpenCV's logging:
    the user saw it above relight's one line. Captured at the descriptor level here."""
    _small_inputs(tmp_path)
    rng = np.random.default_rng(0)
    cv2.imwrite(str(tmp_path / "big.png"), rng.integers(0, 256, (200, 320, 3), dtype=np.uint8))
    data = (tmp_path / "big.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    assert main(_small_argv(tmp_path, color=str(tmp_path / "cut.png"))) == 2
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot read an image from it" in lines[0] and "libpng" not in err, err


def test_float64_depth_beyond_float32_for_invalid_is_invalid_without_numpy_warnings(tmp_path):
    """1e300 marking invalid depth in a float64 array printed numpy's "overflow encountered in cast" (two
    lines) from the float32 conversion, through the Python API and in a .npy given to the command."""
    import warnings

    import illuminet

    color, depth, K = floor_rgbd()
    d = depth.astype(np.float64)
    d[:, :40] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = illuminet.relight(color, d, K, (160, 130), bundle="builtin:vase")
    assert np.isfinite(res.radiance).all()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    np.save(tmp_path / "d.npy", d)
    argv = ["relight", "--color", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d.npy")]
    argv += ["--intrinsics", f"{K.fx},{K.fy},{K.cx},{K.cy}", "--anchor", "160,130", "--out", str(tmp_path / "r.npz")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # pytest keeps warnings off stderr: make one fail the command
        assert main(argv) == 0
