"""Evaluation figure: per-vertex colour rasterisation of the object with moderngl (EGL, headless).

A deliberately simple renderer of this module's own (the compositing renderer draws into camera
frames; here each method's per-vertex intensities are shown as-is): orthographic views of the
object from the front (+Z) and the back (-Z), colours interpolated across triangles, no lighting
of its own. Rows: front / back; columns: ground truth, each baseline, ours.
"""

from __future__ import annotations

import os

import numpy as np

from illuminet.runtime.physics import linear_to_srgb8

_VS = """
#version 330
uniform mat4 mvp;
in vec3 in_pos;
in vec3 in_col;
out vec3 v_col;
void main() { gl_Position = mvp * vec4(in_pos, 1.0); v_col = in_col; }
"""
_FS = """
#version 330
in vec3 v_col;
out vec4 f_col;
void main() { f_col = vec4(v_col, 1.0); }
"""


def _ortho(vertices: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # rotate the object about +Y
    v = vertices @ R.T
    lo, hi = v.min(0), v.max(0)
    ctr = (lo + hi) / 2
    half = max(hi[0] - lo[0], hi[1] - lo[1]) / 2 * 1.1
    depth = max(hi[2] - lo[2], 1e-3)
    M = np.eye(4)
    M[:3, :3] = R
    P = np.diag([1 / half, 1 / half, -1 / depth, 1.0])
    T = np.eye(4)
    T[:3, 3] = -ctr
    return (P @ T @ M).astype("f4")


def render_views(ctx, vertices, faces, colors_linear, size: int = 160) -> list[np.ndarray]:
    """[front, back] RGB uint8 images of a mesh with per-vertex linear colours in [0, 1]."""
    from illuminet.runtime.render.gl import make_current, park, program, read_pixels

    make_current(ctx)  # another context may have been used since
    prog = program(ctx, _VS, _FS)  # GLSL 330, or 300 es on an OpenGL ES context
    srgb = linear_to_srgb8(np.clip(colors_linear, 0, 1)).astype("f4") / 255.0
    data = np.concatenate([vertices.astype("f4"), srgb], 1)
    vbo = ctx.buffer(data.tobytes())
    ibo = ctx.buffer(np.asarray(faces, dtype="i4").tobytes())
    vao = ctx.vertex_array(prog, [(vbo, "3f 3f", "in_pos", "in_col")], index_buffer=ibo)
    fbo = ctx.framebuffer(
        color_attachments=[ctx.renderbuffer((size, size))], depth_attachment=ctx.depth_renderbuffer((size, size))
    )
    out = []
    try:
        for yaw in (0.0, np.pi):
            fbo.use()
            ctx.enable(ctx.DEPTH_TEST)
            fbo.clear(0.25, 0.25, 0.25, 1.0)
            prog["mvp"].write(_ortho(vertices, yaw).T.copy().tobytes())
            vao.render()
            out.append(read_pixels(fbo, 3)[::-1].copy())
    finally:
        park(ctx)  # never release the bound framebuffer (gl.park): the context may be the renderer's
        for o in (vao, vbo, ibo, fbo, prog):
            o.release()
    return out


def figure(path, vertices, faces, panels: list[tuple[str, np.ndarray]], title: str = "", size: int = 160) -> str:
    """Write a PNG grid: one column per (label, linear intensities (R, 3)), rows front / back."""
    import cv2

    from illuminet.runtime.render.gl import create_context

    # a context of its own (released below), desktop GL or OpenGL ES as the renderer would choose
    ctx = create_context("egl", api=os.environ.get("ILLUMINET_GL_API", "auto"))
    try:
        cols = []
        for label, colors in panels:
            front, back = render_views(ctx, vertices, faces, colors, size)
            head = np.full((24, size, 3), 255, np.uint8)
            cv2.putText(head, label[:22], (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
            cols.append(np.concatenate([head, front, back], 0))
        img = np.concatenate(cols, 1)
        if title:
            bar = np.full((26, img.shape[1], 3), 255, np.uint8)
            cv2.putText(bar, title, (4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
            img = np.concatenate([bar, img], 0)
        cv2.imwrite(str(path), img[..., ::-1])
    finally:
        ctx.release()
    return str(path)
