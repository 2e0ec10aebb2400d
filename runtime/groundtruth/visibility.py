"""Visibility of lights from a mesh's vertices: exact ray casts and a precomputed per-object field.

This module owns self-shadowing (the object hiding lights from its own vertices) and the shadow the
object casts on the plane it stands on, both for ground truth. Rays are cast with trimesh's ray
interface, which uses Embree (``embreex``) when installed and falls back to trimesh's pure-numpy
intersector otherwise (much slower, same answers).

:class:`VisibilityField` precomputes, once per object, the distance to the first hit along a dense
set of directions (a Fibonacci sphere) from every vertex; looking up a light is then a table lookup
with no ray casting, and it stays right for near lights because a light is visible when it is
nearer than the first hit. Its error against exact casts is measured by :meth:`VisibilityField.error`.
"""

from __future__ import annotations

import numpy as np
import trimesh

from illuminet.runtime.groundtruth.lighting import PointLights, fibonacci_sphere

#: Rays start this far off the surface (metres) so they do not hit the face they start on.
DEFAULT_EPS = 1e-4


def _intersector(mesh: trimesh.Trimesh):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # needs embreex

        return RayMeshIntersector(mesh)
    except Exception:  # no Embree on this platform: the numpy intersector gives the same hits
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


def _first_hit_distance(intersector, origins: np.ndarray, directions: np.ndarray, chunk: int = 1 << 19) -> np.ndarray:
    """Distance along each (unit) ray to its first hit, ``inf`` where it escapes."""
    out = np.full(origins.shape[0], np.inf)
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s : s + chunk], directions[s : s + chunk]
        loc, idx_ray, _ = intersector.intersects_location(o, d, multiple_hits=False)
        if len(idx_ray):
            dist = np.einsum("ix,ix->i", loc - o[idx_ray], d[idx_ray])
            np.minimum.at(out[s : s + chunk], idx_ray, dist)
    return out


def first_hits(
    mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray, chunk: int = 1 << 18, progress=None
) -> tuple[np.ndarray, np.ndarray]:
    """The triangle each ray hits first and where (Embree when installed).

    Parameters
    ----------
    mesh : the occluder
    origins, directions : (N, 3) ray starts and unit directions
    chunk : rays per call into the intersector
    progress : callable ``(done, total)``, optional, called after every chunk

    Returns
    -------
    tri : (N,) int64, the first triangle hit, -1 where the ray escapes
    location : (N, 3) float64, the hit point (NaN where the ray escapes)
    """
    rmi = _intersector(mesh)
    n = len(origins)
    tri = np.full(n, -1, np.int64)
    loc = np.full((n, 3), np.nan)
    for s in range(0, n, chunk):
        o, d = origins[s : s + chunk], directions[s : s + chunk]
        t, ray, p = rmi.intersects_id(o, d, multiple_hits=False, return_locations=True)
        if len(ray):
            tri[s + ray], loc[s + ray] = t, p
        if progress is not None:
            progress(min(s + chunk, n), n)
    return tri, loc


def gather_hits(mesh: trimesh.Trimesh, rows, directions, tri, loc, weights, n_rows: int):
    """Sparse (n_rows, V_mesh) matrix that reads values on the mesh's vertices at rays' hit points.

    Ray i (of row ``rows[i]``, along ``directions[i]``, first hit ``tri[i]`` at ``loc[i]`` as
    :func:`first_hits` gives them) adds ``weights[i]`` times the barycentric weights of its hit to the
    hit triangle's three corners; rays that escape (``tri < 0``) or meet a back face (an open mesh
    seen from inside) add nothing; entries of one row and corner are summed. ``M @ values`` is then,
    per row, the weighted sum of the values interpolated at its rays' hit points. Needs scipy.
    """
    from scipy.sparse import csr_matrix

    tri = np.asarray(tri)
    d = np.asarray(directions, np.float64)
    ok = tri >= 0
    ok[ok] = np.einsum("px,px->p", np.asarray(mesh.face_normals, np.float64)[tri[ok]], d[ok]) < 0.0
    corner = np.asarray(mesh.faces, np.int64)[tri[ok]]
    bary = trimesh.triangles.points_to_barycentric(np.asarray(mesh.vertices, np.float64)[corner], loc[ok])
    bary = np.clip(bary, 0.0, 1.0)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-12)
    vals = np.asarray(weights, np.float64)[ok][:, None] * bary
    return csr_matrix(
        (vals.ravel(), (np.repeat(np.asarray(rows)[ok], 3), corner.ravel())), shape=(n_rows, len(mesh.vertices))
    )


def _origins(points: np.ndarray, normals: np.ndarray | None, directions: np.ndarray, eps: float) -> np.ndarray:
    """Ray origins pushed off the surface: along the normal when known, else along the ray."""
    if normals is None:
        return points + eps * directions
    return points + eps * normals


def exact_visibility(
    mesh: trimesh.Trimesh,
    points: np.ndarray,
    light_positions: np.ndarray,
    eps: float = DEFAULT_EPS,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """Whether each light is visible from each point, by casting a ray to it (exact).

    Parameters
    ----------
    mesh : the occluder (usually the object itself)
    points : (V, 3) ray start points, same frame as ``mesh``
    light_positions : (N, 3) or a :class:`PointLights`
    eps : ray start offset off the surface, metres
    normals : (V, 3) optional surface normals of ``points``; rays then start ``eps`` along the
        normal (robust at grazing angles), else ``eps`` along the ray

    Returns
    -------
    (V, N) bool: True where nothing of ``mesh`` lies between the point and the light.
    """
    lp = light_positions.positions if isinstance(light_positions, PointLights) else np.asarray(light_positions, float)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    V, N = pts.shape[0], lp.shape[0]
    d = lp[None, :, :] - pts[:, None, :]
    r = np.linalg.norm(d, axis=2)
    d = d / np.maximum(r, 1e-12)[..., None]
    nrm = None if normals is None else np.repeat(np.asarray(normals, float).reshape(-1, 3), N, axis=0)
    o = _origins(np.repeat(pts, N, axis=0), nrm, d.reshape(-1, 3), eps)
    hit = _first_hit_distance(_intersector(mesh), o, d.reshape(-1, 3))
    return (hit >= r.reshape(-1) - eps).reshape(V, N)


def shadow_on_plane(
    mesh: trimesh.Trimesh, plane_points: np.ndarray, lights: PointLights | np.ndarray, eps: float = DEFAULT_EPS
) -> np.ndarray:
    """Visibility of each light from points on the plane the object stands on (its cast shadow).

    Parameters
    ----------
    mesh : the object, in the object frame (standing on y = 0)
    plane_points : (P, 3) points on the plane y = 0, object frame
    lights : PointLights or (N, 3) light positions, object frame

    Returns
    -------
    (P, N) float64 in {0, 1}: 0 where the object blocks the light (the point is in its shadow).
    Multiply into :func:`~illuminet.runtime.groundtruth.lighting.irradiance`'s ``visibility``.
    """
    pts = np.asarray(plane_points, dtype=np.float64).reshape(-1, 3)
    up = np.tile([0.0, 1.0, 0.0], (pts.shape[0], 1))
    return exact_visibility(mesh, pts, lights, eps, normals=up).astype(np.float64)


class VisibilityField:
    """Per-vertex first-hit distances over a dense set of directions, precomputed once per object.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object (object frame).
    points, normals : (V, 3), optional
        Where to evaluate (default: the mesh's vertices and vertex normals).
    n_directions : int
        Size of the Fibonacci direction set (1024: ~6.3 deg between neighbours).
    eps : float
        Ray start offset along the normal, metres.
    table_size : int
        The direction -> neighbours lookup table is ``2*table_size x table_size`` (equirectangular).
    k : int
        Field directions blended per lookup (soft visibility at shadow edges).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        points: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        n_directions: int = 1024,
        eps: float = DEFAULT_EPS,
        table_size: int = 96,
        k: int = 4,
    ):
        self.points = np.asarray(mesh.vertices if points is None else points, dtype=np.float64)
        self.normals = np.asarray(mesh.vertex_normals if normals is None else normals, dtype=np.float64)
        if self.points.shape != self.normals.shape:
            raise ValueError(f"points {self.points.shape} and normals {self.normals.shape} must both be (V, 3)")
        self.mesh = mesh
        self.eps = eps
        self.directions = fibonacci_sphere(n_directions)
        V, D = self.points.shape[0], n_directions
        o = np.repeat(self.points + eps * self.normals, D, axis=0)
        d = np.tile(self.directions, (V, 1))
        # float32 distances: 4 bytes x V x D (4 MB for 1000 vertices x 1024 directions)
        self.hit_distance = _first_hit_distance(_intersector(mesh), o, d).reshape(V, D).astype(np.float32)
        self._build_table(table_size, k)

    def _build_table(self, size: int, k: int) -> None:
        h, w = size, 2 * size
        theta = np.pi * (np.arange(h) + 0.5) / h
        phi = 2.0 * np.pi * (np.arange(w) + 0.5) / w
        st = np.sin(theta)[:, None]
        cells = np.stack(
            [st * np.cos(phi)[None], np.broadcast_to(np.cos(theta)[:, None], (h, w)), st * np.sin(phi)[None]], -1
        ).reshape(-1, 3)
        cos = cells @ self.directions.T
        idx = np.argpartition(-cos, k, axis=1)[:, :k]
        ang = np.arccos(np.clip(np.take_along_axis(cos, idx, 1), -1, 1))
        spacing = np.sqrt(4.0 * np.pi / len(self.directions))
        wgt = np.exp(-((ang / (0.6 * spacing)) ** 2))
        self._tab_idx = idx.astype(np.int32)
        self._tab_w = (wgt / wgt.sum(1, keepdims=True)).astype(np.float32)
        self._tab_shape = (h, w)

    def _cells(self, d: np.ndarray) -> np.ndarray:
        h, w = self._tab_shape
        theta = np.arccos(np.clip(d[..., 1], -1.0, 1.0))
        phi = np.mod(np.arctan2(d[..., 2], d[..., 0]), 2.0 * np.pi)
        row = np.minimum((theta / np.pi * h).astype(np.int64), h - 1)
        col = np.minimum((phi / (2.0 * np.pi) * w).astype(np.int64), w - 1)
        return row * w + col

    def lookup(self, directions: np.ndarray, distances: np.ndarray | None = None) -> np.ndarray:
        """Soft visibility (V, N) in [0, 1] of lights in ``directions``.

        Parameters
        ----------
        directions : (N, 3) unit directions shared by all vertices (distant lights), or (V, N, 3)
            per-vertex directions (near lights)
        distances : (N,) or (V, N) distance to each light; ``None`` = infinitely far
        """
        d = np.asarray(directions, dtype=np.float64)
        V = self.points.shape[0]
        if d.ndim == 2:
            d = np.broadcast_to(d[None], (V,) + d.shape)
        if d.shape[0] != V or d.shape[-1] != 3:
            raise ValueError(f"directions must be (N, 3) or (V={V}, N, 3), got {np.shape(directions)}")
        cell = self._cells(d)  # (V, N)
        idx = self._tab_idx[cell]  # (V, N, k)
        wgt = self._tab_w[cell]
        hit = np.take_along_axis(self.hit_distance[:, None, :], idx.reshape(V, -1)[:, None, :], axis=2)
        hit = hit.reshape(idx.shape)
        if distances is None:
            vis = np.isinf(hit)
        else:
            r = np.broadcast_to(np.asarray(distances, dtype=np.float64), d.shape[:2])
            vis = hit >= (r[..., None] - self.eps)
        return (vis * wgt).sum(axis=2)

    def lookup_lights(self, lights: PointLights | np.ndarray) -> np.ndarray:
        """Soft visibility (V, N) of point lights at their actual positions (object frame)."""
        lp = lights.positions if isinstance(lights, PointLights) else np.asarray(lights, float)
        v = lp[None, :, :] - self.points[:, None, :]
        r = np.linalg.norm(v, axis=2)
        return self.lookup(v / np.maximum(r, 1e-12)[..., None], r)

    def error(self, lights: PointLights | np.ndarray) -> dict[str, float]:
        """Compare :meth:`lookup_lights` with exact ray casts for these lights.

        Returns
        -------
        dict with ``mae`` (mean |soft - exact| over vertex-light pairs facing each other),
        ``disagree`` (share of pairs where the rounded soft value differs) and
        ``irradiance_rel`` (mean relative error of the resulting luminance irradiance).
        """
        from illuminet.runtime.groundtruth.lighting import irradiance

        lp = lights.positions if isinstance(lights, PointLights) else np.asarray(lights, float)
        exact = exact_visibility(self.mesh, self.points, lp, self.eps, normals=self.normals).astype(float)
        soft = self.lookup_lights(lp)
        facing = np.einsum("vnx,vx->vn", lp[None] - self.points[:, None], self.normals) > 0
        out = {
            "mae": float(np.abs(soft - exact)[facing].mean()) if facing.any() else 0.0,
            "disagree": float((np.round(soft) != exact)[facing].mean()) if facing.any() else 0.0,
        }
        if isinstance(lights, PointLights):
            luma = np.array([0.2126, 0.7152, 0.0722])
            e_exact = irradiance(self.points, self.normals, lights, exact) @ luma
            e_soft = irradiance(self.points, self.normals, lights, soft) @ luma
            out["irradiance_rel"] = float(np.abs(e_soft - e_exact).sum() / max(e_exact.sum(), 1e-12))
        return out
