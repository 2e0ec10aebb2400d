"""The renderer on OpenGL ES 3.x through EGL (what embedded GPUs such as a Raspberry Pi 5's offer).

On Mesa (llvmpipe without a GPU) an ES 3.2 context is made beside the desktop GL one and the same
frames are drawn on both: the pictures must agree within a code value or two (on llvmpipe they are
identical). The slow tests (subprocesses; ``-m slow``, and .ci/run's second job) run the whole
render test module with ``ILLUMINET_GL_API=gles``, the demo on ES, and an ES 3.1 driver without
32-bit float filtering or float render targets (a Pi-like feature level, emulated with Mesa's
override variables), which must still draw the same picture.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from illuminet.runtime import config as C
from illuminet.runtime.render.gl import (
    GLES_HEADER,
    GLError,
    context_info,
    create_context,
    float_target_dtype,
    float_texture_dtype,
    glsl,
    is_gles,
    make_current,
)
from illuminet.runtime.render.stage import RenderStage

from .test_render import BG, camera_pose, directional_shading, make_frame, sphere_mesh

pytestmark = pytest.mark.gl

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def gles(gl_ctx):
    """An OpenGL ES context of its own beside the shared desktop one (skips where EGL has no ES 3)."""
    try:
        ctx = create_context(api="gles")
    except GLError as e:
        pytest.skip(f"no OpenGL ES 3.x context through EGL: {e}")
    yield ctx
    ctx.release()
    make_current(gl_ctx)


def _draw(ctx, response_lut=None, mesh=None, **render) -> np.ndarray:
    mesh = mesh if mesh is not None else sphere_mesh()
    cfg = C.apply_overrides(C.defaults(), [("render", k, v) for k, v in render.items()])
    st = RenderStage(cfg, mesh=mesh, ctx=ctx, response_lut=response_lut)
    st.open()
    try:
        T = camera_pose()
        f = st.process(make_frame(T, directional_shading(mesh, [-1.0, 1.0, 0.3])))
        return f.results["composite"].astype(int)
    finally:
        st.close()


def test_es_context_is_described_and_speaks_glsl_es(gles, gl):
    info = context_info(gles)
    assert info.api == "gles" and is_gles(gles) and not is_gles(gl)
    assert info.version.startswith("OpenGL ES 3.") and gles.version_code >= 300
    assert "OpenGL ES" in info.describe() and info.renderer in info.describe()
    src = "\n#version 330\nout vec4 c;\nvoid main() { c = vec4(1.0); }\n"
    assert glsl(gl, src) == src  # desktop GL: untouched
    es = glsl(gles, src)
    assert es.startswith(GLES_HEADER) and "#version 330" not in es
    with pytest.raises(ValueError, match="#version 330"):
        glsl(gles, "#version 450\nvoid main() {}\n")
    # llvmpipe filters and renders 32-bit floats on ES 3.2: the same formats as desktop GL
    assert float_texture_dtype(gles)[0] == "f4" and float_target_dtype(gles)[0] == "f4"
    assert gles.error == "GL_NO_ERROR"  # moderngl's desktop-only set-up leaves nothing behind


@pytest.mark.parametrize(
    "render",
    [{"antialias": "edge"}, {"antialias": "msaa"}, {"antialias": "off", "shadow": False}, {"lut": True}],
    ids=["edge", "msaa", "off-noshadow", "response-lut"],
)
def test_es_draws_the_same_picture_as_desktop_gl(gles, gl, render):
    render = dict(render)
    lut = None
    if render.pop("lut", False):  # a measured camera response: the LUT textures and shader path
        lut = np.stack([np.linspace(0.0, 1.0, 256) ** 2.0] * 3, axis=1).astype(np.float32)
    desk = _draw(gl, lut, **render)
    es = _draw(gles, lut, **render)
    assert gles.error == "GL_NO_ERROR"
    drawn = (np.abs(desk - BG) > 2).any(-1)
    assert drawn.sum() > 2000  # the sphere and its shadow are there
    diff = np.abs(desk - es)
    assert diff.max() <= 2, diff.max()
    assert (diff > 0).any(-1).sum() <= 0.01 * drawn.sum()


def test_es_textured_mesh_and_figure_views(gles, gl):
    """Textured parts (mipmapped RGB texture, the textured program) and the evaluation figure's views."""
    import trimesh

    from illuminet.models.figure import render_views
    from illuminet.runtime.render.mesh import RenderMesh

    s = trimesh.creation.box(extents=(0.15, 0.15, 0.15))
    s.apply_translation([0.0, 0.075, 0.0])
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[::8] = 255  # stripes
    uv = np.stack([s.vertices[:, 0] + 0.5, s.vertices[:, 1] + 0.5], 1)
    s.visual = trimesh.visual.TextureVisuals(uv=uv)
    mesh = RenderMesh.from_trimesh(s, texture=tex)
    assert any(p.texture is not None for p in mesh.parts)
    desk, es = _draw(gl, mesh=mesh), _draw(gles, mesh=mesh)
    assert np.abs(desk - es).max() <= 2
    v, f = mesh.vertices, mesh.faces
    cols = np.clip(v - v.min(0), 0, None) / np.ptp(v, axis=0)
    a = render_views(gl, v, f, cols, size=64)
    b = render_views(gles, v, f, cols, size=64)
    for x, y in zip(a, b):
        assert np.abs(x.astype(int) - y.astype(int)).max() <= 2


def _env(**extra) -> dict:
    env = dict(os.environ, **extra)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.mark.slow  # subprocesses (~10-25 s each); .ci/run's old-moderngl job runs them
def test_every_render_test_passes_on_gles():
    """tests/test_render.py on an ES context: the conftest's shared context follows ILLUMINET_GL_API."""
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "tests/test_render.py", "-q", "-rs", "-p", "no:cacheprovider", "-x"],
        cwd=REPO,
        env=_env(ILLUMINET_GL_API="gles"),
        capture_output=True,
        text=True,
        timeout=280,
    )
    tail = (r.stdout + r.stderr)[-3000:]
    assert r.returncode == 0, tail
    assert " passed" in tail, tail
    # the only skip allowed is a test on real captures where ../shared/data is absent (a fresh clone)
    skips = [ln for ln in tail.splitlines() if ln.startswith("SKIPPED")]
    assert all("shared data not found" in ln for ln in skips), tail


def _demo_png(tmp: Path, api: str, extra_env: dict | None = None) -> np.ndarray:
    out = tmp / api
    cmd = [sys.executable, "-m", "illuminet", "--set", f"render.gl_api={api}", "demo", "--frames", "2"]
    cmd += ["--no-video", "--png-dir", str(out), "--still", str(tmp / f"{api}.png"), "--strict"]
    cmd += ["--source", "synthetic://indoor?seed=0&frames=2&size=640x400"]
    r = subprocess.run(cmd, cwd=REPO, env=_env(**(extra_env or {})), capture_output=True, text=True, timeout=200)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    files = sorted(out.glob("*.png"))
    assert len(files) == 2
    return cv2.imread(str(files[-1])).astype(int)


@pytest.mark.slow  # subprocesses (~10-25 s each); .ci/run's old-moderngl job runs them
def test_demo_frames_on_gles_match_desktop_gl(tmp_path):
    desk = _demo_png(tmp_path, "gl")
    es = _demo_png(tmp_path, "gles")
    diff = np.abs(desk - es)
    assert diff.max() <= 2 and (diff > 0).any(-1).mean() < 0.001, (diff.max(), (diff > 0).any(-1).sum())


@pytest.mark.slow  # subprocesses (~10-25 s each); .ci/run's old-moderngl job runs them
def test_pi_like_es31_without_float32_filtering_or_targets(tmp_path):
    """ES 3.1, no GL_OES_texture_float_linear, no GL_EXT_color_buffer_float (Mesa overrides): the
    renderer takes half floats for the filtered tables and the contact map, and draws the same."""
    code = (
        "import numpy as np, sys\n"
        "from tests.test_render_gles import _draw\n"
        "from illuminet.runtime.render.gl import create_context, float_texture_dtype, float_target_dtype\n"
        "ctx = create_context(api=sys.argv[1])\n"
        "lut = np.stack([np.linspace(0.0, 1.0, 256) ** 2.0] * 3, axis=1).astype(np.float32)\n"
        "print(ctx.version_code, float_texture_dtype(ctx)[0], float_target_dtype(ctx)[0])\n"
        "np.save(sys.argv[2], np.stack([_draw(ctx, lut), _draw(ctx, None, antialias='msaa')]))\n"
    )
    pi_env = {
        "MESA_GLES_VERSION_OVERRIDE": "3.1",
        "MESA_EXTENSION_OVERRIDE": "-GL_OES_texture_float_linear -GL_EXT_color_buffer_float",
    }
    outs = {}
    for api, env in (("gl", {}), ("gles", pi_env)):
        path = tmp_path / f"{api}.npy"
        r = subprocess.run(
            [sys.executable, "-c", code, api, str(path)],
            cwd=REPO,
            env=_env(**env),
            capture_output=True,
            text=True,
            timeout=200,
        )
        assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
        outs[api] = (r.stdout.split("\n")[-2], np.load(path).astype(int))
    assert outs["gles"][0] == "310 f2 f2", outs["gles"][0]  # the emulated feature level took the half-float path
    diff = np.abs(outs["gl"][1] - outs["gles"][1])
    assert diff.max() <= 2, diff.max()
    assert (diff > 0).any(-1).sum() < 500
