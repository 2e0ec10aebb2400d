"""Evaluation of a bundle against ground truth and baselines (what ``illuminet eval`` reports).

Test cases are drawn like training data but from different seeds (and, for real HDR lighting, from
HDR maps held out of training: every 4th map). For every case the ground truth is the shading of
**every render-mesh vertex** (front and back) with self-visibility; predictions are carried from the
proxy to the render mesh. Intensities are compared as a camera would record them: a white
Lambertian surface, ``I = clip(E / pi * k, 0, 1)`` with the *same* exposure ``k`` for prediction and
truth, ``k`` set by auto exposure on the plane (its mean radiance at albedo 0.5 -> 0.18).

Metrics: MAE and RMSE of I (the paper's table), scale-invariant RMSE (best single gain on the
prediction), dominant-light angular error (luminance-weighted OI direction, degrees) and temporal
flicker (mean |I_t - I_(t-1)| over a static scene whose plane is re-measured with fresh noise each
frame; with the runtime's temporal smoothing for the model).

Methods, all in the same run: ours (int8 and fp32 ONNX), constant prior (the bundle's mean training
shading times the plane scale), ambient (the plane's mean irradiance everywhere), SH (second-order
spherical harmonics fitted by least squares to all observed RGB-D samples with their normals:
here the plane's observed cells), and the oracle (SH projected from the true lights).

These are the *lighting suites* (the training data's grid simulation of a plane patch). The end-to-end
suites on the synthetic camera, through the pipeline's own stages, are :mod:`illuminet.models.camera_eval`.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from illuminet.models import datagen
from illuminet.runtime.assets.bundle import Bundle, TransferChain, load_bundle
from illuminet.runtime.stages.shading import LUMA, dominant_light_from_oi, preprocess_plane

log = logging.getLogger(__name__)

SUITES = ("indoor", "outdoor", "spatial")
METHODS = ("ours_int8", "ours_fp32", "constant", "ambient", "sh_rgbd", "oracle_sh")
LABELS = {
    "ours_int8": "Ours (int8)",
    "ours_fp32": "Ours (fp32)",
    "constant": "Constant prior",
    "ambient": "Ambient only",
    "sh_rgbd": "SH from RGB-D",
    "oracle_sh": "Oracle SH (true light)",
    "ablation_full": "GAN stage, all losses",
    "ablation_noshsm": "GAN stage, no shading/smooth",
}
SEED_BASE = 1_000_003  # test seeds never collide with training seeds (seed*1000 + 1/2)


# --------------------------------------------------------------------------- spherical harmonics
# the SH basis and the RGB-D fit live in the runtime (the stage's `sh` mode uses them too)
from illuminet.runtime.sh import SH_A_HAT as _A_HAT  # noqa: E402
from illuminet.runtime.sh import sh9, sh_eval  # noqa: E402
from illuminet.runtime.sh import sh_fit as sh_fit_rgbd  # noqa: E402

#: regularisation strengths tried on validation cases for the SH baseline (the best one is used)
SH_LAMBDAS = (0.0, 1e-3, 1e-2, 0.1, 1.0, 10.0)


def sh_oracle(light_pos: np.ndarray, light_rgb: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """SH9 irradiance coefficients (9, 3) of the true lights seen from the object's centre.

    Lights below the plane are dropped (the plane blocks them for the whole object)."""
    d = light_pos - centre
    r2 = (d * d).sum(1)
    w = d / np.sqrt(r2)[:, None]
    keep = light_pos[:, 1] > 0
    L = sh9(w[keep]).T @ (light_rgb[keep] / r2[keep, None])  # radiance SH of the point lights
    return L * _A_HAT[:, None]


def sh_dominant(coef: np.ndarray) -> np.ndarray | None:
    lin = coef[1:4] @ LUMA  # (y, z, x) order of the linear band
    d = np.array([lin[2], lin[0], lin[1]])
    n = np.linalg.norm(d)
    return None if n < 1e-12 else d / n


# --------------------------------------------------------------------------- metrics


def exposed(e: np.ndarray, k: float) -> np.ndarray:
    """Irradiance -> recorded intensity of a white Lambertian surface, clipped to [0, 1]."""
    return np.clip(np.asarray(e) / np.pi * k, 0.0, 1.0)


def case_metrics(pred_e: np.ndarray, true_e: np.ndarray, k: float) -> dict:
    p, t = exposed(pred_e, k), exposed(true_e, k)
    err = p - t
    a = float((p * t).sum() / max((p * p).sum(), 1e-12))
    return {
        "mae": float(np.abs(err).mean()),
        "rmse": float(np.sqrt((err**2).mean())),
        "si_rmse": float(np.sqrt(((a * p - t) ** 2).mean())),
    }


def angle_deg(a, b) -> float | None:
    if a is None or b is None:
        return None
    c = float(np.clip(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12), -1, 1))
    return float(np.degrees(np.arccos(c)))


# --------------------------------------------------------------------------- evaluation


class Evaluator:
    """Holds a bundle, its chains and the ground-truth scene (visibility tables of the render mesh)."""

    def __init__(self, bundle: str | Bundle, hdr_dir: str | None = None):
        import trimesh

        self.bundle = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
        b = self.bundle
        self.chains = {p: TransferChain(b, p) for p in ("int8", "fp32")}
        mesh = trimesh.Trimesh(b.vertices, b.faces, process=False)
        geom = datagen.ObjectGeometry(
            b.vertices, b.normals, b.faces, b.proxy_index, b.proxy_edges, b.carry_index, b.carry_weight, b.name
        )
        t0 = time.time()
        self.scene = datagen.Scene(geom, mesh, b.grid, b.extent_m, render_vis=True)
        log.info(
            "evaluation scene for %s: %d render vertices (visibility tables %.1fs)",
            b.name,
            len(b.vertices),
            time.time() - t0,
        )
        self.centre = np.array([0.0, float(np.ptp(b.vertices[:, 1])) / 2, 0.0])
        self.hdr, self.hdr_names = held_out_lights(hdr_dir)
        self.extra_predictors: dict = {}  # name -> f(x (P', 4)) -> proxy shading / s (ablation models)
        self.sh_lambda = 0.0

    def tune_scores(self, si: int, suite: str, n: int = 30) -> dict[float, list[float]]:
        """The SH baseline's MAE per regulariser on ``n`` validation cases of suite number ``si``."""
        scores: dict[float, list[float]] = {lam: [] for lam in SH_LAMBDAS}
        b, sc = self.bundle, self.scene
        rng = np.random.default_rng(SEED_BASE + 50_000 + si)
        for _ in range(n):
            pos, rgb, e_plane, _, true_e = self._case(suite, rng)
            meas, mask = sc.measure(e_plane, rng)
            k = 0.18 / max(float((0.5 * e_plane @ LUMA).mean() / np.pi), 1e-12)
            m = mask.astype(bool)
            for lam in SH_LAMBDAS:
                coef = sh_fit_rgbd(sc.plane_n[m], meas[m], lam=lam)
                scores[lam].append(case_metrics(sh_eval(coef, b.normals), true_e, k)["mae"])
        return scores

    def tune_sh(self, n: int = 30) -> dict:
        """Pick the SH baseline's regulariser on validation cases (seeds apart from the test set),
        so the baseline is at its best rather than at an arbitrary setting. Returns MAE per lambda."""
        return self.set_sh_lambda([self.tune_scores(si, s, n) for si, s in enumerate(self.suites())])

    def set_sh_lambda(self, per_suite: list[dict]) -> dict:
        """Use :func:`pick_sh_lambda` of every suite's :meth:`tune_scores`; returns MAE per lambda."""
        self.sh_lambda, res = pick_sh_lambda(per_suite)
        return res

    def suites(self) -> list[str]:
        return suites(self.hdr)

    def _case(self, kind: str, rng: np.random.Generator):
        pos, rgb = datagen.sample_lights(kind, rng, hdr_lights=self.hdr)
        pos = pos @ datagen._yaw(rng.uniform(0, 2 * np.pi)).T
        e_plane, oi_true, _ = self.scene.truth(pos, rgb)
        true_e = self.scene.render_truth(pos, rgb)
        return pos, rgb, e_plane, oi_true, true_e

    def predict_all(self, meas, mask, pos, rgb) -> dict:
        """Every method's render-mesh irradiance (R, 3) and dominant direction for one measurement."""
        b, sc = self.bundle, self.scene
        x, s = preprocess_plane(meas, mask, b.grid, b.pool)
        out = {}
        for prec, ch in self.chains.items():
            oi, sh = ch(x)
            out[f"ours_{prec}"] = (b.carry(np.maximum(sh, 0) * s), dominant_light_from_oi(oi)[0])
        out["constant"] = (b.carry(b.prior_shading * s), None)
        m = mask.astype(bool)
        amb = meas[m].mean(0)
        out["ambient"] = (np.tile(amb[None], (len(b.vertices), 1)), None)
        coef = sh_fit_rgbd(sc.plane_n[m], meas[m], lam=self.sh_lambda)
        out["sh_rgbd"] = (sh_eval(coef, b.normals), sh_dominant(coef))
        coef_o = sh_oracle(pos, rgb, self.centre)
        out["oracle_sh"] = (sh_eval(coef_o, b.normals), sh_dominant(coef_o))
        for name, f in self.extra_predictors.items():
            out[name] = (b.carry(np.maximum(f(x), 0) * s), None)
        return out

    def run(
        self,
        n_cases: int = 100,
        n_flicker: int = 8,
        flicker_frames: int = 12,
        smoothing: float = 0.7,
        seed: int = 0,
        progress=None,
        keep_examples: bool = True,
    ) -> dict:
        """All suites; returns the report dict (per suite and method: mean metrics)."""
        sh_scores = self.tune_sh()
        report = report_head(self.bundle, self.hdr_names, n_cases, seed, self.sh_lambda, sh_scores)
        self.examples = {}
        suites = self.suites()
        for si, suite in enumerate(suites):

            def bar(c, _total, si=si):
                if progress:
                    progress(si * n_cases + c, len(suites) * n_cases)

            res, example = self.run_suite(
                si, suite, n_cases, n_flicker, flicker_frames, smoothing, seed, bar, keep_examples
            )
            report["suites"][suite] = res
            if example is not None:
                self.examples[suite] = example
        return report

    def run_suite(
        self,
        si: int,
        suite: str,
        n_cases: int = 100,
        n_flicker: int = 8,
        flicker_frames: int = 12,
        smoothing: float = 0.7,
        seed: int = 0,
        progress=None,
        keep_examples: bool = True,
    ) -> tuple[dict, dict | None]:
        """Suite number ``si`` (its own random streams: a shard of its own): per method the mean
        metrics and flicker, and the figure's example case (or None)."""
        rng = np.random.default_rng(SEED_BASE + 7 * seed + si)
        acc: dict[str, list] = {}
        ang: dict[str, list] = {}
        best_ex = None
        for c in range(n_cases):
            pos, rgb, e_plane, oi_true, true_e = self._case(suite, rng)
            meas, mask = self.scene.measure(e_plane, rng)
            k = 0.18 / max(float((0.5 * e_plane @ LUMA).mean() / np.pi), 1e-12)
            preds = self.predict_all(meas, mask, pos, rgb)
            d_true = dominant_light_from_oi(oi_true)[0]
            for mth, (pe, pd) in preds.items():
                acc.setdefault(mth, []).append(case_metrics(pe, true_e, k))
                a = angle_deg(pd, d_true)
                if a is not None:
                    ang.setdefault(mth, []).append(a)
            if keep_examples and c < 12:
                # the figure shows the case with the largest spread of true intensities (most telling)
                spread = float(np.std(exposed(true_e, k) @ LUMA))
                if best_ex is None or spread > best_ex[0]:
                    best_ex = (spread, {"true": true_e, "k": k, **{m: v[0] for m, v in preds.items()}})
            if progress:
                progress(c + 1, n_cases)
        res = {}
        for mth, lst in acc.items():
            res[mth] = {key: float(np.mean([d[key] for d in lst])) for key in ("mae", "rmse", "si_rmse")}
            res[mth]["angle_deg"] = float(np.median(ang[mth])) if mth in ang else None
        flick = self.flicker(suite, n_flicker, flicker_frames, smoothing, seed)
        for mth, v in flick.items():
            res.setdefault(mth, {})["flicker"] = v
        return res, (best_ex[1] if best_ex is not None else None)

    def flicker(self, suite: str, n: int, frames: int, smoothing: float, seed: int) -> dict:
        """Mean frame-to-frame change of the intensities on static scenes (fresh plane noise per frame)."""
        rng = np.random.default_rng(
            SEED_BASE + 999 + 10 * seed + (self.suites().index(suite) if suite in self.suites() else 9)
        )
        out: dict[str, list] = {}
        for _ in range(n):
            pos, rgb, e_plane, _, _ = self._case(suite, rng)
            k = 0.18 / max(float((0.5 * e_plane @ LUMA).mean() / np.pi), 1e-12)
            prev: dict = {}
            ema = None
            for _ in range(frames):
                # the same lighting, a new measurement: noise, texture and masks change per frame only
                # through sensor noise: a static camera sees the same plane texture and holes
                frng = np.random.default_rng(int(rng.integers(1 << 31)))
                meas, mask = self.scene.measure(e_plane, np.random.default_rng(12345), noise=0.0)
                meas = meas * (1 + 0.03 * frng.normal(0, 1, meas.shape)).astype(np.float32)
                preds = self.predict_all(meas, mask, pos, rgb)
                cur = {m: exposed(v[0], k) for m, v in preds.items() if m in ("ours_int8", "ambient", "sh_rgbd")}
                ema = cur["ours_int8"] if ema is None else smoothing * ema + (1 - smoothing) * cur["ours_int8"]
                cur["ours_int8_smoothed"] = ema
                for m, v in cur.items():
                    if m in prev:
                        out.setdefault(m, []).append(float(np.abs(v - prev[m]).mean()))
                prev = cur
        return {m: float(np.mean(v)) for m, v in out.items()}


def pick_sh_lambda(per_suite: list[dict]) -> tuple[float, dict]:
    """The SH regulariser of the lowest mean validation MAE over every suite's cases (suites in order)
    and the mean MAE per regulariser."""
    res = {lam: float(np.mean([v for d in per_suite for v in d[lam]])) for lam in SH_LAMBDAS}
    return min(res, key=res.get), res


def held_out_lights(hdr_dir) -> tuple[list, list[str]]:
    """The held-out HDR maps' median-cut lights and file names (both empty without maps)."""
    hdr = datagen.load_hdr_lights(hdr_dir, split="test") if hdr_dir else []
    return hdr, ([p.name for p in datagen.hdr_maps(hdr_dir, "test")] if hdr else [])


def suites(hdr_lights) -> list[str]:
    """The lighting suites: the synthetic ones, and ``hdr`` when held-out maps were loaded."""
    return list(SUITES) + (["hdr"] if hdr_lights else [])


def report_head(bundle: Bundle, hdr_names: list[str], n_cases: int, seed: int, sh_lambda, sh_scores: dict) -> dict:
    """The report's fields around the per-suite results (``suites`` is filled by the caller)."""
    return {
        "bundle": bundle.name,
        "n_cases": n_cases,
        "seed": seed,
        "suites": {},
        "sh_lambda": sh_lambda,
        "sh_lambda_validation_mae": {str(k): v for k, v in sh_scores.items()},
        "hdr_test_maps": hdr_names,
        "render_vertices": int(len(bundle.vertices)),
        "exposure": "white Lambertian, I = clip(E/pi*k, 0, 1), k: plane mean radiance (albedo 0.5) -> 0.18",
    }


# --------------------------------------------------------------------------- report writing


def _fmt(v, nd=3):
    return "n/a" if v is None else f"{v:.{nd}f}"


def markdown(report: dict) -> str:
    """The lighting suites' report (empty when they were skipped with ``--cases 0``)."""
    suites = list(report["suites"])
    if not suites:
        return f"# Evaluation: bundle `{report['bundle']}`\n"
    methods = [m for m in list(METHODS) + ["ablation_full", "ablation_noshsm"] if m in report["suites"][suites[0]]]
    lines = [
        f"# Evaluation: bundle `{report['bundle']}`",
        "",
        f"{report['n_cases']} test cases per suite, every render vertex ({report['render_vertices']}) front "
        f"and back; {report['exposure']}. Test seeds differ from training seeds"
        + (
            f"; real HDR suite uses held-out maps: {', '.join(report['hdr_test_maps'])}"
            if report["hdr_test_maps"]
            else ""
        )
        + f". SH baseline regulariser chosen on separate validation cases: lambda = {report.get('sh_lambda')}"
        + ".",
        "",
        "## Relighting error (the paper's table)",
        "",
        "| Method | " + " | ".join(f"{s} MAE | {s} RMSE" for s in suites) + " |",
        "|---|" + "---|---|" * len(suites),
    ]
    for m in methods:
        row = [LABELS.get(m, m)]
        for s in suites:
            r = report["suites"][s].get(m, {})
            row += [_fmt(r.get("mae")), _fmt(r.get("rmse"))]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "## Scale-invariant RMSE, dominant-light angular error (median, degrees), temporal flicker",
        "",
        "| Method | " + " | ".join(f"{s} si-RMSE | {s} angle | {s} flicker" for s in suites) + " |",
        "|---|" + "---|---|---|" * len(suites),
    ]
    for m in methods + ["ours_int8_smoothed"]:
        row = [LABELS.get(m, m if m != "ours_int8_smoothed" else "Ours (int8) + temporal smoothing")]
        for s in suites:
            r = report["suites"][s].get(m, {})
            row += [_fmt(r.get("si_rmse")), _fmt(r.get("angle_deg"), 1), _fmt(r.get("flicker"), 4)]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "## Ours vs the baselines (MAE; positive = ours better)", ""]
    for s in suites:
        r = report["suites"][s]
        o = r["ours_int8"]["mae"]
        parts = []
        for m in ("constant", "ambient", "sh_rgbd", "oracle_sh"):
            parts.append(f"{LABELS[m]} {r[m]['mae'] - o:+.3f} ({(r[m]['mae'] - o) / max(r[m]['mae'], 1e-9):+.0%})")
        lines.append(f"- **{s}**: " + "; ".join(parts))
    d = report.get("int8_vs_fp32_mae_max_diff")
    if d is not None:
        lines += ["", f"int8 vs fp32: largest MAE difference over suites {d:.4f} (target <= 0.005)."]
    return "\n".join(lines) + "\n"


def finish(report: dict) -> dict:
    if not report["suites"]:
        return report
    report["int8_vs_fp32_mae_max_diff"] = float(
        max(abs(r["ours_int8"]["mae"] - r["ours_fp32"]["mae"]) for r in report["suites"].values())
    )
    wins = {}
    for s, r in report["suites"].items():
        wins[s] = {m: bool(r["ours_int8"]["mae"] < r[m]["mae"]) for m in ("constant", "ambient", "sh_rgbd")}
    report["ours_beats"] = wins
    return report


def write_outputs(report: dict, out_dir: Path, figure_png: Path | None = None) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "eval.json").write_text(json.dumps(report, indent=2) + "\n")
    md = markdown(report)
    if "camera" in report:
        from illuminet.models.camera_eval import markdown as camera_markdown

        md += camera_markdown(report["camera"])
    if figure_png is not None:
        md += f"\n![ground truth, baselines and ours, front and back]({figure_png.name})\n"
    (out_dir / "eval.md").write_text(md)
    return {"json": str(out_dir / "eval.json"), "md": str(out_dir / "eval.md")}
