"""Training and test data for the learned transfer: lighting environments, ground-truth OI, and the
plane measurement the runtime would see.

One sample is a lighting environment (32 RGB point lights in the object frame: object at the
origin standing on the plane y = 0, +Y up) and everything derived from it:

* the **plane** grid (``grid x grid`` vertices over ``extent x extent`` metres, vertex ``i*G+j`` at
  ``(x_j, 0, z_i)``, the layout of the plane-light stage) with its true irradiance. The object is
  *virtual*: it casts no shadow on the real plane and hides none of it from the camera, so neither
  appears in the plane input (an earlier version simulated both, which taught the model a cue that
  real frames never contain);
* the same grid as the runtime *measures* it: textured albedo divided out with the wrong (mean)
  albedo, sensor noise, 8-bit quantisation at an auto exposure, random holes and out-of-view
  regions masked;
* the object's **proxy** vertices' true OI ``(V, 3, 3)`` (vertex, channel, xyz) and shading, with
  self-visibility and the plane blocking light from below.

Visibility uses per-vertex tables over a dense set of directions, computed once per object by ray
casting (embree when available) and looked up by direction; a point light is treated as visible
when the ray towards it leaves the object. This is exact for distant light and for lights outside
the object's bounding volume, which is where the samplers put them.

Lighting kinds (the evaluation suites): ``indoor`` (ceiling lamps and wall fill in a room),
``outdoor`` (sun plus a sky dome, sometimes overcast), ``spatial`` (a few bright lamps close to the
object, so light varies across the plane) and ``hdr`` (real HDR maps, median cut into 32 lights,
randomly rotated and exposed) when HDR files are available.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from illuminet.runtime.assets.objects import load_object
from illuminet.runtime.groundtruth.lighting import fibonacci_sphere, load_hdr, median_cut
from illuminet.runtime.stages.shading import preprocess_plane

log = logging.getLogger(__name__)

KINDS = ("indoor", "outdoor", "spatial")
N_LIGHTS = 32
DISTANT_R = 50.0  # metres at which "distant" lights (sun, sky, HDR) are placed


# --------------------------------------------------------------------------- object geometry


@dataclass
class ObjectGeometry:
    """An object's render mesh, its lighting proxy (a vertex subset with a graph), and the mapping.

    Attributes
    ----------
    vertices, normals, faces : render mesh (R, 3), (R, 3), (F, 3)
    proxy_index : (V,) int, render vertex index of each proxy vertex
    proxy_edges : (E, 2) int, undirected proxy graph edges (k nearest neighbours, symmetrised)
    carry_index, carry_weight : (R, k) int / float, how render vertices interpolate proxy values
    name : str
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    proxy_index: np.ndarray
    proxy_edges: np.ndarray
    carry_index: np.ndarray
    carry_weight: np.ndarray
    name: str = "object"

    @property
    def proxy_vertices(self) -> np.ndarray:
        return self.vertices[self.proxy_index]

    @property
    def proxy_normals(self) -> np.ndarray:
        return self.normals[self.proxy_index]


def load_mesh(spec: str):
    """``builtin:NAME`` or a mesh file -> trimesh.Trimesh in the object frame (y = 0 base, +Y up).

    Thin wrapper over :func:`illuminet.runtime.assets.objects.load_object` (render detail, files scaled
    to its default height), kept so that training and evaluation name one entry point.

    Raises
    ------
    illuminet.runtime.assets.objects.ObjectLoadError
        Naming the spec or file when it is unknown, unreadable or holds no triangles.
    """
    return load_object(spec)


#: farthest-point sampling over more points than this first draws this many at random and samples
#: those (a 1.3M-face mesh: `illuminet bundle` spent 43 s here, now its whole mesh-and-proxy step is 8 s); fewer
#: points get exactly the selection they always got
FPS_MAX_POINTS = 50_000


def _farthest_points(x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (sorted) of ``n`` rows of ``x`` chosen by greedy farthest-point sampling from a random start."""
    n = min(n, len(x))
    if len(x) > FPS_MAX_POINTS and n < FPS_MAX_POINTS:
        sub = np.sort(rng.choice(len(x), FPS_MAX_POINTS, replace=False))
        return sub[_farthest_points(x[sub], n, rng)]  # sorted: both index lists are
    idx = np.empty(n, dtype=np.int64)
    idx[0] = rng.integers(len(x))
    d = np.linalg.norm(x - x[idx[0]], axis=1)
    for i in range(1, n):
        idx[i] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(x - x[idx[i]], axis=1))
    return np.sort(idx)


def build_geometry(mesh, n_proxy: int = 400, k_graph: int = 6, seed: int = 0, name: str = "object") -> ObjectGeometry:
    """Render mesh -> lighting proxy (farthest-point vertex subset + kNN graph) and carry mapping.

    Proxy neighbours and carry weights use a distance that also penalises differing normals, so
    light does not leak through thin walls (inside vs outside of a bowl).
    """
    from scipy.spatial import cKDTree

    v = np.asarray(mesh.vertices, dtype=np.float64)
    n = np.asarray(mesh.vertex_normals, dtype=np.float64)
    rng = np.random.default_rng(seed)
    scale = float(np.linalg.norm(np.ptp(v, axis=0)))
    feat = np.concatenate([v, n * 0.1 * scale], axis=1)  # position + normal-weighted
    pidx = _farthest_points(feat, n_proxy, rng)
    tree = cKDTree(feat[pidx])
    # a mesh with fewer vertices than neighbours asked for (a single triangle): cKDTree pads the missing
    # ones with index P (one past the proxy) at an infinite distance
    P = len(pidx)
    _, nb = tree.query(feat[pidx], k=k_graph + 1)
    edges = set()
    for i, row in enumerate(nb):
        for j in row[1:]:
            if i != j and j < P:
                edges.add((min(i, int(j)), max(i, int(j))))
    edges = np.array(sorted(edges), dtype=np.int64).reshape(-1, 2)
    d, ci = tree.query(feat, k=3)
    ci = np.where(ci < P, ci, ci[:, :1])  # a padded neighbour: any valid index, its weight is 0
    w = 1.0 / np.maximum(d, 1e-6) ** 2
    w /= w.sum(1, keepdims=True)
    return ObjectGeometry(
        vertices=v.astype(np.float32),
        normals=n.astype(np.float32),
        faces=np.asarray(mesh.faces, dtype=np.int32),
        proxy_index=pidx.astype(np.int32),
        proxy_edges=edges.astype(np.int32),
        carry_index=ci.astype(np.int32),
        carry_weight=w.astype(np.float32),
        name=name,
    )


# --------------------------------------------------------------------------- visibility


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` near-uniform unit directions on the sphere, (n, 3) float32.

    The runtime's :func:`~illuminet.runtime.groundtruth.lighting.fibonacci_sphere` lattice mirrored in z: this
    module's lattice always spiralled the other way, and the visibility tables and the outdoor sky
    of the shipped bundles' training data were built on it. For the sizes used here (1024 table
    directions, 62 sky directions) the result is bit-identical to the former own implementation;
    for other ``n`` it agrees to within float32 rounding (<= 1 ulp).
    """
    return (fibonacci_sphere(n) * (1.0, 1.0, -1.0)).astype(np.float32)


class DirectionVisibility:
    """Per-point visibility over a fixed direction set, looked up by direction (nearest direction).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Occluder (the object).
    points, normals : (N, 3)
        Where visibility is wanted; rays start slightly off the surface along the normal.
    n_dirs : int
        Size of the direction set (1024 gives ~6 degree spacing).
    plane_blocks : bool
        The plane y = 0 blocks directions pointing below the horizon.
    """

    def __init__(self, mesh, points, normals, n_dirs: int = 1024, plane_blocks: bool = True):
        from scipy.spatial import cKDTree

        self.dirs = fibonacci_directions(n_dirs)
        self._tree = cKDTree(self.dirs)
        pts = np.asarray(points, dtype=np.float64) + 1e-4 * np.asarray(normals, dtype=np.float64)
        n_pts = len(pts)
        origins = np.repeat(pts, n_dirs, axis=0)
        dirs = np.tile(self.dirs.astype(np.float64), (n_pts, 1))
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            rmi = RayMeshIntersector(mesh)
        except Exception:  # no embree: trimesh's pure-python intersector (slow but exact)
            rmi = mesh.ray
        hit = np.zeros(len(origins), dtype=bool)
        step = 1 << 20
        for s in range(0, len(origins), step):
            hit[s : s + step] = rmi.intersects_any(origins[s : s + step], dirs[s : s + step])
        vis = ~hit.reshape(n_pts, n_dirs)
        if plane_blocks:
            vis &= (self.dirs[None, :, 1] >= -1e-3) | (pts[:, None, 1] < 1e-3)
        self.table = vis

    def lookup(self, points: np.ndarray, light_pos: np.ndarray) -> np.ndarray:
        """(N, L) bool: is light l visible from point i (N must match the construction points)."""
        d = light_pos[None, :, :] - points[:, None, :]
        d /= np.linalg.norm(d, axis=-1, keepdims=True) + 1e-12
        _, k = self._tree.query(d.reshape(-1, 3))
        k = k.reshape(d.shape[:2])
        return np.take_along_axis(self.table, k, axis=1)


def oi_point_lights(points, normals, light_pos, light_rgb, vis=None) -> np.ndarray:
    """OI (N, 3, 3) of point lights (see :mod:`illuminet.runtime.physics`): channel x xyz.

    Same formula and clamp (r^2 >= 1e-6) as :func:`illuminet.runtime.groundtruth.lighting.oi_point_lights`,
    but computed in float32 on plain arrays. Kept on purpose rather than calling the runtime one:
    that computes in float64, which changes the float32 training targets by ~1e-7 (relative) and
    so would stop ``illuminet train`` from reproducing the shipped bundles bit for bit.
    """
    d = light_pos[None, :, :] - points[:, None, :]  # N, L, 3
    r2 = np.maximum((d * d).sum(-1), 1e-6)
    w = d / np.sqrt(r2)[..., None]
    cos = (w * normals[:, None, :]).sum(-1)
    g = (cos > 0).astype(np.float32) / r2
    if vis is not None:
        g = g * vis
    return np.einsum("nl,lc,nlx->ncx", g, light_rgb, w).astype(np.float32)


# --------------------------------------------------------------------------- lighting samplers


def _rand_color(rng, warmth: float) -> np.ndarray:
    """A light colour between blue-ish (warmth -1) and warm tungsten (+1), unit luminance-ish."""
    c = np.array([1.0 + 0.45 * warmth, 1.0, 1.0 - 0.5 * warmth]) * rng.uniform(0.9, 1.1, 3)
    c = np.clip(c, 0.2, None)
    return c / (0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])


def _distant(dirs: np.ndarray) -> np.ndarray:
    return dirs * DISTANT_R


def sample_lights(kind: str, rng: np.random.Generator, n: int = N_LIGHTS, hdr_lights=None):
    """One lighting environment: (positions (n, 3), rgb intensities (n, 3)) in the object frame.

    Intensities of distant lights are scaled by ``DISTANT_R**2`` so their irradiance does not depend
    on the placement distance.
    """
    pos = np.zeros((n, 3))
    rgb = np.zeros((n, 3))
    if kind == "indoor":
        k_main = rng.integers(1, 5)
        h = rng.uniform(2.2, 3.2)
        cx, cz = rng.uniform(-1.5, 1.5, 2)
        for j in range(n):
            if j < k_main:  # ceiling / lamps, bright, warm or cool
                pos[j] = [cx + rng.uniform(-1.8, 1.8), rng.uniform(1.2, h), cz + rng.uniform(-1.8, 1.8)]
                rgb[j] = _rand_color(rng, rng.uniform(-0.6, 1.0)) * rng.uniform(1.0, 4.0)
            else:  # diffuse fill: walls and ceiling, dim, all around
                a = rng.uniform(0, 2 * np.pi)
                r = rng.uniform(1.5, 3.5)
                pos[j] = [r * np.cos(a), rng.uniform(0.1, h), r * np.sin(a)]
                rgb[j] = _rand_color(rng, rng.uniform(-0.3, 0.6)) * rng.uniform(0.02, 0.25)
    elif kind == "outdoor":
        overcast = rng.random() < 0.3
        el = np.deg2rad(rng.uniform(8, 75))
        az = rng.uniform(0, 2 * np.pi)
        sun = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        pos[0] = _distant(sun)
        rgb[0] = _rand_color(rng, rng.uniform(0.1, 0.6)) * (
            rng.uniform(0.2, 1.0) if overcast else rng.uniform(3.0, 8.0)
        )
        sky = fibonacci_directions(2 * (n - 1))
        sky = sky[sky[:, 1] > 0][: n - 1]
        pos[1:] = _distant(sky)
        sky_i = (rng.uniform(0.6, 1.2) if overcast else rng.uniform(0.15, 0.5)) / (n - 1)
        # brighter sky towards the sun and the horizon
        shape = 1.0 + 0.8 * np.clip(sky @ sun, 0, None) ** 2 + 0.3 * (1 - sky[:, 1])
        rgb[1:] = (
            _rand_color(rng, rng.uniform(-0.9, -0.2) if not overcast else 0.0)[None] * (sky_i * shape)[:, None] * 6
        )
        # ground bounce: a dim light from low directions (the plane stops anything below y = 0)
        rgb[1:] *= rng.uniform(0.8, 1.2, (n - 1, 1))
        rgb *= DISTANT_R**2 / 6
    elif kind == "spatial":
        k_near = rng.integers(2, 6)
        for j in range(n):
            if j < k_near:  # small lamps near the object: light varies across the plane
                a = rng.uniform(0, 2 * np.pi)
                r = rng.uniform(0.25, 0.8)
                pos[j] = [r * np.cos(a), rng.uniform(0.05, 0.6), r * np.sin(a)]
                rgb[j] = _rand_color(rng, rng.uniform(-0.8, 1.0)) * rng.uniform(0.05, 0.3)
            else:
                a = rng.uniform(0, 2 * np.pi)
                r = rng.uniform(2.0, 4.0)
                pos[j] = [r * np.cos(a), rng.uniform(0.3, 3.0), r * np.sin(a)]
                rgb[j] = _rand_color(rng, rng.uniform(-0.3, 0.5)) * rng.uniform(0.01, 0.12)
    elif kind == "hdr":
        if not hdr_lights:
            raise ValueError("kind 'hdr' needs hdr_lights (median-cut lights of HDR maps)")
        dirs, rgb0 = hdr_lights[int(rng.integers(len(hdr_lights)))]
        a = rng.uniform(0, 2 * np.pi)  # random rotation about +Y (yaw) and a small pitch
        p = np.deg2rad(rng.uniform(-10, 10))
        Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
        d = dirs @ (Rx @ Ry).T
        pos = _distant(d[:n])
        rgb = rgb0[:n] * DISTANT_R**2 * np.exp(rng.uniform(-1.0, 1.0))
    else:
        raise ValueError(f"unknown lighting kind {kind!r}; expected one of {KINDS + ('hdr',)}")
    return pos.astype(np.float32), rgb.astype(np.float32)


def median_cut_lights(env: np.ndarray, n: int = N_LIGHTS) -> tuple[np.ndarray, np.ndarray]:
    """Median cut of an equirectangular linear-RGB map -> n (direction, rgb) lights, float32.

    :func:`illuminet.runtime.groundtruth.lighting.median_cut` cast to float32: directions in the object frame
    (+Y up, convention of :func:`~illuminet.runtime.groundtruth.lighting.equirect_directions`: image top =
    up, centre column = -Z), rgb the region's integral of radiance over solid angle, so that a
    distant light of direction d gives irradiance ``rgb * max(n.d, 0)``.
    """
    d, c = median_cut(env, n)
    return d.astype(np.float32), c.astype(np.float32)


def hdr_maps(folder: str | Path | None, split: str = "all") -> list[Path]:
    """The ``.hdr`` files of ``folder``, sorted; every 4th map (index % 4 == 3) is held out for testing.

    split : "train" (the other maps), "test" (the held-out ones) or "all".
    """
    if folder is None or not str(folder) or not Path(folder).is_dir():
        return []
    maps = sorted(Path(folder).glob("*.hdr"))
    if split == "train":
        return [p for i, p in enumerate(maps) if i % 4 != 3]
    if split == "test":
        return [p for i, p in enumerate(maps) if i % 4 == 3]
    return maps


def load_hdr_lights(folder: str | Path | None, n: int = N_LIGHTS, split: str = "all"):
    """Median-cut lights of the ``.hdr`` maps in ``folder`` (see :func:`hdr_maps`; empty when absent)."""
    import cv2

    out = []
    for p in hdr_maps(folder, split):
        try:
            img = load_hdr(p)
        except (OSError, ValueError) as e:  # one unreadable map should not stop training
            log.warning("%s; skipped", e)
            continue
        env = cv2.resize(img, (256, 128), interpolation=cv2.INTER_AREA)
        d, c = median_cut_lights(np.nan_to_num(env), n)
        c = c / max(float(c.sum(0).max()), 1e-9) * 3.0  # normalise total power; exposure is random later
        out.append((d, c))
    return out


# --------------------------------------------------------------------------- plane + samples


def plane_grid(grid: int, extent: float) -> np.ndarray:
    """(G*G, 3) plane vertices, vertex i*G+j = (x_j, 0, z_i) (the plane-light stage's layout)."""
    x = np.linspace(-extent / 2, extent / 2, grid)
    zz, xx = np.meshgrid(x, x, indexing="ij")
    return np.stack([xx.ravel(), np.zeros(grid * grid), zz.ravel()], 1).astype(np.float32)


class Scene:
    """Everything fixed for one object: geometry, plane grid and visibility tables."""

    def __init__(
        self,
        geom: ObjectGeometry,
        mesh,
        grid: int = 32,
        extent: float = 1.0,
        n_dirs: int = 1024,
        render_vis: bool = False,
    ):
        self.geom = geom
        self.grid = grid
        self.extent = extent
        self.plane_v = plane_grid(grid, extent)
        self.plane_n = np.tile(np.array([[0, 1, 0]], np.float32), (len(self.plane_v), 1))
        self.obj_vis = DirectionVisibility(mesh, geom.proxy_vertices, geom.proxy_normals, n_dirs)
        self.render_vis = DirectionVisibility(mesh, geom.vertices, geom.normals, n_dirs) if render_vis else None

    def truth(self, pos, rgb):
        """True plane irradiance (P, 3), proxy OI (V, 3, 3) and proxy shading (V, 3)."""
        # the virtual object does not shadow the real plane: no object visibility here
        plane_oi = oi_point_lights(self.plane_v, self.plane_n, pos, rgb, None)
        e_plane = plane_oi[:, :, 1]  # normal is +Y: E = OI . n = y component
        g = self.geom
        ov = self.obj_vis.lookup(g.proxy_vertices, pos)
        oi = oi_point_lights(g.proxy_vertices, g.proxy_normals, pos, rgb, ov)
        return e_plane, oi, np.einsum("vcx,vx->vc", oi, g.proxy_normals)

    def render_truth(self, pos, rgb):
        """True shading (R, 3) of every render-mesh vertex (needs ``render_vis=True``)."""
        g = self.geom
        vis = self.render_vis.lookup(g.vertices, pos)
        oi = oi_point_lights(g.vertices, g.normals, pos, rgb, vis)
        return np.einsum("vcx,vx->vc", oi, g.normals)

    def measure(self, e_plane: np.ndarray, rng: np.random.Generator, noise: float = 0.03):
        """What the plane-light stage would report: (irradiance (P, 3), mask (P,)).

        The plane has a textured albedo that the stage does not know (it divides by the mean);
        auto exposure puts the plane's mean at mid grey; noise then 8-bit sRGB quantisation; half the
        time part of the patch is out of view; random depth holes.
        """
        G = self.grid
        # smooth random albedo texture around 1 (relative), plus fine grain
        coarse = rng.normal(0, 1, (5, 5))
        import cv2

        tex = cv2.resize(coarse, (G, G), interpolation=cv2.INTER_CUBIC).ravel()
        alb = np.exp(0.15 * tex + 0.05 * rng.normal(0, 1, G * G))
        alb *= rng.uniform(0.92, 1.08, 3)[None, :].mean(1)  # wrong assumed albedo level: 1 channel
        albc = alb[:, None] * rng.uniform(0.95, 1.05, (1, 3))  # slight plane tint
        rad = e_plane * albc
        k = 0.18 / max(float(rad.mean()), 1e-9) * np.exp(rng.uniform(-0.7, 0.7))  # auto exposure
        pix = np.clip(rad * k * (1 + noise * rng.normal(0, 1, rad.shape)), 0, 1)
        s = np.where(pix <= 0.0031308, 12.92 * pix, 1.055 * np.power(pix, 1 / 2.4) - 0.055)
        s = np.round(s * 255) / 255
        lin = np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)
        meas = lin / k
        mask = np.ones(G * G, bool)  # the virtual object hides nothing of the real plane
        rel = self.plane_v[:, [0, 2]]
        if rng.random() < 0.5:  # part of the patch out of view / off the real plane
            nrm = rng.normal(0, 1, 2)
            nrm /= np.linalg.norm(nrm)
            mask &= rel @ nrm < rng.uniform(0.15, 0.5) * self.extent
        holes = rng.random(G * G) < rng.uniform(0, 0.1)  # depth holes
        mask &= ~holes
        meas[~mask] = 0
        return meas.astype(np.float32), mask


def _yaw(a: float) -> np.ndarray:
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], np.float32)


def _draw(scene: Scene, rng: np.random.Generator, kinds, hdr_lights, hdr_share: float, all_kinds: list):
    """One training sample from ``rng``: (plane input, scale, OI / scale, shading / scale, kind index)."""
    if hdr_lights and rng.random() < hdr_share:
        kind = "hdr"
    else:
        kind = kinds[int(rng.integers(len(kinds)))]
    pos, rgb = sample_lights(kind, rng, hdr_lights=hdr_lights)
    pos = pos @ _yaw(rng.uniform(0, 2 * np.pi)).T  # pose perturbation: object yaw vs the room
    e_plane, oi, sh = scene.truth(pos, rgb)
    meas, mask = scene.measure(e_plane, rng)
    x, s = preprocess_plane(meas, mask, scene.grid)
    return x, s, oi / s, sh / s, all_kinds.index(kind)


def _stack(samples: list) -> dict[str, np.ndarray]:
    planes, scales, ois, shs, ks = zip(*samples) if samples else ((), (), (), (), ())
    return {
        "plane": np.stack(planes).astype(np.float32),
        "scale": np.asarray(scales, np.float32),
        "oi": np.stack(ois).astype(np.float32),
        "shading": np.stack(shs).astype(np.float32),
        "kind": np.asarray(ks, np.int32),
    }


def generate(
    scene: Scene, n: int, seed: int, kinds=KINDS, hdr_lights=None, hdr_share: float = 0.25, progress=None
) -> dict[str, np.ndarray]:
    """``n`` training samples as arrays, all drawn from one random stream (what ``illuminet train`` uses).

    Returns
    -------
    dict with ``plane`` (n, P', 4) preprocessed plane input, ``scale`` (n,), ``oi`` (n, V, 3, 3)
    and ``shading`` (n, V, 3) both divided by ``scale``, ``kind`` (n,) int index into kinds (+hdr).

    The single stream makes sample ``i`` depend on every sample before it, so this data set cannot be
    split across machines; :func:`generate_indexed` (``illuminet datagen``) can. This one is kept as
    it is because the shipped bundles were trained on it (``illuminet train`` reproduces them).
    """
    rng = np.random.default_rng(seed)
    all_kinds = list(kinds) + (["hdr"] if hdr_lights else [])
    samples = []
    for i in range(n):
        samples.append(_draw(scene, rng, kinds, hdr_lights, hdr_share, all_kinds))
        if progress is not None:
            progress(i + 1, n)
    return _stack(samples)


def sample_rng(seed: int, index: int) -> np.random.Generator:
    """The random stream of sample ``index`` of data set ``seed``: ``SeedSequence([seed, index])``.

    Independent of every other sample, so any range of samples can be generated anywhere (a shard on
    another machine) and comes out bit for bit as in one process. ``seed`` and ``index`` >= 0.
    """
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def generate_indexed(
    scene: Scene,
    start: int,
    stop: int,
    seed: int,
    kinds=KINDS,
    hdr_lights=None,
    hdr_share: float = 0.25,
    progress=None,
) -> dict[str, np.ndarray]:
    """Samples ``start .. stop - 1`` of data set ``seed``, each from its own stream (:func:`sample_rng`).

    The same arrays as :func:`generate`'s layout; ``generate_indexed(s, 0, n)`` equals the
    concatenation of ``generate_indexed(s, a, b)`` over any split of ``0 .. n`` (what the sharded
    ``illuminet datagen --ray`` relies on).
    """
    if not 0 <= start <= stop:
        raise ValueError(f"sample range [{start}, {stop}) is not a range of indices >= 0")
    all_kinds = list(kinds) + (["hdr"] if hdr_lights else [])
    samples = []
    for i in range(start, stop):
        samples.append(_draw(scene, sample_rng(seed, i), kinds, hdr_lights, hdr_share, all_kinds))
        if progress is not None:
            progress(i - start + 1, stop - start)
    return _stack(samples)


# --------------------------------------------------------------------------- data sets as a job


@dataclass
class DataSpec:
    """Everything that defines a data set of :func:`generate_indexed`, self-contained (the mesh as
    arrays, HDR maps as their median-cut lights): a worker on another machine needs no files.

    Build with :func:`data_spec`; :meth:`scene` builds (once per process) the object's scene.
    """

    object: str
    seed: int
    n_proxy: int
    grid: int
    extent_m: float
    kinds: tuple
    hdr_share: float
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    hdr_lights: list
    hdr_maps: list
    name: str = "object"

    def meta(self) -> dict:
        """The JSON description of the data set (no arrays): what a data file records."""
        return {
            "object": self.object,
            "name": self.name,
            "seed": self.seed,
            "n_proxy": self.n_proxy,
            "grid": self.grid,
            "extent_m": self.extent_m,
            "kinds": list(self.kinds) + (["hdr"] if self.hdr_lights else []),
            "hdr_share": self.hdr_share if self.hdr_lights else 0.0,
            "hdr_maps": list(self.hdr_maps),
            "seeding": "sample i: numpy default_rng(SeedSequence([seed, i]))",
            "mesh_sha256": self.mesh_digest(),
        }

    def mesh_digest(self) -> str:
        import hashlib

        h = hashlib.sha256()
        for a in (self.vertices, self.faces, self.normals):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def scene(self) -> Scene:
        """The object's :class:`Scene` (proxy geometry + visibility tables), cached per process."""
        key = (self.mesh_digest(), self.seed, self.n_proxy, self.grid, self.extent_m)
        hit = _SCENES.get(key)
        if hit is None:
            import trimesh

            mesh = trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self.normals, process=False)
            geom = build_geometry(mesh, self.n_proxy, seed=self.seed, name=self.name)
            hit = Scene(geom, mesh, self.grid, self.extent_m)
            _SCENES.clear()  # one object at a time per process: tables are tens of MB
            _SCENES[key] = hit
        return hit

    def generate(self, start: int, stop: int, progress=None) -> dict[str, np.ndarray]:
        """Samples ``start .. stop - 1`` (:func:`generate_indexed`)."""
        share = self.hdr_share if self.hdr_lights else 0.0
        return generate_indexed(
            self.scene(), start, stop, self.seed, self.kinds, self.hdr_lights, share, progress=progress
        )


_SCENES: dict = {}


def data_spec(
    obj: str,
    seed: int = 0,
    n_proxy: int = 400,
    grid: int = 32,
    extent_m: float = 1.0,
    kinds=KINDS,
    hdr_dir: str | Path | None = None,
    hdr_share: float = 0.25,
) -> DataSpec:
    """Load the object and the training split of the HDR maps into a :class:`DataSpec`.

    Raises :class:`~illuminet.runtime.assets.objects.ObjectLoadError` for an unknown or unreadable
    object, ``ValueError`` for an unknown lighting kind or a negative seed.
    """
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise ValueError(f"lighting kinds {list(kinds)}: expected one or more of {', '.join(KINDS)}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    mesh = load_mesh(obj)
    name = obj.split(":", 1)[1] if obj.startswith("builtin:") else Path(obj).stem
    hdr = load_hdr_lights(hdr_dir, split="train") if hdr_dir else []
    names = [p.name for p in hdr_maps(hdr_dir, "train")] if hdr else []
    return DataSpec(
        object=obj,
        seed=int(seed),
        n_proxy=int(n_proxy),
        grid=int(grid),
        extent_m=float(extent_m),
        kinds=tuple(kinds),
        hdr_share=float(hdr_share),
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        normals=np.asarray(mesh.vertex_normals, dtype=np.float64),
        hdr_lights=hdr,
        hdr_maps=names,
        name=name,
    )


# --------------------------------------------------------------------------- data files


def data_bytes(arrays: dict[str, np.ndarray], meta: dict | None = None) -> bytes:
    """Arrays (+ a JSON ``meta`` record stored as uint8 bytes, no pickle) as the bytes of an npz file."""
    import io
    import json

    buf = io.BytesIO()
    extra = {"meta": np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)} if meta is not None else {}
    np.savez(buf, **arrays, **extra)
    return buf.getvalue()


def read_data(src) -> tuple[dict[str, np.ndarray], dict]:
    """An npz written by :func:`data_bytes` (a path or the bytes) -> (arrays, meta)."""
    import io
    import json

    with np.load(io.BytesIO(src) if isinstance(src, bytes) else src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(bytes(z["meta"]).decode()) if "meta" in z.files else {}
    return arrays, meta


def concat_data(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Sample ranges (in order) -> one data set."""
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
