"""Second-order real spherical harmonics (9 coefficients): basis, irradiance convolution, fits.

Conventions (used everywhere in the runtime, and by the ``LightEstimate`` it exports):

* basis order ``[Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22]`` evaluated as
  ``(1, y, z, x, xy, yz, 3z^2-1, xz, x^2-y^2)`` times the usual constants (the order of three.js's
  ``SphericalHarmonics3`` and of WebXR's ``sphericalHarmonicsCoefficients``);
* *irradiance* coefficients ``E_lm`` satisfy ``E(n) = sh9(n) @ E`` (clamped at 0); they are the
  *radiance* coefficients convolved with the clamped cosine, ``E_lm = A_hat_l L_lm`` with
  ``A_hat = (pi, 2pi/3, pi/4)`` (Ramamoorthi & Hanrahan 2001).
"""

from __future__ import annotations

import numpy as np


def sh9(n: np.ndarray) -> np.ndarray:
    """Real SH basis up to order 2 at unit directions n (N, 3) -> (N, 9)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return np.stack(
        [
            np.full_like(x, 0.282095),
            0.488603 * y,
            0.488603 * z,
            0.488603 * x,
            1.092548 * x * y,
            1.092548 * y * z,
            0.315392 * (3 * z * z - 1),
            1.092548 * x * z,
            0.546274 * (x * x - y * y),
        ],
        1,
    )


SH_A_HAT = np.array([np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5)


SH_BAND = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])


def sh_fit(
    normals: np.ndarray, irradiance: np.ndarray, weights: np.ndarray | None = None, lam: float = 0.0
) -> np.ndarray:
    """Regularised least-squares SH9 irradiance coefficients (9, 3) from samples with normals.

    The classic physics baseline: every valid RGB-D sample, its normal and its irradiance. The
    Laplacian (band l penalised by lam * (l (l + 1))^2, relative to the mean sample energy) keeps the
    fit sensible when the normals span few directions (one plane: the unregularised minimum-norm
    solution turns every side face black). ``lam = 0`` is plain minimum-norm least squares.
    """
    B = sh9(np.asarray(normals, np.float64))
    E = np.asarray(irradiance, np.float64)
    if weights is not None:
        w = np.sqrt(np.asarray(weights, np.float64))[:, None]
        B, E = B * w, E * w
    if lam <= 0:
        coef, *_ = np.linalg.lstsq(B, E, rcond=1e-6)
        return coef
    G = B.T @ B
    reg = lam * np.trace(G) / 9 * np.diag((SH_BAND * (SH_BAND + 1.0)) ** 2)
    return np.linalg.solve(G + reg + 1e-9 * np.eye(9), B.T @ E)


def sh_eval(coef: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (N, 3) of SH9 coefficients (9, 3) at unit normals (clamped at 0)."""
    return np.maximum(sh9(np.asarray(normals, np.float64)) @ coef, 0.0).astype(np.float32)
