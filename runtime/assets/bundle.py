"""Object bundles: what an object ships as, and loading it with integrity and shape checks.

A bundle is a folder::

    bundle.json          metadata: object, vertex counts, sha256 + size of every file, package version;
                         for a learned transfer also the plane grid, normalisation, ONNX interface,
                         training config + seed + command and evaluation figures; for PRT how the
                         tables were made (command, seed, ray counts, timings)
    mesh.npz             render mesh (vertices, normals, faces), the lighting proxy (proxy_index into
                         the render vertices, proxy_edges), the carry mapping (carry_index,
                         carry_weight: each render vertex interpolates k proxy vertices) and
                         prior_shading (the constant-prior baseline, relative to the plane's scale)
    prt.npz              optional: precomputed radiance transfer of the proxy vertices, and optionally
                         of every render vertex (layout in :mod:`illuminet.runtime.prt`; made by
                         ``illuminet bundle``)
    transfer_fp32.onnx   optional (``illuminet train``): the learned inference chain, fp32
    transfer_int8.onnx   the same with its FC layers dynamically quantised to int8

A bundle has the ONNX pair when its ``bundle.json`` declares an ``onnx`` interface (then both files
are required); ``illuminet bundle`` makes bundles with ``mesh.npz`` + ``prt.npz`` only, which
shade physically from a light estimate (``[model] shading = "prt"``) but cannot use mode ``model``.

``builtin:NAME`` names a bundle shipped in the package (``illuminet/models/bundles/NAME``); any
other value is a folder path. :func:`load_bundle` says exactly what is wrong when something is
(missing file, checksum mismatch, array shapes that disagree with the metadata).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from illuminet.runtime.prt import PRT_FILE, PrtTables

BUNDLE_FORMAT = 1
METADATA = "bundle.json"
#: every file a bundle may hold; ``mesh`` always, the ONNX pair when ``bundle.json`` has ``onnx``, ``prt`` optional
FILES = {"mesh": "mesh.npz", "fp32": "transfer_fp32.onnx", "int8": "transfer_int8.onnx", "prt": PRT_FILE}
MODEL_FILES = ("fp32", "int8")
MESH_KEYS = (
    "vertices",
    "normals",
    "faces",
    "proxy_index",
    "proxy_edges",
    "carry_index",
    "carry_weight",
    "prior_shading",
)


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import BundleError  # noqa: E402,F401


def builtin_dir() -> Path:
    """Folder of the bundles shipped with the package (``models/bundles`` in a checkout)."""
    # runtime/assets/ sits two levels below the folder that holds models/, both in a checkout and installed
    # (illuminet/runtime/assets, illuminet/models); locating the data by path keeps runtime from importing models.
    return Path(__file__).resolve().parents[2] / "models" / "bundles"


def builtin_names() -> list[str]:
    d = builtin_dir()
    return sorted(p.name for p in d.iterdir() if (p / METADATA).is_file()) if d.is_dir() else []


def resolve_bundle(spec: str | Path) -> Path:
    """``builtin:NAME`` or a folder -> the bundle folder (not yet checked)."""
    s = str(spec)
    if not s.strip():  # Path("") is ".": the working folder would be blamed for having no bundle.json
        raise BundleError(
            f"[model] bundle is empty; expected builtin:NAME (built-in: "
            f"{', '.join('builtin:' + n for n in builtin_names()) or 'none installed'}) or a bundle folder"
        )
    if s.startswith("builtin:"):
        name = s.split(":", 1)[1]
        p = builtin_dir() / name
        if not (p / METADATA).is_file():
            raise BundleError(
                f"bundle {s!r}: no built-in bundle named {name!r}; built-in: "
                f"{', '.join('builtin:' + n for n in builtin_names()) or '(none installed)'}"
            )
        return p
    p = Path(s)
    if p.is_file() and p.name == METADATA:
        p = p.parent
    if p.exists() and not p.is_dir():  # "folder not found" sent users looking for a typo in a name that is there
        raise BundleError(
            f"bundle {s!r}: is a file, not a bundle folder (expected builtin:NAME or a bundle folder containing "
            f"{METADATA}; `illuminet bundle --object {s}` makes one from a mesh file)"
        )
    if not p.is_dir():
        raise BundleError(
            f"bundle {s!r}: folder not found (expected builtin:NAME or a bundle folder containing {METADATA})"
        )
    return p


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class Bundle:
    """A loaded, checked bundle. Arrays are read-only views of ``mesh.npz``."""

    path: Path
    meta: dict
    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    proxy_index: np.ndarray
    proxy_edges: np.ndarray
    carry_index: np.ndarray
    carry_weight: np.ndarray
    prior_shading: np.ndarray
    prt: PrtTables | None = None
    extra: dict = field(default_factory=dict)
    # carry's columns, contiguous (made on first use, for the carry arrays they were made from)
    _carry_cols: tuple | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def name(self) -> str:
        return str(self.meta.get("name", self.path.name))

    @property
    def n_proxy(self) -> int:
        return int(len(self.proxy_index))

    @property
    def proxy_vertices(self) -> np.ndarray:
        return self.vertices[self.proxy_index]

    @property
    def proxy_normals(self) -> np.ndarray:
        return self.normals[self.proxy_index]

    @property
    def has_model(self) -> bool:
        """True when the bundle holds the learned transfer (ONNX chain; ``illuminet train``)."""
        return "onnx" in self.meta

    def _no_model(self, what: str) -> BundleError:
        return BundleError(
            f"bundle {self.name} ({self.path}) has no learned model (made by `illuminet bundle`, "
            f'PRT only), so it has no {what}: use [model] shading = "prt" or "auto", or a '
            "bundle made by `illuminet train`"
        )

    def _plane(self, key: str):
        if "plane" not in self.meta:
            raise self._no_model("plane input")
        return self.meta["plane"][key]

    @property
    def grid(self) -> int:
        return int(self._plane("grid"))

    @property
    def pool(self) -> int:
        return int(self._plane("pool"))

    @property
    def extent_m(self) -> float:
        return float(self._plane("extent_m"))

    def onnx_path(self, precision: str = "int8") -> Path:
        if precision not in ("int8", "fp32"):
            raise BundleError(f"precision {precision!r}: expected 'int8' or 'fp32'")
        if not self.has_model:
            raise self._no_model('ONNX chain for shading mode "model"')
        return self.path / FILES[precision]

    def carry(self, proxy_values: np.ndarray) -> np.ndarray:
        """Proxy-vertex values (V, ...) -> render-vertex values (R, ...) by the carry weights."""
        v = np.asarray(proxy_values)
        if v.shape[0] != self.n_proxy:
            raise ValueError(f"carry: expected {self.n_proxy} proxy values, got {v.shape[0]}")
        # one gather per neighbour, summed in the same order as ``(v[index] * w).sum(1)`` (the same
        # bits), without the (R, K, ...) temporary and numpy's slow reduction over a short middle
        # axis: 0.5 ms instead of 1.7 ms per frame for the vase's 9026 render vertices; each column's
        # indices and weights contiguous (``np.take`` of an intp column): 0.10 -> 0.045 ms for (V,)
        cols = self._carry_cols
        if cols is None or cols[0] is not self.carry_index or cols[1] is not self.carry_weight:
            idx, wt = self.carry_index, self.carry_weight
            cols = (
                idx,
                wt,
                [np.ascontiguousarray(idx[:, k], dtype=np.intp) for k in range(idx.shape[1])],
                [np.ascontiguousarray(wt[:, k]) for k in range(wt.shape[1])],
            )
            self._carry_cols = cols
        _, _, idx_k, wt_k = cols
        tail = (1,) * (v.ndim - 1)
        out = np.take(v, idx_k[0], axis=0) * wt_k[0].reshape((-1,) + tail)
        for i, w in zip(idx_k[1:], wt_k[1:]):
            out += np.take(v, i, axis=0) * w.reshape((-1,) + tail)
        return out.astype(np.float32, copy=False)


def load_bundle(spec: str | Path, verify: bool = True) -> Bundle:
    """Load and check a bundle.

    Parameters
    ----------
    spec : str or Path
        ``builtin:NAME`` or a bundle folder.
    verify : bool
        Check every file's sha256 against ``bundle.json`` (a few tens of ms).

    Raises
    ------
    BundleError
        With the file and what is wrong: missing file, bad JSON, unsupported format, checksum or
        size mismatch, missing arrays, shapes that disagree with each other or with the metadata.
    """
    path = resolve_bundle(spec)
    mpath = path / METADATA
    if not mpath.is_file():
        raise BundleError(f"{path}: no {METADATA} (not a bundle folder?)")
    try:
        meta = json.loads(mpath.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(f"{mpath}: not valid JSON: {e}") from None
    except RecursionError:  # [[[[...]]]] thousands deep: a traceback from the JSON decoder
        raise BundleError(f"{mpath}: JSON nested too deeply to be a bundle's metadata; remake the bundle") from None
    except ValueError as e:  # an int of over 4300 digits: json raises a bare ValueError (a traceback)
        raise BundleError(f"{mpath}: not valid JSON: {e}") from None
    check_metadata(meta, mpath)
    required = [FILES["mesh"]] + ([FILES[k] for k in MODEL_FILES] if "onnx" in meta else [])
    for name in required:
        if name not in meta["files"]:
            raise BundleError(f"{mpath}: no checksum recorded for {name}")
    for name in FILES.values():
        rec = meta["files"].get(name)
        if rec is None:
            continue  # an optional file this bundle does not have
        p = path / name
        if not p.is_file():
            raise BundleError(f"{path}: missing file {name}")
        size = p.stat().st_size
        if size != rec.get("bytes"):
            raise BundleError(
                f"{p}: size {size} bytes, {METADATA} records {rec.get('bytes')} (file damaged or replaced)"
            )
        if verify:
            digest = _sha256(p)
            if digest != rec.get("sha256"):
                raise BundleError(
                    f"{p}: sha256 {digest} does not match {METADATA} ({rec.get('sha256')}); "
                    "the file is damaged or was replaced"
                )
    _check_npz_magic(path / FILES["mesh"])
    try:
        with np.load(path / FILES["mesh"], allow_pickle=False) as z:
            missing = [k for k in MESH_KEYS if k not in z.files]
            if missing:
                raise BundleError(f"{path / FILES['mesh']}: missing arrays {', '.join(missing)}")
            _check_npz_sizes(z, path / FILES["mesh"])
            arr = {k: z[k] for k in MESH_KEYS}
    except BundleError:
        raise
    except Exception as e:  # zip/npz errors
        raise BundleError(f"{path / FILES['mesh']}: cannot read: {e}") from None
    _check_dtypes(arr, path / FILES["mesh"])
    b = Bundle(path=path, meta=meta, **arr)
    _check_finite(b, path / FILES["mesh"])
    _check_shapes(b, path / FILES["mesh"])
    if PRT_FILE in meta["files"]:
        _check_npz_magic(path / PRT_FILE)
        try:
            with np.load(path / PRT_FILE, allow_pickle=False) as z:
                _check_npz_sizes(z, path / PRT_FILE)
                b.prt = PrtTables.from_arrays({k: z[k] for k in z.files}, b.n_proxy, len(b.vertices))
        except BundleError:
            raise
        except ValueError as e:
            raise BundleError(f"{path / PRT_FILE}: {e}") from None
        except Exception as e:  # zip/npz errors
            raise BundleError(f"{path / PRT_FILE}: cannot read: {e}") from None
    return b


def _check_npz_magic(p: Path) -> None:
    """Refuse a file that is not a zip archive (an npz) before ``np.load`` reads it: for anything else numpy
    said "This file contains pickled (object) data. If you trust the file you can load it unsafely using the
    `allow_pickle=` keyword argument" (advice to unpickle a damaged file), or loaded a ``.npy`` array in its
    place and failed with an AttributeError."""
    with open(p, "rb") as f:
        head = f.read(4)
    if head not in (b"PK\x03\x04", b"PK\x05\x06"):
        kind = "a single .npy array" if head == b"\x93NUM" else f"it starts with {head!r}"
        raise BundleError(
            f"{p}: not an npz archive ({kind}; expected a zip of arrays written by numpy.savez); the file is "
            "damaged or was replaced: remake the bundle with `illuminet bundle`"
        )


#: an array in a bundle's npz files larger than this once decompressed is refused before it is read
#: (the shipped bundles' largest is 0.3 MB; a 2000-vertex proxy's bounce matrix 8 MB)
MAX_ARRAY_BYTES = 256 * 2**20


#: an array over BOMB_MIN_BYTES decompressed that is over BOMB_RATIO times its stored size is refused: the
#: shipped bundles' arrays compress at most 8x (the visibility bits); zeros compress ~1000x
BOMB_MIN_BYTES = 16 * 2**20
BOMB_RATIO = 100


def _check_npz_sizes(z, path: Path) -> None:
    """Refuse an npz whose arrays would decompress beyond :data:`MAX_ARRAY_BYTES` each, from their
    headers, before any is read: a few kB of zeros can declare gigabytes (a zip bomb)."""
    for name in z.files:
        with z.zip.open(name + ".npy") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
            else:
                raise BundleError(f"{path}: array {name!r} has .npy format {version}; expected 1.0 or 2.0")
        nbytes = int(np.prod(shape, dtype=np.float64) * dtype.itemsize)
        stored = z.zip.getinfo(name + ".npy").compress_size
        if nbytes > BOMB_MIN_BYTES and nbytes > BOMB_RATIO * max(stored, 1):
            # within the size limit, but made of nothing: five 240 MB arrays of zeros in a 1.2 MB mesh.npz took
            # 3.6 GB and 28 s to "relight" 20 million vertices at one point, exit 0
            raise BundleError(
                f"{path}: array {name!r} of shape {tuple(shape)} would take {nbytes / 2**20:.0f} MB from "
                f"{stored / 2**10:.0f} kB stored ({nbytes / max(stored, 1):.0f}x: no mesh or table compresses like "
                f"that); the file is damaged or not a bundle: remake it with `illuminet bundle`"
            )
        if nbytes > MAX_ARRAY_BYTES:
            raise BundleError(
                f"{path}: array {name!r} of shape {tuple(shape)} would take {nbytes / 2**20:.0f} MB "
                f"(at most {MAX_ARRAY_BYTES // 2**20} MB); remake the bundle with `illuminet bundle`"
            )


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _int_list(v: object) -> bool:
    return isinstance(v, list) and all(_is_int(x) for x in v)


def check_metadata(meta: object, mpath: Path) -> None:
    """Validate the structure of ``bundle.json`` before any of it is used.

    Raises :class:`BundleError` naming the key (``files.mesh.npz.bytes``, ``plane.pool``, ...) and
    what was expected, so a hand-edited or truncated file is one line, not a ``KeyError`` deep inside.
    """

    def bad(key: str, expected: str, got: object) -> BundleError:
        return BundleError(f"{mpath}: key {key!r}: expected {expected}, got {got!r}")

    if not isinstance(meta, dict):
        raise BundleError(f"{mpath}: expected a JSON object, got a {type(meta).__name__}")
    fmt = meta.get("format")
    if fmt != BUNDLE_FORMAT or isinstance(fmt, bool):
        raise BundleError(
            f"{mpath}: bundle format {fmt!r} is not supported (this version reads format "
            f"{BUNDLE_FORMAT}); retrain or update illuminet"
        )
    for key in ("files", "vertices") + (("plane",) if "onnx" in meta else ()):
        if key not in meta:
            raise BundleError(f"{mpath}: missing key {key!r}")
    files = meta["files"]
    if not isinstance(files, dict):
        raise bad("files", "an object of file name -> {sha256, bytes}", files)
    for name, rec in files.items():
        if not isinstance(rec, dict):
            raise bad(f"files.{name}", "an object with 'sha256' and 'bytes'", rec)
        if not (_is_int(rec.get("bytes")) and rec["bytes"] >= 0):
            raise bad(f"files.{name}.bytes", "a file size (an int >= 0)", rec.get("bytes"))
        if not isinstance(rec.get("sha256"), str):
            raise bad(f"files.{name}.sha256", "a hex digest string", rec.get("sha256"))
    counts = meta["vertices"]
    if not isinstance(counts, dict):
        raise bad("vertices", "an object with 'render' and 'proxy' counts", counts)
    for key in ("render", "proxy"):
        if not (_is_int(counts.get(key)) and counts[key] > 0):
            raise bad(f"vertices.{key}", "a vertex count (an int >= 1)", counts.get(key))
    if "onnx" not in meta:
        return
    plane = meta["plane"]
    if not isinstance(plane, dict):
        raise bad("plane", "an object with 'grid', 'pool' and 'extent_m'", plane)
    for key in ("grid", "pool"):
        if not (_is_int(plane.get(key)) and plane[key] >= 1):
            raise bad(f"plane.{key}", "an int >= 1", plane.get(key))
    if plane["grid"] % plane["pool"]:
        raise bad("plane.pool", f"a divisor of plane.grid ({plane['grid']})", plane["pool"])
    ext = plane.get("extent_m")
    if not (isinstance(ext, (int, float)) and not isinstance(ext, bool) and np.isfinite(ext) and ext > 0):
        raise bad("plane.extent_m", "a finite positive number of metres", ext)
    io = meta["onnx"]
    if not isinstance(io, dict):
        raise bad("onnx", "an object with 'input' and 'outputs' shapes", io)
    inp = io.get("input")
    if not (isinstance(inp, dict) and _int_list(inp.get("plane"))):
        raise bad("onnx.input.plane", "a shape (a list of ints)", inp)
    outs = io.get("outputs")
    if not (isinstance(outs, dict) and _int_list(outs.get("shading"))):
        raise bad("onnx.outputs.shading", "a shape (a list of ints)", outs)


#: mesh.npz arrays that index vertices (integers) and those that hold numbers (floats)
MESH_INDEX_KEYS = ("faces", "proxy_index", "proxy_edges", "carry_index")
MESH_FLOAT_KEYS = ("vertices", "normals", "carry_weight", "prior_shading")


def _check_dtypes(arr: dict, where: Path) -> None:
    """Index arrays must hold integers and the others real numbers: float indices were an IndexError
    traceback, text vertices "could not convert string to float" without the file, bool vertices a
    silently wrong object."""
    for key in MESH_INDEX_KEYS + MESH_FLOAT_KEYS:
        kinds, expected = ("iu", "integers") if key in MESH_INDEX_KEYS else ("f", "floating-point numbers")
        if arr[key].dtype.kind not in kinds:
            raise BundleError(
                f"{where}: array {key!r} holds {arr[key].dtype}; expected {expected}; remake the bundle "
                "(`illuminet bundle` or `illuminet train`)"
            )


def _check_finite(b: Bundle, where: Path) -> None:
    # a NaN vertex renders nothing and a NaN weight or prior makes every shading value NaN, silently
    for key in ("vertices", "normals", "carry_weight", "prior_shading"):
        a = getattr(b, key)
        if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
            n = int(a.size - np.count_nonzero(np.isfinite(a)))
            raise BundleError(f"{where}: array {key!r} has {n} non-finite value(s) (NaN or inf); the mesh is damaged")


def _check_shapes(b: Bundle, where: Path) -> None:
    def need(cond: bool, what: str) -> None:
        if not cond:
            raise BundleError(f"{where}: {what}; remake the bundle (`illuminet bundle` or `illuminet train`)")

    # the shapes len() needs first: a 0-d vertices or proxy_index (a hand-written npz) was a TypeError traceback
    need(b.vertices.ndim == 2 and b.vertices.shape[1] == 3, f"vertices must be (R, 3), got {b.vertices.shape}")
    need(b.proxy_index.ndim == 1, f"proxy_index must be (V,) render-vertex indices, got {b.proxy_index.shape}")
    R = len(b.vertices)
    V = b.n_proxy
    counts = b.meta["vertices"]
    need(b.normals.shape == b.vertices.shape, f"normals {b.normals.shape} must match vertices {b.vertices.shape}")
    need(R > 0, "vertices is empty: the bundle has no mesh to draw")
    need(
        b.faces.ndim == 2 and b.faces.shape[1] == 3 and len(b.faces) > 0,
        f"faces must be (F, 3) triangles with F > 0, got {b.faces.shape}",
    )
    need(b.faces.min() >= 0 and b.faces.max() < R, f"faces index outside 0..{R - 1}")
    need(R == counts.get("render"), f"{R} render vertices, metadata says {counts.get('render')}")
    need(V == counts.get("proxy"), f"{V} proxy vertices, metadata says {counts.get('proxy')}")
    need(
        b.proxy_index.ndim == 1 and (V == 0 or (b.proxy_index.min() >= 0 and b.proxy_index.max() < R)),
        f"proxy_index must index the {R} render vertices",
    )
    need(
        b.proxy_edges.ndim == 2 and b.proxy_edges.shape[1] == 2,
        f"proxy_edges must be (E, 2), got {b.proxy_edges.shape}",
    )
    need(
        b.proxy_edges.size == 0 or (b.proxy_edges.min() >= 0 and b.proxy_edges.max() < V),
        f"proxy_edges index outside 0..{V - 1}",
    )
    need(
        b.carry_index.shape == b.carry_weight.shape
        and b.carry_index.ndim == 2
        and len(b.carry_index) == R
        and b.carry_index.shape[1] >= 1,  # k = 0 was numpy's "zero-size array to reduction operation minimum"
        f"carry_index {b.carry_index.shape} and carry_weight {b.carry_weight.shape} must both be (R={R}, k >= 1)",
    )
    need(b.carry_index.min() >= 0 and b.carry_index.max() < V, f"carry_index outside 0..{V - 1}")
    need(bool(np.allclose(b.carry_weight.sum(1), 1.0, atol=1e-3)), "carry_weight rows must sum to 1")
    need(b.prior_shading.shape == (V, 3), f"prior_shading must be ({V}, 3), got {b.prior_shading.shape}")
    if not b.has_model:
        return
    g, pool = b.grid, b.pool
    P = (g // pool) ** 2
    io = b.meta["onnx"]
    need(list(io["input"]["plane"]) == [1, P, 4], f"ONNX input plane {io['input']['plane']} != [1, {P}, 4]")
    need(list(io["outputs"]["shading"]) == [1, V, 3], f"ONNX output shading {io['outputs']['shading']} != [1, {V}, 3]")


class TransferChain:
    """One of a bundle's ONNX chains in onnxruntime, with its interface checked against the bundle.

    Parameters
    ----------
    bundle : Bundle
    precision : "int8" or "fp32"
    threads : int
        onnxruntime intra-op threads; 1 is fastest for this small per-frame model (no thread wake-ups).
    """

    def __init__(self, bundle: Bundle, precision: str = "int8", threads: int = 1):
        import onnxruntime as ort

        self.bundle = bundle
        self.precision = precision
        path = bundle.onnx_path(precision)
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        except Exception as e:
            raise BundleError(f"{path}: onnxruntime cannot load it: {e}") from None
        P = (bundle.grid // bundle.pool) ** 2
        V = bundle.n_proxy
        ins = {i.name: i.shape for i in self.session.get_inputs()}
        outs = {o.name: o.shape for o in self.session.get_outputs()}
        if ins.get("plane") != [1, P, 4]:
            raise BundleError(f"{path}: input 'plane' has shape {ins.get('plane')}, expected [1, {P}, 4]")
        if outs.get("shading") != [1, V, 3] or outs.get("oi") != [1, V, 3, 3]:
            raise BundleError(f"{path}: outputs {outs}, expected shading [1, {V}, 3] and oi [1, {V}, 3, 3]")

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Preprocessed plane input (P, 4) -> (OI (V, 3, 3), shading (V, 3)), both relative to s."""
        oi, sh = self.session.run(["oi", "shading"], {"plane": np.ascontiguousarray(x, np.float32)[None]})
        return oi[0], sh[0]
