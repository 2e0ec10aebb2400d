"""End-to-end evaluation on the synthetic camera: what ``illuminet eval`` reports per camera suite.

Each suite renders RGB-D frames of synthetic scenes (``synthetic://KIND``: sensor noise, auto
exposure, textured planes, stereo-like depth, indirect light) and runs them through the pipeline's
lighting chain exactly as ``illuminet run`` builds it (the caller passes
``illuminet.pipeline.build_stages``, used with ``render=False``, run through
:class:`~illuminet.runtime.stage.StageChain`; this layer may not import the entry package); the anchor is pinned to the
scene's object position. "Ours" is whatever that chain puts in ``results[SHADING]`` (and, when a
stage provides it, ``results[LIGHT]`` for the dominant light), so a new default shading is measured
as soon as it is the default. Named variants (``--variant name:section.key=value,...``) run the same
frames through chains built from other configurations: the ablation of each cue.

Suites (:data:`SUITES`): ``indoor``, ``outdoor`` (the held-out HDR maps, every 4th; the analytic sky
when no maps are found), ``lamp`` (a near lamp), ``spatial`` (several object positions) and
``cluttered`` (boxes that shadow the floor and sometimes the object). Not run by default:
``outdoor_look`` (:data:`LOOK_SUITES`), the ``outdoor`` suite's scenes, seeds and maps seen by a user
who looks around once before looking back at the object (``path=look``: the view raised to the
horizon, one full turn in place; at least :data:`LOOK_FRAMES` frames, so the turn is one a camera
can follow), scored on the last frame as the others; ``outdoor_boxes`` (:data:`VARIANT_SUITES`), the
``outdoor`` suite's scenes, seeds and maps with three boxes on the ground: real cast shadows in view,
the cue the dominant-light target asks for ("wherever ... a cue is in view"), which the ``outdoor``
scenes do not have.

Methods side by side: the variants, the learned transfer (``[model] shading = "model"`` on the same
plane light), the constant prior, ambient, SH fitted to every valid RGB-D pixel (the regularised
fair baseline of :mod:`illuminet.runtime.groundtruth.baselines`, best regulariser per suite), that
SH shaded with the object's visibility (PRT), and three oracles fitted to the true shading: best
SH2 without visibility, best SH2 *with* visibility (the PRT oracle: least-squares ``L`` with
``T_i . L = E_i``, ``T_i = integral max(0, n.w) V_i(w) Y_lm(w) dw`` plus the light the object
reflects onto itself at the truth's ``object_albedo``), and the PRT oracle restricted to light
symmetric about the up axis (no azimuth: what an estimate can reach with no cue to the light's side).

Metrics per method (ground truth: ``scene.true_object_shading`` on the render mesh, with indirect
light, the object's own included at ``object_albedo``, 0.8 by default; intensities as a camera
records a white Lambertian object at the frame's own exposure ``k``):

``mae``, ``rmse``
    per-vertex error of sRGB intensities ``srgb(clip(a * E * k / pi))`` after the best single gain
    ``a`` (least squares on linear intensities): the paper's metric, blind to the overall scale.
``mae_abs``
    the same without the gain (absolute brightness counts).
``rmse_lin``
    linear intensities, best gain, no clipping or clamping: the criterion the oracles minimise, so
    an oracle is never worse than its fitted baseline on it.
``angle``
    degrees between the method's dominant-light direction and the true one (the luminance-weighted
    vector irradiance of the direct lights at the object's centre, scene occlusion included). For
    ``ours`` the estimate's primary light, or, when it has none, the direction of its ambient SH's
    linear band (the ambient's vector irradiance, as for the oracles).
``angle_primary``
    ``angle``'s median over only the scenes whose primary light carries at least
    :data:`PRIMARY_SHARE_MIN` of the object's light (issue 11's target: where a dominant light exists
    there is a direction to get right; elsewhere the "dominant" direction is the small asymmetry of
    diffuse light). The primary light is the strongest light at the object's centre (scene occlusion
    included) together with every light within :data:`PRIMARY_CONE_DEG` of it (an HDR map's sun and
    an area lamp are several point lights); its share is the direct irradiance it gives the evaluated
    vertices (the object's self-shadowing and the scene's occluders included) over their true
    irradiance (luminance, summed). The per-scene share is ``primary_share`` in each case.
``chroma``
    degrees between the mean RGB of the predicted and of the true shading (the light's colour).
``flicker``
    mean |change| of the sRGB intensities between consecutive frames of the static scene, over the
    second half of the frames (after the plane measurement settled), without the gain.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from illuminet.runtime.config import Config, ConfigError, apply_overrides, parse_override
from illuminet.runtime.scene import ANCHOR, LIGHT, PLANE_LIGHT, SHADING
from illuminet.runtime.sh import SH_A_HAT, sh9, sh_fit
from illuminet.runtime.stage import StageChain

log = logging.getLogger(__name__)


def _as_is(values: np.ndarray) -> np.ndarray:
    """No carry: :meth:`CameraEval._render` carries proxy values itself."""
    return values


SUITES = ("indoor", "outdoor", "lamp", "spatial", "cluttered")
#: suites that are another suite's scenes with something added to their URL: (that suite, the addition)
VARIANT_SUITES = {"outdoor_look": ("outdoor", "&path=look"), "outdoor_boxes": ("outdoor", "&boxes=3")}
#: the variant suites whose scenes are seen by a user looking around (``path=look``): longer runs
LOOK_SUITES = {s: kind for s, (kind, extra) in VARIANT_SUITES.items() if "path=look" in extra}
#: a look-around suite runs at least this many frames a scene (the turn in place takes half of them:
#: 300 frames is 10 s at 30 fps, at most ~3.6 deg a frame; 100 frames lost the turn)
LOOK_FRAMES = 300
#: the baselines and the flicker are computed on the last frames only (at most this many): half of a
#: 30-frame scene, the last half second of a longer one
TAIL_FRAMES = 15
#: regularisers tried for the RGB-D SH baseline; the best per suite is reported (its fairest setting)
SH_LAMBDAS = (0.0, 1e-2, 0.1)
LUMA = np.array([0.2126, 0.7152, 0.0722])
SEED_BASE = 1_000_003 % 100_000  # scene seeds apart from the training data's
#: ``angle_primary`` counts the scenes whose primary light carries at least this share (issue 11: 40 %)
PRIMARY_SHARE_MIN = 0.4
#: lights this close (degrees, seen from the object) to the strongest one belong to the primary light
PRIMARY_CONE_DEG = 15.0

LABELS = {
    "model": "IllumiNet transfer ([model] shading = model)",
    "constant": "Constant prior",
    "ambient": "Ambient (picture mean)",
    "sh_rgbd": "SH fitted to RGB-D",
    "sh_rgbd_prt": "SH fitted to RGB-D, shaded with visibility",
    "oracle_sh": "Oracle SH2 (no visibility)",
    "oracle_prt": "Oracle SH2 with visibility (PRT)",
    "oracle_prt_zonal": "Oracle SH2 with visibility, no azimuth (zonal)",
}
BASELINES = tuple(LABELS)


def _zonal_basis() -> np.ndarray:
    """(9, 3) orthonormal basis of the SH9 coefficient vectors that are symmetric about the object's
    up axis (y, the anchor plane's normal): Y00, Y1 along y and the band-2 function of y alone.

    ``oracle_prt_zonal`` is the PRT oracle restricted to it: the best any estimate can do that knows
    how the light varies with height but not from which side it comes. A frame that shows no cue to
    the light's azimuth (no shadow, wall, emitter or lamp pool in view) bounds every method there."""
    # 3 y^2 - 1 in the basis of :func:`sh9`: 0.315392 (3 z^2 - 1) and 0.546274 (x^2 - y^2) terms
    v = np.zeros(9)
    v[6] = -0.5 / 0.315392
    v[8] = -1.5 / 0.546274
    Z = np.stack([np.eye(9)[0], np.eye(9)[1], v / np.linalg.norm(v)], 1)
    return Z


ZONAL_BASIS = _zonal_basis()
METRICS = ("mae", "rmse", "mae_abs", "rmse_lin", "angle", "chroma", "flicker")
#: metrics aggregated by their median over scenes (the others: the mean)
MEDIAN_METRICS = ("angle", "angle_primary", "chroma")


@dataclass
class Variant:
    """A named configuration of the pipeline: ``overrides`` on top of the evaluated config."""

    name: str
    overrides: list = field(default_factory=list)
    cfg: Config | None = None  # the base configuration with the overrides applied (set by CameraEval)


_SPLIT = re.compile(r",(?=\s*[A-Za-z_]\w*\.[A-Za-z_]\w*\s*=)")


def parse_variant(spec: str) -> Variant:
    """``"name:section.key=value,section.key=value"`` -> :class:`Variant` (values in TOML syntax,
    so lists with commas work: ``v:anchor.point=[0, 0.3, 1.5]``)."""
    if ":" not in spec:
        raise ConfigError(f"--variant {spec!r}: expected NAME:section.key=value[,section.key=value...]")
    name, rest = spec.split(":", 1)
    name = name.strip()
    if not name or not re.fullmatch(r"[\w.-]+", name):
        raise ConfigError(f"--variant {spec!r}: the name must be letters, digits, '_', '-' or '.'")
    items = [s for s in _SPLIT.split(rest) if s.strip()]
    return Variant(name, [parse_override(s) for s in items])


def check_variants(cfg: Config, variants) -> list[Variant]:
    """``ours`` and ``variants``, each with its configuration (``.cfg``): a repeated or reserved name, or a
    wrong key or value, is a :class:`ConfigError` (``illuminet eval`` calls this before any work, also
    with ``--camera-scenes 0``, where a bad variant once went unnoticed with exit 0)."""
    out = [Variant("ours", [])] + list(variants)
    names = [v.name for v in out]
    if len(set(names)) != len(names) or set(names) & set(BASELINES):
        raise ConfigError(f"--variant names must be unique and not one of ours, {', '.join(BASELINES)}: got {names}")
    for v in out:
        try:
            v.cfg = apply_overrides(cfg, v.overrides)
        except ConfigError as e:  # "override: [render] msaa ..." did not say which flag
            raise ConfigError(f"--variant {v.name}: {e}") from None
    return out


# ------------------------------------------------------------------------------------- metrics


def srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def shading_metrics(pred: np.ndarray, true: np.ndarray, k: float, raw: np.ndarray | None = None) -> dict:
    """The per-case intensity metrics (module docstring) of a predicted irradiance (V, 3).

    ``raw``: the method's linear output before clamping at 0 (for ``rmse_lin``; default ``pred``).
    """
    p = np.asarray(pred, np.float64) * k / np.pi
    t = np.asarray(true, np.float64) * k / np.pi
    a = float((p * t).sum() / max((p * p).sum(), 1e-30))
    ts = srgb(t)
    es = srgb(a * p) - ts
    ea = srgb(p) - ts
    r = np.asarray(pred if raw is None else raw, np.float64) * k / np.pi
    ar = float((r * t).sum() / max((r * r).sum(), 1e-30))
    return {
        "mae": float(np.abs(es).mean()),
        "rmse": float(np.sqrt((es**2).mean())),
        "mae_abs": float(np.abs(ea).mean()),
        "rmse_lin": float(np.sqrt(((ar * r - t) ** 2).mean())),
        "gain": a,
    }


def angle_deg(a, b) -> float | None:
    if a is None or b is None:
        return None
    a, b = np.asarray(a, float), np.asarray(b, float)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return None
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1, 1))))


def sh_direction(coef: np.ndarray) -> np.ndarray | None:
    """Direction of an SH9 set's linear band (luminance), i.e. of its vector irradiance."""
    lin = np.asarray(coef)[1:4] @ LUMA  # (y, z, x) order
    d = np.array([lin[2], lin[0], lin[1]])
    n = np.linalg.norm(d)
    return None if n < 1e-12 else d / n


def _lights_at(scene, T_cam_obj: np.ndarray, frame: int, centre: np.ndarray):
    """The scene's lights in the object frame, the unit directions (N, 3) from ``centre`` to them and
    the irradiance (N,) each gives there at normal incidence (luminance, scene occlusion included)."""
    lights = scene.object_lights(T_cam_obj, frame)
    T_wo = scene.poses[frame % len(scene.poses)] @ np.asarray(T_cam_obj, float)
    cw = T_wo[:3, :3] @ centre + T_wo[:3, 3]
    vis = scene.occlusion(cw[None])[0]
    d = lights.positions - centre
    r2 = np.maximum((d * d).sum(1), 1e-12)
    return lights, d / np.sqrt(r2)[:, None], (lights.intensities @ LUMA) * vis / r2


def true_dominant(scene, T_cam_obj: np.ndarray, frame: int, centre: np.ndarray) -> np.ndarray | None:
    """The true dominant-light direction (object frame): vector irradiance of the direct lights at
    the object's centre, luminance-weighted, with the scene's occlusion."""
    _, u, e = _lights_at(scene, T_cam_obj, frame, centre)
    s = (e[:, None] * u).sum(0)
    n = np.linalg.norm(s)
    return None if n < 1e-12 else s / n


def primary_share(scene, mesh, T_cam_obj: np.ndarray, frame: int, centre: np.ndarray, points, normals, true_e):
    """Share of the object's true irradiance (luminance, summed over the evaluated vertices) that its
    primary light gives directly (module docstring, ``angle_primary``): the strongest light at the
    centre and those within :data:`PRIMARY_CONE_DEG` of it, with the object's self-shadowing and the
    scene's occluders. None when the scene has no light or the object no irradiance."""
    from illuminet.runtime.groundtruth import lighting as GL
    from illuminet.runtime.groundtruth.visibility import exact_visibility

    lights, u, e = _lights_at(scene, T_cam_obj, frame, centre)
    total = float((np.asarray(true_e) @ LUMA).sum())
    if len(lights.positions) == 0 or total <= 0:
        return None
    k = int(np.argmax(e))
    if e[k] <= 0:
        return 0.0
    group = np.flatnonzero((u @ u[k]) >= np.cos(np.radians(PRIMARY_CONE_DEG)))
    sub = GL.PointLights(lights.positions[group], lights.intensities[group])
    world = GL.PointLights(scene.lights.positions[group], scene.lights.intensities[group])
    T_wo = scene.poses[frame % len(scene.poses)] @ np.asarray(T_cam_obj, float)
    pts, nrm = np.asarray(points, float), np.asarray(normals, float)
    pw = pts @ T_wo[:3, :3].T + T_wo[:3, 3]
    v = exact_visibility(mesh, pts, sub.positions, normals=nrm).astype(float) * scene.occlusion(pw, world)
    return float((GL.irradiance(pts, nrm, sub, v) @ LUMA).sum()) / total


# ------------------------------------------------------------------------------------ the runner


class CameraEval:
    """The camera suites for one bundle, one base configuration and its variants.

    Parameters
    ----------
    cfg : Config
        The evaluated configuration ("ours" = the chain it builds).
    build_stages : callable
        ``illuminet.pipeline.build_stages``: ``(cfg, render=False) -> [Stage, ...]``.
    bundle : bundle spec (default ``cfg.model.bundle``): the object and the learned transfer.
    variants : more named configurations (:class:`Variant`) run on the same frames.
    hdr_dir : folder of HDR maps for the ``outdoor`` suite (its held-out maps are used).
    vertices : evaluate on this many render vertices (evenly spread; ``None`` = all).
    object_albedo : grey albedo of the object in the ground truth's light transport: the light it
        reflects onto itself (its inside, under its lip) is part of the truth. ``None`` = the albedo
        the renderer draws an uncoloured mesh with (``DEFAULT_ALBEDO``, 0.8); 0 = a black object that
        only blocks light (the truth of the evaluations before the sixth wave).
    """

    def __init__(
        self,
        cfg: Config,
        build_stages,
        bundle: str | None = None,
        variants=(),
        hdr_dir: str | Path | None = None,
        vertices: int | None = None,
        object_albedo: float | None = None,
    ):
        import trimesh

        from illuminet.runtime.assets.bundle import load_bundle
        from illuminet.runtime.render.mesh import DEFAULT_ALBEDO

        self.object_albedo = DEFAULT_ALBEDO if object_albedo is None else float(object_albedo)
        if not 0.0 <= self.object_albedo < 1.0:
            raise ValueError(f"--object-albedo: expected a number in [0, 1), got {object_albedo!r}")
        self.build_stages = build_stages
        self.spec = bundle or cfg.model.bundle
        self.bundle = load_bundle(self.spec)
        b = self.bundle
        self.base = apply_overrides(cfg, [("model", "bundle", str(self.spec))])
        self.variants = check_variants(self.base, variants)
        self.model_cfg = apply_overrides(self.base, [("model", "shading", "model")])
        # the bundle's own normals: the truth's evaluated points are then exactly the mesh's vertices
        self.mesh = trimesh.Trimesh(b.vertices, b.faces, vertex_normals=b.normals, process=False)
        R = len(b.vertices)
        self.sel = np.arange(R) if not vertices or vertices >= R else np.linspace(0, R - 1, int(vertices)).astype(int)
        self.points, self.normals = np.asarray(b.vertices)[self.sel], np.asarray(b.normals)[self.sel]
        self.centre = np.array([0.0, float(np.ptp(b.vertices[:, 1])) / 2, 0.0])
        from illuminet.models.datagen import hdr_maps

        self.hdr_maps = hdr_maps(hdr_dir, "test") if hdr_dir else []
        self._transfer = None

    # -- object-side precomputation (once per run)
    def transfer(self) -> np.ndarray:
        """(V, 9) PRT transfer of the evaluated vertices (the ground truth's own hemisphere rays), with
        the object's light onto itself at the truth's ``object_albedo``: the oracles and the RGB-D SH
        baseline shaded "with visibility" get the same object as the ground truth."""
        if self._transfer is None:
            from illuminet.hw.synthetic import bounce as B
            from illuminet.hw.synthetic.scene import object_hemisphere

            t = object_hemisphere(self.mesh, self.points, self.normals).transfer_sh9()
            if self.object_albedo > 0:
                on_mesh = B.on_mesh_vertices(self.mesh, self.points, self.normals)
                verts, vn = np.asarray(self.mesh.vertices), np.asarray(self.mesh.vertex_normals)
                t_mesh = t if on_mesh else object_hemisphere(self.mesh, verts, vn).transfer_sh9()
                t = t + B.object_light(self.mesh, self.points, self.normals, t_mesh, self.object_albedo, on_mesh)
            self._transfer = t
        return self._transfer

    def _render(self, proxy_or_render: np.ndarray) -> np.ndarray:
        """A prediction on the proxy (carried) or on the render mesh, at the evaluated vertices."""
        v = np.asarray(proxy_or_render, np.float64)
        if v.shape[0] == self.bundle.n_proxy:
            v = self.bundle.carry(v)
        if v.shape[0] != len(self.bundle.vertices):
            raise ValueError(
                f"shading has {v.shape[0]} values; expected {self.bundle.n_proxy} (proxy) or "
                f"{len(self.bundle.vertices)} (render mesh)"
            )
        return v[self.sel]

    def url(self, suite: str, i: int, seed: int, frames: int) -> str:
        kind, extra = VARIANT_SUITES.get(suite, (suite, ""))
        u = f"synthetic://{kind}?seed={SEED_BASE + 31 * seed + i}&frames={frames}{extra}"
        if kind == "spatial":  # the camera frames the position evaluated (scene_case: i % count)
            u += f"&position={i}"
        if kind == "outdoor" and self.hdr_maps:
            u += f"&hdr={self.hdr_maps[(i + seed) % len(self.hdr_maps)]}"
        return u

    def scene_case(self, suite: str, i: int, seed: int = 0, frames: int = 30) -> dict | None:
        """Every method's metrics on one scene (None when no real plane was found under the object)."""
        from illuminet.hw.synthetic import open_url
        from illuminet.runtime.groundtruth import baselines as BL
        from illuminet.runtime.physics import linearize
        from illuminet.runtime.stages.shading import ShadingStage, preprocess_plane

        if suite in LOOK_SUITES:
            frames = max(frames, LOOK_FRAMES)
        src = open_url(self.url(suite, i, seed, frames))
        src.open()
        sc = src.scene
        pos = i % len(sc.object_positions)
        T0 = sc.default_anchor(0, position=pos)
        pin = [("anchor", "mode", "point"), ("anchor", "point", [float(x) for x in T0[:3, 3]])]
        frames_in = [src.read() for _ in range(frames)]
        # the metrics use the last frame and the flicker the second half (after the estimate settled):
        # the baselines (one RGB-D SH fit per regulariser a frame) are computed on that half only
        settle = frames - min(frames - frames // 2, TAIL_FRAMES)  # = frames // 2 up to 30 frames
        src.close()
        per_frame: dict[str, list] = {}  # method -> [(irradiance (V, 3), raw, direction)] per frame
        last = {}
        for v in self.variants:
            stages = self.build_stages(apply_overrides(v.cfg, pin), render=False)
            model = ShadingStage(self.model_cfg) if v.name == "ours" else None
            for st in stages + ([model] if model else []):
                st.open()
            chain = StageChain(stages, source=src)
            try:
                for j, f in enumerate(frames_in):
                    out = chain(f)
                    sh, light = out.results.get(SHADING.name), out.results.get(LIGHT.name)
                    d = None
                    if light is not None and light.primary_dir is not None:
                        d = light.primary_dir
                    elif light is not None:  # no primary light: the ambient's own gradient (its vector irradiance)
                        d = sh_direction(light.sh9)
                    elif sh is not None:
                        d = sh.dominant_dir
                    drawn = None if sh is None else self._render(sh.on_render_mesh(_as_is))
                    per_frame.setdefault(v.name, []).append(None if drawn is None else (drawn, None, d))
                    last[v.name] = out
                    if model is None or j < settle:  # the baselines count on the second half only
                        continue
                    pl = out.results.get(PLANE_LIGHT.name)
                    ms = None
                    if pl is not None:
                        try:
                            ms = model.process(out).results[SHADING.name]
                        except Exception as e:  # the learned transfer cannot use this frame's plane
                            log.debug("model baseline skipped a frame: %s", e)
                    per_frame.setdefault("model", []).append(
                        None if ms is None else (self._render(ms.on_render_mesh(_as_is)), None, ms.dominant_dir)
                    )
                    self._frame_baselines(out, pl, per_frame, BL, linearize, preprocess_plane)
            finally:
                for st in stages + ([model] if model else []):
                    st.close()
        for seq in per_frame.values():  # the baselines' first half: not computed
            seq[:0] = [None] * (frames - len(seq))
        out = last["ours"]
        anchor = out.results.get(ANCHOR.name)
        if anchor is None or anchor.synthetic or per_frame["ours"][-1] is None:
            return None
        T = anchor.T_cam_obj
        fi = frames - 1
        true_e = sc.true_object_shading(
            self.mesh, T, frame=fi, points=self.points, normals=self.normals, object_albedo=self.object_albedo
        )
        k = float(out.exposure.scale)
        d_true = true_dominant(sc, T, fi, self.centre)
        # the oracles: fitted to the true shading (constant over frames)
        B9 = sh9(self.normals)
        coef = sh_fit(self.normals, true_e)
        raw = B9 @ coef
        oracles = {"oracle_sh": (np.maximum(raw, 0), raw, sh_direction(coef))}
        Tr = self.transfer()
        L, *_ = np.linalg.lstsq(Tr, true_e, rcond=None)
        raw = Tr @ L
        oracles["oracle_prt"] = (np.maximum(raw, 0), raw, sh_direction(L))
        Z = ZONAL_BASIS
        a, *_ = np.linalg.lstsq(Tr @ Z, true_e, rcond=None)
        raw = Tr @ (Z @ a)
        oracles["oracle_prt_zonal"] = (np.maximum(raw, 0), raw, sh_direction(Z @ a))
        res = {
            "url": self.url(suite, i, seed, frames),
            "k": k,
            "anchor_error_m": float(np.linalg.norm(T[:3, 3] - T0[:3, 3])),
            "indirect_share": None,
            "methods": {},
        }
        direct = sc.true_object_shading(
            self.mesh, T, frame=fi, points=self.points, normals=self.normals, indirect=False
        )
        res["indirect_share"] = float(1 - (direct @ LUMA).sum() / max((true_e @ LUMA).sum(), 1e-12))
        res["primary_share"] = primary_share(sc, self.mesh, T, fi, self.centre, self.points, self.normals, true_e)
        for m, seq in list(per_frame.items()) + [(m, [p]) for m, p in oracles.items()]:
            if seq[-1] is None:
                continue
            pred, raw, d = seq[-1]
            r = shading_metrics(pred, true_e, k, raw)
            r["angle"] = angle_deg(d, d_true)
            r["chroma"] = angle_deg(pred.mean(0), true_e.mean(0))
            tail = [s for s in seq[settle:] if s is not None]
            if len(tail) >= 2 and len(seq) > 1:
                ints = [srgb(s[0] * k / np.pi) for s in tail]
                r["flicker"] = float(np.mean([np.abs(b_ - a_).mean() for a_, b_ in zip(ints, ints[1:])]))
            else:
                r["flicker"] = None
            res["methods"][m] = r
        return res

    def _frame_baselines(self, out, pl, per_frame, BL, linearize, preprocess_plane) -> None:
        """Constant prior, ambient and the RGB-D SH fits (plain and with visibility) on one frame."""
        b = self.bundle
        n = len(self.sel)
        k = float(out.exposure.scale)
        anchor = out.results.get(ANCHOR.name)
        albedo = float(self.base.plane_light.assumed_albedo)
        entries: dict[str, tuple | None] = {}
        if pl is not None and anchor is not None:
            sl = pl.plane_slices[0] if pl.plane_slices else slice(0, len(pl.irradiance))
            try:
                _, s = preprocess_plane(pl.irradiance[sl], pl.mask[sl], b.grid, b.pool, pl.confidence[sl])
                entries["constant"] = (self._render(b.prior_shading * s), None, None)
            except ValueError:
                entries["constant"] = None
        lin = linearize(out.color)
        entries["ambient"] = (np.tile(BL.ambient_from_image(lin, albedo, k), (n, 1)), None, None)
        if anchor is not None:
            T = anchor.T_cam_obj
            nrm, e = BL.sh_samples_from_rgbd(lin, out.depth, out.intrinsics, albedo, T[:3, :3].T, k)
            B9, Tr = sh9(self.normals), self.transfer()
            for lam in SH_LAMBDAS:
                if nrm.shape[0] < 9:
                    entries[f"sh_rgbd@{lam}"] = entries[f"sh_rgbd_prt@{lam}"] = None
                    continue
                coef = sh_fit(nrm, e, lam=lam)
                raw = B9 @ coef
                entries[f"sh_rgbd@{lam}"] = (np.maximum(raw, 0), raw, sh_direction(coef))
                raw = Tr @ (coef / SH_A_HAT[:, None])  # irradiance -> radiance coefficients
                entries[f"sh_rgbd_prt@{lam}"] = (np.maximum(raw, 0), raw, sh_direction(coef))
        for m, v in entries.items():
            per_frame.setdefault(m, []).append(v)

    def run(self, suites=SUITES, scenes: int = 8, frames: int = 30, seed: int = 0, progress=None) -> dict:
        """Every suite: per method the mean (mae, rmse, mae_abs, rmse_lin, flicker) and median
        (angle, chroma) over scenes; the RGB-D SH baselines at their best regulariser per suite."""
        self.check(suites, frames)
        t0 = time.time()
        cases: dict[str, list] = {}
        done, total = 0, len(suites) * scenes
        for suite in suites:
            cases[suite] = []
            for i in range(scenes):
                cases[suite].append(self.scene_case(suite, i, seed, frames))
                done += 1
                if progress:
                    progress(done, total)
        return self.assemble(cases, scenes, frames, seed, time.time() - t0)

    @staticmethod
    def check(suites, frames: int) -> None:
        known = SUITES + tuple(VARIANT_SUITES)
        bad = [s for s in suites if s not in known]
        if bad:
            raise ValueError(f"unknown camera suite(s) {', '.join(bad)}; known: {', '.join(known)}")
        if frames < 2:
            raise ValueError(f"camera frames must be >= 2 (flicker needs two), got {frames}")

    def assemble(self, cases: dict[str, list], scenes: int, frames: int, seed: int, wall_s: float) -> dict:
        """The report from every suite's :meth:`scene_case` results in scene order (``None`` where a
        scene had no plane): what :meth:`run` returns, also when the cases were computed elsewhere."""
        report = {
            "bundle": self.bundle.name,
            "scenes": scenes,
            "frames": frames,
            "seed": seed,
            "vertices": int(len(self.sel)),
            "object_albedo": self.object_albedo,
            "variants": {v.name: [f"{s}.{k}={val!r}" for s, k, val in v.overrides] for v in self.variants},
            "hdr_test_maps": [p.name for p in self.hdr_maps],
            "suites": {},
        }
        for suite, lst in cases.items():
            report["suites"][suite] = self._aggregate([c for c in lst if c is not None], scenes)
        report["wall_s"] = round(wall_s, 1)
        return report

    def _aggregate(self, cases: list, n: int) -> dict:
        res: dict = {
            "_scenes": {"evaluated": len(cases), "no_plane": n - len(cases)},
            "_indirect_share": float(np.mean([c["indirect_share"] for c in cases])) if cases else None,
            "_primary_scenes": sum(1 for c in cases if (c.get("primary_share") or 0.0) >= PRIMARY_SHARE_MIN),
        }
        methods = sorted({m for c in cases for m in c["methods"]})
        for m in methods:
            rows = [c["methods"][m] for c in cases if m in c["methods"]]
            agg = {"n": len(rows)}
            strong = [
                c["methods"][m].get("angle")
                for c in cases
                if m in c["methods"] and (c.get("primary_share") or 0.0) >= PRIMARY_SHARE_MIN
            ]
            for key in METRICS + ("angle_primary",):
                vals = [r[key] for r in rows if r.get(key) is not None] if key != "angle_primary" else strong
                vals = [x for x in vals if x is not None]
                if not vals:
                    agg[key] = None
                elif key in MEDIAN_METRICS:
                    agg[key] = float(np.median(vals))
                else:
                    agg[key] = float(np.mean(vals))
            res[m] = agg
        for base in ("sh_rgbd", "sh_rgbd_prt"):
            cand = [lam for lam in SH_LAMBDAS if res.get(f"{base}@{lam}", {}).get("mae") is not None]
            if cand:
                best = min(cand, key=lambda lam: res[f"{base}@{lam}"]["mae"])
                res[base] = dict(res[f"{base}@{best}"], lam=best)
            for lam in SH_LAMBDAS:
                res.pop(f"{base}@{lam}", None)
        return res


# ------------------------------------------------------------------------------------ reporting


def _fmt(v, nd=3):
    return "n/a" if v is None else f"{v:.{nd}f}"


def method_order(report: dict) -> list[str]:
    return list(report["variants"]) + list(BASELINES)


def table(report: dict) -> str:
    """One markdown table: a row per (suite, method), the metrics as columns."""
    lines = [
        "| suite | method | MAE | RMSE | MAE (no gain) | angle (deg) | angle, primary >= 40 % (deg) | chroma (deg) "
        "| flicker |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for suite, res in report["suites"].items():
        for m in method_order(report):
            r = res.get(m)
            if r is None:
                continue
            label = m if m in report["variants"] else LABELS[m]
            if m in ("sh_rgbd", "sh_rgbd_prt") and "lam" in r:
                label += f" (lambda {r['lam']:g})"
            lines.append(
                f"| {suite} | {label} | {_fmt(r['mae'])} | {_fmt(r['rmse'])} | {_fmt(r['mae_abs'])} | "
                f"{_fmt(r['angle'], 1)} | {_fmt(r.get('angle_primary'), 1)} | {_fmt(r['chroma'], 1)} | "
                f"{_fmt(r['flicker'], 4)} |"
            )
    return "\n".join(lines)


def markdown(report: dict) -> str:
    head = [
        "",
        "## End to end on the synthetic camera",
        "",
        f"Bundle `{report['bundle']}`, {report['scenes']} scene(s) per suite, {report['frames']} frames each"
        + (
            f" ({', '.join(s for s in report['suites'] if s in LOOK_SUITES)}: a look around first, "
            f"{max(report['frames'], LOOK_FRAMES)} frames)"
            if any(s in LOOK_SUITES for s in report.get("suites", {}))
            else ""
        )
        + f", {report['vertices']} render vertices; ground truth with indirect light"
        + (
            f" and the object's light onto itself (albedo {report['object_albedo']:g})"
            if report.get("object_albedo")
            else " (the object black: it only blocks light)"
        )
        + ". MAE/RMSE: sRGB intensities "
        "after the best gain; angle: dominant light; chroma: the light's colour; flicker: frame to frame "
        "(see models/camera_eval.py).",
    ]
    if len(report["variants"]) > 1:
        head.append(
            "Variants: "
            + "; ".join(
                f"`{n}` = {', '.join(o) or 'the configuration as given'}" for n, o in report["variants"].items()
            )
            + "."
        )
    if report.get("hdr_test_maps"):
        head.append("Outdoor: held-out HDR maps " + ", ".join(report["hdr_test_maps"]) + ".")
    foot = [
        "",
        "Scenes evaluated (no real plane under the object) and the indirect share of the true "
        "shading: "
        + ", ".join(
            f"{s} {r['_scenes']['evaluated']} ({r['_scenes']['no_plane']}), {_fmt(r['_indirect_share'], 2)}"
            for s, r in report["suites"].items()
        ),
        "",
        f"Scenes whose primary light carries >= {100 * PRIMARY_SHARE_MIN:.0f} % of the object's light (the "
        "`angle, primary` column's scenes): "
        + ", ".join(f"{s} {r.get('_primary_scenes', 0)}" for s, r in report["suites"].items()),
    ]
    return "\n".join(head) + "\n\n" + table(report) + "\n" + "\n".join(foot) + "\n"
