"""Relight API and CLI on a synthetic RGB-D view of a floor lit from the right."""

from __future__ import annotations

import json

import cv2
import numpy as np

from illuminet.cli import main
from illuminet.runtime.config import defaults
from illuminet.runtime.frame import depth_to_mm
from illuminet.runtime.relight import relight

from ._learn_helpers import floor_rgbd

NPZ_KEYS = {"vertices", "normals", "faces", "radiance", "irradiance", "proxy_irradiance", "oi", "T_cam_obj",
            "exposure_scale", "dominant_dir", "dominant_share", "method", "bundle", "plane_observed",
            "format"}


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
    assert np.isfinite(res.radiance).all() and (res.radiance >= 0).all() and res.radiance.mean() > 0
    # radiance in the image's linear units: a white object under this floor's light is of the same order
    # as the floor's linear pixel values divided by its albedo (0.15 / 0.5)
    assert 0.01 < res.radiance.mean() < 3.0
    assert res.plane_observed > 0.2


def test_relight_cli_writes_documented_npz(tmp_path):
    color, depth, K = floor_rgbd()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth))
    (tmp_path / "k.json").write_text(json.dumps({"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}))
    out = tmp_path / "r.npz"
    rc = main(["relight", "--color", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d.png"),
               "--intrinsics", str(tmp_path / "k.json"), "--anchor", "160,130", "--bundle", "builtin:bowl",
               "--out", str(out)])
    assert rc == 0
    z = np.load(out, allow_pickle=False)
    assert NPZ_KEYS <= set(z.files)
    assert z["faces"].max() < len(z["vertices"])
    assert str(z["method"]) == "model:int8"


def test_relight_cli_errors(tmp_path, capsys):
    color, depth, K = floor_rgbd()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth)[:-10])
    args = ["relight", "--color", str(tmp_path / "c.png"), "--depth", str(tmp_path / "d.png"),
            "--intrinsics", "256,256,160,100", "--anchor", "160,130", "--out", str(tmp_path / "r.npz")]
    assert main(args) == 2
    assert "must be aligned to colour" in capsys.readouterr().err
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth))
    args[args.index("--anchor") + 1] = "900,130"
    assert main(args) == 2
    assert "outside the 320x200 image" in capsys.readouterr().err
    args[args.index("--intrinsics") + 1] = "256,256"
    assert main(args) == 2
    assert "--intrinsics: expected 4" in capsys.readouterr().err
