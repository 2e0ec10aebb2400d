"""Physics baselines: SH fit from RGB-D recovers known lighting; oracle, ambient and constant."""

from __future__ import annotations

import numpy as np
import pytest

from illuminet.runtime.frame import Intrinsics
from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.groundtruth.baselines import (
    ambient_from_image,
    ambient_shading,
    constant_shading,
    fit_sh_from_rgbd,
    normals_from_depth,
    sh9,
    sh_from_lights,
    sh_irradiance,
    sh_samples_from_rgbd,
)
from illuminet.runtime.physics import linear_to_srgb8, linearize
from illuminet.runtime.sh import sh_fit

K = Intrinsics(fx=400.0, fy=400.0, cx=319.5, cy=199.5, width=640, height=400)


def _sphere_frame(centre=(0.0, 0.0, 1.2), radius=0.45, wall_z=2.5):
    """Depth and camera-frame normals of a ball in front of a wall (analytic ray casting)."""
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], -1)
    c = np.asarray(centre)
    a = (d * d).sum(-1)
    b = -2 * (d @ c)
    cc = c @ c - radius**2
    disc = b * b - 4 * a * cc
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    hit = disc > 0
    z = np.where(hit, t, wall_z)
    p = d * z[..., None]
    n = np.where(hit[..., None], (p - c) / radius, np.array([0.0, 0.0, -1.0]))
    return z.astype(np.float32), n


def _known_sh():
    # a smooth, strictly positive environment: sky-like gradient plus two broad lights
    lights = L.uniform_environment([0.3, 0.35, 0.4], n=512, distance=50.0)
    lights = lights.concatenated(
        L.directional_lights([[0.5, -0.6, -0.6], [-0.7, -0.2, -0.4]], [[2.0, 1.6, 1.2], [0.4, 0.5, 0.9]])
    )
    return sh_from_lights(lights, plane_blocks=False)


@pytest.mark.parametrize("quantise", [False, True])
def test_sh_fit_recovers_known_sh_lighting(quantise):
    coeffs = _known_sh()
    z, n = _sphere_frame()
    E = sh9(n.reshape(-1, 3)) @ coeffs
    assert E.min() > 0
    albedo, scale = 0.6, 0.25
    lin = (albedo * E / np.pi * scale).reshape(K.height, K.width, 3)
    assert lin.max() < 0.98
    if quantise:  # through the camera's 8-bit sRGB encoding and back
        lin = linearize(linear_to_srgb8(lin))
    fit = fit_sh_from_rgbd(lin, z, K, albedo, exposure_scale=scale, lam=0.0, stride=1)
    # irradiance over every direction the picture shows (the camera-facing hemisphere)
    dirs = L.fibonacci_sphere(2000)
    seen = dirs[dirs[:, 2] < -0.2]
    got, want = sh_irradiance(fit, seen), sh_irradiance(coeffs, seen)
    rel = np.abs(got - want).mean() / want.mean()
    assert rel < 0.02, rel


def test_sh_fit_from_two_opposite_views_recovers_the_coefficients():
    """One view determines the irradiance only on the normals it shows; two opposite views of the
    ball show every normal, and then the 9 x 3 coefficients themselves come back within 2 %."""
    coeffs = _known_sh()
    z, n = _sphere_frame()
    albedo, scale = 0.6, 0.25
    normals, shading = [], []
    for yaw in (0.0, 180.0):
        R = L.rotation_y(yaw)  # camera -> object frame
        E = sh9(n.reshape(-1, 3) @ R.T) @ coeffs
        lin = linearize(linear_to_srgb8((albedo * E / np.pi * scale).reshape(K.height, K.width, 3)))
        nn, ee = sh_samples_from_rgbd(lin, z, K, albedo, R_obj_cam=R, exposure_scale=scale, stride=1)
        normals.append(nn)
        shading.append(ee)
    fit = sh_fit(np.concatenate(normals), np.concatenate(shading), lam=0.0)
    assert np.linalg.norm(fit - coeffs) / np.linalg.norm(coeffs) < 0.02
    dirs = L.fibonacci_sphere(2000)
    rel = np.abs(sh_irradiance(fit, dirs) - sh_irradiance(coeffs, dirs)).mean() / sh_irradiance(coeffs, dirs).mean()
    assert rel < 0.01


def test_sh_fit_in_the_object_frame():
    coeffs_cam = _known_sh()
    z, n = _sphere_frame()
    E = sh9(n.reshape(-1, 3)) @ coeffs_cam
    lin = (0.5 * E / np.pi * 0.2).reshape(K.height, K.width, 3)
    R = L.rotation_y(30) @ np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # camera -> object
    fit = fit_sh_from_rgbd(lin, z, K, 0.5, R_obj_cam=R, exposure_scale=0.2, lam=0.0, stride=1)
    nc = L.fibonacci_sphere(500)
    nc = nc[nc[:, 2] < -0.2]
    np.testing.assert_allclose(sh_irradiance(fit, nc @ R.T), sh_irradiance(coeffs_cam, nc), rtol=0.03, atol=1e-3)


def test_normals_from_depth_of_a_sphere():
    z, n_true = _sphere_frame()
    _, n, valid = normals_from_depth(z, K)
    assert valid.mean() > 0.5
    cos = np.einsum("hwx,hwx->hw", n, n_true)[valid]
    assert np.median(cos) > 0.999 and np.percentile(cos, 1) > 0.98


def test_oracle_sh_of_a_uniform_environment_is_pi_L():
    env = L.uniform_environment([1.0, 0.5, 0.25], n=4096, distance=100.0)
    c = sh_from_lights(env, plane_blocks=False)
    dirs = L.fibonacci_sphere(100)
    np.testing.assert_allclose(sh_irradiance(c, dirs), np.pi * np.array([[1.0, 0.5, 0.25]]).repeat(100, 0), rtol=0.01)


def test_oracle_sh_tracks_true_irradiance_of_smooth_light():
    lights = L.hdr_lights(np.full((32, 64, 3), 0.2, np.float32), 64)  # an overcast-like dome
    sun = L.directional_lights([[0.3, 0.8, 0.2]], [[1.0, 1.0, 1.0]])
    env = lights.concatenated(sun)
    n = L.fibonacci_sphere(300)
    true = L.irradiance(np.zeros_like(n), n, env)
    sh = sh_irradiance(sh_from_lights(env, plane_blocks=False), n)
    assert np.abs(sh - true).mean() / true.mean() < 0.05  # order-2 SH of a smooth environment


def test_oracle_drops_lights_under_the_plane():
    above = L.PointLights([[0, 1.0, 0]], [[1.0, 1, 1]])
    below = above.concatenated(L.PointLights([[0, -1.0, 0]], [[5.0, 5, 5]]))
    np.testing.assert_allclose(sh_from_lights(below), sh_from_lights(above))


def test_ambient_and_constant():
    img = np.full((10, 20, 3), 0.1)
    e = ambient_from_image(img, 0.5, exposure_scale=0.01)
    np.testing.assert_allclose(e, np.pi * 0.1 / 0.5 / 0.01)
    sh = ambient_shading(e, 7)
    assert sh.shape == (7, 3) and np.all(sh == e)
    c = constant_shading([1.0, 2.0, 3.0], 5, scale=2.0)
    np.testing.assert_allclose(c, [[2.0, 4.0, 6.0]] * 5)
    with pytest.raises(ValueError, match="mean_shading"):
        constant_shading(np.ones((4, 3)), 5)
    with pytest.raises(ValueError, match="no pixels"):
        ambient_from_image(img, 0.5, mask=np.zeros((10, 20), bool))


def test_sh_fit_on_a_synthetic_camera_frame_predicts_the_floor():
    """One SH fitted to every pixel of a synthetic-camera frame gives, facing up, the irradiance the
    floor has on average over what the camera sees of it; at the anchor it is off by exactly as much
    as the room's near lamps make the anchor differ from that average (a spatial variation one
    direction-only SH cannot represent)."""
    from illuminet.hw.synthetic import open_url

    # direct light only (bounce=0): the premise is one albedo over the floor, which inter-reflected
    # light from the walls (another albedo) would break
    src = open_url("synthetic://indoor?seed=2&table=0&bounce=0")
    f = src.read()
    sc = src.scene
    T = sc.default_anchor()
    lin = linearize(f.color)
    albedo = sc.planes[0].albedo_mean  # the baseline is told the floor's true mean albedo here
    fit = fit_sh_from_rgbd(
        lin, f.depth, f.intrinsics, albedo, R_obj_cam=T[:3, :3].T, exposure_scale=f.exposure.scale, lam=1e-2
    )
    up = T[:3, 1]
    pred = sh_irradiance(fit, np.array([[0.0, 1.0, 0.0]]))[0]
    # the floor the camera sees: depth points within 2 cm of the anchor's plane (every 4th pixel)
    k, z = f.intrinsics, f.depth[::4, ::4]
    v, u = np.mgrid[0 : f.depth.shape[0] : 4, 0 : f.depth.shape[1] : 4]
    pts = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], -1)[z > 0]
    seen_floor = pts[np.abs((pts - T[:3, 3]) @ up) < 0.02]
    assert len(seen_floor) > 1000
    floor_mean = sc.true_plane_irradiance(seen_floor, up).mean(0)
    # 3 %: order-2 truncation, sensor noise and the floor's albedo texture (measured: ~1 %)
    np.testing.assert_allclose(pred, floor_mean, rtol=0.03)
    # at the anchor: the spatial variation (here the anchor is ~20-30 % darker than the seen floor's
    # mean) plus the same 3 %
    at_anchor = sc.true_plane_irradiance(T[:3, 3][None], up)[0]
    assert np.all(np.abs(pred / at_anchor - 1) <= np.abs(floor_mean / at_anchor - 1) + 0.03), (pred, at_anchor)
