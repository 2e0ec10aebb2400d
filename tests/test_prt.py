"""Precomputed radiance transfer: the tables (models/prt.py), their run-time evaluation (runtime/prt.py),
the shading stage's "prt" mode, PRT-only bundles and `illuminet bundle`."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from illuminet.cli import main
from illuminet.models.prt import compute_prt, interreflection
from illuminet.runtime.assets.bundle import BundleError, TransferChain, load_bundle
from illuminet.runtime.assets.objects import builtin_object
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.groundtruth.visibility import exact_visibility
from illuminet.runtime.prt import KERNEL_RADIUS, floor_factor, prt_geometry, prt_irradiance, unoccluded_transfer
from illuminet.runtime.scene import LIGHT, PLANE_LIGHT, SHADING, LightEstimate
from illuminet.runtime.sh import SH_A_HAT, sh9
from illuminet.runtime.stages.shading import ShadingStage

from ._learn_helpers import plane_light

FAST = {"transfer_rays": 1024, "table_directions": 512}


def _mesh_prt(name: str, albedo: float = 0.0, floor_shadow: bool = False):
    """PRT of a built-in proxy; without the floor's shadow by default (the formula tests: the object's
    self-visibility alone), see test_floor_under_the_object_is_its_shadow for the floor."""
    mesh = builtin_object(name, "proxy")
    res = compute_prt(mesh, mesh.vertices, mesh.vertex_normals, albedo=albedo, floor_shadow=floor_shadow, **FAST)
    return mesh, res


def test_floor_under_the_object_is_its_shadow():
    """A vertex resting on the floor sees no light from below (the floor there is under the object);
    a down-facing vertex higher up sees the floor lit around the object."""
    mesh, res = _mesh_prt("sphere", floor_shadow=True)
    _, free = _mesh_prt("sphere", floor_shadow=False)
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    # uniform radiance 1 from every direction: the DC transfer is the irradiance. The lowest vertex
    # looks at the contact point; the ring just above it at the floor in the sphere's own shadow
    lowest = np.argmin(v[:, 1])
    assert res.transfer[lowest, 0] < 0.05 * free.transfer[lowest, 0]
    bottom = v[:, 1] < 0.01
    assert res.transfer[bottom, 0].mean() < 0.3 * free.transfer[bottom, 0].mean()
    side_down = (n[:, 1] < -0.3) & (n[:, 1] > -0.7) & (v[:, 1] > 0.05)
    assert side_down.any()
    ratio = res.transfer[side_down, 0] / free.transfer[side_down, 0]
    assert (ratio > 0.3).all() and (ratio < 1.0).all(), ratio


@pytest.fixture(scope="module")
def sphere():
    return _mesh_prt("sphere")


@pytest.fixture(scope="module")
def bowl():
    return _mesh_prt("bowl", albedo=0.5)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _ambient(level=1.0, seed=0):
    """Irradiance SH of a smooth, everywhere-positive environment (floor below included)."""
    sh = np.random.default_rng(seed).normal(size=(9, 3)) * 0.05 * level
    sh[0] = level * np.array([2.0, 1.9, 1.7])
    return sh


def test_unoccluded_sphere_transfer_is_the_no_visibility_formula(sphere):
    mesh, res = sphere
    n = np.asarray(mesh.vertex_normals)
    # a convex object occludes none of its own directions: the closed form, lower hemisphere included
    assert np.allclose(res.transfer, unoccluded_transfer(n), atol=1e-6)
    assert np.allclose(res.transfer, SH_A_HAT * sh9(n), atol=1e-6)
    # so E_i = T_i . L_radiance = sh9(n_i) @ sh9_irradiance
    est = LightEstimate(sh9=_ambient(), primary_dir=None, primary_rgb=np.zeros(3))
    E = prt_irradiance(res.tables(), mesh.vertices, n, est)
    assert np.allclose(E, np.maximum(sh9(n) @ est.sh9, 0), rtol=1e-5, atol=1e-5)
    # vertices facing the floor keep the floor's light (the lower hemisphere is not zeroed)
    down = n[:, 1] < -0.9
    assert down.any() and (E[down] > 0.3).all()


def test_concave_bowl_has_less_transfer_inside(bowl):
    mesh, res = bowl
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    ao = res.transfer[:, 0] / unoccluded_transfer(n)[:, 0]
    radial = v[:, [0, 2]] / np.maximum(np.linalg.norm(v[:, [0, 2]], axis=1, keepdims=True), 1e-9)
    inward = np.einsum("vx,vx->v", n[:, [0, 2]], radial)
    inside = (inward < -0.3) & (v[:, 1] > 0.02)  # the inner wall
    outside = (inward > 0.3) & (v[:, 1] > 0.02)  # the outer wall
    assert inside.sum() > 20 and outside.sum() > 20
    assert ao[inside].mean() < ao[outside].mean() - 0.15
    assert (ao <= 1.0 + 1e-4).all() and (ao > 0).all()
    # every transfer is at most the unoccluded one in the DC term, the band-1 vectors shrink too
    assert (
        np.linalg.norm(res.transfer[inside, 1:4], axis=1).mean()
        < np.linalg.norm(unoccluded_transfer(n)[inside, 1:4], axis=1).mean()
    )


def test_primary_visibility_table(bowl):
    mesh, res = bowl
    tab = res.tables()
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    bottom_in = (np.linalg.norm(v[:, [0, 2]], axis=1) < 0.03) & (n[:, 1] > 0.9) & (v[:, 1] > 0.005)
    facing_down = n[:, 1] < -0.8
    assert bottom_in.any() and facing_down.any()
    up = tab.primary_visibility(_unit([0.05, 1.0, 0.02]))
    assert np.allclose(up[bottom_in], 1.0)  # lit through the opening
    assert np.allclose(up[facing_down], 0.0)  # facing away
    low = _unit([np.cos(np.deg2rad(20)), np.sin(np.deg2rad(20)), 0.0])
    assert np.allclose(tab.primary_visibility(low)[bottom_in], 0.0)  # the bowl's wall is in the way
    # below the floor nothing is lit
    assert np.allclose(tab.primary_visibility(_unit([0.3, -0.4, 0.2])), 0.0)
    # against exact ray casts towards a distant light, away from shadow edges
    d = _unit([0.6, 0.7, -0.3])
    exact = exact_visibility(mesh, v, d[None] * 100.0, normals=n)[:, 0] & (n @ d > 0)
    soft = tab.primary_visibility(d)
    assert np.mean(np.round(soft) != exact) < 0.05
    # no popping: a light moving in 0.25 degree steps changes each vertex's visibility gradually
    angles = np.deg2rad(np.arange(10.0, 80.0, 0.25))
    sweep = np.stack([tab.primary_visibility(np.array([np.cos(a), np.sin(a), 0.1])) for a in angles])
    assert np.abs(np.diff(sweep, axis=0)).max() < 0.2


def test_near_light_visibility_per_vertex_matches_distant_when_far(bowl):
    mesh, res = bowl
    tab = res.tables()
    d = _unit([0.3, 0.9, 0.2])
    far = tab.primary_visibility_per_vertex(np.tile(d, (len(mesh.vertices), 1)))
    assert np.allclose(far, tab.primary_visibility(d), atol=1e-6)


def test_near_light_visibility_per_vertex_is_the_kernel_average(bowl):
    """A lamp close to the object spreads the vertices' directions over many table directions: each
    vertex's value is still the kernel-weighted mean of its own neighbours (the dense sum)."""
    mesh, res = bowl
    tab = res.tables()
    pos = np.array([0.08, 0.12, 0.03])  # a few centimetres from the bowl: directions ~90 degrees apart
    v = np.asarray(mesh.vertices)
    d = (pos - v) / np.linalg.norm(pos - v, axis=1, keepdims=True)
    cos = d @ tab.directions.T
    r2 = (2.0 * np.sin(KERNEL_RADIUS * np.sqrt(4.0 * np.pi / len(tab.directions)) / 2.0)) ** 2
    w = np.maximum(1.0 - (2.0 - 2.0 * cos) / r2, 0.0) ** 2
    dense = (w * tab.visibility.T).sum(1) / w.sum(1) * floor_factor(d[:, 1])
    got = tab.primary_visibility_per_vertex(d)
    assert np.allclose(got, dense, atol=1e-6)
    assert 0.05 < got.mean() < 0.95  # partly shadowed: the test compares something


def test_precomputed_geometry_shades_the_same(sphere):
    mesh, res = sphere
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    geom = prt_geometry(v, n)
    for pos in (None, np.array([0.5, 0.4, -0.2]), np.array([0.05, 0.3, 0.0])):
        d = _unit([0.5, 0.4, -0.2] if pos is None else pos)
        est = LightEstimate(sh9=_ambient(0.3), primary_dir=d, primary_rgb=np.array([3.0, 2.8, 2.5]), primary_pos=pos)
        a = prt_irradiance(res.tables(), v, n, est)
        b = prt_irradiance(res.tables(), v, n, est, geom)
        assert np.allclose(a, b, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="same shape"):
        prt_geometry(v, n[:-1])


def test_primary_light_from_plus_x_lights_plus_x_and_leaves_minus_x_ambient(sphere):
    mesh, res = sphere
    n = np.asarray(mesh.vertex_normals)
    d = _unit([1.0, 0.25, 0.0])  # from +X, a little above the floor's horizon
    est = LightEstimate(sh9=_ambient(0.3), primary_dir=d, primary_rgb=np.array([3.0, 2.8, 2.5]))
    E = prt_irradiance(res.tables(), mesh.vertices, n, est)
    ambient = np.maximum(res.transfer @ est.radiance_sh9(), 0)
    plus, minus = n @ d > 0.5, n @ d < -0.05
    assert np.allclose(E[minus], ambient[minus], atol=1e-6)  # only the ambient light: the ambient level
    assert (E[minus] > 0.1).all()  # not black
    assert np.allclose(E[plus], ambient[plus] + (n[plus] @ d)[:, None] * est.primary_rgb, rtol=1e-4)


def test_near_light_falls_off_with_distance(sphere):
    mesh, res = sphere
    n = np.asarray(mesh.vertex_normals)
    pos = np.array([0.6, 0.4, 0.0])
    est = LightEstimate(sh9=np.zeros((9, 3)), primary_dir=_unit(pos), primary_rgb=np.ones(3), primary_pos=pos)
    E = prt_irradiance(res.tables(), mesh.vertices, n, est)[:, 0]
    v = np.asarray(mesh.vertices)
    to = pos - v
    r = np.linalg.norm(to, axis=1)
    want = np.maximum(np.einsum("vx,vx->v", n, to / r[:, None]), 0) * (pos @ pos) / r**2
    lit = np.einsum("vx,vx->v", n, to / r[:, None]) > 0.3
    assert np.allclose(E[lit], want[lit], rtol=1e-4)


def test_the_bounces_converge_to_the_multi_bounce_solution(bowl):
    _, res = bowl
    L = np.zeros(9)
    L[0] = np.sqrt(4 * np.pi)  # a white furnace: uniform radiance 1
    e0 = res.transfer @ L
    e1 = interreflection(res, 0.5, 1) @ L
    ref = interreflection(res, 0.5, 40) @ L
    assert res.bounces == 8
    # the stored bounce is the sum of the 8 bounces, and bounce_primary the first alone
    assert np.allclose(e0 + res.bounce @ L, interreflection(res, 0.5, 8) @ L, atol=1e-4)
    assert np.allclose(e1, e0 + res.bounce_primary @ L, atol=1e-4)
    assert (e1 >= e0 - 1e-6).all()
    assert np.abs(e1 - ref).mean() < 0.5 * np.abs(e0 - ref).mean()
    # 8 bounces at albedo 0.5: within 0.1 % of converged everywhere
    assert np.abs(e0 + res.bounce @ L - ref).max() < 1e-3 * ref.max()
    # a single bounce is what --bounces 1 stores, with no separate primary array
    mesh = builtin_object("bowl", "proxy")
    one = compute_prt(mesh, mesh.vertices, mesh.vertex_normals, albedo=0.5, floor_shadow=False, bounces=1, **FAST)
    assert one.bounce_primary is None and "bounce_primary" not in one.arrays()
    assert np.allclose(one.bounce, res.bounce_primary, atol=1e-5)


def test_the_bounce_matrix_is_every_bounce_of_a_direct_light(bowl):
    _, res = bowl
    M = res.bounce_matrix
    assert M is not None and M.shape == (len(res.transfer),) * 2 and (M >= -1e-6).all()
    # the SH bounce is every bounce of the transfer's direct light: the matrix gives it from any direct light
    rng = np.random.default_rng(3)
    for _ in range(3):
        L = rng.normal(size=9)
        np.testing.assert_allclose(M @ (res.transfer @ L), res.bounce @ L, rtol=1e-4, atol=1e-5)
    # the light on the bowl's outside never comes back to it; the inside reflects onto itself
    inside = res.transfer[:, 0] < 0.9 * res.transfer[:, 0].max()  # occluded: the inside
    assert inside.any() and (~inside).any()
    assert M[:, ~inside].sum(0).mean() < 0.25 * M[:, inside].sum(0).mean()
    # a proxy above MAX_BOUNCE_MATRIX vertices gets none (V x V would not fit a board's memory)
    from illuminet.models import prt as P

    mesh = builtin_object("bowl", "proxy")
    old, P.MAX_BOUNCE_MATRIX = P.MAX_BOUNCE_MATRIX, 10
    try:
        small = compute_prt(mesh, mesh.vertices, mesh.vertex_normals, albedo=0.5, floor_shadow=False, **FAST)
    finally:
        P.MAX_BOUNCE_MATRIX = old
    assert small.bounce_matrix is None and "bounce_matrix" not in small.arrays()


def test_every_long_step_reports_progress():
    """`illuminet bundle` draws a bar per step: the bounce matrix (20 s of a 36k-vertex scan's 30 s,
    after the visibility bar had finished) once ran with none, so the command looked hung."""
    mesh = builtin_object("bowl", "proxy")
    seen: dict[str, list[tuple[int, int]]] = {}
    res = compute_prt(
        mesh,
        mesh.vertices,
        mesh.vertex_normals,
        albedo=0.5,
        floor_shadow=False,
        progress=lambda step, done, total: seen.setdefault(step, []).append((done, total)),
        **FAST,
    )
    assert res.bounce_matrix is not None
    assert {"transfer", "visibility", "bounce"} <= set(seen)
    n = len(mesh.vertices)
    assert seen["bounce"][-1] == (n, n) and len(seen["bounce"]) > 1  # advances block by block


def test_the_primary_light_bounces_its_own_direct_light_and_the_ambient_light_converged(bowl):
    mesh, res = bowl
    t = res.tables()
    n = np.asarray(mesh.vertex_normals)
    amb = LightEstimate(sh9=_ambient(1.0), primary_dir=None, primary_rgb=np.zeros(3))
    prim = LightEstimate(sh9=np.zeros((9, 3)), primary_dir=_unit([0.3, 0.8, 0.2]), primary_rgb=np.ones(3))
    Ea = prt_irradiance(t, mesh.vertices, n, amb)
    Ep = prt_irradiance(t, mesh.vertices, n, prim)
    from illuminet.runtime.prt import primary_radiance_sh9

    L = amb.radiance_sh9()
    np.testing.assert_allclose(Ea, np.maximum(t.transfer @ L + t.bounce @ L, 0), rtol=1e-5, atol=1e-6)
    direct = prt_irradiance(
        dataclasses.replace(t, bounce=None, bounce_primary=None, bounce_matrix=None), mesh.vertices, n, prim
    )
    want = np.maximum(direct + t.bounce_matrix @ direct, 0)
    np.testing.assert_allclose(Ep, want, rtol=1e-4, atol=1e-5)
    # tables without the matrix (bundles before it): the first bounce of the primary's SH2 lobe
    Eo = prt_irradiance(dataclasses.replace(t, bounce_matrix=None), mesh.vertices, n, prim)
    want = np.maximum(direct + t.bounce_primary @ primary_radiance_sh9(prim.primary_dir, prim.primary_rgb), 0)
    np.testing.assert_allclose(Eo, want, rtol=1e-5, atol=1e-6)
    # a lamp above the bowl's mouth lights its inside through the bounces more than one low at its side
    up = dataclasses.replace(prim, primary_dir=_unit([0.0, 1.0, 0.0]), primary_pos=np.array([0.0, 0.5, 0.0]))
    side = dataclasses.replace(prim, primary_dir=_unit([1.0, 0.05, 0.0]), primary_pos=np.array([0.5, 0.025, 0.0]))
    bounce_up = prt_irradiance(t, mesh.vertices, n, up) - prt_irradiance(
        dataclasses.replace(t, bounce=None, bounce_primary=None, bounce_matrix=None), mesh.vertices, n, up
    )
    bounce_side = prt_irradiance(t, mesh.vertices, n, side) - prt_irradiance(
        dataclasses.replace(t, bounce=None, bounce_primary=None, bounce_matrix=None), mesh.vertices, n, side
    )
    assert bounce_up.mean() > 0 and bounce_side.mean() < 0.1 * bounce_up.mean()
    # ... which the primary's SH2 lobe could not tell: it bounced light into the bowl from the low lamp too
    lobe = dataclasses.replace(t, bounce_matrix=None)
    lobe_side = prt_irradiance(lobe, mesh.vertices, n, side) - prt_irradiance(
        dataclasses.replace(t, bounce=None, bounce_primary=None, bounce_matrix=None), mesh.vertices, n, side
    )
    assert lobe_side.mean() > 5.0 * max(float(bounce_side.mean()), 1e-9)


# --------------------------------------------------------------------------- bundles and the stage


def _write_mesh(path):
    """A small concave mesh (a torus: its hole shadows its inner side) written as PLY."""
    trimesh.creation.torus(0.08, 0.03).export(path)
    return path


@pytest.fixture(scope="module")
def prt_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("prtb")
    mesh = _write_mesh(d / "thing.ply")
    out = d / "bundle"
    rc = main(
        [
            "bundle",
            "--object",
            str(mesh),
            "--out",
            str(out),
            "--height",
            "0.15",
            "--n-proxy",
            "120",
            "--transfer-rays",
            "512",
            "--directions",
            "256",
            "--quiet",
        ]
    )
    assert rc == 0
    return out


def _stage(bundle, **model):
    cfg = apply_overrides(defaults(), [("model", "bundle", str(bundle))] + [("model", k, v) for k, v in model.items()])
    st = ShadingStage(cfg)
    st.open()
    return st


def _frame(pl=None, light=None):
    f = Frame(
        seq=0,
        t_device_ns=0,
        t_host_ns=0,
        color=np.zeros((4, 4, 3), np.uint8),
        depth=None,
        intrinsics=Intrinsics(1, 1, 1, 1, 4, 4),
    )
    if pl is not None:
        f = f.with_result(PLANE_LIGHT, pl)
    if light is not None:
        f = f.with_result(LIGHT, light)
    return f


def _estimate():
    return LightEstimate(sh9=_ambient(0.5), primary_dir=_unit([0.4, 0.8, 0.2]), primary_rgb=np.array([2.0, 1.8, 1.5]))


def test_bundle_command_makes_a_prt_only_bundle_that_loads_and_shades(prt_bundle):
    b = load_bundle(prt_bundle)
    assert not b.has_model and b.prt is not None and b.n_proxy == 120
    assert set(b.meta["files"]) == {"mesh.npz", "prt.npz"}
    assert b.meta["prt"]["seed"] == 0 and "illuminet bundle" in b.meta["prt"]["command"]
    assert abs(np.ptp(b.vertices[:, 1]) - 0.15) < 1e-4
    assert len(b.carry(np.ones((b.n_proxy, 3)))) == len(b.vertices)
    st = _stage(prt_bundle, shading="prt", temporal_smoothing=0.0)
    est = _estimate()
    out = st.process(_frame(light=est)).results[SHADING.name]
    assert out.method == "prt" and out.irradiance.shape == (120, 3) and np.isfinite(out.irradiance).all()
    assert (out.irradiance > 0).any()
    assert np.allclose(out.dominant_dir, est.primary_dir) and out.dominant_share == pytest.approx(est.primary_share())
    # the constant baseline works from the uniform-environment prior (1 - ambient occlusion)
    c = _stage(prt_bundle, shading="constant").predict(plane_light())
    assert c.irradiance.shape == (120, 3) and (b.prior_shading <= 1.0 + 1e-4).all()


def test_the_shading_is_computed_again_only_when_the_light_changes(prt_bundle):
    st = _stage(prt_bundle, shading="prt", temporal_smoothing=0.0)
    est = _estimate()
    first = st.process(_frame(light=est)).results[SHADING.name]
    # a frame between two estimates: the same light with another pose -> the same (read-only) arrays
    moved = dataclasses.replace(est, T_cam_obj=np.eye(4))
    again = st.process(_frame(light=moved)).results[SHADING.name]
    assert again.irradiance is first.irradiance and not first.irradiance.flags.writeable
    with pytest.raises(ValueError):
        first.irradiance[0, 0] = 1.0
    # a new estimate (brighter primary light, or the same light moved) is shaded anew
    brighter = dataclasses.replace(est, primary_rgb=est.primary_rgb * 2)
    b = st.process(_frame(light=brighter)).results[SHADING.name]
    assert b.irradiance is not first.irradiance and b.irradiance.sum() > first.irradiance.sum()
    near = dataclasses.replace(est, primary_pos=np.array([0.3, 0.6, 0.1]))
    n = st.process(_frame(light=near)).results[SHADING.name]
    assert not np.allclose(n.irradiance, b.irradiance)
    assert np.allclose(st.process(_frame(light=est)).results[SHADING.name].irradiance, first.irradiance)


def test_prt_only_bundle_refuses_model_mode_in_one_line(prt_bundle):
    with pytest.raises(BundleError, match="has no learned model") as e:
        _stage(prt_bundle, shading="model")
    assert "\n" not in str(e.value)
    with pytest.raises(BundleError, match="no learned model"):
        TransferChain(load_bundle(prt_bundle))


def test_stage_contract_follows_the_mode(prt_bundle):
    assert _stage(prt_bundle, shading="prt").requires == (LIGHT,)
    st = _stage(prt_bundle, shading="auto", temporal_smoothing=0.0)
    assert st.requires == (PLANE_LIGHT,) and st.optional == (LIGHT,)
    assert _stage("builtin:vase", shading="sh").optional == ()
    # auto: PRT on frames with an estimate; without one a PRT-only bundle falls back to ambient
    assert st.process(_frame(plane_light(), _estimate())).results[SHADING.name].method == "prt"
    assert st.process(_frame(plane_light())).results[SHADING.name].method == "ambient"
    # a trained bundle with PRT: the estimate wins, else its learned model
    vase = _stage("builtin:vase", shading="auto", temporal_smoothing=0.0)
    assert vase.process(_frame(plane_light(), _estimate())).results[SHADING.name].method == "prt"
    assert vase.process(_frame(plane_light())).results[SHADING.name].method == "model:int8"
    # prt mode without an estimate on the frame is a frame error naming the key
    with pytest.raises(Exception, match=r"results\['light'\]"):
        _stage(prt_bundle, shading="prt").process(_frame(plane_light()))


def test_prt_mode_on_a_bundle_without_tables_names_the_command(tmp_path):
    import shutil

    from illuminet.models.export import finalize_bundle

    d = tmp_path / "vase"
    shutil.copytree(load_bundle("builtin:vase").path, d)
    (d / "prt.npz").unlink()
    meta = json.loads((d / "bundle.json").read_text())
    meta.pop("prt")
    finalize_bundle(d, meta)
    with pytest.raises(BundleError, match="illuminet bundle --object builtin:vase"):
        _stage(d, shading="prt")


def _write_prt(d, arr):
    """Write ``arr`` as bundle ``d``'s prt.npz, with bundle.json's checksum brought up to date."""
    from illuminet.models.export import finalize_bundle

    np.savez_compressed(d / "prt.npz", **arr)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))


def test_damaged_prt_table_is_reported(tmp_path, prt_bundle):
    import shutil

    d = tmp_path / "b"
    shutil.copytree(prt_bundle, d)
    with np.load(prt_bundle / "prt.npz") as z:
        good = {k: z[k] for k in z.files}
    assert good["bounce_matrix"].shape == (120, 120)
    assert good["floor_shadow"].shape == (120, len(good["floor_dirs"]))
    # each array cut by one row or column, the others intact: named with the shape it must have
    for key, cut, message in [
        ("transfer", lambda a: a[:-1], r"prt\.npz: transfer must be \(120, 9\)"),
        # the primary light's bounce matrix is checked the same way
        ("bounce_matrix", lambda a: a[:, :-1], r"prt\.npz: bounce_matrix must be \(120, 120\)"),
        # ... and the primary light's floor-shadow table
        ("floor_shadow", lambda a: a[:-1], r"prt\.npz: floor_shadow must be \(120, 512\)"),
    ]:
        _write_prt(d, {**good, key: cut(good[key])})
        with pytest.raises(BundleError, match=message):
            load_bundle(d)


def test_an_array_declaring_gigabytes_is_refused_before_it_is_read(tmp_path, prt_bundle):
    """A zip bomb: a few bytes of npz whose header declares a 3.6 GB bounce matrix."""
    import io
    import shutil
    import zipfile

    from illuminet.models.export import finalize_bundle

    d = tmp_path / "b"
    shutil.copytree(prt_bundle, d)
    with np.load(d / "prt.npz") as z:
        arr = {k: z[k] for k in z.files if k != "bounce_matrix"}
    np.savez_compressed(d / "prt.npz", **arr)
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f4", "fortran_order": False, "shape": (30000, 30000)})
    with zipfile.ZipFile(d / "prt.npz", "a", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("bounce_matrix.npy", b"\x93NUMPY\x01\x00" + head.getvalue()[8:] + bytes(64))
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))
    with pytest.raises(
        BundleError, match=r"prt\.npz: array 'bounce_matrix' of shape \(30000, 30000\) would take 3433 MB"
    ):
        load_bundle(d)


@pytest.mark.parametrize("name", ["vase", "bowl"])
def test_shipped_bundles_have_prt_made_by_the_command(name):
    b = load_bundle(f"builtin:{name}")
    assert b.has_model and b.prt is not None and b.prt.bounce is not None
    p = b.meta["prt"]
    assert p["command"].startswith(f"illuminet bundle --object builtin:{name}") and p["seed"] == 0
    # proxy tables (transfer, 4096-direction visibility, bounce matrix, floor shadow: ~0.5 MB) + the
    # transfer and the two bounce arrays of every render vertex (9026 x 9 x 3 float32), compressed
    assert (b.path / "prt.npz").stat().st_size < 1536 * 1024
    assert b.prt.floor_shadow is not None and b.prt.bounce_matrix is not None
    # the inside of the object is darker in the transfer than outside on average
    ao = b.prt.transfer[:, 0] / unoccluded_transfer(b.proxy_normals)[:, 0]
    assert ao.min() < 0.7 and ao.max() > 0.95
    # the render-mesh transfer is the same integral: at the proxy's own vertices it matches the proxy's
    assert p["render_transfer"]["vertices"] == len(b.vertices)
    rt = b.prt.render_transfer[b.proxy_index]
    assert np.abs(rt - b.prt.transfer).max() < 1e-3 * np.abs(b.prt.transfer).max() + 1e-6
    # ... and between them it holds occlusion detail the carried proxy blurs (grooves, the lip)
    carried = b.carry(b.prt.transfer)[:, 0]
    assert np.percentile(np.abs(b.prt.render_transfer[:, 0] - carried), 99) > 0.05 * b.prt.render_transfer[:, 0].max()


@pytest.fixture(scope="module")
def render_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("prtr")
    mesh = _write_mesh(d / "thing.ply")
    out = d / "bundle"
    args = ["bundle", "--object", str(mesh), "--out", str(out), "--height", "0.15", "--n-proxy", "120"]
    rc = main(args + ["--transfer-rays", "512", "--directions", "256", "--render-transfer", "--quiet"])
    assert rc == 0
    return out


def test_render_transfer_shades_every_render_vertex(render_bundle, prt_bundle):
    """``--render-transfer``: the stage shades the render mesh itself; the proxy's values are its rows."""
    b = load_bundle(render_bundle)
    R = len(b.vertices)
    assert b.prt.render_transfer.shape == (R, 9) and b.prt.render_bounce.shape == (R, 9)
    assert b.prt.render_bounce_primary.shape == (R, 9) and b.meta["prt"]["bounces"] == 8
    st = _stage(render_bundle, shading="prt", temporal_smoothing=0.0)
    for est in (
        _estimate(),
        LightEstimate(
            sh9=_ambient(0.3),
            primary_dir=_unit([0.5, 0.5, 0.1]),
            primary_rgb=np.array([3.0, 2.5, 2.0]),
            primary_pos=np.array([0.2, 0.2, 0.04]),
        ),
    ):
        out = st.process(_frame(light=est)).results[SHADING.name]
        assert out.render_irradiance.shape == (R, 3) and np.isfinite(out.render_irradiance).all()
        assert np.array_equal(out.irradiance, out.render_irradiance[b.proxy_index])
        # at the proxy's vertices: the proxy-table shading (same rays; the bounce differs only by how
        # the hit points' light is interpolated)
        ref = prt_irradiance(b.prt, b.proxy_vertices, b.proxy_normals, est)
        rel = np.abs(out.irradiance - ref).mean() / ref.mean()
        assert rel < 0.03, rel
        # a light from +x lights the +x side more, on the render mesh too
        d = np.asarray(est.primary_dir)
        facing = b.normals @ d
        assert out.render_irradiance[facing > 0.5].mean() > 1.5 * out.render_irradiance[facing < -0.5].mean()
    # a bundle without them keeps shading the proxy only (the renderer carries it)
    plain = _stage(prt_bundle, shading="prt", temporal_smoothing=0.0)
    assert plain.process(_frame(light=_estimate())).results[SHADING.name].render_irradiance is None


def test_damaged_render_transfer_is_reported(tmp_path, render_bundle):
    import shutil

    d = tmp_path / "b"
    shutil.copytree(render_bundle, d)
    with np.load(d / "prt.npz") as z:
        arr = {k: z[k] for k in z.files}
    R = len(arr["render_transfer"])
    arr["render_transfer"] = arr["render_transfer"][:-1]
    _write_prt(d, arr)
    with pytest.raises(BundleError, match=rf"prt\.npz: render_transfer must be \({R}, 9\)"):
        load_bundle(d)


def test_bundle_command_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "garbage.ply").write_text("not a mesh")
    (tmp_path / "empty.obj").write_text("")
    cases = [
        (tmp_path / "missing.glb", "no such file"),
        (tmp_path / "garbage.ply", "cannot read as a mesh"),
        (tmp_path / "empty.obj", "no geometry"),
    ]
    for path, msg in cases:
        assert main(["bundle", "--object", str(path), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    assert main(["bundle", "--object", "builtin:sphere", "--out", str(load_bundle("builtin:vase").path)]) == 2
    assert "holds a bundle of 'builtin:vase'" in capsys.readouterr().err


def test_a_mesh_with_fewer_vertices_than_graph_neighbours_makes_a_bundle_that_loads(tmp_path, capsys):
    # a single triangle: the proxy's kNN graph and the carry once asked for more neighbours than there
    # are vertices, and the padded index (3) made the bundle the command had just written unloadable
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0.02\nf 1 2 3\n")
    assert main(["bundle", "--object", str(tmp_path / "tri.obj"), "--out", str(tmp_path / "b")]) == 0
    b = load_bundle(str(tmp_path / "b"))
    assert b.n_proxy == 3 and b.proxy_edges.max() < 3 and b.carry_index.max() < 3
    assert sorted(map(tuple, b.proxy_edges.tolist())) == [(0, 1), (0, 2), (1, 2)]
    np.testing.assert_allclose(b.carry_weight.sum(1), 1.0, rtol=1e-5)


def test_low_sun_is_not_dimmed_by_the_floor_and_below_it_is_dark(sphere):
    mesh, res = sphere
    tab = res.tables()
    n = np.asarray(mesh.vertex_normals)
    for elev in (3.0, 8.0):
        d = np.array([np.cos(np.deg2rad(elev)), np.sin(np.deg2rad(elev)), 0.0])
        facing = n @ d > 0.3
        assert np.allclose(tab.primary_visibility(d)[facing], 1.0)  # the floor blocks only below the horizon
    below = np.array([np.cos(np.deg2rad(3.0)), -np.sin(np.deg2rad(3.0)), 0.0])
    assert np.allclose(tab.primary_visibility(below), 0.0)
    assert np.allclose(tab.primary_visibility_per_vertex(np.tile(below, (len(n), 1))), 0.0)


def test_the_bundle_command_defaults_to_the_models_table_directions():
    import argparse

    from illuminet.commands import bundle as cmd
    from illuminet.models.prt import DEFAULT_TABLE_DIRECTIONS

    p = argparse.ArgumentParser()
    cmd.register(p.add_subparsers())
    assert p.parse_args(["bundle", "--object", "x", "--out", "y"]).directions == DEFAULT_TABLE_DIRECTIONS


def _standing_cylinder():
    m = trimesh.creation.cylinder(radius=0.05, height=0.15, sections=24)
    m.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # axis z -> y
    m.apply_translation([0, -m.bounds[0][1], 0])  # standing on the floor
    return m


def test_the_object_shadows_the_primary_lights_floor_bounce_on_its_far_side():
    # ground truth shadows every light on the floor under and beside the object; the floor bounce of
    # the transfer was the ambient's times the floor's sky visibility, the same on every side
    from illuminet.models.prt import compute_prt

    m = _standing_cylinder()
    assert abs(m.bounds[0][1]) < 1e-9
    sub = m.subdivide().subdivide()
    pts, nrm = np.asarray(sub.vertices), np.asarray(sub.vertex_normals)
    res = compute_prt(m, pts, nrm, transfer_rays=1024, table_directions=256, albedo=0.0)
    tab = res.tables()
    assert tab.floor_shadow is not None and tab.floor_shadow.shape == (len(tab.floor_dirs), len(pts))
    low = _unit([1.0, 0.45, 0.0])  # a lamp low on +x: a long shadow on -x
    q = tab.floor_shadow_at(low)
    near_floor = pts[:, 1] < 0.03
    far, near = near_floor & (pts[:, 0] < -0.03), near_floor & (pts[:, 0] > 0.03)
    assert q[far].mean() < -0.05  # the floor it sees lies in the shadow (its sky visibility said lit)
    assert q[near].mean() > q[far].mean() + 0.1
    # mirrored light, mirrored answer (up to the tables' direction sampling)
    q2 = tab.floor_shadow_at(low * [-1, 1, 1])
    assert q2[near].mean() < -0.05 and abs(q2[near].mean() - q[far].mean()) < 0.05
    # a light from straight above casts no shadow beside the object: the sky's share is what changes
    assert abs(tab.floor_shadow_at(_unit([0, 1, 0]))[far].mean()) < abs(q[far].mean())
    # below the horizon the light does not reach the floor
    assert np.allclose(tab.floor_shadow_at(_unit([1, -0.2, 0])), 0.0)
    # the shading: the far side's floor bounce is darker, the near side's lighter; a grey floor from below
    sh = np.zeros((9, 3))
    sh[0] = 1.0 / 0.282095 * np.pi * 0.3  # uniform ambient
    est = LightEstimate(sh9=sh, primary_dir=low, primary_rgb=np.array([3.0, 3.0, 3.0]))
    from illuminet.runtime.prt import prt_irradiance

    with_t = prt_irradiance(tab, pts, nrm, est)
    without = prt_irradiance(dataclasses.replace(tab, floor_shadow=None, floor_dirs=None), pts, nrm, est)
    down_far = far & (nrm[:, 1] < -0.5)
    assert (with_t[down_far] <= without[down_far] + 1e-6).all() and (with_t[down_far] < without[down_far]).any()
