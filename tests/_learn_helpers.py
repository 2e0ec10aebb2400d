"""Helpers shared by the learned-transfer tests: a synthetic RGB-D view of a floor, plane-light fixtures."""

from __future__ import annotations

import numpy as np

from illuminet.runtime.frame import Intrinsics
from illuminet.runtime.physics import linear_to_srgb8
from illuminet.runtime.scene import PlaneLight


def floor_rgbd(w: int = 320, h: int = 200, height: float = 1.0, pitch_deg: float = 50.0, seed: int = 0):
    """A camera ``height`` m above a floor, pitched down: (colour uint8, depth float32 m, Intrinsics).

    The floor is lit brighter towards +x (a lamp on the right), so the relit object must be too.
    """
    K = Intrinsics(fx=0.8 * w, fy=0.8 * w, cx=w / 2 - 0.5, cy=h / 2 - 0.5, width=w, height=h)
    t = np.deg2rad(pitch_deg)
    up = np.array([0.0, -np.cos(t), -np.sin(t)])  # world up in camera coordinates (OpenCV)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, dtype=float)], -1)
    denom = rays @ up
    tt = np.where(denom < -1e-6, -height / np.minimum(denom, -1e-6), 0.0)
    depth = (tt * rays[..., 2]).astype(np.float32)
    depth[depth > 6] = 0
    pts = rays * tt[..., None]
    lin = 0.15 * (1.0 + 0.8 * np.clip(pts[..., 0], -1, 1))[..., None] * np.array([1.0, 0.95, 0.85])
    lin *= np.random.default_rng(seed).uniform(0.97, 1.03, lin.shape)
    color = linear_to_srgb8(lin)
    return color, depth, K


def plane_light(grid: int = 32, extent: float = 1.0, scale: float = 1.0, seed: int = 0) -> PlaneLight:
    rng = np.random.default_rng(seed)
    x = np.linspace(-extent / 2, extent / 2, grid)
    zz, xx = np.meshgrid(x, x, indexing="ij")
    v = np.stack([xx.ravel(), np.zeros(grid * grid), zz.ravel()], 1).astype(np.float32)
    irr = (1.0 + 0.8 * xx.ravel())[:, None] * np.array([1.0, 0.9, 0.8]) * scale
    irr = (irr * rng.uniform(0.98, 1.02, irr.shape)).astype(np.float32)
    mask = rng.random(grid * grid) > 0.1
    return PlaneLight(
        vertices=v,
        normals=np.tile([[0, 1, 0]], (grid * grid, 1)).astype(np.float32),
        irradiance=irr,
        mask=mask,
        confidence=np.ones(grid * grid, np.float32),
        grid=grid,
        exposure_scale=1.0,
        plane_slices=(slice(0, grid * grid),),
        labels=("floor",),
    )
