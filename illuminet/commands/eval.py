"""``illuminet eval``: the evaluation report of a bundle (markdown + JSON + PNG figure).

Example::

    illuminet eval --bundle builtin:vase --cases 100 --out docs/eval/vase --hdr ../shared/data/hdri

Suites: indoor, outdoor, spatially-varying (synthetic, always) and real HDR lighting (held-out maps)
when ``--hdr`` points at a folder of ``.hdr`` maps. Methods in the same run: ours int8 and fp32,
constant prior, ambient, SH fitted to the RGB-D samples, oracle SH. ``--ablation`` also retrains the
GAN stage with and without the shading + smoothness losses from the bundle's training work folder
(needs the training extra and ``<bundle>/work`` from ``illuminet train``). ``--update-bundle``
writes the figures into the bundle (``eval.json`` and the ``evaluation`` section of bundle.json).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

log = logging.getLogger("illuminet.eval")


def register(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a bundle against ground truth and baselines",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bundle", default=None, help="bundle to evaluate (default: [model] bundle)")
    p.add_argument("--cases", type=int, default=100, help="test cases per suite (default 100)")
    p.add_argument("--flicker-scenes", type=int, default=8, help="static scenes per suite for temporal flicker")
    p.add_argument("--seed", type=int, default=0, help="test-set seed (default 0)")
    p.add_argument("--hdr", metavar="DIR", default=None,
                   help="folder of .hdr maps for the real-lighting suite (held-out maps only); default: "
                        "../shared/data/hdri when present")
    p.add_argument("--out", metavar="DIR", default=None, help="report folder (default: eval/<bundle name>)")
    p.add_argument("--ablation", action="store_true", help="also run the loss ablation (retrains the GAN stage)")
    p.add_argument("--ablation-epochs", type=int, default=8, help="GAN epochs per ablation variant (default 8)")
    p.add_argument("--no-figure", action="store_true", help="skip the rendered PNG figure")
    p.add_argument("--camera-scenes", type=int, default=8,
                   help="scenes per kind for the end-to-end synthetic-camera suite (0 = skip; default 8)")
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


def run(args: argparse.Namespace, cfg) -> int:
    from illuminet.commands.train import DEFAULT_HDR
    from illuminet.models.eval import Evaluator, finish, markdown, write_outputs
    from illuminet.models.train import Progress
    from illuminet.runtime.assets.bundle import BundleError

    spec = args.bundle or cfg.model.bundle
    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    try:
        ev = Evaluator(spec, hdr or None)
    except BundleError as e:
        print(f"illuminet eval: {e}", file=sys.stderr)
        return 2
    if hdr:
        print(f"# real HDR lighting from {hdr} (held-out maps: {', '.join(ev.hdr_names) or 'none'})")
    t0 = time.time()
    if args.ablation:
        try:
            _ablation(ev, args.ablation_epochs)
        except (ImportError, FileNotFoundError) as e:
            print(f"illuminet eval: ablation skipped: {e}", file=sys.stderr)
    report = ev.run(args.cases, args.flicker_scenes, smoothing=cfg.model.temporal_smoothing, seed=args.seed,
                    progress=Progress("eval", 1))
    report = finish(report)
    if args.camera_scenes > 0:
        from illuminet.models.eval import run_camera

        report["camera"] = run_camera(ev, cfg, n_scenes=args.camera_scenes, seed=args.seed,
                                      progress=Progress("camera", 1))
    report["eval_wall_s"] = round(time.time() - t0, 1)
    out = Path(args.out or Path("eval") / ev.bundle.name)
    out.mkdir(parents=True, exist_ok=True)
    fig = None if args.no_figure else _figure(ev, report, out)
    paths = write_outputs(report, out, fig)
    print(markdown(report))
    print(f"wrote {paths['md']}, {paths['json']}" + (f", {fig}" if fig else ""))
    if args.update_bundle:
        _update_bundle(ev, report)
    return 0


def _figure(ev, report: dict, out: Path) -> Path | None:
    """The rendered comparison (ground truth, baselines, ours) of one test case; None without one."""
    from illuminet.models.eval import LABELS

    if not ev.examples:
        return None
    try:
        from illuminet.models.figure import figure

        suite = "outdoor" if "outdoor" in ev.examples else next(iter(ev.examples))
        ex = ev.examples[suite]
        order = ["true", "constant", "ambient", "sh_rgbd", "oracle_sh", "ours_int8"]
        names = {"true": "Ground truth", **LABELS}
        panels = [(names[m], ex[m] / 3.14159265 * ex["k"]) for m in order if m in ex]
        fig = out / "eval.png"
        figure(fig, ev.bundle.vertices, ev.bundle.faces, panels,
               title=f"{ev.bundle.name}: {suite} test case (front row, back row)")
    except Exception as e:  # no EGL: the report is still written
        print(f"illuminet eval: figure skipped ({e})", file=sys.stderr)
        return None
    report["figure"] = fig.name
    return fig


def _update_bundle(ev, report: dict) -> None:
    """--update-bundle: the report as the bundle's eval.json, its headline figures in bundle.json."""
    from illuminet.models.export import finalize_bundle

    (ev.bundle.path / "eval.json").write_text(json.dumps(report, indent=2) + "\n")
    meta = dict(ev.bundle.meta)
    meta["evaluation"] = {s: {m: {k: v for k, v in r.items()} for m, r in res.items()
                              if m in ("ours_int8", "ours_fp32", "constant", "ambient", "sh_rgbd", "oracle_sh")}
                          for s, res in report["suites"].items()}
    meta["evaluation"]["n_cases"] = report["n_cases"]
    meta["evaluation"]["int8_vs_fp32_mae_max_diff"] = report["int8_vs_fp32_mae_max_diff"]
    finalize_bundle(ev.bundle.path, meta)
    print(f"updated {ev.bundle.path / 'bundle.json'}")
