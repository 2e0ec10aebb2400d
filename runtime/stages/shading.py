"""The transfer stage: the room's light -> the object's shading, per frame.

Owns :func:`preprocess_plane` (the plane input normalisation shared by training and run time) and
:class:`ShadingStage`: ``results["light"]`` (the light estimate) through the bundle's precomputed
radiance transfer, or ``results["plane_light"]`` through the learned ONNX chain
(:class:`~illuminet.runtime.assets.bundle.TransferChain`) or a baseline, as ``[model] shading`` asks,
-> ``results["shading"]`` with temporal smoothing.

Normalisation: the plane's measured irradiance is divided by its mean luminance ``s`` over the
observed cells, so the network sees lighting *shape and colour*, never absolute brightness (which
depends on exposure, plane albedo and units). The network predicts the object's shading divided by
the same ``s``; multiplying back gives scene-referred irradiance in the plane's units.
"""

from __future__ import annotations

import logging

import numpy as np

from illuminet.runtime.prt import PRT_FILE, prt_geometry, prt_irradiance, prt_irradiance_render
from illuminet.runtime.scene import LIGHT, PLANE_LIGHT, SHADING, ObjectShading
from illuminet.runtime.sh import sh_eval, sh_fit
from illuminet.runtime.stage import FrameError, Stage

log = logging.getLogger(__name__)

LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

#: plane grid cells are pooled by this factor per side before the network (32x32 -> 16x16)
POOL = 2


def preprocess_plane(
    irradiance: np.ndarray, mask: np.ndarray, grid: int, pool: int = POOL, confidence: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """Plane irradiance grid -> network input (cells, 4) and the normalising scale ``s``.

    Parameters
    ----------
    irradiance : (grid*grid, 3)
        Linear RGB irradiance per plane vertex (row-major grid, vertex i*grid+j).
    mask : (grid*grid,) bool
        Observed vertices.
    grid : int
        Vertices per side; must be divisible by ``pool``.
    pool : int
        Cells per side merged into one network vertex (mask-weighted mean).
    confidence : (grid*grid,) float, optional
        Extra per-vertex weights in [0, 1].

    Returns
    -------
    x : (grid/pool)^2 x 4 float32
        Normalised RGB irradiance and the observed fraction of each pooled cell.
    s : float
        Mean observed luminance (the scale the prediction is multiplied back by).
    """
    e = np.asarray(irradiance, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    n = grid * grid
    if e.shape != (n, 3) or m.shape != (n,):
        raise ValueError(
            f"plane irradiance must be ({n}, 3) with mask ({n},) for grid {grid}, got {e.shape} and {m.shape}"
        )
    if grid % pool:
        raise ValueError(f"plane grid {grid} is not divisible by the pooling factor {pool}")
    w = _cell_weights(m, confidence)
    e = np.where(np.isfinite(e), e, 0.0)
    s = plane_scale(e, m, confidence)
    g2 = grid // pool
    ew = (e / s * w[:, None]).reshape(g2, pool, g2, pool, 3).sum((1, 3))
    ws = w.reshape(g2, pool, g2, pool).sum((1, 3))
    x = np.zeros((g2, g2, 4), dtype=np.float32)
    x[..., :3] = ew / np.maximum(ws, 1e-6)[..., None]
    x[..., 3] = ws / (pool * pool)
    return x.reshape(g2 * g2, 4), s


def _cell_weights(mask: np.ndarray, confidence: np.ndarray | None) -> np.ndarray:
    w = np.asarray(mask, dtype=bool).astype(np.float32)
    if confidence is not None:
        w = w * np.clip(np.asarray(confidence, dtype=np.float32), 0.0, 1.0)
    return w


def plane_scale(irradiance: np.ndarray, mask: np.ndarray, confidence: np.ndarray | None = None) -> float:
    """The plane's scale ``s``: mean observed luminance (Rec.709) of its irradiance, confidence-weighted.

    Raises
    ------
    ValueError
        When no cell is observed or the mean is not positive.
    """
    e = np.asarray(irradiance, dtype=np.float32)
    e = np.where(np.isfinite(e), e, 0.0)
    w = _cell_weights(mask, confidence)
    wsum = float(w.sum())
    if wsum <= 0:
        raise ValueError("no observed plane cells: cannot measure the plane's illumination")
    s = float((e @ LUMA * w).sum() / wsum)
    if not s > 0:
        raise ValueError(f"plane irradiance has non-positive mean luminance {s}")
    return s


def dominant_light_from_oi(oi: np.ndarray, normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Dominant light direction (towards the light, object frame) and its share, from per-vertex OI.

    The OI vectors of all vertices point towards where light comes from; their luminance-weighted
    sum is the dominant direction, and the ratio of the sum's length to the sum of lengths says how
    much of the light comes from that one direction (1 = a single distant light, 0 = uniform).
    """
    lum = np.einsum("vcx,c->vx", np.asarray(oi, dtype=np.float32), LUMA)
    tot = lum.sum(0)
    norm = float(np.linalg.norm(tot))
    lens = float(np.linalg.norm(lum, axis=1).sum())
    if norm <= 1e-12 or lens <= 1e-12:
        return np.array([0.0, 1.0, 0.0], dtype=np.float32), 0.0
    return (tot / norm).astype(np.float32), float(np.clip(norm / lens, 0.0, 1.0))


def plane_mean_shading(plane_irr: np.ndarray, mask: np.ndarray, n_vertices: int) -> np.ndarray:
    """Ambient-only shading (what phone AR frameworks give): every vertex gets the plane's mean RGB
    irradiance. (The full baselines, incl. SH from RGB-D, are in :mod:`illuminet.runtime.groundtruth.baselines`.)"""
    m = np.asarray(mask, dtype=bool)
    mean = np.asarray(plane_irr, dtype=np.float32)[m].mean(0) if m.any() else np.zeros(3, np.float32)
    return np.tile(mean[None, :], (n_vertices, 1)).astype(np.float32)


def _light_key(light) -> tuple:
    """What PRT shading reads of a light estimate (its pose does not matter: the light is in the object's
    frame), as copies to compare with the next frame's."""

    def a(x):
        return None if x is None else np.array(x, np.float64)

    return (a(light.sh9), a(light.primary_dir), a(light.primary_rgb), a(light.primary_pos))


def _same_key(k1: tuple, k2: tuple) -> bool:
    return all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y)) for x, y in zip(k1, k2)
    )


def _frozen(x: np.ndarray) -> np.ndarray:
    """``x`` made read-only: a cached shading is handed to every frame until the light changes."""
    x.flags.writeable = False
    return x


class ShadingStage(Stage):
    """The object's shading per frame -> ``results["shading"]`` (:class:`ObjectShading` of the proxy mesh).

    ``[model] shading``:

    * ``prt``: physical shading from the frame's light estimate (``results["light"]``) through the
      bundle's precomputed radiance transfer (:func:`illuminet.runtime.prt.prt_irradiance`): the
      ambient SH through each vertex's self-shadowed transfer vector, the primary light through its
      visibility table, and the bundle's interreflection bounce. The dominant light for the cast
      shadow is the estimate's primary light and its share. Requires ``light``;
    * ``model``: the bundle's learned ONNX chain (``[model] precision`` int8 or fp32) on the anchor
      plane's irradiance (the paper's transfer);
    * ``auto`` (default): ``prt`` on frames that carry a light estimate when the bundle has PRT
      tables, else ``model`` when the bundle has one, else ``ambient``; also ``ambient`` when the
      bundle cannot load (logged once);
    * ``constant``: the bundle's prior (``prior_shading``) times the plane's scale;
    * ``ambient``: the plane's mean irradiance everywhere;
    * ``sh``: second-order SH fitted (minimum-norm least squares) to the plane-light samples with
      their normals (all planes of the frame's ``plane_light``), evaluated at the proxy normals.

    Contract: ``prt`` requires ``light`` only; every other mode requires ``plane_light``, and
    ``auto`` also reads ``light`` when present (set per instance from the configuration).

    In ``prt`` the shading is computed again only when the estimate's light changes (``sh9``, the
    primary light's direction, colour and position: at ``[light] rate_hz``); frames in between get
    the same (read-only) arrays.

    Temporal smoothing: an exponential moving average of the predicted shading and OI with weight
    ``[model] temporal_smoothing`` on the previous value (0 = none), reset when the method changes.
    """

    name = "shading"
    requires = (PLANE_LIGHT,)  # (LIGHT,) in mode "prt" (set in __init__)
    optional = ()  # (LIGHT,) in mode "auto"
    provides = (SHADING,)

    def __init__(self, cfg):
        self.cfg = cfg
        m = cfg.model
        self.mode = m.shading
        self.precision = m.precision
        self.alpha = float(m.temporal_smoothing)
        if not 0.0 <= self.alpha < 1.0:
            raise ValueError(f"[model] temporal_smoothing must be in [0, 1), got {self.alpha}")
        if self.mode == "prt":
            self.requires = (LIGHT,)
        elif self.mode == "auto":
            self.optional = (LIGHT,)
        self.object_scale = float(cfg.render.object_scale)
        self.bundle = None
        self.chain = None
        self.fallback = None  # what "auto" uses on frames without a light estimate (set in open)
        self._proxy = None
        self._render_mesh = None
        self._prt_cache: tuple | None = None  # (the light's values, the ObjectShading they gave)
        self._prev: tuple | None = None
        self.frames = 0
        self.methods: dict[str, int] = {}

    def open(self) -> None:
        from illuminet.runtime.assets.bundle import BundleError, TransferChain, load_bundle

        try:
            self.bundle = load_bundle(self.cfg.model.bundle)
            if self.mode == "model" or (self.mode == "auto" and self.bundle.has_model):
                self.chain = TransferChain(self.bundle, self.precision)
            if self.mode == "prt" and self.bundle.prt is None:
                raise BundleError(
                    f"bundle {self.bundle.name} ({self.bundle.path}) has no PRT tables ({PRT_FILE}) for "
                    f'[model] shading = "prt": add them with `illuminet bundle --object '
                    f"{self.bundle.meta.get('object', 'MESH')} --out {self.bundle.path}`"
                )
        except BundleError as e:
            if self.mode != "auto":
                raise
            log.error("%s; shading falls back to the ambient baseline", e)
            self.mode = "ambient"
        if self.mode == "auto":
            self.fallback = "model" if self.chain is not None else "ambient"
            if self.bundle.prt is None:
                log.info("bundle %s has no PRT tables: shading uses %s", self.bundle.name, self.fallback)
            elif self.fallback == "ambient":
                log.info(
                    "bundle %s has no learned model: frames without a light estimate use the ambient baseline",
                    self.bundle.name,
                )

    def close(self) -> None:
        self.chain = None

    def stats(self) -> dict:
        return {
            "mode": self.mode,
            "precision": self.precision if self.chain is not None else None,
            "frames": self.frames,
            "methods": dict(self.methods),
        }

    def _plane_input(self, pl):
        sl = pl.plane_slices[0] if pl.plane_slices else slice(0, len(pl.irradiance))
        irr, mask = pl.irradiance[sl], pl.mask[sl]
        conf = pl.confidence[sl] if pl.confidence is not None else None
        return irr, mask, conf

    def method_for(self, pl, light) -> str:
        """The mode this frame is shaded with (``auto`` resolved by what the frame and bundle have)."""
        if self.mode != "auto":
            return self.mode
        if light is not None and self.bundle is not None and self.bundle.prt is not None:
            return "prt"
        return self.fallback or "ambient"

    def predict(self, pl=None, light=None) -> ObjectShading:
        """One prediction (no smoothing) from a :class:`~illuminet.runtime.scene.PlaneLight` and/or a
        :class:`~illuminet.runtime.scene.LightEstimate`, as the mode needs."""
        b = self.bundle
        mode = self.method_for(pl, light)
        if mode == "prt":
            if light is None:
                raise FrameError("shading mode prt needs a light estimate (results['light']) on this frame")
            key = _light_key(light)
            if self._prt_cache is not None and _same_key(self._prt_cache[0], key):
                return self._prt_cache[1]  # the estimate updates at [light] rate_hz; frames between reuse it
            if self._proxy is None:  # the proxy's points (at the drawn scale) and normals, once
                pts, nrm = np.asarray(b.proxy_vertices, np.float64) * self.object_scale, b.proxy_normals
                self._proxy = (pts, np.asarray(nrm, np.float64), prt_geometry(pts, nrm))
            render = None
            if b.prt.render_transfer is not None:
                # every render vertex from its own transfer (the self-occlusion in the grooves is finer
                # than the proxy); the proxy's values are the same at its vertices
                if self._render_mesh is None:
                    pts = np.asarray(b.vertices, np.float32) * np.float32(self.object_scale)
                    nrm = np.asarray(b.normals, np.float32)
                    self._render_mesh = (pts, nrm, prt_geometry(pts, nrm))
                pts, nrm, geom = self._render_mesh
                render = prt_irradiance_render(b.prt, pts, nrm, b.proxy_index, b.carry, light, geom)
                irr = render[b.proxy_index]
            else:
                irr = prt_irradiance(b.prt, self._proxy[0], self._proxy[1], light, self._proxy[2])
            d = None if light.primary_dir is None else np.array(light.primary_dir, np.float32)
            out = ObjectShading(
                irradiance=_frozen(irr),
                method="prt",
                dominant_dir=None if d is None else _frozen(d),
                dominant_share=light.primary_share() if d is not None else 0.0,
                render_irradiance=None if render is None else _frozen(render),
            )
            self._prt_cache = (key, out)
            return out
        if pl is None:
            raise FrameError(f"shading mode {mode} needs the plane light (results['plane_light']) on this frame")
        irr, mask, conf = self._plane_input(pl)
        if mode == "model":
            if pl.grid != b.grid:
                raise FrameError(
                    f"plane grid is {pl.grid}x{pl.grid} but bundle {b.name} was trained on "
                    f"{b.grid}x{b.grid}: set [plane_light] grid = {b.grid}"
                )
            try:
                x, s = preprocess_plane(irr, mask, b.grid, b.pool, conf)
            except ValueError as e:
                raise FrameError(str(e)) from None
            oi, sh = self.chain(x)
            oi, sh = oi * s, np.maximum(sh, 0.0) * s
            d, share = dominant_light_from_oi(oi)
            return ObjectShading(
                irradiance=sh, method=f"model:{self.precision}", oi=oi, dominant_dir=d, dominant_share=share
            )
        if mode == "constant":
            try:
                s = plane_scale(irr, mask, conf)
            except ValueError as e:
                raise FrameError(str(e)) from None
            return ObjectShading(irradiance=b.prior_shading * s, method="constant")
        if mode == "ambient":
            n = b.n_proxy if b is not None else 1
            return ObjectShading(irradiance=plane_mean_shading(irr, mask, n), method="ambient")
        if mode == "sh":
            m = np.asarray(pl.mask, bool)  # every plane's samples, not only the anchor plane
            if not m.any():
                raise FrameError("no observed plane samples to fit SH lighting to")
            coef = sh_fit(pl.normals[m], pl.irradiance[m])
            lin = coef[1:4] @ LUMA
            d = np.array([lin[2], lin[0], lin[1]], np.float32)
            nd = float(np.linalg.norm(d))
            return ObjectShading(
                irradiance=sh_eval(coef, b.proxy_normals),
                method="sh",
                dominant_dir=d / nd if nd > 0 else None,
                dominant_share=float(np.clip(nd / max(float(coef[0] @ LUMA), 1e-12), 0, 1)),
            )
        raise FrameError(f"unknown shading mode {mode!r}")

    def process(self, frame):
        light = frame.results.get(LIGHT.name)
        if self.mode == "prt":
            light = self.require(frame, LIGHT)
        pl = frame.results.get(PLANE_LIGHT.name)
        if self.method_for(pl, light) != "prt":
            pl = self.require(frame, PLANE_LIGHT)
        shading = self._smooth(self.predict(pl, light))
        self.frames += 1
        self.methods[shading.method] = self.methods.get(shading.method, 0) + 1
        return frame.with_result(SHADING, shading)

    def _smooth(self, s: ObjectShading) -> ObjectShading:
        a = self.alpha
        prev = self._prev
        if a > 0 and prev is not None and prev[0] == s.method and prev[1].shape == s.irradiance.shape:
            irr = a * prev[1] + (1 - a) * s.irradiance
            oi = s.oi if (s.oi is None or prev[2] is None) else a * prev[2] + (1 - a) * s.oi
            d, share = dominant_light_from_oi(oi) if oi is not None else (s.dominant_dir, s.dominant_share)
            r = s.render_irradiance
            if r is not None and prev[3] is not None and prev[3].shape == r.shape:
                r = (a * prev[3] + (1 - a) * r).astype(np.float32)
            s = ObjectShading(
                irradiance=irr.astype(np.float32),
                method=s.method,
                oi=None if oi is None else oi.astype(np.float32),
                dominant_dir=d,
                dominant_share=share,
                render_irradiance=r,
            )
        self._prev = (s.method, s.irradiance, s.oi, s.render_irradiance)
        return s
