"""Physics baselines for the object's shading, from the same inputs the learned model sees.

Every baseline returns per-vertex irradiance ``(V, 3)`` in scene-referred linear units (see
:mod:`illuminet.runtime.physics`), so it can be compared with ground truth and the model directly:

constant prior
    :func:`constant_shading` — the mean shading of the training set (times an optional scale).
ambient only
    :func:`ambient_from_image` + :func:`ambient_shading` — one RGB irradiance for every vertex,
    from the picture's mean radiance and an assumed albedo (what phone AR frameworks give:
    an intensity and a colour correction).
second-order spherical harmonics from RGB-D
    :func:`fit_sh_from_rgbd` — normals from the depth image, shading ``E = pi B / albedo`` per
    pixel, a regularised least-squares fit of 9 irradiance coefficients per channel, evaluated at
    the object's normals with :func:`sh_irradiance` (the classic approach; it sees only the
    normals present in the picture).
oracle
    :func:`sh_from_lights` — the SH projection of the true lights seen from the object's centre.

The SH basis, its order and the fit are the runtime's (:mod:`illuminet.runtime.stages.shading`:
``sh9``, ``sh_fit``, ``sh_eval``), so the ``shading = "sh"`` stage and these baselines agree.
Coefficients are *irradiance* coefficients: the cosine lobe's ``A_hat`` (Ramamoorthi & Hanrahan
2001) is already applied, ``E(n) = sh9(n) @ coeffs``.
"""

from __future__ import annotations

import numpy as np

from illuminet.runtime.frame import Intrinsics
from illuminet.runtime.groundtruth.lighting import PointLights
from illuminet.runtime.sh import SH_A_HAT, sh9, sh_eval, sh_fit

__all__ = [
    "constant_shading",
    "ambient_from_image",
    "ambient_shading",
    "normals_from_depth",
    "fit_sh_from_rgbd",
    "sh_samples_from_rgbd",
    "sh_irradiance",
    "sh_from_lights",
    "sh9",
]


def constant_shading(mean_shading: np.ndarray, n_vertices: int, scale: float | np.ndarray = 1.0) -> np.ndarray:
    """The constant prior: the training set's mean shading, (3,) or (V, 3), times ``scale``.

    Returns
    -------
    (V, 3) float64
    """
    m = np.asarray(mean_shading, dtype=np.float64)
    if m.ndim == 1:
        m = np.tile(m.reshape(1, 3), (n_vertices, 1))
    if m.shape != (n_vertices, 3):
        raise ValueError(f"mean_shading must be (3,) or ({n_vertices}, 3), got {m.shape}")
    return m * np.asarray(scale, dtype=np.float64)


def _albedo_image(albedo, shape_hw) -> np.ndarray:
    a = np.asarray(albedo, dtype=np.float64)
    H, W = shape_hw
    if a.ndim == 0:
        return np.full((H, W, 3), float(a))
    if a.shape == (3,):
        return np.broadcast_to(a, (H, W, 3))
    if a.shape == (H, W):
        return np.repeat(a[..., None], 3, axis=2)
    if a.shape == (H, W, 3):
        return a
    raise ValueError(f"albedo must be a scalar, (3,), (H, W) or (H, W, 3) with H, W = {shape_hw}; got {a.shape}")


def ambient_from_image(
    color_lin: np.ndarray, albedo: float | np.ndarray, exposure_scale: float = 1.0, mask: np.ndarray | None = None
) -> np.ndarray:
    """Ambient irradiance (3,) from a picture: ``pi * mean(radiance) / albedo``.

    Parameters
    ----------
    color_lin : (H, W, 3) linear RGB (``physics.linearize`` of the frame)
    albedo : assumed albedo of what the camera sees (scalar, RGB, or per pixel)
    exposure_scale : ``Exposure.scale`` (or a relative scale): radiance = linear / scale
    mask : (H, W) bool pixels to use (default: all)

    Returns
    -------
    (3,) irradiance that a uniform environment of the picture's mean radiance would give.
    """
    c = np.asarray(color_lin, dtype=np.float64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"color_lin must be H x W x 3 linear RGB, got {c.shape}")
    if not exposure_scale > 0:
        raise ValueError(f"exposure_scale must be > 0, got {exposure_scale}")
    a = _albedo_image(albedo, c.shape[:2])
    m = np.ones(c.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if not m.any():
        raise ValueError("ambient_from_image: the mask selects no pixels")
    e = np.pi * c[m] / np.maximum(a[m], 1e-3) / exposure_scale
    return e.mean(axis=0)


def ambient_shading(ambient: np.ndarray, n_vertices: int) -> np.ndarray:
    """Ambient-only object shading: the same irradiance (3,) at every vertex, (V, 3)."""
    return np.tile(np.asarray(ambient, dtype=np.float64).reshape(1, 3), (n_vertices, 1))


def normals_from_depth(
    depth: np.ndarray, intrinsics: Intrinsics, step: int = 3, max_rel_jump: float = 0.04
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points and unit normals from a depth image by central differences.

    Parameters
    ----------
    depth : (H, W) float32 metres, 0 = invalid
    intrinsics : of the (aligned) image
    step : pixel distance of the differences (larger = smoother normals, fewer near edges)
    max_rel_jump : a neighbour whose depth differs by more than this fraction is an edge: no normal

    Returns
    -------
    points (H, W, 3), normals (H, W, 3) pointing towards the camera, valid (H, W) bool
    """
    z = np.asarray(depth, dtype=np.float64)
    H, W = z.shape
    K = intrinsics
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    P = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=-1)
    s = int(step)
    valid = np.zeros((H, W), bool)
    nrm = np.zeros((H, W, 3))
    c = (slice(s, H - s), slice(s, W - s))
    zc = z[c]
    zl, zr = z[s : H - s, : W - 2 * s], z[s : H - s, 2 * s :]
    zu, zd = z[: H - 2 * s, s : W - s], z[2 * s :, s : W - s]
    ok = zc > 0
    for zn in (zl, zr, zu, zd):
        ok &= (zn > 0) & (np.abs(zn - zc) <= max_rel_jump * zc)
    du = P[s : H - s, 2 * s :] - P[s : H - s, : W - 2 * s]
    dv = P[2 * s :, s : W - s] - P[: H - 2 * s, s : W - s]
    n = np.cross(dv, du)
    ln = np.linalg.norm(n, axis=-1)
    ok &= ln > 0
    n = n / np.maximum(ln, 1e-12)[..., None]
    flip = np.einsum("hwx,hwx->hw", n, P[c]) > 0  # face the camera
    n[flip] *= -1
    nrm[c] = n
    valid[c] = ok
    return P, nrm, valid


def sh_samples_from_rgbd(
    color_lin: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    albedo: float | np.ndarray,
    R_obj_cam: np.ndarray | None = None,
    exposure_scale: float = 1.0,
    mask: np.ndarray | None = None,
    stride: int = 2,
    step: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """The shading samples of an RGB-D frame: (normals (S, 3), irradiance (S, 3)).

    Parameters are those of :func:`fit_sh_from_rgbd`; samples from several frames (each with its
    own ``R_obj_cam``) can be concatenated and fitted together with ``transfer.sh_fit``.
    """
    c = np.asarray(color_lin, dtype=np.float64)
    if c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"color_lin must be H x W x 3 linear RGB, got {c.shape}")
    if np.shape(depth) != c.shape[:2]:
        raise ValueError(f"depth {np.shape(depth)} must be aligned to colour {c.shape[:2]}")
    if not exposure_scale > 0:
        raise ValueError(f"exposure_scale must be > 0, got {exposure_scale}")
    _, n, valid = normals_from_depth(depth, intrinsics, step)
    if mask is not None:
        valid &= np.asarray(mask, bool)
    # saturated or black pixels say nothing about the shading
    valid &= np.all((c > 1e-4) & (c < 0.98), axis=-1)
    sub = np.zeros_like(valid)
    sub[::stride, ::stride] = True
    valid &= sub
    a = _albedo_image(albedo, c.shape[:2])
    e = np.pi * c[valid] / np.maximum(a[valid], 1e-3) / exposure_scale
    normals = n[valid]
    if R_obj_cam is not None:
        normals = normals @ np.asarray(R_obj_cam, dtype=np.float64).T
    return normals, e


def fit_sh_from_rgbd(
    color_lin: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    albedo: float | np.ndarray,
    R_obj_cam: np.ndarray | None = None,
    exposure_scale: float = 1.0,
    mask: np.ndarray | None = None,
    lam: float = 1e-2,
    stride: int = 2,
    step: int = 3,
) -> np.ndarray:
    """Second-order SH irradiance (9, 3) fitted to the shading of an RGB-D frame's pixels.

    Parameters
    ----------
    color_lin : (H, W, 3) linear RGB
    depth : (H, W) metres aligned to colour, 0 = invalid
    intrinsics : of the colour image
    albedo : assumed albedo (scalar, RGB or per pixel); shading = pi * radiance / albedo
    R_obj_cam : 3x3 rotation camera -> object frame (``anchor.R.T``); when given the coefficients
        are in the object frame (evaluate them on object-frame normals), else in the camera frame
    exposure_scale : radiance = linear / exposure_scale (``Exposure.scale``)
    mask : (H, W) bool pixels allowed (e.g. plane inliers); default all with a valid normal
    lam : band-Laplacian regularisation (see ``transfer.sh_fit``); 0 = plain least squares. A
        single view shows only camera-facing normals (often just a floor and a wall), so the
        unregularised fit is only determined on those directions.
    stride : use every stride-th pixel in each direction (speed)
    step : finite-difference step for the normals (:func:`normals_from_depth`)

    Returns
    -------
    (9, 3) irradiance SH coefficients: ``E(n) = sh9(n) @ coeffs``.
    """
    normals, e = sh_samples_from_rgbd(
        color_lin, depth, intrinsics, albedo, R_obj_cam, exposure_scale, mask, stride, step
    )
    if normals.shape[0] < 9:
        raise ValueError(f"fit_sh_from_rgbd: only {normals.shape[0]} usable pixels (need >= 9 with depth and normals)")
    return sh_fit(normals, e, lam=lam)


def sh_irradiance(coeffs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (V, 3) of SH coefficients (9, 3) at unit normals (V, 3), clamped at 0."""
    return sh_eval(np.asarray(coeffs, dtype=np.float64), np.asarray(normals, dtype=np.float64)).astype(np.float64)


def sh_from_lights(lights: PointLights, point: np.ndarray | None = None, plane_blocks: bool = True) -> np.ndarray:
    """Oracle: SH irradiance coefficients (9, 3) of point lights seen from ``point`` (object frame).

    Each light is a delta of irradiance ``I / r^2`` from its direction; its radiance SH is
    projected and convolved with the clamped cosine (``A_hat``). With ``plane_blocks`` lights below
    the plane y = 0 are dropped (the plane the object stands on hides them from all of it).

    Parameters
    ----------
    lights : PointLights in the object frame
    point : (3,) where the object is summarised (default: the origin; use the object's centre)
    """
    p = np.zeros(3) if point is None else np.asarray(point, dtype=np.float64).reshape(3)
    d = lights.positions - p
    r2 = np.maximum((d * d).sum(1), 1e-12)
    w = d / np.sqrt(r2)[:, None]
    keep = lights.positions[:, 1] > 0 if plane_blocks else np.ones(len(lights), bool)
    radiance_sh = sh9(w[keep]).T @ (lights.intensities[keep] / r2[keep, None])
    return radiance_sh * SH_A_HAT[:, None]
