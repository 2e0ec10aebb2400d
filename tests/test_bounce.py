"""Indirect light of the synthetic scene: the analytic case, its size, switching it off, boxes."""

from __future__ import annotations

import numpy as np
import pytest

from illuminet.hw.synthetic import SyntheticError, open_url
from illuminet.hw.synthetic import scene as S
from illuminet.runtime.assets.objects import load_object
from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.groundtruth.hemisphere import HemisphereVisibility, cosine_directions, disk_directions
from illuminet.runtime.sh import SH_A_HAT, sh9


def _white_ground_under_sky(rho: float):
    """An infinite ground of uniform albedo ``rho`` under a uniform sky (far lights above the horizon)."""
    tile = np.full((8, 8, 3), rho, np.float32)
    inf = np.array([np.inf, np.inf])
    ground = S.SyntheticPlane("ground", "ground", 1, 0.0, 1.0, (0, 2), -inf, inf, tile, 1.0)
    d = L.fibonacci_sphere(256)
    d = d[d[:, 1] > 0.02]
    sky = L.directional_lights(d, np.full((len(d), 3), 4 * np.pi / 256), 200.0)  # radiance 1
    poses = [S._look_at(np.array([0.0, 1.5, 1.5]), np.zeros(3))]
    sc = S.SyntheticScene(
        "outdoor",
        0,
        sky,
        [ground],
        [S.Occluder(1, 0.0)],
        np.zeros((1, 3)),
        S.OAKD_INTRINSICS_1280.scaled(160, 100),
        poses,
    )
    sc.bake(1)
    return sc, L.irradiance(np.zeros((1, 3)), np.array([[0, 1.0, 0]]), sky)[0]


def test_white_floor_under_a_uniform_sky_matches_the_closed_form():
    rho = 0.8
    sc, e_floor = _white_ground_under_sky(rho)
    pts = np.array([[0, 0.01, 0], [0.3, 0.5, -0.2], [0, 0.01, 0], [0, 0.2, 0]])
    nrm = np.array([[0, -1.0, 0], [0, -1.0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    e = sc.indirect_irradiance(pts, nrm)
    # facing down, the floor fills the hemisphere: E = pi * (rho E_floor / pi) = rho E_floor
    np.testing.assert_allclose(e[:2], rho * e_floor[None].repeat(2, 0), rtol=0.02)
    # facing sideways it fills half of the cosine-weighted hemisphere; facing up, none of it
    np.testing.assert_allclose(e[2], 0.5 * rho * e_floor, rtol=0.03)
    np.testing.assert_allclose(e[3], 0.0, atol=1e-9)
    # the same through the object's ground truth (no mesh, no visibility)
    T = sc.T_cam_world(0)
    got = sc.true_object_shading(None, T, visibility=False, points=pts, normals=nrm)
    direct = sc.true_object_shading(None, T, visibility=False, points=pts, normals=nrm, indirect=False)
    np.testing.assert_allclose(got - direct, e, rtol=1e-9)
    # a lone plane receives no bounce light of its own
    g = sc.planes[0]
    np.testing.assert_allclose(g.irradiance_grid, g.direct_grid)


def test_cosine_directions_and_transfer_without_visibility():
    d = disk_directions(512)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.all(d[:, 2] > 0)
    assert d[:, 2].mean() == pytest.approx(2 / 3, abs=0.01)  # E[cos] under the cos/pi density
    n = L.fibonacci_sphere(20)
    dirs = cosine_directions(n, 64)
    assert np.all(np.einsum("vkx,vx->vk", dirs, n) > 0)
    hv = HemisphereVisibility(None, np.zeros((20, 3)), n, 1024)
    # without anything in the way the transfer is the irradiance basis A_hat_l Y_lm(n)
    np.testing.assert_allclose(hv.transfer_sh9(), sh9(n) * SH_A_HAT, atol=0.02)


def test_bounce_lifts_down_facing_vertices_by_a_physically_sane_amount():
    src = open_url("synthetic://lamp?seed=2&size=160x100&frames=1")
    sc = src.scene
    mesh = load_object("builtin:bowl", "proxy")
    T = sc.default_anchor(0)
    direct = sc.true_object_shading(mesh, T, indirect=False)
    total = sc.true_object_shading(mesh, T)
    ind = (total - direct) @ L._LUMA
    assert np.all(ind >= -1e-9)
    down = mesh.vertex_normals[:, 1] < -0.5
    up = mesh.vertex_normals[:, 1] > 0.5
    assert down.sum() > 20
    # the underside gets almost nothing directly and a good deal from the floor
    assert np.median(ind[down]) > 2 * np.median(direct[down] @ L._LUMA)
    floor = sc.planes[0]
    e_floor = float(floor.irradiance_grid.reshape(-1, 3).max(0) @ L._LUMA)
    rho_floor = float(floor.albedo_mean @ L._LUMA)
    # no surface can send more than rho E / pi: a vertex gets at most the brightest plane's rho E
    bound = max(float(p.albedo_mean.max()) * float(p.irradiance_grid.max()) for p in sc.planes)
    assert np.all(ind <= bound)
    # a vertex facing the floor sees floor radiance, which is at most rho_floor * E_floor / pi
    assert np.max(ind[down]) <= 1.05 * rho_floor * e_floor
    # the object's own shadow and its self-visibility keep the inside of the bowl below the outside rim
    assert np.median(ind[up]) > 0


def test_bounce_is_switchable_from_the_url():
    on = open_url("synthetic://indoor?seed=1&size=160x100&frames=1")
    off = open_url("synthetic://indoor?seed=1&size=160x100&frames=1&bounce=0")
    assert on.scene.bounces == S.DEFAULT_BOUNCES > 0 and off.scene.bounces == 0
    for p in off.scene.planes:
        assert p.direct_grid is None and p.lattice is None
    for p_on, p_off in zip(on.scene.planes, off.scene.planes):
        np.testing.assert_allclose(p_on.direct_grid, p_off.irradiance_grid)
        assert np.all(p_on.irradiance_grid >= p_off.irradiance_grid - 1e-6)
    # the picture: the same geometry, brighter planes (in radiance, before exposure)
    on.open()
    off.open()
    r_on, _ = on._renderer.render(on.scene.poses[0])
    r_off, _ = off._renderer.render(off.scene.poses[0])
    assert np.all(r_on >= r_off - 1e-6) and r_on.mean() > 1.1 * r_off.mean()
    # the walls' bottoms: a wall point 5 cm above the floor is lit by the floor
    wall = next(p for p in on.scene.planes if p.label == "wall")
    x = np.zeros((1, 3))
    x[0, wall.axis] = wall.coord
    x[0, 1] = 0.05
    x[0, 2 if wall.axis == 0 else 0] = (
        (wall.lo[1] + wall.hi[1]) / 2 if wall.axis == 0 else (wall.lo[0] + wall.hi[0]) / 2
    )
    T = on.scene.T_cam_world(0)
    pc = x @ T[:3, :3].T + T[:3, 3]
    n = T[:3, :3] @ wall.normal
    e_on = on.scene.true_plane_irradiance(pc, n)
    e_off = off.scene.true_plane_irradiance(pc, n)
    assert np.all(e_on > e_off)
    mesh = load_object("builtin:sphere", "proxy")
    Ta = off.scene.default_anchor()
    np.testing.assert_allclose(
        off.scene.true_object_shading(mesh, Ta), off.scene.true_object_shading(mesh, Ta, indirect=False)
    )


@pytest.mark.parametrize("value", ["-1", "99", "x"])
def test_bad_bounce_values_are_refused(value):
    with pytest.raises(SyntheticError, match="bounce"):
        open_url(f"synthetic://indoor?bounce={value}")


def test_boxes_block_like_solids():
    box = S.BoxOccluder(np.zeros(3), np.ones(3))
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 2, (400, 1, 3))
    q = rng.uniform(-1, 2, (1, 20, 3))
    t = np.linspace(0, 1, 801)[:, None, None, None]
    inside = np.all(((p + t * (q - p)) > 0) & ((p + t * (q - p)) < 1), axis=-1).any(0)
    got = box.blocks(p, q)
    assert got.shape == (400, 20)
    assert (got != inside).mean() < 0.002  # only grazing segments the sampling misses


def test_cluttered_scene_has_boxes_that_shadow_the_floor_and_never_hide_the_object():
    src = open_url("synthetic://cluttered?seed=1&size=320x200&frames=1")
    sc = src.scene
    boxes = [o for o in sc.occluders if isinstance(o, S.BoxOccluder)]
    assert 2 <= len(boxes) <= 4 and len(sc.info["boxes"]) == len(boxes)
    assert sum(p.label == "box" for p in sc.planes) == 5 * len(boxes)
    src.open()
    idx = src._renderer.geometry(sc.poses[0])[0].reshape(200, 320)
    K = sc.intrinsics
    x = sc.default_anchor()[:3, 3]
    u, v = int(K.fx * x[0] / x[2] + K.cx), int(K.fy * x[1] / x[2] + K.cy)
    assert sc.planes[idx[v, u]].label == "floor"
    assert np.isin([i for i, p in enumerate(sc.planes) if p.label == "box"], idx).any()  # boxes in view
    # some floor lies in a box's shadow: the key light is blocked there
    floor = sc.planes[0]
    g = np.stack(np.meshgrid(np.linspace(floor.lo[0], floor.hi[0], 80), np.linspace(floor.lo[1], floor.hi[1], 80)), -1)
    pts = np.zeros((80 * 80, 3))
    pts[:, 0], pts[:, 2] = g[..., 0].ravel(), g[..., 1].ravel()
    key = L.PointLights(sc.lights.positions[:1], sc.lights.intensities[:1])
    assert (sc.occlusion(pts, key) == 0).mean() > 0.005
    with pytest.raises(SyntheticError, match="boxes"):
        open_url("synthetic://indoor?boxes=13")


def test_the_object_lights_itself_when_it_has_an_albedo():
    from illuminet.hw.synthetic import bounce as B

    src = open_url("synthetic://lamp?seed=2&size=160x100&frames=1")
    sc = src.scene
    mesh = load_object("builtin:bowl", "proxy")
    T = sc.default_anchor(0)
    black = sc.true_object_shading(mesh, T)
    assert np.array_equal(sc.true_object_shading(mesh, T, object_albedo=0.0), black)
    grey = sc.true_object_shading(mesh, T, object_albedo=0.4)
    white = sc.true_object_shading(mesh, T, object_albedo=0.8)
    G = B.object_gather(mesh, np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals))
    blocked = np.asarray(G.sum(1)).ravel()  # share of a vertex's cosine-weighted rays meeting the object
    free = blocked == 0
    assert free.any() and (~free).sum() > 20
    # a vertex that sees none of the object gets nothing from it
    np.testing.assert_allclose(white[free], black[free])
    # light is only added, more with a lighter object
    assert np.all(grey >= black - 1e-9) and np.all(white >= grey - 1e-9)
    assert (white - black)[~free].sum() > 0
    # no more than a surface of albedo rho lit by the brightest converged irradiance can send
    added = (white - black) @ L._LUMA
    assert np.all(added <= 0.8 * blocked * float((white @ L._LUMA).max()) + 1e-9)
    # converged: the sum satisfies E = E_room + rho G E at the bowl's own vertices
    np.testing.assert_allclose(white, black + 0.8 * (G @ white), rtol=2e-3, atol=1e-6 * float(white.max()))
    with pytest.raises(ValueError, match="object_albedo"):
        sc.true_object_shading(mesh, T, object_albedo=1.0)
