"""The Python API: ``illuminet.open`` (a stream of results), ``illuminet.relight`` and
``illuminet.render_preview``; the README's example; ``import illuminet`` stays light; ``illuminet
relight`` with depth at another resolution and ``--preview``."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import cv2
import jsonschema
import numpy as np
import pytest

import illuminet
from illuminet.runtime.config import ConfigError
from illuminet.runtime.frame import depth_to_mm
from illuminet.runtime.stream.estimate_json import load_schema

from ._learn_helpers import floor_rgbd
from ._sessions import env
from .conftest import REPO


def test_import_illuminet_loads_no_heavy_modules():
    code = (
        "import sys, illuminet; heavy = ('numpy', 'cv2', 'moderngl', 'onnxruntime', 'illuminet.api'); "
        "print([m for m in heavy if m in sys.modules]); "
        "illuminet.open; print('illuminet.api' in sys.modules)"
    )
    p = subprocess.run([sys.executable, "-c", code], env=env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["[]", "True"]  # nothing heavy until the API is touched
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        illuminet.nope  # noqa: B018


def test_open_streams_results_with_estimates_and_closes():
    from illuminet.commands.demo import DEFAULT_SESSION

    schema = load_schema()
    with illuminet.open(f"replay://{DEFAULT_SESSION}", render=False, timing="asap", max_frames=5) as stream:
        results = list(stream)
    assert [r.frame.seq for r in results] == [0, 1, 2, 3, 4]
    assert all(r.composite is None for r in results)  # render=False
    assert results[-1].estimate is not None and results[-1].shading is not None and results[-1].anchor is not None
    d = results[-1].estimate_json()
    jsonschema.validate(d, schema)
    assert d["frameId"] == 4
    assert stream.failures == {} and stream.frames == 5
    assert list(stream) == []  # exhausted and closed
    stream.close()  # idempotent


def test_open_overrides_and_their_errors(tmp_path):
    s = illuminet.open("synthetic://indoor", light__rate_hz=5.0, timing="asap", **{"output.fps": 12.0})
    assert s.cfg.light.rate_hz == 5.0 and s.cfg.source.timing == "asap" and s.cfg.output.fps == 12.0
    with pytest.raises(ConfigError, match="url=.*in sections source, imu; write section__url"):
        illuminet.open("synthetic://indoor", url="x")
    with pytest.raises(ConfigError, match="nope=1: no section has it"):
        illuminet.open("synthetic://indoor", nope=1)
    with pytest.raises(ConfigError, match="timing"):
        illuminet.open("synthetic://indoor", timing="sometimes")
    (tmp_path / "c.toml").write_text('[source]\ntiming = "asap"\n')
    assert illuminet.open("synthetic://indoor", str(tmp_path / "c.toml")).cfg.source.timing == "asap"


def test_relight_accepts_depth_at_another_resolution_and_plain_intrinsics():
    color, depth, K = floor_rgbd()  # 320x200
    full = illuminet.relight(color, depth, K, (160, 130), bundle="builtin:vase")
    half_mm = depth_to_mm(depth)[::2, ::2]  # a stereo camera's half resolution, uint16 millimetres
    half = illuminet.relight(color, half_mm, (K.fx, K.fy, K.cx, K.cy), (160, 130), bundle="builtin:vase")
    assert np.allclose(half.T_cam_obj[:3, 3], full.T_cam_obj[:3, 3], atol=0.01)
    assert np.allclose(half.radiance.mean(0), full.radiance.mean(0), rtol=0.1)
    with pytest.raises(ValueError, match="another aspect ratio than the colour image 320x200"):
        illuminet.relight(color, depth[:, :150], K, (160, 130), bundle="builtin:vase")
    with pytest.raises(ValueError, match="intrinsics: expected"):
        illuminet.relight(color, depth, (1.0, 2.0), (160, 130), bundle="builtin:vase")
    # a negative or NaN focal length is named, not reported later as "no real plane observed"
    with pytest.raises(ValueError, match=r"intrinsics: expected finite fx, fy > 0 .* got fx=-\d"):
        illuminet.relight(color, depth, (-K.fx, K.fy, K.cx, K.cy), (160, 130), bundle="builtin:vase")
    with pytest.raises(ValueError, match="got fx=nan"):
        illuminet.relight(color, depth, (float("nan"), K.fy, K.cx, K.cy), (160, 130), bundle="builtin:vase")


@pytest.mark.gl
def test_relight_cli_with_half_resolution_depth_writes_a_preview(tmp_path, gl, capsys):
    from illuminet.cli import main

    color, depth, K = floor_rgbd()
    cv2.imwrite(str(tmp_path / "c.png"), color[..., ::-1])
    cv2.imwrite(str(tmp_path / "d.png"), depth_to_mm(depth)[::2, ::2])  # 160x100 depth for 320x200 colour
    (tmp_path / "k.json").write_text(json.dumps({"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy}))
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
            "builtin:vase",
            "--out",
            str(tmp_path / "r.npz"),
            "--preview",
            str(tmp_path / "p.png"),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    pic = cv2.imread(str(tmp_path / "p.png"))[..., ::-1]
    assert pic.shape == color.shape
    diff = pic.astype(int).sum(-1) - color.astype(int).sum(-1)
    obj, shadow = diff > 24, diff < -24  # the white object is brighter than the grey floor, its shadow darker
    assert 100 < obj.sum() < 0.2 * obj.size and shadow.sum() > 50
    ys, xs = np.nonzero(obj)
    # the object stands on the anchor pixel (160, 130): above it, around its column
    assert abs(np.median(xs) - 160) < 15 and ys.max() <= 140 and ys.min() < 110
    # the floor is lit from the right (floor_rgbd): the cast shadow falls to the left of the object
    assert np.median(np.nonzero(shadow)[1]) < np.median(xs) - 10


@pytest.mark.gl
def test_readme_python_example_runs(gl, capsys):
    text = (REPO / "README.md").read_text()
    section = text.split("## Use from Python", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    ns: dict = {}
    exec(compile(code, "README.md (Use from Python)", "exec"), ns)
    out = capsys.readouterr().out
    assert "(9026, 3)" in out and ns["preview"].shape == (400, 640, 3)
    assert ns["res"].radiance.mean() > 0 and ns["picture"].dtype == np.uint8
    assert re.search(r"^\d+ True ", out, re.M)  # estimates with a primary light were printed


def test_relight_api_refuses_mistaken_inputs_with_one_line_each():
    from illuminet.runtime.frame import Exposure, Intrinsics

    color, depth, K = floor_rgbd()  # 320x200, fx 256

    def bad(match, **kw):
        args = {"depth": depth, "intrinsics": K} | kw
        exposure = args.pop("exposure", None)
        with pytest.raises(ValueError, match=match) as e:
            illuminet.relight(color, args["depth"], args["intrinsics"], (160, 130), "builtin:vase", exposure=exposure)
        assert "\n" not in str(e.value)

    bad(r"depth: empty \(shape \(0, 0\)\)", depth=np.ones((0, 0), np.float32))
    bad("depth: expected depths as numbers", depth=depth > 0)
    bad("depth: median depth .* looks like millimetres", depth=depth * 1000)
    bad(r"depth: no valid depth: .*\(64000 NaN\)", depth=np.full_like(depth, np.nan))
    bad("made for a 640x200 image but the colour image is 320x200", intrinsics=Intrinsics(256, 256, 160, 100, 640, 200))
    bad("width x height 1e\\+30x1e\\+30 is over 100000", intrinsics=Intrinsics(256, 256, 160, 100, 1e30, 1e30))
    bad("intrinsics: expected numbers in pixels, got a bool", intrinsics=(True, 256, 160, 100))
    bad("intrinsics: fx=1e\\+30 pixels for an image 320 px wide", intrinsics=(1e30, 1e30, 160, 100))
    bad("intrinsics: fx=1e-09 pixels", intrinsics=(1e-9, 1e-9, 160, 100))
    bad(r"a 3x3 camera matrix must be .*\(transposed\?\)", intrinsics=K.K.T)
    bad("exposure: the ISO must be a finite number", exposure=Exposure(exposure_us=8000.0, iso=float("nan")))
    bad("exposure: the exposure time must be", exposure=Exposure(exposure_us=1e308, iso=1e308))
    with pytest.raises(ValueError, match="color: expected a non-empty"):
        illuminet.relight(np.zeros((0, 0, 3), np.uint8), depth, K, (160, 130), "builtin:vase")


def test_relight_api_scales_intrinsics_of_a_proportional_size_and_save_names_the_file(tmp_path):
    from illuminet.runtime.frame import Intrinsics

    color, depth, K = floor_rgbd()
    full = illuminet.relight(color, depth, K, (160, 130), bundle="builtin:vase")
    big = Intrinsics(4 * K.fx, 4 * K.fy, (K.cx + 0.5) * 4 - 0.5, (K.cy + 0.5) * 4 - 0.5, 1280, 800)  # same camera
    scaled = illuminet.relight(color, depth, big, (160, 130), bundle="builtin:vase")
    assert np.allclose(scaled.T_cam_obj, full.T_cam_obj, atol=1e-4)
    assert scaled.save(tmp_path / "r.out") == str(tmp_path / "r.out.npz")  # numpy's rule, told
    assert (tmp_path / "r.out.npz").is_file()
    assert full.save(tmp_path / "r.npz") == str(tmp_path / "r.npz")
