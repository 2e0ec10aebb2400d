"""The per-frame lighting estimate: the room's light at the anchor, from everything the frame shows.

What this module owns
---------------------
:class:`LightEstimateStage` reads the anchor, the plane light and the frame's colour and depth, and
writes a :class:`~illuminet.runtime.scene.LightEstimate` (results key ``LIGHT``): ambient irradiance
as SH9 x RGB plus one primary light, in the anchor's gravity-aligned object frame (+Y up).

Observations (each switchable in ``[light]`` for the ablation in ``illuminet eval``)
------------------------------------------------------------------------------------
* **environment** -- every valid pixel of the depth cloud is a surface point whose radiance the camera
  measures (linear pixel / exposure scale). Seen from the object's centre it is the radiance arriving
  from that direction: walls, the floor around the object (its bounce onto the object's underside),
  furniture. Pixels without depth (sky, windows, far) arrive from the camera ray's direction. The
  samples are binned on a latitude-longitude grid in the object frame and fused over frames: the
  object frame is world-locked (odometry), so looking around fills the map (ARKit's environment
  texturing, LitAR). The radiance is used as measured: no albedo assumption.
* **planes** -- the irradiance of every tracked plane (the anchor plane's fused grid from
  :class:`~illuminet.runtime.stages.plane_light.PlaneLightStage`, and pixel samples of the other
  planes: walls, table tops) with each plane's normal: a wall sees directions the floor cannot.
  Irradiance needs an albedo: ``[plane_light] assumed_albedo``, with the plane's colour divided by
  the scene's illuminant colour (grey world over all surfaces) so that a beige floor does not make a
  beige light.
* **near light** -- a lamp near the object makes the irradiance on the planes fall off as
  ``cos / r^2``: a grid search over light positions, refined locally every frame, scored by how much
  of the anchor grid's differences between neighbouring cells ``max(0, n.(p-x)) / |p-x|^3`` explains
  with Huber weights (:func:`fit_near_light_gradient`: the ambient drops out of differences, and the
  floor texture's edges are outliers). It searches the plane light's 2 m context grid first (a lamp's
  whole pool of light, where the 1 m grid often holds only its tail), then the 1 m grid when the lamp
  found there does not explain the light near the object (another lamp's pool farther off); when no
  lamp explains the differences, by how much of the planes' spatial
  variation in values it explains (:func:`fit_near_light`, a per-plane intercept for the ambient part:
  a room's ceiling lights 1.5-2 m off). This gives direction, distance and the primary/ambient split
  and colour (the solve below).
* **emitters** -- bins far brighter than the rest of the map (a lamp shade, a window, the sky's sun
  region) give a direction.
* **shadows** -- real cast shadows scored against the caster geometry from depth
  (:mod:`illuminet.runtime.stages.shadow_cue`): the sun's azimuth on a uniform floor. A full search
  about once a second, refined locally in between; used when its confidence reaches 0.3.

Solve
-----
For the chosen primary light (a near position, a direction, or none), one weighted linear least
squares gives the ambient *radiance* SH (9 x RGB) and the primary's RGB irradiance together: the
environment bins constrain the radiance directly (rows ``Y(w) . L = L_bin``); the plane samples
constrain its cosine convolution plus the primary's term (rows ``A_hat Y(n) . L + g . E_p = E``);
a Laplacian band penalty keeps unseen directions smooth. Without any cue for a primary light, the
primary is extracted from the first SH band (direction of the luminance gradient), with a confidence
that says how directional the light is.

Temporal filter: exponential in time (``[light] time_constant_s``, default 0.1 s: a light switched on
or off is followed within 0.5 s, to 98 %), reset when the anchor is placed again. The environment map
keeps 90 % of a bin per update, except when most of the bins in view changed at once (the light was
switched: :func:`light_changed`), when they take the frame's value.

Costs on this machine (``illuminet bench light``): see docs/lighting.md.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.physics import linearize
from illuminet.runtime.scene import ANCHOR, LIGHT, ODOMETRY, PLANE_LIGHT, PLANES, Anchor, LightEstimate, PlaneLight
from illuminet.runtime.sh import SH_A_HAT, SH_BAND, sh9
from illuminet.runtime.stage import LogOnce, Stage
from illuminet.runtime.stages.shadow_cue import ShadowTracker

log = logging.getLogger(__name__)

LUMA = np.array([0.2126, 0.7152, 0.0722])

#: the estimate's worker thread (``[light] pipelined``)
WORKER_NAME = "illuminet-light"

#: latitude-longitude bins of the environment map (theta from +Y, phi around it)
ENV_THETA, ENV_PHI = 12, 24
#: where the object is summarised (object frame, metres): a little above the plane
CENTRE = np.array([0.0, 0.1, 0.0])
#: depth beyond this (m) is treated as distant (its direction from the camera ray)
FAR_M = 8.0
#: candidate lamp positions of the coarse near-light search (object frame, metres)
_NEAR_XZ = np.linspace(-1.2, 1.2, 13)
_NEAR_Y = np.array([0.12, 0.3, 0.55, 0.9, 1.4])
NEAR_GRID = np.stack([a.ravel() for a in np.meshgrid(_NEAR_XZ, _NEAR_Y, _NEAR_XZ, indexing="ij")], 1)
#: a shadow cue below this confidence does not set the primary light (bench shadows: wrong answers
#: came with confidence <= 0.04, sunny scenes with >= 0.3)
SHADOW_MIN_CONFIDENCE = 0.3
#: the Planckian locus (2000-10000 K) in log chromaticity (log R/G, log B/G) of linear sRGB is close to the
#: line through D65 (0, 0) along (0.594, -0.804); its unit normal (tests/test_light_estimate.py checks it
#: against the black-body colours of runtime.groundtruth.lighting):
LOCUS_NORMAL = np.array([0.804, 0.594])
#: pixels this far off the locus (log chromaticity) vote exp(-1) as much as a pixel on it
LOCUS_SIGMA = 0.2
#: a surface votes for the light's colour with at least this many pixel samples near the locus
SURFACE_MIN_VOTES = 5.0
#: a seen emitter whose bins are clipped this much (luminance-weighted share of clipped pixels) is only
#: a lower bound on its light, in the clip's colour (:meth:`LightEstimateStage._emitter_rgb`)
EMITTER_CLIPPED = 0.3
#: the emitter cue needs its bright bins gathered: the length of their luminance-weighted mean direction
#: at least this (0.95: within ~18 deg of their centre on average; a lamp, a window, the sun's bins)
EMITTER_COMPACT = 0.95
#: a diffuse surface sends back at most the light it receives (energy conservation): the estimate must
#: light every tracked plane at least as brightly as its measured radiance asks of an albedo this high
#: (:meth:`LightEstimateStage._albedo_bound`)
ALBEDO_MAX = 1.0
#: the neutral prior's weight against the share of pixels that voted (0.1: a tenth of the view on the locus
#: already gives half the measured colour)
LOCUS_PRIOR = 0.1
#: the anchor plane's pixels out to this distance from the object (m) join its grid's observations
FLOOR_RADIUS_M = 1.5
#: ... and count in the ambient solve with a Gaussian weight of this radius (m): the floor far away is
#: lit by other lamps' pools as well, and says less about the light at the object
FLOOR_SIGMA_M = 0.75
#: ... and all of them together at most this share of the grid's weight
FLOOR_WEIGHT_MAX = 0.5
#: a near light is accepted only if it explains at least this share of the spatial variation of the
#: irradiance on the grid and the other planes (the far floor excluded): a lamp fitted to a distant
#: pool of light, not to the object's surroundings, is not the light at the object (0.3 -> 0.5 on the
#: eval's 11 scenes a suite: spatial MAE 0.078 -> 0.073, its colour 1.9 -> 1.3 deg)
LOCAL_R2_MIN = 0.5
#: a plane other than the anchor's whose irradiance varies across it by this much (relative standard
#: deviation of an affine fit over its surface: the lighting's gradient, not its texture) counts half
#: in the ambient solve
LOCAL_VARIATION = 0.1
#: plane samples the near-light fit uses per frame (a random subset, fixed per frame number)
NEAR_ROWS = 300
#: the near-light search on the anchor grid's neighbour differences (:func:`fit_near_light_gradient`):
#: residuals beyond this many robust sigmas (MAD) weigh less (Huber): the edges of the floor's texture
GRAD_HUBER = 1.5
#: neighbour pairs the coarse search scores per frame (a random subset; the refinement twice as many,
#: the final share all)
GRAD_PAIRS = 600
#: about this many of them give each candidate's robust sigma (every k-th pair)
GRAD_MAD_PAIRS = 256
#: a lamp found again moves only when its new place explains this much more of the differences
GRAD_KEEP = 0.01
#: fewer observed neighbour pairs than this on the grid: the value-domain search (:func:`fit_near_light`)
MIN_GRAD_PAIRS = 60
#: a lamp found in the gradient domain must explain at least this robust share of the grid's
#: differences (lamp scenes 0.39-0.60, rooms without a lamp near the object 0.02-0.04: eval suites)
GRAD_MIN_SHARE = 0.2


def _subsample(n: int, k: int, seed: int) -> np.ndarray:
    """Indices of at most ``k`` of ``n`` rows, deterministic per ``seed`` (replays are repeatable)."""
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def _bin_geometry() -> tuple[np.ndarray, np.ndarray]:
    """Centre directions (B, 3) and solid angles (B,) of the lat-long bins."""
    t0 = np.arange(ENV_THETA) * np.pi / ENV_THETA
    t1 = t0 + np.pi / ENV_THETA
    tc = 0.5 * (t0 + t1)
    pc = (np.arange(ENV_PHI) + 0.5) * 2 * np.pi / ENV_PHI - np.pi
    T, P = np.meshgrid(tc, pc, indexing="ij")
    dirs = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    omega = np.repeat((np.cos(t0) - np.cos(t1)) * 2 * np.pi / ENV_PHI, ENV_PHI)
    return dirs, omega


BIN_DIRS, BIN_OMEGA = _bin_geometry()


def bin_index(w: np.ndarray) -> np.ndarray:
    """Lat-long bin of unit directions (N, 3), object frame (+Y up)."""
    th = np.arccos(np.clip(w[:, 1], -1.0, 1.0))
    ph = np.arctan2(w[:, 2], w[:, 0])
    i = np.minimum((th * (ENV_THETA / np.pi)).astype(np.int64), ENV_THETA - 1)
    j = np.minimum(((ph + np.pi) * (ENV_PHI / (2 * np.pi))).astype(np.int64), ENV_PHI - 1)
    return i * ENV_PHI + j


@dataclass
class Samples:
    """One frame's pixel samples in the object frame."""

    radiance: np.ndarray  # (N, 3) scene-referred linear RGB
    direction: np.ndarray  # (N, 3) unit, from CENTRE towards the sample (object frame)
    position: np.ndarray | None  # (N, 3) object-frame point, NaN rows for distant samples
    plane: np.ndarray  # (N,) index into the frame's planes tuple, -1 when on none
    saturated: np.ndarray  # (N,) bool: some channel at the top of the range


def frame_samples(
    frame: Frame,
    anchor: Anchor,
    exposure_scale: float,
    planes: tuple,
    response_lut: np.ndarray | None = None,
    stride: int = 2,
) -> Samples:
    """Pixel samples on the planes' depth-cloud grid (every ``stride``-th cloud point).

    The cloud grid is the one :class:`~illuminet.runtime.stages.planes.PlaneStage` fitted planes on
    (``Plane.cloud_stride`` depth pixels per cloud point), so plane membership comes for free.
    """
    depth = frame.depth
    H, W = frame.color.shape[:2]
    if depth is None:
        cs = max(1, int(round(W / 160)))
        dH, dW = H, W
    else:
        dH, dW = depth.shape[:2]
        cs = next((p.cloud_stride for p in planes if getattr(p, "cloud_stride", 0)), max(1, int(round(dW / 160))))
    s = cs * stride
    vv, uu = np.mgrid[0:dH:s, 0:dW:s]
    sy, sx = H / dH, W / dW
    cu = np.minimum((uu * sx).astype(np.int64), W - 1)
    cv = np.minimum((vv * sy).astype(np.int64), H - 1)
    lin = linearize(frame.color[cv, cu], response_lut).reshape(-1, 3).astype(np.float64)
    sat = (frame.color[cv, cu].reshape(-1, 3) >= 250).any(1)
    intr = frame.intrinsics
    if (intr.width, intr.height) != (W, H):
        intr = intr.scaled(W, H)
    x = ((uu * sx).ravel() - intr.cx) / intr.fx
    y = ((vv * sy).ravel() - intr.cy) / intr.fy
    rays = np.stack([x, y, np.ones_like(x)], 1)
    if depth is not None:
        z = np.asarray(depth[vv, uu], np.float64).ravel()
        if depth.dtype == np.uint16:
            z = z * 0.001
    else:
        z = np.zeros(len(x))
    near = np.isfinite(z) & (z > 0.05) & (z < FAR_M)
    R, t = anchor.R, anchor.t
    pts = (rays * np.where(near, z, 0.0)[:, None] - t) @ R  # object frame
    pts[~near] = np.nan
    w = np.where(near[:, None], pts - CENTRE, rays @ R)
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)
    plane_idx = np.full(len(x), -1, np.int64)
    if depth is not None:
        ci, cj = (vv // cs).ravel(), (uu // cs).ravel()
        for k, p in enumerate(planes):
            m = getattr(p, "cloud_mask", None)
            if m is None:
                continue
            ok = (ci < m.shape[0]) & (cj < m.shape[1])
            on = np.zeros(len(x), bool)
            on[ok] = m[ci[ok], cj[ok]]
            plane_idx[on & near] = k
    return Samples(radiance=lin / max(exposure_scale, 1e-12), direction=w, position=pts, plane=plane_idx, saturated=sat)


#: a bin seen again this far from its fused luminance (relative) has changed; more than half the bins
#: seen again at once (and at least ``LIGHT_CHANGE_MIN_BINS``) means the light changed
LIGHT_CHANGE_REL = 0.35
LIGHT_CHANGE_MIN_BINS = 8


def light_changed(new_lum: np.ndarray, old_lum: np.ndarray) -> bool:
    """Whether the luminances of the bins seen again moved together: more than half of them by more than
    :data:`LIGHT_CHANGE_REL` (the plane light's rule for its cells, ``OUTLIER_REL``)."""
    if len(new_lum) < LIGHT_CHANGE_MIN_BINS:
        return False
    rel = np.abs(new_lum - old_lum) / np.maximum(old_lum, 1e-9)
    return int((rel > LIGHT_CHANGE_REL).sum()) > 0.5 * len(new_lum)


class EnvMap:
    """Radiance per lat-long bin, fused over frames (object frame, so world-locked)."""

    def __init__(self, keep: float = 0.9) -> None:
        self.keep = keep
        self.light_changes = 0  # updates whose bins in view took the new value (light_changed)
        self.reset()

    def reset(self) -> None:
        n = ENV_THETA * ENV_PHI
        self.radiance = np.zeros((n, 3))
        self.weight = np.zeros(n)
        self.saturated = np.zeros(n)

    def update(self, s: Samples) -> None:
        idx = bin_index(s.direction)
        n = ENV_THETA * ENV_PHI
        cnt = np.bincount(idx, minlength=n).astype(np.float64)
        tot = np.stack([np.bincount(idx, s.radiance[:, c], minlength=n) for c in range(3)], 1)
        sat = np.bincount(idx, s.saturated.astype(np.float64), minlength=n)
        seen = cnt > 0
        mean = tot[seen] / cnt[seen, None]
        # a bin seen now is mostly this frame's value (lights change); unseen bins keep their memory
        old = self.weight[seen] > 0
        if light_changed(mean[old] @ LUMA, self.radiance[seen][old] @ LUMA):
            # the light was switched (most of the bins in view moved at once, the plane light's rule for its
            # cells): the bins in view take this frame's value; with keep per update a switched-off room
            # stayed lit in the map for seconds (0.9 ** 5 = 59 % of the old light 0.5 s later)
            self.light_changes += 1
            old = np.zeros_like(old)
        a = np.where(old, self.keep, 0.0)[:, None]
        self.radiance[seen] = a * self.radiance[seen] + (1 - a) * mean
        self.saturated[seen] = a[:, 0] * self.saturated[seen] + (1 - a[:, 0]) * (sat[seen] / cnt[seen])
        self.weight[seen] = np.minimum(self.weight[seen] + cnt[seen], 50.0)

    @property
    def seen(self) -> np.ndarray:
        return self.weight > 0

    def coverage(self) -> float:
        return float(BIN_OMEGA[self.seen].sum() / (4 * np.pi))


def _near_basis(pos: np.ndarray, x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """cos / r^2 of point lights at ``pos`` (C, 3) seen from points ``x`` (K, 3) with normals ``n``: (C, K).

    ``|p - x|^2 = |p|^2 - 2 p.x + |x|^2`` and ``n.(p - x) = p.n - x.n``: two (C, 3) x (3, K) products
    instead of (C, K, 3) differences (the coarse near-light search scores ~100 positions a frame)."""
    pos = np.asarray(pos)
    xx = np.einsum("kx,kx->k", x, x)
    xn = np.einsum("kx,kx->k", x, n)
    r2 = (pos * pos).sum(1)[:, None] - 2.0 * (pos @ x.T)
    r2 += xx[None, :]
    np.maximum(r2, 1e-4, out=r2)
    cos = pos @ n.T
    cos -= xn[None, :]
    np.maximum(cos, 0.0, out=cos)
    cos /= r2 * np.sqrt(r2)
    return cos


def _centred(v: np.ndarray, groups: np.ndarray, w: np.ndarray, G: int) -> np.ndarray:
    """Subtract each group's weighted mean along the last axis."""
    sw = np.maximum(np.bincount(groups, w, minlength=G), 1e-12)
    if v.ndim == 1:
        m = np.bincount(groups, v * w, minlength=G) / sw
        return v - m[groups]
    # all rows at once: the weighted group sums are one product with the (K, G) weighted one-hot matrix
    onehot = np.zeros((len(groups), G), v.dtype)
    onehot[np.arange(len(groups)), groups] = w
    m = (v @ onehot) / sw.astype(v.dtype)
    return v - m[:, groups]


@dataclass
class NearFit:
    position: np.ndarray
    r2: float  # share of the planes' spatial variation the lamp explains
    slope: np.ndarray  # (3,) RGB intensity (irradiance * m^2) of the lamp
    intercepts: np.ndarray  # (G, 3) per-plane ambient irradiance


def _shares(
    cands: np.ndarray,
    x: np.ndarray,
    n: np.ndarray,
    w: np.ndarray,
    groups: np.ndarray,
    G: int,
    oc: np.ndarray,
    var: float,
) -> np.ndarray:
    """Share of the planes' centred luminance ``oc`` (weighted variance ``var``) that point lights at
    ``cands`` (C, 3) explain, each alone with one slope (0 where the slope would be negative)."""
    gc = _centred(_near_basis(cands, x, n), groups, w, G)
    num = gc @ (w * oc)
    den = (gc * gc) @ w
    return np.where((num > 0) & (den > 1e-12), num * num / np.maximum(den, 1e-12) / var, 0.0)


def explained_share(
    pos: np.ndarray, x: np.ndarray, n: np.ndarray, e: np.ndarray, w: np.ndarray, groups: np.ndarray
) -> float:
    """Share of the planes' spatial variation (within each plane) a lamp at ``pos`` explains (0-1)."""
    if len(x) < 8:
        return 0.0
    G = int(groups.max()) + 1
    oc = _centred(e @ LUMA, groups, w, G)
    var = float((w * oc * oc).sum())
    if var <= 1e-12:
        return 0.0
    return float(_shares(np.asarray(pos, np.float64)[None], x, n, w, groups, G, oc, var)[0])


def fit_near_light(
    x: np.ndarray, n: np.ndarray, e: np.ndarray, w: np.ndarray, groups: np.ndarray, seeds: np.ndarray
) -> NearFit | None:
    """Point light explaining the spatial variation of plane irradiance (see module docstring).

    Parameters
    ----------
    x, n : (K, 3) sample positions and normals (object frame); e : (K, 3) RGB irradiance;
    w : (K,) weights; groups : (K,) plane index per sample;
    seeds : (S, 3) candidate positions to start from (a slice of the coarse grid and the last answer):
        the best of them is refined locally (3x3x3 steps, halved twice).
    """
    G = int(groups.max()) + 1 if len(groups) else 0
    if len(x) < 30 or len(seeds) == 0:
        return None
    x = x.astype(np.float32)
    n = n.astype(np.float32)
    lum = (e @ LUMA).astype(np.float32)
    w = w.astype(np.float32)
    oc = _centred(lum, groups, w, G)
    var = float((w * oc * oc).sum())
    if var <= 1e-12:
        return None

    def score(cands: np.ndarray) -> np.ndarray:
        return _shares(cands.astype(np.float32), x, n, w, groups, G, oc, var)

    r2 = score(seeds)
    best = seeds[np.argsort(r2)[-2:]]
    step = np.array([0.1, 0.1, 0.1])
    offs = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * 3), indexing="ij"), -1).reshape(-1, 3)
    for _ in range(2):
        cands = (best[:, None, :] + (offs * step)[None]).reshape(-1, 3)
        cands[:, 1] = np.maximum(cands[:, 1], 0.05)
        r2 = score(cands)
        best = cands[np.argsort(r2)[-1:]]
        step = step / 2
    p = best[-1].astype(np.float64)
    r2 = float(score(best[-1:])[0])
    g = _near_basis(p[None], x.astype(np.float64), n.astype(np.float64))[0]
    w64 = w.astype(np.float64)
    gc = _centred(g, groups, w64, G)
    den = max(float((w64 * gc * gc).sum()), 1e-12)
    slope = np.array([(w64 * gc * _centred(e[:, c], groups, w64, G)).sum() / den for c in range(3)])
    sw = np.maximum(np.bincount(groups, w64, minlength=G), 1e-12)
    inter = np.stack([np.bincount(groups, w64 * (e[:, c] - slope[c] * g), minlength=G) / sw for c in range(3)], 1)
    return NearFit(position=p, r2=r2, slope=slope, intercepts=inter)


def grid_pairs(mask: np.ndarray, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (a, b) of the 4-neighbour cell pairs of a ``grid x grid`` row-major grid both observed."""
    idx = np.arange(grid * grid).reshape(grid, grid)
    a = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    b = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    ok = mask[a] & mask[b]
    return a[ok], b[ok]


def _gradient_shares(
    cands: np.ndarray,
    x: np.ndarray,
    n: np.ndarray,
    dl: np.ndarray,
    pa: np.ndarray,
    pb: np.ndarray,
    iters: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust share (C,) of the neighbour differences ``dl`` (luminance at ``pb`` minus at ``pa``) that
    point lights at ``cands`` (C, 3) explain, each with its own slope (C,); 0 for a negative slope.
    ``iters`` Huber reweightings (:data:`GRAD_HUBER` robust sigmas)."""
    # the basis at the cells these pairs use only (a subsample's pairs touch a fraction of the grid);
    # the cells' new indices by a mark and a running count (np.unique sorted them: ~1 ms an estimate)
    mark = np.zeros(len(x), bool)
    mark[pa] = True
    mark[pb] = True
    used = np.flatnonzero(mark)
    slot = np.cumsum(mark) - 1
    g = _near_basis(cands, x[used], n[used])
    dg = g[:, slot[pb]] - g[:, slot[pa]]
    w = np.ones_like(dg)
    for it in range(iters + 1):
        wdg = w * dg
        s = (wdg @ dl) / np.maximum((wdg * dg).sum(1), 1e-12)
        r = dl[None, :] - s[:, None] * dg
        if it < iters:
            # the robust sigma (MAD) from every few pairs: a median over all of them cost half the fit
            step = max(1, r.shape[1] // GRAD_MAD_PAIRS)
            ar = np.abs(r)
            k = GRAD_HUBER * 1.4826 * np.median(ar[:, ::step], axis=1, keepdims=True)
            w = np.minimum(1.0, k / np.maximum(ar, 1e-12))
    share = 1.0 - (w * r * r).sum(1) / np.maximum((w * dl[None, :] ** 2).sum(1), 1e-12)
    return np.where(s > 0, np.maximum(share, 0.0), 0.0), s


def fit_near_light_gradient(
    x: np.ndarray,
    n: np.ndarray,
    e: np.ndarray,
    pa: np.ndarray,
    pb: np.ndarray,
    seeds: np.ndarray,
    seed: int = 0,
    keep: NearFit | None = None,
) -> NearFit | None:
    """Point light explaining the anchor grid's *differences* between neighbouring cells.

    The floor's albedo texture multiplies the light: fitted through the cells' values, a lamp's
    falloff comes out too flat and the lamp too high (eval lamp suite: 0.2 m at the median, up to
    0.8 m; docs/eval.md). In differences the ambient (a constant) drops out, the texture's edges (planks,
    tiles, a rug's border) are a few large differences, which the Huber weights set aside, and the
    lamp's smooth falloff is what remains (Retinex's split of edges and shading, with the falloff's
    shape as the shading). ``x, n`` (P, 3) are the grid's cells, ``e`` (P, 3) their RGB irradiance,
    ``pa, pb`` the observed neighbour pairs (:func:`grid_pairs`). The coarse search scores ``seeds`` on
    :data:`GRAD_PAIRS` pairs with one reweighting; the best is refined locally (3x3x3 steps, halved
    twice) on twice as many pairs with two. ``r2`` is the robust share explained, over every pair.
    (About 4 ms an estimate on this machine; the whole grid of seeds, after a placement, ~22 ms.)

    ``keep``: the lamp found before; it is returned (with its share now) unless the new place explains
    at least :data:`GRAD_KEEP` more. Each estimate's search moves a lamp by a step or two, which turned
    the shadow by a degree and redrew its map (~9 ms on llvmpipe) 6x as often.
    """
    if len(pa) < MIN_GRAD_PAIRS or len(seeds) == 0:
        return None
    x32, n32 = x.astype(np.float32), n.astype(np.float32)
    lum = (e @ LUMA).astype(np.float32)
    dl = lum[pb] - lum[pa]
    if float(np.abs(dl).max()) <= 1e-12:
        return None
    sub = _subsample(len(pa), GRAD_PAIRS, seed)
    r2, _ = _gradient_shares(seeds.astype(np.float32), x32, n32, dl[sub], pa[sub], pb[sub], 1)
    best = seeds[np.argsort(r2)[-1:]]
    if keep is None and float(r2.max()) < 0.5 * GRAD_MIN_SHARE:
        # nothing near a lamp among these seeds (a room lit from afar): not worth refining (~3 ms)
        return NearFit(
            position=best[-1].astype(np.float64), r2=float(r2.max()), slope=np.zeros(3), intercepts=np.zeros((1, 3))
        )
    # a lamp still best among the coarse seeds is being tracked: it was refined to a 5 cm step before,
    # so only the fine step is searched around it (one round of 27 positions, ~1.5 ms an estimate, not
    # two); a lamp that moved farther than that is found by the seeds again, with both rounds
    tracking = keep is not None and bool(np.all(best[-1] == keep.position))
    step = np.full(3, 0.05 if tracking else 0.1)
    offs = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * 3), indexing="ij"), -1).reshape(-1, 3)
    ref = _subsample(len(pa), 2 * GRAD_PAIRS, seed + 1)
    for _ in range(1 if tracking else 2):
        cands = (best[:, None, :] + (offs * step)[None]).reshape(-1, 3)
        cands[:, 1] = np.maximum(cands[:, 1], 0.05)
        r2, _ = _gradient_shares(cands.astype(np.float32), x32, n32, dl[ref], pa[ref], pb[ref], 2)
        best = cands[np.argsort(r2)[-1:]]
        step = step / 2
    p = best[-1].astype(np.float64)
    if keep is not None:
        kept = float(_gradient_shares(keep.position[None].astype(np.float32), x32, n32, dl, pa, pb, 2)[0][0])
        if np.all(best[-1] == keep.position):  # the fine step kept it where it was
            return dataclasses.replace(keep, r2=kept)
    r2, _ = _gradient_shares(best[-1:].astype(np.float32), x32, n32, dl, pa, pb, 2)
    if keep is not None and float(r2[0]) < kept + GRAD_KEEP:
        return dataclasses.replace(keep, r2=kept)
    # the slope and the ambient (the intercept) per colour channel, from the cells' values at p
    g = _near_basis(p[None], x.astype(np.float64), n.astype(np.float64))[0]
    X = np.c_[g, np.ones(len(g))]
    coef, *_ = np.linalg.lstsq(X, e.astype(np.float64), rcond=None)
    return NearFit(position=p, r2=float(r2[0]), slope=coef[0], intercepts=coef[1:2])


#: directions where the ambient radiance must not be negative (the lat-long bin centres)
_NONNEG_Y = sh9(BIN_DIRS)
#: passes of the non-negativity active set (each adds the directions still negative)
NONNEG_PASSES = 4


def _solve_nonnegative(G: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Least squares (normal equations ``G x = rhs``, one column of ``rhs`` per colour channel) with the
    ambient radiance (the first 9 unknowns, SH) kept non-negative in every direction and the primary's
    irradiance (a 10th unknown, when present) non-negative.

    Light is never negative, but a least-squares split between a primary light and the ambient SH is
    free to trade one against the other where the observations cannot tell them apart (a floor seen
    alone sees both from above): it then "pays" for a too-strong primary with negative ambient light
    from the sky. A few active-set passes add a stiff penalty towards zero at the directions (and on
    the primary) that came out negative, per channel.
    """
    sol = np.linalg.solve(G, rhs)
    ncol = G.shape[0]
    stiff = 1e3 * (np.trace(G) / ncol + 1e-12)
    for c in range(rhs.shape[1]):
        x = sol[:, c]
        active = np.zeros(len(_NONNEG_Y), bool)
        neg_p = False
        for _ in range(NONNEG_PASSES):
            vals = _NONNEG_Y @ x[:9]
            new = (vals < 0) & ~active
            new_p = ncol > 9 and x[9] < 0 and not neg_p
            if not new.any() and not new_p:
                break
            active |= new
            neg_p |= new_p
            Yc = _NONNEG_Y[active]
            Gc = G.copy()
            Gc[:9, :9] += stiff / len(_NONNEG_Y) * (Yc.T @ Yc)
            if neg_p:
                Gc[9, 9] += stiff
            x = np.linalg.solve(Gc, rhs[:, c])
        sol[:, c] = x
    return sol


def _plane_basis(xs: np.ndarray, ns: np.ndarray, primary_dir, primary_pos) -> np.ndarray:
    """The plane rows' irradiance per unknown of the solve, (N, 9 or 10): the 9 ambient radiance SH
    coefficients (cosine-convolved), then, with a primary light, its irradiance (a near lamp's falloff
    scaled to 1 at the object, else the cosine of a distant light)."""
    A = np.zeros((len(xs), 9 if primary_dir is None else 10))
    A[:, :9] = sh9(ns) * SH_A_HAT[None, :]
    if primary_dir is not None:
        if primary_pos is not None:
            A[:, 9] = _near_basis(primary_pos[None], xs, ns)[0] * float(np.sum((primary_pos - CENTRE) ** 2))
        else:
            A[:, 9] = np.maximum(ns @ primary_dir, 0.0)
    return A


def _sh_extract_primary(L_rad: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Direction of the luminance gradient of radiance SH and how directional the light is (0-1)."""
    lum = L_rad @ LUMA
    d = np.array([lum[3], lum[1], lum[2]])  # (x, y, z) from Y11, Y1-1, Y10
    nd = float(np.linalg.norm(d))
    if nd <= 1e-12 or lum[0] <= 1e-12:
        return None, 0.0
    # a single direction gives |L1| / L0 = 0.4886 / 0.2821 = sqrt(3); uniform light gives 0
    return d / nd, float(np.clip(nd / lum[0] / math.sqrt(3.0), 0.0, 1.0))


class LightEstimateStage(Stage):
    """Estimates the room's lighting at the anchor every frame; writes ``results["light"]``.

    Parameters
    ----------
    cfg : Config
        ``[light]`` (cues on/off, filter) and ``[plane_light] assumed_albedo``.
    response_lut : (256, 3) array, optional
        Camera response (else sRGB), as the plane light stage uses.
    """

    name = "light"
    requires = (ANCHOR, PLANE_LIGHT)
    optional = (PLANES, ODOMETRY)
    provides = (LIGHT,)

    def __init__(self, cfg, response_lut: np.ndarray | None = None) -> None:
        c = cfg.light
        self.use_env, self.use_planes, self.use_near = bool(c.environment), bool(c.planes), bool(c.near_light)
        self.use_emitters, self.use_shadows = bool(c.emitters), bool(c.shadows)
        self.tau = float(c.time_constant_s)
        self.search_every = max(1, int(c.search_every))
        self.near_gradient = bool(c.near_gradient)
        self.lam = float(c.smoothness)
        self.unseen_w = float(c.unseen_illuminant)
        self.emitter_measured = bool(c.emitter_measured)
        self._emitter_seen = (np.zeros(3), 0.0)  # what the map measured of the last emitter (_emitter)
        self.albedo = float(cfg.plane_light.assumed_albedo)
        if not 0 < self.albedo <= 1:
            raise ValueError(f"[plane_light] assumed_albedo: expected a number in (0, 1], got {self.albedo!r}")
        self.lut = response_lut
        self.env = EnvMap()
        self._shadows = ShadowTracker()
        self._first_search = True
        self.last_shadow = None
        self._warn = LogOnce(log, "light")
        self._near: NearFit | None = None
        self._near_grad = False  # whether _near came from the grid's differences (its r2 is theirs)
        self._near_src = -1  # which of _grid_cells' grids it came from
        self._shadow_prior: np.ndarray | None = None
        self._state: dict[str, Any] | None = None
        self._t_prev: int | None = None
        self._anchor_T: np.ndarray | None = None
        self.frames = 0
        self.skipped = 0
        self.ms: list[float] = []
        self.cpu_s = 0.0  # thread CPU time of every estimate
        self.worker_cpu_s = 0.0  # of those computed on the worker thread (pipelined)
        rate = float(c.rate_hz)
        self.period_ns = int(1e9 / rate) if rate > 0 else 0
        self._last: LightEstimate | None = None
        self._t_est: int | None = None
        self.pipelined = bool(c.pipelined)
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: concurrent.futures.Future | None = None

    # ------------------------------------------------------------------ per frame

    def open(self) -> None:
        if self.pipelined and self._pool is None:
            self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=WORKER_NAME)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._pending = None

    def process(self, frame: Frame) -> Frame:
        """Schedule (``[light] rate_hz``) and, when ``pipelined``, overlap the estimate with the loop.

        An update is due when ``1 / rate_hz`` has passed in the frames' own timestamps (so a replay
        gives the same estimates however fast it runs). Pipelined, the estimate computed from the
        frame of one update is collected at the next update (one period later: 0.1 s at 10 Hz) while
        a worker thread computes the next one; the output is the same whatever the machine's speed.
        Frames in between reuse the last estimate with their own anchor pose.
        """
        anchor: Anchor = self.require(frame, ANCHOR)
        pl: PlaneLight = self.require(frame, PLANE_LIGHT)
        t = frame.t_device_ns or frame.t_host_ns
        due = (
            self._last is None
            or self.period_ns <= 0
            or t is None
            or self._t_est is None
            or not 0 <= t - self._t_est < self.period_ns
            or self._moved(anchor)
        )
        if due:
            self._t_est = t
            if self._pending is not None:
                self._last = self._pending.result()
                self._pending = None
            if self._pool is not None and self._last is not None and not self._moved(anchor):
                self._pending = self._pool.submit(self._estimate, frame, anchor, pl)
            else:  # first estimate, a re-placed anchor, or not pipelined: compute now
                self._last = self._estimate(frame, anchor, pl)
        else:
            self.skipped += 1
        est = (
            self._last
            if self._last.T_cam_obj is anchor.T_cam_obj
            else dataclasses.replace(self._last, T_cam_obj=anchor.T_cam_obj)
        )
        return frame.with_result(LIGHT, est)

    def _estimate(self, frame: Frame, anchor: Anchor, pl: PlaneLight) -> LightEstimate:
        """One estimate from one frame (the body of the stage; runs on the worker when pipelined)."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        planes = tuple(frame.results.get(PLANES.name, ()))
        self._maybe_reset(anchor, frame)
        scale = float(pl.exposure_scale) if pl.exposure_scale and pl.exposure_scale > 0 else 1.0
        s = frame_samples(frame, anchor, scale, planes, self.lut)
        if self.use_env and not anchor.synthetic:
            self.env.update(s)
        illum = self._illuminant(s)
        xs, ns, es, ws, gs, labels, beyond = self._plane_rows(pl, s, planes, anchor, illum)
        cues: list[str] = []
        primary_dir = primary_pos = None
        near = None
        local_share = None
        if self.use_near and len(xs):
            # the coarse search is spread over search_every frames (a lamp is fixed in the world), and
            # the last answer is refined every frame; at most NEAR_ROWS samples keep it cheap.
            k = self.frames % self.search_every
            # the coarse grid, spread over search_every frames; whole on the first estimate after a
            # placement, so a lamp is found at once rather than a third of a second later
            seeds = NEAR_GRID if self._first_search else NEAR_GRID[k :: self.search_every]
            self._first_search = False
            if self._near is not None:
                seeds = np.concatenate([seeds, self._near.position[None]])
            # a lamp near the object first, from the grid's differences (robust to the floor's texture);
            # when none explains them, a light farther away (a room's ceiling light 1.5-2 m off, whose
            # falloff the 1 m grid barely shows) from the values of the grid, the floor out to 1.5 m and
            # the walls
            grids = self._grid_cells(pl) if self.near_gradient else []
            last_grad = self._near if self._near_grad else None
            last_vals = None if self._near_grad else self._near
            grad = False
            for gi, (x_, n_, e_, pa_, pb_) in enumerate(grids):
                # the wider context grid first (a lamp's whole pool); the grid around the object when
                # the lamp found there does not explain the light near the object (another lamp's pool)
                keep = last_grad if self._near_src == gi else None
                cand = fit_near_light_gradient(x_, n_, e_, pa_, pb_, seeds, self.frames, keep=keep)
                if keep is not None and cand is not None and cand.r2 < keep.r2 - 0.2:
                    cand = fit_near_light_gradient(x_, n_, e_, pa_, pb_, keep.position[None], self.frames, keep=keep)
                if cand is None or cand.r2 < GRAD_MIN_SHARE:
                    continue
                share = None
                if gi + 1 < len(grids):
                    share = self._local_share(cand, xs, ns, es, ws, gs, beyond, GRAD_MIN_SHARE)
                    if share < LOCAL_R2_MIN:
                        continue
                near, grad, self._near_src, local_share = cand, True, gi, share
                break
            if near is None:
                sub = _subsample(len(xs), NEAR_ROWS, self.frames)
                near = fit_near_light(xs[sub], ns[sub], es[sub], ws[sub], gs[sub], seeds)
                if last_vals is not None and near is not None and near.r2 < last_vals.r2 - 0.2:
                    near = fit_near_light(xs[sub], ns[sub], es[sub], ws[sub], gs[sub], last_vals.position[None])
            min_r2 = GRAD_MIN_SHARE if grad else 0.5
            self._near = near if (near is not None and near.r2 >= min(0.3, min_r2)) else None
            self._near_grad = grad
        # how much of the planes' spatial variation near the object the lamp explains (its values, the far
        # floor left out): the acceptance test, and the confidence in its position (already known for a
        # lamp from the context grid, which had to pass it)
        if near is None:
            local_share = 0.0
        elif local_share is None:
            local_share = self._local_share(near, xs, ns, es, ws, gs, beyond, min_r2)
        if local_share >= LOCAL_R2_MIN:
            primary_pos = near.position
            v = near.position - CENTRE
            primary_dir = v / np.linalg.norm(v)
            cues.append("near_light")
        shadow = None
        if primary_dir is None and self.use_shadows:
            shadow = self._shadow_cue(frame, anchor, planes)
            if shadow is not None:
                primary_dir = shadow[0]
                cues.append("shadow")
        emitters = 0
        if primary_dir is None and self.use_emitters:
            d, emitters = self._emitter()
            if d is not None:
                primary_dir = d
                cues.append("emitter")
        # the floor beyond the grid is lit by other lamps' pools too: it counts less the farther it is
        if len(xs):
            r2 = xs[:, 0] ** 2 + xs[:, 2] ** 2
            ws = np.where(beyond, ws * np.exp(-0.5 * r2 / FLOOR_SIGMA_M**2), ws)
            # ... and, together, at most FLOOR_WEIGHT_MAX of the grid it extends: the patch under the
            # object is the evidence, the far floor context (uncapped, its many rows moved the outdoor
            # light colour from 2.7 to 4.0 deg off, cause not isolated; 2.8 with the cap: 11 scenes)
            wb, wg = float(ws[beyond].sum()), float(ws[~beyond & (gs == 0)].sum())
            if wb > FLOOR_WEIGHT_MAX * wg:
                ws = np.where(beyond, ws * (FLOOR_WEIGHT_MAX * wg / max(wb, 1e-12)), ws)
            ws = self._distant_weight(xs, es, ws, gs)
        L_rad, E_p = self._solve(xs, ns, es, ws, primary_dir, primary_pos, illum)
        if cues and cues[-1] == "emitter" and self.emitter_measured:
            L_rad, E_p = self._solve(
                xs, ns, es, ws, primary_dir, None, illum, primary_rgb=self._emitter_rgb(E_p, illum)
            )
        conf_dir = 0.0
        if primary_dir is None:
            d, directional = _sh_extract_primary(L_rad)
            if d is not None and directional > 0.25:
                # move the directional part of the ambient into a primary light (it casts the shadow)
                primary_dir = d
                cues.append("sh_gradient")
                L_rad, E_p = self._solve(xs, ns, es, ws, primary_dir, None, illum)
                conf_dir = 0.5 * directional
        else:
            conf_dir = {
                "near_light": min(1.0, local_share),
                "shadow": shadow[1] if shadow else 0.0,
                "emitter": 0.6,
            }.get(cues[0], 0.5)
        if primary_dir is not None and float(E_p @ LUMA) <= 0:
            primary_dir, primary_pos, E_p, conf_dir = None, None, np.zeros(3), 0.0
        if self.use_planes:
            k = self._albedo_bound(xs, ns, es, gs, L_rad, E_p, primary_dir, primary_pos)
            L_rad, E_p = L_rad * k, E_p * k
        raw = {"sh9": L_rad * SH_A_HAT[:, None], "dir": primary_dir, "rgb": E_p, "pos": primary_pos}
        filt = self._filter(raw, frame)
        obs = {
            "planes": len(set(labels)),
            "plane_labels": sorted(set(labels)),
            "shadow": None if shadow is None else round(float(shadow[1]), 3),
            "env_coverage": round(self.env.coverage(), 3),
            "emitters": int(emitters),
            "cues": cues,
        }
        n_rows = len(xs)
        est = LightEstimate(
            sh9=filt["sh9"].astype(np.float32),
            primary_dir=None if filt["dir"] is None else filt["dir"].astype(np.float32),
            primary_rgb=np.asarray(filt["rgb"], np.float32),
            primary_pos=None if filt["pos"] is None else np.asarray(filt["pos"], np.float32),
            confidence={
                "ambient": float(np.clip(0.3 + 0.7 * self.env.coverage() + 0.1 * (n_rows > 100), 0, 1)),
                "direction": float(conf_dir),
                "intensity": float(0.7 * conf_dir),
                "colour": float(np.clip(0.4 + 0.6 * self.env.coverage() * 2, 0, 1)),
                "position": float(local_share) if primary_pos is not None else 0.0,
            },
            observed=obs,
            exposure_scale=scale,
            method="scene",
            T_cam_obj=anchor.T_cam_obj,
        )
        self.frames += 1
        self.ms.append((time.perf_counter() - t0) * 1e3)
        c = time.thread_time() - c0
        self.cpu_s += c
        if threading.current_thread().name.startswith(WORKER_NAME):
            self.worker_cpu_s += c
        if len(self.ms) > 2000:
            del self.ms[:1000]
        return est

    # ------------------------------------------------------------------ pieces

    @staticmethod
    def _plausible(near: NearFit, es: np.ndarray, gs: np.ndarray, min_r2: float = 0.5) -> bool:
        """A lamp, not texture or vignetting: most of the variation explained (``min_r2``: 0.5 of the
        values, :data:`GRAD_MIN_SHARE` of the differences), a falloff worth measuring (>= 8 % of the
        mean), the lamp above the object's horizon and within 3 m."""
        v = near.position - CENTRE
        r = float(np.linalg.norm(v))
        lum = es @ LUMA
        spread = float(np.std(lum) / max(float(np.mean(lum)), 1e-12))
        return near.r2 >= min_r2 and spread >= 0.08 and r < 3.0 and v[1] / max(r, 1e-12) > 0.17

    @classmethod
    def _local_share(cls, near, xs, ns, es, ws, gs, beyond, min_r2: float) -> float:
        """The share of the planes' spatial variation near the object (``~beyond``) that the lamp
        explains in values; 0 when it is not a plausible lamp (:meth:`_plausible`)."""
        if not cls._plausible(near, es, gs, min_r2):
            return 0.0
        m = ~beyond
        return explained_share(near.position, xs[m], ns[m], es[m], ws[m], gs[m])

    def _moved(self, anchor: Anchor) -> bool:
        """The anchor jumped (re-placed) since the last estimate: do not reuse it."""
        T = self._last.T_cam_obj if self._last is not None else None
        return T is None or float(np.linalg.norm(np.asarray(T)[:3, 3] - anchor.t)) > 0.3

    def _maybe_reset(self, anchor: Anchor, frame: Frame) -> None:
        """A new placement (the anchor jumped in the world) starts the map and the filter again."""
        odo = frame.results.get(ODOMETRY.name)
        T = anchor.T_cam_obj
        if odo is not None and getattr(odo, "T_cam_world", None) is not None:
            T = np.linalg.inv(odo.T_cam_world) @ T  # world pose of the object: fixed while locked
        if self._anchor_T is not None and odo is not None:
            if np.linalg.norm(T[:3, 3] - self._anchor_T[:3, 3]) > 0.15:
                self.env.reset()
                self._state = None
                self._near = None
                self._shadows.reset()
                self._first_search = True
        elif self._anchor_T is not None and odo is None:
            # camera-locked anchor: the object frame moves with the camera; keep the map short-lived
            self.env.keep = 0.5
        self._anchor_T = T

    def _illuminant(self, s: Samples) -> np.ndarray:
        """Scene illuminant chroma (unit luminance RGB): grey world over the pixels that could be a grey
        surface under a real illuminant.

        Real illuminants lie near the Planckian locus (warm to cool, little green or magenta), a line
        in log chromaticity (log R/G, log B/G); a pixel's log chromaticity is its surface's plus the
        illuminant's, so a pixel far off that line (grass, brick, a purple carpet) belongs to a
        coloured surface whatever the light, and says nothing about the light's colour. The pixels
        within :data:`LOCUS_SIGMA` of the line vote (grey world among them, one vote per surface: a
        tracked plane, or the pixels on none), the answer is moved onto
        the line, and it is shrunk towards neutral (D65) by how few pixels voted: a view of a green
        lawn and a brick wall gives daylight, not a yellow light.
        """
        keep = np.isfinite(s.position[:, 0]) & ~s.saturated
        rad = s.radiance[keep]
        grp = s.plane[keep]
        ok = (rad > 1e-9).all(1)
        rad, grp = rad[ok], grp[ok]
        if len(rad) < 20:
            return np.ones(3)
        uv = np.log(rad[:, [0, 2]] / rad[:, 1:2])
        off = uv @ LOCUS_NORMAL
        w = np.exp(-((off / LOCUS_SIGMA) ** 2))
        evidence = float(w.mean())
        # grey world over surfaces, not pixels: each plane (and the pixels on no plane, together)
        # votes once with its mean chroma, so a large, bright wood floor in a lamp's pool does not
        # outvote the walls (wood is orange, on the locus: pixel-weighted it read as a warmer light)
        votes = []
        for gi in np.unique(grp):
            sel = grp == gi
            wsum = float(w[sel].sum())
            if wsum < SURFACE_MIN_VOTES:
                continue
            mg = (w[sel, None] * rad[sel]).sum(0) / wsum
            lg = float(mg @ LUMA)
            if lg > 1e-12:
                votes.append(mg / lg)
        m = np.mean(votes, axis=0) if votes else (w[:, None] * rad).sum(0) / max(float(w.sum()), 1e-12)
        if not np.all(m > 1e-12):
            return np.ones(3)
        uv_m = np.log(m[[0, 2]] / m[1])
        uv_m = uv_m - (uv_m @ LOCUS_NORMAL) * LOCUS_NORMAL  # onto the locus
        uv_m *= evidence / (evidence + LOCUS_PRIOR)  # few voters: towards neutral
        c = np.array([np.exp(uv_m[0]), 1.0, np.exp(uv_m[1])])
        return c / float(c @ LUMA)

    def _plane_rows(self, pl: PlaneLight, s: Samples, planes: tuple, anchor: Anchor, illum: np.ndarray):
        """Plane irradiance observations: positions, normals, RGB irradiance, weights, plane groups."""
        xs, ns, es, ws, gs, labels, bs = [], [], [], [], [], [], []
        if not self.use_planes and not self.use_near:
            z3 = np.zeros((0, 3))
            return z3, z3, z3, np.zeros(0), np.zeros(0, np.int64), labels, np.zeros(0, bool)
        g = 0
        slices = pl.plane_slices or (slice(0, len(pl.irradiance)),)
        for k, sl in enumerate(slices):
            m = np.asarray(pl.mask[sl], bool)
            if m.sum() < 8:
                continue
            e = np.asarray(pl.irradiance[sl], np.float64)[m]
            xs.append(np.asarray(pl.vertices[sl], np.float64)[m])
            ns.append(np.asarray(pl.normals[sl], np.float64)[m])
            es.append(self._neutral(e, illum))
            conf = np.asarray(pl.confidence[sl], np.float64)[m] if pl.confidence is not None else np.ones(m.sum())
            ws.append(np.clip(conf, 0.05, 1.0))
            gs.append(np.full(m.sum(), g))
            bs.append(np.zeros(m.sum(), bool))
            labels.append(pl.labels[k] if k < len(pl.labels) else "plane")
            g += 1
        if self.use_planes and not anchor.synthetic:
            R = anchor.R
            half = self._grid_half_extent(pl)
            for k, p in enumerate(planes):
                on = (s.plane == k) & ~s.saturated  # a clipped pixel says only "at least this bright"
                group = g
                if p.id == anchor.plane_id:
                    # the grid above measures the patch around the object; the rest of the floor
                    # (out to FLOOR_RADIUS_M) shows where a lamp's pool of light peaks and how fast it
                    # falls off, which the patch alone often cannot (a lamp 0.5 m to the side)
                    if not xs or half is None:
                        continue
                    pos = s.position
                    with np.errstate(invalid="ignore"):
                        outside = np.maximum(np.abs(pos[:, 0]), np.abs(pos[:, 2])) > half
                        near_obj = np.hypot(pos[:, 0], pos[:, 2]) < FLOOR_RADIUS_M
                    on &= outside & near_obj
                    group = 0  # same plane, same albedo and ambient as the grid
                if on.sum() < 20:
                    continue
                n_obj = np.asarray(p.normal, np.float64) @ R
                e = s.radiance[on] * (np.pi / self.albedo)
                xs.append(s.position[on])
                ns.append(np.repeat(n_obj[None], on.sum(), 0))
                es.append(self._neutral(e, illum))
                ws.append(np.full(on.sum(), 0.5))
                gs.append(np.full(on.sum(), group))
                bs.append(np.full(on.sum(), group != g))
                if group == g:
                    labels.append(p.label)
                    g += 1
        if not xs:
            z3 = np.zeros((0, 3))
            return z3, z3, z3, np.zeros(0), np.zeros(0, np.int64), labels, np.zeros(0, bool)
        return (
            np.concatenate(xs),
            np.concatenate(ns),
            np.concatenate(es),
            np.concatenate(ws),
            np.concatenate(gs).astype(np.int64),
            labels,
            np.concatenate(bs),
        )

    @staticmethod
    def _grid_cells(pl: PlaneLight) -> list[tuple]:
        """The grids for :func:`fit_near_light_gradient`, the wider context grid first when the plane
        light measured one (``[plane_light] context_extent_m``), then the anchor grid: each as observed
        cells' positions, normals and RGB irradiance (P, 3; before any smoothing, which would blur
        the texture's edges into gradients) and the neighbour pairs (a, b) into them; a grid with
        fewer than :data:`MIN_GRAD_PAIRS` pairs is left out."""
        out = []
        sl = pl.plane_slices[0] if pl.plane_slices else slice(0, len(pl.irradiance))
        src = pl.irradiance_raw if pl.irradiance_raw is not None else pl.irradiance
        grids = [(int(pl.grid), np.asarray(pl.mask[sl], bool), pl.vertices[sl], pl.normals[sl], src[sl])]
        if pl.context_grid and pl.context_mask is not None:
            C = int(pl.context_grid)
            up = np.tile(np.array([0.0, 1.0, 0.0]), (C * C, 1))
            grids.insert(0, (C, np.asarray(pl.context_mask, bool), pl.context_vertices, up, pl.context_irradiance))
        for G, m, verts, norms, irr in grids:
            if G < 2 or len(m) != G * G:
                continue
            a, b = grid_pairs(m, G)
            if len(a) < MIN_GRAD_PAIRS:
                continue
            keep = np.flatnonzero(m)
            remap = np.full(G * G, -1)
            remap[keep] = np.arange(len(keep))
            x = np.asarray(verts, np.float64)[keep]
            n = np.asarray(norms, np.float64)[keep]
            e = np.asarray(irr, np.float64)[keep]
            out.append((x, n, e, remap[a], remap[b]))
        return out

    @staticmethod
    def _distant_weight(xs: np.ndarray, es: np.ndarray, ws: np.ndarray, gs: np.ndarray) -> np.ndarray:
        """Weights of the other planes' rows in the ambient solve, lowered for a plane lit from near it.

        The solve reads a plane's irradiance as the light at the object, which holds for distant
        light (a sunlit facade, evenly lit at every point). A wall with a lamp's pool on it says how
        that lamp lights the wall, not the object 2 m away: its irradiance varies smoothly across it.
        An affine fit over the plane's points measures that variation (the albedo texture averages
        out); the plane's weight is ``1 / (1 + (variation / LOCAL_VARIATION)^2)``.
        """
        out = ws.copy()
        if LOCAL_VARIATION <= 0:
            return out
        lum = es @ LUMA
        for g in np.unique(gs):
            m = gs == g
            if g == 0 or m.sum() < 8:
                continue
            X = np.c_[np.ones(int(m.sum())), xs[m] - xs[m].mean(0)]
            coef, *_ = np.linalg.lstsq(X, lum[m], rcond=None)
            rel = float(np.std(X[:, 1:] @ coef[1:]) / max(float(np.mean(lum[m])), 1e-12))
            out[m] *= 1.0 / (1.0 + (rel / LOCAL_VARIATION) ** 2)
        return out

    def _albedo_bound(self, xs, ns, es, gs, L_rad, E_p, primary_dir, primary_pos) -> float:
        """Factor (>= 1) the light must grow by so that no tracked plane needs an albedo over ALBEDO_MAX.

        Every plane's irradiance row assumes ``[plane_light] assumed_albedo``, and the solve weighs the
        planes by their rows: a large dark floor outweighs the small white table top the object stands
        on. A real OAK-D frame (a white plate 18 cm above a green floor, the plate's 38 cells against
        the floor's 1700 pixels) lit the object at a third of what the plate itself measured: the plate
        would have needed an albedo of 1.4-1.6 under that light, so the virtual white vase came out far
        darker than the real white plate beside it. No diffuse surface reflects more than it receives,
        so the median ratio of measured to predicted irradiance of each plane (a few glossy or clipped
        cells move no median) times the assumed albedo is a lower bound on the light's level; the
        ambient and the primary are scaled together (their split and directions stay as solved)."""
        if not len(xs):
            return 1.0
        A = _plane_basis(xs, ns, primary_dir, primary_pos)  # the solve's own rows
        pred = A[:, :9] @ L_rad
        if primary_dir is not None:
            pred = pred + A[:, 9:] * np.asarray(E_p, np.float64)[None, :]
        pred_l, obs_l = pred @ LUMA, es @ LUMA
        k = 1.0
        for g in np.unique(gs):
            m = (gs == g) & (pred_l > 1e-12)
            if m.sum() < 8:
                continue
            k = max(k, float(np.median(obs_l[m] / pred_l[m])) * self.albedo / ALBEDO_MAX)
        return k

    @staticmethod
    def _grid_half_extent(pl: PlaneLight) -> float | None:
        """Half the side of the anchor plane's grid (object frame, metres), None without a grid."""
        sl = pl.plane_slices[0] if pl.plane_slices else slice(0, len(pl.irradiance))
        v = np.asarray(pl.vertices[sl], np.float64)
        if len(v) < 4:
            return None
        side = float(np.max(np.abs(v[:, [0, 2]])))
        return side + side / (max(int(pl.grid), 2) - 1)  # to the outer edge of the outer cells

    @staticmethod
    def _neutral(e: np.ndarray, illum: np.ndarray) -> np.ndarray:
        """Divide a plane's mean colour out and give it the illuminant's (grey-world albedo)."""
        m = e.mean(0)
        lum = float(m @ LUMA)
        if lum <= 1e-12:
            return e
        albedo_chroma = np.clip((m / lum) / illum, 0.2, 5.0)
        return e / albedo_chroma

    def _emitter(self) -> tuple[np.ndarray | None, int]:
        """Direction of bins far brighter than the map's median (lamps, windows, the sun's region)."""
        seen = self.env.seen
        if seen.sum() < 10:
            return None, 0
        lum = self.env.radiance @ LUMA
        med = float(np.median(lum[seen]))
        hot = seen & (lum > 8.0 * max(med, 1e-9)) & (BIN_DIRS[:, 1] > -0.1)
        if not hot.any():
            return None, 0
        w = lum[hot] * BIN_OMEGA[hot]
        d = (BIN_DIRS[hot] * w[:, None]).sum(0)
        nd = float(np.linalg.norm(d))
        if nd < EMITTER_COMPACT * float(w.sum()):
            # spread over a wide patch (a bright sky seen while looking around): that is ambient light,
            # which the map's own bins already carry, not one light with one direction
            return None, int(hot.sum())
        # what the map saw of it: its irradiance on a surface facing it (radiance x solid angle), and
        # how much of it was clipped (then that is only a lower bound, and its colour is the clip's)
        self._emitter_seen = (
            (self.env.radiance[hot] * BIN_OMEGA[hot, None]).sum(0),
            float((self.env.saturated[hot] * w).sum() / max(float(w.sum()), 1e-12)),
        )
        return (d / nd if nd > 0 else None), int(hot.sum())

    def _emitter_rgb(self, E_p: np.ndarray, illum: np.ndarray | None) -> np.ndarray:
        """The primary irradiance of a seen emitter: what the map measured of it, not a free fit.

        A free per-channel fit of the primary to the planes gave a seen patch of sky a primary with no
        red at all, and a window at the horizon one brighter than the room (look-around, docs/eval.md):
        the fit explains the planes' residuals with whatever the direction allows. An unclipped emitter's
        irradiance is measured (radiance x solid angle over its bins, in the map's units); a clipped one
        (the sun in an 8-bit picture) is at least that bright, with the fit's intensity if higher, and
        the scene illuminant's colour (the clip's white is not the light's colour)."""
        seen_rgb, clipped = self._emitter_seen
        lum_seen = float(seen_rgb @ LUMA)
        if lum_seen <= 0:
            return E_p
        if clipped < EMITTER_CLIPPED:
            return np.asarray(seen_rgb, np.float64)
        chroma = np.ones(3) if illum is None else np.asarray(illum, np.float64)
        chroma = chroma / max(float(chroma @ LUMA), 1e-12)
        return max(float(E_p @ LUMA), lum_seen) * chroma

    def _shadow_cue(self, frame: Frame, anchor: Anchor, planes: tuple) -> tuple[np.ndarray, float] | None:
        """Direction and confidence from real cast shadows (:mod:`~illuminet.runtime.stages.shadow_cue`):
        a full search about once a second, a local refinement in between (:class:`ShadowTracker`)."""
        if frame.depth is None or not planes:
            return None
        depth = frame.depth
        if depth.dtype == np.uint16:
            depth = depth.astype(np.float32) * np.float32(0.001)
        dH, dW = depth.shape[:2]
        color = frame.color
        if color.shape[:2] != (dH, dW):  # the cue works at the depth's resolution
            import cv2

            color = cv2.resize(color, (dW, dH), interpolation=cv2.INTER_AREA)
        intr = frame.intrinsics
        if (intr.width, intr.height) != (dW, dH):
            intr = intr.scaled(dW, dH)
        t_ns = frame.t_device_ns or frame.t_host_ns or 0
        cue = self._shadows.update(linearize(color, self.lut), depth, intr, planes, anchor.T_cam_obj, t_ns * 1e-9)
        self.last_shadow = cue
        if cue is None or cue.confidence < SHADOW_MIN_CONFIDENCE:
            return None
        return np.asarray(cue.direction, np.float64), float(cue.confidence)

    def _solve(
        self, xs, ns, es, ws, primary_dir, primary_pos, illum=None, primary_rgb=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ambient radiance SH (9, 3) and primary RGB irradiance (3,) by weighted least squares.

        The directions the environment map has not seen (the sky above a lawn, a ceiling out of view)
        are otherwise filled by the smoothness penalty from the seen surfaces, so they took the lawn's
        green or the bricks' red; a second solve gives them the scene illuminant's colour at the
        luminance the first solve gives them, each weighing ``[light] unseen_illuminant`` times a seen
        direction of the same solid angle (docs/lighting.md).

        ``primary_rgb`` fixes the primary's irradiance (a seen emitter's, :meth:`_emitter_rgb`): only the
        ambient is solved, with the primary's share moved to the right-hand side."""
        ne = self._normal_equations(xs, ns, es, ws, primary_dir, primary_pos)
        if ne is None:
            return np.zeros((9, 3)), np.zeros(3)
        if primary_rgb is not None and ne[3]:
            G, Ab, _, _, env_scale = ne
            fixed = np.asarray(primary_rgb, np.float64)
            ne = (G[:9, :9], Ab[:9] - G[:9, 9][:, None] * fixed[None, :], 9, False, env_scale)
            return self._solve_rest(ne, illum)[0], fixed
        return self._solve_rest(ne, illum)

    def _solve_rest(self, ne, illum) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_solve` from its normal equations: the solve, then the unseen directions' second pass."""
        L_rad, E_p = self._finish(*ne)
        if illum is None or self.unseen_w <= 0 or not (self.use_env and self.env.seen.any()):
            return L_rad, E_p
        unseen = ~self.env.seen
        if not unseen.any():
            return L_rad, E_p
        # the unseen bins' rows added to the same normal equations (the seen rows are not built again)
        G, Ab, ncol, has_p, env_scale = ne
        Y = _NONNEG_Y[unseen]
        lum = np.maximum(Y @ L_rad @ LUMA, 0.0)
        chroma = np.asarray(illum, float) / max(float(np.asarray(illum) @ LUMA), 1e-12)
        w = np.sqrt(BIN_OMEGA[unseen] / (4 * np.pi) * 4.0 * self.unseen_w)[:, None]
        Aw = np.zeros((len(Y), ncol))
        Aw[:, :9] = Y * w
        return self._finish(G + Aw.T @ Aw, Ab + Aw.T @ (lum[:, None] * chroma[None] * w), ncol, has_p, env_scale)

    def _normal_equations(self, xs, ns, es, ws, primary_dir, primary_pos):
        """The weighted normal equations ``(G, A^T W b, ncol, has_p, env_scale)`` of the map's seen bins
        and the plane rows (None without any row)."""
        rows, rhs, wts = [], [], []
        has_p = primary_dir is not None
        ncol = 10 if has_p else 9
        env_scale = 1.0
        if self.use_env and self.env.seen.any():
            seen = self.env.seen
            B = _NONNEG_Y[seen]
            L = self.env.radiance[seen].copy()
            if has_p:  # the emitter itself is the primary light, not ambient
                lum = L @ LUMA
                med = float(np.median(lum))
                L = np.where((lum > 8.0 * max(med, 1e-9))[:, None], med * L / np.maximum(lum, 1e-12)[:, None], L)
            A = np.zeros((len(B), ncol))
            A[:, :9] = B
            rows.append(A)
            rhs.append(L)
            wts.append(BIN_OMEGA[seen] / (4 * np.pi) * 4.0)
            env_scale = max(float(np.median(L @ LUMA)), 1e-9)
        if len(xs) and self.use_planes:
            A = _plane_basis(xs, ns, primary_dir, primary_pos)
            rows.append(A / np.pi)  # irradiance rows in radiance units, comparable with the bins
            rhs.append(es / np.pi)
            wts.append(ws / max(ws.sum(), 1e-12))
        if not rows:
            return None
        A = np.concatenate(rows)
        b = np.concatenate(rhs)
        w = np.sqrt(np.concatenate(wts))[:, None]
        Aw, bw = A * w, b * w
        return Aw.T @ Aw, Aw.T @ bw, ncol, has_p, env_scale

    def _finish(self, G, Ab, ncol, has_p, env_scale) -> tuple[np.ndarray, np.ndarray]:
        """The regularised, non-negative solve of the normal equations: (ambient radiance SH, primary RGB)."""
        reg = np.zeros(ncol)
        reg[:9] = (self.lam * (SH_BAND * (SH_BAND + 1.0)) ** 2 + 1e-6) * (np.trace(G[:9, :9]) / 9 + 1e-12)
        reg[9:] = 1e-6 * (np.trace(G) / ncol + 1e-12)
        # a weak prior towards uniform light at the map's level keeps a barely observed scene sane
        prior = np.zeros((ncol, 3))
        prior[0] = env_scale / 0.282095 if self.env.seen.any() else 0.0
        sol = _solve_nonnegative(G + np.diag(reg), Ab + reg[:, None] * prior)
        L_rad = sol[:9]
        E_p = np.maximum(sol[9], 0.0) if has_p else np.zeros(3)
        return L_rad, E_p

    def _filter(self, raw: dict, frame: Frame) -> dict:
        """Exponential smoothing in time; direction by normalised blend, reset after a jump."""
        t = frame.t_device_ns or frame.t_host_ns
        if self._state is None or self._t_prev is None or t is None or t <= self._t_prev:
            a = 0.0 if self._state is None else 0.6
        else:
            a = math.exp(-((t - self._t_prev) * 1e-9) / max(self.tau, 1e-6))
        self._t_prev = t
        prev = self._state
        if prev is None or a == 0.0:
            self._state = {k: (None if v is None else np.array(v, np.float64)) for k, v in raw.items()}
            return self._state
        out = {"sh9": a * prev["sh9"] + (1 - a) * raw["sh9"], "rgb": a * prev["rgb"] + (1 - a) * raw["rgb"]}
        if raw["dir"] is None:
            out["dir"] = prev["dir"] if float(out["rgb"] @ LUMA) > 0.05 * float(raw["sh9"][0] @ LUMA) else None
            # a faded primary takes its position with it: the estimate JSON had hasPrimaryLight false
            # with a lamp position that a client would light
            out["pos"] = prev["pos"] if out["dir"] is not None else None
        elif prev["dir"] is None:
            out["dir"], out["pos"] = raw["dir"], raw["pos"]
        else:
            d = a * prev["dir"] + (1 - a) * raw["dir"]
            out["dir"] = d / max(np.linalg.norm(d), 1e-12)
            out["pos"] = (
                raw["pos"] if prev["pos"] is None or raw["pos"] is None else a * prev["pos"] + (1 - a) * raw["pos"]
            )
        self._state = out
        return out

    def stats(self) -> dict[str, Any]:
        st: dict[str, Any] = {
            "frames": self.frames,
            "reused": self.skipped,
            "env_coverage": round(self.env.coverage(), 3),
            "warnings": dict(self._warn.counts),
        }
        if self.ms:
            st["median_ms"] = round(float(np.median(self.ms)), 2)
            st["cpu_ms"] = round(self.cpu_s / self.frames * 1e3, 2)  # thread CPU time per estimate
        s = self._state
        if s is not None and s.get("dir") is not None:
            st["primary_dir"] = [round(float(v), 2) for v in s["dir"]]
        return st
