"""The primary light's direction from the real shadows the camera sees: a cue of the light estimate.

A floor lit by a distant sun is uniformly bright, so its irradiance says nothing about the sun's
azimuth; the shadows that real objects (boxes, chairs, people) cast onto it do. Here the casters'
geometry is known from depth, so every candidate direction predicts a shadow mask on the floor,
and the candidate whose mask best matches the observed darkness wins (the idea of Sato, Sato &
Ikeuchi 1999, "Illumination from shadows", with known geometry instead of a known shape;
Panagopoulos et al. 2009-2011 and Arief et al. 2012 estimate it without depth). DESIGN.md §6 "Real
shadows" has the feasibility experiment this follows.

What this module owns
    * :func:`shadow_direction`: one frame -> :class:`ShadowCue` (or ``None``). Pure numpy + OpenCV;
      no ground truth, no state.
    * :class:`ShadowTracker`: the schedule: a full search about once a second, a cheap local refine
      around the last answer on the frames between (the sun is fixed in the world and the anchor
      is world-locked, so the last answer in the object frame stays right while the camera moves).

Method
    1. **Receiver and casters.** The receiver is the anchor's plane (the floor under the object).
       Depth pixels (every ``stride``-th) within the stereo noise of it are *receiver* samples;
       pixels higher above it than ``min_caster_m`` (and twice that noise) are *casters*. Each
       caster is extended straight down to the receiver (its footprint): depth sees only the front
       of an object, and something standing on the floor is solid down to it. Only the tallest
       caster per footprint cell matters then, so the casters reduce to a height map on a coarse
       grid of the receiver (``cell_m``, 3 cm), in plane coordinates.
    2. **Observed darkness** per receiver cell: ``1 - L / L_ref`` clipped to [0, 1], with ``L`` the
       cell's mean luminance and ``L_ref`` the lit floor's brightness: a quadratic surface fitted
       to log luminance with the darker cells (shadows) left out, shifted up to an upper percentile
       of the lit cells, so that smooth lighting gradients (a lamp's falloff, vignetting) and slow
       albedo changes matter less.
       Footprint cells are left out (the floor under an object is not seen).
    3. **Predicted shadow** of a candidate (azimuth phi, zenith angle theta): every caster column
       of height h casts a segment from its footprint, ``h tan(theta)`` long, away from the light.
       For one azimuth the grid is rotated so that the shadows run along its rows; then a receiver
       cell is in shadow when the running maximum of the casters' reach to its left reaches it
       (``np.maximum.accumulate``): one pass gives the masks of all zenith angles of an azimuth.
    4. **Score**: the Pearson correlation of the predicted mask with the observed darkness over the
       observed floor (the mask must explain the shadows), times the contrast between the mask and
       a 30 cm band around it (its edges must be shadow edges: a mask that lands inside a large
       unexplained shadow, such as a building's, has a dark band too). Full search: a 10 deg grid
       over the upper hemisphere (36 azimuths x 9 zenith angles), the best three peaks refined at
       2 deg, then 0.5 deg. Local refine (``prior``): about four azimuth passes around the prior,
       each scoring an elevation profile, the azimuth from a parabola through the best three.
    5. **Gates**: the score, the peak's *sharpness* (its score minus the best score more than 30 deg
       away) and the lit/shadow contrast decide the confidence; an overcast or unlit scene still
       has a best candidate, but a flat one. The local refine does not see the whole hemisphere:
       it carries the last full search's sharpness, scaled by how much of its score it keeps.

Known failure modes (and what the code does about them)
    * **Whole visible floor in shadow** (e.g. behind a building): no lit reference, no contrast; the
      score and the lit/shadow ratio show it and the confidence drops (``None`` when nothing
      scores).
    * **Sun near the zenith**: shadows shrink to the footprints and the azimuth is undetermined.
      ``azimuth_confidence`` measures how much better the best azimuth scores than azimuths more
      than 45 deg away; 6-10 deg from the zenith (shadows of one or two cells) the elevation is
      still found while the azimuth confidence drops to about 0. Within a few degrees of the zenith
      no shadow leaves the footprints at all: the answer has no confidence, as for an overcast sky
      (the two look the same to this cue; the casters' own shading, lit tops and dark sides, would
      tell them apart).
    * **Soft shadows** (indoor area lights, overcast): the penumbra widens the observed shadow and
      pulls the best elevation low (a longer predicted shadow covers more of the blur); the
      sharpness gate lowers the confidence but does not remove the bias.
    * **The virtual object** is never a caster: it is not in the depth (only real geometry is), and
      the picture searched is the camera's, not the composite.
    * **Holes in the depth** are neither casters nor receiver: only valid depth is used; pixels at
      depth discontinuities (flying pixels between an edge and the background) are dropped; caster
      cells with no caster neighbours are dropped as speckle. A caster missing from the depth
      (black or shiny object) leaves its shadow unexplained, which only lowers the score.
    * **Large walls and ceilings** are not casters by default: their extent beyond the frame is
      unknown (a facade cut by the top of the picture casts a longer shadow than its visible part,
      which would pull the elevation low), and a ceiling does not stand on the floor. Tracked
      planes labelled ``wall`` of at least ``wall_min_area_m2``, planes facing down, and points
      higher than ``max_caster_m`` are excluded. A table top is a caster (extended down: its
      legs' region is seldom visible, so the error lands mostly in unobserved cells).
    * **Near lights** (a lamp 0.5 m from the casters) cast radial shadows that no single distant
      direction fits: the synthetic ``lamp`` scenes give confidence 0. (Sweeping the lamp's
      footprint with a polar grid around it, where radial shadows run along rows, would extend the
      same running-maximum pass to point lights.)

Frames: camera coordinates (OpenCV) in, the anchor's object frame (+Y up, see
:class:`~illuminet.runtime.scene.Anchor`) out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from illuminet.runtime.frame import Intrinsics
from illuminet.runtime.scene import Plane

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass(frozen=True)
class ShadowParams:
    """Settings of the search (the defaults are what the tests and ``illuminet bench shadows`` use).

    Attributes
    ----------
    stride : int
        Every ``stride``-th depth pixel in each direction is used (2 at 640x400: 64k samples).
    cell_m : float
        Receiver grid cell (metres): the resolution of predicted and observed shadows.
    max_range_m : float
        Depth beyond which pixels are ignored (stereo depth noise and cell coverage degrade).
    on_plane_at_1m : float
        Receiver tolerance at 1 m (metres), growing with z^2 like stereo noise, clipped to
        [0.01, 0.10] m.
    min_caster_m : float
        A caster is at least this high above the receiver (and twice the receiver tolerance).
    max_caster_m : float
        Points higher than this are not casters (ceilings, overhead lamps, tree canopies).
    wall_min_area_m2 : float
        Tracked ``wall`` planes at least this large are not casters (see the module docstring);
        ``inf`` makes every wall a caster.
    ref_percentile, shadow_drop : float
        The lit floor's brightness: a smooth surface fitted to the cells' log luminance, leaving out
        cells more than ``shadow_drop`` under it, shifted up to this percentile of the lit cells.
    min_shadow_cells : int
        A candidate must predict at least this many observed shadow cells to score.
    """

    stride: int = 3
    cell_m: float = 0.03
    max_range_m: float = 4.5
    on_plane_at_1m: float = 0.02
    min_caster_m: float = 0.05
    max_caster_m: float = 2.5
    wall_min_area_m2: float = 1.0
    ref_percentile: float = 90.0
    shadow_drop: float = 0.15
    min_shadow_cells: int = 12


@dataclass(frozen=True)
class ShadowCue:
    """The light direction the shadows point to.

    Attributes
    ----------
    direction : (3,) float
        Unit vector *towards* the light, in the anchor's object frame (+Y up).
    confidence : float
        In [0, 1]: how much the direction (elevation at least) can be trusted.
    azimuth_confidence : float
        In [0, 1], at most ``confidence``: near 0 when the light is near the zenith (short shadows
        point nowhere in particular).
    score : float
        Correlation of the predicted shadow mask with the observed darkness, in [-1, 1].
    sharpness : float
        ``score`` minus the best score more than 30 deg away (full search); the local refine
        carries the prior's, scaled by the share of the prior's score it keeps.
    shadow_ratio : float
        Median luminance in the predicted shadow over that of the lit cells around it (relative to
        the local reference): ``E_shadow / E_lit`` on the receiver, i.e. the ambient share of the
        receiver's irradiance (1 = no visible shadow).
    n_casters : int
        Caster cells (footprint cells of the receiver grid with something standing on them).
    receiver_id : int
        The id of the receiving plane.
    elapsed_s : float
        Time spent in :func:`shadow_direction`.
    search : str
        ``"full"`` or ``"local"``.
    """

    direction: np.ndarray
    confidence: float
    azimuth_confidence: float
    score: float
    sharpness: float
    shadow_ratio: float
    n_casters: int
    receiver_id: int
    elapsed_s: float
    search: str = "full"

    @property
    def elevation_deg(self) -> float:
        """Elevation of the light above the receiver (degrees)."""
        return float(np.degrees(np.arcsin(np.clip(self.direction[1], -1.0, 1.0))))

    @property
    def azimuth_deg(self) -> float:
        """Azimuth in the object frame's X-Z plane: ``atan2(x, z)`` in degrees."""
        return float(np.degrees(np.arctan2(self.direction[0], self.direction[2])))


# ------------------------------------------------------------------------------------ observation


@dataclass
class _Observation:
    """One frame reduced to the receiver grid (plane coordinates a, b; cell (i, j) = (b, a))."""

    basis: np.ndarray  # (3, 3) rows e1, e2, n (camera frame): plane coordinates a, b and height
    R_obj: np.ndarray  # object -> camera rotation
    lo: np.ndarray  # (2,) a, b of the grid's corner
    shape: tuple[int, int]  # rows (b), cols (a)
    cell: float
    weights: np.ndarray  # (rows, cols) float32: 1 where observed and usable
    dark: np.ndarray  # (rows, cols) float32 observed darkness in [0, 1]
    rel: np.ndarray  # (rows, cols) float32 luminance over the local reference
    caster_ab: np.ndarray  # (C, 2) footprint cell centres, sorted by height (ascending)
    caster_h: np.ndarray  # (C,) heights (metres)
    n: float = 0.0
    mean: float = 0.0
    var_n: float = 0.0  # n * variance of the darkness
    n_min: int = 12  # fewest predicted shadow cells (weights) a candidate needs to score
    stack: np.ndarray = field(default=None)  # (rows, cols, 2) float32: weights * dark, weights


def _receiver(planes, T_cam_obj: np.ndarray, receiver_id: int | None) -> Plane | None:
    """The anchor's plane: the given id, else the plane the anchor origin lies on and whose normal
    is the object's +Y, else the largest horizontal one."""
    if receiver_id is not None:
        for p in planes:
            if p.id == receiver_id:
                return p
        return None
    up, o = T_cam_obj[:3, 1], T_cam_obj[:3, 3]
    fits = [p for p in planes if float(np.dot(p.normal, up)) > np.cos(np.radians(10)) and abs(p.distance(o)) < 0.05]
    if fits:
        return min(fits, key=lambda p: abs(p.distance(o)))
    horiz = [p for p in planes if p.label in ("floor", "table") and float(np.dot(p.normal, up)) > 0.9]
    return max(horiz, key=lambda p: p.area_m2) if horiz else None


def _lit_surface(L2: np.ndarray, seen2: np.ndarray, q: float, drop: float, iters: int = 4) -> np.ndarray:
    """The brightness of the lit floor (rows, cols): a quadratic in the plane coordinates fitted to
    the seen cells' log luminance, cells more than ``drop`` under it left out at each iteration (the
    shadows), shifted up to the ``q`` percentile of the lit cells' residuals.

    Why a surface and not a local percentile: a lamp's falloff or the lens's vignetting darkens one
    side of the floor smoothly, and a long predicted shadow over that side would correlate with it
    (seen on the real OAK-D frames); a quadratic follows such gradients but not a shadow's edges.
    Normal equations written as einsums (no BLAS threads, see _azimuth_scores)."""
    rows, cols = L2.shape
    ii, jj = np.nonzero(seen2)
    y = np.log(np.maximum(L2[ii, jj], 1e-9)).astype(np.float64)
    sc = 1.0 / max(rows, cols)
    x1, x2 = (jj - cols / 2) * sc, (ii - rows / 2) * sc
    A = np.stack([np.ones_like(x1), x1, x2, x1 * x1, x1 * x2, x2 * x2], axis=1)
    w = np.ones_like(y)
    coef = np.zeros(6)
    for _ in range(iters):
        AtA = np.einsum("ni,n,nj->ij", A, w, A) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(AtA, np.einsum("ni,n,n->i", A, w, y))
        r = y - np.einsum("ni,i->n", A, coef)
        w = (r > -drop).astype(np.float64)
    shift = float(np.percentile(r[w > 0], q)) if w.any() else 0.0
    J, I = np.meshgrid((np.arange(cols) - cols / 2) * sc, (np.arange(rows) - rows / 2) * sc)
    surf = coef[0] + coef[1] * J + coef[2] * I + coef[3] * J * J + coef[4] * J * I + coef[5] * I * I
    return np.exp(surf + shift).astype(np.float32)


_RAYS: dict = {}


def _rays(intr: Intrinsics, s: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(x / z, y / z) of the camera ray through every ``s``-th pixel (cached: one camera, one size)."""
    key = (intr.fx, intr.fy, intr.cx, intr.cy, s, shape)
    if key not in _RAYS:
        _RAYS.clear()
        v, u = np.mgrid[0 : shape[0] * s : s, 0 : shape[1] * s : s].astype(np.float32)
        _RAYS[key] = ((u - np.float32(intr.cx)) / np.float32(intr.fx), (v - np.float32(intr.cy)) / np.float32(intr.fy))
    return _RAYS[key]


def _observe(
    color_linear, depth, intr: Intrinsics, planes, T_cam_obj, receiver: Plane, prm: ShadowParams
) -> _Observation | None:
    s = prm.stride
    z = np.ascontiguousarray(depth[::s, ::s], np.float32)
    rx, ry = _rays(intr, s, z.shape)
    valid = np.isfinite(z) & (z > 0) & (z < prm.max_range_m)
    # depth discontinuities: stereo mixes the two sides there (flying pixels), so neither counts; inf - inf (depth
    # with inf for invalid, which the planes take) printed numpy's "invalid value encountered in subtract" lines
    with np.errstate(invalid="ignore"):
        jx = np.abs(np.diff(z, axis=1)) > 0.05 * np.minimum(z[:, 1:], z[:, :-1])
        jy = np.abs(np.diff(z, axis=0)) > 0.05 * np.minimum(z[1:], z[:-1])
    valid[:, 1:] &= ~jx
    valid[:, :-1] &= ~jx
    valid[1:] &= ~jy
    valid[:-1] &= ~jy
    # only valid depths from here on: 1e30 or float32's max for invalid overflowed "z ** 2" below (numpy's
    # two-line RuntimeWarning on every frame); every use of z is masked by valid
    z = np.where(valid, z, np.float32(0))

    n = np.asarray(receiver.normal, np.float64)
    R = np.asarray(T_cam_obj, np.float64)[:3, :3]
    e1 = R[:, 0] - np.dot(R[:, 0], n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(e1, n)  # object X x Y = Z: (e1, n, e2) is the object frame's (X, Y, Z)
    origin = T_cam_obj[:3, 3] - receiver.distance(T_cam_obj[:3, 3]) * n
    basis = np.stack([e1, e2, n])
    off = basis @ origin

    def coord(e, o):  # e . (x, y, z) - o on the strided grid: z * (e . ray) - o
        return z * (np.float32(e[0]) * rx + np.float32(e[1]) * ry + np.float32(e[2])) - np.float32(o)

    h = coord(n, off[2])
    tol = np.clip(
        np.float32(prm.on_plane_at_1m) * np.maximum(z, np.float32(0.5)) ** 2, np.float32(0.01), np.float32(0.10)
    )
    on = valid & (np.abs(h) < tol)
    up = valid & (h > np.maximum(np.float32(prm.min_caster_m), 2 * tol)) & (h < np.float32(prm.max_caster_m))
    # points on large walls and on planes facing down are not casters (module docstring); tested by
    # distance, not by the planes' inlier masks: a wall's lowest rows go to the floor's inliers
    for p in planes:
        if p.id == receiver.id:
            continue
        if (p.label == "wall" and p.area_m2 >= prm.wall_min_area_m2) or float(np.dot(p.normal, n)) < -0.7:
            up &= np.abs(coord(p.normal, -p.offset)) > 2 * tol
    n_on = int(np.count_nonzero(on))
    if n_on < 50 or not up.any():
        return None
    a, b = coord(e1, off[0]), coord(e2, off[1])
    a_on, b_on, a_up, b_up, h_up = a[on], b[on], a[up], b[up], h[up]
    rgb = color_linear[::s, ::s][on]
    # channel by channel: a matrix product here would start BLAS threads (see _azimuth_scores)
    L = (LUMA[0] * rgb[:, 0] + LUMA[1] * rgb[:, 1] + LUMA[2] * rgb[:, 2]).astype(np.float32)

    c = prm.cell_m
    lo = np.array([min(a_on.min(), a_up.min()), min(b_on.min(), b_up.min())], np.float64) - c
    hi = np.array([max(a_on.max(), a_up.max()), max(b_on.max(), b_up.max())], np.float64) + c
    cols, rows = np.ceil((hi - lo) / c).astype(int) + 1
    if rows * cols > 600 * 600:  # a grazing view of a huge floor: keep the 18 m x 18 m around the casters
        ctr = np.array([np.median(a_up), np.median(b_up)])
        lo, hi = np.maximum(lo, ctr - 9.0), np.minimum(hi, ctr + 9.0)
        cols, rows = np.ceil((hi - lo) / c).astype(int) + 1
    size = rows * cols

    def cells(aa, bb):  # flat cell index, and which points fall inside the grid
        inside = (aa >= lo[0]) & (aa < hi[0]) & (bb >= lo[1]) & (bb < hi[1])
        return ((bb - lo[1]) / c).astype(np.int64) * cols + ((aa - lo[0]) / c).astype(np.int64), inside

    flat_on, in_on = cells(a_on, b_on)
    cnt = np.bincount(flat_on[in_on], minlength=size).astype(np.float32)
    lsum = np.bincount(flat_on[in_on], weights=L[in_on], minlength=size).astype(np.float32)
    seen = cnt > 0
    Lc = np.where(seen, lsum / np.maximum(cnt, 1), 0).astype(np.float32)

    # casters: the tallest per footprint cell; speckle (no caster neighbour) is dropped
    flat_up, in_up = cells(a_up, b_up)
    hmax = np.zeros(size, np.float32)
    order = np.argsort(h_up[in_up])
    hmax[flat_up[in_up][order]] = h_up[in_up][order]  # ascending: the tallest is written last
    hmax = hmax.reshape(rows, cols)
    has = (hmax > 0).astype(np.float32)
    neigh = cv2.boxFilter(has, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    hmax[neigh < 2] = 0
    cidx = np.flatnonzero(hmax.ravel() > 0)
    if cidx.size == 0:
        return None
    ch = hmax.ravel()[cidx]
    order = np.argsort(ch)
    cidx, ch = cidx[order], ch[order]
    cab = np.stack([lo[0] + (cidx % cols + 0.5) * c, lo[1] + (cidx // cols + 0.5) * c], axis=1)

    seen2 = seen.reshape(rows, cols)
    L2 = Lc.reshape(rows, cols)
    ref = _lit_surface(L2, seen2, prm.ref_percentile, prm.shadow_drop)
    rel = np.where(seen2, L2 / ref, 0).astype(np.float32)
    dark = np.clip(1.0 - rel, 0.0, 1.0).astype(np.float32)

    # a cell's weight grows with its samples up to 4 (far cells hold one pixel: texture and noise);
    # footprint cells do not count (under an object; their neighbours do: a sun near the zenith
    # casts shadows only a cell or two long)
    w = (np.minimum(cnt.reshape(rows, cols), 4.0) / 4.0 * (hmax == 0)).astype(np.float32)
    obs = _Observation(
        basis=basis,
        R_obj=R,
        lo=lo,
        shape=(rows, cols),
        cell=c,
        weights=w,
        dark=dark,
        rel=rel,
        caster_ab=cab,
        caster_h=ch,
        n_min=prm.min_shadow_cells,
    )
    obs.n = float(w.sum())
    if obs.n < 50:
        return None
    stack = np.empty((rows, cols, 2), np.float32)
    np.multiply(w, dark, out=stack[..., 0])
    stack[..., 1] = w
    obs.stack = stack
    obs.mean = float(stack[..., 0].sum(dtype=np.float64) / obs.n)
    obs.var_n = float((stack[..., 0] * dark).sum(dtype=np.float64) - obs.n * obs.mean * obs.mean)
    return obs


# ------------------------------------------------------------------------------------ scoring


def _direction(phi: float, theta: float) -> np.ndarray:
    """Plane-basis unit vector towards the light: azimuth phi from e1 towards e2, zenith angle theta."""
    st = np.sin(theta)
    return np.array([st * np.cos(phi), st * np.sin(phi), np.cos(theta)])


def _azimuth_masks(obs: _Observation, phi: float, tans: np.ndarray, pad: int = 0):
    """Predicted shadow masks of azimuth ``phi`` for zenith tangents ``tans`` on a canvas whose rows
    run along the shadows, ``pad`` cells wider than the casters on three sides (not past the far end).
    Returns (masks (T, rows, cols) bool, canvas -> grid affine 2x3) or None."""
    c = obs.cell
    sd = np.array([-np.cos(phi), -np.sin(phi)])  # shadows run away from the light
    sp = np.array([-sd[1], sd[0]])
    ab = obs.caster_ab
    xc = ab[:, 0] * sd[0] + ab[:, 1] * sd[1]
    yc = ab[:, 0] * sp[0] + ab[:, 1] * sp[1]
    rows_g, cols_g = obs.shape
    corners = obs.lo + np.array([[0, 0], [cols_g, 0], [0, rows_g], [cols_g, rows_g]]) * c
    x0, y0 = float(xc.min()) - (0.5 + pad) * c, float(yc.min()) - (0.5 + pad) * c
    # up to the grid's far edge, or as far as the longest shadow (plus the ring) reaches
    far = min(float((corners @ sd).max()), float(xc.max()) + float(obs.caster_h[-1]) * float(np.max(tans)) + pad * c)
    cols = int(np.ceil((far - x0) / c)) + 1
    rows = int(np.ceil((float(yc.max()) + (0.5 + pad) * c - y0) / c))
    if cols <= 1 or rows <= 0:
        return None
    I = np.minimum(((yc - y0) / c).astype(np.int64), rows - 1)
    J = np.minimum(((xc - x0) / c).astype(np.int64), cols - 1)
    hcan = np.zeros(rows * cols, np.float32)
    hcan[I * cols + J] = obs.caster_h  # sorted ascending: the tallest per canvas cell wins
    hcan = hcan.reshape(rows, cols)
    col = np.arange(cols, dtype=np.float32) + np.float32(0.5)
    base = np.where(hcan > 0, col[None, :], -np.inf).astype(np.float32)
    reach = base[None] + hcan[None] * (np.asarray(tans, np.float32)[:, None, None] / np.float32(c))
    np.maximum.accumulate(reach, axis=2, out=reach)
    masks = reach >= col[None, None, :]
    # canvas (J, I) -> grid (col, row) index, pixel centres at integers (for warpAffine)
    ox = x0 + 0.5 * c
    oy = y0 + 0.5 * c
    M = np.array(
        [
            [sd[0], sp[0], (ox * sd[0] + oy * sp[0] - obs.lo[0]) / c - 0.5],
            [sd[1], sp[1], (ox * sd[1] + oy * sp[1] - obs.lo[1]) / c - 0.5],
        ]
    )
    return masks, M


#: Width of the band around a predicted shadow that must be lit (metres): the score's contrast term.
RING_M = 0.3


def _azimuth_scores(obs: _Observation, phi: float, tans: np.ndarray) -> np.ndarray:
    """Scores of the predicted masks for azimuth ``phi`` and each zenith tangent in ``tans`` (T,).

    score = Pearson correlation of the mask with the darkness over the whole observed floor (the
    mask must explain the shadows: too short or too long loses) x max(0, mean darkness inside the
    mask - mean darkness in a ``RING_M`` band around it) (its edges must be shadow edges: a mask
    that lands inside a large unexplained shadow, such as a building's, has a dark band too).
    """
    ring_cells = max(1, int(round(RING_M / obs.cell)))
    out = _azimuth_masks(obs, phi, tans, pad=ring_cells)
    if out is None:
        return np.zeros(len(tans))
    masks, M = out
    T, rows, cols = masks.shape
    can = cv2.warpAffine(
        obs.stack,
        M,
        (cols, rows),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    # (2, N): sums over masks as a uint8 x float32 einsum, which never starts BLAS threads (a
    # skinny float matmul does, and on a busy machine that costs several times the work)
    can = np.ascontiguousarray(can.reshape(-1, 2).T)
    # the band around each mask: one dilation of the masks stacked vertically (the canvas has
    # ring_cells empty rows above and below the casters, so neighbours do not bleed into each other)
    m8 = masks.view(np.uint8).reshape(T * rows, cols)
    k = np.ones((2 * ring_cells + 1, 2 * ring_cells + 1), np.uint8)
    both = np.concatenate([m8.reshape(T, -1), (cv2.dilate(m8, k) - m8).reshape(T, -1)])
    sums = np.einsum("tn,kn->tk", both, can).astype(np.float64)  # (2T, 2): sum of w * dark, of w
    sm, sr = sums[:T], sums[T:]
    contrast = np.where(
        (sm[:, 1] >= obs.n_min) & (sr[:, 1] >= obs.n_min),
        sm[:, 0] / np.maximum(sm[:, 1], 1e-9) - sr[:, 0] / np.maximum(sr[:, 1], 1e-9),
        0.0,
    )
    corr = _pearson(obs.n, obs.mean, obs.var_n, sm[:, 0], sm[:, 1], obs.n_min)
    return corr * np.maximum(contrast, 0.0)


def _pearson(n, mean, var_n, sd, so, n_min) -> np.ndarray:
    """Correlation of a binary mask (sum of weights ``so``, of weighted darkness ``sd``) with the
    darkness over cells of total weight ``n``, mean darkness ``mean`` and ``n * variance`` ``var_n``."""
    den = np.sqrt(np.maximum(so * (1.0 - so / np.maximum(n, 1e-9)), 0) * np.maximum(var_n, 0))
    ok = (so >= n_min) & (n - so >= n_min) & (den > 0)
    return np.where(ok, (sd - so * mean) / np.where(ok, den, 1.0), 0.0)


def _mask_on_grid(obs: _Observation, phi: float, theta: float) -> np.ndarray:
    """The predicted shadow of one direction on the receiver grid (rows, cols) bool."""
    out = _azimuth_masks(obs, phi, np.array([np.tan(theta)]))
    if out is None:
        return np.zeros(obs.shape, bool)
    masks, M = out
    Mi = cv2.invertAffineTransform(M)
    g = cv2.warpAffine(
        masks[0].astype(np.uint8),
        Mi,
        (obs.shape[1], obs.shape[0]),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return g.astype(bool)


# ------------------------------------------------------------------------------------ search

#: Coarse grid of the full search (radians): 9 zenith angles x 36 azimuths.
COARSE_THETA = np.radians(np.arange(5.0, 90.0, 10.0))
COARSE_PHI = np.radians(np.arange(0.0, 360.0, 10.0))
#: Upper bound of the zenith angle searched (the light 5 deg above the horizon).
MAX_THETA = np.radians(85.0)


def _refine(obs: _Observation, phi: float, theta: float, step_deg: float, half: int) -> tuple[float, float, float]:
    """Best (score, phi, theta) on a (2*half+1)^2 grid of ``step_deg`` around (phi, theta); the
    azimuth step widens as 1/sin(theta) so that steps are ``step_deg`` on the sphere."""
    st = np.radians(step_deg)
    thetas = np.clip(theta + st * np.arange(-half, half + 1), np.radians(0.5), MAX_THETA)
    thetas = np.unique(thetas)
    dphi = min(st / max(np.sin(theta), 0.05), np.pi / half)
    best = (-np.inf, phi, theta)
    tans = np.tan(thetas)
    for k in range(-half, half + 1):
        p = phi + k * dphi
        s = _azimuth_scores(obs, p, tans)
        i = int(np.argmax(s))
        if s[i] > best[0]:
            best = (float(s[i]), p, float(thetas[i]))
    return best


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (radians) between unit vectors u (..., 3) and v (3,)."""
    return np.arccos(np.clip(u[..., 0] * v[0] + u[..., 1] * v[1] + u[..., 2] * v[2], -1.0, 1.0))


def _full_search(obs: _Observation, n_peaks: int = 3):
    """((score, phi, theta), sharpness, azimuth sharpness) of the best direction on the hemisphere,
    or None when no candidate scores (module docstring, steps 4-5)."""
    tans = np.tan(COARSE_THETA)
    S = np.stack([_azimuth_scores(obs, p, tans) for p in COARSE_PHI])  # (phi, theta)
    P, Tt = np.meshgrid(COARSE_PHI, COARSE_THETA, indexing="ij")
    dirs = np.stack([np.sin(Tt) * np.cos(P), np.sin(Tt) * np.sin(P), np.cos(Tt)], axis=-1).reshape(-1, 3)
    flat = S.ravel()
    peaks: list[int] = []
    for i in np.argsort(-flat):
        if flat[i] <= 0 or len(peaks) == n_peaks:
            break
        if all(_angle(dirs[i], dirs[j]) > np.radians(20) for j in peaks):
            peaks.append(int(i))
    if not peaks:
        return None
    best = (-np.inf, 0.0, 0.0)
    for i in peaks:
        r = _refine(obs, float(P.ravel()[i]), float(Tt.ravel()[i]), 2.0, 3)
        if r[0] > best[0]:
            best = r
    best = max(best, _refine(obs, best[1], best[2], 0.5, 3), key=lambda r: r[0])
    d = _direction(best[1], best[2])
    far = _angle(dirs, d) > np.radians(30)
    sharp = best[0] - (float(flat[far].max()) if far.any() else 0.0)
    dphi = np.abs((P.ravel() - best[1] + np.pi) % (2 * np.pi) - np.pi)
    other_az = dphi > np.radians(45)
    az_sharp = best[0] - (float(flat[other_az].max()) if other_az.any() else 0.0)
    return best, sharp, az_sharp


def _local_search(obs: _Observation, phi0: float, theta0: float) -> tuple[float, float, float]:
    """Best (score, phi, theta) near (phi0, theta0) in about four azimuth passes. Each pass scores a
    whole elevation profile (+-10 deg at 2.5 deg), so only the azimuth is searched: three azimuths
    3 deg apart on the sphere, stepping outwards while the best is at an end (a prior up to ~15 deg
    off), the vertex of a parabola through the best and its neighbours, and there the elevation at
    0.5 deg."""
    th_off = np.radians(np.arange(-10.0, 10.01, 2.5))
    cache: dict[float, tuple[float, float]] = {}

    def profile(phi: float) -> tuple[float, float]:
        if phi not in cache:
            th = np.clip(theta0 + th_off, np.radians(0.5), MAX_THETA)
            s = _azimuth_scores(obs, phi, np.tan(th))
            i = int(np.argmax(s))
            cache[phi] = (float(s[i]), float(th[i]))
        return cache[phi]

    dphi = min(np.radians(3.0) / max(np.sin(theta0), 0.1), np.radians(30.0))
    ks = {k: profile(phi0 + k * dphi) for k in (-1, 0, 1)}
    for _ in range(4):
        kb = max(ks, key=lambda k: ks[k][0])
        if kb == min(ks):
            ks[kb - 1] = profile(phi0 + (kb - 1) * dphi)
        elif kb == max(ks):
            ks[kb + 1] = profile(phi0 + (kb + 1) * dphi)
        else:
            break
    kb = max(ks, key=lambda k: ks[k][0])
    off = 0.0
    if kb - 1 in ks and kb + 1 in ks:
        ym, y0, yp = ks[kb - 1][0], ks[kb][0], ks[kb + 1][0]
        den = ym - 2 * y0 + yp
        off = float(np.clip(0.5 * (ym - yp) / den, -0.5, 0.5)) if den < 0 else 0.0
    phi, theta = phi0 + (kb + off) * dphi, ks[kb][1]
    # the elevation at 0.5 deg at the final azimuth
    th = np.clip(theta + np.radians(np.arange(-2.0, 2.01, 0.5)), np.radians(0.5), MAX_THETA)
    s = _azimuth_scores(obs, phi, np.tan(th))
    i = int(np.argmax(s))
    best = max(cache.items(), key=lambda kv: kv[1][0])
    if s[i] >= best[1][0]:
        return float(s[i]), phi, float(th[i])
    return best[1][0], best[0], best[1][1]


#: Confidence scales (measured on the synthetic scenes, see the tests): full confidence needs a
#: score of SCORE_FULL, a peak SHARPNESS_FULL above anything 30 deg away (none below
#: SHARPNESS_MIN: wrong answers and overcast frames stay under it), and the predicted shadow at
#: most RATIO_FULL as bright as the lit floor around it.
SCORE_FULL = 0.3
SHARPNESS_MIN = 0.03
SHARPNESS_FULL = 0.2
RATIO_FULL = 0.5


def shadow_direction(
    color_linear: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    planes,
    anchor_T_cam_obj: np.ndarray,
    receiver_id: int | None = None,
    params: ShadowParams | None = None,
    prior: ShadowCue | None = None,
) -> ShadowCue | None:
    """The direction towards the light that the shadows on the anchor plane point to.

    Parameters
    ----------
    color_linear : (H, W, 3) float
        The camera picture, linear RGB (any scale: only ratios are used).
    depth : (H, W) float32
        Metres, aligned to the colour, 0 where invalid.
    intrinsics : Intrinsics
        Of the colour/depth image.
    planes : sequence of Plane
        The tracked planes (``results[PLANES]``).
    anchor_T_cam_obj : (4, 4)
        The anchor pose (``Anchor.T_cam_obj``): the answer is in its object frame.
    receiver_id : int, optional
        The plane the shadows fall on; default: the one the anchor stands on.
    params : ShadowParams, optional
    prior : ShadowCue, optional
        The last answer (same object frame): refine locally around it instead of searching the
        whole hemisphere (about 4 azimuth passes instead of about 60; converges from 10-15 deg off).

    Returns
    -------
    ShadowCue or None
        None when there is no receiver, no caster, too little observed floor, or no candidate
        predicts a shadow on the observed floor.
    """
    t0 = time.perf_counter()
    prm = params or ShadowParams()
    T = np.asarray(anchor_T_cam_obj, np.float64)
    receiver = _receiver(planes, T, receiver_id)
    if receiver is None:
        return None
    obs = _observe(color_linear, depth, intrinsics, planes, T, receiver, prm)
    if obs is None:
        return None
    if prior is not None:
        w = obs.basis @ (obs.R_obj @ np.asarray(prior.direction, np.float64))  # object -> camera -> plane
        theta = float(np.clip(np.arccos(np.clip(w[2], -1, 1)), np.radians(0.5), MAX_THETA))
        score, phi, theta = _local_search(obs, float(np.arctan2(w[1], w[0])), theta)
        # the peak's sharpness is measured by the full search; here it scales with the score kept
        keep = float(np.clip(score / max(prior.score, 1e-9), 0.0, 1.0))
        sharp = prior.sharpness * keep
        az_factor = prior.azimuth_confidence / max(prior.confidence, 1e-9) if prior.confidence > 0 else 0.0
        search = "local"
    else:
        res = _full_search(obs)
        if res is None:
            return None
        (score, phi, theta), sharp, az_sharp = res
        az_factor = float(np.clip((az_sharp - SHARPNESS_MIN) / (SHARPNESS_FULL - SHARPNESS_MIN), 0, 1))
        search = "full"
    if not np.isfinite(score) or score <= 0:
        return None
    # lit/shadow contrast: predicted shadow against the lit cells within 30 cm of it
    mask = _mask_on_grid(obs, phi, theta)
    seen = obs.weights > 0
    ring = cv2.dilate(mask.astype(np.uint8), np.ones((2 * int(0.3 / obs.cell) + 1,) * 2, np.uint8)).astype(bool)
    sh, lit = obs.rel[mask & seen], obs.rel[ring & ~mask & seen]
    ratio = float(np.median(sh) / max(np.median(lit), 1e-6)) if sh.size >= 4 and lit.size >= 4 else 1.0
    conf = float(
        np.clip(score / SCORE_FULL, 0, 1)
        * np.clip((sharp - SHARPNESS_MIN) / (SHARPNESS_FULL - SHARPNESS_MIN), 0, 1)
        * np.clip((1.0 - ratio) / (1.0 - RATIO_FULL), 0, 1)
    )
    az_conf = conf * az_factor
    w = _direction(phi, theta)
    d_obj = obs.R_obj.T @ (obs.basis.T @ w)
    d_obj /= np.linalg.norm(d_obj)
    return ShadowCue(
        direction=d_obj,
        confidence=float(conf),
        azimuth_confidence=float(az_conf),
        score=float(score),
        sharpness=float(sharp),
        shadow_ratio=float(ratio),
        n_casters=int(obs.caster_h.size),
        receiver_id=int(receiver.id),
        elapsed_s=time.perf_counter() - t0,
        search=search,
    )


class ShadowTracker:
    """Full search every ``full_every_s`` seconds, a local refine around the last answer on the
    frames between; between full searches without a usable last answer (no shadow seen, or one
    below ``min_confidence``) nothing is searched and the last answer is returned again, so a
    scene without shadows costs one full search a second, not one a frame.

    Parameters
    ----------
    full_every_s : float
        Period of the full search (the sun is fixed in the world: about once a second is plenty).
    min_confidence : float
        A last answer below this is not refined locally.
    params : ShadowParams, optional

    Attributes
    ----------
    last : ShadowCue or None
        The last answer.
    full_searches, local_refines : int
        How many of each ran.
    """

    def __init__(self, full_every_s: float = 1.0, min_confidence: float = 0.2, params: ShadowParams | None = None):
        self.full_every_s = float(full_every_s)
        self.min_confidence = float(min_confidence)
        self.params = params
        self.last: ShadowCue | None = None
        self.full_searches = 0
        self.local_refines = 0
        self._last_full_s: float | None = None

    def reset(self) -> None:
        """Forget the last answer (the anchor was placed again: its object frame changed)."""
        self.last = None
        self._last_full_s = None

    def update(self, color_linear, depth, intrinsics, planes, anchor_T_cam_obj, t_s: float) -> ShadowCue | None:
        """The cue for the frame at time ``t_s`` (seconds, any origin)."""
        if self._last_full_s is None or t_s - self._last_full_s >= self.full_every_s:
            self.last = shadow_direction(color_linear, depth, intrinsics, planes, anchor_T_cam_obj, params=self.params)
            self._last_full_s = t_s
            self.full_searches += 1
        elif self.last is not None and self.last.confidence >= self.min_confidence:
            self.last = shadow_direction(
                color_linear, depth, intrinsics, planes, anchor_T_cam_obj, params=self.params, prior=self.last
            )
            self.local_refines += 1
        return self.last
