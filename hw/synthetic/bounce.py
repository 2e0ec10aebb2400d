"""Indirect light of the synthetic scene: diffuse inter-reflection between its planes and onto objects.

Every plane is Lambertian: under irradiance ``E`` a plane of (mean) albedo ``rho`` has radiance
``rho E / pi`` on its front side; its back side reflects nothing but blocks light like the front.
Real rooms get a noticeable share of their light this way (a white floor lifts the underside of an
object and the bottom of the walls), so the ground truth and the picture carry it.

Method: radiosity on a lattice of patches per plane (10-25 cm, at most ~40 per side; each patch is a
block of the plane's 1-2 cm direct-light grid, averaged). From every patch centre
:data:`PLANE_DIRECTIONS` cosine-distributed rays (:mod:`illuminet.runtime.groundtruth.hemisphere`)
find the first plane they hit; that table of hits is the whole transport, computed once per scene.
Bounce ``k``'s irradiance is the mean radiance of bounce ``k - 1`` over a patch's rays times pi
(the cosine-weighted integral; patches are piecewise constant, as in classic radiosity): the
table of (receiving patch, source patch) pairs is built once, and ``N`` bounces cost ``N`` sums. The sum of
bounces ``1..N``,
bilinearly interpolated to the plane's fine grid, is added to its baked irradiance: the camera's
picture shows it at no cost per frame.

An object's vertex (:func:`object_radiance`) casts its own cosine-distributed rays (self-visibility
by the mesh in :class:`~illuminet.runtime.groundtruth.hemisphere.HemisphereVisibility`); where a ray
meets a plane it reads that plane's radiance from the fine direct grid plus bounces ``1..N-1`` (so
the vertex receives bounces ``1..N``), less the object's own shadow on the plane it stands on
(:func:`support_shadow`: the floor under a bowl is darker, so it lifts the bowl's underside less).
The object itself is black here unless an ``object_albedo`` is given
(:meth:`~illuminet.hw.synthetic.scene.SyntheticScene.true_object_shading`): then the light it
reflects onto itself (:func:`object_gather`, converged over :data:`OBJECT_PASSES` passes) is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.groundtruth.hemisphere import disk_directions, tangent_frames

#: rays per lattice patch for plane-to-plane transport (stratified, the same pattern on every patch)
PLANE_DIRECTIONS = 64
#: default rays per object vertex (see HemisphereVisibility)
OBJECT_DIRECTIONS = 128
#: patch size of the radiosity lattice: plane extent / 40, clipped to this range (metres)
PATCH_M = (0.1, 0.25)
#: rays start this far in front of a surface (metres)
EPS = 1e-4
#: hits this far outside a rectangle still count (closes the seams of a room's corners)
PAD = 1e-5


@dataclass
class Lattice:
    """A plane's radiosity patches: blocks of ``m x m`` nodes of its fine irradiance grid.

    Attributes
    ----------
    m : nodes per patch side; shape : (Lu, Lv) patches; lo, cell : the fine grid's origin and node
    spacing (``SyntheticPlane.grid_lo``, ``grid_cell_m``); direct : (Lu, Lv, 3) patch-mean direct
    irradiance; bounce : (Lu, Lv, 3) bounces 1..N; bounce_prev : bounces 1..N-1.
    """

    m: int
    shape: tuple[int, int]
    lo: np.ndarray
    cell: float
    direct: np.ndarray
    bounce: np.ndarray | None = None
    bounce_prev: np.ndarray | None = None

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """In-plane coordinates of the patch centres along the plane's two axes."""
        ca = self.lo[0] + ((np.arange(self.shape[0]) + 0.5) * self.m - 0.5) * self.cell
        cb = self.lo[1] + ((np.arange(self.shape[1]) + 0.5) * self.m - 0.5) * self.cell
        return ca, cb

    def bilinear(self, xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat patch indices (P, 4) and weights (P, 4) interpolating between patch centres."""
        Lu, Lv = self.shape
        fa = np.clip((np.asarray(xa, np.float64) - self.lo[0]) / self.cell + 0.5, 0, None) / self.m - 0.5
        fb = np.clip((np.asarray(xb, np.float64) - self.lo[1]) / self.cell + 0.5, 0, None) / self.m - 0.5
        fa = np.clip(fa, 0.0, Lu - 1.0)
        fb = np.clip(fb, 0.0, Lv - 1.0)
        ia = np.minimum(np.floor(fa).astype(np.int64), max(Lu - 2, 0))
        ib = np.minimum(np.floor(fb).astype(np.int64), max(Lv - 2, 0))
        ta, tb = fa - ia, fb - ib
        ia1, ib1 = np.minimum(ia + 1, Lu - 1), np.minimum(ib + 1, Lv - 1)
        idx = np.stack([ia * Lv + ib, ia * Lv + ib1, ia1 * Lv + ib, ia1 * Lv + ib1], axis=1)
        w = np.stack([(1 - ta) * (1 - tb), (1 - ta) * tb, ta * (1 - tb), ta * tb], axis=1)
        return idx, w

    def patch(self, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        """Flat index of the patch containing each in-plane point (clamped to the lattice)."""
        ia = np.clip(((np.asarray(xa) - self.lo[0]) / self.cell + 0.5) // self.m, 0, self.shape[0] - 1).astype(np.int64)
        ib = np.clip(((np.asarray(xb) - self.lo[1]) / self.cell + 0.5) // self.m, 0, self.shape[1] - 1).astype(np.int64)
        return ia * self.shape[1] + ib

    def sample(self, values: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of patch ``values`` (Lu, Lv, 3) at in-plane coordinates, (P, 3)."""
        idx, w = self.bilinear(xa, xb)
        return np.einsum("pk,pkc->pc", w, values.reshape(-1, 3)[idx])


def make_lattice(p) -> Lattice:
    """The radiosity lattice of a baked :class:`~illuminet.hw.synthetic.scene.SyntheticPlane`."""
    g = p.irradiance_grid if p.direct_grid is None else p.direct_grid
    nu, nv = g.shape[:2]
    ext = np.array([nu - 1, nv - 1]) * p.grid_cell_m
    target = float(np.clip(ext.max() / 40.0, *PATCH_M))
    m = max(1, int(round(target / p.grid_cell_m)))
    Lu, Lv = -(-nu // m), -(-nv // m)
    pad = np.pad(g, ((0, Lu * m - nu), (0, Lv * m - nv), (0, 0)), mode="edge")
    direct = pad.reshape(Lu, m, Lv, m, 3).mean(axis=(1, 3)).astype(np.float64)
    return Lattice(m, (Lu, Lv), np.asarray(p.grid_lo, np.float64), float(p.grid_cell_m), direct)


class PlaneCaster:
    """First hits of rays among axis-aligned rectangles (every plane blocks from both sides)."""

    def __init__(self, planes):
        self.planes = list(planes)

    def cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Plane index (N,) (-1: the ray leaves the scene) and distance (N,) of each ray's first hit.

        Parameters
        ----------
        o, d : (N, 3) origins and directions (any length; ``t`` is in units of ``|d|``)
        """
        o = np.asarray(o, np.float32)
        d = np.asarray(d, np.float32)
        n = o.shape[0]
        best_t = np.full(n, np.inf, np.float32)
        best_i = np.full(n, -1, np.int16)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / d
            for i, p in enumerate(self.planes):
                ax = p.axis
                t = (np.float32(p.coord) - o[:, ax]) * inv[:, ax]
                ok = (t > 0) & (t < best_t)
                if np.all(np.isfinite(p.lo)):
                    a, b = p.axes
                    xa = o[:, a] + t * d[:, a]
                    xb = o[:, b] + t * d[:, b]
                    ok &= (xa >= p.lo[0] - PAD) & (xa <= p.hi[0] + PAD) & (xb >= p.lo[1] - PAD) & (xb <= p.hi[1] + PAD)
                np.copyto(best_t, t, where=ok)
                np.copyto(best_i, np.int16(i), where=ok)
        return best_i, best_t


def _hits_by_plane(planes, o, d, idx, t):
    """Yield (plane index, ray indices, in-plane coordinates xa, xb) for rays that hit a front side."""
    order = np.argsort(idx, kind="stable")
    bounds = np.searchsorted(idx[order], np.arange(-1, len(planes) + 1))
    for j, p in enumerate(planes):
        sel = order[bounds[j + 1] : bounds[j + 2]]
        if sel.size == 0:
            continue
        sel = sel[d[sel, p.axis] * p.sign < 0]  # the back of a plane reflects nothing
        if sel.size == 0:
            continue
        a, b = p.axes
        tt = t[sel].astype(np.float64)
        yield j, sel, o[sel, a] + tt * d[sel, a], o[sel, b] + tt * d[sel, b]


def bake(scene, bounces: int, n_directions: int = PLANE_DIRECTIONS) -> None:
    """Add ``bounces`` diffuse inter-reflections between the scene's planes to their baked irradiance.

    Needs every plane's direct light baked (``irradiance_grid``). Sets on each plane
    ``direct_grid`` (the direct light alone), ``lattice`` (with ``bounce``/``bounce_prev``) and adds
    the bounce light to ``irradiance_grid``. ``bounces = 0`` leaves the planes as they are.
    """
    import cv2

    planes = scene.planes
    if bounces <= 0 or not planes:
        return
    for p in planes:
        if p.direct_grid is None:  # a second bake starts from the direct light again
            p.direct_grid = p.irradiance_grid
        p.lattice = make_lattice(p)
    caster = PlaneCaster(planes)
    local = disk_directions(n_directions)
    sizes = [int(np.prod(p.lattice.shape)) for p in planes]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    # the transport as a list of (receiving patch, source patch) pairs, one per ray that meets a
    # plane's front side (each ray carries pi / D of the cosine-weighted integral)
    recv_all, src_all = [], []
    for i, p in enumerate(planes):
        lat = p.lattice
        ca, cb = lat.centres()
        if np.all(np.isfinite(p.lo)):
            ca = np.clip(ca, p.lo[0], p.hi[0])
            cb = np.clip(cb, p.lo[1], p.hi[1])
        R = ca.size * cb.size
        pts = np.zeros((R, 3))
        pts[:, p.axis] = p.coord + EPS * p.sign
        pts[:, p.axes[0]] = np.repeat(ca, cb.size)
        pts[:, p.axes[1]] = np.tile(cb, ca.size)
        dirs = local @ tangent_frames(p.normal[None])[0].T  # (D, 3) world, same for all patches
        o = np.repeat(pts, n_directions, axis=0)
        d = np.tile(dirs, (R, 1))
        idx, t = caster.cast(o, d)
        for j, sel, xa, xb in _hits_by_plane(planes, o, d, idx, t):
            recv_all.append(offsets[i] + sel // n_directions)
            src_all.append(offsets[j] + planes[j].lattice.patch(xa, xb))
    S = int(offsets[-1])
    recv = np.concatenate(recv_all) if recv_all else np.zeros(0, np.int64)
    src = np.concatenate(src_all) if src_all else np.zeros(0, np.int64)
    # albedo / pi of every patch turns its irradiance into the radiance it sends out
    rho = np.concatenate([np.tile(p.albedo_mean / np.pi, (s, 1)) for p, s in zip(planes, sizes)])
    e_prev = np.concatenate([p.lattice.direct.reshape(-1, 3) for p in planes])  # irradiance of bounce k-1
    total = np.zeros_like(e_prev)
    for k in range(bounces):
        if k == bounces - 1:
            for i, p in enumerate(planes):
                p.lattice.bounce_prev = total[offsets[i] : offsets[i + 1]].reshape(*p.lattice.shape, 3).copy()
        rad = (e_prev * rho)[src]
        e_new = (
            np.pi
            / n_directions
            * np.stack([np.bincount(recv, weights=rad[:, c], minlength=S) for c in range(3)], axis=1)
        )
        total += e_new
        e_prev = e_new
    for i, p in enumerate(planes):
        lat = p.lattice
        lat.bounce = total[offsets[i] : offsets[i + 1]].reshape(*lat.shape, 3)
        nu, nv = p.direct_grid.shape[:2]
        # fine node j sits at lattice coordinate (j + 0.5) / m - 0.5
        mu = np.broadcast_to(((np.arange(nu, dtype=np.float32) + 0.5) / lat.m - 0.5)[:, None], (nu, nv))
        mv = np.broadcast_to(((np.arange(nv, dtype=np.float32) + 0.5) / lat.m - 0.5)[None, :], (nu, nv))
        up = cv2.remap(
            lat.bounce.astype(np.float32),
            np.ascontiguousarray(mv),
            np.ascontiguousarray(mu),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        p.irradiance_grid = (p.direct_grid + up.reshape(nu, nv, 3)).astype(np.float32)


@dataclass
class SupportShadow:
    """The object's own shadow on the plane it stands on, on a local grid: the direct irradiance it
    removes, and the share of the plane's inter-reflected light it lets through (the cosine-weighted
    part of the hemisphere the object does not cover: under a bowl, almost none)."""

    plane: int
    lo: np.ndarray  # in-plane coordinates of node (0, 0)
    cell: float
    delta: np.ndarray  # (nu, nv, 3) direct irradiance removed (>= 0)
    open_share: np.ndarray  # (nu, nv) in [0, 1]

    def at(self, xa: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(direct irradiance removed (P, 3), share of indirect light let through (P,))."""
        nu, nv = self.delta.shape[:2]
        ia = np.rint((xa - self.lo[0]) / self.cell).astype(np.int64)
        ib = np.rint((xb - self.lo[1]) / self.cell).astype(np.int64)
        inside = (ia >= 0) & (ia < nu) & (ib >= 0) & (ib < nv)
        delta = np.zeros((xa.shape[0], 3))
        delta[inside] = self.delta[ia[inside], ib[inside]]
        share = np.ones(xa.shape[0])
        share[inside] = self.open_share[ia[inside], ib[inside]]
        return delta, share


def support_shadow(
    scene, mesh, T_world_obj: np.ndarray, cells: int = 64, share: float = 0.0, n_directions: int = 32
) -> SupportShadow | None:
    """The shadow ``mesh`` (object frame, standing at ``T_world_obj``) casts on its supporting plane.

    The supporting plane is the up-facing plane through the object's origin. Lights giving more than
    ``share`` of the plane's irradiance at the origin are traced (default: every light that reaches
    it; with 2 % the error under a bowl in a 32-light room doubled); the share of indirect light the
    object lets through is the mean of ``n_directions``
    cosine-distributed rays. The grid spans 4x the object's size around it, ``cells`` nodes per
    side. ``None`` when the object does not stand on a plane.
    """
    from illuminet.runtime.groundtruth.hemisphere import HemisphereVisibility
    from illuminet.runtime.groundtruth.visibility import exact_visibility

    origin = T_world_obj[:3, 3]
    support = scene.support_plane(origin)
    if support is None:
        return None
    p = scene.planes[support]
    up = np.array([[0.0, 1.0, 0.0]])
    vis = scene.occlusion(origin[None] + 1e-4 * up)
    per = _per_light(origin, scene.lights, vis[0])
    strong = np.flatnonzero((per > 0) & (per >= share * max(per.sum(), 1e-12)))
    size = float(np.ptp(np.asarray(mesh.vertices), axis=0).max())
    r = 2.0 * max(size, 0.05)
    cell = 2 * r / (cells - 1)
    a, b = p.axes
    lo = np.array([origin[a] - r, origin[b] - r])
    ga, gb = np.meshgrid(lo[0] + np.arange(cells) * cell, lo[1] + np.arange(cells) * cell, indexing="ij")
    pts = np.zeros((cells * cells, 3))
    pts[:, 1] = p.coord
    pts[:, a] = ga.ravel()
    pts[:, b] = gb.ravel()
    T_ow = np.linalg.inv(T_world_obj)
    pts_obj = pts @ T_ow[:3, :3].T + T_ow[:3, 3]
    up_obj = np.tile(T_ow[:3, :3] @ up[0], (len(pts), 1))
    delta = np.zeros((len(pts), 3))
    if strong.size:
        lights = L.PointLights(scene.lights.positions[strong], scene.lights.intensities[strong])
        occ = scene.occlusion(pts + 1e-4 * up, lights)
        lights_obj = lights.transformed(T_ow[:3, :3], T_ow[:3, 3])
        obj_vis = exact_visibility(mesh, pts_obj, lights_obj, normals=up_obj)
        delta = L.irradiance(pts, np.tile(up, (len(pts), 1)), lights, occ * (1.0 - obj_vis))
    open_share = HemisphereVisibility(mesh, pts_obj, up_obj, n_directions, eps=EPS).visible.mean(1)
    return SupportShadow(support, lo, cell, delta.reshape(cells, cells, 3), open_share.reshape(cells, cells))


def _per_light(point: np.ndarray, lights: L.PointLights, vis: np.ndarray) -> np.ndarray:
    """Luminance of the irradiance each light gives an up-facing point (scene occlusion applied)."""
    d = lights.positions - point
    r2 = np.maximum((d * d).sum(1), L.MIN_LIGHT_DISTANCE**2)
    cos = np.maximum(d[:, 1] / np.sqrt(r2), 0.0)
    return cos / r2 * vis * (lights.intensities @ L._LUMA)


def object_radiance(
    scene, origins: np.ndarray, directions: np.ndarray, shadow: SupportShadow | None = None, chunk: int = 1 << 18
) -> np.ndarray:
    """Radiance (V, n, 3) the scene's planes send along rays (world frame) towards an object.

    Parameters
    ----------
    origins : (V, 3) ray start points (world); directions : (V, n, 3) unit directions (world)
    shadow : the object's own shadow on its supporting plane (:func:`support_shadow`), if any

    A ray that leaves the scene or meets a plane's back side carries nothing (the sky and the lights
    are the direct light's, already counted). A plane's radiance is its albedo / pi times its direct
    irradiance (fine grid, nearest node) plus bounces 1..N-1 (so the object receives bounces 1..N).
    """
    V, n = directions.shape[:2]
    o = np.repeat(np.asarray(origins, np.float64), n, axis=0)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    out = np.zeros((V * n, 3))
    planes = scene.planes
    caster = PlaneCaster(planes)
    for s in range(0, V * n, chunk):
        oc, dc = o[s : s + chunk], d[s : s + chunk]
        idx, t = caster.cast(oc, dc)
        for j, sel, xa, xb in _hits_by_plane(planes, oc, dc, idx, t):
            p = planes[j]
            g = p.direct_grid if p.direct_grid is not None else p.irradiance_grid
            ia = np.clip(np.rint((xa - p.grid_lo[0]) / p.grid_cell_m).astype(np.int64), 0, g.shape[0] - 1)
            ib = np.clip(np.rint((xb - p.grid_lo[1]) / p.grid_cell_m).astype(np.int64), 0, g.shape[1] - 1)
            e = g[ia, ib].astype(np.float64)
            open_share = None
            if shadow is not None and shadow.plane == j:
                delta, open_share = shadow.at(xa, xb)
                e = np.maximum(e - delta, 0.0)
            if p.lattice is not None and p.lattice.bounce_prev is not None:
                ind = p.lattice.sample(p.lattice.bounce_prev, xa, xb)
                e += ind if open_share is None else ind * open_share[:, None]
            out[s + sel] = e * (p.albedo_mean / np.pi)
    return out.reshape(V, n, 3)


_OBJECT_GATHERS: dict = {}


def object_gather(mesh, pts: np.ndarray, nrm: np.ndarray):
    """The object's light onto itself at ``pts``: a sparse (P, V_mesh) operator ``G`` such that, for
    irradiance ``E`` (V_mesh, 3) on the mesh's vertices, ``albedo * G @ E`` is the irradiance that
    the object (grey Lambertian, ``albedo``) reflects onto the points.

    Each of a point's cosine-distributed rays (the same :func:`~illuminet.hw.synthetic.scene.object_hemisphere`
    rays that gather the room's light) that the mesh blocks reads the hit point's radiance
    ``albedo / pi * E(hit)``, ``E`` interpolated barycentrically in the hit triangle; the cosine-weighted
    mean times pi makes ``G[p, v] = (1 / n) * sum of v's barycentric weights over p's front-face hits``.
    A ray that meets a back face (an open mesh seen from inside out) gets nothing. Cached per geometry.
    """
    from illuminet.hw.synthetic.scene import object_hemisphere
    from illuminet.runtime.groundtruth.visibility import first_hits, gather_hits

    parts = [pts, nrm, np.asarray(mesh.vertices), np.asarray(mesh.faces)]
    key = hash(tuple(np.ascontiguousarray(a).tobytes() for a in parts))
    G = _OBJECT_GATHERS.get(key)
    if G is not None:
        return G
    hv = object_hemisphere(mesh, pts, nrm)
    P, n = hv.visible.shape
    pi_, ki = np.nonzero(~hv.visible)
    d = hv.directions[pi_, ki].astype(np.float64)
    tri, loc = first_hits(mesh, hv.origins()[pi_], d)
    G = gather_hits(mesh, pi_, d, tri, loc, np.full(len(pi_), 1.0 / n), P)
    if len(_OBJECT_GATHERS) >= 4:
        _OBJECT_GATHERS.pop(next(iter(_OBJECT_GATHERS)))
    _OBJECT_GATHERS[key] = G
    return G


def on_mesh_vertices(mesh, pts: np.ndarray, nrm: np.ndarray) -> bool:
    """Whether ``pts`` / ``nrm`` are exactly the mesh's own vertices and vertex normals (then the light
    the room gives them is already the source :func:`object_light` needs, and its gather is shared)."""
    v = np.asarray(mesh.vertices)
    return np.shape(pts) == v.shape and np.array_equal(pts, v) and np.array_equal(nrm, np.asarray(mesh.vertex_normals))


#: interreflection passes of the object onto itself (albedo 0.8: the 6th pass adds < 1e-4 of the total)
OBJECT_PASSES = 8


def object_light(mesh, pts: np.ndarray, nrm: np.ndarray, source: np.ndarray, albedo: float, on_mesh: bool = False):
    """What the object (grey ``albedo``) reflects onto ``pts``, every bounce: (P, k).

    ``source`` (V_mesh, k) is the light the room gives the mesh's own vertices (vertex normals): an
    irradiance, or any quantity linear in the light such as a PRT transfer. ``on_mesh``: ``pts`` are
    the mesh's vertices with its vertex normals (the gather is then shared)."""
    if not 0.0 < albedo < 1.0:
        raise ValueError(f"object_albedo must be in (0, 1), got {albedo}")
    verts = np.asarray(mesh.vertices, np.float64)
    G = object_gather(mesh, verts, np.asarray(mesh.vertex_normals, np.float64))
    x = np.asarray(source, np.float64)
    for _ in range(OBJECT_PASSES):
        x = source + albedo * (G @ x)
    Gp = G if on_mesh else object_gather(mesh, pts, nrm)
    return albedo * (Gp @ x)
