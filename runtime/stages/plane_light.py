"""Illumination measured on the anchor plane: the ``PlaneLightStage`` (per-vertex plane OI input).

What this module owns
    * The grid: ``G x G`` vertices on the anchor plane in the object frame, row-major,
      ``vertex[i*G + j] = (x_j, 0, z_i)``, ``x_j = z_j = linspace(-extent/2, extent/2, G)``
      (:func:`grid_vertices`; the transfer model is trained on exactly this layout). Vertex
      (i, j) owns the square cell of side ``h = extent/(G-1)`` centred on it.
    * Measuring one frame (:func:`measure_cells`): every cell is sampled by ``K x K`` points; one
      ``cv2.warpPerspective`` through the plane-to-image homography fetches their colour and
      measured depth (nearest neighbour, so depth is never blended across edges and colour is
      linearised exactly per sample). A sample counts when it is in front of the camera, inside
      the image, has valid depth that agrees with the plane (within 3 inlier thresholds: nearer
      means occluded, e.g. a person; farther means the plane is not there), and is not saturated.
      A cell is observed when at least half its samples count; its value is the mean of their
      linear colour (area averaging suppresses albedo texture and noise). Texture coarser than a
      cell is further reduced by a masked Gaussian over the fused grid (:func:`smooth_cells`,
      ``[plane_light] smoothing_cells``); ``PlaneLight.irradiance_raw`` keeps the cells' own values
      (the near-light fit of the light estimate works on their differences: the texture's edges stay
      sharp there, and a robust fit sets them aside).
    * Units: linear (``physics.linearize`` with the camera's response LUT when given), divided by
      the exposure scale (from ``Frame.exposure`` when known; otherwise estimated from the plane
      itself, see :class:`PlaneLightStage`), converted to irradiance ``E = pi * radiance / albedo``
      with ``[plane_light] assumed_albedo``.
    * Fusion over frames (:class:`CellFusion`): per-cell exponential fusion with weight
      ``[plane_light] fusion`` for the previous estimate; an observation more than 35 % away from
      the running estimate (luminance) is rejected as an outlier (specular highlight, a passing
      shadow); a cell that stays an outlier for 5 frames, or more than half the cells at once
      (the light changed), resets to the new value. The state resets when the anchor has moved by
      more than half a cell or turned by more than 2 degrees since the last reset. With a
      world-locked anchor (``results["odometry"]`` present, ``[anchor] lock = "world"``) this is
      measured on the anchor's *world* pose ``T_world_cam @ T_cam_obj``: a camera moving around a
      placed object keeps the fused grid (its cells are fixed in the room), while a re-placement
      of the object still restarts it.

The representation (:class:`~illuminet.runtime.scene.PlaneLight`) concatenates planes via
``plane_slices``; the anchor plane is the first slice. With ``[plane_light] extra_planes = N``
the stage also measures up to N other tracked planes (walls first: they see light the floor
cannot), each on a grid of the same size, as further slices in the same object frame.
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np

from illuminet.runtime.config import Config
from illuminet.runtime.frame import Frame
from illuminet.runtime.physics import linearize, load_response_lut
from illuminet.runtime.scene import ANCHOR, ODOMETRY, PLANE_LIGHT, PLANES, Anchor, PlaneLight
from illuminet.runtime.stage import LogOnce, Stage
from illuminet.runtime.stages.anchor import object_frame
from illuminet.runtime.stages.plane_fit import inlier_threshold

log = logging.getLogger(__name__)

#: Samples per cell side (K x K samples per cell).
SAMPLES_PER_CELL = 6
#: Fraction of a cell's samples that must count for the cell to be observed.
MIN_CELL_COVERAGE = 0.5
#: uint8 value from which a channel is taken as saturated (clipped highlights carry no radiance).
SATURATED = 250
#: Outlier test and reset rules of the fusion.
OUTLIER_REL = 0.35
OUTLIER_FRAMES = 5
#: Relative luminance the plane's median is mapped to when the exposure is unknown.
REFERENCE_RADIANCE = 0.18
_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def grid_coords(grid: int, extent_m: float) -> np.ndarray:
    """``linspace(-extent/2, extent/2, grid)``: the x (= z) coordinates of the vertices."""
    return np.linspace(-extent_m / 2.0, extent_m / 2.0, grid)


def grid_vertices(grid: int, extent_m: float) -> np.ndarray:
    """(G*G, 3) object-frame vertices, row-major: ``vertex[i*G + j] = (x_j, 0, z_i)``."""
    c = grid_coords(grid, extent_m)
    zz, xx = np.meshgrid(c, c, indexing="ij")
    return np.stack([xx.ravel(), np.zeros(grid * grid), zz.ravel()], axis=1)


def measure_cells(
    frame: Frame,
    T_cam_obj: np.ndarray,
    grid: int,
    extent_m: float,
    inlier_threshold_m: float,
    response_lut: np.ndarray | None = None,
    samples: int = SAMPLES_PER_CELL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-averaged linear colour per cell in one frame (module docstring).

    Returns
    -------
    linear : (G*G, 3) float32
        Mean linear RGB of the counted samples (0 where not observed).
    observed : (G*G,) bool
    coverage : (G*G,) float32
        Fraction of the cell's samples that counted.
    """
    G, K = int(grid), int(samples)
    S = G * K
    h = extent_m / (G - 1) if G > 1 else extent_m
    hs = h / K
    x0 = -extent_m / 2.0 - h / 2.0 + hs / 2.0  # centre of the first sample
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    W, H = frame.size
    intr = frame.intrinsics
    if (intr.width, intr.height) != (W, H):
        intr = intr.scaled(W, H)
    # sample (col a, row b) -> plane (x, z) = (x0 + a*hs, x0 + b*hs) -> camera R[:,0] x + R[:,2] z + t
    A = np.array([[hs, 0.0, x0], [0.0, hs, x0], [0.0, 0.0, 1.0]])
    M_cam = np.stack([R[:, 0], R[:, 2], t], axis=1) @ A  # (3x3): sample -> camera point
    Hm = intr.K @ M_cam  # sample -> homogeneous pixel
    flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    # warpPerspective samples src at the pixel centre convention (x = col index); ours matches.
    col = cv2.warpPerspective(
        frame.color, Hm, (S, S), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0)
    )
    # depth the plane predicts at each sample (camera z of the sample point), and whether in front
    a = np.arange(S, dtype=np.float32)
    z_pred = np.float32(M_cam[2, 0]) * a[None, :] + np.float32(M_cam[2, 1]) * a[:, None] + np.float32(M_cam[2, 2])
    ok = z_pred > 0.05
    if frame.depth is not None:
        # outside the image the border value 0 reads as invalid depth
        dm = cv2.warpPerspective(frame.depth, Hm, (S, S), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        tol = 3.0 * inlier_threshold(z_pred, inlier_threshold_m)
        with np.errstate(invalid="ignore"):
            ok &= np.abs(dm - z_pred) < tol  # NaN compares False; 0 (invalid) is far from z_pred
    else:
        inside = cv2.warpPerspective(
            np.ones((H, W), np.uint8), Hm, (S, S), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        ok &= inside > 0
    # (np.max over a length-3 last axis is ~20x slower than two element-wise maxima)
    ok &= np.maximum(np.maximum(col[..., 0], col[..., 1]), col[..., 2]) < SATURATED
    lin = cv2.LUT(col, _lut_table(response_lut))  # = physics.linearize, applied by OpenCV
    okf = ok.astype(np.float32)
    lin *= okf[..., None]
    # block means over the K x K samples of each cell (INTER_AREA with an integer factor is exact)
    sums = cv2.resize(lin, (G, G), interpolation=cv2.INTER_AREA).reshape(-1, 3)
    coverage = cv2.resize(okf, (G, G), interpolation=cv2.INTER_AREA).reshape(-1)
    observed = coverage >= MIN_CELL_COVERAGE
    linear = np.where(observed[:, None], sums / np.maximum(coverage[:, None], 1e-6), 0.0)
    return linear.astype(np.float32), observed, coverage.astype(np.float32)


_LUT_CACHE: dict[int, tuple[Any, np.ndarray]] = {}


def _lut_table(response_lut: np.ndarray | None) -> np.ndarray:
    """(256, 1, 3) float32 table of :func:`~illuminet.runtime.physics.linearize` for ``cv2.LUT``."""
    key = id(response_lut)
    hit = _LUT_CACHE.get(key)
    if hit is not None and hit[0] is response_lut:
        return hit[1]
    ramp = np.repeat(np.arange(256, dtype=np.uint8).reshape(256, 1, 1), 3, axis=2)
    table = np.ascontiguousarray(linearize(ramp, response_lut), dtype=np.float32)
    if len(_LUT_CACHE) > 8:
        _LUT_CACHE.clear()
    _LUT_CACHE[key] = (response_lut, table)
    return table


def smooth_cells(values: np.ndarray, observed: np.ndarray, grid: int, sigma_cells: float) -> np.ndarray:
    """Masked Gaussian smoothing of per-cell values over the grid (observed cells only).

    Light varies smoothly over a floor except at shadow edges, while albedo texture coarser than
    a cell (tiles, grout, planks) does not average out inside one cell; a small kernel trades a
    little shadow-edge sharpness for less texture. Unobserved cells neither contribute nor get a
    value. ``sigma_cells <= 0`` returns ``values`` unchanged.
    """
    if sigma_cells <= 0 or not observed.any():
        return values
    w = observed.reshape(grid, grid).astype(np.float32)
    x = values.reshape(grid, grid, 3).astype(np.float32) * w[..., None]
    num = cv2.GaussianBlur(x, (0, 0), sigma_cells, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(w, (0, 0), sigma_cells, borderType=cv2.BORDER_CONSTANT)
    out = num / np.maximum(den, 1e-6)[..., None]
    return np.where(observed[:, None], out.reshape(-1, 3), 0.0).astype(np.float32)


class CellFusion:
    """Robust per-cell temporal fusion of irradiance (module docstring).

    Parameters
    ----------
    n_cells : int
    fusion : float
        Weight of the previous estimate in [0, 1); 0 = no fusion (each frame stands alone).
    """

    def __init__(self, n_cells: int, fusion: float):
        if not 0.0 <= fusion < 1.0:
            raise ValueError(f"[plane_light] fusion: expected a number in [0, 1), got {fusion!r}")
        self.f = float(fusion)
        self.n = n_cells
        self.reset()
        self.outliers_rejected = 0
        self.resets = 0

    def reset(self) -> None:
        self.est = np.zeros((self.n, 3), np.float32)
        self.nobs = np.zeros(self.n, np.int32)
        self.run = np.zeros(self.n, np.int32)  # consecutive outlier frames
        self.conf = np.zeros(self.n, np.float32)

    def update(self, value: np.ndarray, observed: np.ndarray, coverage: np.ndarray) -> None:
        # element-wise over all cells with np.where (the same float32 operations per cell as boolean-
        # indexed assignments, without their gathers and scatters)
        f = self.f
        fresh = observed & (self.nobs == 0)
        old = observed & (self.nobs > 0)
        lum_v = value @ _LUMA
        lum_e = self.est @ _LUMA
        rel = np.abs(lum_v - lum_e) / np.maximum(lum_e, 1e-6)
        out = old & (rel > OUTLIER_REL)
        n_old = np.count_nonzero(old)
        if f > 0 and n_old >= 8 and np.count_nonzero(out) > 0.5 * n_old:
            # more than half the plane changed at once: the light changed, start again
            self.resets += 1
            self.reset()
            fresh, old, out = observed.copy(), np.zeros_like(observed), np.zeros_like(observed)
        if f == 0:
            out[:] = False
        self.run = np.where(out, self.run + 1, np.where(observed, 0, self.run))
        persistent = out & (self.run >= OUTLIER_FRAMES)
        take = fresh | persistent
        blend = old & ~out
        kept_out = out & ~persistent
        self.outliers_rejected += int(np.count_nonzero(kept_out))
        # take and blend are disjoint (blend needs an earlier value, take is new or a persistent outlier)
        self.est = np.where(take[:, None], value, np.where(blend[:, None], f * self.est + (1.0 - f) * value, self.est))
        self.nobs = np.where(take, np.int32(1), self.nobs + blend.astype(np.int32))
        self.run[take] = 0
        # confidence: how many observations the estimate rests on (saturating at the fusion window),
        # times this frame's coverage; decays while the cell is not seen.
        window = 1.0 / (1.0 - f) if f > 0 else 1.0
        c_obs = np.minimum(self.nobs / window, 1.0) * np.clip(coverage / MIN_CELL_COVERAGE, 0, 1) ** 0.5
        self.conf = np.where(take | blend, np.maximum(c_obs, 0.5 * self.conf), self.conf * max(f, 0.5)).astype(
            np.float32
        )
        self.conf[kept_out] *= 0.9

    @property
    def has_value(self) -> np.ndarray:
        return self.nobs > 0


def _moved(T_prev: np.ndarray, T: np.ndarray, cell_m: float) -> bool:
    """Whether a grid frame moved by more than half a cell or turned by more than 2 degrees."""
    dt = np.linalg.norm(T[:3, 3] - T_prev[:3, 3])
    cosang = (np.trace(T_prev[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
    return dt > cell_m / 2.0 or np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))) > 2.0


def _world_pose(odo: Any, T_cam_obj: np.ndarray) -> np.ndarray | None:
    """``T_world_obj`` from a frame's odometry result (``results["odometry"]``), or None without one."""
    T_cw = getattr(odo, "T_cam_world", None)
    if T_cw is None:
        return None
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    T_wc = np.eye(4)
    T_wc[:3, :3], T_wc[:3, 3] = R.T, -R.T @ t
    return T_wc @ T_cam_obj


class PlaneLightStage(Stage):
    """Measures the anchor plane's illumination; writes ``results["plane_light"]`` (:class:`PlaneLight`).

    Reads ``results["anchor"]`` (and ``results["planes"]`` for the plane's label). On a synthetic
    anchor nothing real lies under the object: no cell is observed, the fused estimate (if any) is
    dropped, and ``PlaneLight.mask`` is all False.

    Exposure: with ``Frame.exposure.scale`` known, radiance = linear / scale (absolute). Otherwise
    the scale is estimated from the plane: the median ratio of this frame's linear values to the
    fused radiance over cells seen in both (so a changing auto exposure is followed without the
    light level drifting), or on the first frame the scale that maps the plane's median luminance
    to 0.18. ``PlaneLight.exposure_scale`` records the scale used and ``exposure_source`` where it
    came from.

    Parameters
    ----------
    cfg : Config
    response_lut : (256, 3) array, optional
        The camera's response curve; default: loaded from ``[source] response_curve`` when set,
        else the sRGB curve.
    """

    name = "plane_light"
    requires = (ANCHOR,)
    optional = (PLANES, ODOMETRY)
    provides = (PLANE_LIGHT,)

    def __init__(self, cfg: Config, response_lut: np.ndarray | None = None):
        pl = cfg.plane_light
        if pl.grid < 2:
            raise ValueError(f"[plane_light] grid: expected an int >= 2, got {pl.grid!r}")
        if not pl.extent_m > 0:
            raise ValueError(f"[plane_light] extent_m: expected a positive length in metres, got {pl.extent_m!r}")
        if not pl.assumed_albedo > 0:
            raise ValueError(f"[plane_light] assumed_albedo: expected a number in (0, 1], got {pl.assumed_albedo!r}")
        self.grid = int(pl.grid)
        self.extent = float(pl.extent_m)
        self.albedo = float(pl.assumed_albedo)
        self.sigma = float(pl.smoothing_cells)
        self.n_extra = int(pl.extra_planes)
        if self.n_extra < 0:
            raise ValueError(f"[plane_light] extra_planes: expected an int >= 0, got {pl.extra_planes!r}")
        self._extra_state: dict[int, tuple[CellFusion, np.ndarray]] = {}
        if self.sigma < 0:
            raise ValueError(f"[plane_light] smoothing_cells: expected a number >= 0, got {pl.smoothing_cells!r}")
        self.thr = float(cfg.planes.inlier_threshold_m)
        if response_lut is None and cfg.source.response_curve:
            response_lut = load_response_lut(cfg.source.response_curve)
        self.lut = response_lut
        self.vertices = grid_vertices(self.grid, self.extent)
        self.normals = np.tile(np.array([0.0, 1.0, 0.0]), (self.grid * self.grid, 1))
        self.fusion = CellFusion(self.grid * self.grid, float(pl.fusion))
        # the wider context grid for the light estimate's lamp search (0 = off)
        self.ctx_extent = float(pl.context_extent_m)
        self.ctx_grid = int(pl.context_grid) if self.ctx_extent > 0 else 0
        if self.ctx_extent < 0 or (self.ctx_extent > 0 and self.ctx_grid < 2):
            raise ValueError(
                f"[plane_light] context_extent_m / context_grid: expected a length >= 0 and an int >= 2, "
                f"got {pl.context_extent_m!r} / {pl.context_grid!r}"
            )
        if self.ctx_grid:
            self.ctx_vertices = grid_vertices(self.ctx_grid, self.ctx_extent)
            self.ctx_fusion = CellFusion(self.ctx_grid * self.ctx_grid, float(pl.fusion))
        self.ctx_every = int(pl.context_every)
        self._ctx_age = 0  # frames since the context grid was last measured
        self._ctx: dict[str, Any] = {}  # its PlaneLight fields since then ({} before the first)
        self._T_ref: np.ndarray | None = None  # anchor pose (camera frame) at the last restart of the fusion
        self._T_ref_world: np.ndarray | None = None  # the same in the odometry's world frame, when known
        self._scale_rel: float | None = None
        self._warn = LogOnce(log, "plane_light")
        self._last: PlaneLight | None = None
        self.frames = 0
        self.anchor_resets = 0
        self.observed_cells = 0

    def _moved(self, T: np.ndarray, T_world: np.ndarray | None = None) -> bool:
        """Whether the grid must restart: the anchor moved since the last restart (in the world when
        both poses are known there, so that camera motion alone does not count)."""
        cell = self.extent / (self.grid - 1)
        if T_world is not None and self._T_ref_world is not None:
            return _moved(self._T_ref_world, T_world, cell)
        return self._T_ref is None or _moved(self._T_ref, T, cell)

    def process(self, frame: Frame) -> Frame:
        self.frames += 1
        anchor: Anchor = self.require(frame, ANCHOR)
        label = "synthetic"
        for p in frame.results.get(PLANES.name, ()):
            if p.id == anchor.plane_id:
                label = p.label
        P = self.grid * self.grid
        if anchor.synthetic:
            self.fusion.reset()
            if self.ctx_grid:
                self.ctx_fusion.reset()
                self._ctx = {}
            self._T_ref = None
            self._T_ref_world = None
            lin = np.zeros((P, 3), np.float32)
            observed = np.zeros(P, bool)
            coverage = np.zeros(P, np.float32)
        else:
            # Compared with the pose at the last restart, not the previous frame, so that slow
            # drift (a moving camera re-anchoring a little each frame) also restarts the grid once
            # it adds up to half a cell. The relative exposure scale is kept: moving is no reason
            # for the exposure to have changed.
            odo = frame.results.get(ODOMETRY.name)
            T_world = _world_pose(odo, anchor.T_cam_obj)
            if self._moved(anchor.T_cam_obj, T_world):
                if self._T_ref is not None:
                    self.anchor_resets += 1
                self.fusion.reset()
                if self.ctx_grid:
                    self.ctx_fusion.reset()
                    self._ctx = {}
                self._T_ref_world = T_world
                self._T_ref = anchor.T_cam_obj.copy()
            lin, observed, coverage = measure_cells(frame, anchor.T_cam_obj, self.grid, self.extent, self.thr, self.lut)
        self.observed_cells = int(observed.sum())
        scale, source = self._exposure(frame, lin, observed)
        E = (np.pi / self.albedo) * lin / np.float32(scale)
        self.fusion.update(E.astype(np.float32), observed, coverage)
        has = self.fusion.has_value
        raw = np.where(has[:, None], self.fusion.est, 0.0).astype(np.float32)
        parts = [
            (
                self.vertices,
                self.normals,
                smooth_cells(raw, has, self.grid, self.sigma),
                has.copy(),
                np.where(has, self.fusion.conf, 0.0),
                observed,
                label,
                raw,
            )
        ]
        if self.n_extra and not anchor.synthetic:
            parts += self._extra(frame, anchor, scale)
        elif self._extra_state:
            self._extra_state.clear()
        if self.ctx_grid and not anchor.synthetic:
            self._ctx_age += 1
            if self._ctx_age >= self.ctx_every or not self.ctx_fusion.has_value.any():
                self._ctx_age = 0
                # same samples a cell, exposure scale and albedo as the grid: the same units, over a
                # wider square (3 x 3 samples a cell were tried: the lamp suite 0.044 -> 0.064)
                lin_c, obs_c, cov_c = measure_cells(
                    frame, anchor.T_cam_obj, self.ctx_grid, self.ctx_extent, self.thr, self.lut
                )
                E_c = (np.pi / self.albedo) * lin_c / np.float32(scale)
                self.ctx_fusion.update(E_c.astype(np.float32), obs_c, cov_c)
                has_c = self.ctx_fusion.has_value
                # built when measured only; the frames between carry the same arrays
                self._ctx = {
                    "context_grid": self.ctx_grid,
                    "context_vertices": self.ctx_vertices,
                    "context_irradiance": np.where(has_c[:, None], self.ctx_fusion.est, 0.0).astype(np.float32),
                    "context_mask": has_c.copy(),
                }
        ctx = self._ctx if not anchor.synthetic else {}
        self._last = PlaneLight(
            vertices=np.concatenate([p[0] for p in parts]) if len(parts) > 1 else self.vertices,
            normals=np.concatenate([p[1] for p in parts]) if len(parts) > 1 else self.normals,
            irradiance=np.concatenate([p[2] for p in parts]).astype(np.float32),
            mask=np.concatenate([p[3] for p in parts]),
            confidence=np.concatenate([p[4] for p in parts]).astype(np.float32),
            grid=self.grid,
            exposure_scale=float(scale),
            plane_slices=tuple(slice(k * P, (k + 1) * P) for k in range(len(parts))),
            labels=tuple(p[6] for p in parts),
            observed=np.concatenate([p[5] for p in parts]),
            exposure_source=source,
            irradiance_raw=np.concatenate([p[7] for p in parts]),
            **ctx,
        )
        return frame.with_result(PLANE_LIGHT, self._last)

    def _extra(self, frame: Frame, anchor: Anchor, scale: float) -> list[tuple]:
        """Measure up to ``[plane_light] extra_planes`` more planes (walls first, then by area).

        Each gets a grid of the same size on its own plane, centred on the anchor origin projected
        onto it and lifted by half the extent along the anchor's up direction (so a wall's grid
        stands on the floor rather than reaching under it). Vertices and normals are expressed in
        the anchor's object frame; each plane has its own fusion, reset when its grid moves.
        """
        planes = [p for p in frame.results.get(PLANES.name, ()) if p.id != anchor.plane_id]
        planes.sort(key=lambda p: (p.label != "wall", -p.area_m2))
        R_a, t_a = anchor.R, anchor.t
        up = R_a[:, 1]
        out, keep = [], set()
        P = self.grid * self.grid
        for p in planes[: self.n_extra]:
            n = np.asarray(p.normal, np.float64)
            o = t_a - p.distance(t_a) * n
            lift = up - (up @ n) * n
            if np.linalg.norm(lift) > 1e-6:
                o = o + (self.extent / 2.0) * lift / np.linalg.norm(lift)
            T = object_frame(n, o)
            fusion, T_ref = self._extra_state.get(p.id, (None, None))
            if fusion is None:
                fusion = CellFusion(P, self.fusion.f)
            if T_ref is None or _moved(T_ref, T, self.extent / (self.grid - 1)):
                fusion.reset()
                T_ref = T
            lin, obs, cov = measure_cells(frame, T, self.grid, self.extent, self.thr, self.lut)
            fusion.update(((np.pi / self.albedo) * lin / np.float32(scale)).astype(np.float32), obs, cov)
            self._extra_state[p.id] = (fusion, T_ref)
            keep.add(p.id)
            has = fusion.has_value
            raw = np.where(has[:, None], fusion.est, 0.0).astype(np.float32)
            v_cam = self.vertices @ T[:3, :3].T + T[:3, 3]
            v_obj = (v_cam - t_a) @ R_a
            n_obj = np.tile(R_a.T @ n, (P, 1))
            out.append(
                (
                    v_obj,
                    n_obj,
                    smooth_cells(raw, has, self.grid, self.sigma),
                    has.copy(),
                    np.where(has, fusion.conf, 0.0),
                    obs,
                    p.label,
                    raw,
                )
            )
        for pid in list(self._extra_state):
            if pid not in keep:
                del self._extra_state[pid]
        return out

    def _exposure(self, frame: Frame, lin: np.ndarray, observed: np.ndarray) -> tuple[float, str]:
        s = frame.exposure.scale
        if s is not None and s > 0:
            return float(s), "metadata"
        lum = lin @ _LUMA
        both = observed & self.fusion.has_value
        if self._scale_rel is not None and both.sum() >= 8:
            rad = (self.fusion.est[both] @ _LUMA) * (self.albedo / np.pi)
            ratio = lum[both] / np.maximum(rad, 1e-9)
            self._scale_rel = float(np.median(ratio))
        elif self._scale_rel is None and observed.any():
            self._scale_rel = float(np.median(lum[observed])) / REFERENCE_RADIANCE
        if not self._scale_rel or not np.isfinite(self._scale_rel) or self._scale_rel <= 0:
            self._scale_rel = 1.0
        return self._scale_rel, "plane"

    def stats(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "observed_cells": self.observed_cells,
            "fused_cells": int(self.fusion.has_value.sum()),
            "outliers_rejected": self.fusion.outliers_rejected,
            "light_change_resets": self.fusion.resets,
            "anchor_moved_resets": self.anchor_resets,
            "warnings": dict(self._warn.counts),
        }
