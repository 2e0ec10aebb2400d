"""``illuminet bench transfer``: the per-frame cost of the object's shading.

For the configured bundle, on one plane measurement (32x32 grid, 10 % unobserved) and one light
estimate (ambient SH + a primary light):

* learned transfer (bundles with an ONNX model): ``preprocess`` (plane normalisation + pooling),
  ``chain_int8`` / ``chain_fp32`` (the ONNX chain alone, onnxruntime, 1 thread) and ``stage_int8``
  (the whole :class:`~illuminet.runtime.stages.shading.ShadingStage` per frame: preprocess, chain,
  scale, dominant light, temporal smoothing) — the figure the 2 ms target applies to;
* precomputed radiance transfer (bundles with PRT tables): ``stage_prt`` (the stage per frame with a
  distant primary light: SH transfer, table visibility, bounce, smoothing) and ``stage_prt_near``
  (a near light: per-vertex directions, falloff and visibility) — target 1 ms. With render-mesh
  transfer (``illuminet bundle --render-transfer``, the shipped bundles) the stage shades every render
  vertex, so it includes the carry to the render mesh the renderer otherwise does: ``*_drawn`` (stage
  + carry when needed) against ``*_drawn_proxy_only`` (the same tables without it), same run.
  Each call gets a new light (the frames a new estimate arrives on, at ``[light] rate_hz``);
  ``stage_prt_same_light`` is the frames between, when the stage reuses its shading.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools

import numpy as np

from illuminet.runtime.assets.bundle import load_bundle
from illuminet.runtime.config import apply_overrides
from illuminet.runtime.scene import LightEstimate, PlaneLight
from illuminet.runtime.stages.shading import ShadingStage, preprocess_plane
from illuminet.runtime.stream.timing import measure

TARGET_MS = 2.0
TARGET_PRT_MS = 1.0


def _plane_light(grid: int, extent: float, seed: int = 0) -> PlaneLight:
    rng = np.random.default_rng(seed)
    x = np.linspace(-extent / 2, extent / 2, grid)
    zz, xx = np.meshgrid(x, x, indexing="ij")
    v = np.stack([xx.ravel(), np.zeros(grid * grid), zz.ravel()], 1).astype(np.float32)
    irr = (0.5 + 0.5 * np.exp(-((xx.ravel() - 0.2) ** 2 + zz.ravel() ** 2) * 4))[:, None] * [1.0, 0.9, 0.8]
    irr = (irr * rng.uniform(0.95, 1.05, irr.shape)).astype(np.float32)
    mask = rng.random(grid * grid) > 0.1
    return PlaneLight(
        vertices=v,
        normals=np.tile([[0, 1, 0]], (grid * grid, 1)).astype(np.float32),
        irradiance=irr,
        mask=mask,
        confidence=np.ones(grid * grid, np.float32),
        grid=grid,
        exposure_scale=1.0,
        plane_slices=(slice(0, grid * grid),),
        labels=("floor",),
    )


def _estimate(near: bool) -> LightEstimate:
    sh = np.zeros((9, 3))
    sh[0] = [1.2, 1.1, 1.0]
    sh[1] = [0.3, 0.3, 0.35]  # brighter above
    d = np.array([0.5, 0.8, 0.3]) / np.linalg.norm([0.5, 0.8, 0.3])
    return LightEstimate(
        sh9=sh, primary_dir=d, primary_rgb=np.array([3.0, 2.8, 2.4]), primary_pos=d * 0.8 if near else None
    )


def _changing(est: LightEstimate):
    """A function giving ``est`` with a slightly different primary light at each call (no two alike:
    the shading stage computes only when the light changes)."""
    n = itertools.count(1)
    return lambda: dataclasses.replace(est, primary_rgb=est.primary_rgb * (1.0 + 1e-6 * next(n)))


def _report(out: dict, keys) -> None:
    for k in keys:
        r = out[k]
        print(f"{k:14s} median {r['median_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms  (n={r['n']})")


def run(args, cfg) -> dict:
    repeat = 50 if getattr(args, "quick", False) else 1000
    bundle = load_bundle(cfg.model.bundle)
    out: dict = {"bundle": cfg.model.bundle, "proxy_vertices": bundle.n_proxy}
    if bundle.has_model:
        stages = {}
        for prec in ("int8", "fp32"):
            c = apply_overrides(cfg, [("model", "precision", prec), ("model", "shading", "model")])
            st = ShadingStage(c)
            st.open()
            stages[prec] = st
        b = stages["int8"].bundle
        pl = _plane_light(b.grid, b.extent_m)
        out["preprocess"] = measure(lambda: preprocess_plane(pl.irradiance, pl.mask, b.grid, b.pool), repeat)
        x, _ = preprocess_plane(pl.irradiance, pl.mask, b.grid, b.pool)
        for prec, st in stages.items():
            out[f"chain_{prec}"] = measure(lambda st=st: st.chain(x), repeat)
        st = stages["int8"]
        out["stage_int8"] = measure(lambda: st._smooth(st.predict(pl)), repeat)
        _report(out, ("preprocess", "chain_int8", "chain_fp32", "stage_int8"))
        out["int8_speedup_vs_fp32"] = out["chain_fp32"]["median_ms"] / max(out["chain_int8"]["median_ms"], 1e-9)
        out["target_ms"] = TARGET_MS
        out["meets_target"] = out["stage_int8"]["median_ms"] <= TARGET_MS
        print(
            f"int8 vs fp32 chain: x{out['int8_speedup_vs_fp32']:.2f}; per-frame stage median "
            f"{out['stage_int8']['median_ms']:.3f} ms vs target {TARGET_MS} ms: "
            f"{'OK' if out['meets_target'] else 'MISSED'}"
        )
        for st in stages.values():
            st.close()
    else:
        print(f"bundle {bundle.name} has no learned model: only the PRT figures")
    if bundle.prt is not None:
        st = ShadingStage(apply_overrides(cfg, [("model", "shading", "prt")]))
        st.open()
        # the same tables without the render-mesh transfer: the proxy shaded, the renderer carries it
        proxy_only = ShadingStage(apply_overrides(cfg, [("model", "shading", "prt")]))
        proxy_only.open()
        proxy_only.bundle = copy.copy(proxy_only.bundle)
        proxy_only.bundle.prt = dataclasses.replace(
            proxy_only.bundle.prt, render_transfer=None, render_bounce=None, render_bounce_primary=None
        )

        def drawn(stage, est):
            """The stage and what the renderer then needs: render-mesh values (carried when only the proxy's)."""
            return stage._smooth(stage.predict(None, est)).on_render_mesh(stage.bundle.carry)

        for key, near in (("stage_prt", False), ("stage_prt_near", True)):
            new = _changing(_estimate(near))  # a new light every call: the frames an estimate arrives on
            out[key] = measure(lambda new=new: st._smooth(st.predict(None, new())), repeat)
            out[key + "_drawn"] = measure(lambda new=new: drawn(st, new()), repeat)
            out[key + "_drawn_proxy_only"] = measure(lambda new=new: drawn(proxy_only, new()), repeat)
        # the frames between two estimates: the same light again (the stage reuses its shading)
        est = _estimate(True)
        out["stage_prt_same_light"] = measure(lambda: st._smooth(st.predict(None, est)), repeat)
        st.close()
        proxy_only.close()
        keys = ("stage_prt", "stage_prt_near")
        _report(
            out, keys + tuple(k + s for k in keys for s in ("_drawn", "_drawn_proxy_only")) + ("stage_prt_same_light",)
        )
        if bundle.prt.render_transfer is not None:
            parts = []
            for k in keys:
                a, p = out[k + "_drawn"]["median_ms"], out[k + "_drawn_proxy_only"]["median_ms"]
                out[k + "_drawn_ratio"] = a / max(p, 1e-9)
                parts.append(f"{k[6:]} {a:.3f} ms vs {p:.3f} ms proxy-only (x{a / max(p, 1e-9):.2f})")
            print(
                "render-mesh transfer: stage + carry to the render mesh "
                + ", ".join(parts)
                + " (the stage figures include what the renderer no longer carries)"
            )
        worst = max(out["stage_prt"]["median_ms"], out["stage_prt_near"]["median_ms"])
        out["prt_target_ms"] = TARGET_PRT_MS
        out["prt_meets_target"] = worst <= TARGET_PRT_MS
        print(
            f"PRT per-frame stage median (worst of distant/near) {worst:.3f} ms vs target {TARGET_PRT_MS} ms: "
            f"{'OK' if out['prt_meets_target'] else 'MISSED'}"
        )
    else:
        print(f"bundle {bundle.name} has no PRT tables (illuminet bundle adds them): no PRT figures")
    return out
