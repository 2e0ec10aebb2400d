"""Relight API: one RGB-D image + intrinsics + anchor pixel + bundle -> the placed object and its
predicted radiance (what ``illuminet relight`` writes; the way to check results from outside).

Pipeline: the project's plane detection, anchor and plane-light stages (``[planes]``, ``[anchor]``,
``[plane_light]``; :func:`lighting_stages`) when present in this build, else
:func:`fallback_plane_light` (a local plane fit around the anchor pixel and direct sampling of the
grid; documented below), then the shading
(:class:`~illuminet.runtime.stages.shading.ShadingStage`: the bundle's PRT from the frame's light
estimate when the chain produced one, else its learned chain), then carrying proxy shading to the
render mesh. When the frame has a light estimate (``results["light"]``), the npz also carries it
(:func:`light_fields`).

Units: ``radiance`` is the linear RGB that a *white Lambertian* surface (albedo 1) would show in the
input image's own linear units, i.e. ``radiance = E / pi * exposure_scale``; re-encoding with the
frame's transfer curve (sRGB unless a response curve is configured) gives pixel values.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from illuminet.runtime.config import Config, apply_overrides
from illuminet.runtime.frame import Exposure, Frame, Intrinsics
from illuminet.runtime.physics import INV_PI, linearize
from illuminet.runtime.scene import ANCHOR, LIGHT, PLANE_LIGHT, Anchor, LightEstimate, PlaneLight
from illuminet.runtime.stage import StageChain

log = logging.getLogger(__name__)


@dataclass
class RelightResult:
    """The placed object (camera coordinates) and its predicted per-vertex radiance."""

    vertices: np.ndarray      # (R, 3) camera coordinates, metres
    normals: np.ndarray       # (R, 3) camera coordinates, unit
    faces: np.ndarray         # (F, 3) int32
    radiance: np.ndarray      # (R, 3) linear RGB of a white diffuse surface, input image's linear units
    irradiance: np.ndarray    # (R, 3) scene-referred irradiance E (radiance = E / pi * exposure_scale)
    proxy_irradiance: np.ndarray  # (V, 3)
    oi: np.ndarray            # (V, 3, 3) proxy OI, camera frame (channel, xyz)
    T_cam_obj: np.ndarray     # (4, 4)
    exposure_scale: float
    dominant_dir: np.ndarray  # (3,) towards the dominant light, camera frame
    dominant_share: float
    method: str
    bundle: str
    plane_source: str         # "stages" or "fallback"
    plane_observed: float     # fraction of the plane grid that was observed
    light: LightEstimate | None = None  # the frame's light estimate, when the chain made one

    def save(self, path) -> None:
        """Write the documented npz (see docs/models.md, "relight npz"), with :func:`light_fields` when
        the frame had a light estimate."""
        extra = light_fields(self.light) if self.light is not None else {}
        np.savez_compressed(
            path, vertices=self.vertices.astype(np.float32), normals=self.normals.astype(np.float32),
            faces=self.faces.astype(np.int32), radiance=self.radiance.astype(np.float32),
            irradiance=self.irradiance.astype(np.float32), proxy_irradiance=self.proxy_irradiance.astype(np.float32),
            oi=self.oi.astype(np.float32), T_cam_obj=self.T_cam_obj.astype(np.float64),
            exposure_scale=np.float64(self.exposure_scale), dominant_dir=self.dominant_dir.astype(np.float32),
            dominant_share=np.float64(self.dominant_share), method=np.str_(self.method),
            bundle=np.str_(self.bundle), plane_source=np.str_(self.plane_source),
            plane_observed=np.float64(self.plane_observed), format=np.int64(1), **extra,
        )


#: the frame the light fields of the relight npz are given in
LIGHT_FRAME = "object: anchor-centred, +Y up (gravity-aligned), metres"


def light_fields(estimate: LightEstimate) -> dict[str, np.ndarray]:
    """The relight npz's fields of a :class:`~illuminet.runtime.scene.LightEstimate` (object frame).

    ``sh9`` (9, 3) ambient irradiance SH and ``sh9_radiance`` (9, 3) the same as radiance (both
    without the primary light), ``primary_dir`` (3,) towards the primary light (NaN when there is
    none), ``primary_rgb`` (3,) its irradiance at the anchor (0 when there is none), ``primary_pos``
    (3,) its position (NaN when unknown: a distant light), ``light_frame`` (:data:`LIGHT_FRAME`).
    """
    nan3 = np.full(3, np.nan, np.float32)
    has = estimate.primary_dir is not None
    return {
        "sh9": np.asarray(estimate.sh9, np.float32).reshape(9, 3),
        "sh9_radiance": estimate.radiance_sh9().astype(np.float32),
        "primary_dir": np.asarray(estimate.primary_dir, np.float32).reshape(3) if has else nan3,
        "primary_rgb": np.asarray(estimate.primary_rgb, np.float32).reshape(3) if has else np.zeros(3, np.float32),
        "primary_pos": (np.asarray(estimate.primary_pos, np.float32).reshape(3)
                        if estimate.primary_pos is not None else nan3),
        "light_frame": np.str_(LIGHT_FRAME),
    }


def lighting_stages(cfg: Config, response_lut=None) -> list | None:
    """The stages that measure the light for relight (unopened): the project's plane / anchor /
    plane-light stages, when this build has them (``None``: use :func:`fallback_plane_light`).

    A stage added here that provides ``results["light"]`` (the light estimate) makes relight shade
    with the bundle's PRT and write the light into the npz.
    """
    try:
        from illuminet.runtime.stages.anchor import AnchorStage
        from illuminet.runtime.stages.plane_light import PlaneLightStage
        from illuminet.runtime.stages.planes import PlaneStage
    except ImportError:  # a stripped-down build: use the local fallback
        return None
    stages = [PlaneStage(cfg), AnchorStage(cfg), PlaneLightStage(cfg, response_lut=response_lut)]
    if cfg.light.enabled:
        from illuminet.runtime.stages.light_estimate import LightEstimateStage

        stages.append(LightEstimateStage(cfg, response_lut=response_lut))
    return stages


def fallback_plane_light(frame: Frame, pixel: tuple[float, float], grid: int, extent: float,
                         albedo: float, response_lut=None) -> tuple[Anchor, PlaneLight]:
    """Minimal anchor + plane light for builds without the planes stages (used by :func:`relight`).

    Fits a plane (least squares with iterative inlier selection, threshold growing with z^2) to the
    depth points within 0.4 m of the anchor pixel's 3D point, builds the object frame (origin at the
    anchor on the plane, +Y the plane normal towards the camera, X along the image's x axis), and
    samples the grid: each vertex projected into the image is observed when the depth there agrees
    with the plane; irradiance = linear colour (3x3 mean) * pi / (albedo * exposure scale).
    """
    depth, K = frame.depth, frame.intrinsics
    if depth is None:
        raise ValueError("relight needs a depth image aligned to the colour image")
    h, w = depth.shape
    px, py = int(round(pixel[0])), int(round(pixel[1]))
    if not (0 <= px < w and 0 <= py < h):
        raise ValueError(f"anchor pixel ({pixel[0]}, {pixel[1]}) is outside the {w}x{h} image")
    win = depth[max(py - 4, 0):py + 5, max(px - 4, 0):px + 5]
    if not (win > 0).any():
        raise ValueError(f"no valid depth near the anchor pixel ({px}, {py})")
    z0 = float(np.median(win[win > 0]))
    a = np.array([(px - K.cx) / K.fx * z0, (py - K.cy) / K.fy * z0, z0])
    ys, xs = np.nonzero(depth > 0)
    step = max(1, int(np.sqrt(len(xs) / 40000)))
    ys, xs = ys[::step], xs[::step]
    z = depth[ys, xs]
    pts = np.stack([(xs - K.cx) / K.fx * z, (ys - K.cy) / K.fy * z, z], 1)
    near = np.linalg.norm(pts - a, axis=1) < 0.4
    p = pts[near]
    if len(p) < 50:
        raise ValueError(f"too few depth points around the anchor ({len(p)}) to fit a plane")
    thr = 0.01 * max(z0, 0.3) ** 2 * 2
    inl = np.ones(len(p), bool)
    for _ in range(5):
        c = p[inl].mean(0)
        _, _, vt = np.linalg.svd(p[inl] - c, full_matrices=False)
        n = vt[2]
        d = np.abs((p - c) @ n)
        new = d < max(thr, np.percentile(d, 60))
        if new.sum() < 30:
            break
        inl = new
    if n @ c > 0:  # normal towards the camera
        n = -n
    origin = a - ((a - c) @ n) * n
    xa = np.array([1.0, 0, 0]) - n * n[0]
    if np.linalg.norm(xa) < 1e-3:
        xa = np.array([0, 0, 1.0]) - n * n[2]
    xa /= np.linalg.norm(xa)
    za = np.cross(xa, n)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = xa, n, za, origin
    anchor = Anchor(T_cam_obj=T, plane_id=0, synthetic=False)

    g = np.linspace(-extent / 2, extent / 2, grid)
    zz, xx = np.meshgrid(g, g, indexing="ij")
    v_obj = np.stack([xx.ravel(), np.zeros(grid * grid), zz.ravel()], 1)
    v_cam = v_obj @ T[:3, :3].T + T[:3, 3]
    zc = v_cam[:, 2]
    u = K.fx * v_cam[:, 0] / np.maximum(zc, 1e-6) + K.cx
    vv = K.fy * v_cam[:, 1] / np.maximum(zc, 1e-6) + K.cy
    ui, vi = np.rint(u).astype(int), np.rint(vv).astype(int)
    inside = (zc > 0.05) & (ui >= 1) & (ui < w - 1) & (vi >= 1) & (vi < h - 1)
    lin = linearize(frame.color, response_lut)
    k = frame.exposure.scale or 1.0
    irr = np.zeros((grid * grid, 3), np.float32)
    mask = np.zeros(grid * grid, bool)
    for i in np.nonzero(inside)[0]:
        dz = depth[vi[i] - 1:vi[i] + 2, ui[i] - 1:ui[i] + 2]
        ok = dz > 0
        if not ok.any() or abs(float(np.median(dz[ok])) - zc[i]) > 0.03 + 0.02 * zc[i] ** 2:
            continue  # off the plane, occluded, or a depth hole
        irr[i] = lin[vi[i] - 1:vi[i] + 2, ui[i] - 1:ui[i] + 2].reshape(-1, 3).mean(0) * np.pi / (albedo * k)
        mask[i] = True
    pl = PlaneLight(vertices=v_obj.astype(np.float32), normals=np.tile([[0, 1, 0]], (grid * grid, 1)).astype(np.float32),
                    irradiance=irr, mask=mask, confidence=mask.astype(np.float32), grid=grid, exposure_scale=k,
                    plane_slices=(slice(0, grid * grid),), labels=("floor",))
    return anchor, pl


def relight(color: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, anchor_px: tuple[float, float],
            cfg: Config, bundle: str | None = None, exposure: Exposure | None = None,
            precision: str | None = None) -> RelightResult:
    """Predict the radiance of a virtual object placed at ``anchor_px`` in one RGB-D image.

    Parameters
    ----------
    color : (H, W, 3) uint8 RGB (sRGB, or the configured response curve)
    depth : (H, W) float32 metres aligned to colour, 0 = invalid
    intrinsics : Intrinsics of the colour image
    anchor_px : (x, y) pixel where the object stands
    cfg : Config (``[planes]``, ``[anchor]``, ``[plane_light]``, ``[model]`` are used)
    bundle, precision : override ``[model] bundle`` / ``precision``
    exposure : Exposure metadata, when known (else the image's own linear units are used)
    """
    from illuminet.runtime.assets.bundle import load_bundle
    from illuminet.runtime.stages.shading import ShadingStage

    h, w = np.shape(depth)[:2]
    if not (0 <= anchor_px[0] < w and 0 <= anchor_px[1] < h):
        raise ValueError(f"anchor pixel ({anchor_px[0]}, {anchor_px[1]}) is outside the {w}x{h} image")
    over = [("anchor", "mode", "pixel"), ("anchor", "pixel", [float(anchor_px[0]), float(anchor_px[1])])]
    if bundle is not None:
        over.append(("model", "bundle", bundle))
    if precision is not None:
        over.append(("model", "precision", precision))
    if cfg.model.shading != "auto":
        log.info("relight uses [model] shading = %s", cfg.model.shading)
    cfg = apply_overrides(cfg, over)
    frame = Frame(seq=0, t_device_ns=0, t_host_ns=0, color=color, depth=depth, intrinsics=intrinsics,
                  exposure=exposure or Exposure())
    response_lut = None
    if cfg.source.response_curve:
        from illuminet.runtime.physics import load_response_lut

        response_lut = load_response_lut(cfg.source.response_curve)
    load_bundle(cfg.model.bundle)  # a missing or damaged bundle is an error here, not a fallback
    shading_stage = ShadingStage(apply_overrides(cfg, [("model", "temporal_smoothing", 0.0)]))
    shading_stage.open()
    b = shading_stage.bundle
    stages = lighting_stages(cfg, response_lut)
    light = None
    if stages is not None:
        f = frame
        for st in stages:
            st.open()
        try:
            f = StageChain(stages)(f)
        finally:
            for st in stages:
                st.close()
        if ANCHOR.name not in f.results or PLANE_LIGHT.name not in f.results:
            raise ValueError(f"no plane found under the anchor pixel ({anchor_px[0]}, {anchor_px[1]}): "
                             "the depth there does not belong to a detected plane")
        anchor, pl, source = f.results[ANCHOR.name], f.results[PLANE_LIGHT.name], "stages"
        light = f.results.get(LIGHT.name)
        if anchor.synthetic or not np.any(pl.mask):
            raise ValueError(f"no real plane observed under the anchor pixel ({anchor_px[0]}, {anchor_px[1]}); "
                             "relight needs the plane under the object to be visible in the image")
    else:
        anchor, pl = fallback_plane_light(frame, anchor_px, cfg.plane_light.grid, cfg.plane_light.extent_m,
                                          cfg.plane_light.assumed_albedo, response_lut)
        source = "fallback"
    if shading_stage.mode == "prt" and light is None:
        raise ValueError('[model] shading = "prt" needs a light estimate, and relight\'s chain made none on this '
                         'image: use shading "auto" or "model"')
    sh = shading_stage.predict(pl, light)
    shading_stage.close()
    R, t = anchor.R, anchor.t
    scale = float(cfg.render.object_scale)
    irr = np.maximum(b.carry(sh.irradiance), 0.0)
    oi = sh.oi if sh.oi is not None else np.zeros((b.n_proxy, 3, 3), np.float32)
    dom = sh.dominant_dir if sh.dominant_dir is not None else np.array([0, 1, 0], np.float32)
    first = pl.plane_slices[0] if pl.plane_slices else slice(None)
    return RelightResult(
        vertices=(b.vertices * scale) @ R.T + t, normals=b.normals @ R.T, faces=b.faces,
        radiance=irr * INV_PI * pl.exposure_scale, irradiance=irr, proxy_irradiance=sh.irradiance,
        oi=np.einsum("vcx,yx->vcy", oi, R), T_cam_obj=np.asarray(anchor.T_cam_obj), exposure_scale=float(pl.exposure_scale),
        dominant_dir=(R @ dom).astype(np.float32), dominant_share=float(sh.dominant_share), method=sh.method,
        bundle=str(b.path), plane_source=source, plane_observed=float(np.mean(pl.mask[first])), light=light,
    )
