"""The virtual object's shadow on the anchor plane (paper §3.4): dominant light, shadow map, contact shadow.

What this module owns
---------------------
* :func:`dominant_light`: the direction *towards* the dominant light and the share of the light it
  carries, from the object's predicted shading (its ``dominant_dir`` when the predictor gives one,
  else the irradiance-weighted mean of its OI vectors, else a first-order fit of irradiance against
  the vertex normals).
* :class:`ShadowCaster`: the GPU side. A depth **shadow map** of the object seen from the dominant
  light (orthographic: the light is distant) and, from it, the **visible fraction** of that light
  over the plane patch under the object (16-tap Poisson PCF into a small texture in plane
  coordinates), both redrawn only when the direction moves by more than
  :attr:`ShadowCaster.REDRAW_DEG`; a **contact map** (ambient-occlusion-like darkening under the
  object's base), computed once per mesh from a height map of the object's underside seen from
  below. The **receiver program** (:data:`RECEIVER_VS` / :data:`RECEIVER_FS`, drawn by the
  compositor, :mod:`illuminet.runtime.render.compositor`) looks both up per pixel and multiplies
  the camera picture by

      f = share * visible_fraction(PCF) + (1 - share) * (1 - contact_strength * ao)

  in linear light. With share = 1 (one hard sun) only the cast shadow darkens; with share = 0 (fully
  diffuse light) only the contact shadow remains; the mix follows the physics of the plane's
  irradiance (direct part times visibility plus ambient part times its occlusion).

Frames: everything here is in the object frame (origin on the plane, +Y up), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from illuminet.runtime.render.gl import (
    depth_texture,
    float_target_dtype,
    float_texture_dtype,
    make_current,
    park,
    program,
    read_pixels,
)
from illuminet.runtime.render.nogil import gl_nogil
from illuminet.runtime.scene import ObjectShading

#: Rec.709 luminance weights: the light's "amount" when colours must be summed to one number
LUMA = np.array([0.2126, 0.7152, 0.0722])

#: lights lower than this (sine of elevation) cast no shadow: it would be infinitely long and faint
MIN_ELEVATION_SIN = 0.08


def dominant_light(
    shading: ObjectShading,
    normals: np.ndarray | None = None,
    irradiance: np.ndarray | None = None,
) -> tuple[np.ndarray | None, float]:
    """Direction towards the dominant light (object frame) and the share of light it carries.

    Parameters
    ----------
    shading : ObjectShading
        The predicted shading. Used in order of preference: ``dominant_dir``/``dominant_share`` when
        given; else the OI (``oi``, (V,3,3)): direction = normalised sum of the vertices' luminance
        OI vectors, share = |sum| / sum of |vectors| (1 when all vertices see one direction, ~0 for
        uniform ambient light, whose OI vectors follow the normals and cancel).
    normals, irradiance : (V, 3) arrays, optional
        Vertex normals and per-vertex irradiance on the same vertices (e.g. the render mesh after
        carrying), used when neither of the above is present: a least-squares fit
        E(n) = a + b . n of luminance irradiance. For a directional light of irradiance I plus
        uniform ambient A this gives b = I/2 d and a = A + I/4 (first spherical-harmonic band of
        the clamped cosine), hence d = b/|b| and the share on an upward plane
        I d_y / (I d_y + A).

    Returns
    -------
    (direction, share) : ((3,) unit array or None, float in [0, 1])
        ``None`` and 0 when no direction can be told (e.g. constant shading).
    """
    d = shading.dominant_dir
    if d is not None:
        d = np.asarray(d, dtype=np.float64).reshape(3)
        n = np.linalg.norm(d)
        if np.isfinite(n) and n > 1e-9:
            return d / n, float(np.clip(shading.dominant_share, 0.0, 1.0))
    if shading.oi is not None:
        oi = np.asarray(shading.oi, dtype=np.float64)
        if oi.ndim == 3 and oi.shape[1:] == (3, 3) and len(oi):
            lv = np.einsum("vcx,c->vx", oi, LUMA)
            s = lv.sum(axis=0)
            total = np.linalg.norm(lv, axis=1).sum()
            ns = np.linalg.norm(s)
            if total > 1e-12 and ns > 1e-12:
                return s / ns, float(np.clip(ns / total, 0.0, 1.0))
    if normals is not None and irradiance is not None and len(normals) >= 4:
        e = np.asarray(irradiance, dtype=np.float64) @ LUMA
        a_mat = np.concatenate([np.ones((len(e), 1)), np.asarray(normals, dtype=np.float64)], axis=1)
        coef, *_ = np.linalg.lstsq(a_mat, e, rcond=None)
        a, b = coef[0], coef[1:]
        nb = np.linalg.norm(b)
        if nb > 1e-9 and np.isfinite(nb):
            d = b / nb
            direct = 2.0 * nb * max(d[1], 0.0)
            ambient = max(a - 0.5 * nb, 0.0)
            share = direct / (direct + ambient) if direct + ambient > 1e-12 else 0.0
            return d, float(np.clip(share, 0.0, 1.0))
    return None, 0.0


def look_at_ortho(direction: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """4x4 matrix taking object-frame points to the clip space of an orthographic light camera.

    The camera sits ``2 radius`` from ``center`` towards ``direction``, looks back along
    ``-direction``, and its box covers the sphere (``center``, ``radius``): depth 0 at the near side
    of the sphere, 1 at ``4 radius`` (points beyond clamp to 1 in the receiver shader).
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    fwd = -d
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.95 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    eye = np.asarray(center, dtype=np.float64) + d * 2.0 * radius
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, up, -fwd
    view[:3, 3] = -view[:3, :3] @ eye
    near, far = radius, 5.0 * radius
    proj = np.diag([1.0 / radius, 1.0 / radius, -2.0 / (far - near), 1.0])
    proj[2, 3] = -(far + near) / (far - near)
    return proj @ view


def shadow_patch(
    direction: np.ndarray | None,
    bbox_min: np.ndarray,
    bbox_max: np.ndarray,
    margin: float,
    max_length: float,
) -> np.ndarray:
    """Rectangle (xmin, zmin, xmax, zmax) on the plane y = 0 that holds the shadow and contact shadow.

    The object's bounding-box corners are projected along ``-direction`` onto the plane; the result
    is the union with the footprint, grown by ``margin`` and limited to ``max_length`` from the
    object's centre (long low-sun shadows are clipped, they fade anyway).
    """
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pts = [corners[:, [0, 2]]]
    if direction is not None and direction[1] > MIN_ELEVATION_SIN:
        t = corners[:, 1] / direction[1]
        proj = corners - t[:, None] * direction[None, :]
        pts.append(proj[:, [0, 2]])
    p = np.concatenate(pts)
    c = 0.5 * (lo[[0, 2]] + hi[[0, 2]])
    p = c + np.clip(p - c, -max_length, max_length)
    return np.array([p[:, 0].min() - margin, p[:, 1].min() - margin, p[:, 0].max() + margin, p[:, 1].max() + margin])


# ---------------------------------------------------------------------------------------- GPU side

_DEPTH_VS = """
#version 330
uniform mat4 u_mvp;
in vec3 in_pos;
void main() { gl_Position = u_mvp * vec4(in_pos, 1.0); }
"""
_DEPTH_FS = """
#version 330
void main() {}
"""

# height of the object's underside above the plane, seen from below (for the contact shadow)
_HEIGHT_VS = """
#version 330
uniform vec4 u_rect;   // xmin, zmin, xmax, zmax of the map on the plane
uniform float u_hmax;  // heights are stored up to this (metres)
in vec3 in_pos;
out float v_h;
void main() {
    vec2 uv = (in_pos.xz - u_rect.xy) / (u_rect.zw - u_rect.xy);
    v_h = in_pos.y;
    gl_Position = vec4(uv * 2.0 - 1.0, clamp(in_pos.y / u_hmax, 0.0, 1.0) * 2.0 - 1.0, 1.0);
}
"""
_HEIGHT_FS = """
#version 330
in float v_h;
out float f_h;
void main() { f_h = v_h; }
"""

#: GLSL for the receiver: the plane patch multiplies the camera picture (included by render.py's
#: compositing pass, which owns the background and colour-encoding uniforms)
RECEIVER_VS = """
#version 330
uniform mat4 u_clip_from_obj;  // object frame -> crop clip space
uniform mat4 u_cam_from_obj;   // object frame -> camera (metres)
uniform vec4 u_draw;           // xmin, zmin, xmax, zmax on the plane y = 0 to draw
in vec2 in_uv;                 // unit quad
out vec3 v_obj;
out float v_zcam;
void main() {
    vec3 p = vec3(mix(u_draw.x, u_draw.z, in_uv.x), 0.0, mix(u_draw.y, u_draw.w, in_uv.y));
    v_obj = p;
    v_zcam = (u_cam_from_obj * vec4(p, 1.0)).z;
    gl_Position = u_clip_from_obj * vec4(p, 1.0);
}
"""

RECEIVER_FS = """
#version 330
uniform sampler2D u_bg;            // camera picture crop, sRGB-encoded
uniform sampler2D u_real_depth;    // frame depth crop, metres, 0 = invalid
uniform sampler2D u_dec_lut;       // 256 x 1: code value -> linear, per channel
uniform sampler2D u_enc_lut;       // N x 1: linear -> code value / 255, per channel
uniform sampler2D u_vis;           // visible fraction of the dominant light over the patch (precomputed)
uniform sampler2D u_ao;            // contact occlusion on the plane, 0..1
uniform vec4 u_patch;
uniform vec4 u_ao_rect;
uniform float u_share;             // share of the light the dominant direction carries
uniform float u_contact;           // contact shadow strength
uniform float u_depth_tol;         // metres at 1 m; grows with z^2 like stereo noise
in vec3 v_obj;
in float v_zcam;
out vec4 f_color;

//DECODE//
//ENCODE//

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float d = texelFetch(u_real_depth, px, 0).r;
    // the shadow lands only where the real surface is the plane: not on things in front of it,
    // not past its edge (where the real depth is farther); invalid depth (0) counts as plane
    float tol = u_depth_tol * max(v_zcam * v_zcam, 1.0);
    if (d > 0.0 && abs(d - v_zcam) > tol) discard;
    float visible = texture(u_vis, (v_obj.xz - u_patch.xy) / (u_patch.zw - u_patch.xy)).r;
    vec2 auv = (v_obj.xz - u_ao_rect.xy) / (u_ao_rect.zw - u_ao_rect.xy);
    float ao = texture(u_ao, auv).r;
    float f = u_share * visible + (1.0 - u_share) * (1.0 - u_contact * ao);
    f = min(f, 1.0 - u_contact * 0.6 * ao);  // the contact shadow stays visible under a hard light
    if (f > 0.998) discard;                  // nothing to darken: keep the picture bit-exact
    vec3 bg = decode(texelFetch(u_bg, px, 0).rgb);
    f_color = vec4(encode(bg * f), 1.0);
}
"""

# visible fraction of the dominant light on the plane patch, drawn once per light direction into a
# small texture in plane coordinates, so the per-frame receiver needs one lookup instead of a PCF
_VIS_VS = """
#version 330
uniform vec4 u_patch;
in vec2 in_uv;
out vec3 v_obj;
void main() {
    v_obj = vec3(mix(u_patch.x, u_patch.z, in_uv.x), 0.0, mix(u_patch.y, u_patch.w, in_uv.y));
    gl_Position = vec4(in_uv * 2.0 - 1.0, 0.0, 1.0);
}
"""
_VIS_FS = """
#version 330
uniform sampler2DShadow u_shadow;  // object depth seen from the dominant light
uniform mat4 u_light_from_obj;
uniform float u_softness;          // PCF radius in shadow-map uv units
in vec3 v_obj;
out float f_vis;
const vec2 POISSON[16] = vec2[](
    vec2(-0.942, -0.399), vec2(0.946, -0.769), vec2(-0.094, -0.929), vec2(0.345, 0.294),
    vec2(-0.916, 0.458), vec2(-0.815, -0.879), vec2(-0.383, 0.277), vec2(0.975, 0.756),
    vec2(0.443, -0.975), vec2(0.537, -0.474), vec2(-0.265, -0.419), vec2(0.792, 0.191),
    vec2(-0.242, 0.997), vec2(-0.814, 0.914), vec2(0.200, 0.786), vec2(0.144, -0.141));
void main() {
    vec4 lc = u_light_from_obj * vec4(v_obj, 1.0);
    vec3 l = lc.xyz * 0.5 + 0.5;
    l.z = min(l.z, 1.0) - 0.002;
    float s = 0.0;
    for (int i = 0; i < 16; ++i) {
        vec2 q = l.xy + POISSON[i] * u_softness;
        // outside the light's box there is no object: lit
        s += (all(greaterThan(q, vec2(0.0))) && all(lessThan(q, vec2(1.0)))) ? texture(u_shadow, vec3(q, l.z)) : 1.0;
    }
    f_vis = s / 16.0;
}
"""


@dataclass
class ShadowParams:
    """Receiver inputs for one frame, from :meth:`ShadowCaster.params`."""

    share: float
    use_shadow: bool
    patch: np.ndarray  # xmin, zmin, xmax, zmax on the plane: where the visibility texture lies
    ao_rect: np.ndarray  # the contact map's rectangle on the plane
    draw_rect: np.ndarray  # the part of the plane the receiver must draw (darkened at all)


class ShadowCaster:
    """Shadow map and contact map of one mesh; hands the receiver pass its textures and uniforms.

    Parameters
    ----------
    ctx : moderngl.Context
        The shared GL context (:func:`illuminet.runtime.render.gl.get_context`).
    vertices : (N, 3) float array
        Object-frame vertices, already scaled (metres).
    faces : (F, 3) int array
    size : int
        Shadow map resolution ([render] shadow_map).
    softness : float
        Penumbra radius as a fraction of the object's bounding radius.
    vis_size : int
        Resolution of the precomputed visibility texture over the shadow patch.
    closed : bool
        The mesh is watertight and outward-facing: the shadow pass draws only its back faces
        (half the triangles, and no self-shadow acne on the lit side).
    """

    #: contact strength the visible extent of the contact shadow is judged at (1 = full strength)
    CONTACT_VISIBLE_SCALE = 1.0

    #: the shadow is redrawn when the light direction moves more than this (degrees); the stage
    #: smooths the direction, so a still light redraws nothing and a turning one every few frames
    REDRAW_DEG = 1.0

    def __init__(
        self,
        ctx,
        vertices: np.ndarray,
        faces: np.ndarray,
        size: int = 1024,
        softness: float = 0.05,
        vis_size: int = 160,
        closed: bool = False,
    ):
        import moderngl

        if size < 16 or size > 8192:
            raise ValueError(f"[render] shadow_map: expected 16..8192 pixels, got {size}")
        make_current(ctx)
        self.ctx = ctx
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32)
        self.bbox_min, self.bbox_max = v.min(axis=0).astype(float), v.max(axis=0).astype(float)
        self.center = 0.5 * (self.bbox_min + self.bbox_max)
        self.radius = float(max(np.linalg.norm(v - self.center, axis=1).max(), 1e-4))
        self.softness = float(softness)
        self._soft: float | None = None  # the penumbra the visibility was last drawn with
        self.closed = bool(closed)
        self.size = int(size)
        self.redraws = 0
        self._dir: np.ndarray | None = None
        self._light_from_obj = np.eye(4)

        self._vbo = ctx.buffer(v.tobytes())
        self._ibo = ctx.buffer(f.tobytes())
        self._n_indices = int(f.size)
        self._depth_prog = program(ctx, _DEPTH_VS, _DEPTH_FS)
        self._depth_vao = ctx.vertex_array(self._depth_prog, [(self._vbo, "3f", "in_pos")], self._ibo)
        self.shadow_tex = depth_texture(ctx, (self.size, self.size))
        self.shadow_tex.compare_func = "<="
        self.shadow_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.shadow_tex.repeat_x = self.shadow_tex.repeat_y = False
        self._shadow_fbo = ctx.framebuffer(depth_attachment=self.shadow_tex)

        quad = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float32)
        self._quad = ctx.buffer(quad.tobytes())
        self._vis_prog = program(ctx, _VIS_VS, _VIS_FS)
        self._vis_vao = ctx.vertex_array(self._vis_prog, [(self._quad, "2f", "in_uv")])
        self.vis_tex = ctx.texture((vis_size, vis_size), 1, dtype="f1")
        self.vis_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.vis_tex.repeat_x = self.vis_tex.repeat_y = False
        self._vis_fbo = ctx.framebuffer(color_attachments=[self.vis_tex])
        self._vis_fbo.use()
        self._vis_fbo.clear(red=1.0)  # fully lit until a light direction is known
        self.ao_tex, self.ao_rect = self._contact_map(v, f)
        self.patch = self._patch(None)
        self.cast_rect: np.ndarray | None = None

    # -- contact shadow ---------------------------------------------------------------------------
    def _contact_map(self, v: np.ndarray, f: np.ndarray, res: int = 128):
        """Darkening under the base: height of the underside seen from below, turned into occlusion.

        A plane point is occluded in proportion to how low the object hangs over its neighbourhood:
        w = (1 - h / h0)^2 over the footprint, then a Gaussian blur spreads it outwards (the soft
        halo an object leaves where it stands). Independent of the light, so computed once.
        """
        import cv2
        import moderngl

        ctx = self.ctx
        height = float(self.bbox_max[1] - max(self.bbox_min[1], 0.0))
        foot = max(self.bbox_max[0] - self.bbox_min[0], self.bbox_max[2] - self.bbox_min[2])
        # undersides higher than h0 leave no contact shadow; the halo reaches about 2 sigma past
        # the footprint, enough to show beyond a bulging body (a vase hides its own base)
        h0 = 0.5 * max(height, 1e-3)
        sigma_m = 0.10 * foot + 0.04 * height
        margin = 3.0 * sigma_m
        rect = np.array(
            [self.bbox_min[0] - margin, self.bbox_min[2] - margin, self.bbox_max[0] + margin, self.bbox_max[2] + margin]
        )
        hmax = float(self.bbox_max[1]) + 1e-3
        tgt_dt, _ = float_target_dtype(ctx)  # half floats where OpenGL ES cannot render into 32-bit
        tex = ctx.texture((res, res), 1, dtype=tgt_dt)
        depth = ctx.depth_renderbuffer((res, res))
        fbo = ctx.framebuffer(color_attachments=[tex], depth_attachment=depth)
        prog = program(ctx, _HEIGHT_VS, _HEIGHT_FS)
        vao = ctx.vertex_array(prog, [(self._vbo, "3f", "in_pos")], self._ibo)
        prog["u_rect"].value = tuple(float(x) for x in rect)
        prog["u_hmax"].value = hmax
        fbo.use()
        fbo.viewport = (0, 0, res, res)
        fbo.clear(red=6e4, depth=1.0)  # "nothing above": far higher than any object (and < the f2 maximum)
        ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        vao.render(moderngl.TRIANGLES)
        ctx.disable(moderngl.DEPTH_TEST)
        h = read_pixels(fbo, 1, tgt_dt)[:, :, 0].astype(np.float32)
        park(ctx)
        for obj in (vao, prog, fbo, depth, tex):
            obj.release()
        h = np.maximum(h, 0.0)
        w = np.clip(1.0 - h / h0, 0.0, 1.0) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma_px = float(sigma_m / ((rect[2] - rect[0]) / res))
        if not np.isfinite(sigma_px):  # a degenerate (zero-size) mesh: a one-pixel blur, not an OpenCV error
            sigma_px = 0.5
        ao = cv2.GaussianBlur(w.astype(np.float32), (0, 0), sigmaX=min(max(sigma_px, 0.5), res))
        # normalise so that the middle of a broad base is fully occluded
        peak = float(ao.max())
        if peak > 1e-6:
            ao = np.clip(ao / max(peak, 0.5), 0.0, 1.0)
        ao[[0, -1], :] = 0.0  # the edges of the map clamp outwards: keep them at zero
        ao[:, [0, -1]] = 0.0
        # the receiver draws only where the darkening is visible at all (the blur's far tail is not)
        rows, cols = np.nonzero(ao * self.CONTACT_VISIBLE_SCALE > 0.01)
        sx, sz = (rect[2] - rect[0]) / res, (rect[3] - rect[1]) / res
        if len(rows):
            self.ao_draw_rect = np.array(
                [
                    rect[0] + (cols.min() - 1) * sx,
                    rect[1] + (rows.min() - 1) * sz,
                    rect[0] + (cols.max() + 2) * sx,
                    rect[1] + (rows.max() + 2) * sz,
                ]
            )
        else:
            self.ao_draw_rect = np.array([self.center[0], self.center[2], self.center[0], self.center[2]])
        dt, np_dt = float_texture_dtype(ctx)  # sampled with LINEAR filtering
        ao_tex = ctx.texture((res, res), 1, ao.astype(np_dt).tobytes(), dtype=dt)
        ao_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        ao_tex.repeat_x = ao_tex.repeat_y = False
        self.contact_peak = peak
        return ao_tex, rect

    def _patch(self, direction: np.ndarray | None) -> np.ndarray:
        height = self.bbox_max[1] - min(self.bbox_min[1], 0.0)
        use = direction is not None and direction[1] > MIN_ELEVATION_SIN
        p = shadow_patch(
            direction if use else None,
            self.bbox_min,
            self.bbox_max,
            margin=0.15 * self.radius,
            max_length=6.0 * max(height, self.radius),
        )
        return np.array(
            [
                min(p[0], self.ao_rect[0]),
                min(p[1], self.ao_rect[1]),
                max(p[2], self.ao_rect[2]),
                max(p[3], self.ao_rect[3]),
            ]
        )

    # -- cast shadow -------------------------------------------------------------------------------
    def penumbra(self, share: float | None) -> float:
        """PCF radius (fraction of the object's radius) for a primary light carrying ``share``.

        A light that dominates (a sun, a bare bulb close by) casts a crisp shadow; as the ambient
        part grows the visible edge softens (the shadow is the primary's only, and the ambient fills
        it in unevenly): up to 4x the base penumbra at share 0.
        """
        if share is None:
            return self.softness
        return self.softness * (1.0 + 3.0 * (1.0 - float(np.clip(share, 0.0, 1.0))))

    def update(self, direction: np.ndarray | None, share: float | None = None) -> bool:
        """Redraw the shadow map and the patch's visibility when the light moved (or its penumbra,
        which follows the primary light's share, changed by a quarter); True when redrawn."""
        import moderngl

        if direction is None or direction[1] <= MIN_ELEVATION_SIN:
            return False
        d = np.asarray(direction, dtype=np.float64)
        soft = self.penumbra(share)
        same_soft = self._soft is not None and abs(soft - self._soft) <= 0.25 * self._soft
        if self._dir is not None and same_soft and float(np.dot(self._dir, d)) > np.cos(np.radians(self.REDRAW_DEG)):
            return False
        self._dir = d.copy()
        self._soft = soft
        self._light_from_obj = look_at_ortho(d, self.center, self.radius)
        self.patch = self._patch(d)
        ctx = self.ctx
        self._shadow_fbo.use()
        self._shadow_fbo.viewport = (0, 0, self.size, self.size)
        self._shadow_fbo.clear(depth=1.0)
        ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        if self.closed:
            ctx.front_face = "ccw"
            ctx.cull_face = "front"
            ctx.enable(moderngl.CULL_FACE)
        self._depth_prog["u_mvp"].write(self._light_from_obj.T.astype(np.float32).tobytes())
        nogil = gl_nogil()  # the mesh's draw without the GIL when possible (runtime/render/nogil.py)
        if nogil is not None:
            nogil.draw_triangles(self._depth_prog.glo, self._depth_vao.glo, self._n_indices, 0)
        else:
            self._depth_vao.render(moderngl.TRIANGLES)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.cull_face = "back"

        self._vis_fbo.use()
        self._vis_fbo.viewport = (0, 0) + self.vis_tex.size
        self.shadow_tex.use(0)
        self._vis_prog["u_shadow"].value = 0
        self._vis_prog["u_light_from_obj"].write(self._light_from_obj.T.astype(np.float32).tobytes())
        self._vis_prog["u_softness"].value = soft / 2.0  # the light's box spans 2 radii
        self._vis_prog["u_patch"].value = tuple(float(x) for x in self.patch)
        if nogil is not None:
            nogil.draw_strip(self._vis_prog.glo, self._vis_vao.glo)
            nogil.finish()  # the 16-tap PCF pass, waited for without the GIL before the read-back
        else:
            self._vis_vao.render(moderngl.TRIANGLE_STRIP)
        # the receiver is drawn only over the part of the patch that is darkened at all: the
        # visibility is read back (a few kB) and the patch shrunk to its shadowed texels
        vs = self.vis_tex.size
        vis = read_pixels(self._vis_fbo, 1)[:, :, 0]
        rows, cols = np.nonzero(vis < 254)
        if len(rows):
            p = self.patch
            sx, sz = (p[2] - p[0]) / vs[0], (p[3] - p[1]) / vs[1]
            self.cast_rect = np.array(
                [
                    p[0] + (cols.min() - 1) * sx,
                    p[1] + (rows.min() - 1) * sz,
                    p[0] + (cols.max() + 2) * sx,
                    p[1] + (rows.max() + 2) * sz,
                ]
            )
        else:
            self.cast_rect = None
        self.redraws += 1
        return True

    def params(self, direction: np.ndarray | None, share: float) -> ShadowParams:
        """Receiver inputs for this frame (call after :meth:`update`)."""
        use = direction is not None and direction[1] > MIN_ELEVATION_SIN and share > 0.0 and self._dir is not None
        # long shadows of a low light fade in over the last few degrees instead of popping
        fade = 0.0 if direction is None else float(np.clip((direction[1] - MIN_ELEVATION_SIN) / 0.1, 0.0, 1.0))
        draw = self.ao_draw_rect.copy()
        if use and self.cast_rect is not None:
            c = self.cast_rect
            draw = np.array([min(draw[0], c[0]), min(draw[1], c[1]), max(draw[2], c[2]), max(draw[3], c[3])])
        return ShadowParams(
            share=float(np.clip(share, 0.0, 1.0)) * fade if use else 0.0,
            use_shadow=bool(use),
            patch=self.patch if use else self._patch(None),
            ao_rect=self.ao_rect,
            draw_rect=draw,
        )

    def release(self) -> None:
        """Free the GPU objects; safe to call twice."""
        if getattr(self, "_vbo", None) is not None:
            make_current(self.ctx)
            park(self.ctx)
        for name in (
            "_depth_vao",
            "_depth_prog",
            "_shadow_fbo",
            "shadow_tex",
            "_vis_vao",
            "_vis_prog",
            "_vis_fbo",
            "vis_tex",
            "ao_tex",
            "_quad",
            "_vbo",
            "_ibo",
        ):
            obj = getattr(self, name, None)
            if obj is not None:
                obj.release()
                setattr(self, name, None)
