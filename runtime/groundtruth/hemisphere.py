"""Cosine-weighted hemisphere sampling around surface normals, and a mesh's self-visibility over it.

This module owns the direction sets with which the ground truth integrates light arriving from
*surfaces* rather than from point lights: the indirect light of the synthetic camera's planes
(:mod:`illuminet.hw.synthetic.bounce`) and the precomputed radiance transfer of a mesh (Sloan, Kautz
& Snyder 2002) through which the evaluation's PRT oracle fits lighting.

Sampling: ``n`` directions per point, distributed with density ``cos(theta) / pi`` about the normal
(Malley's method on a golden-angle spiral of the unit disk, so they are stratified, not random). With
that density the cosine-weighted integral of any incident radiance ``L`` is a plain mean::

    E = integral L(w) max(0, n.w) dw  ~=  pi / n * sum_k L(w_k)

Self-visibility is one ray cast per direction against the mesh (Embree via trimesh, see
:mod:`illuminet.runtime.groundtruth.visibility`), computed once per mesh and reused.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from illuminet.runtime.sh import sh9

if TYPE_CHECKING:  # trimesh is slow to import; the direction sets do not need it
    import trimesh

#: rays start this far along the normal (metres); the same as visibility.DEFAULT_EPS
DEFAULT_EPS = 1e-4

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def disk_directions(n: int) -> np.ndarray:
    """``n`` cosine-distributed unit directions about +Z, stratified (local frame), (n, 3) float64.

    Points of a golden-angle spiral fill the unit disk uniformly; lifting them to the hemisphere
    (``z = sqrt(1 - r^2)``) gives the density ``cos(theta) / pi`` (Malley's method).
    """
    if n < 1:
        raise ValueError(f"disk_directions: n must be >= 1, got {n}")
    k = np.arange(n, dtype=np.float64) + 0.5
    r = np.sqrt(k / n)
    phi = _GOLDEN_ANGLE * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - r * r))], axis=1)


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(V, 3, 3) orthonormal frames whose third column is the unit normal (Duff et al. 2017)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    s = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t1 = np.stack([1.0 + s * n[:, 0] ** 2 * a, s * b, -s * n[:, 0]], axis=1)
    t2 = np.stack([b, s + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return np.stack([t1, t2, n], axis=2)


def cosine_directions(normals: np.ndarray, n: int) -> np.ndarray:
    """(V, n, 3) cosine-distributed unit directions about each normal (same pattern, rotated)."""
    frames = tangent_frames(normals)
    return np.einsum("vij,kj->vki", frames, disk_directions(n))


class HemisphereVisibility:
    """Per-vertex cosine-distributed directions and whether each escapes the mesh (precomputed once).

    Parameters
    ----------
    mesh : trimesh.Trimesh, optional
        The occluder (usually the object itself, object frame); ``None`` = nothing blocks.
    points, normals : (V, 3), optional
        Where to evaluate (default: the mesh's vertices and vertex normals).
    n_directions : int
        Directions per point (128: the mean's error on smooth incident light is ~1 %).
    eps : float
        Rays start this far along the normal, metres.

    Attributes
    ----------
    directions : (V, n, 3) float32 unit directions, same frame as the mesh
    visible : (V, n) bool, True where the ray leaves without hitting the mesh
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh | None,
        points: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        n_directions: int = 128,
        eps: float = DEFAULT_EPS,
    ):
        if mesh is None and (points is None or normals is None):
            raise ValueError("HemisphereVisibility: give points and normals when there is no mesh")
        self.points = np.asarray(mesh.vertices if points is None else points, dtype=np.float64).reshape(-1, 3)
        nrm = np.asarray(mesh.vertex_normals if normals is None else normals, dtype=np.float64).reshape(-1, 3)
        if self.points.shape != nrm.shape:
            raise ValueError(f"points {self.points.shape} and normals {nrm.shape} must both be (V, 3)")
        self.normals = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        self.eps = float(eps)
        d = cosine_directions(self.normals, int(n_directions))
        self.directions = d.astype(np.float32)
        V, n = d.shape[:2]
        if mesh is None:
            self.visible = np.ones((V, n), bool)
        else:
            from illuminet.runtime.groundtruth.visibility import _first_hit_distance, _intersector

            o = np.repeat(self.points + eps * self.normals, n, axis=0)
            hit = _first_hit_distance(_intersector(mesh), o, d.reshape(-1, 3))
            self.visible = np.isinf(hit).reshape(V, n)

    @property
    def n_directions(self) -> int:
        return self.directions.shape[1]

    def origins(self) -> np.ndarray:
        """(V, 3) ray start points (pushed ``eps`` off the surface)."""
        return self.points + self.eps * self.normals

    def irradiance(self, radiance: np.ndarray) -> np.ndarray:
        """Irradiance (V, 3) from incident radiance (V, n, 3) along :attr:`directions`, masked by
        :attr:`visible` (the mesh hides what lies behind it)."""
        L = np.asarray(radiance, dtype=np.float64)
        return np.pi / self.n_directions * np.einsum("vkc,vk->vc", L, self.visible)

    def vector_irradiance(self, radiance: np.ndarray) -> np.ndarray:
        """OI (V, 3 channels, 3 xyz): ``integral L(w) w V(w) dw``; its dot with the normal is
        :meth:`irradiance` exactly (each sample carries ``w / cos``)."""
        L = np.asarray(radiance, dtype=np.float64)
        d = self.directions.astype(np.float64)
        cos = np.einsum("vkx,vx->vk", d, self.normals)
        w = self.visible / np.maximum(cos, 1e-6)
        return np.pi / self.n_directions * np.einsum("vkc,vk,vkx->vcx", L, w, d)

    def transfer_sh9(self, visibility: bool = True) -> np.ndarray:
        """Precomputed radiance transfer (V, 9): ``T_i(lm) = integral max(0, n_i.w) V_i(w) Y_lm(w) dw``.

        For *radiance* SH coefficients ``L`` (9, 3) of distant light, ``E_i = T_i @ L``. Without
        visibility ``T_i = A_hat_l Y_lm(n_i)`` (up to sampling error): the plain irradiance basis.
        """
        V, n = self.visible.shape
        Y = sh9(self.directions.reshape(-1, 3).astype(np.float64)).reshape(V, n, 9)
        m = self.visible if visibility else np.ones_like(self.visible)
        return np.pi / n * np.einsum("vkl,vk->vl", Y, m)
