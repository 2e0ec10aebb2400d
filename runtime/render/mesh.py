"""Drawable meshes: what the renderer draws and with which albedo.

What this module owns
---------------------
* :class:`RenderMesh` (and its :class:`MeshPart` face runs): object-frame geometry with its albedo
  (texture x UV, vertex colours, material base colour).
* :func:`load_render_mesh`: a RenderMesh from a GLB/glTF/OBJ/PLY/STL/OFF file or a trimesh object.
  Textures are decoded with OpenCV, so Pillow is not needed (trimesh alone would drop them).
* :func:`mesh_from_bundle`: the render mesh of an object bundle, coloured by the object it was
  trained for when that object's mesh matches.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


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

    def scaled(self, s: float) -> RenderMesh:
        """The same mesh with vertex positions multiplied by ``s`` (about the object origin)."""
        if not (s > 0 and np.isfinite(s)):
            raise ValueError(f"[render] object_scale: expected a positive number, got {s!r}")
        return RenderMesh(
            self.vertices * np.float32(s),
            self.normals,
            self.faces,
            self.uv,
            self.colors,
            self.parts,
            self.source,
            self.closed,
        )

    @classmethod
    def from_trimesh(cls, mesh, source: str = "<trimesh>", texture: np.ndarray | None = None) -> RenderMesh:
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
            vertices=np.concatenate(verts),
            normals=np.concatenate(norms),
            faces=np.concatenate(faces),
            uv=np.concatenate(uvs) if any_uv else None,
            colors=np.concatenate(cols) if any_col else None,
            parts=parts,
            source=source,
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
    import io

    import trimesh
    from trimesh.exchange.obj import load_obj

    from illuminet.runtime.assets.objects import (
        ObjectLoadError,
        _check_obj_indices,
        _check_xyz,
        _text_safe,
        _TextResolver,
    )

    # not UTF-8 (a Latin-1 comment): read as Latin-1, not guessed by trimesh with an optional module
    data = _text_safe(path.read_bytes(), ".obj")
    _check_obj_indices(data, path)  # `f 0 1 2`: the object loader's check (trimesh reads 0 as the last vertex)
    try:
        loaded = load_obj(io.BytesIO(data), resolver=_TextResolver(str(path)), skip_materials=False)
    except Exception as e:  # trimesh raises many types for broken files
        raise ObjectLoadError(
            f"{path}: cannot read as a mesh: not a valid OBJ file, or a truncated one ({type(e).__name__}: {e}); "
            "expected a complete OBJ file: export or copy it again"
        ) from None
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
    for g in geoms.values():
        vis = g.get("visual")
        uv = getattr(vis, "uv", None) if vis is not None else None
        m = trimesh.Trimesh(vertices=g["vertices"], faces=g["faces"], process=False)
        _check_xyz(m, path)  # `v x y` lines: the object loader's line, not a numpy error from the normals
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
        if any_uv
        else None,
        colors=np.concatenate(
            [m.colors if m.colors is not None else np.full((m.n_vertices, 3), 255, np.uint8) for m in meshes]
        )
        if any_col
        else None,
        parts=parts,
        source=source,
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
            chunk = data[off + 8 : off + 8 + length]
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
                blob = bin_chunk[bv.get("byteOffset", 0) : bv.get("byteOffset", 0) + bv["byteLength"]]
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

    from illuminet.runtime.assets.objects import check_geometry, check_mesh_path, read_mesh

    path = Path(src)
    if not path.exists() and not path.is_symlink():
        raise ValueError(f"{path}: object mesh file not found (expected a .glb, .gltf, .obj or .ply file)")
    check_mesh_path(path, str(path))  # a directory, a symlink loop, an empty file: one line saying so
    ext = path.suffix.lower()
    if ext == ".obj":
        mesh = _load_obj(path)  # this module's own parser (materials, textures); then the same checks
        check_geometry(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False), path)
        return mesh
    if ext not in (".glb", ".gltf", ".ply", ".stl", ".off"):
        raise ValueError(f"{path}: unknown mesh kind {ext!r}; expected .glb, .gltf, .obj, .ply, .stl or .off")
    with np.errstate(all="ignore"):  # a node scaled by 1e300: the check below says so, not numpy's warnings
        loaded = read_mesh(path, process=False, label=str(path))  # ObjectLoadError (a ValueError) naming the file
        if isinstance(loaded, trimesh.Trimesh):
            check_geometry(loaded, path)  # before RenderMesh: its float32 turns 1e300 into inf
        elif isinstance(loaded, trimesh.Scene) and loaded.geometry:
            check_geometry(loaded.to_mesh(), path)
        mesh = RenderMesh.from_trimesh(loaded, source=str(path))
    if ext in (".glb", ".gltf") and mesh.uv is not None and all(p.texture is None for p in mesh.parts):
        texs = _gltf_textures(path)
        if texs:  # trimesh could not decode the images (no Pillow): give the first one to textured parts
            for p in mesh.parts:
                p.texture = texs[0]
    return mesh


def mesh_from_bundle(bundle) -> RenderMesh:
    """The render mesh of an object bundle (:class:`illuminet.runtime.assets.bundle.Bundle`).

    The bundle stores geometry only (vertices, normals, faces: the vertices the carry mapping
    refers to). Colour comes from the object it was trained for (``bundle.json`` "object") when
    that is a file whose mesh has the same vertices (texture/UV, vertex colours, base colour);
    built-in objects are plain glazed white (:data:`DEFAULT_ALBEDO`).
    """
    from illuminet.runtime.errors import BundleError

    try:  # load_bundle checks all of this; a Bundle made some other way is still one line, not a traceback
        mesh = RenderMesh(
            vertices=bundle.vertices, normals=bundle.normals, faces=bundle.faces, source=f"bundle {bundle.name}"
        )
    except ValueError as e:
        raise BundleError(f"{e}; remake the bundle (`illuminet bundle` or `illuminet train`)") from None
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
            log.warning(
                "bundle %s: %s has %d vertices, the bundle %d; its colours cannot be matched, plain albedo",
                bundle.name,
                spec,
                look.n_vertices,
                mesh.n_vertices,
            )
    return mesh
