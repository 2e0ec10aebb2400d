"""Rendering and compositing: the shaded, shadowed virtual object drawn into the camera picture.

What this module owns
---------------------
* :class:`RenderMesh` and :func:`load_render_mesh`: a drawable mesh from a GLB/glTF/OBJ/PLY file or
  a trimesh object, with its albedo (texture x UV, vertex colours, material base colour).
  Textures are decoded with OpenCV, so Pillow is not needed (trimesh alone would drop them).
* :class:`Compositor`: the GPU side, on plain arrays (camera picture, depth, intrinsics, pose,
  irradiance per render vertex). Per frame it draws only the screen rectangle that the object and
  its shadow can touch: that crop of the camera picture is uploaded, the shadow patch multiplies it
  in linear light, the object is drawn over it with MSAA, real geometry nearer than the object
  hides it, the crop is resolved and read back, and pasted into a copy of the picture.
* :class:`RenderStage`: the pipeline stage. Reads ``results["anchor"]``, ``results["shading"]``
  and ``results["plane_light"]`` and writes ``results["composite"]`` (H x W x 3 uint8 RGB).

Colour (see :mod:`illuminet.runtime.physics`): the object's linear pixel value is
``albedo * E / pi * exposure_scale`` with E the scene-referred irradiance, encoded with the camera's
transfer curve (sRGB, or the measured response's inverse), so the object sits in the picture with
the frame's own exposure. The shadow is applied to the linearised picture and re-encoded the same
way.

Image orientation: the crop is rendered with image row 0 at GL row 0, so what glReadPixels returns
is already in image order (no flip on the CPU); triangle winding is therefore mirrored and face
culling stays off (the depth test resolves visibility).
"""

from __future__ import annotations

import logging
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.render.gl import check_gl, make_current, park
from illuminet.runtime.physics import srgb_to_linear
from illuminet.runtime.scene import ANCHOR, COMPOSITE, PLANE_LIGHT, SHADING, ObjectShading
from illuminet.runtime.render.shadow import RECEIVER_FS, RECEIVER_VS, ShadowCaster, dominant_light
from illuminet.runtime.stage import FrameError, Stage

log = logging.getLogger(__name__)

#: anti-aliasing methods ([render] antialias): "edge" filters the object layer's silhouette (cheap),
#: "msaa" draws it multisampled ([render] msaa samples; llvmpipe pays ~2x the object's cost), "off"
ANTIALIAS = ("edge", "msaa", "off")

#: entries of the linear -> code value table used to encode (interpolated in the shader)
ENCODE_LUT_SIZE = 4096

#: albedo of a mesh that says nothing about its colour (white glazed ceramic is ~0.8, not 1: a
#: perfect white would clip under light the plane itself does not clip under)
DEFAULT_ALBEDO = 0.8


# ------------------------------------------------------------------------------------------ meshes

@dataclass
class MeshPart:
    """A run of faces drawn with one albedo source.

    ``first``/``count`` index into the flattened face list (3 indices per face). ``texture`` is an
    H x W x 3 or 4 uint8 sRGB image (or None); ``base_color`` a linear RGB factor (glTF
    baseColorFactor, OBJ Kd).
    """

    first: int
    count: int
    texture: np.ndarray | None = None
    base_color: np.ndarray = field(default_factory=lambda: np.ones(3, dtype=np.float32))


@dataclass
class RenderMesh:
    """A drawable mesh in the object frame (origin on the plane under the object, +Y up, metres).

    Attributes
    ----------
    vertices, normals : (N, 3) float32
    faces : (F, 3) uint32
    uv : (N, 2) float32 or None
        Texture coordinates, origin at the image's bottom-left (OBJ/trimesh convention).
    colors : (N, 3) uint8 or None
        Per-vertex albedo, sRGB-encoded (PLY scans' convention).
    parts : list of MeshPart
        Face runs with their texture / base colour; together they cover all faces.
    source : str
        Where it came from (for messages).
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    colors: np.ndarray | None = None
    parts: list[MeshPart] = field(default_factory=list)
    source: str = "<arrays>"
    closed: bool | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"{self.source}: vertices must be (N, 3) with N > 0, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"{self.source}: faces must be (F, 3) triangles with F > 0, got {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"{self.source}: face indices must lie in [0, {len(v) - 1}], got [{f.min()}, {f.max()}]")
        if not np.isfinite(v).all():
            raise ValueError(f"{self.source}: vertices contain NaN or infinity")
        self.vertices = v.astype(np.float32)
        self.faces = f.astype(np.uint32)
        self.normals = np.asarray(self.normals, dtype=np.float32).reshape(len(v), 3)
        if self.uv is not None:
            self.uv = np.asarray(self.uv, dtype=np.float32).reshape(len(v), 2)
        if self.colors is not None:
            c = np.asarray(self.colors)
            if c.dtype != np.uint8:
                c = np.clip(np.rint(c * 255.0) if c.max() <= 1.0 else c, 0, 255).astype(np.uint8)
            self.colors = c[:, :3].reshape(len(v), 3)
        if self.closed is None:
            self.closed = _is_closed(self.vertices, self.faces)
        if not self.parts:
            base = np.full(3, 1.0 if self.colors is not None else DEFAULT_ALBEDO, dtype=np.float32)
            self.parts = [MeshPart(0, 3 * len(self.faces), None, base)]

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def scaled(self, s: float) -> "RenderMesh":
        """The same mesh with vertex positions multiplied by ``s`` (about the object origin)."""
        if not (s > 0 and np.isfinite(s)):
            raise ValueError(f"[render] object_scale: expected a positive number, got {s!r}")
        return RenderMesh(self.vertices * np.float32(s), self.normals, self.faces, self.uv, self.colors,
                          self.parts, self.source, self.closed)

    @classmethod
    def from_trimesh(cls, mesh, source: str = "<trimesh>", texture: np.ndarray | None = None) -> "RenderMesh":
        """Convert a ``trimesh.Trimesh`` or ``trimesh.Scene`` (its visuals become the albedo).

        ``texture`` overrides the material's image (used when trimesh could not decode it).
        """
        import trimesh

        if isinstance(mesh, trimesh.Scene):
            geoms = []
            for node in mesh.graph.nodes_geometry:
                transform, name = mesh.graph[node]
                g = mesh.geometry[name]
                if isinstance(g, trimesh.Trimesh) and len(g.faces):
                    geoms.append((g, np.asarray(transform, dtype=np.float64)))
            if not geoms:
                raise ValueError(f"{source}: the scene holds no triangle mesh")
        elif isinstance(mesh, trimesh.Trimesh):
            geoms = [(mesh, np.eye(4))]
        else:
            raise TypeError(f"{source}: expected a trimesh.Trimesh or trimesh.Scene, got {type(mesh).__name__}")

        verts, norms, faces, uvs, cols, parts = [], [], [], [], [], []
        n0 = f0 = 0
        any_uv = any(_uv_of(g) is not None for g, _ in geoms)
        any_col = any(_colors_of(g) is not None for g, _ in geoms)
        for g, tf in geoms:
            v = np.asarray(g.vertices, dtype=np.float64)
            v = v @ tf[:3, :3].T + tf[:3, 3]
            n = np.asarray(g.vertex_normals, dtype=np.float64) @ np.linalg.inv(tf[:3, :3]).T
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            verts.append(v)
            norms.append(n)
            faces.append(np.asarray(g.faces, dtype=np.int64) + n0)
            uv = _uv_of(g)
            uvs.append(uv if uv is not None else np.zeros((len(v), 2)))
            c = _colors_of(g)
            cols.append(c if c is not None else np.full((len(v), 3), 255, np.uint8))
            tex, base = _material_of(g)
            if c is None and tex is None and getattr(getattr(g, "visual", None), "material", None) is None:
                base = np.full(3, DEFAULT_ALBEDO, dtype=np.float32)
            if texture is not None and len(geoms) == 1:
                tex = texture
            parts.append(MeshPart(3 * f0, 3 * len(g.faces), tex if uv is not None else None, base))
            n0 += len(v)
            f0 += len(g.faces)
        return cls(
            vertices=np.concatenate(verts), normals=np.concatenate(norms), faces=np.concatenate(faces),
            uv=np.concatenate(uvs) if any_uv else None, colors=np.concatenate(cols) if any_col else None,
            parts=parts, source=source,
        )


def _is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """True for a watertight, consistently wound, outward-facing mesh: its back faces can be culled.

    Culling halves the triangles llvmpipe rasterises; an open or inconsistently wound mesh (a
    single-sided bowl, a broken scan) keeps every face, since its inside can be seen.
    """
    import trimesh

    try:
        m = trimesh.Trimesh(vertices, faces, process=True)  # merges seam duplicates for the check only
        return bool(m.is_watertight and m.is_winding_consistent and m.volume > 0)
    except Exception:
        return False


def _uv_of(g) -> np.ndarray | None:
    vis = getattr(g, "visual", None)
    if vis is not None and getattr(vis, "kind", None) == "texture" and getattr(vis, "uv", None) is not None:
        uv = np.asarray(vis.uv, dtype=np.float64)
        if uv.shape == (len(g.vertices), 2):
            return uv
    return None


def _colors_of(g) -> np.ndarray | None:
    vis = getattr(g, "visual", None)
    if vis is not None and getattr(vis, "kind", None) in ("vertex", "face"):
        c = np.asarray(vis.vertex_colors)
        if c.shape[0] == len(g.vertices):
            return c[:, :3].astype(np.uint8)
    return None


def _image_array(img) -> np.ndarray | None:
    """A material image (PIL image or array) as uint8 RGB(A), or None when it is not usable."""
    if img is None:
        return None
    try:
        if hasattr(img, "convert"):  # PIL, when installed
            img = img.convert("RGBA")
        a = np.asarray(img)
    except Exception:
        return None
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.size == 0:
        return None
    if a.dtype != np.uint8:
        a = np.clip(a * (255.0 if a.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return a


def _material_of(g) -> tuple[np.ndarray | None, np.ndarray]:
    """(texture or None, linear base colour) of a trimesh geometry's material."""
    base = np.ones(3, dtype=np.float32)
    vis = getattr(g, "visual", None)
    mat = getattr(vis, "material", None) if vis is not None and getattr(vis, "kind", None) == "texture" else None
    if mat is None:
        return None, base
    tex = None
    if hasattr(mat, "baseColorFactor"):  # PBRMaterial (glTF): the factor is linear, stored as uint8
        if mat.baseColorFactor is not None:
            base = np.asarray(mat.baseColorFactor[:3], dtype=np.float32) / 255.0
        try:
            tex = _image_array(mat.baseColorTexture)
        except Exception:
            tex = None
    else:  # SimpleMaterial (OBJ): Kd
        try:
            tex = _image_array(getattr(mat, "image", None))
        except Exception:
            tex = None
        diffuse = getattr(mat, "diffuse", None)
        if diffuse is not None:
            base = np.asarray(diffuse[:3], dtype=np.float32) / 255.0
    return tex, base


def _read_image(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot read the texture image (missing or not an image OpenCV can decode)")
    return _cv_to_rgb(img)


def _cv_to_rgb(img: np.ndarray) -> np.ndarray:
    import cv2

    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _obj_textures(path: Path) -> dict[str, tuple[Path | None, np.ndarray | None]]:
    """material name -> (map_Kd path, Kd) from the MTL files an OBJ names."""
    out: dict[str, tuple[Path | None, np.ndarray | None]] = {}
    text = path.read_text(errors="replace")
    for lib in re.findall(r"^\s*mtllib\s+(.+?)\s*$", text, flags=re.M):
        mtl = path.parent / lib
        if not mtl.is_file():
            log.warning("%s: material library %s not found; the object gets a plain colour", path, mtl)
            continue
        name = None
        for line in mtl.read_text(errors="replace").splitlines():
            parts = line.strip().split()
            if not parts:
                continue
            key = parts[0].lower()
            if key == "newmtl":
                name = " ".join(parts[1:])
                out.setdefault(name, (None, None))
            elif key == "map_kd" and name is not None:
                # options (-s, -o ...) come before the file name; the file name is the last token
                out[name] = (mtl.parent / parts[-1], out[name][1])
            elif key == "kd" and name is not None and len(parts) >= 4:
                out[name] = (out[name][0], np.array([float(x) for x in parts[1:4]], dtype=np.float32))
    return out


def _load_obj(path: Path) -> RenderMesh:
    """OBJ through trimesh's parser (geometry, UVs), textures through OpenCV (no Pillow needed)."""
    import trimesh
    from trimesh.exchange.obj import load_obj

    with open(path, "rb") as f:
        loaded = load_obj(f, resolver=trimesh.resolvers.FilePathResolver(str(path)), skip_materials=False)
    mats = _obj_textures(path)
    if not any(t for t, _ in mats.values()):
        # OBJs shipped without an MTL (e.g. Keenan Crane's spot) keep their texture beside them:
        # take the folder's only image, and say so
        imgs = sorted(p for p in path.parent.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        if len(imgs) == 1:
            log.info("%s: no material library names a texture; using %s beside it", path, imgs[0].name)
            mats = {"": (imgs[0], None)}
    geoms = loaded.get("geometry", {}) if isinstance(loaded, dict) else {}
    if not geoms:
        raise ValueError(f"{path}: no faces found in the OBJ file")
    meshes, textures = [], []
    for name, g in geoms.items():
        vis = g.get("visual")
        uv = getattr(vis, "uv", None) if vis is not None else None
        m = trimesh.Trimesh(vertices=g["vertices"], faces=g["faces"], process=False)
        if uv is not None and len(uv) == len(m.vertices):
            m.visual = trimesh.visual.TextureVisuals(uv=uv)
        elif "vertex_colors" in g:
            m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=g["vertex_colors"])
        mat_name = getattr(getattr(vis, "material", None), "name", None)
        tex_path, kd = mats.get(mat_name, (None, None)) if mat_name else (None, None)
        if uv is None:
            tex_path = None
        if tex_path is None and len(mats) == 1:  # one material: its name may not survive the parser
            tex_path, kd = next(iter(mats.values()))
        textures.append((_read_image(tex_path) if tex_path is not None else None, kd))
        meshes.append(m)
    out = []
    for m, (tex, kd) in zip(meshes, textures):
        rm = RenderMesh.from_trimesh(m, source=str(path), texture=tex)
        # trimesh invents a grey (0.4) diffuse when the MTL gives none; OBJ's own Kd or white it is
        rm.parts[0].base_color = kd if kd is not None else np.ones(3, dtype=np.float32)
        if tex is not None and rm.uv is not None:
            rm.parts[0].texture = tex
        out.append(rm)
    return _concat(out, str(path))


def _concat(meshes: list[RenderMesh], source: str) -> RenderMesh:
    if len(meshes) == 1:
        meshes[0].source = source
        return meshes[0]
    n0 = f0 = 0
    parts = []
    for m in meshes:
        for p in m.parts:
            parts.append(MeshPart(p.first + 3 * f0, p.count, p.texture, p.base_color))
        n0 += m.n_vertices
        f0 += len(m.faces)
    offs = np.cumsum([0] + [m.n_vertices for m in meshes[:-1]])
    any_uv = any(m.uv is not None for m in meshes)
    any_col = any(m.colors is not None for m in meshes)
    return RenderMesh(
        vertices=np.concatenate([m.vertices for m in meshes]),
        normals=np.concatenate([m.normals for m in meshes]),
        faces=np.concatenate([m.faces.astype(np.int64) + o for m, o in zip(meshes, offs)]),
        uv=np.concatenate([m.uv if m.uv is not None else np.zeros((m.n_vertices, 2), np.float32) for m in meshes])
        if any_uv else None,
        colors=np.concatenate([m.colors if m.colors is not None else np.full((m.n_vertices, 3), 255, np.uint8)
                               for m in meshes]) if any_col else None,
        parts=parts, source=source,
    )


def _gltf_textures(path: Path) -> list[np.ndarray]:
    """Base-colour images of a .glb/.gltf decoded with OpenCV, in material order (trimesh needs Pillow)."""
    import base64
    import json
    import struct

    import cv2

    data = path.read_bytes()
    bin_chunk = b""
    if data[:4] == b"glTF":
        off = 12
        header = None
        while off + 8 <= len(data):
            length, ctype = struct.unpack_from("<I4s", data, off)
            chunk = data[off + 8: off + 8 + length]
            if ctype == b"JSON":
                header = json.loads(chunk)
            elif ctype == b"BIN\x00":
                bin_chunk = chunk
            off += 8 + length
        if header is None:
            return []
    else:
        header = json.loads(data)
    out = []
    for mat in header.get("materials", []):
        tex_ref = mat.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if tex_ref is None:
            continue
        try:
            img = header["images"][header["textures"][tex_ref["index"]]["source"]]
            if "bufferView" in img:
                bv = header["bufferViews"][img["bufferView"]]
                blob = bin_chunk[bv.get("byteOffset", 0): bv.get("byteOffset", 0) + bv["byteLength"]]
            elif img.get("uri", "").startswith("data:"):
                blob = base64.b64decode(img["uri"].split(",", 1)[1])
            else:
                blob = (path.parent / img["uri"]).read_bytes()
            dec = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
            if dec is not None:
                out.append(_cv_to_rgb(dec))
        except (KeyError, IndexError, OSError) as e:
            log.warning("%s: material texture not readable (%s); using its base colour", path, e)
    return out


def load_render_mesh(src: Any) -> RenderMesh:
    """Load a drawable mesh from a file (.glb, .gltf, .obj, .ply, .stl, .off) or a trimesh object.

    Parameters
    ----------
    src : str, Path, trimesh.Trimesh, trimesh.Scene or RenderMesh
        Object-frame geometry in metres (origin on the plane under the object, +Y up).

    Raises
    ------
    ValueError
        When the file is missing, of an unknown kind, or holds no triangles; the message names it.
    """
    if isinstance(src, RenderMesh):
        return src
    if not isinstance(src, (str, os.PathLike)):
        return RenderMesh.from_trimesh(src)
    import trimesh

    path = Path(src)
    if not path.is_file():
        raise ValueError(f"{path}: object mesh file not found (expected a .glb, .gltf, .obj or .ply file)")
    ext = path.suffix.lower()
    if ext == ".obj":
        return _load_obj(path)
    if ext not in (".glb", ".gltf", ".ply", ".stl", ".off"):
        raise ValueError(f"{path}: unknown mesh kind {ext!r}; expected .glb, .gltf, .obj, .ply, .stl or .off")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as e:
        raise ValueError(f"{path}: cannot be read as a mesh: {e}") from None
    mesh = RenderMesh.from_trimesh(loaded, source=str(path))
    if ext in (".glb", ".gltf") and mesh.uv is not None and all(p.texture is None for p in mesh.parts):
        texs = _gltf_textures(path)
        if texs:  # trimesh could not decode the images (no Pillow): give the first one to textured parts
            for p in mesh.parts:
                p.texture = texs[0]
    return mesh


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
    return np.array([
        [2.0 * fx / w, 0.0, 2.0 * (cx + 0.5 - x0) / w - 1.0, 0.0],
        [0.0, 2.0 * fy / h, 2.0 * (cy + 0.5 - y0) / h - 1.0, 0.0],
        [0.0, 0.0, a, b],
        [0.0, 0.0, 1.0, 0.0],
    ])


#: GLSL colour transfer functions: the sRGB formulas (default, cheapest on llvmpipe), or lookups in
#: the measured camera response's tables when one is configured
_ENCODE_SRGB = """vec3 encode(vec3 l) {
    l = clamp(l, 0.0, 1.0);
    return mix(l * 12.92, 1.055 * pow(l, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, l));
}"""
_DECODE_SRGB = """vec3 decode(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c));
}"""
_ENCODE_LUT = """vec3 encode(vec3 l) {
    float n = float(textureSize(u_enc_lut, 0).x);
    vec3 x = clamp(l, 0.0, 1.0) * ((n - 1.0) / n) + 0.5 / n;
    return vec3(texture(u_enc_lut, vec2(x.r, 0.5)).r, texture(u_enc_lut, vec2(x.g, 0.5)).g,
                texture(u_enc_lut, vec2(x.b, 0.5)).b);
}"""
_DECODE_LUT = """vec3 decode(vec3 c) {
    ivec3 i = ivec3(c * 255.0 + 0.5);
    return vec3(texelFetch(u_dec_lut, ivec2(i.r, 0), 0).r, texelFetch(u_dec_lut, ivec2(i.g, 0), 0).g,
                texelFetch(u_dec_lut, ivec2(i.b, 0), 0).b);
}"""


def _with_transfer(src: str, custom: bool) -> str:
    """Insert the encode/decode functions into a shader source at its //ENCODE// and //DECODE// marks."""
    return src.replace("//ENCODE//", _ENCODE_LUT if custom else _ENCODE_SRGB).replace(
        "//DECODE//", _DECODE_LUT if custom else _DECODE_SRGB).replace("//OCCLUSION//", _OCCLUSION_GLSL)


def _mat(m: np.ndarray) -> bytes:
    """numpy row-major 4x4 -> the column-major bytes GLSL's mat4 expects."""
    return np.ascontiguousarray(m.T, dtype=np.float32).tobytes()


# --------------------------------------------------------------------------------------- shaders

_BG_VS = """
#version 330
in vec2 in_uv;
void main() { gl_Position = vec4(in_uv * 2.0 - 1.0, 0.0, 1.0); }
"""
_BG_FS = """
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
_OBJ_VS_TEX = """
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
_OBJ_VS_PLAIN = """
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
_OCCLUSION_GLSL = """
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

_OBJ_FS_TEX = """
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
_OBJ_FS_PLAIN = """
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
_OVER_FS = """
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
_OVER_EDGE_FS = """
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


# ------------------------------------------------------------------------------------- compositor

@dataclass
class DrawInfo:
    """What the last :meth:`Compositor.draw` did (for stats and tests)."""

    crop: tuple[int, int, int, int] = (0, 0, 0, 0)
    drawn: bool = False
    shadow: bool = False
    light_dir: np.ndarray | None = None
    share: float = 0.0


class Compositor:
    """GPU renderer for one mesh: draws it, its shadow and the occlusion into camera pictures.

    Passes per frame, all inside the crop rectangle the object and its shadow can touch:

    1. the crop of the camera picture is uploaded and drawn (single-sampled);
    2. the shadow patch on the plane multiplies it in linear light (one lookup in the precomputed
       visibility texture, one in the contact map);
    3. the object is drawn into its own multisampled layer (its bounding rectangle only, the most
       expensive buffer kept smallest), with fragments behind real geometry discarded;
    4. the layer is resolved and blended over the picture by its coverage (anti-aliased edges,
       also against real occluders); the crop is read back and pasted into the output.

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

    def __init__(self, ctx, mesh: RenderMesh, msaa: int = 4, shadow: bool = True, shadow_map: int = 1024,
                 occlusion: bool = True, depth_tolerance_m: float = 0.03, shadow_softness: float = 0.05,
                 contact_shadow: float = 0.75, response_lut: np.ndarray | None = None, antialias: str = "edge"):
        import moderngl

        make_current(ctx)
        self.ctx = ctx
        self.mesh = mesh
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
        self._fbos: dict[str, Any] = {}
        self._ofbos: dict[str, Any] = {}
        self._bbox = (mesh.vertices.min(axis=0).astype(float), mesh.vertices.max(axis=0).astype(float))

        # --- colour tables (camera response and its inverse)
        self._dec_lut = ctx.texture((256, 1), 3, decode_lut(response_lut).tobytes(), dtype="f4")
        self._dec_lut.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._enc_lut = ctx.texture((ENCODE_LUT_SIZE, 1), 3, encode_lut(response_lut).tobytes(), dtype="f4")
        self._enc_lut.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._enc_lut.repeat_x = self._enc_lut.repeat_y = False

        # --- mesh buffers: static attributes once, irradiance rewritten per frame
        n = mesh.n_vertices
        uv = mesh.uv if mesh.uv is not None else np.zeros((n, 2), np.float32)
        alb = srgb_to_linear(mesh.colors) if mesh.colors is not None else np.ones((n, 3), np.float32)
        static = np.concatenate([mesh.vertices, uv, alb], axis=1).astype(np.float32)
        self._vbo = ctx.buffer(static.tobytes())
        self._ibo = ctx.buffer(mesh.faces.astype(np.uint32).tobytes())
        self._irr = ctx.buffer(reserve=n * 12, dynamic=True)
        custom = response_lut is not None
        attrs = [(self._vbo, "3f 2f 3f", "in_pos", "in_uv", "in_albedo"), (self._irr, "3f", "in_irr")]
        self._obj_progs = {}
        for textured, (vs, fs) in ((False, (_OBJ_VS_PLAIN, _OBJ_FS_PLAIN)), (True, (_OBJ_VS_TEX, _OBJ_FS_TEX))):
            if textured and all(p.texture is None for p in mesh.parts):
                continue
            prog = ctx.program(vertex_shader=_with_transfer(vs, custom), fragment_shader=_with_transfer(fs, custom))
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

        quad = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float32)
        self._quad = ctx.buffer(quad.tobytes())
        self._bg_prog = ctx.program(vertex_shader=_BG_VS, fragment_shader=_BG_FS)
        self._bg_vao = ctx.vertex_array(self._bg_prog, [(self._quad, "2f", "in_uv")])
        self._over_prog = ctx.program(vertex_shader=_BG_VS,
                                      fragment_shader=_OVER_EDGE_FS if self.antialias == "edge" else _OVER_FS)
        self._over_vao = ctx.vertex_array(self._over_prog, [(self._quad, "2f", "in_uv")])
        self.shadow = (ShadowCaster(ctx, mesh.vertices, mesh.faces, shadow_map, shadow_softness, closed=bool(mesh.closed))
                       if shadow else None)
        if self.shadow is not None:
            self._rcv_prog = ctx.program(vertex_shader=RECEIVER_VS,
                                         fragment_shader=_with_transfer(RECEIVER_FS, custom))
            self._rcv_vao = ctx.vertex_array(self._rcv_prog, [(self._quad, "2f", "in_uv")])
        check_gl(ctx, f"setting up the renderer for {mesh.source}")

    # -- framebuffers sized to the largest crop seen so far ------------------------------------------
    def _ensure_capacity(self, w: int, h: int, ow: int, oh: int) -> None:
        import moderngl

        ctx = self.ctx
        cw, ch = self._cap
        if w > cw or h > ch:
            cw, ch = max(cw, -(-w // 128) * 128), max(ch, -(-h // 128) * 128)
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
            self._readbuf = np.empty(cw * ch * 3, dtype=np.uint8)
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
        """Pixel rectangle (x0, y0, x1, y1) covering object-frame points, or 'all'/None."""
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
        import moderngl

        if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
            raise ValueError(f"color must be an HxWx3 uint8 RGB array, got {color.shape} {color.dtype}")
        hgt, wid = color.shape[:2]
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
        if depth is not None and depth.shape != (hgt, wid):
            raise ValueError(f"depth {depth.shape} must be aligned to colour {(hgt, wid)}")
        make_current(self.ctx)
        self._t_mark = self.profile_clock()
        if out is None:
            out = color.copy()
        elif out is not color:
            np.copyto(out, color)

        ctx = self.ctx
        sp = None
        if self.shadow is not None:
            self.shadow.update(light_dir)
            sp = self.shadow.params(light_dir, share)
        lo, hi = self._bbox
        corners = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        orect, oz = self._project_rect(K, cam_from_obj, corners, (wid, hgt))
        pts = corners
        if sp is not None:
            pa = sp.draw_rect
            pts = corners + [[pa[0], 0, pa[1]], [pa[2], 0, pa[1]], [pa[0], 0, pa[3]], [pa[2], 0, pa[3]]]
        rect, z = self._project_rect(K, cam_from_obj, pts, (wid, hgt))
        self.info = DrawInfo(drawn=rect is not None, shadow=bool(sp is not None and sp.use_shadow),
                             light_dir=light_dir, share=share)
        if rect is None:
            return out
        x0, y0, x1, y1 = rect
        w, h = x1 - x0, y1 - y0
        crop = (x0, y0, w, h)
        self.info.crop = crop
        zpos = z[z > 1e-3]
        near = float(max(1e-3, 0.5 * zpos.min()))
        far = float(max(zpos.max() * 2.0, near * 10.0))
        if orect is not None:
            ox0, oy0, ox1, oy1 = orect
            ow, oh = ox1 - ox0, oy1 - oy0
        else:
            ow = oh = 0
        self._ensure_capacity(w, h, max(ow, 1), max(oh, 1))
        f, o = self._fbos, self._ofbos
        f["bg"].write(np.ascontiguousarray(color[y0:y1, x0:x1]), viewport=(0, 0, w, h))
        if depth is not None:
            f["depth_in"].write(np.ascontiguousarray(depth[y0:y1, x0:x1], dtype=np.float32), viewport=(0, 0, w, h))
        else:
            f["depth_in"].write(self._zeros[: w * h], viewport=(0, 0, w, h))

        clip = crop_projection(K, crop, near, far) @ cam_from_obj
        main = f["main"]
        main.use()
        main.viewport = (0, 0, w, h)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)

        mark = self._mark
        mark("setup")
        # 1. the camera picture
        f["bg"].use(0)
        self._bg_prog["u_bg"].value = 0
        self._bg_vao.render(moderngl.TRIANGLE_STRIP)

        mark("background")
        # 2. the shadow patch multiplies it (reads the same picture, writes the darkened one)
        if sp is not None:
            prog = self._rcv_prog
            units = (("u_bg", f["bg"]), ("u_real_depth", f["depth_in"]), ("u_dec_lut", self._dec_lut),
                     ("u_enc_lut", self._enc_lut), ("u_vis", self.shadow.vis_tex), ("u_ao", self.shadow.ao_tex))
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
            prog["u_depth_tol"].value = self.depth_tol if depth is not None else 1e9
            self._rcv_vao.render(moderngl.TRIANGLE_STRIP)

        mark("shadow")
        # 3. the object, into its own (multisampled) layer over its bounding rectangle
        if orect is not None:
            self._irr.write(irr.tobytes())
            layer = o["draw"]
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
            f["depth_in"].use(1)
            self._enc_lut.use(3)
            oclip = crop_projection(K, (ox0, oy0, ow, oh), near, far) @ cam_from_obj
            common = {
                "u_tex": 0, "u_real_depth": 1, "u_enc_lut": 3, "u_offset": (ox0 - x0, oy0 - y0),
                "u_radiance_scale": float(exposure_scale) / np.pi,
                "u_occlusion": 1.0 if (self.occlusion and depth is not None) else 0.0,
                "u_depth_tol": self.depth_tol, "u_mark_occluded": 1.0 if self.antialias == "edge" else 0.0,
            }
            for prog, _ in self._obj_progs.values():
                for name, value in common.items():
                    if name in prog:  # unused uniforms are compiled out
                        prog[name].value = value
                prog["u_clip_from_obj"].write(_mat(oclip))
                prog["u_cam_from_obj"].write(_mat(cam_from_obj))
            for part, tex in zip(self.mesh.parts, self._part_tex):
                prog, vao = self._obj_progs[tex is not None]
                if tex is not None:
                    tex.use(0)
                prog["u_base"].value = tuple(float(x) for x in part.base_color[:3])
                vao.render(moderngl.TRIANGLES, vertices=part.count, first=part.first)
            ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
            ctx.front_face = "ccw"
            if self.msaa:
                ctx.copy_framebuffer(o["resolve"], layer)

            mark("object")
            # 4. the layer over the picture, weighted by its coverage (premultiplied alpha)
            main.use()
            main.viewport = (ox0 - x0, oy0 - y0, ow, oh)
            ctx.enable(moderngl.BLEND)
            ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
            o["layer"].use(0)
            self._over_prog["u_obj"].value = 0
            self._over_prog["u_offset"].value = (ox0 - x0, oy0 - y0)
            if "u_hi" in self._over_prog:
                self._over_prog["u_hi"].value = (ow - 1, oh - 1)
            self._over_vao.render(moderngl.TRIANGLE_STRIP)
            ctx.disable(moderngl.BLEND)

        mark("over")
        # 5. read the crop back (already in image row order) and paste it
        n = w * h * 3
        main.read_into(self._readbuf, viewport=(0, 0, w, h), components=3, alignment=1)
        out[y0:y1, x0:x1] = self._readbuf[:n].reshape(h, w, 3)
        mark("readback")
        check_gl(ctx, "drawing a frame")
        return out

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
        for name in ("_bg_vao", "_bg_prog", "_over_vao", "_over_prog", "_rcv_vao", "_rcv_prog", "_vbo", "_ibo",
                     "_irr", "_quad", "_dec_lut", "_enc_lut"):
            obj = getattr(self, name, None)
            if obj is not None:
                obj.release()
                setattr(self, name, None)
        if getattr(self, "shadow", None) is not None:
            self.shadow.release()
            self.shadow = None


# ------------------------------------------------------------------------------------------ stage

class RenderStage(Stage):
    """Pipeline stage: the object, lit by the predicted shading, composited into the frame.

    Reads ``results["anchor"]`` (:class:`~illuminet.runtime.scene.Anchor`), ``results["shading"]``
    (:class:`~illuminet.runtime.scene.ObjectShading`, irradiance per proxy vertex) and
    ``results["plane_light"]`` (for ``exposure_scale``); writes ``results["composite"]``, an
    H x W x 3 uint8 RGB picture. Frames without an anchor or shading pass through unchanged
    (``composite`` is the camera picture) and are counted.

    Parameters
    ----------
    config : Config
        Uses [render] (object_scale, shadow, shadow_map, shadow_softness, contact_shadow,
        occlusion, depth_tolerance_m, msaa, gl_backend) and [model] bundle.
    mesh : RenderMesh, trimesh object or path, optional
        The object to draw. Default: the render mesh of the bundle ``[model] bundle``
        (:func:`illuminet.runtime.assets.bundle.load_bundle`).
    carry : callable, optional
        ``carry(values_on_proxy) -> values_on_render_mesh``. Default: the bundle's; the identity
        when the shading already has one value per render vertex.
    ctx : moderngl.Context, optional
        GL context; default the process-wide one (:func:`illuminet.runtime.render.gl.get_context`).
    response_lut : (256, 3) array, optional
        Camera response (code -> linear) to encode with; sRGB when None.
    """

    name = "render"
    requires = (ANCHOR, SHADING)
    optional = (PLANE_LIGHT,)
    provides = (COMPOSITE,)
    hold_last_good = False  # a composite belongs to its own frame: without one, sinks show the camera picture

    #: exponential smoothing of the dominant light direction and share: the shadow must not flicker
    #: when the per-frame prediction jitters (0 = none)
    LIGHT_SMOOTHING = 0.7

    def __init__(self, config, mesh: Any = None, carry: Callable[[np.ndarray], np.ndarray] | None = None,
                 ctx=None, response_lut: np.ndarray | None = None):
        self.cfg = config
        self._mesh_src = mesh
        self._carry = carry
        self._ctx = ctx
        self._response_lut = response_lut
        self.comp: Compositor | None = None
        self._light: tuple[np.ndarray | None, float] = (None, 0.0)
        self._counts = {"drawn": 0, "passed_through": 0, "no_anchor": 0, "no_shading": 0}
        self._crop_px: list[int] = []

    def open(self) -> None:
        """Create (or take) the GL context, load the object and upload it to the GPU once."""
        from illuminet.runtime.render.gl import get_context

        r = self.cfg.render
        ctx = self._ctx if self._ctx is not None else get_context(r.gl_backend)
        mesh_src, carry = self._mesh_src, self._carry
        if mesh_src is None:
            spec = self.cfg.model.bundle
            try:
                bundle = _load_bundle(spec)
            except (RuntimeError, ValueError) as e:
                if not str(spec).startswith("builtin:"):
                    raise
                # the shading stage falls back to a baseline in this case; draw the same built-in
                # object from its generator so the stream still shows it
                from illuminet.runtime.assets.objects import load_object

                log.warning("%s; drawing %s from its generator, without the bundle", e, spec)
                mesh_src = load_object(spec)
            else:
                mesh_src = mesh_from_bundle(bundle)
                if carry is None:
                    carry = bundle.carry
        mesh = load_render_mesh(mesh_src)
        if r.object_scale != 1.0:
            mesh = mesh.scaled(r.object_scale)
        self._carry = carry
        self.comp = Compositor(
            ctx, mesh, msaa=r.msaa, shadow=r.shadow, shadow_map=r.shadow_map, occlusion=r.occlusion,
            depth_tolerance_m=r.depth_tolerance_m, shadow_softness=r.shadow_softness,
            contact_shadow=r.contact_shadow, response_lut=self._response_lut, antialias=r.antialias,
        )
        from illuminet.runtime.render.gl import renderer_name

        log.info("render: %s, %d vertices, %d faces, antialias %s%s, GL %s", mesh.source, mesh.n_vertices,
                 len(mesh.faces), self.comp.antialias, f" x{self.comp.msaa}" if self.comp.msaa else "",
                 renderer_name(ctx))

    def close(self) -> None:
        """Free the GPU objects (the shared context stays); safe to call twice."""
        if self.comp is not None:
            self.comp.release()
            self.comp = None

    def render_irradiance(self, shading: ObjectShading) -> np.ndarray:
        """The shading's irradiance carried to the render mesh's vertices, (N, 3) float32."""
        irr = np.asarray(shading.irradiance, dtype=np.float32)
        n = self.comp.mesh.n_vertices
        if irr.ndim != 2 or irr.shape[1] != 3:
            raise FrameError(f"shading irradiance must be (V, 3), got {irr.shape} (method {shading.method})")
        if irr.shape[0] == 1:  # one value for the whole object (e.g. the ambient baseline without a bundle)
            out = np.repeat(irr, n, axis=0)
        elif self._carry is not None:
            out = np.asarray(self._carry(irr), dtype=np.float32)
        elif irr.shape[0] == n:
            out = irr
        else:
            raise FrameError(
                f"shading has {irr.shape[0]} vertices, the render mesh {n}, and no carry function maps "
                f"one to the other (give RenderStage a bundle or carry=)"
            )
        if out.shape != (n, 3):
            raise FrameError(f"carry returned shape {out.shape}, expected ({n}, 3)")
        return out

    def process(self, frame: Frame) -> Frame:
        if self.comp is None:
            raise RuntimeError("RenderStage.process called before open()")
        anchor, shading = self.require(frame, ANCHOR), self.require(frame, SHADING)
        irr = self.render_irradiance(shading)
        scale = _exposure_scale(frame)
        d, share = dominant_light(shading, self.comp.mesh.normals, irr)
        d, share = self._smooth_light(d, share)
        intr = frame.intrinsics
        w, h = frame.size
        if (intr.width, intr.height) != (w, h):
            intr = intr.scaled(w, h)
        T = np.asarray(anchor.T_cam_obj, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise FrameError(f"anchor T_cam_obj must be a finite 4x4 matrix, got {T.shape}")
        out = self.comp.draw(frame.color, frame.depth, intr.K, T, irr, scale, d, share)
        self._counts["drawn"] += 1
        self._crop_px.append(self.comp.info.crop[2] * self.comp.info.crop[3])
        if len(self._crop_px) > 10000:
            del self._crop_px[:5000]
        return frame.with_result(COMPOSITE, out)

    def _smooth_light(self, d: np.ndarray | None, share: float) -> tuple[np.ndarray | None, float]:
        prev_d, prev_s = self._light
        a = self.LIGHT_SMOOTHING
        if d is not None and prev_d is not None:
            m = a * prev_d + (1.0 - a) * d
            nm = np.linalg.norm(m)
            d = m / nm if nm > 1e-9 else d
            share = a * prev_s + (1.0 - a) * share
        self._light = (d, share)
        return d, share

    def stats(self) -> dict[str, Any]:
        s: dict[str, Any] = dict(self._counts)
        if self.comp is not None:
            s["antialias"] = self.comp.antialias + (f"x{self.comp.msaa}" if self.comp.msaa else "")
            s["shadow_redraws"] = self.comp.shadow.redraws if self.comp.shadow is not None else 0
        if self._crop_px:
            s["crop_px_median"] = int(np.median(self._crop_px))
        d, share = self._light
        if d is not None:  # the (smoothed) dominant light of the last frame, object frame
            s["light_dir"] = [round(float(x), 2) for x in d]
            s["light_share"] = round(float(share), 2)
        return s


def _exposure_scale(frame: Frame) -> float:
    """Linear pixel per unit radiance for this frame: the plane light's, else the metadata's, else 1."""
    pl = frame.results.get(PLANE_LIGHT.name)
    if pl is not None and getattr(pl, "exposure_scale", None) is not None:
        return float(pl.exposure_scale)
    s = frame.exposure.scale
    return float(s) if s is not None else 1.0


def mesh_from_bundle(bundle) -> RenderMesh:
    """The render mesh of an object bundle (:class:`illuminet.runtime.assets.bundle.Bundle`).

    The bundle stores geometry only (vertices, normals, faces: the vertices the carry mapping
    refers to). Colour comes from the object it was trained for (``bundle.json`` "object") when
    that is a file whose mesh has the same vertices (texture/UV, vertex colours, base colour);
    built-in objects are plain glazed white (:data:`DEFAULT_ALBEDO`).
    """
    mesh = RenderMesh(vertices=bundle.vertices, normals=bundle.normals, faces=bundle.faces,
                      source=f"bundle {bundle.name}")
    spec = str(bundle.meta.get("object", "") or "")
    if spec and not spec.startswith("builtin:") and Path(spec).is_file():
        try:
            look = load_render_mesh(spec)
        except ValueError as e:
            log.warning("bundle %s: object %s not readable for its colours (%s); plain albedo", bundle.name, spec, e)
            return mesh
        if look.n_vertices == mesh.n_vertices and len(look.faces) == len(mesh.faces):
            mesh.uv, mesh.colors, mesh.parts = look.uv, look.colors, look.parts
        else:
            log.warning("bundle %s: %s has %d vertices, the bundle %d; its colours cannot be matched, plain albedo",
                        bundle.name, spec, look.n_vertices, mesh.n_vertices)
    return mesh


def _load_bundle(spec: str):
    try:
        from illuminet.runtime.assets.bundle import load_bundle
    except ImportError as e:
        raise RuntimeError(
            f"[model] bundle = {spec!r}: the bundle loader illuminet.runtime.assets.bundle is not available ({e}); "
            "give RenderStage a mesh (mesh=PATH or a trimesh) instead"
        ) from None
    return load_bundle(spec)
