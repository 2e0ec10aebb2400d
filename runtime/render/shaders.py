"""GLSL sources of the compositor, and the colour-transfer tables they sample.

What this module owns
---------------------
* The shader programs' sources: the background copy, the two object programs (textured and
  plain), the occlusion test they share, and the two "layer over picture" programs (plain, and
  with edge anti-aliasing). The cast shadow's receiver program lives with the shadow
  (:mod:`illuminet.runtime.render.shadow`).
* :func:`with_transfer`: fills a source's ``//ENCODE//``, ``//DECODE//`` and ``//OCCLUSION//``
  marks with the camera's colour transfer (sRGB formulas, or lookups in the measured response).
* :func:`encode_lut` / :func:`decode_lut`: those lookup tables, built on the CPU.

Colour (see :mod:`illuminet.runtime.physics`): the object's linear pixel value is
``albedo * E / pi * exposure_scale`` with E the scene-referred irradiance, encoded with the camera's
transfer curve, so the object sits in the picture with the frame's own exposure.
"""

from __future__ import annotations

import numpy as np

from illuminet.runtime.physics import srgb_to_linear

#: entries of the linear -> code value table used to encode (interpolated in the shader)
ENCODE_LUT_SIZE = 4096


# --------------------------------------------------------------------------------- colour encoding


def encode_lut(response_lut: np.ndarray | None = None, size: int = ENCODE_LUT_SIZE) -> np.ndarray:
    """(size, 3) float32 table: linear value i/(size-1) -> code value / 255 per channel.

    The inverse of the camera's response: sRGB by default, or the measured ``response_lut``
    ((256, 3) code -> linear, from photometric calibration), inverted by interpolation.
    """
    x = np.linspace(0.0, 1.0, size, dtype=np.float64)
    if response_lut is None:
        y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
        return np.repeat(y[:, None], 3, axis=1).astype(np.float32)
    lut = np.asarray(response_lut, dtype=np.float64)
    if lut.shape != (256, 3):
        raise ValueError(f"response LUT must have shape (256, 3), got {lut.shape}")
    codes = np.arange(256) / 255.0
    out = np.empty((size, 3))
    for c in range(3):
        out[:, c] = np.interp(x, np.maximum.accumulate(lut[:, c]), codes)
    return out.astype(np.float32)


def decode_lut(response_lut: np.ndarray | None = None) -> np.ndarray:
    """(256, 3) float32 table: code value -> linear (sRGB by default)."""
    if response_lut is None:
        lin = srgb_to_linear(np.arange(256, dtype=np.uint8))
        return np.repeat(lin[:, None], 3, axis=1).astype(np.float32)
    lut = np.asarray(response_lut, dtype=np.float32)
    if lut.shape != (256, 3):
        raise ValueError(f"response LUT must have shape (256, 3), got {lut.shape}")
    return lut


#: GLSL colour transfer functions: the sRGB formulas (default, cheapest on llvmpipe), or lookups in
#: the measured camera response's tables when one is configured
ENCODE_SRGB = """vec3 encode(vec3 l) {
    l = clamp(l, 0.0, 1.0);
    return mix(l * 12.92, 1.055 * pow(l, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, l));
}"""
DECODE_SRGB = """vec3 decode(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c));
}"""
ENCODE_LUT = """vec3 encode(vec3 l) {
    float n = float(textureSize(u_enc_lut, 0).x);
    vec3 x = clamp(l, 0.0, 1.0) * ((n - 1.0) / n) + 0.5 / n;
    return vec3(texture(u_enc_lut, vec2(x.r, 0.5)).r, texture(u_enc_lut, vec2(x.g, 0.5)).g,
                texture(u_enc_lut, vec2(x.b, 0.5)).b);
}"""
DECODE_LUT = """vec3 decode(vec3 c) {
    ivec3 i = ivec3(c * 255.0 + 0.5);
    return vec3(texelFetch(u_dec_lut, ivec2(i.r, 0), 0).r, texelFetch(u_dec_lut, ivec2(i.g, 0), 0).g,
                texelFetch(u_dec_lut, ivec2(i.b, 0), 0).b);
}"""


def with_transfer(src: str, custom: bool) -> str:
    """Insert the encode/decode functions into a shader source at its //ENCODE// and //DECODE// marks."""
    return (
        src.replace("//ENCODE//", ENCODE_LUT if custom else ENCODE_SRGB)
        .replace("//DECODE//", DECODE_LUT if custom else DECODE_SRGB)
        .replace("//OCCLUSION//", OCCLUSION_GLSL)
    )


# --------------------------------------------------------------------------------------- shaders

BG_VS = """
#version 330
in vec2 in_uv;
void main() { gl_Position = vec4(in_uv * 2.0 - 1.0, 0.0, 1.0); }
"""
BG_FS = """
#version 330
uniform sampler2D u_bg;
out vec4 f_color;
void main() { f_color = vec4(texelFetch(u_bg, ivec2(gl_FragCoord.xy), 0).rgb, 1.0); }
"""

# Two object programs. Textured parts: albedo from the texture per fragment, then encoded per
# fragment. Untextured parts (the common case: built-in objects, vertex colours): the colour is
# computed and encoded per vertex and interpolated -- the shading is per-vertex (Gouraud) anyway
# and the render mesh's triangles are a few pixels wide, so interpolating encoded instead of linear
# values changes nothing visible, while the fragment shader shrinks to the occlusion test (llvmpipe
# spends most of the object's time in fragment work; this saves ~30 % of it).
OBJ_VS_TEX = """
#version 330
uniform mat4 u_clip_from_obj;
uniform mat4 u_cam_from_obj;
in vec3 in_pos;
in vec2 in_uv;
in vec3 in_albedo;   // linear vertex albedo
in vec3 in_irr;      // scene-referred irradiance of this vertex
out vec2 v_uv;
out vec3 v_albedo;
out vec3 v_irr;
out float v_zcam;
void main() {
    v_uv = in_uv;
    v_albedo = in_albedo;
    v_irr = max(in_irr, vec3(0.0));
    v_zcam = (u_cam_from_obj * vec4(in_pos, 1.0)).z;
    gl_Position = u_clip_from_obj * vec4(in_pos, 1.0);
}
"""
OBJ_VS_PLAIN = """
#version 330
uniform mat4 u_clip_from_obj;
uniform mat4 u_cam_from_obj;
uniform sampler2D u_enc_lut;
uniform vec3 u_base;
uniform float u_radiance_scale;  // exposure_scale / pi
in vec3 in_pos;
in vec3 in_albedo;
in vec3 in_irr;
out vec3 v_color;
out float v_zcam;
//ENCODE//
void main() {
    v_color = encode(u_base * in_albedo * max(in_irr, vec3(0.0)) * u_radiance_scale);
    v_zcam = (u_cam_from_obj * vec4(in_pos, 1.0)).z;
    gl_Position = u_clip_from_obj * vec4(in_pos, 1.0);
}
"""

# shared by both fragment programs: real geometry nearer than this fragment (beyond the depth
# noise) stays in front; a hidden fragment leaves a mark (transparent, red set) so that the edge
# filter keeps the occluder's outline exact, or nothing at all
OCCLUSION_GLSL = """
uniform sampler2D u_real_depth;
uniform float u_occlusion;
uniform float u_depth_tol;
uniform ivec2 u_offset;          // this framebuffer's origin inside the crop (depth texture)
uniform float u_mark_occluded;
bool hidden(float zcam) {
    if (u_occlusion < 0.5) return false;
    float d = texelFetch(u_real_depth, ivec2(gl_FragCoord.xy) + u_offset, 0).r;
    return d > 0.0 && d < zcam - u_depth_tol * max(zcam * zcam, 1.0);
}
"""

OBJ_FS_TEX = """
#version 330
uniform sampler2D u_tex;
uniform sampler2D u_enc_lut;
uniform vec3 u_base;
uniform float u_radiance_scale;
in vec2 v_uv;
in vec3 v_albedo;
in vec3 v_irr;
in float v_zcam;
out vec4 f_color;
//OCCLUSION//
vec3 srgb_decode(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c));
}
//ENCODE//
void main() {
    if (hidden(v_zcam)) {
        if (u_mark_occluded > 0.5) { f_color = vec4(1.0, 0.0, 0.0, 0.0); return; }
        discard;
    }
    vec3 albedo = u_base * v_albedo * srgb_decode(texture(u_tex, v_uv).rgb);
    f_color = vec4(encode(albedo * v_irr * u_radiance_scale), 1.0);
}
"""
OBJ_FS_PLAIN = """
#version 330
in vec3 v_color;
in float v_zcam;
out vec4 f_color;
//OCCLUSION//
void main() {
    if (hidden(v_zcam)) {
        if (u_mark_occluded > 0.5) { f_color = vec4(1.0, 0.0, 0.0, 0.0); return; }
        discard;
    }
    f_color = vec4(v_color, 1.0);
}
"""


# the resolved object layer (premultiplied by its coverage) over the picture
OVER_FS = """
#version 330
uniform sampler2D u_obj;
uniform ivec2 u_offset;
out vec4 f_color;
void main() { f_color = texelFetch(u_obj, ivec2(gl_FragCoord.xy) - u_offset, 0); }
"""

# the same for a single-sampled layer, with edge anti-aliasing: where the 3x3 neighbourhood's
# coverage is mixed (the silhouette, or the edge of a real occluder), the premultiplied layer is
# tent-filtered, a one-pixel feather like a small resolve filter; elsewhere it is taken as is, so
# texture detail inside the object stays sharp. Costs nine fetches per layer pixel, where true
# MSAA costs llvmpipe about as much again as drawing the object.
OVER_EDGE_FS = """
#version 330
uniform sampler2D u_obj;
uniform ivec2 u_offset;
uniform ivec2 u_hi;  // last texel of this frame's layer (the texture is larger; beyond is stale)
out vec4 f_color;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy) - u_offset;
    ivec2 hi = u_hi;
    vec4 c = texelFetch(u_obj, p, 0);
    if (c.a < 0.5 && c.r > 0.5) discard;  // hidden behind real geometry: the picture stays exact
    // most pixels are plainly inside or outside: four neighbours tell, and outside draws nothing
    float a4 = texelFetch(u_obj, clamp(p + ivec2(1, 0), ivec2(0), hi), 0).a
             + texelFetch(u_obj, clamp(p - ivec2(1, 0), ivec2(0), hi), 0).a
             + texelFetch(u_obj, clamp(p + ivec2(0, 1), ivec2(0), hi), 0).a
             + texelFetch(u_obj, clamp(p - ivec2(0, 1), ivec2(0), hi), 0).a;
    if (a4 < 0.5 && c.a < 0.5) discard;
    if (a4 > 3.5 && c.a > 0.5) { f_color = c; return; }
    vec4 sum = vec4(0.0);
    float amin = 1.0, amax = 0.0;
    bool near_occluder = false;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
            vec4 t = texelFetch(u_obj, clamp(p + ivec2(dx, dy), ivec2(0), hi), 0);
            if (t.a < 0.5 && t.r > 0.5) { near_occluder = true; t = vec4(0.0); }
            float w = float((2 - abs(dx)) * (2 - abs(dy)));
            sum += w * t;
            amin = min(amin, t.a);
            amax = max(amax, t.a);
        }
    if (c.a < 0.5 && near_occluder) discard;  // do not feather the object onto an occluder
    f_color = (amax - amin > 0.5) ? sum / 16.0 : c;
}
"""
