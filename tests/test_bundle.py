"""Bundles: the shipped ones load and are small; damage is reported with the file and the problem."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from illuminet.runtime.assets.bundle import FILES, BundleError, TransferChain, builtin_names, load_bundle
from illuminet.runtime.prt import PRT_FILE

MAX_BYTES = 10 * 1024 * 1024


@pytest.mark.parametrize("name", ["vase", "bowl"])
def test_shipped_bundle_loads_and_is_small(name):
    b = load_bundle(f"builtin:{name}")
    assert b.name == name
    total = sum((b.path / f).stat().st_size for f in list(FILES.values()) + ["bundle.json"])
    assert total <= MAX_BYTES
    tr = b.meta["training"]
    assert tr["seed"] == 0 and f"--object builtin:{name}" in tr["command"]
    assert len(b.carry(np.ones((b.n_proxy, 3)))) == len(b.vertices)
    for prec in ("int8", "fp32"):
        TransferChain(b, prec)


def test_carry_is_the_weighted_sum_of_the_proxy_neighbours_and_follows_new_carry_arrays():
    b = load_bundle("builtin:vase")
    rng = np.random.default_rng(0)
    for shape in ((b.n_proxy,), (b.n_proxy, 1), (b.n_proxy, 3)):
        v = rng.random(shape).astype(np.float32)
        ref = v[b.carry_index] * b.carry_weight.reshape(b.carry_weight.shape + (1,) * (v.ndim - 1))
        got = b.carry(v)
        assert got.shape == (len(b.vertices),) + shape[1:] and got.dtype == np.float32
        np.testing.assert_allclose(got, ref.sum(1), rtol=1e-6, atol=1e-7)
    # the cached columns belong to the arrays they were made from: new carry arrays are used as given
    b.carry_index = np.zeros_like(b.carry_index)
    v = rng.random(b.n_proxy).astype(np.float32)
    np.testing.assert_allclose(b.carry(v), v[0] * b.carry_weight.sum(1), rtol=1e-6)


def test_builtin_names_lists_shipped():
    assert {"vase", "bowl"} <= set(builtin_names())


def _copy(tmp_path, name="vase"):
    src = load_bundle(f"builtin:{name}").path
    dst = tmp_path / name
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("work"))
    return dst


def test_unknown_builtin_lists_known():
    with pytest.raises(BundleError, match="builtin:vase"):
        load_bundle("builtin:teapot")
    a_file = Path(__file__).parent / "__init__.py"  # there, but a file
    with pytest.raises(BundleError, match="is a file, not a bundle folder"):  # was "folder not found"
        load_bundle(str(a_file))


def test_checksum_mismatch_names_file(tmp_path):
    d = _copy(tmp_path)
    p = d / FILES["int8"]
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"transfer_int8\.onnx: sha256"):
        load_bundle(d)


def test_missing_file_and_bad_json(tmp_path):
    d = _copy(tmp_path)
    (d / FILES["fp32"]).unlink()
    with pytest.raises(BundleError, match="missing file transfer_fp32.onnx"):
        load_bundle(d)
    (d / "bundle.json").write_text("{not json")
    with pytest.raises(BundleError, match="not valid JSON"):
        load_bundle(d)


def test_shape_mismatch_is_reported(tmp_path):
    from illuminet.models.export import finalize_bundle

    d = _copy(tmp_path)
    with np.load(d / FILES["mesh"]) as z:
        arr = {k: z[k] for k in z.files}
    arr["prior_shading"] = arr["prior_shading"][:-1]
    np.savez_compressed(d / FILES["mesh"], **arr)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))  # checksums agree, shapes do not
    with pytest.raises(BundleError, match="prior_shading must be"):
        load_bundle(d)


def test_wrong_format_version(tmp_path):
    d = _copy(tmp_path)
    meta = json.loads((d / "bundle.json").read_text())
    meta["format"] = 99
    (d / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match="format 99 is not supported"):
        load_bundle(d)


def test_a_bundle_without_faces_is_refused_at_load_and_a_run_says_so_in_one_line(tmp_path, capsys):
    # mesh.npz with faces (0, 3) and matching checksums loaded, and the render stage's RenderMesh then
    # raised a bare ValueError: a traceback through runtime/render/mesh.py instead of one line
    from illuminet.cli import main
    from illuminet.models.export import finalize_bundle
    from illuminet.runtime.render.mesh import mesh_from_bundle

    d = _copy(tmp_path)
    with np.load(d / FILES["mesh"]) as z:
        arr = {k: z[k] for k in z.files}
    arr["faces"] = np.zeros((0, 3), np.int32)
    np.savez_compressed(d / FILES["mesh"], **arr)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))  # checksums agree: only the faces are bad
    with pytest.raises(BundleError, match=r"mesh\.npz: faces must be \(F, 3\) triangles with F > 0, got \(0, 3\)"):
        load_bundle(d)
    assert main(["--set", f"model.bundle={d}", "run", "synthetic://indoor?frames=1"]) == 2
    err = capsys.readouterr().err
    assert "illuminet: " in err and "F > 0" in err and "Traceback" not in err, err
    # a Bundle that skipped the checks still reaches the renderer as a BundleError (printed in one line)
    b = load_bundle("builtin:vase")
    b.faces = np.zeros((0, 3), np.int32)
    with pytest.raises(BundleError, match="F > 0.*remake the bundle"):
        mesh_from_bundle(b)


def _edit_npz(d, name, edit):
    """Rewrite ``d/name`` with ``edit(arrays)`` applied and the checksums in bundle.json made to agree."""
    from illuminet.models.export import finalize_bundle

    with np.load(d / name) as z:
        arr = {k: z[k] for k in z.files}
    edit(arr)
    np.savez_compressed(d / name, **arr)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))


@pytest.mark.parametrize(
    "name, key, make, match",
    [
        # an IndexError traceback deep in the carry
        (
            FILES["mesh"],
            "proxy_index",
            lambda a: a.astype(np.float64),
            "array 'proxy_index' holds float64; expected int",
        ),
        (FILES["mesh"], "faces", lambda a: a.astype(np.float32), "array 'faces' holds float32; expected integers"),
        # "could not convert string to float", naming no file
        (FILES["mesh"], "vertices", lambda a: a.astype("U8"), "array 'vertices' holds <U8; expected floating-point"),
        (FILES["mesh"], "vertices", lambda a: a > 0, "array 'vertices' holds bool"),  # a silently wrong object
        (FILES["mesh"], "proxy_edges", lambda a: -a - 1, "proxy_edges index outside 0..399"),  # wrapped around
        # a bool bounce matrix shaded 50x too bright, text tables were parsed as numbers: both silently
        (PRT_FILE, "bounce_matrix", lambda a: a > 0, "prt.npz: bounce_matrix holds bool; expected floating-point"),
        (PRT_FILE, "transfer", lambda a: a.astype("U6"), "prt.npz: transfer holds <U6; expected floating-point"),
    ],
)
def test_bundle_arrays_of_the_wrong_kind_are_refused_naming_them(tmp_path, capsys, name, key, make, match):
    from illuminet.cli import main

    d = _copy(tmp_path)

    def edit(arr):
        arr[key] = make(arr[key])

    _edit_npz(d, name, edit)
    with pytest.raises(BundleError, match=re.escape(match)):
        load_bundle(d)
    assert main(["--set", f"model.bundle={d}", "run", "synthetic://indoor?frames=1"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and match in lines[0], lines


@pytest.mark.parametrize(
    "key, make, match",
    [
        # a 0-d array (a hand-written npz) was "TypeError: len() of unsized object", a traceback
        ("vertices", lambda a: np.asarray(a.ravel()[0]), "vertices must be (R, 3), got ()"),
        ("proxy_index", lambda a: np.asarray(a.ravel()[0]), "proxy_index must be (V,) render-vertex indices, got ()"),
        # no carry neighbours: numpy's "zero-size array to reduction operation minimum", naming no file
        ("carry_index", lambda a: a[:, :0], "carry_index (9026, 0) and carry_weight (9026, 0) must both be"),
    ],
)
def test_mesh_npz_arrays_of_the_wrong_shape_are_one_line_naming_the_file(tmp_path, key, make, match):
    d = _copy(tmp_path)

    def edit(arr):
        arr[key] = make(arr[key])
        if key == "carry_index":
            arr["carry_weight"] = arr["carry_weight"][:, :0]

    _edit_npz(d, FILES["mesh"], edit)
    with pytest.raises(BundleError, match=r"mesh\.npz: " + re.escape(match)):
        load_bundle(d)


@pytest.mark.parametrize("name", [FILES["mesh"], PRT_FILE])
@pytest.mark.parametrize("data", [b"hello, not an archive", b"\x93NUMPY"])
def test_a_bundle_npz_that_is_no_zip_archive_is_named_without_advice_to_unpickle_it(tmp_path, name, data):
    from illuminet.models.export import finalize_bundle

    d = _copy(tmp_path)
    if data.startswith(b"\x93NUMPY"):  # a .npy array written in its place
        with open(d / name, "wb") as f:
            np.save(f, np.zeros(3))
    else:
        (d / name).write_bytes(data)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))  # checksums agree: only the file is bad
    with pytest.raises(BundleError) as e:
        load_bundle(d)
    msg = str(e.value)
    assert f"{name}: not an npz archive" in msg and "pickle" not in msg and "\n" not in msg, msg


def test_a_bundle_json_nested_too_deeply_is_one_line(tmp_path):
    d = _copy(tmp_path)
    (d / "bundle.json").write_text('{"format": ' + "[" * 100000 + "]" * 100000 + "}")  # was a RecursionError
    with pytest.raises(BundleError, match="bundle.json: JSON nested too deeply"):
        load_bundle(d)


def test_a_mesh_npz_of_zeros_that_would_take_gigabytes_is_refused_from_its_headers(tmp_path):
    """Within the per-array limit but made of nothing: five 240 MB arrays of zeros in a 1.2 MB mesh.npz took
    3.6 GB and 28 s to relight 20 million vertices at one point, exit 0."""
    d = _copy(tmp_path)

    def zeros(arr):
        arr["vertices"] = np.zeros((2_000_000, 3), np.float32)  # 24 MB from ~25 kB

    _edit_npz(d, FILES["mesh"], zeros)
    assert (d / FILES["mesh"]).stat().st_size < 1_000_000
    with pytest.raises(BundleError, match=r"array 'vertices' of shape \(2000000, 3\) would take 23 MB from \d+ kB"):
        load_bundle(d)
