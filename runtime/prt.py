"""Precomputed radiance transfer (PRT) at run time: the layout of a bundle's PRT tables and shading
the lighting proxy's vertices with them under a :class:`~illuminet.runtime.scene.LightEstimate`.

The tables are computed once per mesh, offline (:mod:`illuminet.models.prt`, ``illuminet bundle``);
this module only reads and evaluates them, in well under a millisecond per frame. Per proxy vertex i:

* ``transfer`` T_i (9,): ``T_i(lm) = integral over directions w of max(0, n_i . w) V_i(w) Y_lm(w) dw``
  with V_i the object's **self**-visibility (Sloan, Kautz & Snyder 2002, without their 1/pi), so that
  ``E_i = T_i . L`` with L the ambient *radiance* coefficients (``LightEstimate.radiance_sh9()``).
  For a vertex the object does not occlude, ``T_i(lm) = A_hat_l Y_lm(n_i)`` and ``E_i = sh9(n_i) @
  sh9_irradiance`` (:mod:`illuminet.runtime.sh`). The floor is **not** an occluder in T: rays that
  leave the object downwards meet the floor, whose radiance is the lower hemisphere of the estimate's
  ambient SH (the floor bounce), so that hemisphere is kept.
* ``visibility`` V_i(w_k) of the primary light over K table directions w_k (a Fibonacci sphere): 1
  where a ray from the vertex leaves the object and the vertex faces it (``n_i . w_k > 0``), else 0.
  A light between table directions is interpolated with a smooth compact kernel over its ~7 nearest
  directions (:data:`KERNEL_RADIUS` spacings), so a moving light does not make shadows pop. Stored
  bit-packed (``vis_bits`` (K, ceil(V/8)) uint8, little bit order along the vertices). For direct
  light the floor does block the lower hemisphere: :func:`floor_factor` multiplies it in at run time,
  sharp at the horizon (in the table it would be blurred over the kernel, dimming a low sun).
* ``bounce`` B_i (9,), optional: the object's light onto itself for its albedo (every bounce the
  bundle summed, ``bundle.json`` ``prt.bounces``), ``E_i += B_i . L``; ``bounce_primary`` B1_i, optional:
  the first bounce alone, for the primary light, ``E_i += B1_i . (primary as SH)`` (without it B_i
  serves the primary too: bundles with one bounce). The primary light's SH2 lobe is ~90 degrees wide
  and would light a cavity it cannot see into; more bounces would multiply that.
* ``bounce_matrix`` M (V, V) float16, optional (bundles since 2026-11-29): every bounce onto vertex i
  of a unit direct irradiance at vertex j, the object's albedo included. When present it replaces
  ``bounce_primary``: the primary light's interreflection is ``M @ g`` with g its direct light on the
  proxy (cosine, distance, visibility: below), so a lamp shining into the vase's mouth lights its
  inside and one beside it does not, which the SH2 lobe could not tell apart. The render mesh gets
  the proxy's values carried (an interreflection is smooth).
* ``floor_dirs`` (F, 3) and ``floor_shadow`` (V, F) float16, optional (bundles since the tenth wave):
  the transfer gives the floor a downward ray meets the ambient's floor radiance times the floor's
  sky visibility, right for the ambient but not for the primary light, whose share of the floor's
  light the object shadows in the light's own direction (a long shadow behind a low lamp, full light
  in front). ``floor_shadow_i(w_f)`` sums, over vertex i's downward rays, ``dw cos`` times (whether
  direction f is open from the floor point the ray meets minus that point's sky visibility); at run
  time ``E_i += floor_shadow_i(d) s L_floor`` with s the primary's share of the floor's irradiance and
  L_floor the ambient's radiance straight down (:func:`_floor_shadow_colour`). The render mesh gets the
  proxy's values carried.
* ``render_transfer``, ``render_bounce``, ``render_bounce_primary`` (R, 9), optional (``illuminet bundle
  --render-transfer``): the same integrals at every vertex of the render mesh. The object's
  self-occlusion varies faster than the lighting proxy's few hundred vertices sample it (the vase's
  grooves and lip); carried from the proxy, the ambient shading is blurred across them (camera eval,
  vase, 11 scenes a suite: MAE 0.051 -> 0.048 indoor, 0.092 -> 0.085 lamp). With them,
  :func:`prt_irradiance_render` shades every render vertex: ambient and bounce from its own transfer
  vectors, the primary light with its own cosine and distance and the proxy's visibility carried (a
  shadow is smooth; keeping the (K, R) visibility table would take ~37 MB and ~6 ms a frame for a near
  light).

Primary light: ``E_i += rgb * max(0, n_i . d) * V_i(d)``; for a near light (``primary_pos`` known)
d is the direction from each vertex to the light and ``rgb`` falls off as ``(|pos| / |pos - x_i|)^2``
(``primary_rgb`` is the irradiance at the anchor, the frame's origin). Visibility to a near light is
visibility to infinity in its direction, exact for lights outside the object's convex hull.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from illuminet.runtime.sh import SH_A_HAT, sh9

#: file name of the PRT tables in a bundle
PRT_FILE = "prt.npz"
#: arrays of ``prt.npz`` (``bounce`` is optional)
PRT_KEYS = ("transfer", "vis_directions", "vis_bits")
#: the arrays of ``prt.npz`` that hold real numbers (all but the packed ``vis_bits``)
PRT_FLOAT_KEYS = (
    "transfer",
    "vis_directions",
    "bounce",
    "bounce_primary",
    "bounce_matrix",
    "floor_dirs",
    "floor_shadow",
    "render_transfer",
    "render_bounce",
    "render_bounce_primary",
)
#: interpolation kernel radius, in units of the mean table spacing sqrt(4 pi / K)
KERNEL_RADIUS = 1.5


#: the floor's shadow of the primary light ramps from 0 to 1 over this height of the light's direction
#: above the horizon (~1 degree): sharp, but without a jump when a light crosses it
FLOOR_RAMP = 0.02


def floor_factor(dy: np.ndarray | float) -> np.ndarray:
    """How much of a light in a direction with y component ``dy`` the floor (y = 0) lets through."""
    return np.clip(np.asarray(dy, np.float64) / FLOOR_RAMP, 0.0, 1.0)


def pack_visibility(vis: np.ndarray) -> np.ndarray:
    """(V, K) bool visibility -> ``vis_bits`` (K, ceil(V/8)) uint8 (rows per direction, little bit order)."""
    return np.packbits(np.asarray(vis, bool).T, axis=1, bitorder="little")


def unpack_visibility(bits: np.ndarray, n_vertices: int) -> np.ndarray:
    """``vis_bits`` -> (K, V) float32 of 0/1 (the layout :class:`PrtTables` evaluates)."""
    return np.unpackbits(np.asarray(bits, np.uint8), axis=1, count=n_vertices, bitorder="little").astype(np.float32)


def _kernel_chord2(n_directions: int) -> float:
    """Squared chord length of the kernel radius (:data:`KERNEL_RADIUS` spacings of a table of
    ``n_directions``)."""
    r = KERNEL_RADIUS * np.sqrt(4.0 * np.pi / n_directions)
    return float((2.0 * np.sin(min(r, np.pi) / 2.0)) ** 2)


def _kernel_weights(cos: np.ndarray, r2: float) -> np.ndarray:
    """Kernel weights from cosines to table directions (``cos`` overwritten): (1 - chord^2 / R^2)^2
    inside the radius R (``r2`` = R^2), else 0; chord^2 = 2 - 2 cos, so the base is linear in cos (in
    place: per frame)."""
    w = np.multiply(cos, 2.0 / r2, out=cos)
    w += 1.0 - 2.0 / r2
    np.maximum(w, 0.0, out=w)
    w *= w
    return w


@dataclass(frozen=True)
class PrtTables:
    """A bundle's PRT tables for its V proxy vertices (see the module docstring).

    Attributes
    ----------
    transfer : (V, 9) float64
    directions : (K, 3) float64 unit table directions
    visibility : (K, V) float32 0/1 (unpacked ``vis_bits``)
    bounce : (V, 9) float64 or None
    bounce_primary : (V, 9) float64 or None (then ``bounce`` serves the primary light too)
    bounce_matrix : (V, V) float32 or None (when present, the primary light's interreflection instead
        of ``bounce_primary``)

    (float64 once at load: the per-frame products then convert nothing.)
    """

    transfer: np.ndarray
    directions: np.ndarray
    visibility: np.ndarray
    bounce: np.ndarray | None = None
    render_transfer: np.ndarray | None = None  # (R, 9) float32, optional
    render_bounce: np.ndarray | None = None  # (R, 9) float32, optional
    bounce_primary: np.ndarray | None = None  # (V, 9) float64, optional
    render_bounce_primary: np.ndarray | None = None  # (R, 9) float32, optional
    bounce_matrix: np.ndarray | None = None  # (V, V) float32, optional
    floor_dirs: np.ndarray | None = None  # (F, 3) float64 unit, optional
    floor_shadow: np.ndarray | None = None  # (F, V) float32, optional (stored (V, F))

    @property
    def n_vertices(self) -> int:
        return int(self.transfer.shape[0])

    @property
    def _chord2(self) -> float:
        """Squared chord length of the kernel radius."""
        return _kernel_chord2(len(self.directions))

    @classmethod
    def from_arrays(cls, arrays, n_vertices: int, n_render: int | None = None) -> PrtTables:
        """Check ``prt.npz``'s arrays against the proxy vertex count (and the render mesh's ``n_render``
        vertices, for the optional render-mesh arrays) and unpack them.

        Raises
        ------
        ValueError
            Naming the missing array or the shape that disagrees.
        """
        missing = [k for k in PRT_KEYS if k not in arrays]
        if missing:
            raise ValueError(f"missing arrays {', '.join(missing)}")
        for key in PRT_FLOAT_KEYS:
            # every table but the visibility bits is real numbers: a bool bounce matrix shaded 50x too bright
            # and text parsed as numbers, both without a word
            if key in arrays and np.asarray(arrays[key]).dtype.kind != "f":
                raise ValueError(f"{key} holds {np.asarray(arrays[key]).dtype}; expected floating-point numbers")
        V = n_vertices
        t = np.asarray(arrays["transfer"], np.float32)
        d = np.asarray(arrays["vis_directions"], np.float32)
        bits = np.asarray(arrays["vis_bits"])
        if t.shape != (V, 9):
            raise ValueError(f"transfer must be ({V}, 9) for the {V} proxy vertices, got {t.shape}")
        if d.ndim != 2 or d.shape[1] != 3 or len(d) < 8:
            raise ValueError(f"vis_directions must be (K >= 8, 3), got {d.shape}")
        if not np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-4):
            raise ValueError("vis_directions must be unit vectors")
        if bits.dtype != np.uint8 or bits.shape != (len(d), (V + 7) // 8):
            raise ValueError(f"vis_bits must be uint8 ({len(d)}, {(V + 7) // 8}), got {bits.dtype} {bits.shape}")
        bounce = None
        if "bounce" in arrays:
            bounce = np.asarray(arrays["bounce"], np.float32)
            if bounce.shape != (V, 9):
                raise ValueError(f"bounce must be ({V}, 9), got {bounce.shape}")
        bounce_primary = None
        if "bounce_primary" in arrays:
            bounce_primary = np.asarray(arrays["bounce_primary"], np.float32)
            if bounce is None or bounce_primary.shape != (V, 9):
                raise ValueError(f"bounce_primary must be ({V}, 9) and come with bounce, got {bounce_primary.shape}")
        bounce_matrix = None
        if "bounce_matrix" in arrays:
            bounce_matrix = np.asarray(arrays["bounce_matrix"], np.float32)
            if bounce is None or bounce_matrix.shape != (V, V):
                raise ValueError(f"bounce_matrix must be ({V}, {V}) and come with bounce, got {bounce_matrix.shape}")
        floor_dirs = floor_shadow = None
        if ("floor_dirs" in arrays) != ("floor_shadow" in arrays):
            raise ValueError("floor_dirs and floor_shadow come together (the primary light's floor-shadow table)")
        if "floor_shadow" in arrays:
            floor_dirs = np.asarray(arrays["floor_dirs"], np.float32)
            floor_shadow = np.asarray(arrays["floor_shadow"], np.float32)
            if floor_dirs.ndim != 2 or floor_dirs.shape[1] != 3 or len(floor_dirs) < 8:
                raise ValueError(f"floor_dirs must be (F >= 8, 3), got {floor_dirs.shape}")
            if not np.allclose(np.linalg.norm(floor_dirs, axis=1), 1.0, atol=1e-4):
                raise ValueError("floor_dirs must be unit vectors")
            if floor_shadow.shape != (V, len(floor_dirs)):
                raise ValueError(f"floor_shadow must be ({V}, {len(floor_dirs)}), got {floor_shadow.shape}")
        if not all(a is None or np.isfinite(a).all() for a in (t, bounce, bounce_primary, bounce_matrix, floor_shadow)):
            raise ValueError("transfer/bounce/floor_shadow hold non-finite values")
        render = {}
        for key in ("render_transfer", "render_bounce", "render_bounce_primary"):
            if key not in arrays:
                continue
            a = np.asarray(arrays[key], np.float32)
            if n_render is None or a.shape != (n_render, 9):
                raise ValueError(f"{key} must be ({n_render}, 9) for the render mesh's vertices, got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"{key} holds non-finite values")
            render[key] = a  # float32: evaluated in float32 (runtime cost, R x 9)
        if ("render_bounce" in render) != (bounce is not None and "render_transfer" in render):
            raise ValueError("render_bounce must come with render_transfer and bounce (and only then)")
        if ("render_bounce_primary" in render) != (bounce_primary is not None and "render_transfer" in render):
            raise ValueError("render_bounce_primary must come with render_transfer and bounce_primary (and only then)")
        return cls(
            transfer=t.astype(np.float64),
            directions=d.astype(np.float64) / np.linalg.norm(d, axis=1, keepdims=True),
            visibility=unpack_visibility(bits, V),
            bounce=None if bounce is None else bounce.astype(np.float64),
            bounce_primary=None if bounce_primary is None else bounce_primary.astype(np.float64),
            bounce_matrix=bounce_matrix,
            floor_dirs=None
            if floor_dirs is None
            else floor_dirs.astype(np.float64) / np.linalg.norm(floor_dirs, axis=1, keepdims=True),
            floor_shadow=None if floor_shadow is None else np.ascontiguousarray(floor_shadow.T),
            **render,
        )

    def _weights(self, cos: np.ndarray) -> np.ndarray:
        """Kernel weights from cosines to table directions (overwritten): :func:`_kernel_weights`."""
        return _kernel_weights(cos, self._chord2)

    def primary_visibility(self, direction: np.ndarray) -> np.ndarray:
        """Visibility (V,) in [0, 1] of a distant light in ``direction`` (unit, object frame), floor included."""
        d = np.asarray(direction, np.float64).reshape(3)
        f = float(floor_factor(d[1]))
        if f <= 0.0:
            return np.zeros(self.n_vertices)
        w = self._weights(self.directions @ d)
        sel = np.flatnonzero(w)
        w = w[sel]
        return (w @ self.visibility[sel]) * (f / w.sum())

    def floor_shadow_at(self, direction: np.ndarray) -> np.ndarray:
        """The floor-shadow table (V,) for a light in ``direction`` (unit, object frame), interpolated
        over ``floor_dirs`` with the same kernel as the visibility (in units of its own spacing)."""
        d = np.asarray(direction, np.float64).reshape(3)
        w = _kernel_weights(self.floor_dirs @ d, _kernel_chord2(len(self.floor_dirs)))
        sel = np.flatnonzero(w)
        return (w[sel] @ self.floor_shadow[sel]) / max(float(w[sel].sum()), 1e-12)

    def primary_visibility_per_vertex(self, directions: np.ndarray) -> np.ndarray:
        """Visibility (V,) of a light seen from each vertex in its own direction ``directions`` (V, 3),
        floor included."""
        d = np.asarray(directions, np.float64)
        centre = d.sum(0)
        n = np.linalg.norm(centre)
        centre = centre / n if n > 1e-9 else d[0]
        spread = np.arccos(np.clip((d @ centre).min(), -1.0, 1.0))
        reach = KERNEL_RADIUS * np.sqrt(4.0 * np.pi / len(self.directions)) + spread
        cand = np.flatnonzero(self.directions @ centre >= np.cos(min(reach, np.pi)) - 1e-6)
        cos = d @ self.directions[cand].T  # (V, C); the kernel reaches ~7 of the C candidates per vertex
        # only the kernel's non-zero weights (w > 0 where chord^2 < R^2, i.e. cos > 1 - R^2 / 2): a near
        # light spreads the vertices' directions over ~100 candidates (0.25 -> 0.1 ms for the vase's proxy)
        idx = np.flatnonzero(cos > 1.0 - self._chord2 / 2.0)
        row, col = np.divmod(idx, cos.shape[1])
        wv = self._weights(cos.ravel()[idx])
        n = len(d)
        vis = np.bincount(row, weights=wv * self.visibility[cand[col], row], minlength=n)
        return vis * floor_factor(d[:, 1]) / np.maximum(np.bincount(row, weights=wv, minlength=n), 1e-12)


def primary_radiance_sh9(direction: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Radiance SH (9, 3) of a distant light of irradiance ``rgb`` (at normal incidence) from ``direction``."""
    d = np.asarray(direction, np.float64).reshape(1, 3)
    return sh9(d)[0][:, None] * np.asarray(rgb, np.float64)[None, :]


@dataclass(frozen=True)
class PrtGeometry:
    """What the per-frame shading needs of some vertices' positions, computed once for a mesh that does
    not change (:func:`prt_geometry`): the near light's distances and cosines are then two
    matrix-vector products a frame, ``|p - x|^2 = |x|^2 - 2 x.p + |p|^2`` and ``n.(p - x) = n.p - n.x``,
    instead of an (R, 3) direction array."""

    points: np.ndarray  # (N, 3) float64
    normals: np.ndarray  # (N, 3) float64
    xx: np.ndarray  # (N,) |x|^2
    nx: np.ndarray  # (N,) n . x


def prt_geometry(points: np.ndarray, normals: np.ndarray) -> PrtGeometry:
    """:class:`PrtGeometry` of vertices (object frame, metres at the drawn scale) and their unit normals."""
    x = np.array(points, np.float64).reshape(-1, 3)
    n = np.array(normals, np.float64).reshape(-1, 3)
    if n.shape != x.shape:
        raise ValueError(f"points {x.shape} and normals {n.shape} must have the same shape")
    return PrtGeometry(x, n, np.einsum("vx,vx->v", x, x), np.einsum("vx,vx->v", n, x))


def _directions_to(pos: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unit directions (N, 3) from each point to ``pos``."""
    v = pos[None, :] - points
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-4)


def _shade(
    transfer,
    bounce,
    geom: PrtGeometry,
    estimate,
    vis_distant,
    vis_near,
    dtype,
    bounce_primary=None,
    bounce_of=None,
    floor_of=None,
) -> np.ndarray:
    """Shading of some vertices (the proxy's or the render mesh's) from their transfer and bounce
    arrays; ``vis_distant(d)`` / ``vis_near(pos)`` give those vertices' visibility of a distant light in
    direction d / of a light at pos (module docstring); ``bounce_primary`` (else ``bounce``) carries the
    primary light's interreflection, unless ``bounce_of(g)`` gives it from the primary's direct light g
    on these vertices (the tables' ``bounce_matrix``); ``floor_of(d)`` gives these vertices' floor-shadow
    values for a primary light in direction d (the tables' ``floor_shadow``). Evaluated in ``dtype``;
    returns float32 clamped at 0.

    ``E = (T + B) . L + B1 . Lp + g rgb`` (Lp: the primary light as SH): ``T . L + B . (L + Lp)`` when
    the tables have no ``bounce_primary`` (B1 = B), the transfer alone without a bounce."""
    L = estimate.radiance_sh9().astype(dtype)
    E = transfer @ L
    if bounce is not None:
        E += bounce @ L
    d = estimate.primary_dir
    rgb = np.asarray(estimate.primary_rgb, np.float64).reshape(3)
    if d is not None and np.any(rgb > 0):
        d = np.asarray(d, np.float64).reshape(3)
        d = d / max(np.linalg.norm(d), 1e-12)
        pos = estimate.primary_pos
        if pos is not None and float(np.dot(pos, pos)) < 1e-6:
            pos = None  # a "near" light at the anchor itself says nothing about falloff: treat it as distant
        if pos is None:
            g = np.maximum(geom.normals @ d, 0.0) * vis_distant(d)
        else:
            pos = np.asarray(pos, np.float64).reshape(3)
            pp = float(pos @ pos)
            r2 = geom.xx - 2.0 * (geom.points @ pos)
            r2 += pp
            np.maximum(r2, 1e-8, out=r2)
            g = geom.normals @ pos
            g -= geom.nx
            np.maximum(g, 0.0, out=g)  # n . (pos - x), then / |pos - x| is the cosine
            g *= pp
            g /= r2 * np.sqrt(r2)  # cosine x (|pos| / |pos - x|)^2
            g *= vis_near(pos)
        if bounce_of is not None:
            g = g + bounce_of(g)
        # per-vertex scalars times a colour each, added by one (N, k) @ (k, 3) product: numpy's
        # broadcast (N, 1) * (3,) runs a 3-long inner loop (0.08 ms a term for 9026 vertices, 0.03 ms
        # for the product of both)
        scalars, colours = [g], [rgb]
        if bounce is not None and bounce_of is None:
            E += (bounce_primary if bounce_primary is not None else bounce) @ primary_radiance_sh9(d, rgb).astype(dtype)
        if floor_of is not None:
            to_light = d if pos is None else pos / np.linalg.norm(pos)
            colour = _floor_shadow_colour(estimate, L, to_light, rgb)
            if colour is not None:
                scalars.append(floor_of(to_light))
                colours.append(colour)
        S = np.empty((len(E), len(scalars)), dtype)
        for i, v in enumerate(scalars):
            S[:, i] = v
        E += S @ np.array(colours, dtype)
    np.maximum(E, 0.0, out=E)
    return E.astype(np.float32, copy=False)


_UP = sh9(np.array([[0.0, 1.0, 0.0]]))[0]
_DOWN = sh9(np.array([[0.0, -1.0, 0.0]]))[0]


def _floor_shadow_colour(estimate, L_rad, to_light: np.ndarray, rgb: np.ndarray) -> np.ndarray | None:
    """The colour the floor-shadow table is weighted by (3,): the primary light's share of the floor
    bounce moved by the object's shadow on the floor is ``floor_shadow(d) x s x L_floor``, with s the
    primary's share of the floor's irradiance (per channel, at the anchor; for a near light its
    direction from the anchor) and L_floor the ambient's radiance straight down (the floor, as the
    transfer sees it). None for a light below the horizon."""
    up = float(to_light[1])
    if up <= 0.0:
        return None
    p = rgb * up  # the primary light's irradiance on the floor at the anchor
    a = np.maximum(_UP @ np.asarray(estimate.sh9, np.float64), 0.0)  # the ambient's, from above
    share = p / np.maximum(p + a, 1e-12)
    l_floor = np.maximum(_DOWN @ np.asarray(L_rad, np.float64), 0.0)
    return share * l_floor


def prt_irradiance(
    tables: PrtTables, points: np.ndarray, normals: np.ndarray, estimate, geometry: PrtGeometry | None = None
) -> np.ndarray:
    """Irradiance (V, 3) of the proxy vertices under a :class:`~illuminet.runtime.scene.LightEstimate`.

    Parameters
    ----------
    tables : PrtTables
    points, normals : (V, 3)
        The proxy vertices (object frame, metres, at the scale the object is drawn) and unit normals.
    estimate : LightEstimate
    geometry : the :func:`prt_geometry` of ``points, normals``, made once by a caller that shades the
        same vertices every frame (else computed here)

    Returns
    -------
    (V, 3) float32, clamped at 0: ambient through the transfer vectors, the primary light with its
    table visibility, and the bounce when the tables have one.
    """
    geom = prt_geometry(points, normals) if geometry is None else geometry
    return _shade(
        tables.transfer,
        tables.bounce,
        geom,
        estimate,
        tables.primary_visibility,
        lambda pos: tables.primary_visibility_per_vertex(_directions_to(pos, geom.points)),
        np.float64,
        tables.bounce_primary,
        None if tables.bounce_matrix is None else (lambda g: tables.bounce_matrix @ g.astype(np.float32)),
        None if tables.floor_shadow is None else tables.floor_shadow_at,
    )


def prt_irradiance_render(
    tables: PrtTables,
    points: np.ndarray,
    normals: np.ndarray,
    proxy_index: np.ndarray,
    carry,
    estimate,
    geometry: PrtGeometry | None = None,
) -> np.ndarray:
    """Irradiance (R, 3) of every render vertex, from the tables' render-mesh arrays (module docstring).

    Parameters
    ----------
    tables : PrtTables with ``render_transfer`` (else ValueError)
    points, normals : (R, 3) the render mesh's vertices (object frame, metres, drawn scale) and normals
    proxy_index : (V,) the proxy's vertices among them; carry : proxy values (V, k) -> render values (R, k)
    estimate : LightEstimate
    geometry : the :func:`prt_geometry` of ``points, normals``, made once by a caller that shades the
        same mesh every frame (else computed here)

    Returns
    -------
    (R, 3) float32, clamped at 0. At a proxy vertex it is :func:`prt_irradiance` up to the ray noise of
    the two tables; the primary light's visibility is the proxy's, carried.
    """
    if tables.render_transfer is None:
        raise ValueError("these PRT tables have no render-mesh transfer (illuminet bundle --render-transfer)")
    proxy_index = np.asarray(proxy_index)
    geom = prt_geometry(points, normals) if geometry is None else geometry

    def carried(vis: np.ndarray) -> np.ndarray:
        return np.asarray(carry(vis.astype(np.float32)[:, None]), np.float32)[:, 0]

    return _shade(
        tables.render_transfer,
        tables.render_bounce,
        geom,
        estimate,
        lambda d: carried(tables.primary_visibility(d)),
        lambda pos: carried(tables.primary_visibility_per_vertex(_directions_to(pos, geom.points[proxy_index]))),
        np.float32,
        tables.render_bounce_primary,
        None
        if tables.bounce_matrix is None
        else (lambda g: carried(tables.bounce_matrix @ g[proxy_index].astype(np.float32))),
        None if tables.floor_shadow is None else (lambda d: carried(tables.floor_shadow_at(d))),
    )


def unoccluded_transfer(normals: np.ndarray) -> np.ndarray:
    """Transfer (V, 9) of vertices nothing occludes: ``A_hat_l Y_lm(n)`` (then ``E = sh9(n) @ E_irr``)."""
    return sh9(np.asarray(normals, np.float64)) * SH_A_HAT[None, :]
