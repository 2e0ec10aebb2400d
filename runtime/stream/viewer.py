"""The browser pages' assets: the static files the MJPEG server serves and the viewer's model as GLB.

What this module owns
---------------------
* :data:`STATIC_DIR` (``runtime/stream/static``, package data): ``index.html`` (the live stream
  with its overlay), ``viewer.html`` + ``viewer.js`` (the three.js page lit by the estimate) and
  ``three/`` (three.js, vendored from npm by ``tools/vendor_three.sh``; version and licence in
  ``three/VERSION`` and ``three/LICENSE``). :func:`static_file` reads one of them by URL path,
  refusing anything outside the folder.
* :func:`model_glb`: the model ``/viewer`` draws, as GLB bytes: a ``.glb`` file as it is; other
  mesh files (``.gltf`` with embedded buffers, ``.obj``, ``.ply``, ``.stl``, ``.off``) and the
  built-in objects (``builtin:vase``, ...) converted with trimesh, in the object frame (+Y up,
  metres, base on y = 0) with the renderer's default albedo as the glTF base colour.

Nothing here runs per frame: the model is made once, on the first request.
"""

from __future__ import annotations

import mimetypes
from pathlib import Path, PurePosixPath

import numpy as np

STATIC_DIR = Path(__file__).with_name("static")

#: content types of the static files (mimetypes' table differs between systems for .js and .glb)
_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".json": "application/json",
    ".css": "text/css; charset=utf-8",
    ".glb": "model/gltf-binary",
    ".png": "image/png",
    ".txt": "text/plain; charset=utf-8",
}
#: mesh files the viewer can draw (a .glb is served as it is; the others are converted)
MODEL_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")


def content_type(name: str) -> str:
    """The Content-Type of a served file name (``LICENSE``/``VERSION``: plain text)."""
    suffix = Path(name).suffix.lower()
    if suffix in _TYPES:
        return _TYPES[suffix]
    if not suffix:
        return "text/plain; charset=utf-8"
    return mimetypes.guess_type(name)[0] or "application/octet-stream"


def static_file(rel: str) -> tuple[bytes, str] | None:
    """The bytes and content type of ``STATIC_DIR/rel``, or None when there is no such file.

    ``rel`` comes from a URL: absolute paths, ``..``, backslashes and hidden names are refused
    (None), and the resolved file must lie inside :data:`STATIC_DIR`.
    """
    if not rel or "\\" in rel or "\x00" in rel:
        return None
    p = PurePosixPath(rel)
    if p.is_absolute() or any(part in ("..", ".") or part.startswith(".") for part in p.parts):
        return None
    full = STATIC_DIR.joinpath(*p.parts)
    try:
        if not full.resolve().is_relative_to(STATIC_DIR.resolve()) or not full.is_file():
            return None
        return full.read_bytes(), content_type(full.name)
    except OSError:
        return None


def check_model_spec(spec: str) -> None:
    """Refuse a viewer model that cannot be served, before any server starts (one-line message)."""
    if str(spec).startswith("builtin:"):
        from illuminet.runtime.assets.objects import BUILTIN_OBJECTS

        name = str(spec).split(":", 1)[1]
        if name not in BUILTIN_OBJECTS:
            raise ValueError(
                f"[output] viewer_model = {spec!r}: unknown built-in object; expected "
                f"builtin:{'|'.join(BUILTIN_OBJECTS)} or a mesh file"
            )
        return
    from illuminet.runtime.assets.objects import ObjectLoadError, check_mesh_path

    path = Path(spec)
    try:
        # a folder, a symlink loop, a dangling link, an empty file: said as such (a folder was "no such file")
        check_mesh_path(path, f"[output] viewer_model = {spec!r}")
    except ObjectLoadError as e:
        raise ValueError(f"{e} (--viewer-model PATH)") from None
    if path.suffix.lower() not in MODEL_SUFFIXES:
        raise ValueError(
            f"[output] viewer_model = {spec!r}: unknown mesh format {path.suffix!r}; expected one of "
            f"{', '.join(MODEL_SUFFIXES)}"
        )


def model_glb(spec: str, scale: float = 1.0) -> bytes:
    """The viewer's model as GLB bytes.

    Parameters
    ----------
    spec : str
        ``builtin:NAME`` or a mesh file (see :data:`MODEL_SUFFIXES`). A ``.glb`` is returned as it
        is (its own size and materials: the author's choice); other files are loaded with
        :func:`~illuminet.runtime.assets.objects.load_object` keeping their size (metres).
    scale : float
        ``[render] object_scale``, applied to converted models (as the renderer draws them).
    """
    check_model_spec(spec)
    import trimesh

    if not str(spec).startswith("builtin:") and Path(spec).suffix.lower() == ".glb":
        from illuminet.runtime.assets.objects import ObjectLoadError, check_glb

        try:
            check_glb(Path(spec))  # truncated or not a GLB at all: from the header, not an IndexError
        except ObjectLoadError as e:
            raise ValueError(f"[output] viewer_model = {spec!r}: {e}") from None
        try:
            scene = trimesh.load(str(spec), force="scene")
        except Exception as e:  # noqa: BLE001 (trimesh raises many types for a broken file)
            raise ValueError(f"[output] viewer_model = {spec!r}: not a readable glTF binary ({e})") from None
        if not any(len(getattr(g, "faces", ())) for g in scene.geometry.values()):
            raise ValueError(f"[output] viewer_model = {spec!r}: holds no triangles to draw")
        from illuminet.runtime.assets.objects import check_geometry

        try:  # what the bundle's and the renderer's loaders refuse: NaN, far stray vertices, no area, too large
            with np.errstate(all="ignore"):
                check_geometry(scene.to_mesh(), Path(spec))
        except ObjectLoadError as e:
            raise ValueError(f"[output] viewer_model = {spec!r}: {e}") from None
        return Path(spec).read_bytes()

    from illuminet.runtime.assets.objects import load_object
    from illuminet.runtime.render.mesh import DEFAULT_ALBEDO

    try:
        mesh = load_object(str(spec), height=None)
    except Exception as e:  # noqa: BLE001 (an empty or broken mesh file: named, not a traceback)
        raise ValueError(f"[output] viewer_model = {spec!r}: cannot load it as a mesh ({e})") from None
    if len(mesh.faces) == 0:
        raise ValueError(f"[output] viewer_model = {spec!r}: holds no triangles to draw")
    if scale != 1.0:
        mesh.apply_scale(float(scale))
    visual = getattr(mesh, "visual", None)
    kind = getattr(visual, "kind", None)
    plain = visual is None or kind is None or (kind == "texture" and not _texture_image(visual))
    if plain:  # no texture or colours of its own: the grey the project's renderer gives it
        a = float(DEFAULT_ALBEDO)
        mesh.visual = trimesh.visual.TextureVisuals(
            material=trimesh.visual.material.PBRMaterial(
                baseColorFactor=np.array([a, a, a, 1.0]), metallicFactor=0.0, roughnessFactor=0.9
            )
        )
    # with normals: without them glTF viewers shade flat (faceted)
    try:
        return trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), include_normals=True)
    except Exception as e:  # noqa: BLE001 (trimesh raises many types, e.g. a missing Pillow for a texture)
        raise ValueError(
            f"[output] viewer_model = {spec!r}: cannot convert it to glTF ({type(e).__name__}: {e}); "
            "expected a mesh trimesh can export, or give a .glb"
        ) from None


def _texture_image(visual) -> bool:
    """Whether a texture visual has an image to export. An OBJ with texture coordinates and no
    material file gets trimesh's default material, whose image is a stand-in that raises when
    touched without Pillow: exporting it was a traceback at start (``--viewer-model spot.obj``)."""
    material = getattr(visual, "material", None)
    try:
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        return image is not None and hasattr(image, "size")
    except Exception:  # noqa: BLE001 (trimesh's ExceptionWrapper re-raises the missing import)
        return False
