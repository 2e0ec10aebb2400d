"""Procedural albedo textures of the synthetic camera's planes (tileable noise, wood, tiles, carpet...)."""

from __future__ import annotations

import numpy as np

# ------------------------------------------------------------------------------------ textures


def _periodic_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth value noise of ``size``^2 that tiles seamlessly, from a ``cells``^2 random lattice."""
    import cv2

    base = rng.random((cells, cells)).astype(np.float32)
    pad = np.pad(base, 2, mode="wrap")
    scale = size / cells
    big = cv2.resize(
        pad, (int(round(pad.shape[1] * scale)), int(round(pad.shape[0] * scale))), interpolation=cv2.INTER_CUBIC
    )
    o = int(round(2 * scale))
    return big[o : o + size, o : o + size]


def _fractal(rng: np.random.Generator, size: int, octaves=(4, 16, 64), weights=(0.5, 0.3, 0.2)) -> np.ndarray:
    n = sum(w * _periodic_noise(rng, size, c) for c, w in zip(octaves, weights))
    return (n - n.mean()) / (n.std() + 1e-6)


def make_albedo_tile(kind: str, rng: np.random.Generator, size: int = 512) -> tuple[np.ndarray, float]:
    """A seamless albedo tile (size x size x 3, linear, in [0.02, 0.95]) and its period in metres.

    Kinds: ``wood`` (planks), ``tiles``, ``carpet``, ``paint`` (walls), ``ceiling``, ``concrete``,
    ``grass``, ``brick``, ``tabletop``.
    """
    s = size
    yy, xx = np.mgrid[0:s, 0:s].astype(np.float32) / s
    if kind == "wood":
        period, planks = 1.0, 8
        plank = np.floor(yy * planks).astype(int)
        tint = rng.uniform(0.75, 1.25, planks)[plank]
        grain = np.repeat(_fractal(rng, s, (2, 8, 32))[:1], s, axis=0) * 0.3 + _fractal(rng, s) * 0.15
        base = np.array([0.42, 0.27, 0.15]) * rng.uniform(0.7, 1.4)
        a = base * (tint * (1 + 0.25 * grain))[..., None]
        gap = np.mod(yy * planks, 1.0) < 0.02
        a[gap] *= 0.35
    elif kind == "tiles":
        period, n = 1.0, 4
        base = np.array(rng.uniform(0.45, 0.8, 3))
        base = base * 0.3 + base.mean() * 0.7
        cell = (np.floor(yy * n) * n + np.floor(xx * n)).astype(int)
        tint = rng.uniform(0.9, 1.1, n * n)[cell]
        a = base * (tint * (1 + 0.05 * _fractal(rng, s)))[..., None]
        grout = (np.mod(yy * n, 1.0) < 0.015) | (np.mod(xx * n, 1.0) < 0.015)
        a[grout] = 0.35
    elif kind == "carpet":
        period = 0.5
        base = rng.uniform(0.12, 0.45, 3)
        a = base * (1 + 0.15 * _fractal(rng, s, (8, 64, 256), (0.3, 0.3, 0.4)))[..., None]
    elif kind == "paint":
        period = 2.0
        base = rng.uniform(0.55, 0.8) * np.array([1.0, 1.0, 1.0]) * rng.uniform(0.92, 1.08, 3)
        a = base * (1 + 0.02 * _fractal(rng, s, (2, 8, 32)))[..., None]
    elif kind == "ceiling":
        period = 2.0
        a = np.full((s, s, 3), 0.8) * (1 + 0.01 * _fractal(rng, s))[..., None]
    elif kind == "concrete":
        period, n = 2.0, 2
        base = rng.uniform(0.2, 0.4) * np.array([1.0, 0.98, 0.95])
        a = base * (1 + 0.12 * _fractal(rng, s, (8, 32, 128)))[..., None]
        joint = (np.mod(yy * n, 1.0) < 0.006) | (np.mod(xx * n, 1.0) < 0.006)
        a[joint] *= 0.5
    elif kind == "grass":
        period = 1.0
        base = np.array([0.08, 0.16, 0.04]) * rng.uniform(0.8, 1.3)
        a = base * (1 + 0.3 * _fractal(rng, s, (4, 64, 256), (0.3, 0.3, 0.4)))[..., None]
    elif kind == "brick":
        period = 1.0
        rows, cols = 15, 4
        r = np.floor(yy * rows).astype(int)
        shift = (r % 2) * 0.5 / cols
        c = np.floor(np.mod(xx + shift, 1.0) * cols).astype(int)
        tint = rng.uniform(0.8, 1.2, (rows, cols))[r, c]
        base = np.array([0.45, 0.2, 0.12]) * rng.uniform(0.8, 1.2)
        a = base * (tint * (1 + 0.1 * _fractal(rng, s)))[..., None]
        mortar = (np.mod(yy * rows, 1.0) < 0.12) | (np.mod((xx + shift) * cols, 1.0) < 0.03)
        a[mortar] = 0.5
    elif kind == "tabletop":
        period = 1.0
        base = np.array([0.6, 0.45, 0.3]) * rng.uniform(0.8, 1.2)
        grain = np.repeat(_fractal(rng, s, (2, 8, 32))[:1], s, axis=0)
        a = base * (1 + 0.12 * grain)[..., None]
    else:
        raise ValueError(f"unknown albedo kind {kind!r}")
    return np.clip(a, 0.02, 0.95).astype(np.float32), period


# -------------------------------------------------------------------------------------- planes
