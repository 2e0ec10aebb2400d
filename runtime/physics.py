"""Physics conventions: the one place that defines colour encoding, exposure and illumination units.

Everything that does lighting math imports from here, so that the synthetic camera, the plane
measurement, training data, the models and the renderer all agree.

Colour
    All lighting math is in **linear RGB** (Rec.709/sRGB primaries). Camera pixels are sRGB-encoded
    8-bit; :func:`srgb_to_linear` / :func:`linear_to_srgb` convert. A frame's *exposure scale*
    k = exposure_s * ISO/100 relates scene radiance to linear pixel values; when the camera reports no
    exposure, stages normalise by the plane's own statistics instead (see planes/plane light).

Overall illumination (OI), after the paper
    For a vertex v with unit normal n, OI is a 3-vector per colour channel, L_c(v), such that the
    **irradiance** reaching v is E_c(v) = L_c(v) . n(v). Array layout: ``(V, 3, 3)`` =
    (vertex, colour channel R/G/B, xyz). For point lights j at p_j with RGB radiant intensity e_j
    (W/sr) and visibility V_j(v)::

        L_c(v) = sum_j  e_jc V_j(v) w_j / r_j^2,   w_j = (p_j - v) / r_j,  over lights with n . w_j > 0

    Note the "over lights with n . w_j > 0" makes L depend on n: OI is defined per vertex *with its
    normal*, exactly as in the paper.

Shading and radiance
    *Shading* is the irradiance E = L . n (per channel). A Lambertian surface of albedo rho reflects
    radiance B = rho * E / pi. The value a camera records (linear) is B * k * K_cam with the camera's
    constant; we fold K_cam into the exposure so that ``linear_pixel = B * exposure_scale``.
    Models predict shading E; the renderer draws albedo * E / pi * exposure_scale.

Coordinates
    Camera: OpenCV (x right, y down, z forward), metres. Object / anchor frame: origin on the anchor
    plane under the object's centre, +Y up along the plane normal, right-handed, metres. OI vectors
    exchanged between stages are expressed in the object frame.
"""

from __future__ import annotations

import numpy as np

#: 1/pi, the Lambertian BRDF of a white surface.
INV_PI = 1.0 / np.pi


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values -> linear. uint8 input is scaled from [0, 255]; floats are taken in [0, 1].

    Returns float32.
    """
    if x.dtype == np.uint8:
        return _SRGB_LUT[x]
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values in [0, 1] -> sRGB-encoded float32 in [0, 1] (clipped)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def linear_to_srgb8(x: np.ndarray) -> np.ndarray:
    """Linear values in [0, 1] -> sRGB uint8 (rounded)."""
    return np.rint(linear_to_srgb(x) * 255.0).astype(np.uint8)


_SRGB_LUT = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)
_SRGB_LUT_CV = np.ascontiguousarray(_SRGB_LUT, np.float32).reshape(1, 256)


def linearize(color: np.ndarray, response_lut: np.ndarray | None = None) -> np.ndarray:
    """Camera pixels (H x W x 3 uint8) -> linear float32 RGB in [0, 1].

    Uses the camera's measured response curve when one is given (a (256, 3) float LUT from
    photometric calibration, see ``illuminet calibrate photometric``), else the sRGB curve.
    """
    import cv2  # (imported here: this module is numpy only for the lighting maths)

    color = np.asarray(color)
    fast = color.dtype == np.uint8 and color.ndim in (2, 3) and color.size > 0
    if response_lut is None:
        if fast:  # OpenCV's table lookup: ~7x numpy's fancy indexing on a 640x400 frame (same values)
            return cv2.LUT(np.ascontiguousarray(color), _SRGB_LUT_CV)
        return _SRGB_LUT[color]
    lut = np.asarray(response_lut, dtype=np.float32)
    if lut.shape != (256, 3):
        raise ValueError(f"response LUT must have shape (256, 3), got {lut.shape}")
    if fast and color.ndim == 3 and color.shape[2] == 3:
        return cv2.LUT(np.ascontiguousarray(color), np.ascontiguousarray(lut).reshape(1, 256, 3))
    return np.stack([lut[color[..., c], c] for c in range(3)], axis=-1)


def irradiance_from_oi(oi: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Shading E = L . n per channel.

    Parameters
    ----------
    oi : (V, 3, 3) array
        OI per vertex, per colour channel, xyz.
    normals : (V, 3) array
        Unit normals in the same frame as ``oi``.

    Returns
    -------
    (V, 3) array of per-channel irradiance.
    """
    return np.einsum("vcx,vx->vc", oi, normals)


def lambert_radiance(irradiance: np.ndarray, albedo: np.ndarray | float = 1.0) -> np.ndarray:
    """Radiance reflected by a Lambertian surface: rho * E / pi."""
    return np.asarray(albedo) * irradiance * INV_PI


def load_response_lut(path) -> np.ndarray:
    """Read a camera response LUT written by ``illuminet calibrate photometric``.

    The file is a NumPy ``.npy`` array (or a text table readable by ``numpy.loadtxt``) of shape
    (256, 3): linear value in [0, 1] per 8-bit code, per channel R, G, B, non-decreasing. Used by
    :func:`linearize` when ``[source] response_curve`` names a file. Lives here (not in
    calibration/) so the runtime can use a LUT without importing the calibration tools.

    Raises
    ------
    ValueError
        Missing or unreadable file, wrong shape, non-finite or decreasing values; the message names
        the file and what was expected.
    """
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: response curve file not found (set [source] response_curve = '' for sRGB)")
    if p.suffix == ".npy":
        # numpy reads a .npy of anything else as a pickle it then refuses, saying "If you trust the file you can
        # load it unsafely using the `allow_pickle=` keyword argument", and an .npz archive as a mapping that
        # became "could not convert string to float: 'a'" without the file
        with open(p, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":
            kind = "an .npz archive" if magic.startswith(b"PK") else "not a .npy array"
            raise ValueError(
                f"{p}: {kind}; expected a (256, 3) response curve saved by numpy.save (illuminet calibrate "
                "photometric writes one)"
            )
    try:
        lut = np.load(p, allow_pickle=False) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
        lut = np.asarray(lut, dtype=np.float32)
    except Exception as e:  # numpy raises several types for a corrupt file
        raise ValueError(f"{p}: cannot read response curve: {e}") from None
    if lut.shape != (256, 3):
        raise ValueError(f"{p}: response curve must have shape (256, 3) (code x R,G,B), got {lut.shape}")
    if not np.all(np.isfinite(lut)):
        raise ValueError(f"{p}: response curve contains non-finite values")
    if np.any(np.diff(lut, axis=0) < -1e-6):
        raise ValueError(f"{p}: response curve must be non-decreasing in every channel")
    return lut
