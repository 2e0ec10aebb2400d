"""Relight API: one RGB-D image + intrinsics + anchor pixel + bundle -> the placed object and its
predicted radiance (what ``illuminet relight`` writes; the way to check results from outside).

Pipeline: the project's plane detection, anchor and plane-light stages (``[planes]``, ``[anchor]``,
``[plane_light]``, ``[light]``; :func:`lighting_stages`), then the shading
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
import math
import os
from dataclasses import dataclass

import numpy as np

from illuminet.runtime.config import Config, apply_overrides
from illuminet.runtime.files import written_whole
from illuminet.runtime.frame import Exposure, Frame, Intrinsics
from illuminet.runtime.physics import INV_PI
from illuminet.runtime.scene import ANCHOR, LIGHT, PLANE_LIGHT, LightEstimate
from illuminet.runtime.stage import StageChain

log = logging.getLogger(__name__)


@dataclass
class RelightResult:
    """The placed object (camera coordinates) and its predicted per-vertex radiance."""

    vertices: np.ndarray  # (R, 3) camera coordinates, metres
    normals: np.ndarray  # (R, 3) camera coordinates, unit
    faces: np.ndarray  # (F, 3) int32
    radiance: np.ndarray  # (R, 3) linear RGB of a white diffuse surface, input image's linear units
    irradiance: np.ndarray  # (R, 3) scene-referred irradiance E (radiance = E / pi * exposure_scale)
    proxy_irradiance: np.ndarray  # (V, 3)
    oi: np.ndarray  # (V, 3, 3) proxy OI, camera frame (channel, xyz)
    T_cam_obj: np.ndarray  # (4, 4)
    exposure_scale: float
    dominant_dir: np.ndarray  # (3,) towards the dominant light, camera frame
    dominant_share: float
    method: str
    bundle: str
    plane_source: str  # "stages" (kept in the npz: format 1 never drops a field)
    plane_observed: float  # fraction of the plane grid that was observed
    light: LightEstimate | None = None  # the frame's light estimate, when the chain made one

    def save(self, path) -> str | None:
        """Write the documented npz (see docs/models.md, "relight npz"), with :func:`light_fields` when
        the frame had a light estimate. Returns the file name written (numpy adds ``.npz`` to a name
        without it: :func:`npz_path`), None for a file object."""
        extra = light_fields(self.light) if self.light is not None else {}
        written = None if hasattr(path, "write") else npz_path(path)
        if written is None:
            self._write(path, extra)
            return None
        # a write that failed (a full disk) left a truncated npz in place of the previous result
        with written_whole(written) as tmp:
            self._write(tmp, extra)
        return written

    def _write(self, path, extra: dict) -> None:
        np.savez_compressed(
            path,
            vertices=self.vertices.astype(np.float32),
            normals=self.normals.astype(np.float32),
            faces=self.faces.astype(np.int32),
            radiance=self.radiance.astype(np.float32),
            irradiance=self.irradiance.astype(np.float32),
            proxy_irradiance=self.proxy_irradiance.astype(np.float32),
            oi=self.oi.astype(np.float32),
            T_cam_obj=self.T_cam_obj.astype(np.float64),
            exposure_scale=np.float64(self.exposure_scale),
            dominant_dir=self.dominant_dir.astype(np.float32),
            dominant_share=np.float64(self.dominant_share),
            method=np.str_(self.method),
            bundle=np.str_(self.bundle),
            plane_source=np.str_(self.plane_source),
            plane_observed=np.float64(self.plane_observed),
            format=np.int64(1),
            **extra,
        )


def npz_path(path) -> str:
    """The file :func:`numpy.savez_compressed` writes for ``path``: ``.npz`` appended unless the name
    ends with it (case-sensitively, as numpy does: ``r.out`` -> ``r.out.npz``)."""
    p = os.fspath(path)
    return p if p.endswith(".npz") else p + ".npz"


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
        "primary_pos": (
            np.asarray(estimate.primary_pos, np.float32).reshape(3) if estimate.primary_pos is not None else nan3
        ),
        "light_frame": np.str_(LIGHT_FRAME),
    }


def lighting_stages(cfg: Config, response_lut=None) -> list:
    """The stages that measure the light for relight (unopened): planes, anchor, plane light and,
    with ``[light] enabled``, the light estimate.

    A stage added here that provides ``results["light"]`` (the light estimate) makes relight shade
    with the bundle's PRT and write the light into the npz.
    """
    from illuminet.runtime.stages.anchor import AnchorStage
    from illuminet.runtime.stages.plane_light import PlaneLightStage
    from illuminet.runtime.stages.planes import PlaneStage

    stages = [PlaneStage(cfg), AnchorStage(cfg), PlaneLightStage(cfg, response_lut=response_lut)]
    if cfg.light.enabled:
        from illuminet.runtime.stages.light_estimate import LightEstimateStage

        stages.append(LightEstimateStage(cfg, response_lut=response_lut))
    return stages


#: largest image ``relight`` takes (8K UHD is 33 Mpx): the command refuses an image header (PNG, JPEG, BMP,
#: TIFF, ...) claiming more before decoding it (a minute and gigabytes for a 1 MB PNG that says 20000x20000),
#: the Python API an array from its shape before any copy
MAX_IMAGE_PIXELS = 50_000_000
#: largest image side (pixels) intrinsics may claim: a width or height over it is not a camera's
MAX_INTRINSICS_SIDE = 100_000
#: the field of view (degrees, per axis) focal lengths must give: 2 atan(width / 2 fx) within these
FOV_RANGE_DEG = (0.5, 179.0)
#: relative difference of aspect ratios below which intrinsics made for another size are scaled
ASPECT_TOLERANCE = 0.01
#: exposure time (microseconds) and ISO accepted as metadata: what cameras report, with margin
EXPOSURE_US_RANGE = (1.0, 1e9)
ISO_RANGE = (1.0, 1e7)
#: a median depth over this (metres) is refused as millimetres given where metres were expected
MAX_MEDIAN_DEPTH_M = 100.0


def _is_number(v) -> bool:
    """A real number, not a bool (``True`` is an ``int`` to Python, never a focal length)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _shown(v, limit: int = 60) -> str:
    """``repr(v)`` cut to ``limit`` characters, for a message of one line."""
    r = " ".join(repr(v).split())
    return r if len(r) <= limit else r[: limit - 3] + "..."


def check_anchor_px(anchor_px, width: int, height: int, what: str = "anchor pixel") -> tuple[float, float]:
    """``anchor_px`` as ``(x, y)`` floats: exactly two finite real numbers (ints, floats or numpy scalars,
    not bools) in a tuple, list or (2,) array, inside the ``width`` x ``height`` image."""
    expected = "expected (x, y): two finite numbers in pixels of the colour image"
    if isinstance(anchor_px, np.ndarray):
        if anchor_px.shape != (2,):
            raise ValueError(f"{what}: {expected}, got an array of shape {anchor_px.shape}")
        vals = list(anchor_px)
    elif isinstance(anchor_px, (tuple, list)):
        if len(anchor_px) != 2:
            raise ValueError(f"{what}: {expected}, got {len(anchor_px)} values {_shown(anchor_px)}")
        vals = list(anchor_px)
    else:
        raise ValueError(f"{what}: {expected}, got {type(anchor_px).__name__} {_shown(anchor_px)}")
    for v in vals:
        if not _is_number(v):
            raise ValueError(f"{what}: {expected}, got {_shown(v)} ({type(v).__name__}) in {_shown(anchor_px)}")
    try:
        x, y = float(vals[0]), float(vals[1])
    except OverflowError:  # a Python int beyond any float
        x = y = math.inf
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"{what}: {expected}, got {_shown(anchor_px)}")
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(
            f"{what}: ({x:g}, {y:g}) is outside the {width}x{height} image; expected 0 <= x < {width} and "
            f"0 <= y < {height}"
        )
    return x, y


def check_intrinsics(K: Intrinsics, what: str = "intrinsics") -> None:
    """Focal lengths must be positive and every value finite; the size (when given) positive whole
    pixels up to :data:`MAX_INTRINSICS_SIDE`; the focal lengths a field of view in :data:`FOV_RANGE_DEG`
    for that size (1e30 or 1e-9 pixels is a unit or typing mistake, not a lens)."""
    if not isinstance(K, Intrinsics):
        raise ValueError(f"{what}: expected an Intrinsics, got {type(K).__name__}")
    for name in ("fx", "fy", "cx", "cy", "width", "height"):
        v = getattr(K, name)
        if not _is_number(v):
            raise ValueError(f"{what}: {name} must be a number in pixels, got {v!r} ({type(v).__name__})")
    if not all(math.isfinite(v) for v in (K.fx, K.fy, K.cx, K.cy)) or K.fx <= 0 or K.fy <= 0:
        raise ValueError(
            f"{what}: expected finite fx, fy > 0 and finite cx, cy in pixels, got fx={K.fx:g} fy={K.fy:g} "
            f"cx={K.cx:g} cy={K.cy:g}"
        )
    if not (math.isfinite(K.width) and math.isfinite(K.height)):  # 1e400 in JSON is inf: was "must be > 0"
        raise ValueError(
            f"{what}: width and height must be finite, got {K.width}x{K.height}; expected the image size in pixels"
        )
    if K.width <= 0 or K.height <= 0:
        raise ValueError(f"{what}: width and height must be > 0 pixels, got {K.width}x{K.height}")
    if K.width != int(K.width) or K.height != int(K.height):
        raise ValueError(f"{what}: width and height must be whole pixels, got {K.width:g}x{K.height:g}")
    if K.width > MAX_INTRINSICS_SIDE or K.height > MAX_INTRINSICS_SIDE:
        raise ValueError(
            f"{what}: width x height {K.width:g}x{K.height:g} is over {MAX_INTRINSICS_SIDE} pixels a side, not a "
            f"camera image; expected the image size in pixels the intrinsics were calibrated at"
        )
    if not (0 <= K.cx <= K.width and 0 <= K.cy <= K.height):
        # the optical axis outside the picture is no camera's; -5000 (a sign or unit slip) placed nothing and
        # blamed the plane ("no real plane observed under the anchor pixel")
        raise ValueError(
            f"{what}: principal point cx={K.cx:g}, cy={K.cy:g} is outside the {K.width:g}x{K.height:g} image; "
            f"expected pixels inside it, usually near the centre ({K.width / 2:g}, {K.height / 2:g})"
        )
    lo, hi = FOV_RANGE_DEG
    for f, side, fname, sname in ((K.fx, K.width, "fx", "wide"), (K.fy, K.height, "fy", "high")):
        fov = math.degrees(2.0 * math.atan(side / (2.0 * f)))
        if not lo <= fov <= hi:
            raise ValueError(
                f"{what}: {fname}={f:g} pixels for an image {int(side)} px {sname} is a {fov:.3g} deg field of "
                f"view; expected focal lengths in pixels giving {lo:g}-{hi:g} deg (typically 0.5-2x the image "
                f"width)"
            )


def fit_intrinsics(K: Intrinsics, width: int, height: int, what: str = "intrinsics") -> Intrinsics:
    """``K`` for a ``width`` x ``height`` image: as is when made for that size, scaled when made for a
    proportional one (calibrated at 1280x960, image 640x480), refused for another aspect ratio (scaling
    would stretch fx and fy differently: a silently wrong camera)."""
    if (K.width, K.height) == (width, height):
        return K
    a, b = K.width / K.height, width / height
    if abs(a - b) > ASPECT_TOLERANCE * b:
        raise ValueError(
            f"{what}: made for a {K.width:g}x{K.height:g} image but the colour image is {width}x{height}, another "
            f"aspect ratio; give the width and height the intrinsics were calibrated at (or none, for intrinsics "
            f"of this image)"
        )
    return K.scaled(width, height)


def check_depth(depth: np.ndarray, what: str = "depth") -> None:
    """Depth in metres must hold some finite value > 0 and not look like millimetres (median over
    :data:`MAX_MEDIAN_DEPTH_M`); else no plane can be found and the error would blame the plane."""
    d = np.asarray(depth)
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"{what}: expected a non-empty 2-D array of depths, got shape {d.shape}")
    if d.dtype.kind not in "fiu":
        raise ValueError(f"{what}: expected depths as numbers (metres), got {d.dtype}")
    valid = np.isfinite(d) & (d > 0)
    if not valid.any():
        with np.errstate(invalid="ignore"):
            counts = {
                "NaN": int(np.isnan(d).sum()) if d.dtype.kind == "f" else 0,
                "infinite": int(np.isinf(d).sum()) if d.dtype.kind == "f" else 0,
                "negative": int((d < 0).sum()),
                "zero (invalid)": int((d == 0).sum()),
            }
        parts = ", ".join(f"{n} {k}" for k, n in counts.items() if n)
        raise ValueError(
            f"{what}: no valid depth: none of its {d.size} values is a finite number > 0 ({parts}); expected "
            f"distances in metres (0 = invalid)"
        )
    med = float(np.median(d[valid]))
    if med > MAX_MEDIAN_DEPTH_M:
        raise ValueError(
            f"{what}: median depth {med:g} m looks like millimetres; float depth is in metres: divide by 1000 "
            f"(or give uint16 millimetres, e.g. a 16-bit PNG)"
        )
    # what the planes stage refuses (a map under 32x24, under 1 % valid, a median of 1 mm or 65.535 m):
    # said here, not as a warning followed by "no real plane observed under the anchor pixel"
    from illuminet.runtime.stages.plane_fit import check_depth as planes_check_depth

    with np.errstate(over="ignore"):  # float64 beyond float32: inf, which the planes count as invalid
        problem = planes_check_depth(d.astype(np.float32, copy=False))
    if problem is not None:
        raise ValueError(f"{what}: {problem[1]}")
    # depth beyond the planes' range (a wall 20 m off) is no cloud point: said here, not as "no real plane
    # observed under the anchor pixel ... needs the plane to be visible" for a plane in full view
    from illuminet.runtime.stages.plane_fit import MAX_DEPTH_M, MIN_DEPTH_M

    dv = d[valid]
    inside = float(np.mean((dv > MIN_DEPTH_M) & (dv < MAX_DEPTH_M)))
    if inside < 0.01:
        raise ValueError(
            f"{what}: {100 * (1 - inside):.0f} % of the valid depths lie outside {MIN_DEPTH_M:g}-{MAX_DEPTH_M:g} m, "
            f"the range planes are fitted in (median {med:g} m); expected a scene within it"
        )


def check_exposure(exposure, what: str = "exposure") -> None:
    """Exposure metadata, when given, must be plausible: time in microseconds within
    :data:`EXPOSURE_US_RANGE`, ISO within :data:`ISO_RANGE` (0, NaN or 1e308 would be ignored or
    turn the radiance into NaN)."""
    if exposure is None:
        return
    if not isinstance(exposure, Exposure):
        raise ValueError(
            f"{what}: expected an Exposure(exposure_us=..., iso=...) or None, got {type(exposure).__name__}"
        )
    for v, name, unit, (lo, hi) in (
        (exposure.exposure_us, "exposure time", " microseconds", EXPOSURE_US_RANGE),
        (exposure.iso, "ISO", "", ISO_RANGE),
    ):
        if v is None:
            continue
        if not _is_number(v) or not math.isfinite(v) or not lo <= v <= hi:
            shown = f"{v:g}" if _is_number(v) else repr(v)
            raise ValueError(
                f"{what}: the {name} must be a finite number from {lo:g} to {hi:g}{unit}, got {shown}; "
                f"expected the exposure time in microseconds and the ISO, e.g. 8000,400"
            )


def _clipped_share(color: np.ndarray, anchor_px: tuple[float, float], radius: int = 24) -> float:
    """Share of the colour pixels within ``radius`` of the anchor pixel with a channel clipped
    (>= :data:`~illuminet.runtime.stages.plane_light.SATURATED`): the plane light skips them."""
    from illuminet.runtime.stages.plane_light import SATURATED

    c = np.asarray(color)
    if c.ndim != 3 or c.dtype != np.uint8:
        return 0.0
    u, v = int(round(anchor_px[0])), int(round(anchor_px[1]))
    win = c[max(0, v - radius) : v + radius + 1, max(0, u - radius) : u + radius + 1]
    return float(np.mean(win.max(axis=2) >= SATURATED)) if win.size else 0.0


def relight(
    color: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    anchor_px: tuple[float, float],
    cfg: Config,
    bundle: str | None = None,
    exposure: Exposure | None = None,
    precision: str | None = None,
) -> RelightResult:
    """Predict the radiance of a virtual object placed at ``anchor_px`` in one RGB-D image.

    Parameters
    ----------
    color : (H, W, 3) uint8 RGB (sRGB, or the configured response curve)
    depth : (H, W) float32 metres aligned to colour, 0 = invalid
    intrinsics : Intrinsics of the colour image (made for a proportional size: scaled; another aspect
        ratio, an implausible field of view or size: refused, :func:`check_intrinsics`)
    anchor_px : (x, y) pixel where the object stands
    cfg : Config (``[planes]``, ``[anchor]``, ``[plane_light]``, ``[model]`` are used)
    bundle, precision : override ``[model] bundle`` / ``precision``
    exposure : Exposure metadata, when known (else the image's own linear units are used); values
        outside :data:`EXPOSURE_US_RANGE` / :data:`ISO_RANGE` are refused (:func:`check_exposure`)

    Raises
    ------
    ValueError
        A mistake in the inputs, one line naming it: see :func:`check_intrinsics`, :func:`check_depth`
        (no valid depth, or millimetres where metres are expected), :func:`check_exposure`, the anchor.
    """
    from illuminet.runtime.assets.bundle import load_bundle
    from illuminet.runtime.stages.shading import ShadingStage

    check_intrinsics(intrinsics)
    check_depth(depth)
    check_exposure(exposure)
    h, w = np.shape(depth)[:2]
    intrinsics = fit_intrinsics(intrinsics, w, h)  # made for a proportional size: scaled; else refused
    anchor_px = check_anchor_px(anchor_px, w, h)
    over = [("anchor", "mode", "pixel"), ("anchor", "pixel", list(anchor_px))]
    if bundle is not None:
        over.append(("model", "bundle", bundle))
    if precision is not None:
        over.append(("model", "precision", precision))
    if cfg.model.shading != "auto":
        log.info("relight uses [model] shading = %s", cfg.model.shading)
    cfg = apply_overrides(cfg, over)
    frame = Frame(
        seq=0,
        t_device_ns=0,
        t_host_ns=0,
        color=color,
        depth=depth,
        intrinsics=intrinsics,
        exposure=exposure or Exposure(),
    )
    response_lut = None
    if cfg.source.response_curve:
        from illuminet.runtime.physics import load_response_lut

        response_lut = load_response_lut(cfg.source.response_curve)
    load_bundle(cfg.model.bundle)  # a missing or damaged bundle is an error here, not a fallback
    shading_stage = ShadingStage(apply_overrides(cfg, [("model", "temporal_smoothing", 0.0)]))
    shading_stage.open()
    b = shading_stage.bundle
    from illuminet.runtime.stages.anchor import AnchorStage

    stages = lighting_stages(cfg, response_lut)
    for st in stages:
        if isinstance(st, AnchorStage):  # the caller gave the pixel, not [anchor] pixel: name it so
            st.pixel_name = "anchor pixel"
        st.open()
    try:
        f = StageChain(stages)(frame)
    finally:
        for st in stages:
            st.close()
    if ANCHOR.name not in f.results or PLANE_LIGHT.name not in f.results:
        raise ValueError(
            f"no plane found under the anchor pixel ({anchor_px[0]:g}, {anchor_px[1]:g}): "
            "the depth there does not belong to a detected plane"
        )
    anchor, pl, source = f.results[ANCHOR.name], f.results[PLANE_LIGHT.name], "stages"
    light = f.results.get(LIGHT.name)
    if not anchor.synthetic and not np.any(pl.mask):
        from illuminet.runtime.stages.plane_light import SATURATED

        clipped = _clipped_share(color, anchor_px)
        if clipped >= 0.5:
            raise ValueError(
                f"the plane under the anchor pixel ({anchor_px[0]:g}, {anchor_px[1]:g}) is overexposed: "
                f"{100 * clipped:.0f} % of the pixels around it are clipped (a channel >= {SATURATED}) and "
                "measure no light; use a shorter exposure, or an anchor pixel on a surface that is not clipped"
            )
    if anchor.synthetic or not np.any(pl.mask):
        raise ValueError(
            f"no real plane observed under the anchor pixel ({anchor_px[0]:g}, {anchor_px[1]:g}); "
            "relight needs the plane under the object to be visible in the image"
        )
    if shading_stage.mode == "prt" and light is None:
        raise ValueError(
            '[model] shading = "prt" needs a light estimate, and relight\'s chain made none on this '
            'image: use shading "auto" or "model"'
        )
    sh = shading_stage.predict(pl, light)
    shading_stage.close()
    R, t = anchor.R, anchor.t
    scale = float(cfg.render.object_scale)
    irr = np.maximum(sh.on_render_mesh(b.carry), 0.0)
    oi = sh.oi if sh.oi is not None else np.zeros((b.n_proxy, 3, 3), np.float32)
    dom = sh.dominant_dir if sh.dominant_dir is not None else np.array([0, 1, 0], np.float32)
    first = pl.plane_slices[0] if pl.plane_slices else slice(None)
    return RelightResult(
        vertices=(b.vertices * scale) @ R.T + t,
        normals=b.normals @ R.T,
        faces=b.faces,
        radiance=irr * INV_PI * pl.exposure_scale,
        irradiance=irr,
        proxy_irradiance=sh.irradiance,
        oi=np.einsum("vcx,yx->vcy", oi, R),
        T_cam_obj=np.asarray(anchor.T_cam_obj),
        exposure_scale=float(pl.exposure_scale),
        dominant_dir=(R @ dom).astype(np.float32),
        dominant_share=float(sh.dominant_share),
        method=sh.method,
        bundle=str(b.path),
        plane_source=source,
        plane_observed=float(np.mean(pl.mask[first])),
        light=light,
    )
