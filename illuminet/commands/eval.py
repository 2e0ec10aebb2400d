"""``illuminet eval``: the evaluation report of a bundle (markdown + JSON + PNG figure).

Example::

    illuminet eval --bundle builtin:vase --cases 100 --out docs/eval/vase --hdr ../shared/data/hdri

Lighting suites (``--cases N`` per suite; 0 skips them): indoor, outdoor, spatially-varying
(synthetic) and real HDR lighting (held-out maps) when ``--hdr`` points at a folder of ``.hdr`` maps.
Methods in the same run: ours int8 and fp32, constant prior, ambient, SH fitted to the RGB-D samples,
oracle SH. ``--ablation`` also retrains the GAN stage with and without the shading + smoothness
losses from the bundle's training work folder (needs the training extra and ``<bundle>/work`` from
``illuminet train``). ``--update-bundle`` writes the figures into the bundle (``eval.json`` and the
``evaluation`` section of bundle.json).

Camera suites (``--camera-scenes N`` per suite; 0 skips them; :mod:`illuminet.models.camera_eval`):
RGB-D frames of the synthetic camera (indoor, outdoor with the held-out HDR maps, lamp, spatial,
cluttered) through the pipeline's own lighting chain; "ours" is what the configured chain produces,
beside the learned transfer, the constant prior, ambient, SH fitted to RGB-D (plain and with the
object's visibility) and the two SH2 oracles. ``--variant NAME:section.key=value,...`` (repeatable)
adds a row per named configuration (ablations), all in one table::

    illuminet eval --cases 0 --camera-scenes 8 --variant no_walls:plane_light.extra_planes=0

``--crosscheck`` instead compares the synthetic camera's ground truth with the path tracer Mitsuba 3
(optional: ``pip install 'illuminet[groundtruth]'``) on a few scenes (:mod:`illuminet.models.crosscheck`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

log = logging.getLogger("illuminet.eval")

#: the camera suites and cross-check scenes (spelled here so that --help needs no heavy imports)
CAMERA_SUITES = ("indoor", "outdoor", "lamp", "spatial", "cluttered")
CROSSCHECK_SCENES = ("lamp_room", "area_lamp_boxes", "indoor_table", "outdoor_hdr")


def register(sub) -> None:
    p = sub.add_parser(
        "eval",
        help="evaluate a bundle against ground truth and baselines",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--bundle", default=None, help="bundle to evaluate (default: [model] bundle)")
    p.add_argument("--cases", type=int, default=100, help="test cases per lighting suite (default 100; 0 = skip them)")
    p.add_argument("--flicker-scenes", type=int, default=8, help="static scenes per suite for temporal flicker")
    p.add_argument("--seed", type=int, default=0, help="test-set seed (default 0)")
    p.add_argument(
        "--hdr",
        metavar="DIR",
        default=None,
        help="folder of .hdr maps for the real-lighting suite (held-out maps only); default: "
        "../shared/data/hdri when present",
    )
    p.add_argument("--out", metavar="DIR", default=None, help="report folder (default: eval/<bundle name>)")
    p.add_argument("--ablation", action="store_true", help="also run the loss ablation (retrains the GAN stage)")
    p.add_argument("--ablation-epochs", type=int, default=8, help="GAN epochs per ablation variant (default 8)")
    p.add_argument("--no-figure", action="store_true", help="skip the rendered PNG figure")
    p.add_argument(
        "--camera-scenes",
        type=int,
        default=8,
        help="scenes per camera suite (end to end on the synthetic camera; 0 = skip; default 8)",
    )
    p.add_argument("--camera-frames", type=int, default=6, help="frames per camera scene (default 6)")
    p.add_argument(
        "--camera-suites",
        default=",".join(CAMERA_SUITES),
        metavar="LIST",
        help=f"comma-separated camera suites (default: {','.join(CAMERA_SUITES)})",
    )
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME:SECTION.KEY=VALUE,...",
        help="another named configuration of the pipeline for the camera suites (repeatable)",
    )
    p.add_argument(
        "--vertices",
        type=int,
        default=0,
        help="camera suites: evaluate this many render vertices, evenly spread (0 = all)",
    )
    p.add_argument(
        "--crosscheck",
        action="store_true",
        help="compare the synthetic ground truth with Mitsuba 3 instead (needs illuminet[groundtruth])",
    )
    p.add_argument(
        "--crosscheck-scenes",
        default=",".join(CROSSCHECK_SCENES),
        metavar="LIST",
        help=f"cross-check scenes (default: {','.join(CROSSCHECK_SCENES)})",
    )
    p.add_argument("--crosscheck-vertices", type=int, default=300, help="object vertices compared (default 300)")
    p.add_argument("--crosscheck-spp", type=int, default=512, help="Mitsuba rays per vertex (default 512)")
    p.add_argument(
        "--crosscheck-object", default="builtin:bowl", help="object of the cross-check (default builtin:bowl)"
    )
    p.add_argument(
        "--crosscheck-bounces",
        type=int,
        default=None,
        help="in-house bounces to check (default: the synthetic camera's default)",
    )
    p.add_argument(
        "--mitsuba-variant",
        choices=("scalar_rgb", "llvm"),
        default="scalar_rgb",
        help="Mitsuba variant: scalar_rgb (always works) or llvm (llvm_ad_rgb, several times faster; "
        "needs libLLVM >= 16, point DRJIT_LIBLLVM_PATH at it)",
    )
    p.add_argument("--update-bundle", action="store_true", help="store the figures in the bundle")
    p.set_defaults(func=run)


def _ablation(ev, epochs: int) -> None:
    """Retrain the GAN stage twice (paper losses vs without shading + smoothness) on the bundle's data."""
    import numpy as np

    from illuminet.models.train import TrainConfig, Trainer, predict_jax

    b = ev.bundle
    work = b.path / "work"
    if not work.is_dir():
        raise FileNotFoundError(f"--ablation needs {work} (the training work folder of `illuminet train`)")
    conf = dict(b.meta["training"]["config"])
    conf["kinds"] = tuple(conf["kinds"])
    conf["betas_gae"] = tuple(conf["betas_gae"])
    conf["betas_gan"] = tuple(conf["betas_gan"])
    tr = Trainer(TrainConfig(**conf), b.path, show_progress=False)
    base = tr.train(stop_after="colour_gae")  # loads the finished GAE checkpoints
    tr.cfg.epochs_gan = epochs
    import jax

    for name, bsh, bsm in (("ablation_full", tr.cfg.beta_shading, tr.cfg.beta_smooth), ("ablation_noshsm", 0.0, 0.0)):
        ck = tr.work / f"{name}.npz"
        if ck.is_file():
            ck.unlink()  # always a fresh run with the requested epochs
        t0 = time.time()
        res = dict(base)
        res.update(tr.train_gan(base, jax.random.PRNGKey(tr.cfg.seed + 99), bsh, bsm, name))
        log.info("ablation %s: %d GAN epochs in %.0f s", name, epochs, time.time() - t0)

        def f(x, res=res):
            return np.asarray(predict_jax(res, tr.a_plane, tr.a_obj, tr.normals, x[None])[1][0])

        ev.extra_predictors[name] = f


def _crosscheck(args, hdr: str) -> int:
    from illuminet.models.crosscheck import CrosscheckUnavailable, markdown, run_crosscheck
    from illuminet.models.train import Progress

    names = [n for n in args.crosscheck_scenes.split(",") if n]
    bad = [n for n in names if n not in CROSSCHECK_SCENES]
    if bad:
        print(
            f"illuminet eval: unknown cross-check scene(s) {', '.join(bad)}; known: {', '.join(CROSSCHECK_SCENES)}",
            file=sys.stderr,
        )
        return 2
    try:
        report = run_crosscheck(
            names,
            args.crosscheck_object,
            args.crosscheck_vertices,
            args.crosscheck_spp,
            bounces=args.crosscheck_bounces,
            hdr_dir=hdr or None,
            variant=args.mitsuba_variant,
            progress=Progress("crosscheck", len(names)),
        )
    except CrosscheckUnavailable as e:
        print(f"illuminet eval: {e}", file=sys.stderr)
        return 2
    out = Path(args.out or Path("eval") / "crosscheck")
    out.mkdir(parents=True, exist_ok=True)
    (out / "crosscheck.json").write_text(json.dumps(report, indent=2) + "\n")
    md = markdown(report)
    (out / "crosscheck.md").write_text(md)
    print(md)
    print(f"wrote {out / 'crosscheck.md'}, {out / 'crosscheck.json'}")
    return 0


def run(args: argparse.Namespace, cfg) -> int:
    from illuminet.commands.train import DEFAULT_HDR
    from illuminet.models.train import Progress
    from illuminet.runtime.assets.bundle import BundleError
    from illuminet.runtime.config import ConfigError

    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    if args.crosscheck:
        return _crosscheck(args, hdr)
    from illuminet.models.eval import LABELS, Evaluator, finish, markdown, write_outputs

    spec = args.bundle or cfg.model.bundle
    suites = [s for s in args.camera_suites.split(",") if s]
    bad = [s for s in suites if s not in CAMERA_SUITES]
    if bad:
        print(
            f"illuminet eval: unknown camera suite(s) {', '.join(bad)}; known: {', '.join(CAMERA_SUITES)}",
            file=sys.stderr,
        )
        return 2
    cam = None
    try:
        if args.camera_scenes > 0:
            from illuminet.models.camera_eval import CameraEval, parse_variant
            from illuminet.pipeline import build_stages

            cam = CameraEval(
                cfg, build_stages, spec, [parse_variant(v) for v in args.variant], hdr or None, args.vertices or None
            )
        ev = Evaluator(spec, hdr or None) if args.cases > 0 else None
    except (BundleError, ConfigError) as e:
        print(f"illuminet eval: {e}", file=sys.stderr)
        return 2
    if hdr and ev is not None:
        print(f"# real HDR lighting from {hdr} (held-out maps: {', '.join(ev.hdr_names) or 'none'})")
    t0 = time.time()
    if ev is not None:
        if args.ablation:
            try:
                _ablation(ev, args.ablation_epochs)
            except (ImportError, FileNotFoundError) as e:
                print(f"illuminet eval: ablation skipped: {e}", file=sys.stderr)
        report = finish(
            ev.run(
                args.cases,
                args.flicker_scenes,
                smoothing=cfg.model.temporal_smoothing,
                seed=args.seed,
                progress=Progress("eval", 1),
            )
        )
        name = ev.bundle.name
    else:
        name = cam.bundle.name if cam is not None else str(spec)
        report = {"bundle": name, "suites": {}}
    if cam is not None:
        report["camera"] = cam.run(
            suites, args.camera_scenes, args.camera_frames, args.seed, progress=Progress("camera", 1)
        )
    report["eval_wall_s"] = round(time.time() - t0, 1)
    out = Path(args.out or Path("eval") / name)
    out.mkdir(parents=True, exist_ok=True)
    fig = None
    if ev is not None and not args.no_figure and ev.examples:
        try:
            from illuminet.models.figure import figure

            suite = "outdoor" if "outdoor" in ev.examples else next(iter(ev.examples))
            ex = ev.examples[suite]
            order = ["true", "constant", "ambient", "sh_rgbd", "oracle_sh", "ours_int8"]
            names = {"true": "Ground truth", **LABELS}
            panels = [(names[m], ex[m] / 3.14159265 * ex["k"]) for m in order if m in ex]
            fig = out / "eval.png"
            figure(
                fig,
                ev.bundle.vertices,
                ev.bundle.faces,
                panels,
                title=f"{ev.bundle.name}: {suite} test case (front row, back row)",
            )
            report["figure"] = fig.name
        except Exception as e:  # no EGL: the report is still written
            print(f"illuminet eval: figure skipped ({e})", file=sys.stderr)
            fig = None
    paths = write_outputs(report, out, fig)
    print(markdown(report))
    if cam is not None:
        from illuminet.models.camera_eval import markdown as camera_markdown

        print(camera_markdown(report["camera"]))
    print(f"wrote {paths['md']}, {paths['json']}" + (f", {fig}" if fig else ""))
    if args.update_bundle and ev is not None:
        from illuminet.models.export import finalize_bundle

        (ev.bundle.path / "eval.json").write_text(json.dumps(report, indent=2) + "\n")
        meta = dict(ev.bundle.meta)
        meta["evaluation"] = {
            s: {
                m: {k: v for k, v in r.items()}
                for m, r in res.items()
                if m in ("ours_int8", "ours_fp32", "constant", "ambient", "sh_rgbd", "oracle_sh")
            }
            for s, res in report["suites"].items()
        }
        meta["evaluation"]["n_cases"] = report["n_cases"]
        meta["evaluation"]["int8_vs_fp32_mae_max_diff"] = report["int8_vs_fp32_mae_max_diff"]
        finalize_bundle(ev.bundle.path, meta)
        print(f"updated {ev.bundle.path / 'bundle.json'}")
    return 0
