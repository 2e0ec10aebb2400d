"""Cross-check of the ground truth's light transport against a path tracer (Mitsuba 3).

The synthetic camera's ground truth (:meth:`~illuminet.hw.synthetic.scene.SyntheticScene.true_object_shading`)
is computed in-house: exact direct light from point lights and a radiosity approximation of the
light the room's planes inter-reflect (:mod:`illuminet.hw.synthetic.bounce`). Here the same scene
(the same planes with their mean albedo, the same point lights, the object as a grey diffuse mesh
of the albedo the renderer draws it with, 0.8, or black with ``object_albedo=0``) is handed to
Mitsuba 3, and at a subset of the object's vertices Mitsuba's path tracer
estimates the light arriving *from surfaces*: cosine-distributed rays leave each vertex and
Mitsuba's ``path`` integrator returns the radiance along them (every bounce; a second run with
``max_depth = 2`` gives exactly one bounce). Point lights cannot be hit by a ray, so the direct light
at the vertex is not part of Mitsuba's estimate; it is the same closed form in both (``I cos / r^2``
times exact visibility) and is added to both sides. What is compared is therefore the in-house
indirect term against the path tracer's, inside the total irradiance.

Figures per scene: mean relative error of the vertices' total irradiance (luminance) with and
without the in-house bounce term, the same over down-facing vertices, Mitsuba's own noise (from two
independent halves of its samples), and the ratio of the indirect light summed over the vertices,
in-house over Mitsuba, for all bounces and for exactly one (in-house baked with ``bounce=1``).

Mitsuba is an optional dependency (``pip install 'illuminet[groundtruth]'``), imported only here and
only when a cross-check runs. The variant is ``scalar_rgb`` (always available) unless ``llvm_ad_rgb``
is asked for and loads (it needs libLLVM; set ``DRJIT_LIBLLVM_PATH`` when it is not found).
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from illuminet.runtime.groundtruth import lighting as L

log = logging.getLogger(__name__)

LUMA = np.array([0.2126, 0.7152, 0.0722])

#: the scenes of the cross-check: name -> (synthetic kind, seed, what it tests)
SCENES = {
    "lamp_room": ("lamp", 2, "floor, walls, ceiling; a warm point lamp 0.35-0.7 m from the object, dim ceiling lights"),
    "area_lamp_boxes": (
        "cluttered",
        4,
        "room with boxes and a table; the key light replaced by a 20 cm disc of 16 points",
    ),
    "indoor_table": ("indoor", 1, "room with a table under 32 ceiling, lamp and window lights"),
    "outdoor_hdr": ("outdoor", 3, "ground and facade under the median cut (32 lights) of a held-out HDR map"),
}


class CrosscheckUnavailable(RuntimeError):
    """Mitsuba 3 is not installed (the message says how to install it)."""


def load_mitsuba(variant: str = "scalar_rgb"):
    """Import Mitsuba 3 and set ``variant`` (``"llvm"``: try ``llvm_ad_rgb``, else ``scalar_rgb``)."""
    try:
        import mitsuba as mi
    except ImportError:
        raise CrosscheckUnavailable(
            "the cross-check needs Mitsuba 3: pip install 'illuminet[groundtruth]' (or: pip install mitsuba)"
        ) from None
    if variant == "llvm":
        try:
            mi.set_variant("llvm_ad_rgb")
            import drjit as dr

            dr.eval(dr.llvm.Float([1.0]) * 2)  # the JIT loads libLLVM on first use
            return mi
        except Exception as e:  # no libLLVM: fall back to the variant that always works
            log.warning("Mitsuba llvm_ad_rgb unavailable (%s); using scalar_rgb", e)
        variant = "scalar_rgb"
    mi.set_variant(variant)
    return mi


# ------------------------------------------------------------------------------ scene conversion


def _rect_transform(mi, p, lo, hi):
    """Mitsuba's ``rectangle`` ([-1, 1]^2 at z = 0, normal +z) onto a plane's rectangle."""
    n = p.normal
    u = np.zeros(3)
    u[p.axes[0]] = 1.0
    v = np.cross(n, u)  # right-handed (u, v, n)
    c = np.zeros(3)
    c[p.axis] = p.coord
    c[p.axes[0]] = (lo[0] + hi[0]) / 2
    c[p.axes[1]] = (lo[1] + hi[1]) / 2
    half = (np.asarray(hi) - np.asarray(lo)) / 2
    M = np.eye(4)
    M[:3, 0] = u * half[0]
    M[:3, 1] = v * half[1]  # v lies along the plane's second axis
    M[:3, 2] = n
    M[:3, 3] = c
    return mi.ScalarTransform4f(M.tolist())


def to_mitsuba(
    mi,
    scene,
    mesh=None,
    T_world_obj: np.ndarray | None = None,
    max_depth: int = -1,
    ground_half_m: float = 500.0,
    object_albedo: float = 0.0,
):
    """A Mitsuba scene of a :class:`~illuminet.hw.synthetic.scene.SyntheticScene`.

    Planes become one-sided diffuse rectangles of their mean albedo (back sides black, as in the
    in-house transport), unbounded ground a ``2 * ground_half_m`` square, point lights ``point``
    emitters of the same RGB intensity, and ``mesh`` (object frame, placed by ``T_world_obj``) a
    diffuse mesh of grey ``object_albedo`` (0: black, it blocks and reflects nothing).
    """
    d: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth), "rr_depth": 50}}
    for i, p in enumerate(scene.planes):
        lo, hi = np.array(p.lo, float), np.array(p.hi, float)
        if not np.all(np.isfinite(lo)):
            lo, hi = np.full(2, -ground_half_m), np.full(2, ground_half_m)
        d[f"plane{i}_{p.name}"] = {
            "type": "rectangle",
            "to_world": _rect_transform(mi, p, lo, hi),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(x) for x in p.albedo_mean]}},
        }
    for j, (pos, e) in enumerate(zip(scene.lights.positions, scene.lights.intensities)):
        if not np.any(e > 0):
            continue
        d[f"light{j}"] = {
            "type": "point",
            "position": [float(x) for x in pos],
            "intensity": {"type": "rgb", "value": [float(x) for x in e]},
        }
    tmp = None
    if mesh is not None:
        fd, tmp = tempfile.mkstemp(suffix=".ply")
        os.close(fd)
        mesh.export(tmp, file_type="ply")
        d["object"] = {
            "type": "ply",
            "filename": tmp,
            "face_normals": True,
            "to_world": mi.ScalarTransform4f(np.asarray(T_world_obj, float).tolist()),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(object_albedo)] * 3}},
        }
    try:
        return mi.load_dict(d)
    finally:
        if tmp:
            Path(tmp).unlink(missing_ok=True)


def _cosine_rays(normals: np.ndarray, spp: int, rng: np.random.Generator) -> np.ndarray:
    """(V, spp, 3) random cosine-distributed directions about each normal (independent of the
    in-house stratified pattern)."""
    from illuminet.runtime.groundtruth.hemisphere import tangent_frames

    V = normals.shape[0]
    u1, u2 = rng.random((V, spp)), rng.random((V, spp))
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0, 1 - u1))], -1)
    return np.einsum("vij,vkj->vki", tangent_frames(normals), local)


def mitsuba_indirect(
    mi, mscene, points: np.ndarray, normals: np.ndarray, spp: int = 256, seed: int = 0, eps: float = 1e-4
) -> np.ndarray:
    """Irradiance (V, 3) arriving at world points from surfaces (not straight from the point lights),
    by Mitsuba's integrator along ``spp`` cosine-distributed rays per point: ``pi * mean(L_i)``."""
    rng = np.random.default_rng(seed)
    V = points.shape[0]
    dirs = _cosine_rays(normals, spp, rng)
    orig = points + eps * normals
    integ = mscene.integrator()
    sampler = mi.load_dict({"type": "independent"})
    if mi.variant().startswith("scalar"):
        sampler.seed(seed)
        out = np.zeros((V, 3))
        for v in range(V):
            o = mi.Point3f(*orig[v])
            acc = np.zeros(3)
            for k in range(spp):
                spec, _, _ = integ.sample(mscene, sampler, mi.Ray3f(o, mi.Vector3f(*dirs[v, k])))
                sampler.advance()
                acc += (spec[0], spec[1], spec[2])
            out[v] = np.pi * acc / spp
        return out
    import drjit as dr

    n = V * spp
    o = np.repeat(orig, spp, axis=0)
    dd = dirs.reshape(-1, 3)
    sampler.seed(seed, n)
    ray = mi.Ray3f(
        mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
        mi.Vector3f(*(mi.Float(dd[:, i].astype(np.float32)) for i in range(3))),
    )
    spec, _, _ = integ.sample(mscene, sampler, ray)
    dr.eval(spec)
    rgb = np.stack([np.array(spec[i]) for i in range(3)], -1).reshape(V, spp, 3)
    return np.pi * rgb.mean(1)


# ------------------------------------------------------------------------------ the cross-check


def _area_lamp(scene, rng) -> None:
    """Replace the scene's strongest light by 16 points on a 20 cm horizontal disc (same total
    intensity): a lamp with a diffuser, soft shadows."""
    lum = scene.lights.intensities @ LUMA
    j = int(np.argmax(lum))
    k = np.arange(16) + 0.5
    r, phi = 0.1 * np.sqrt(k / 16), np.pi * (3 - np.sqrt(5)) * k
    disc = scene.lights.positions[j] + np.stack([r * np.cos(phi), np.zeros(16), r * np.sin(phi)], 1)
    lamp = L.PointLights(disc, np.tile(scene.lights.intensities[j] / 16, (16, 1)))
    rest = np.arange(len(lum)) != j
    scene.lights = lamp.concatenated(L.PointLights(scene.lights.positions[rest], scene.lights.intensities[rest]))


def build_crosscheck_scene(name: str, bounces: int, hdr_dir: str | Path | None = None):
    """The synthetic scene ``name`` of :data:`SCENES`, baked with ``bounces``."""
    from illuminet.hw.synthetic.scene import build_scene

    kind, seed, _ = SCENES[name]
    hdr = None
    if kind == "outdoor" and hdr_dir:
        from illuminet.models.datagen import hdr_maps

        maps = hdr_maps(hdr_dir, "test")
        hdr = str(maps[seed % len(maps)]) if maps else None
    sc = build_scene(kind, seed, (160, 100), frames=1, hdr=hdr, table=None, bounce=bounces)
    if name == "area_lamp_boxes":
        _area_lamp(sc, np.random.default_rng(seed))
        sc.bake(bounces)
    return sc


def run_crosscheck(
    names=tuple(SCENES),
    obj: str = "builtin:bowl",
    vertices: int = 300,
    spp: int = 256,
    bounces: int | None = None,
    hdr_dir: str | Path | None = None,
    variant: str = "scalar_rgb",
    one_bounce: bool = True,
    progress=None,
    object_albedo: float | None = None,
) -> dict:
    """Per scene: in-house vs Mitsuba irradiance at ``vertices`` vertices of ``obj`` (see module doc).

    Returns a report dict: per scene the mean relative errors (luminance) with and without the
    in-house indirect term, for all and for down-facing vertices, and the indirect term's error.
    ``object_albedo`` (default: the renderer's 0.8) is the object's grey albedo in both transports,
    so the light it reflects onto itself is compared too (0: a black object). The one-bounce
    comparison is of the room's transport and keeps the object black in both.
    """
    from illuminet.hw.synthetic.scene import DEFAULT_BOUNCES
    from illuminet.runtime.assets.objects import load_object
    from illuminet.runtime.render.mesh import DEFAULT_ALBEDO

    rho = DEFAULT_ALBEDO if object_albedo is None else float(object_albedo)

    mi = load_mitsuba(variant)
    n_bounces = DEFAULT_BOUNCES if bounces is None else int(bounces)
    mesh = load_object(obj)
    V = len(mesh.vertices)
    sel = np.linspace(0, V - 1, min(vertices, V)).astype(int)
    pts, nrm = np.asarray(mesh.vertices)[sel], np.asarray(mesh.vertex_normals)[sel]
    report = {
        "object": obj,
        "vertices": int(len(sel)),
        "spp": spp,
        "bounces": n_bounces,
        "variant": mi.variant(),
        "object_albedo": rho,
        "scenes": {},
    }
    for si, name in enumerate(names):
        t0 = time.time()
        sc = build_crosscheck_scene(name, n_bounces, hdr_dir)
        T_co = sc.default_anchor(0)
        T_wo = sc.poses[0] @ T_co
        direct = sc.true_object_shading(mesh, T_co, points=pts, normals=nrm, indirect=False) @ LUMA
        ours = sc.true_object_shading(mesh, T_co, points=pts, normals=nrm, object_albedo=rho) @ LUMA
        t_ours = time.time() - t0
        pw = pts @ T_wo[:3, :3].T + T_wo[:3, 3]
        nw = nrm @ T_wo[:3, :3].T
        t1 = time.time()
        # two independent halves: their mean is the estimate, their difference its noise
        scene_all = to_mitsuba(mi, sc, mesh, T_wo, -1, object_albedo=rho)
        halves = [mitsuba_indirect(mi, scene_all, pw, nw, max(spp // 2, 1), seed=2 * si + h) @ LUMA for h in (0, 1)]
        m_all = (halves[0] + halves[1]) / 2
        t_mi = time.time() - t1
        truth = direct + m_all
        floor = 0.05 * float(truth.mean())  # contact points receive ~0: no relative error there
        down = nw[:, 1] < -0.3

        def rel(pred, m=None, truth=truth, floor=floor):
            m = np.ones(len(truth), bool) if m is None else m
            return float(np.mean(np.abs(pred[m] - truth[m]) / np.maximum(truth[m], floor)))

        res = {
            "kind": SCENES[name][0],
            "seed": SCENES[name][1],
            "what": SCENES[name][2],
            "hdr": sc.info.get("hdr"),
            "rel_err_with_bounce": rel(ours),
            "rel_err_direct_only": rel(direct),
            "rel_err_with_bounce_down": rel(ours, down),
            "rel_err_direct_only_down": rel(direct, down),
            "mitsuba_noise": float(np.mean(np.abs(halves[0] - halves[1]) / 2 / np.maximum(truth, floor))),
            "down_vertices": int(down.sum()),
            "indirect_share_mitsuba": float(m_all.sum() / max(truth.sum(), 1e-12)),
            "indirect_ratio_vs_all": float((ours - direct).sum() / max(m_all.sum(), 1e-12)),
            "seconds_ours": round(t_ours, 2),
            "seconds_mitsuba": round(t_mi, 2),
        }
        if one_bounce:
            # one bounce in both: the in-house transport of a single inter-reflection vs max_depth = 2
            m_one = mitsuba_indirect(mi, to_mitsuba(mi, sc, mesh, T_wo, 2), pw, nw, spp, seed=100 + si) @ LUMA
            sc.bake(1)
            one = sc.true_object_shading(mesh, T_co, points=pts, normals=nrm) @ LUMA - direct
            res["indirect_ratio_one_bounce"] = float(one.sum() / max(m_one.sum(), 1e-12))
        report["scenes"][name] = res
        if progress:
            progress(si + 1, len(names))
    return report


def markdown(report: dict) -> str:
    lines = [
        f"# Cross-check of the ground truth against Mitsuba 3 ({report['variant']})",
        "",
        f"Object `{report['object']}`, {report['vertices']} vertices, {report['spp']} rays per vertex in "
        f"Mitsuba (all bounces); in-house: {report['bounces']} bounce(s); the object's albedo "
        f"{report.get('object_albedo', 0.0):g} in both (its light onto itself counts). Error: mean over vertices of "
        "|ours - Mitsuba| / Mitsuba of the total irradiance (luminance; denominators at least 5 % of the "
        "mean, so contact points do not dominate); 'down': vertices facing down (normal y < -0.3). "
        "Indirect ratios: sum over vertices, ours / Mitsuba (1.00 = the same light); one bounce: the "
        "in-house transport baked with 1 bounce against Mitsuba's `max_depth = 2`.",
        "",
        "| scene | indirect share | error, with bounce | direct only | down: with bounce | down: direct only "
        "| Mitsuba noise | indirect ratio | one-bounce ratio |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in report["scenes"].items():
        one = r.get("indirect_ratio_one_bounce")
        lines.append(
            f"| {name} | {r['indirect_share_mitsuba']:.1%} | {r['rel_err_with_bounce']:.1%} | "
            f"{r['rel_err_direct_only']:.1%} | {r['rel_err_with_bounce_down']:.1%} | "
            f"{r['rel_err_direct_only_down']:.1%} | {r['mitsuba_noise']:.1%} | "
            f"{r['indirect_ratio_vs_all']:.2f} | " + ("n/a" if one is None else f"{one:.2f}") + " |"
        )
    return "\n".join(lines) + "\n"
