"""Mesh files a user gives (``bundle --object``, ``datagen``, ``--viewer-model``): text in any byte
encoding reads, a broken, empty or truncated file or a path that is not a file is one line saying
which and what to do, and a huge mesh is made into a bundle in seconds, not minutes."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import trimesh

from illuminet.cli import main
from illuminet.runtime.assets.objects import ObjectLoadError, load_object
from illuminet.runtime.render.mesh import load_render_mesh

LATIN1 = b"mod\xe8le"  # "modele" with a grave accent in Latin-1: not UTF-8


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(0.1, 0.2, 0.1))


def _latin1_files(tmp_path):
    m = _box()
    obj = trimesh.exchange.obj.export_obj(m).encode()
    off = trimesh.exchange.off.export_off(m).encode()
    stl = trimesh.exchange.stl.export_stl_ascii(m).encode()
    ply_a = trimesh.exchange.ply.export_ply(m, encoding="ascii")
    ply_b = trimesh.exchange.ply.export_ply(m, encoding="binary")
    comment = b"\ncomment " + LATIN1 + b"\n"
    files = {
        "latin.obj": b"# " + LATIN1 + b"\n" + obj,
        "latin.off": b"OFF\n# " + LATIN1 + b"\n" + off.split(b"\n", 1)[1],
        "latin.stl": stl.replace(b"solid", b"solid " + LATIN1, 1),
        "ascii.ply": ply_a.replace(b"\n", comment, 2).replace(comment, b"\n", 1),
        "binary.ply": ply_b.replace(b"\n", comment, 2).replace(comment, b"\n", 1),
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    return sorted(files)


def test_text_meshes_with_a_latin1_byte_read_without_the_optional_charset_module(tmp_path, monkeypatch):
    # trimesh guessed the encoding of non-UTF-8 text with charset_normalizer: without it, every command
    # said "cannot read as a mesh (ModuleNotFoundError: No module named 'charset_normalizer')"
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # import fails as when not installed
    for name in _latin1_files(tmp_path):
        assert len(load_object(str(tmp_path / name)).faces) == 12, name
        assert len(load_render_mesh(tmp_path / name).faces) == 12, name


def test_an_obj_whose_material_library_is_latin1_keeps_its_colour(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    (tmp_path / "m.mtl").write_bytes(b"# " + LATIN1 + b"\nnewmtl red\nKd 1 0 0\n")
    obj = trimesh.exchange.obj.export_obj(_box()).encode()
    (tmp_path / "m.obj").write_bytes(b"# " + LATIN1 + b"\nmtllib m.mtl\nusemtl red\n" + obj)
    assert len(load_object(str(tmp_path / "m.obj")).faces) == 12
    np.testing.assert_allclose(load_render_mesh(tmp_path / "m.obj").parts[0].base_color, [1, 0, 0])


def test_the_bundle_command_makes_a_bundle_of_a_latin1_obj(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    _latin1_files(tmp_path)
    argv = ["bundle", "--object", str(tmp_path / "latin.obj"), "--out", str(tmp_path / "b"), "--n-proxy", "8"]
    assert main(argv + ["--transfer-rays", "64", "--directions", "64", "--quiet"]) == 0, capsys.readouterr().err
    assert (tmp_path / "b" / "bundle.json").is_file()


def _broken_files(tmp_path):
    glb = trimesh.exchange.gltf.export_glb(trimesh.Scene(_box()))
    ply = trimesh.exchange.ply.export_ply(_box(), encoding="binary")
    stl = trimesh.exchange.stl.export_stl(_box())
    (tmp_path / "empty.glb").write_bytes(b"")
    (tmp_path / "half.glb").write_bytes(glb[: len(glb) // 2])
    (tmp_path / "stub.glb").write_bytes(glb[:10])
    (tmp_path / "text.glb").write_text('{"asset": {"version": "2.0"}}')
    (tmp_path / "cut.ply").write_bytes(ply[:-20])
    (tmp_path / "cut.stl").write_bytes(stl[:100])
    (tmp_path / "board.json").write_text('{"board": {"squares_x": 11}}')
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "chair.glb").write_bytes(glb)
    (tmp_path / "loop_a.obj").symlink_to(tmp_path / "loop_b.obj")
    (tmp_path / "loop_b.obj").symlink_to(tmp_path / "loop_a.obj")
    (tmp_path / "dangling.obj").symlink_to(tmp_path / "gone.obj")


BROKEN = [
    ("empty.glb", "empty.glb: the file is empty (0 bytes), so it holds no geometry; expected a GLB"),
    ("half.glb", "half.glb: truncated GLB file: "),
    ("stub.glb", "stub.glb: truncated GLB file: 10 bytes; expected at least its 12-byte header"),
    ("text.glb", "text.glb: not a GLB file (it starts with b'{\"as', expected b'glTF')"),
    ("cut.ply", "cut.ply: cannot read as a mesh: not a valid PLY file, or a truncated one"),
    ("cut.stl", "cut.stl: truncated binary STL file: 100 bytes, its header's 12 triangles take 684; expected"),
    ("folder", "folder: is a directory (it holds chair.glb); expected builtin:"),
    ("loop_a.obj", "loop_a.obj: a symlink loop"),
    ("dangling.obj", "dangling.obj: a broken symlink"),
    # said "not a valid JSON file, or a truncated one (NotImplementedError: file_type 'json' not supported)"
    ("board.json", "board.json: not a mesh file (unknown mesh kind '.json'); expected builtin:"),
]


@pytest.mark.parametrize("name,expect", BROKEN, ids=[n for n, _ in BROKEN])
def test_a_broken_mesh_file_or_path_is_one_line_saying_what_it_is(tmp_path, capsys, name, expect):
    # an empty GLB said "IndexError: index 0 is out of bounds", a truncated one "not enough values to
    # unpack", and a folder or a symlink loop "no such file"
    _broken_files(tmp_path)
    with pytest.raises(ObjectLoadError, match="expected"):
        load_object(str(tmp_path / name))
    assert main(["bundle", "--object", str(tmp_path / name), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err and "Traceback" not in err, err
    assert "no such file" not in err, err
    assert not (tmp_path / "out").exists()
    if name != "folder":  # the renderer's own loader: the same line (a ValueError)
        with pytest.raises(ValueError, match="expected"):
            load_render_mesh(tmp_path / name)


def _bad_geometry_files(tmp_path):
    box = _box()
    v, f = box.vertices.tolist(), (box.faces + 1).tolist()
    lines = [f"v {x} {y}" for x, y, _ in v] + [f"f {a} {b} {c}" for a, b, c in f]
    (tmp_path / "xy.obj").write_text("\n".join(lines))
    lines = [f"v {x} {y} {z}" for x, y, z in v] + ["f 1 1 1", "f 2 2 3"]
    (tmp_path / "degenerate.obj").write_text("\n".join(lines))
    (tmp_path / "collinear.obj").write_text("v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n")
    lines = [f"v {x} {y} {z}" for x, y, z in v] + [f"f {a} {b} {c}" for a, b, c in f] + ["f 0 1 2 # zero"]
    (tmp_path / "zero_index.obj").write_text("\n".join(lines))
    scene = trimesh.Scene()
    scene.add_geometry(box, transform=np.diag([1e300, 1e300, 1e300, 1.0]))
    (tmp_path / "far.glb").write_bytes(trimesh.exchange.gltf.export_glb(scene))


BAD_GEOMETRY = [
    ("xy.obj", "xy.obj: 2 coordinate(s) per vertex; expected x y z"),  # an IndexError traceback
    # a bundle of nothing to draw or light, exit 0
    ("degenerate.obj", "degenerate.obj: all its 2 triangle(s) have zero area (repeated or collinear corners)"),
    ("collinear.obj", "collinear.obj: all its 1 triangle(s) have zero area"),
    # read as -1 (the last vertex): a triangle across the box, without a word
    ("zero_index.obj", "zero_index.obj: line 21 ('f 0 1 2 # zero') uses vertex index 0; expected OBJ indices from 1"),
    ("far.glb", "far.glb: 8 vertex/vertices lie 1e+299 units"),  # after ten lines of numpy overflow warnings
]


@pytest.mark.parametrize("name,expect", BAD_GEOMETRY, ids=[n for n, _ in BAD_GEOMETRY])
def test_a_mesh_without_usable_geometry_is_one_line(tmp_path, capfd, name, expect):
    _bad_geometry_files(tmp_path)
    with pytest.raises(ObjectLoadError, match="expected"):
        load_object(str(tmp_path / name))
    capfd.readouterr()
    assert main(["bundle", "--object", str(tmp_path / name), "--out", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err, err
    assert not (tmp_path / "out").exists()


def test_a_module_trimesh_lacks_is_named_as_such_not_as_a_broken_file(tmp_path, monkeypatch):
    (tmp_path / "m.glb").write_bytes(trimesh.exchange.gltf.export_glb(trimesh.Scene(_box())))

    def load(*a, **k):
        raise ModuleNotFoundError("No module named 'somecodec'", name="somecodec")

    monkeypatch.setattr(trimesh, "load", load)
    with pytest.raises(ObjectLoadError, match=r"m\.glb: reading GLB .* needs the optional module 'somecodec'.*pip"):
        load_object(str(tmp_path / "m.glb"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc refuses new folders on Linux")
def test_an_out_folder_that_cannot_be_made_names_out_before_any_work(capsys):
    assert main(["bundle", "--object", "builtin:sphere", "--out", "/proc/nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("illuminet: --out /proc/nope: cannot write a bundle there (No such file or directory")
    assert "choose another --out" in err and len(err.splitlines()) == 1


def test_farthest_points_over_many_points_sample_a_random_subset_and_small_sets_are_unchanged(monkeypatch):
    # a 2M-face scan's 1M vertices took 42 s (1000 passes over all of them) with no output
    from illuminet.models import datagen

    def reference(x, n, rng):  # the selection before the subset: what every shipped bundle was made with
        idx = [int(rng.integers(len(x)))]
        d = np.linalg.norm(x - x[idx[0]], axis=1)
        for _ in range(1, n):
            idx.append(int(np.argmax(d)))
            d = np.minimum(d, np.linalg.norm(x - x[idx[-1]], axis=1))
        return np.sort(idx)

    x = np.random.default_rng(1).normal(size=(3000, 6))
    monkeypatch.setattr(datagen, "FPS_MAX_POINTS", 3000)
    same = datagen._farthest_points(x, 40, np.random.default_rng(0))
    np.testing.assert_array_equal(same, reference(x, 40, np.random.default_rng(0)))
    monkeypatch.setattr(datagen, "FPS_MAX_POINTS", 500)
    idx = datagen._farthest_points(x, 40, np.random.default_rng(0))
    sub = np.sort(np.random.default_rng(0).choice(len(x), 500, replace=False))
    assert len(idx) == 40 and len(set(idx.tolist())) == 40 and np.all(np.diff(idx) > 0)
    assert set(idx.tolist()) <= set(sub.tolist())  # chosen among the random subset only


def test_a_big_mesh_file_says_it_is_being_read(tmp_path, monkeypatch, capsys):
    from illuminet.commands import bundle as cmd

    monkeypatch.setattr(cmd, "BIG_FILE_BYTES", 100)  # the box's OBJ is "big"
    (tmp_path / "box.obj").write_text(trimesh.exchange.obj.export_obj(_box()))
    argv = ["bundle", "--object", str(tmp_path / "box.obj"), "--out", str(tmp_path / "b"), "--n-proxy", "8"]
    assert main(argv + ["--transfer-rays", "64", "--directions", "64"]) == 0
    err = capsys.readouterr().err
    assert f"reading {tmp_path / 'box.obj'} (0 MiB) and choosing 8 lighting proxy vertices" in err, err


def test_a_closed_mesh_wound_inside_out_is_turned_outwards(tmp_path, caplog):
    """Flipped faces (normals into the object) made a bundle whose PRT lit the object black, exit 0."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    sphere.invert()
    assert sphere.volume < 0
    p = tmp_path / "inside_out.obj"
    sphere.export(p)
    with caplog.at_level("WARNING"):
        m = load_object(str(p))
    assert m.volume > 0
    centre = m.vertices.mean(0)
    assert np.all(np.einsum("ij,ij->i", m.vertex_normals, m.vertices - centre) > 0)  # every normal outwards
    assert "inside out" in caplog.text and "inside_out.obj" in caplog.text
    # an outward one is left as it is, without a word
    caplog.clear()
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ok.obj")
    assert load_object(str(tmp_path / "ok.obj")).volume > 0 and "inside out" not in caplog.text


@pytest.mark.parametrize("spec", ["", " "])
def test_an_empty_object_path_is_named_as_empty_not_as_the_current_folder(tmp_path, monkeypatch, capsys, spec):
    # Path("") is ".": "--object : is a directory (it holds ...)" listed the meshes of the current folder
    monkeypatch.chdir(tmp_path)
    _box().export(tmp_path / "box.obj")
    with pytest.raises(ObjectLoadError, match=f"object {spec!r}: empty; expected builtin:"):
        load_object(spec)
    assert main(["bundle", "--object", spec, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--object {spec!r}: empty; expected builtin:" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name,expect", BAD_GEOMETRY, ids=[n for n, _ in BAD_GEOMETRY])
def test_the_renderers_and_the_viewers_loaders_refuse_what_the_object_loader_refuses(tmp_path, capfd, name, expect):
    """The renderer's own loader (RenderStage(mesh=PATH), the API) and --viewer-model's GLB drew a mesh the
    bundle's object loader refuses: zero-area triangles (nothing to see), coordinates of 1e299 (inf once
    in float32), with numpy's overflow warnings."""
    from illuminet.runtime.stream.viewer import model_glb

    _bad_geometry_files(tmp_path)
    with pytest.raises(ValueError, match="expected") as e:
        load_render_mesh(tmp_path / name)
    assert expect in str(e.value) and "\n" not in str(e.value), str(e.value)
    with pytest.raises(ValueError) as e:
        model_glb(str(tmp_path / name))
    assert expect in str(e.value) and f"viewer_model = {str(tmp_path / name)!r}" in str(e.value), str(e.value)
    assert "Warning" not in capfd.readouterr().err


def test_the_renderers_loader_refuses_a_mesh_over_the_bundle_array_limit(tmp_path, monkeypatch):
    """The bundle loader refuses arrays over MAX_ARRAY_BYTES; the renderer's loader took any size."""
    from illuminet.runtime.assets import bundle

    (tmp_path / "box.ply").write_bytes(trimesh.exchange.ply.export_ply(_box()))
    assert len(load_render_mesh(tmp_path / "box.ply").faces) == 12
    monkeypatch.setattr(bundle, "MAX_ARRAY_BYTES", 100)  # 12 faces take 144 bytes
    with pytest.raises(ObjectLoadError, match=r"box.ply: 12 faces would take 0 MB; expected at most 0 MB"):
        load_render_mesh(tmp_path / "box.ply")
