"""Precomputing an object's radiance transfer (PRT), offline, once per mesh: what ``illuminet bundle``
adds to a bundle so that any mesh can be shaded physically, with no training.

Per lighting-proxy vertex (the layout and the run-time side are in :mod:`illuminet.runtime.prt`):

* the SH transfer vector ``T_i(lm) = integral of max(0, n_i . w) V_i(w) Y_lm(w) dw`` with the
  object's self-visibility V_i, computed as the closed form of an unoccluded vertex,
  ``A_hat_l Y_lm(n_i)``, minus a quadrature of the blocked directions (equal-weight Fibonacci
  directions, ``4 pi / N`` each). A vertex the object does not occlude therefore gets the exact
  no-visibility value, and the quadrature error only touches the occluded part. The floor (y = 0)
  is deliberately not an occluder here: what a ray sees below the horizon is the floor, whose
  radiance is the lower hemisphere of the light estimate's ambient SH (the floor bounce), darkened
  where the object shadows the floor (:func:`floor_occlusion`: nothing under the base);
* the primary light's visibility over K table directions: the object and the vertex's own tangent
  plane (``n_i . w <= 0``) block; the floor is applied at run time, exactly at the horizon (a table
  entry for it would blur the horizon over the interpolation kernel, dimming a low sun);
* optionally one interreflection bounce: light the object reflects onto itself. For each blocked
  ray, the surface it hits reflects ``albedo / pi`` times that point's own irradiance, which is its
  transfer vector (interpolated: proxy -> render vertices by the bundle's carry weights, then
  barycentric in the hit triangle) applied to the same lighting. Back-face hits (open meshes) add
  nothing. :func:`interreflection` iterates the same operator to convergence, which is how the
  bundle command measures what the single bounce leaves out;
* the primary light's interreflection as a (V, V) matrix, ``bounce_matrix``
  (:func:`primary_bounce_matrix`): the same operator applied to each vertex's unit direct light,
  every bounce summed. At run time it bounces the primary light's own direct light (its cosine,
  falloff and visibility), so a lamp shining into a cavity lights its inside and one beside it does
  not, which the primary's SH2 lobe cannot tell apart.

Rays are cast with Embree through :func:`illuminet.runtime.groundtruth.visibility.first_hits`,
starting ``eps`` off the surface along the normal; only directions in front of the vertex are cast.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from illuminet.runtime.groundtruth.lighting import fibonacci_sphere
from illuminet.runtime.groundtruth.visibility import DEFAULT_EPS, first_hits, gather_hits
from illuminet.runtime.prt import PrtTables, pack_visibility, unoccluded_transfer
from illuminet.runtime.sh import sh9

#: directions of the transfer quadrature (only those in front of a vertex are cast: about half)
DEFAULT_TRANSFER_RAYS = 4096
#: directions of the primary light's visibility table (~3.2 degrees apart; the kernel then blurs a
#: shadow line over ~5 degrees instead of ~10: a lamp's shadow inside the bowl, camera eval lamp suite
#: bowl 0.0631 -> 0.0615, vase 0.0438 -> 0.0423; +0.05-0.3 ms a near light's shading, 400 proxy vertices)
DEFAULT_TABLE_DIRECTIONS = 4096
#: interreflection bounces summed into ``bounce`` (albedo 0.8: the vase's 8th adds < 0.1 % of its light)
DEFAULT_BOUNCES = 8
#: proxies with more vertices than this get no ``bounce_matrix`` (V x V: 2000 -> 8 MB in the file, 16 MB
#: loaded, ~1 ms a frame); their primary light bounces through ``bounce_primary`` as before
MAX_BOUNCE_MATRIX = 2000
#: columns of the bounce matrix computed together (memory: the gather's rays x this many floats)
BOUNCE_MATRIX_BLOCK = 64
#: directions of the primary light's floor-shadow table (``floor_shadow``: the object's shadow on the
#: floor, summed over the floor its downward rays see, is smooth in the light's direction)
FLOOR_SHADOW_DIRECTIONS = 512
#: the floor-shadow grid reaches this many object heights beyond the footprint (a lamp 30 degrees up
#: casts a shadow 1.7 heights long)
FLOOR_SHADOW_REACH = 2.0


@dataclass
class PrtResult:
    """What :func:`compute_prt` returns: the tables and how long each step took.

    ``bounce_operator`` keeps the blocked rays' hits (for :func:`interreflection`); it is not stored.
    """

    transfer: np.ndarray  # (V, 9) float32
    vis_directions: np.ndarray  # (K, 3) float32
    visibility: np.ndarray  # (V, K) bool
    bounce: np.ndarray | None  # (V, 9) float32, albedo included: all ``bounces`` interreflections
    albedo: float
    timings_s: dict = field(default_factory=dict)
    bounce_operator: Callable[[np.ndarray], np.ndarray] | None = None
    bounces: int = 1
    bounce_primary: np.ndarray | None = None  # (V, 9) float32: the single bounce, for the primary light
    #: (V, V) float32: every bounce onto point i of a unit direct irradiance at point j (the primary's)
    bounce_matrix: np.ndarray | None = None
    #: (F, 3) directions and (V, F) table of the primary light's shadow on the floor as the points see
    #: it (:func:`floor_shadow_table`)
    floor_dirs: np.ndarray | None = None
    floor_shadow: np.ndarray | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``prt.npz`` (:data:`illuminet.runtime.prt.PRT_KEYS`, + ``bounce``)."""
        out = {
            "transfer": self.transfer.astype(np.float32),
            "vis_directions": self.vis_directions.astype(np.float32),
            "vis_bits": pack_visibility(self.visibility),
        }
        if self.bounce is not None:
            out["bounce"] = self.bounce.astype(np.float32)
        if self.bounce_primary is not None:
            out["bounce_primary"] = self.bounce_primary.astype(np.float32)
        if self.bounce_matrix is not None:
            out["bounce_matrix"] = self.bounce_matrix.astype(np.float16)
        if self.floor_shadow is not None:
            out["floor_dirs"] = self.floor_dirs.astype(np.float32)
            out["floor_shadow"] = self.floor_shadow.astype(np.float16)
        return out

    def tables(self) -> PrtTables:
        """The run-time tables, as :func:`illuminet.runtime.assets.bundle.load_bundle` would read them."""
        return PrtTables.from_arrays(self.arrays(), len(self.transfer))


def _front_pairs(normals: np.ndarray, directions: np.ndarray, extra: np.ndarray | None = None):
    """(vertex, direction) index pairs with ``n . w > 0`` (and ``extra[k]`` when given)."""
    front = normals @ directions.T > 0.0
    if extra is not None:
        front &= extra[None, :]
    return np.nonzero(front)


def compute_prt(
    mesh,
    points: np.ndarray,
    normals: np.ndarray,
    carry: Callable[[np.ndarray], np.ndarray] | None = None,
    transfer_rays: int = DEFAULT_TRANSFER_RAYS,
    table_directions: int = DEFAULT_TABLE_DIRECTIONS,
    albedo: float = 0.0,
    eps: float = DEFAULT_EPS,
    progress: Callable[[str, int, int], None] | None = None,
    floor_shadow: bool = True,
    bounces: int = DEFAULT_BOUNCES,
    with_bounce_matrix: bool = True,
    with_floor_table: bool = True,
) -> PrtResult:
    """PRT tables of ``points`` on ``mesh`` (see the module docstring).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object in its object frame (standing on y = 0, +Y up); the occluder.
    points, normals : (V, 3)
        Where to compute (the lighting proxy's vertices) and their unit normals.
    carry : callable (V, 9) -> (R, 9), optional
        Maps values on ``points`` to the mesh's R vertices (the bundle's carry); needed for the bounce.
        ``None``: ``points`` are the mesh's vertices.
    transfer_rays, table_directions : int
        Fibonacci direction counts of the transfer quadrature and the visibility table.
    albedo : float
        Grey albedo of the object for the interreflection bounces; 0 = no bounce.
    eps : float
        Ray start offset along the normal, metres.
    progress : callable ``(step, done, total)``, optional
        Called as the long steps advance: ``transfer`` and ``visibility`` (rays cast), ``bounce``
        (columns of the bounce matrix).
    floor_shadow : bool
        Darken the floor a downward ray meets by the object's shadow on it (:func:`floor_occlusion`);
        False gives the object's self-visibility alone (an object floating in the light).
    bounces : int
        Interreflections summed into ``bounce`` (>= 1): the light the object reflects onto itself
        once, twice, ... (:func:`interreflection`).
    with_bounce_matrix : bool
        Also the (V, V) ``bounce_matrix`` for the primary light (:func:`primary_bounce_matrix`; off
        for the render mesh's thousands of vertices, and above :data:`MAX_BOUNCE_MATRIX` vertices).
    with_floor_table : bool
        Also the primary light's ``floor_shadow`` table (:func:`floor_shadow_table`; with
        ``floor_shadow``; off for the render mesh, which gets the proxy's carried).

    Returns
    -------
    PrtResult
    """
    P = np.asarray(points, np.float64)
    N = np.asarray(normals, np.float64)
    N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    if P.shape != N.shape or P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points {P.shape} and normals {N.shape} must both be (V, 3)")
    if not 0.0 <= albedo < 1.0:
        raise ValueError(f"albedo must be in [0, 1), got {albedo}")
    if int(bounces) < 1:
        raise ValueError(f"bounces must be >= 1, got {bounces}")
    timings = {}

    def cast(step, vi, D):
        cb = (lambda done, total: progress(step, done, total)) if progress else None
        return first_hits(mesh, P[vi] + eps * N[vi], D, progress=cb)

    # transfer: closed form minus the blocked directions
    t0 = time.perf_counter()
    D = fibonacci_sphere(transfer_rays)
    vi, ki = _front_pairs(N, D)
    tri, loc = cast("transfer", vi, D[ki])
    blocked = tri >= 0
    dw = 4.0 * np.pi / transfer_rays
    Y = sh9(D)
    cos = np.einsum("px,px->p", N[vi], D[ki])
    b = np.flatnonzero(blocked)
    lost = np.zeros((len(P), transfer_rays))  # dw cos of every blocked (vertex, direction)
    lost[vi[b], ki[b]] = dw * cos[b]
    # the floor a downward ray meets is the object's own shadow near the object: its radiance there is
    # the floor's ambient radiance times the floor's unoccluded share (cosine-weighted sky visibility)
    free_down = np.flatnonzero(~blocked & (D[ki, 1] < -1e-6))
    floor_dirs = floor_table = None
    if floor_shadow and len(free_down):
        ao = floor_occlusion(mesh, eps=eps)
        p0, d = P[vi[free_down]], D[ki[free_down]]
        hit = p0 + (-np.maximum(p0[:, 1], 0.0) / d[:, 1])[:, None] * d
        lost[vi[free_down], ki[free_down]] += dw * cos[free_down] * (1.0 - ao(hit[:, [0, 2]]))
    T = unoccluded_transfer(N) - lost @ Y
    timings["transfer_s"] = time.perf_counter() - t0
    if floor_shadow and with_floor_table and len(free_down):
        t0 = time.perf_counter()
        floor_dirs = fibonacci_sphere(FLOOR_SHADOW_DIRECTIONS)
        floor_table = floor_shadow_table(
            mesh, len(P), vi[free_down], hit[:, [0, 2]], dw * cos[free_down], ao, floor_dirs, eps
        )
        timings["floor_shadow_s"] = time.perf_counter() - t0

    # the primary light's visibility table: the object and the vertex's own tangent plane block (the
    # floor is applied at run time: runtime/prt.py)
    t0 = time.perf_counter()
    K = fibonacci_sphere(table_directions)
    vj, kj = _front_pairs(N, K)
    tri_k, _ = cast("visibility", vj, K[kj])
    vis = np.zeros((len(P), table_directions), bool)
    vis[vj, kj] = tri_k < 0
    timings["visibility_s"] = time.perf_counter() - t0

    # the interreflection, from the blocked transfer rays' hit points
    op = None
    bounce = bounce_primary = bounce_matrix = None
    t0 = time.perf_counter()
    # one sparse (V, R) matrix: point i gathers dw cos / pi x barycentric weight of each hit's corners
    gather = gather_hits(mesh, vi[b], D[ki[b]], tri[b], loc[b], dw * cos[b] / np.pi, len(P))
    if gather.nnz:

        def op(t_points: np.ndarray) -> np.ndarray:
            """Transfer on the points -> the transfer of the light those points reflect onto them (albedo 1)."""
            return gather @ np.asarray(carry(t_points) if carry is not None else t_points, np.float64)

        if albedo > 0:
            term, acc = T, np.zeros_like(T)
            for k in range(bounces):
                term = albedo * op(term)
                acc += term
                if k == 0 and bounces > 1:
                    bounce_primary = term.astype(np.float32)
            bounce = acc.astype(np.float32)
            if with_bounce_matrix and len(P) <= MAX_BOUNCE_MATRIX:
                cb = (lambda done, total: progress("bounce", done, total)) if progress else None
                bounce_matrix = primary_bounce_matrix(op, len(P), albedo, bounces, progress=cb)
    elif albedo > 0:
        bounce = np.zeros_like(T, dtype=np.float32)
    timings["bounce_s"] = time.perf_counter() - t0
    return PrtResult(
        transfer=T.astype(np.float32),
        vis_directions=K.astype(np.float32),
        visibility=vis,
        bounce=bounce,
        albedo=float(albedo),
        timings_s=timings,
        bounce_operator=op,
        bounces=int(bounces),
        bounce_primary=bounce_primary,
        bounce_matrix=bounce_matrix,
        floor_dirs=floor_dirs,
        floor_shadow=floor_table,
    )


def floor_shadow_table(
    mesh,
    n_points: int,
    ray_point: np.ndarray,
    hit_xz: np.ndarray,
    ray_weight: np.ndarray,
    ao: Callable[[np.ndarray], np.ndarray],
    directions: np.ndarray,
    eps: float = DEFAULT_EPS,
    cells: int = 48,
) -> np.ndarray:
    """The primary light's shadow on the floor, as each point's downward rays see it: (V, F).

    The transfer gives the floor a downward ray meets the ambient's floor radiance times the floor's
    sky visibility ``ao`` (:func:`floor_occlusion`): right for the ambient light, but the primary
    light's share of the floor's light is shadowed by the object in the light's own direction (a
    long shadow on the far side, full light on the near side). Row i, column f:
    ``sum over point i's downward rays r of w_r (vis_f(x_r) - ao(x_r))``, with ``w_r = dw cos`` the
    ray's weight, ``x_r`` the floor point it meets and ``vis_f(x)`` whether direction f is open from
    x (0 below the horizon). At run time ``E_i += s L_floor floor_shadow_i(d)`` with s the primary
    light's share of the floor's irradiance and L_floor the floor's radiance (runtime/prt.py).
    Computed on a ``cells`` x ``cells`` floor grid over the footprint widened by
    :data:`FLOOR_SHADOW_REACH` object heights (bilinear), 0 beyond it.
    """
    v = np.asarray(mesh.vertices, np.float64)
    h = float(max(v[:, 1].max(), 1e-3))
    lo = v[:, [0, 2]].min(0) - FLOOR_SHADOW_REACH * h
    hi = v[:, [0, 2]].max(0) + FLOOR_SHADOW_REACH * h
    gx, gz = np.linspace(lo[0], hi[0], cells), np.linspace(lo[1], hi[1], cells)
    X, Z = np.meshgrid(gx, gz, indexing="ij")
    grid_xz = np.stack([X.ravel(), Z.ravel()], 1)
    up = np.flatnonzero(directions[:, 1] > 1e-6)
    pts = np.stack([grid_xz[:, 0], np.full(len(grid_xz), eps), grid_xz[:, 1]], 1)
    tri, _ = first_hits(mesh, np.repeat(pts, len(up), 0), np.tile(directions[up], (len(pts), 1)))
    vis = np.zeros((len(pts), len(directions)))
    vis[:, up] = (tri.reshape(len(pts), len(up)) < 0).astype(np.float64)
    # (the floor's own sky visibility at the grid, as the transfer used it)
    diff = vis - ao(grid_xz)[:, None]
    diff[:, directions[:, 1] <= 1e-6] = 0.0  # a light below the horizon does not light the floor
    # bilinear weights of each ray's floor point on the grid, summed per point: H (V, G)
    cell, wts, inside = _floor_bilinear(hit_xz, lo, hi, cells)
    H = np.zeros((n_points, cells * cells))
    w = np.where(inside, ray_weight, 0.0)
    for c in range(4):
        np.add.at(H, (ray_point, cell[:, c]), w * wts[:, c])
    return (H @ diff).astype(np.float32)


def _floor_bilinear(xz: np.ndarray, lo: np.ndarray, hi: np.ndarray, cells: int):
    """Bilinear lookup of floor points ``xz`` (N, 2) on a ``cells`` x ``cells`` grid spanning ``lo`` ..
    ``hi`` (row-major, x first): the 4 corner nodes (N, 4), their weights (N, 4) and whether each
    point lies on the grid (N,)."""
    xz = np.asarray(xz, np.float64)
    fx = (xz[:, 0] - lo[0]) / (hi[0] - lo[0]) * (cells - 1)
    fz = (xz[:, 1] - lo[1]) / (hi[1] - lo[1]) * (cells - 1)
    inside = (fx >= 0) & (fx <= cells - 1) & (fz >= 0) & (fz <= cells - 1)
    i0 = np.clip(np.floor(fx).astype(np.int64), 0, cells - 2)
    j0 = np.clip(np.floor(fz).astype(np.int64), 0, cells - 2)
    tx, tz = np.clip(fx - i0, 0, 1), np.clip(fz - j0, 0, 1)
    node = np.stack([i0 * cells + j0, (i0 + 1) * cells + j0, i0 * cells + j0 + 1, (i0 + 1) * cells + j0 + 1], 1)
    wts = np.stack([(1 - tx) * (1 - tz), tx * (1 - tz), (1 - tx) * tz, tx * tz], 1)
    return node, wts, inside


def primary_bounce_matrix(
    op: Callable[[np.ndarray], np.ndarray],
    n: int,
    albedo: float,
    bounces: int,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """(V, V) float32 ``M``: ``M @ e`` is the light the object reflects onto its points (every one of
    ``bounces`` interreflections, ``albedo`` included) when their direct irradiance is ``e`` (V,).

    The primary light is a lamp or a sun: its interreflection depends on where its direct light
    falls -- into a cavity or beside it -- which its SH2 lobe (~90 degrees wide) cannot say. With
    ``M`` the run time bounces the primary's own direct light, near or distant, shadows included
    (:mod:`illuminet.runtime.prt`). ``op`` is :func:`compute_prt`'s gather (albedo 1). ``progress``
    ``(done, total)`` is called after each block of columns: on a mesh of many render vertices this is
    the longest step of ``illuminet bundle`` (~20 s for a 36k-vertex scan on 2 cores)."""
    acc = np.zeros((n, n), np.float32)
    # columns are independent: a block at a time keeps op's (rays, columns) intermediate small (all
    # 1000 columns at once took ~0.9 GB for a 1000-vertex proxy)
    for c0 in range(0, n, BOUNCE_MATRIX_BLOCK):
        c1 = min(n, c0 + BOUNCE_MATRIX_BLOCK)
        term = np.zeros((n, c1 - c0))
        term[np.arange(c0, c1), np.arange(c1 - c0)] = 1.0
        for _ in range(bounces):
            term = albedo * op(term)
            acc[:, c0:c1] += term
        if progress is not None:
            progress(c1, n)
    return acc


def floor_occlusion(
    mesh, cells: int = 48, rays: int = 128, eps: float = DEFAULT_EPS
) -> Callable[[np.ndarray], np.ndarray]:
    """The floor's sky visibility around the object standing on it: ``ao(xz) -> (N,)`` in [0, 1].

    Cosine-weighted share of the upper hemisphere the object leaves open at floor points (y = 0),
    on a ``cells`` x ``cells`` grid over the object's footprint widened by its height on every side
    (beyond it the object's shadow on the floor is negligible: 1), bilinearly interpolated. Under
    the object's base it is 0: a vertex resting on the floor gets no light from below.
    """
    v = np.asarray(mesh.vertices, np.float64)
    h = float(max(v[:, 1].max(), 1e-3))
    lo, hi = v[:, [0, 2]].min(0) - h, v[:, [0, 2]].max(0) + h
    gx, gz = np.linspace(lo[0], hi[0], cells), np.linspace(lo[1], hi[1], cells)
    X, Z = np.meshgrid(gx, gz, indexing="ij")
    pts = np.stack([X.ravel(), np.full(X.size, eps), Z.ravel()], 1)
    D = fibonacci_sphere(2 * rays)
    D = D[D[:, 1] > 0]
    w = D[:, 1] / D[:, 1].sum()
    tri, _ = first_hits(mesh, np.repeat(pts, len(D), 0), np.tile(D, (len(pts), 1)))
    open_ = (tri.reshape(len(pts), len(D)) < 0).astype(np.float64) @ w

    def ao(xz: np.ndarray) -> np.ndarray:
        node, wts, inside = _floor_bilinear(xz, lo, hi, cells)
        g = open_[node] * wts
        return np.where(inside, g[:, 0] + g[:, 1] + g[:, 2] + g[:, 3], 1.0)

    return ao


def interreflection(result: PrtResult, albedo: float, bounces: int) -> np.ndarray:
    """Transfer (V, 9) with ``bounces`` interreflections at ``albedo`` (0: the direct transfer).

    ``bounces`` large (e.g. 50) gives the converged multi-bounce transfer of the same discretisation,
    the reference against which the single bounce is measured.
    """
    T = result.transfer.astype(np.float64)
    total, term = T.copy(), T
    if result.bounce_operator is None:
        return total
    for _ in range(bounces):
        term = albedo * result.bounce_operator(term)
        total += term
    return total


# --------------------------------------------------------------------------- bundles

#: how ``prior_shading`` of a PRT-only bundle is defined (recorded in its bundle.json)
PRIOR_UNIFORM = (
    "irradiance under a uniform environment (floor included) relative to an unoccluded upward "
    "plane's: 1 - ambient occlusion (+ bounce); no training"
)


def uniform_prior(result: PrtResult) -> np.ndarray:
    """``prior_shading`` (V, 3) of a PRT-only bundle: :data:`PRIOR_UNIFORM` (the constant baseline's shape)."""
    t = result.transfer[:, 0] + (result.bounce[:, 0] if result.bounce is not None else 0.0)
    # uniform radiance 1 has L00 = sqrt(4 pi); an unoccluded upward plane receives pi
    return np.repeat((t * np.sqrt(4.0 * np.pi) / np.pi)[:, None], 3, axis=1).astype(np.float32)


def _carry_fn(carry_index: np.ndarray, carry_weight: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    def carry(values: np.ndarray) -> np.ndarray:
        return (np.asarray(values)[carry_index] * carry_weight[..., None]).sum(1)

    return carry


def render_transfer_arrays(
    mesh, normals: np.ndarray, transfer_rays: int, albedo: float, progress=None, bounces: int = DEFAULT_BOUNCES
) -> tuple[dict[str, np.ndarray], float]:
    """``render_transfer`` (and ``render_bounce`` when ``albedo`` > 0) at every vertex of ``mesh``
    (:mod:`illuminet.runtime.prt`), and the seconds it took. The primary light's visibility stays on
    the proxy (it is carried at run time), so only a token visibility table is cast here."""
    t0 = time.perf_counter()

    def prog(step, done, total):
        if progress is not None:
            progress(f"render {step}", done, total)

    res = compute_prt(
        mesh,
        np.asarray(mesh.vertices, np.float64),
        normals,
        carry=None,
        transfer_rays=transfer_rays,
        table_directions=8,
        albedo=albedo,
        progress=prog,
        bounces=bounces,
        with_bounce_matrix=False,
        with_floor_table=False,
    )
    out = {"render_transfer": res.transfer.astype(np.float32)}
    if res.bounce is not None:
        out["render_bounce"] = res.bounce.astype(np.float32)
    if res.bounce_primary is not None:
        out["render_bounce_primary"] = res.bounce_primary.astype(np.float32)
    return out, time.perf_counter() - t0


def prt_meta(result: PrtResult, transfer_rays: int, table_directions: int, command: str, seed: int) -> dict:
    """The ``prt`` section of bundle.json: how the tables were made, and the conventions they follow."""
    from illuminet import __version__

    return {
        "file": "prt.npz",
        "command": command,
        "seed": int(seed),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "package_version": __version__,
        "vertices": "proxy",
        "transfer_rays": int(transfer_rays),
        "table_directions": int(table_directions),
        "eps_m": DEFAULT_EPS,
        "bounce_albedo": result.albedo,
        "bounces": result.bounces,
        "bounce_matrix": result.bounce_matrix is not None,
        "timings_s": {k: round(v, 3) for k, v in result.timings_s.items()},
        "convention": "E = transfer @ L_radiance (9 SH coefficients, no 1/pi; LightEstimate.radiance_sh9()), object "
        "frame +Y up; unoccluded: transfer = A_hat_l Y_lm(n)",
        "floor": "transfer: the floor does not occlude (its radiance is the ambient SH's lower hemisphere, "
        "darkened where the object shadows it: floor_occlusion); "
        "visibility table: object and facing only; the floor blocks the primary light below the "
        "horizon at run time (runtime/prt.py floor_factor)",
    }


def add_prt(
    bundle_dir,
    transfer_rays: int = DEFAULT_TRANSFER_RAYS,
    table_directions: int = DEFAULT_TABLE_DIRECTIONS,
    albedo: float = 0.8,
    command: str = "",
    seed: int = 0,
    progress=None,
    render: bool = False,
    bounces: int = DEFAULT_BOUNCES,
) -> tuple[Path, PrtResult]:
    """Compute PRT tables for an existing bundle's proxy vertices and add them (``prt.npz``).

    The bundle's other files (mesh, ONNX models, evaluation) are kept as they are; ``bundle.json``
    gets a ``prt`` section and the new file's checksum. ``render``: also the transfer of every render
    vertex (:func:`render_transfer_arrays`). Returns (bundle.json path, result).
    """
    import trimesh

    from illuminet.models.export import finalize_bundle
    from illuminet.runtime.assets.bundle import load_bundle
    from illuminet.runtime.prt import PRT_FILE

    b = load_bundle(bundle_dir)
    mesh = trimesh.Trimesh(np.asarray(b.vertices, np.float64), np.asarray(b.faces), process=False)
    res = compute_prt(
        mesh,
        b.proxy_vertices,
        b.proxy_normals,
        carry=b.carry,
        transfer_rays=transfer_rays,
        table_directions=table_directions,
        albedo=albedo,
        progress=progress,
        bounces=bounces,
    )
    extra = _with_render(res, mesh, b.normals, render, transfer_rays, albedo, progress)
    np.savez_compressed(b.path / PRT_FILE, **res.arrays(), **extra)
    meta = dict(b.meta)
    meta["prt"] = prt_meta(res, transfer_rays, table_directions, command, seed)
    if extra:
        meta["prt"]["render_transfer"] = {"vertices": len(b.vertices), "transfer_rays": int(transfer_rays)}
    return finalize_bundle(b.path, meta), res


def _with_render(res: PrtResult, mesh, normals, render: bool, transfer_rays: int, albedo: float, progress) -> dict:
    """The render-mesh arrays when asked for (their time joins ``res.timings_s``), else {}."""
    if not render:
        return {}
    extra, secs = render_transfer_arrays(mesh, normals, transfer_rays, albedo, progress, res.bounces)
    res.timings_s["render_transfer_s"] = secs
    return extra


def new_bundle(
    spec: str,
    out,
    height: float | None = None,
    n_proxy: int = 1000,
    seed: int = 0,
    transfer_rays: int = DEFAULT_TRANSFER_RAYS,
    table_directions: int = DEFAULT_TABLE_DIRECTIONS,
    albedo: float = 0.8,
    command: str = "",
    progress=None,
    up: str = "y",
    render: bool = False,
    bounces: int = DEFAULT_BOUNCES,
) -> tuple[Path, PrtResult]:
    """A PRT-only bundle (``mesh.npz`` + ``prt.npz`` + ``bundle.json``, no ONNX) of any mesh.

    Parameters
    ----------
    spec : ``builtin:NAME`` or a mesh file (:func:`illuminet.runtime.assets.objects.load_object`)
    out : the bundle folder to write
    height : scale the object to this height in metres (files default to 0.25 m; built-ins keep
        their designed size unless given)
    n_proxy, seed : lighting proxy size and the seed of its farthest-point selection
    transfer_rays, table_directions, albedo, bounces : see :func:`compute_prt`
    up : the file's up axis, ``"y"`` or ``"z"``
    render : also the transfer of every render vertex (:func:`render_transfer_arrays`: finer
        self-occlusion, ~40 s more for the vase's 9026 vertices on 2 cores)

    Raises
    ------
    illuminet.runtime.assets.objects.ObjectLoadError
        Naming the file when it is missing, unreadable or holds no triangles.
    """
    import trimesh

    from illuminet import __version__
    from illuminet.models.datagen import build_geometry
    from illuminet.models.export import finalize_bundle, write_mesh
    from illuminet.runtime.assets.bundle import BUNDLE_FORMAT
    from illuminet.runtime.assets.objects import DEFAULT_HEIGHT, load_object, normalise
    from illuminet.runtime.prt import PRT_FILE

    t0 = time.perf_counter()
    builtin = spec.startswith("builtin:")
    mesh = load_object(spec, height=None if builtin else (height or DEFAULT_HEIGHT), up=up)
    if builtin and height:
        normalise(mesh, height)
    name = spec.split(":", 1)[1] if builtin else Path(spec).stem
    g = build_geometry(mesh, n_proxy=n_proxy, seed=seed, name=name)
    t_geom = time.perf_counter() - t0
    occluder = trimesh.Trimesh(np.asarray(g.vertices, np.float64), g.faces, process=False)
    res = compute_prt(
        occluder,
        g.proxy_vertices,
        g.proxy_normals,
        carry=_carry_fn(g.carry_index, g.carry_weight),
        transfer_rays=transfer_rays,
        table_directions=table_directions,
        albedo=albedo,
        progress=progress,
        bounces=bounces,
    )
    res.timings_s = {"mesh_and_proxy_s": t_geom, **res.timings_s}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    extra = _with_render(res, occluder, g.normals, render, transfer_rays, albedo, progress)
    write_mesh(out, g, uniform_prior(res))
    np.savez_compressed(out / PRT_FILE, **res.arrays(), **extra)
    meta = {
        "format": BUNDLE_FORMAT,
        "name": name,
        "object": spec if builtin else str(Path(spec).resolve()),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "package_version": __version__,
        "vertices": {"render": len(g.vertices), "faces": len(g.faces), "proxy": len(g.proxy_index)},
        "height_m": float(np.ptp(g.vertices[:, 1])),
        "up": up,
        "proxy": {"seed": int(seed), "method": "farthest points in position + normal space (datagen.build_geometry)"},
        "prior_shading": PRIOR_UNIFORM,
        "prt": prt_meta(res, transfer_rays, table_directions, command, seed),
    }
    if extra:
        meta["prt"]["render_transfer"] = {"vertices": len(g.vertices), "transfer_rays": int(transfer_rays)}
    return finalize_bundle(out, meta), res
