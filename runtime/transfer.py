"""The transfer stage: plane illumination -> the object's shading, per frame.

Owns :func:`preprocess_plane` (the plane input normalisation shared by training and run time),
:class:`TransferChain` (the ONNX chain of a bundle in onnxruntime) and :class:`ShadingStage`
(``results["plane_light"]`` -> ``results["shading"]`` with temporal smoothing, or a baseline when
``[model] shading`` asks for one).

Normalisation: the plane's measured irradiance is divided by its mean luminance ``s`` over the
observed cells, so the network sees lighting *shape and colour*, never absolute brightness (which
depends on exposure, plane albedo and units). The network predicts the object's shading divided by
the same ``s``; multiplying back gives scene-referred irradiance in the plane's units.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .scene import ObjectShading
from .stage import FrameError, Stage

log = logging.getLogger(__name__)

LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

#: plane grid cells are pooled by this factor per side before the network (32x32 -> 16x16)
POOL = 2


def preprocess_plane(irradiance: np.ndarray, mask: np.ndarray, grid: int, pool: int = POOL,
                     confidence: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Plane irradiance grid -> network input (cells, 4) and the normalising scale ``s``.

    Parameters
    ----------
    irradiance : (grid*grid, 3)
        Linear RGB irradiance per plane vertex (row-major grid, vertex i*grid+j).
    mask : (grid*grid,) bool
        Observed vertices.
    grid : int
        Vertices per side; must be divisible by ``pool``.
    pool : int
        Cells per side merged into one network vertex (mask-weighted mean).
    confidence : (grid*grid,) float, optional
        Extra per-vertex weights in [0, 1].

    Returns
    -------
    x : (grid/pool)^2 x 4 float32
        Normalised RGB irradiance and the observed fraction of each pooled cell.
    s : float
        Mean observed luminance (the scale the prediction is multiplied back by).
    """
    e = np.asarray(irradiance, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    n = grid * grid
    if e.shape != (n, 3) or m.shape != (n,):
        raise ValueError(f"plane irradiance must be ({n}, 3) with mask ({n},) for grid {grid}, "
                         f"got {e.shape} and {m.shape}")
    if grid % pool:
        raise ValueError(f"plane grid {grid} is not divisible by the pooling factor {pool}")
    w = m.astype(np.float32)
    if confidence is not None:
        w = w * np.clip(np.asarray(confidence, dtype=np.float32), 0.0, 1.0)
    e = np.where(np.isfinite(e), e, 0.0)
    wsum = float(w.sum())
    if wsum <= 0:
        raise ValueError("no observed plane cells: cannot measure the plane's illumination")
    s = float((e @ LUMA * w).sum() / wsum)
    if not s > 0:
        raise ValueError(f"plane irradiance has non-positive mean luminance {s}")
    g2 = grid // pool
    ew = (e / s * w[:, None]).reshape(g2, pool, g2, pool, 3).sum((1, 3))
    ws = w.reshape(g2, pool, g2, pool).sum((1, 3))
    x = np.zeros((g2, g2, 4), dtype=np.float32)
    x[..., :3] = ew / np.maximum(ws, 1e-6)[..., None]
    x[..., 3] = ws / (pool * pool)
    return x.reshape(g2 * g2, 4), s


def dominant_light(oi: np.ndarray, normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Dominant light direction (towards the light, object frame) and its share, from per-vertex OI.

    The OI vectors of all vertices point towards where light comes from; their luminance-weighted
    sum is the dominant direction, and the ratio of the sum's length to the sum of lengths says how
    much of the light comes from that one direction (1 = a single distant light, 0 = uniform).
    """
    lum = np.einsum("vcx,c->vx", np.asarray(oi, dtype=np.float32), LUMA)
    tot = lum.sum(0)
    norm = float(np.linalg.norm(tot))
    lens = float(np.linalg.norm(lum, axis=1).sum())
    if norm <= 1e-12 or lens <= 1e-12:
        return np.array([0.0, 1.0, 0.0], dtype=np.float32), 0.0
    return (tot / norm).astype(np.float32), float(np.clip(norm / lens, 0.0, 1.0))
