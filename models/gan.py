"""The transfer GAN (paper section 3.3 and 3.5): generator, discriminator, losses, unrolled update.

* Generator: 5 FC layers 256 -> 256 -> ... -> 256 (width :data:`GEN_WIDTH`); every layer but the last is
  followed by BatchNorm and LeakyReLU(0.2). It maps the plane latent to the object latent.
* Discriminator: 2 graph convolutions (BN + tanh) on the decoded object OI with its normals, then
  2 FC layers (BN + LeakyReLU on the first). It judges whether an OI field looks like the object's.
* Losses: LSGAN, pairing L1 in latent space, shading (squared error of L.n against the true
  shading, eq. 5) and smoothness of the decoded OI (eq. 6-7); total = LSGAN + 1.0 pair + 0.3 shading
  + 2.5 smooth by default.
* Unrolled GAN (Metz et al.): the generator's adversarial loss is taken against a copy of the
  discriminator advanced ``k`` plain gradient steps on the current batch, differentiated through.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from illuminet.models.gae import LATENT, batchnorm, dense, gconv, init_bn, init_dense, leaky

GEN_WIDTH = 256  # the paper does not give the width; 256 keeps a bundle under 10 MB


def init_generator(key, width: int = GEN_WIDTH) -> tuple[dict, dict]:
    dims = [LATENT, width, width, width, width, LATENT]
    ks = jax.random.split(key, 5)
    params, state = {}, {}
    for i in range(5):
        params[f"fc{i}"] = init_dense(ks[i], dims[i], dims[i + 1])
        if i < 4:
            params[f"bn{i}"], state[f"bn{i}"] = init_bn(dims[i + 1])
    return params, state


def generator(p: dict, s: dict, z, train: bool):
    """(B, 256) -> (B, 256); returns (output, new BN state)."""
    new = {}
    h = z
    for i in range(4):
        h, new[f"bn{i}"] = batchnorm(p[f"bn{i}"], s[f"bn{i}"], dense(p[f"fc{i}"], h), train)
        h = leaky(h)
    return dense(p["fc4"], h), new


def init_discriminator(key, n_vert: int, hidden: int = 16, fc: int = 64) -> tuple[dict, dict]:
    k = jax.random.split(key, 4)
    params = {
        "g1": init_dense(k[0], 12, hidden),
        "g2": init_dense(k[1], hidden, hidden),
        "fc0": init_dense(k[2], n_vert * hidden, fc),
        "fc1": init_dense(k[3], fc, 1),
    }
    state = {}
    for name, n in (("bn_g1", hidden), ("bn_g2", hidden), ("bn_fc0", fc)):
        params[name], state[name] = init_bn(n)
    return params, state


def discriminator(p: dict, s: dict, a_hat, normals, oi, train: bool = True):
    """OI (B, V, 3, 3) -> score (B,); returns (score, new BN state)."""
    b, n = oi.shape[0], oi.shape[1]
    h = jnp.concatenate([jnp.broadcast_to(normals[None], (b, n, 3)), oi.reshape(b, n, 9)], -1)
    new = {}
    h, new["bn_g1"] = batchnorm(p["bn_g1"], s["bn_g1"], gconv(p["g1"], a_hat, h), train)
    h = jnp.tanh(h)
    h, new["bn_g2"] = batchnorm(p["bn_g2"], s["bn_g2"], gconv(p["g2"], a_hat, h), train)
    h = jnp.tanh(h)
    h, new["bn_fc0"] = batchnorm(p["bn_fc0"], s["bn_fc0"], dense(p["fc0"], h.reshape(b, -1)), train)
    return dense(p["fc1"], leaky(h))[:, 0], new


def lsgan_d_loss(d_real, d_fake):
    """Least-squares GAN, discriminator side: real -> 1, fake -> 0."""
    return jnp.mean((d_real - 1.0) ** 2) + jnp.mean(d_fake**2)


def lsgan_g_loss(d_fake):
    """Least-squares GAN, generator side: make the fakes score 1."""
    return jnp.mean((d_fake - 1.0) ** 2)


def smoothness(mean_nb, field):
    """Eq. 6-7: mean |D^-1 A M - M| over vertices and features; field is (B, V, ...)."""
    b, n = field.shape[0], field.shape[1]
    m = field.reshape(b, n, -1)
    return jnp.mean(jnp.abs(jnp.einsum("ij,bjf->bif", mean_nb, m) - m))
