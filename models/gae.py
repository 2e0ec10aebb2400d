"""Graph autoencoders (paper section 3.2 and 3.4) in JAX: plane GAE, object GAE, colour GAE.

Layers are plain functions over parameter dicts (no framework beyond JAX), so that export to ONNX
(:mod:`illuminet.models.export`) can write the very same arithmetic node by node.

Graph convolution (Kipf & Welling): ``H' = act(A_hat @ H @ W + b)`` with the normalised adjacency
``A_hat = D^-1/2 (A + I) D^-1/2`` as a **real matrix product**. (The paper's reference code
multiplies element-wise, which removes all neighbour mixing; that defect is fixed here.)

* Plane GAE: (P, 4) normalised irradiance + observed fraction -> 2 graph convs -> FC -> z (256);
  decoder FC -> per-vertex features -> 2 graph convs -> irradiance (P, 3).
* Object GAE: (V, 12) normals + OI -> 2 graph convs -> FC -> z (256); decoder FC -> per-vertex
  features, **concatenated with the target mesh's normals** -> 2 graph convs -> OI (V, 3, 3).
* Colour GAE: OI + normals (+ the analytic L.n) -> 2 graph convs -> per-channel shading (V, 3),
  a residual on L.n (the paper outputs N x 1 grey; here one value per colour channel).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

LATENT = 256
LEAK = 0.2


# --------------------------------------------------------------------------- graph helpers


def normalized_adjacency(n: int, edges: np.ndarray) -> np.ndarray:
    """Dense ``D^-1/2 (A + I) D^-1/2`` (float32) of an undirected graph with ``n`` nodes."""
    a = np.eye(n, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    a[e[:, 0], e[:, 1]] = 1.0
    a[e[:, 1], e[:, 0]] = 1.0
    d = 1.0 / np.sqrt(a.sum(1))
    return (a * d[:, None] * d[None, :]).astype(np.float32)


def mean_neighbour_matrix(n: int, edges: np.ndarray) -> np.ndarray:
    """``D^-1 A`` without self loops: row i averages i's neighbours (smoothness loss, eq. 6-7)."""
    a = np.zeros((n, n), dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    a[e[:, 0], e[:, 1]] = 1.0
    a[e[:, 1], e[:, 0]] = 1.0
    return (a / np.maximum(a.sum(1, keepdims=True), 1.0)).astype(np.float32)


def grid_edges(g: int) -> np.ndarray:
    """4-neighbour edges of a g x g grid (row-major vertex i*g+j)."""
    idx = np.arange(g * g).reshape(g, g)
    right = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)
    down = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1)
    return np.concatenate([right, down]).astype(np.int32)


# --------------------------------------------------------------------------- layers


def init_dense(key, n_in: int, n_out: int, scale: float = 1.0) -> dict:
    w = jax.random.normal(key, (n_in, n_out), jnp.float32) * (scale * np.sqrt(2.0 / (n_in + n_out)))
    return {"w": w, "b": jnp.zeros((n_out,), jnp.float32)}


def dense(p: dict, x):
    return x @ p["w"] + p["b"]


def gconv(p: dict, a_hat, h):
    """One graph convolution (no activation): ``A_hat @ (H @ W) + b`` for H of shape (B, N, F)."""
    return jnp.einsum("ij,bjf->bif", a_hat, h @ p["w"]) + p["b"]


def dropout(key, x, rate: float, train: bool):
    if not train or rate <= 0 or key is None:
        return x
    keep = jax.random.bernoulli(key, 1.0 - rate, x.shape)
    return jnp.where(keep, x / (1.0 - rate), 0.0)


def init_bn(n: int) -> tuple[dict, dict]:
    """BatchNorm parameters (scale, bias) and state (running mean, var)."""
    return (
        {"g": jnp.ones((n,), jnp.float32), "b": jnp.zeros((n,), jnp.float32)},
        {"m": jnp.zeros((n,), jnp.float32), "v": jnp.ones((n,), jnp.float32)},
    )


def batchnorm(p: dict, s: dict, x, train: bool, momentum: float = 0.9, eps: float = 1e-5):
    """BatchNorm over all axes but the last; returns (y, new_state)."""
    if train:
        axes = tuple(range(x.ndim - 1))
        m = x.mean(axes)
        v = x.var(axes)
        s = {
            "m": momentum * s["m"] + (1 - momentum) * jax.lax.stop_gradient(m),
            "v": momentum * s["v"] + (1 - momentum) * jax.lax.stop_gradient(v),
        }
    else:
        m, v = s["m"], s["v"]
    return (x - m) / jnp.sqrt(v + eps) * p["g"] + p["b"], s


def leaky(x):
    return jnp.where(x >= 0, x, LEAK * x)


# --------------------------------------------------------------------------- plane GAE


def init_plane_gae(key, n_vert: int, f_in: int = 4, hidden: int = 8, dec_feat: int = 8) -> dict:
    k = jax.random.split(key, 6)
    return {
        "enc": {
            "g1": init_dense(k[0], f_in, hidden),
            "g2": init_dense(k[1], hidden, hidden),
            "fc": init_dense(k[2], n_vert * hidden, LATENT),
        },
        "dec": {
            "fc": init_dense(k[3], LATENT, n_vert * dec_feat),
            "g1": init_dense(k[4], dec_feat, hidden),
            "g2": init_dense(k[5], hidden, 3),
        },
    }


def plane_encode(p: dict, a_hat, x, key=None, train: bool = False, rate: float = 0.2):
    """(B, P, 4) -> (B, 256)."""
    k1, k2 = (None, None) if key is None else jax.random.split(key)
    h = jnp.tanh(gconv(p["g1"], a_hat, x))
    h = dropout(k1, h, rate, train)
    h = jnp.tanh(gconv(p["g2"], a_hat, h))
    h = dropout(k2, h, rate, train)
    return dense(p["fc"], h.reshape(h.shape[0], -1))


def plane_decode(p: dict, a_hat, z):
    n = a_hat.shape[0]
    h = jnp.tanh(dense(p["fc"], z).reshape(z.shape[0], n, -1))
    h = jnp.tanh(gconv(p["g1"], a_hat, h))
    return gconv(p["g2"], a_hat, h)


# --------------------------------------------------------------------------- object GAE


def init_object_gae(key, n_vert: int, hidden: int = 16, dec_feat: int = 4, dec_hidden: int = 32) -> dict:
    k = jax.random.split(key, 6)
    return {
        "enc": {
            "g1": init_dense(k[0], 12, hidden),
            "g2": init_dense(k[1], hidden, hidden),
            "fc": init_dense(k[2], n_vert * hidden, LATENT),
        },
        "dec": {
            "fc": init_dense(k[3], LATENT, n_vert * dec_feat),
            "g1": init_dense(k[4], dec_feat + 3, dec_hidden),
            "g2": init_dense(k[5], dec_hidden, 9, scale=0.5),
        },
    }


def object_features(oi, normals):
    """(B, V, 3, 3) OI + (V, 3) normals -> (B, V, 12) encoder input."""
    b = oi.shape[0]
    n = jnp.broadcast_to(normals[None], (b,) + normals.shape)
    return jnp.concatenate([n, oi.reshape(b, oi.shape[1], 9)], -1)


def object_encode(p: dict, a_hat, feats, key=None, train: bool = False, rate: float = 0.2):
    return plane_encode(p, a_hat, feats, key, train, rate)


def object_decode(p: dict, a_hat, normals, z):
    """z (B, 256) + the target's normals (V, 3) -> OI (B, V, 3, 3)."""
    b, n = z.shape[0], a_hat.shape[0]
    h = jnp.tanh(dense(p["fc"], z).reshape(b, n, -1))
    h = jnp.concatenate([h, jnp.broadcast_to(normals[None], (b, n, 3))], -1)
    h = jnp.tanh(gconv(p["g1"], a_hat, h))
    return gconv(p["g2"], a_hat, h).reshape(b, n, 3, 3)


# --------------------------------------------------------------------------- colour GAE


def init_colour(key, hidden: int = 16) -> dict:
    k = jax.random.split(key, 2)
    return {"g1": init_dense(k[0], 15, hidden), "g2": init_dense(k[1], hidden, 3, scale=0.1)}


def shade(oi, normals):
    """Analytic shading L.n per channel: (B, V, 3, 3), (V, 3) -> (B, V, 3)."""
    return jnp.einsum("bvcx,vx->bvc", oi, normals)


def colour(p: dict, a_hat, normals, oi):
    """OI (B, V, 3, 3) -> shading (B, V, 3): L.n plus a learned graph residual."""
    b, n = oi.shape[0], oi.shape[1]
    e = shade(oi, normals)
    h = jnp.concatenate([oi.reshape(b, n, 9), jnp.broadcast_to(normals[None], (b, n, 3)), e], -1)
    h = jnp.tanh(gconv(p["g1"], a_hat, h))
    return e + gconv(p["g2"], a_hat, h)
