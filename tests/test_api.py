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
from illuminet.api import StreamClosed
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
    with pytest.raises(StreamClosed, match="is closed"):  # exhausted and closed
        list(stream)
    stream.close()  # idempotent


def test_a_closed_stream_cannot_be_reopened_or_read_and_says_so():
    """A closed stream could be reopened (`with`), iterated and read with next(): each silently gave
    nothing, as if the source had no frames."""
    url = "synthetic://indoor?frames=50&size=64x48"
    s = illuminet.open(url, render=False, timing="asap")
    with s:
        assert next(s).frame.seq == 0
    for attempt in (lambda: list(s), lambda: next(s), lambda: s.open(), lambda: s.__enter__()):
        with pytest.raises(StreamClosed) as e:
            attempt()
        msg = str(e.value)
        assert "\n" not in msg and "is closed" in msg and f"illuminet.open({url!r}" in msg, msg
    never = illuminet.open(url, render=False)
    never.close()  # closed before its first frame
    with pytest.raises(StreamClosed):
        next(never)


def test_open_overrides_and_their_errors(tmp_path):
    s = illuminet.open("synthetic://indoor", light__rate_hz=5.0, timing="asap", **{"output.fps": 12.0})
    assert s.cfg.light.rate_hz == 5.0 and s.cfg.source.timing == "asap" and s.cfg.output.fps == 12.0
    with pytest.raises(ConfigError, match="url=.*in sections source, imu; write section__url"):
        illuminet.open("synthetic://indoor", url="x")
    with pytest.raises(ConfigError, match="nope=1: no section has it"):
        illuminet.open("synthetic://indoor", nope=1)
    # a typo names the key it is close to (it said only 'no section has it; see config.toml')
    with pytest.raises(
        ConfigError, match=r"timng='asap': no section has it; see config.toml \(did you mean timing\?\)"
    ):
        illuminet.open("synthetic://indoor", timng="asap")
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


# --------------------------------------------------------------------------------------------------
# argument checks: one ValueError naming the argument, what was expected and what was given


def _one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg and len(msg) < 400, msg
    return msg


@pytest.mark.parametrize(
    "anchor, match",
    [
        (None, "anchor_px: expected \\(x, y\\).*got NoneType None"),
        (np.float64(3.0), "anchor_px: expected \\(x, y\\).*got float64"),
        (np.array(5.0), "anchor_px: expected .*got an array of shape \\(\\)"),
        ((5,), "anchor_px: expected .*got 1 values \\(5,\\)"),
        ((160, 130, 99), "anchor_px: expected .*got 3 values \\(160, 130, 99\\)"),
        (("300", "200"), "anchor_px: expected .*got '300' \\(str\\)"),
        ("ab", "anchor_px: expected .*got str 'ab'"),
        ({"x": 1, "y": 2}, "anchor_px: expected .*got dict"),
        ((1 + 2j, 3), "anchor_px: expected .*\\(complex\\)"),
        (np.array([[160.0], [130.0]]), "anchor_px: expected .*got an array of shape \\(2, 1\\)"),
        ((True, True), "anchor_px: expected .*got True \\(bool\\)"),
        (np.array([True, False]), "anchor_px: expected .*\\(bool_?\\)"),
        ((float("nan"), 130), "anchor_px: expected .*two finite numbers.*nan"),
        ((160, float("inf")), "anchor_px: expected .*two finite numbers.*inf"),
        ((10**400, 130), "anchor_px: expected .*two finite numbers"),
        ((900, 130), "anchor_px: \\(900, 130\\) is outside the 320x200 image; expected 0 <= x < 320"),
        ((-1, 130), "anchor_px: \\(-1, 130\\) is outside the 320x200 image"),
        ((160, 200), "anchor_px: \\(160, 200\\) is outside the 320x200 image"),
    ],
)
def test_relight_refuses_a_bad_anchor_px(anchor, match):
    color, depth, K = floor_rgbd()  # 320x200
    with pytest.raises(ValueError, match=match) as e:
        illuminet.relight(color, depth, K, anchor, "builtin:vase")
    _one_line(e)


def test_relight_accepts_anchor_px_as_numpy_scalars_a_list_or_an_array():
    from illuminet.runtime.relight import check_anchor_px

    for ok in ((np.int64(160), np.float32(130)), [160, 130.5], np.array([160, 130]), np.array([160.0, 130.0])):
        x, y = check_anchor_px(ok, 320, 200, "anchor_px")
        assert type(x) is float and type(y) is float and x == 160


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"color": None}, "color: expected a non-empty HxWx3 uint8 RGB image.*got NoneType"),
        ({"color": "c.png"}, "color: expected .*got str 'c.png'"),
        ({"color": np.zeros((200, 320), np.uint8)}, "color: expected .*got \\(200, 320\\) uint8"),
        ({"color": np.zeros((200, 320, 3), np.float32)}, "color: expected .*got \\(200, 320, 3\\) float32"),
        ({"depth": None}, "depth: expected a 2-D array of depths.*got NoneType"),
        ({"depth": "d.png"}, "depth: expected a 2-D array of depths.*got str"),
        ({"intrinsics": None}, "intrinsics: expected an Intrinsics, a 3x3 camera matrix .*got None"),
        ({"intrinsics": "256,256,160,100"}, "intrinsics: expected numbers in pixels"),
        ({"intrinsics": [[256, 0.5, 160], [0, 256, 100], [0, 0, 1]]}, "intrinsics: .*skew K\\[0, 1\\]=0.5.*undistort"),
        ({"config": 5}, "illuminet.relight\\(\\): config: expected a Config, a config.toml path or None, got int"),
        ({"config": b"c.toml"}, "config: expected a Config, a config.toml path or None, got bytes"),
        ({"nope": 1}, "illuminet.relight\\(\\): override nope=1: no section has it"),
    ],
)
def test_relight_refuses_bad_arguments_naming_them(kw, match):
    color, depth, K = floor_rgbd()
    args = {"color": color, "depth": depth, "intrinsics": K} | kw
    with pytest.raises(ValueError, match=match) as e:
        color, depth, K = args.pop("color"), args.pop("depth"), args.pop("intrinsics")
        illuminet.relight(color, depth, K, (160, 130), "builtin:vase", **args)
    _one_line(e)


def test_relight_refuses_a_huge_image_from_its_shape_before_any_copy():
    import time
    import tracemalloc

    from illuminet.commands.relight import MAX_IMAGE_PIXELS

    color, depth, K = floor_rgbd()  # 320x200: the depth of the same aspect ratio would be resized down
    huge_color = np.broadcast_to(np.uint8(128), (20000, 20000, 3))  # 12 bytes that read as 1.2 GB
    huge_depth = np.broadcast_to(np.float32(1.0), (20000, 12500))
    cases = [
        (lambda: illuminet.relight(huge_color, depth, K, (160, 130)), "color: 20000x20000 pixels is over"),
        (lambda: illuminet.relight(color, huge_depth, K, (160, 130)), "depth: 12500x20000 pixels is over"),
        (lambda: illuminet.align_depth(huge_depth, color.shape), "depth: 12500x20000 pixels is over"),
    ]
    for call, match in cases:
        tracemalloc.start()
        t0 = time.perf_counter()
        with pytest.raises(ValueError, match=f"{match} the limit of {MAX_IMAGE_PIXELS / 1e6:g} Mpx") as e:
            call()
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        _one_line(e)
        assert elapsed < 0.5, f"{match}: refused after {elapsed:.2f} s"
        assert peak < 50e6, f"{match}: {peak / 1e6:.0f} MB allocated before refusing"


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"color": None}, "color: expected a non-empty HxWx3 uint8 RGB image.*got NoneType"),
        ({"color": np.broadcast_to(np.uint8(128), (20000, 20000, 3))}, "color: 20000x20000 pixels is over the limit"),
        ({"color": np.zeros((200, 320, 4), np.uint8)}, "color: expected .*got \\(200, 320, 4\\) uint8"),
        ({"result": None}, "result: expected the RelightResult that illuminet.relight\\(\\) returned, got NoneType"),
        ({"result": "x"}, "result: expected the RelightResult .*got str 'x'"),
        ({"depth": "d.png"}, "depth: expected a 2-D array of depths.*got str"),
        ({"intrinsics": (1.0, 2.0)}, "intrinsics: expected"),
        ({"config": 5}, "illuminet.render_preview\\(\\): config: expected a Config"),
        ({"nope": 1}, "illuminet.render_preview\\(\\): override nope=1"),
    ],
)
def test_render_preview_refuses_bad_arguments_before_rendering(kw, match, monkeypatch):
    import illuminet.runtime.render.stage as render_stage
    from illuminet.runtime.relight import RelightResult

    def no_gl(*a, **k):
        raise AssertionError("RenderStage was made before the arguments were checked")

    monkeypatch.setattr(render_stage, "RenderStage", no_gl)
    color, depth, K = floor_rgbd()
    fake = object.__new__(RelightResult)  # never drawn: every case is refused before
    args = {"color": color, "depth": depth, "intrinsics": K, "result": fake} | kw
    with pytest.raises(ValueError, match=match) as e:
        color, depth, K, result = args.pop("color"), args.pop("depth"), args.pop("intrinsics"), args.pop("result")
        illuminet.render_preview(color, depth, K, result, **args)
    _one_line(e)


def test_relight_takes_a_bundle_path_and_refuses_a_bundle_of_another_type():
    from pathlib import Path

    from illuminet.runtime.assets.bundle import builtin_dir

    color, depth, K = floor_rgbd()
    res = illuminet.relight(color, depth, K, (160, 130), Path(builtin_dir() / "vase"))  # was refused
    assert Path(res.bundle) == builtin_dir() / "vase"
    with pytest.raises(ValueError, match="bundle: expected builtin:NAME or a bundle folder .*got int 5") as e:
        illuminet.relight(color, depth, K, (160, 130), 5)  # was "override: [model] bundle: expected string"
    _one_line(e)


@pytest.mark.parametrize(
    "T", [np.eye(3), np.full((4, 4), np.nan), "T", np.diag([1.0, 1.0, 1.0, 2.0])], ids=["3x3", "nan", "str", "row"]
)
def test_render_preview_refuses_a_result_with_a_broken_transform(T, monkeypatch):
    # a 3x3 was an IndexError traceback from the renderer, NaN "cannot convert float NaN to integer"
    import dataclasses

    import illuminet.runtime.render.stage as render_stage

    def no_gl(*a, **k):
        raise AssertionError("RenderStage was made before the arguments were checked")

    color, depth, K = floor_rgbd()
    res = illuminet.relight(color, depth, K, (160, 130), "builtin:vase")
    monkeypatch.setattr(render_stage, "RenderStage", no_gl)
    with pytest.raises(ValueError, match="result.T_cam_obj: expected the finite 4x4 object-to-camera transform") as e:
        illuminet.render_preview(color, depth, K, dataclasses.replace(res, T_cam_obj=T))
    _one_line(e)


@pytest.mark.parametrize(
    "args, kw, match",
    [
        ((5,), {}, "url: expected a source URL string .*got int 5"),
        ((None,), {}, "url: expected a source URL string .*got NoneType"),
        (("synthetic://indoor",), {"strict": "no"}, "strict: expected True, False or None, got str 'no'"),
        (("synthetic://indoor",), {"strict": 0}, "strict: expected True, False or None, got int 0"),
        (("synthetic://indoor",), {"render": "no"}, "render: expected True or False, got str 'no'"),
        (("synthetic://indoor",), {"render": None}, "render: expected True or False, got NoneType"),
        (("synthetic://indoor", 5), {}, "illuminet.open\\(\\): config: expected a Config, a config.toml path or None"),
    ],
)
def test_open_refuses_bad_arguments_naming_them(args, kw, match):
    with pytest.raises(ValueError, match=match) as e:
        illuminet.open(*args, **kw)
    _one_line(e)
    s = illuminet.open("synthetic://indoor", render=np.bool_(False), strict=True)
    assert s.render is False and s.strict is True


#: render_preview on the main thread, a worker, the main thread again, then two previews and two streams
#: at once (a fresh process: no test fixture has made the context current on its main thread)
_ANY_THREAD = """
import threading, numpy as np, illuminet
from tests._learn_helpers import floor_rgbd
color, depth, K = floor_rgbd()
res = illuminet.relight(color, depth, K, (160, 130), "builtin:vase")
out = {}
def preview(i):
    try:
        out[i] = illuminet.render_preview(color, depth, K, res)
    except Exception as e:
        out[i] = e
def stream(i):
    try:
        with illuminet.open("synthetic://lamp?frames=6&size=160x100", timing="asap") as s:
            out[i] = [r.composite is not None for r in s]
    except Exception as e:
        out[i] = e
def run(*targets):
    ts = [threading.Thread(target=f, args=(i,)) for i, f in targets]
    [t.start() for t in ts]
    [t.join() for t in ts]
preview("first")
run(("worker", preview))
preview("main")
run((0, preview), (1, preview), (2, stream), (3, stream))
for i in ("first", "worker", "main", 0, 1):
    assert isinstance(out[i], np.ndarray) and out[i].shape == color.shape, (i, out[i])
    assert np.array_equal(out[i], out["first"]), i
assert out[2] == [True] * 6 and out[3] == [True] * 6, (out[2], out[3])
print("ok")
"""


@pytest.mark.gl
def test_render_preview_and_streams_draw_from_any_thread(gl_ctx):
    # the shared GL context stayed current on the thread that drew last: EGL would not make it current
    # on another, and every later draw there (the main thread after a worker, or two threads at once)
    # failed with moderngl's "cannot create texture"
    p = subprocess.run(
        [sys.executable, "-c", _ANY_THREAD], cwd=REPO, env=env(), capture_output=True, text=True, timeout=300
    )
    assert p.returncode == 0 and p.stdout.split() == ["ok"], p.stderr[-2000:]


def test_stream_closed_from_another_thread_waits_for_the_frame_in_progress():
    # close() from another thread (an app's stop button) closed the stages and sinks while next() was
    # still running them on the iterating thread: the rest of that frame ran on closed stages
    import threading
    import time

    from illuminet.commands.demo import DEFAULT_SESSION

    events: list[str] = []
    s = illuminet.open(f"replay://{DEFAULT_SESSION}", render=False, timing="asap", max_frames=20)
    with s:
        next(s)
        first = s.stages[0]
        process = first.process

        def slow(frame):
            events.append("frame started")
            closer.start()
            time.sleep(0.3)  # the other thread calls close() meanwhile
            out = process(frame)
            events.append("frame done")
            return out

        def close():
            s.close()
            events.append("closed")

        closer = threading.Thread(target=close)
        first.process = slow
        r = next(s)
        closer.join(10)
        assert events == ["frame started", "frame done", "closed"]
        assert r.frame.seq == 1 and r.estimate is not None
        with pytest.raises(StopIteration):  # closed from another thread: the loop reading it ends
            next(s)
        with pytest.raises(StreamClosed):  # and a new read says it is closed
            list(s)


def test_a_stream_left_open_is_closed_when_dropped_and_at_exit(tmp_path):
    # a stream never closed (a `for` without `with`, then a break) kept its sinks' threads running after
    # it was dropped, and at exit the video had no index (48 bytes, unplayable): close() never ran
    import gc
    import threading

    import av

    def frames_in(path):
        with av.open(str(path)) as c:
            return sum(1 for _ in c.decode(video=0))

    url = "synthetic://lamp?frames=20&size=160x100"
    s = illuminet.open(url, render=False, timing="asap", output__video=str(tmp_path / "gc.mp4"))
    for r in s:
        if r.frame.seq == 2:
            break
    del s, r
    gc.collect()
    assert not [t.name for t in threading.enumerate() if t.name.startswith("illuminet-")]
    assert frames_in(tmp_path / "gc.mp4") == 3
    code = (
        "import illuminet, sys\n"
        f"s = illuminet.open({url!r}, render=False, timing='asap', output__video=sys.argv[1])\n"
        "for r in s:\n"
        "    if r.frame.seq == 2:\n"
        "        break\n"
    )
    p = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "exit.mp4")], env=env(), capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert frames_in(tmp_path / "exit.mp4") == 3
