"""The compositor: the shaded, shadowed virtual object drawn into the camera picture on the GPU.

What this module owns
---------------------
* :class:`Compositor`: works on plain arrays (camera picture, depth, intrinsics, pose, irradiance
  per render vertex). Per frame it draws only the screen rectangle that the object and its shadow
  can touch, in five passes (one method each): the crop of the camera picture is uploaded and
  drawn, the shadow patch multiplies it in linear light, the object is drawn into its own layer
  (real geometry nearer than the object hides it), the layer is blended over the picture by its
  coverage, and the crop is read back and pasted into a copy of the picture.
* :func:`crop_projection`: the clip matrix of an OpenCV camera drawing one pixel rectangle.

Image orientation: the crop is rendered with image row 0 at GL row 0, so what glReadPixels returns
is already in image order (no flip on the CPU); triangle winding is therefore mirrored and face
culling stays off for open meshes (the depth test resolves visibility).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from illuminet.runtime.physics import srgb_to_linear
from illuminet.runtime.render.gl import check_gl, float_texture_dtype, is_gles, make_current, park, program
from illuminet.runtime.render.mesh import RenderMesh
from illuminet.runtime.render.nogil import gl_nogil
from illuminet.runtime.render.shaders import (
    BG_FS,
    BG_VS,
    ENCODE_LUT_SIZE,
    OBJ_FS_PLAIN,
    OBJ_FS_TEX,
    OBJ_VS_PLAIN,
    OBJ_VS_TEX,
    OVER_EDGE_FS,
    OVER_FS,
    decode_lut,
    encode_lut,
    with_transfer,
)
from illuminet.runtime.render.shadow import RECEIVER_FS, RECEIVER_VS, ShadowCaster

log = logging.getLogger(__name__)

#: anti-aliasing methods ([render] antialias): "edge" filters the object layer's silhouette (cheap),
#: "msaa" draws it multisampled ([render] msaa samples; llvmpipe pays ~2x the object's cost), "off"
ANTIALIAS = ("edge", "msaa", "off")


# -------------------------------------------------------------------------------------- projection


def crop_projection(K: np.ndarray, crop: tuple[int, int, int, int], near: float, far: float) -> np.ndarray:
    """4x4 clip matrix for an OpenCV pinhole camera drawing only the pixel rectangle ``crop``.

    ``crop = (x0, y0, w, h)`` in image pixels (row 0 at the top). Image row ``y0 + j`` lands on GL
    framebuffer row ``j``, so a read-back needs no flip. OpenCV's pixel centres are at integer
    coordinates, hence the half-pixel shift.
    """
    x0, y0, w, h = crop
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    a = (far + near) / (far - near)
    b = -2.0 * far * near / (far - near)
    return np.array(
        [
            [2.0 * fx / w, 0.0, 2.0 * (cx + 0.5 - x0) / w - 1.0, 0.0],
            [0.0, 2.0 * fy / h, 2.0 * (cy + 0.5 - y0) / h - 1.0, 0.0],
            [0.0, 0.0, a, b],
            [0.0, 0.0, 1.0, 0.0],
        ]
    )


def _strip(prog, vao) -> None:
    """``vao.render(TRIANGLE_STRIP)`` of a screen quad, without the GIL when possible (nogil.py)."""
    nogil = gl_nogil()
    if nogil is not None:
        nogil.draw_strip(prog.glo, vao.glo)
    else:
        import moderngl

        vao.render(moderngl.TRIANGLE_STRIP)


def _mat(m: np.ndarray) -> bytes:
    """numpy row-major 4x4 -> the column-major bytes GLSL's mat4 expects."""
    return np.ascontiguousarray(m.T, dtype=np.float32).tobytes()


# ------------------------------------------------------------------------------------- compositor


#: holes (0) in the real depth narrower than this (pixels) take the farthest depth around them
HOLE_FILL_PX = 7


def fill_holes(depth: np.ndarray) -> np.ndarray:
    """The crop's depth (float32, contiguous) with its narrow holes filled by the farthest valid depth
    within :data:`HOLE_FILL_PX`: a hole then takes the decision of the surface around it. Invalid depth
    counts as the plane in the shadow's plane test, so the holes of a real stereo camera's depth on the
    floor beyond a table's edge (3-6 % of the OAK-D recordings' pixels, clustered at edges) were
    speckled with the shadow the table plane received; the farthest, so that a hole never hides the
    object (occlusion needs nearer real depth) and a hole on the plane stays on it."""
    d = np.ascontiguousarray(depth, dtype=np.float32)
    holes = ~(d > 0)  # 0 and NaN
    if not holes.any():
        return d
    import cv2

    valid = np.where(holes, np.float32(0), d)
    far = cv2.dilate(valid, np.ones((HOLE_FILL_PX, HOLE_FILL_PX), np.uint8))
    return np.where(holes, far, d).astype(np.float32, copy=False)


@dataclass
class DrawInfo:
    """What the last :meth:`Compositor.draw` did (for stats and tests)."""

    crop: tuple[int, int, int, int] = (0, 0, 0, 0)
    drawn: bool = False
    shadow: bool = False
    light_dir: np.ndarray | None = None
    share: float = 0.0


@dataclass
class _Region:
    """Where one frame draws, in image pixels: the crop (object and shadow) and the object's rectangle."""

    crop: tuple[int, int, int, int]  # (x0, y0, w, h)
    obj: tuple[int, int, int, int] | None  # (x0, y0, w, h) of the object's bounding rectangle; None off screen
    near: float  # clip planes around everything drawn, metres
    far: float


class Compositor:
    """GPU renderer for one mesh: draws it, its shadow and the occlusion into camera pictures.

    Passes per frame, all inside the crop rectangle the object and its shadow can touch, one method
    each, called in order by :meth:`draw` (after :meth:`_upload_crop` has uploaded the crop):

    1. :meth:`_draw_background`: the crop of the camera picture (single-sampled);
    2. :meth:`_draw_shadow`: the shadow patch on the plane multiplies it in linear light (one lookup
       in the precomputed visibility texture, one in the contact map);
    3. :meth:`_draw_object`: the object, into its own (multisampled) layer over its bounding
       rectangle only (the most expensive buffer kept smallest), with fragments behind real
       geometry discarded or marked;
    4. :meth:`_draw_over`: the layer, resolved, blended over the picture by its coverage
       (anti-aliased edges, also against real occluders);
    5. :meth:`_read_back`: the crop is read back and pasted into the output.

    Parameters
    ----------
    ctx : moderngl.Context
        The shared GL context (:func:`illuminet.runtime.render.gl.get_context`).
    mesh : RenderMesh
        Object-frame geometry, already scaled.
    msaa : int
        Samples per pixel with ``antialias="msaa"`` (0 or 1 = off).
    shadow : bool
        Draw the shadow and contact shadow on the anchor plane.
    shadow_map : int
        Shadow-map resolution in pixels.
    occlusion : bool
        Let real geometry nearer than the object hide it.
    depth_tolerance_m : float
        How much nearer (metres at 1 m, growing with z^2 like stereo noise) real depth must be to
        hide the object or to stop the shadow.
    shadow_softness : float
        Penumbra radius as a fraction of the object's bounding radius.
    contact_shadow : float
        Strength of the contact shadow in [0, 1].
    response_lut : (256, 3) array, optional
        The camera's measured response (code -> linear); sRGB when None.
    antialias : {"edge", "msaa", "off"}
        How the object's edges are smoothed (see :data:`ANTIALIAS`).
    """

    def __init__(
        self,
        ctx,
        mesh: RenderMesh,
        msaa: int = 4,
        shadow: bool = True,
        shadow_map: int = 1024,
        occlusion: bool = True,
        depth_tolerance_m: float = 0.03,
        shadow_softness: float = 0.05,
        contact_shadow: float = 0.75,
        response_lut: np.ndarray | None = None,
        antialias: str = "edge",
    ):
        make_current(ctx)
        self.ctx = ctx
        self.mesh = mesh
        self._es = is_gles(ctx)  # OpenGL ES: GLSL 300 es, RGBA read-back (gl.py)
        if antialias not in ANTIALIAS:
            raise ValueError(f"[render] antialias: expected one of {', '.join(ANTIALIAS)}, got {antialias!r}")
        if msaa < 0 or msaa > 16:
            raise ValueError(f"[render] msaa: expected 0..16 samples, got {msaa}")
        self.msaa = min(int(msaa), int(ctx.max_samples)) if (msaa > 1 and antialias == "msaa") else 0
        self.antialias = antialias if (antialias != "msaa" or self.msaa) else "off"
        self.occlusion = bool(occlusion)
        self.depth_tol = float(depth_tolerance_m)
        self.contact = float(np.clip(contact_shadow, 0.0, 1.0))
        self.info = DrawInfo()
        #: step -> seconds, when set to a dict (benchmarks): each pass then waits for the GPU, which
        #: itself costs a little; None in normal use
        self.profile: dict[str, float] | None = None
        self.profile_clock = time.perf_counter  # time.process_time: CPU of all threads (llvmpipe's too)
        self._t_mark = 0.0
        self._cap = (0, 0)
        self._ocap = (0, 0)
        #: times the crop's framebuffers were made larger (a new largest crop): each is a high-water
        #: mark the process keeps (the GL driver's buffers are heap memory: ~20 MB at 1280x800)
        self.grows = 0
        self._fbos: dict[str, Any] = {}
        self._ofbos: dict[str, Any] = {}
        self._bbox = (mesh.vertices.min(axis=0).astype(float), mesh.vertices.max(axis=0).astype(float))

        custom = response_lut is not None
        self._upload_colour_tables(response_lut)
        self._upload_mesh(custom)
        self.shadow = (
            ShadowCaster(ctx, mesh.vertices, mesh.faces, shadow_map, shadow_softness, closed=bool(mesh.closed))
            if shadow
            else None
        )
        self._make_screen_programs(custom)
        check_gl(ctx, f"setting up the renderer for {mesh.source}")

    # -- set-up ------------------------------------------------------------------------------------
    def _upload_colour_tables(self, response_lut: np.ndarray | None) -> None:
        """The camera response (decode) and its inverse (encode) as 1-D textures."""
        import moderngl

        ctx = self.ctx
        self._dec_lut = ctx.texture((256, 1), 3, decode_lut(response_lut).tobytes(), dtype="f4")
        self._dec_lut.filter = (moderngl.NEAREST, moderngl.NEAREST)
        # sampled with LINEAR filtering: half floats where OpenGL ES cannot filter 32-bit ones
        dt, np_dt = float_texture_dtype(ctx)
        self._enc_lut = ctx.texture((ENCODE_LUT_SIZE, 1), 3, encode_lut(response_lut).astype(np_dt).tobytes(), dtype=dt)
        self._enc_lut.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._enc_lut.repeat_x = self._enc_lut.repeat_y = False

    def _upload_mesh(self, custom: bool) -> None:
        """Mesh buffers (static attributes once, irradiance rewritten per frame), the object
        programs (plain, and textured when a part has a texture) and the parts' textures."""
        import moderngl

        ctx, mesh = self.ctx, self.mesh
        n = mesh.n_vertices
        uv = mesh.uv if mesh.uv is not None else np.zeros((n, 2), np.float32)
        alb = srgb_to_linear(mesh.colors) if mesh.colors is not None else np.ones((n, 3), np.float32)
        static = np.concatenate([mesh.vertices, uv, alb], axis=1).astype(np.float32)
        self._vbo = ctx.buffer(static.tobytes())
        self._ibo = ctx.buffer(mesh.faces.astype(np.uint32).tobytes())
        self._irr = ctx.buffer(reserve=n * 12, dynamic=True)
        attrs = [(self._vbo, "3f 2f 3f", "in_pos", "in_uv", "in_albedo"), (self._irr, "3f", "in_irr")]
        self._obj_progs = {}
        for textured, (vs, fs) in ((False, (OBJ_VS_PLAIN, OBJ_FS_PLAIN)), (True, (OBJ_VS_TEX, OBJ_FS_TEX))):
            if textured and all(p.texture is None for p in mesh.parts):
                continue
            prog = program(ctx, with_transfer(vs, custom), with_transfer(fs, custom))
            # the plain program has no in_uv: moderngl skips attributes a program does not use
            self._obj_progs[textured] = (prog, ctx.vertex_array(prog, attrs, self._ibo, skip_errors=True))
        self._part_tex = []
        for p in mesh.parts:
            if p.texture is None:
                self._part_tex.append(None)
                continue
            img = np.ascontiguousarray(np.flipud(p.texture[:, :, :3]))  # UV origin is the image bottom
            t = ctx.texture((img.shape[1], img.shape[0]), 3, img.tobytes(), alignment=1)
            t.build_mipmaps()
            t.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            self._part_tex.append(t)

    def _make_screen_programs(self, custom: bool) -> None:
        """The full-screen passes' programs on one quad: background, layer-over-picture, shadow receiver."""
        ctx = self.ctx
        quad = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float32)
        self._quad = ctx.buffer(quad.tobytes())
        self._bg_prog = program(ctx, BG_VS, BG_FS)
        self._bg_vao = ctx.vertex_array(self._bg_prog, [(self._quad, "2f", "in_uv")])
        self._over_prog = program(ctx, BG_VS, OVER_EDGE_FS if self.antialias == "edge" else OVER_FS)
        self._over_vao = ctx.vertex_array(self._over_prog, [(self._quad, "2f", "in_uv")])
        if self.shadow is not None:
            self._rcv_prog = program(ctx, RECEIVER_VS, with_transfer(RECEIVER_FS, custom))
            self._rcv_vao = ctx.vertex_array(self._rcv_prog, [(self._quad, "2f", "in_uv")])

    # -- framebuffers sized to the largest crop seen so far ------------------------------------------
    @property
    def framebuffer_size(self) -> tuple[int, int]:
        """(width, height) of the crop's framebuffers now: the largest crop so far, rounded up."""
        return self._cap

    def _ensure_capacity(self, w: int, h: int, ow: int, oh: int) -> None:
        import moderngl

        ctx = self.ctx
        cw, ch = self._cap
        if w > cw or h > ch:
            cw, ch = max(cw, -(-w // 128) * 128), max(ch, -(-h // 128) * 128)
            self.grows += 1
            log.debug("render: the crop's framebuffers grow to %dx%d (a crop of %dx%d, the largest yet)", cw, ch, w, h)
            park(ctx)
            for obj in self._fbos.values():
                obj.release()
            f: dict[str, Any] = {}
            f["bg"] = ctx.texture((cw, ch), 3, alignment=1)
            f["bg"].filter = (moderngl.NEAREST, moderngl.NEAREST)
            f["depth_in"] = ctx.texture((cw, ch), 1, dtype="f4", alignment=1)
            f["depth_in"].filter = (moderngl.NEAREST, moderngl.NEAREST)
            f["color"] = ctx.renderbuffer((cw, ch), 4)
            f["main"] = ctx.framebuffer(color_attachments=[f["color"]])
            self._fbos = f
            self._cap = (cw, ch)
            # OpenGL ES reads back RGBA only (gl.read_pixels): the alpha is dropped on the CPU
            self._readbuf = np.empty(cw * ch * (4 if self._es else 3), dtype=np.uint8)
            self._zeros = np.zeros(cw * ch, dtype=np.float32)
        cw, ch = self._ocap
        if ow > cw or oh > ch:
            cw, ch = max(cw, -(-ow // 64) * 64), max(ch, -(-oh // 64) * 64)
            park(ctx)
            for obj in self._ofbos.values():
                obj.release()
            o: dict[str, Any] = {}
            o["layer"] = ctx.texture((cw, ch), 4)
            o["layer"].filter = (moderngl.NEAREST, moderngl.NEAREST)
            o["layer_fbo_depth"] = ctx.depth_renderbuffer((cw, ch))
            if self.msaa:
                o["ms_color"] = ctx.renderbuffer((cw, ch), 4, samples=self.msaa)
                o["ms_depth"] = ctx.depth_renderbuffer((cw, ch), samples=self.msaa)
                o["draw"] = ctx.framebuffer(color_attachments=[o["ms_color"]], depth_attachment=o["ms_depth"])
                o["resolve"] = ctx.framebuffer(color_attachments=[o["layer"]])
            else:
                o["draw"] = ctx.framebuffer(color_attachments=[o["layer"]], depth_attachment=o["layer_fbo_depth"])
            self._ofbos = o
            self._ocap = (cw, ch)

    # -- where to draw ---------------------------------------------------------------------------
    @staticmethod
    def _project_rect(K, cam_from_obj, pts, size):
        """Pixel rectangle (x0, y0, x1, y1) covering object-frame points (None: none in front), and their z."""
        p = np.asarray(pts, dtype=np.float64) @ cam_from_obj[:3, :3].T + cam_from_obj[:3, 3]
        z = p[:, 2]
        w, h = size
        if (z <= 1e-3).all():
            return None, z
        if (z <= 1e-3).any():  # straddles the camera plane: take everything, the clipper sorts it out
            return (0, 0, w, h), z
        u = K[0, 0] * p[:, 0] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
        x0, x1 = int(np.floor(max(u.min() - 1, 0))), int(np.ceil(min(u.max() + 2, w)))
        y0, y1 = int(np.floor(max(v.min() - 1, 0))), int(np.ceil(min(v.max() + 2, h)))
        if x1 <= x0 or y1 <= y0:
            return None, z
        return (x0, y0, x1, y1), z

    # -- one frame ---------------------------------------------------------------------------------
    def draw(
        self,
        color: np.ndarray,
        depth: np.ndarray | None,
        K: np.ndarray,
        cam_from_obj: np.ndarray,
        irradiance: np.ndarray,
        exposure_scale: float,
        light_dir: np.ndarray | None = None,
        share: float = 0.0,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Composite the object into ``color``; returns a new H x W x 3 uint8 RGB picture.

        Parameters
        ----------
        color : (H, W, 3) uint8
            Camera picture, RGB, encoded with the camera's response.
        depth : (H, W) float32 or None
            Metres aligned to ``color``, 0 = invalid; None disables occlusion and the plane test.
        K : (3, 3)
            Camera matrix of ``color``.
        cam_from_obj : (4, 4)
            Object frame -> camera (the anchor's ``T_cam_obj``, times the object scale if any).
        irradiance : (N, 3)
            Scene-referred linear irradiance per render-mesh vertex.
        exposure_scale : float
            Linear pixel = radiance x exposure_scale for this frame.
        light_dir : (3,) or None
            Unit direction towards the dominant light, object frame (None: no cast shadow).
        share : float
            Share of the light the dominant direction carries, [0, 1].
        out : (H, W, 3) uint8, optional
            Where to write the result (may be ``color`` itself); a copy of ``color`` when None.
        """
        irr = self._check_inputs(color, depth, irradiance, exposure_scale)
        make_current(self.ctx)
        self._t_mark = self.profile_clock()
        if out is None:
            out = color.copy()
        elif out is not color:
            np.copyto(out, color)

        sp = None
        if self.shadow is not None:
            self.shadow.update(light_dir, share)
            sp = self.shadow.params(light_dir, share)
        region = self._region(K, cam_from_obj, sp, color.shape[1], color.shape[0])
        self.info = DrawInfo(
            drawn=region is not None, shadow=bool(sp is not None and sp.use_shadow), light_dir=light_dir, share=share
        )
        if region is None:
            return out
        self.info.crop = region.crop

        self._upload_crop(color, depth, region)
        self._mark("setup")
        self._draw_background()
        self._mark("background")
        if sp is not None:
            self._draw_shadow(sp, K, cam_from_obj, region, has_depth=depth is not None)
        self._mark("shadow")
        if region.obj is not None:
            self._draw_object(K, cam_from_obj, irr, exposure_scale, region, has_depth=depth is not None)
            self._mark("object")
            self._draw_over(region)
        self._mark("over")
        self._read_back(out, region)
        self._mark("readback")
        check_gl(self.ctx, "drawing a frame")
        return out

    def _check_inputs(
        self, color: np.ndarray, depth: np.ndarray | None, irradiance: np.ndarray, exposure_scale: float
    ) -> np.ndarray:
        """Validate :meth:`draw`'s arrays; returns the irradiance as (N, 3) float32."""
        if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
            raise ValueError(f"color must be an HxWx3 uint8 RGB array, got {color.shape} {color.dtype}")
        irr = np.asarray(irradiance, dtype=np.float32)
        if irr.shape != (self.mesh.n_vertices, 3):
            raise ValueError(
                f"irradiance must have one RGB value per render-mesh vertex, shape ({self.mesh.n_vertices}, 3); "
                f"got {irr.shape}"
            )
        if not np.isfinite(irr).all():
            raise ValueError("irradiance contains NaN or infinity")
        if not (np.isfinite(exposure_scale) and exposure_scale >= 0):
            raise ValueError(f"exposure_scale must be a finite number >= 0, got {exposure_scale!r}")
        if depth is not None and depth.shape != color.shape[:2]:
            raise ValueError(f"depth {depth.shape} must be aligned to colour {color.shape[:2]}")
        return irr

    def _region(self, K: np.ndarray, cam_from_obj: np.ndarray, sp, wid: int, hgt: int) -> _Region | None:
        """The crop this frame draws in (object and shadow patch), or None when neither is in view."""
        lo, hi = self._bbox
        corners = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        orect, _ = self._project_rect(K, cam_from_obj, corners, (wid, hgt))
        pts = corners
        if sp is not None:
            pa = sp.draw_rect
            pts = corners + [[pa[0], 0, pa[1]], [pa[2], 0, pa[1]], [pa[0], 0, pa[3]], [pa[2], 0, pa[3]]]
        rect, z = self._project_rect(K, cam_from_obj, pts, (wid, hgt))
        if rect is None:
            return None
        x0, y0, x1, y1 = rect
        zpos = z[z > 1e-3]
        near = float(max(1e-3, 0.5 * zpos.min()))
        far = float(max(zpos.max() * 2.0, near * 10.0))
        obj = None
        if orect is not None:
            ox0, oy0, ox1, oy1 = orect
            obj = (ox0, oy0, ox1 - ox0, oy1 - oy0)
        return _Region(crop=(x0, y0, x1 - x0, y1 - y0), obj=obj, near=near, far=far)

    def _upload_crop(self, color: np.ndarray, depth: np.ndarray | None, region: _Region) -> None:
        """Setup: size the framebuffers, upload the crop's picture and depth, bind the main framebuffer."""
        import moderngl

        x0, y0, w, h = region.crop
        ow, oh = region.obj[2:] if region.obj is not None else (0, 0)
        self._ensure_capacity(w, h, max(ow, 1), max(oh, 1))
        f = self._fbos
        f["bg"].write(np.ascontiguousarray(color[y0 : y0 + h, x0 : x0 + w]), viewport=(0, 0, w, h))
        if depth is not None:
            f["depth_in"].write(fill_holes(depth[y0 : y0 + h, x0 : x0 + w]), viewport=(0, 0, w, h))
        else:
            f["depth_in"].write(self._zeros[: w * h], viewport=(0, 0, w, h))
        main = f["main"]
        main.use()
        main.viewport = (0, 0, w, h)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)

    def _draw_background(self) -> None:
        """Pass 1: the camera picture."""

        self._fbos["bg"].use(0)
        self._bg_prog["u_bg"].value = 0
        _strip(self._bg_prog, self._bg_vao)

    def _draw_shadow(self, sp, K: np.ndarray, cam_from_obj: np.ndarray, region: _Region, has_depth: bool) -> None:
        """Pass 2: the shadow patch multiplies the picture (reads the same picture, writes the darkened one)."""

        f = self._fbos
        clip = crop_projection(K, region.crop, region.near, region.far) @ cam_from_obj
        prog = self._rcv_prog
        units = (
            ("u_bg", f["bg"]),
            ("u_real_depth", f["depth_in"]),
            ("u_dec_lut", self._dec_lut),
            ("u_enc_lut", self._enc_lut),
            ("u_vis", self.shadow.vis_tex),
            ("u_ao", self.shadow.ao_tex),
        )
        for i, (name, tex) in enumerate(units):
            if name in prog:  # the LUTs are compiled out for the plain sRGB curve
                tex.use(i)
                prog[name].value = i
        prog["u_clip_from_obj"].write(_mat(clip))
        prog["u_cam_from_obj"].write(_mat(cam_from_obj))
        prog["u_patch"].value = tuple(float(x) for x in sp.patch)
        prog["u_draw"].value = tuple(float(x) for x in sp.draw_rect)
        prog["u_ao_rect"].value = tuple(float(x) for x in sp.ao_rect)
        prog["u_share"].value = sp.share
        prog["u_contact"].value = self.contact
        prog["u_depth_tol"].value = self.depth_tol if has_depth else 1e9
        _strip(prog, self._rcv_vao)

    def _draw_object(
        self,
        K: np.ndarray,
        cam_from_obj: np.ndarray,
        irr: np.ndarray,
        exposure_scale: float,
        region: _Region,
        has_depth: bool,
    ) -> None:
        """Pass 3: the object, into its own (multisampled) layer over its bounding rectangle."""
        import moderngl

        ctx = self.ctx
        x0, y0 = region.crop[:2]
        ox0, oy0, ow, oh = region.obj
        self._irr.write(irr.tobytes())
        layer = self._ofbos["draw"]
        layer.use()
        layer.viewport = (0, 0, ow, oh)
        layer.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=(0, 0, ow, oh))
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        if self.mesh.closed:
            # image row 0 on framebuffer row 0 mirrors the winding: outward faces turn clockwise
            ctx.front_face = "cw"
            ctx.cull_face = "back"
            ctx.enable(moderngl.CULL_FACE)
        self._fbos["depth_in"].use(1)
        self._enc_lut.use(3)
        oclip = crop_projection(K, region.obj, region.near, region.far) @ cam_from_obj
        common = {
            "u_tex": 0,
            "u_real_depth": 1,
            "u_enc_lut": 3,
            "u_offset": (ox0 - x0, oy0 - y0),
            "u_radiance_scale": float(exposure_scale) / np.pi,
            "u_occlusion": 1.0 if (self.occlusion and has_depth) else 0.0,
            "u_depth_tol": self.depth_tol,
            "u_mark_occluded": 1.0 if self.antialias == "edge" else 0.0,
        }
        for prog, _ in self._obj_progs.values():
            for name, value in common.items():
                if name in prog:  # unused uniforms are compiled out
                    prog[name].value = value
            prog["u_clip_from_obj"].write(_mat(oclip))
            prog["u_cam_from_obj"].write(_mat(cam_from_obj))
        # the draw itself without the GIL (runtime/render/nogil.py): llvmpipe transforms the object's
        # vertices in this thread, ~5 ms a frame that the pipelined loop's front thread can use
        nogil = gl_nogil()
        for part, tex in zip(self.mesh.parts, self._part_tex):
            prog, vao = self._obj_progs[tex is not None]
            if tex is not None:
                tex.use(0)
            prog["u_base"].value = tuple(float(x) for x in part.base_color[:3])
            if nogil is not None:
                nogil.draw_triangles(prog.glo, vao.glo, part.count, part.first)
            else:
                vao.render(moderngl.TRIANGLES, vertices=part.count, first=part.first)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.front_face = "ccw"
        if self.msaa:
            ctx.copy_framebuffer(self._ofbos["resolve"], layer)

    def _draw_over(self, region: _Region) -> None:
        """Pass 4: the object layer over the picture, weighted by its coverage (premultiplied alpha)."""
        import moderngl

        ctx = self.ctx
        x0, y0 = region.crop[:2]
        ox0, oy0, ow, oh = region.obj
        main = self._fbos["main"]
        main.use()
        main.viewport = (ox0 - x0, oy0 - y0, ow, oh)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        self._ofbos["layer"].use(0)
        self._over_prog["u_obj"].value = 0
        self._over_prog["u_offset"].value = (ox0 - x0, oy0 - y0)
        if "u_hi" in self._over_prog:
            self._over_prog["u_hi"].value = (ow - 1, oh - 1)
        _strip(self._over_prog, self._over_vao)
        ctx.disable(moderngl.BLEND)

    def _read_back(self, out: np.ndarray, region: _Region) -> None:
        """Pass 5: read the crop back (already in image row order) and paste it into ``out``."""
        x0, y0, w, h = region.crop
        nogil = gl_nogil()
        if nogil is not None:
            nogil.finish()  # wait for the rasteriser without the GIL; the read-back then only copies
        n = 4 if self._es else 3
        self._fbos["main"].read_into(self._readbuf, viewport=(0, 0, w, h), components=n, alignment=1)
        out[y0 : y0 + h, x0 : x0 + w] = self._readbuf[: w * h * n].reshape(h, w, n)[:, :, :3]

    def _mark(self, step: str) -> None:
        """With ``profile`` on: wait for the GPU and charge the time since the last mark to ``step``."""
        if self.profile is None:
            return
        self.ctx.finish()
        now = self.profile_clock()
        self.profile[step] = self.profile.get(step, 0.0) + now - self._t_mark
        self._t_mark = now

    def release(self) -> None:
        """Free every GPU object; safe to call twice."""
        if getattr(self, "_vbo", None) is not None:
            make_current(self.ctx)
            park(self.ctx)
        for obj in list(self._fbos.values()) + list(self._ofbos.values()):
            obj.release()
        self._fbos, self._ofbos = {}, {}
        self._cap = self._ocap = (0, 0)
        for t in getattr(self, "_part_tex", []):
            if t is not None:
                t.release()
        self._part_tex = []
        for prog, vao in getattr(self, "_obj_progs", {}).values():
            vao.release()
            prog.release()
        self._obj_progs = {}
        for name in (
            "_bg_vao",
            "_bg_prog",
            "_over_vao",
            "_over_prog",
            "_rcv_vao",
            "_rcv_prog",
            "_vbo",
            "_ibo",
            "_irr",
            "_quad",
            "_dec_lut",
            "_enc_lut",
        ):
            obj = getattr(self, name, None)
            if obj is not None:
                obj.release()
                setattr(self, name, None)
        if getattr(self, "shadow", None) is not None:
            self.shadow.release()
            self.shadow = None
