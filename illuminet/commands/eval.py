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

``--ray [ADDRESS]`` runs the suites as Ray tasks (one per camera scene, per lighting suite and per
suite's SH tuning cases; :mod:`illuminet.cluster`, docs/cluster.md) and writes the same report; the
shards are kept in ``<out>/shards`` until it is written, so a rerun redoes only missing ones.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from illuminet import cluster
from illuminet.runtime.errors import EXIT_USAGE, JobError

log = logging.getLogger("illuminet.eval")

#: the camera suites and cross-check scenes (spelled here so that --help needs no heavy imports)
CAMERA_SUITES = ("indoor", "outdoor", "lamp", "spatial", "cluttered")
#: camera suites run only when named (--camera-suites): the look-around, 300 frames a scene
CAMERA_SUITES_ON_REQUEST = ("outdoor_look", "outdoor_boxes")
CROSSCHECK_SCENES = ("lamp_room", "area_lamp_boxes", "indoor_table", "outdoor_hdr")


def register(sub) -> None:
    from illuminet.commands.train import hdr_help_default

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
        f"{hdr_help_default()} (shared/data/hdri beside the checkout) when present",
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
    p.add_argument(
        "--camera-frames",
        type=int,
        default=30,
        help="frames per camera scene; the metrics are the last frame's (default 30: one second of a 30 fps "
        "camera, when the estimate has settled)",
    )
    p.add_argument(
        "--camera-suites",
        default=",".join(CAMERA_SUITES),
        metavar="LIST",
        help=f"comma-separated camera suites (default: {','.join(CAMERA_SUITES)}; also "
        "outdoor_look: the outdoor scenes seen after a look around, 300 frames each; outdoor_boxes: the "
        "outdoor scenes with three boxes casting shadows in view)",
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
        "--object-albedo",
        type=float,
        default=None,
        metavar="A",
        help="camera suites and --crosscheck: grey albedo of the object in the ground truth, so the light it "
        "reflects onto itself counts (default: the renderer's 0.8; 0 = a black object that only blocks light)",
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
    cluster.add_arguments(p, unit="lighting suite and camera scene")
    p.set_defaults(func=run)


def _usage(msg: str) -> JobError:
    return JobError(msg, exit_code=EXIT_USAGE)


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
    from illuminet.commands.train import check_out
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
            object_albedo=args.object_albedo,
        )
    except CrosscheckUnavailable as e:
        print(f"illuminet eval: {e}", file=sys.stderr)
        return 2
    out = Path(args.out or Path("eval") / "crosscheck")
    check_out("--out", out, folder=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "crosscheck.json").write_text(json.dumps(report, indent=2) + "\n")
    md = markdown(report)
    (out / "crosscheck.md").write_text(md)
    print(md)
    print(f"wrote {out / 'crosscheck.md'}, {out / 'crosscheck.json'}")
    return 0


#: the longest run ``eval`` starts (estimated on one core, from the per-unit costs below): a count beyond it
#: (``--cases 1000000000``) ran for years, nothing written until the end
EVAL_MAX_S = 24 * 3600
#: with ``--ray`` the run is shared by the cluster's workers (how many is not known before it starts): the
#: limit on the one-core estimate is this many times larger
RAY_MAX_FACTOR = 100
#: seconds per lighting test case and per flicker scene, per lighting suite (measured on the 2-core machine:
#: ~0.09 and ~0.07), and per camera frame (~0.22, scene setup included); the estimate is a lower bound
CASE_S, FLICKER_SCENE_S, CAMERA_FRAME_S = 0.09, 0.07, 0.22
#: lighting suites at most (indoor, outdoor, spatial; hdr with held-out maps)
LIGHTING_SUITES_MAX = 4


def duration_text(s: float) -> str:
    """``s`` seconds as a short text: 40 s, 12 min, 5.2 h, 3.1 days, 46 years."""
    for unit, size in (("years", 365 * 86400), ("days", 86400), ("h", 3600), ("min", 60)):
        if s >= 2 * size or unit == "min" and s >= 60:
            return f"{s / size:.3g} {unit}"
    return f"{s:.0f} s"


def check_eval_duration(args: argparse.Namespace) -> None:
    """Refuse a count whose part of the run alone would take over :data:`EVAL_MAX_S` (before any work)."""
    n = max(1, len([s for s in args.camera_suites.split(",") if s.strip()]))
    limit = EVAL_MAX_S * (RAY_MAX_FACTOR if getattr(args, "ray", None) is not None else 1)
    where = f"on one core ({RAY_MAX_FACTOR} x {duration_text(EVAL_MAX_S)} with --ray)" if limit > EVAL_MAX_S else "here"
    lighting = f"over the {LIGHTING_SUITES_MAX} lighting suites"
    camera = (  # scenes x frames: the flag further above its default is named
        (
            "--camera-scenes",
            args.camera_scenes,
            n * args.camera_frames * CAMERA_FRAME_S,
            f"scene in each of {n} suites",
        ),
        (
            "--camera-frames",
            args.camera_frames,
            n * args.camera_scenes * CAMERA_FRAME_S,
            f"frame in each of {args.camera_scenes} scenes x {n} suites",
        ),
    )
    if args.camera_frames / 30 > args.camera_scenes / 8:
        camera = camera[::-1]
    for flag, value, each, what in (
        ("--cases", args.cases, LIGHTING_SUITES_MAX * CASE_S, f"test case {lighting}"),
        ("--flicker-scenes", args.flicker_scenes, LIGHTING_SUITES_MAX * FLICKER_SCENE_S, f"scene {lighting}"),
        *camera,
    ):
        if each > 0 and value * each > limit:
            raise _usage(
                f"{flag} {value}: the run would take about {duration_text(value * each)} {where} (at least "
                f"{each:.3g} s a {what}), over the {duration_text(limit)} limit: expected at most "
                f"{int(limit // each)}; give a smaller count"
            )


def check_eval_arguments(args: argparse.Namespace) -> None:
    """Every count, seed, number and path of the flags, before a bundle is loaded or a suite run."""
    from illuminet.commands.train import check_count, check_hdr, check_out, check_out_given, check_seed

    for flag, value, least, note in (
        ("--cases", args.cases, 0, " (0 skips it)"),
        ("--flicker-scenes", args.flicker_scenes, 0, " (0 skips it)"),
        ("--camera-scenes", args.camera_scenes, 0, " (0 skips it)"),
        ("--vertices", args.vertices, 0, " (0 = all)"),
        ("--ablation-epochs", args.ablation_epochs, 1, ""),
        ("--camera-frames", args.camera_frames, 2, " (the flicker figure compares consecutive frames)"),
        ("--crosscheck-vertices", args.crosscheck_vertices, 1, ""),
        ("--crosscheck-spp", args.crosscheck_spp, 1, ""),
    ):
        check_count(flag, value, least, note=note)
    if args.crosscheck_bounces is not None:
        from illuminet.hw.synthetic.scene import MAX_BOUNCES

        check_count("--crosscheck-bounces", args.crosscheck_bounces, 0, MAX_BOUNCES, note=" (0 = direct light only)")
    check_eval_duration(args)
    if args.cases == 0 and args.camera_scenes == 0 and not args.crosscheck:
        # both suites skipped: the run wrote a report with a title only and exit code 0 (and never
        # looked at --bundle, so a missing bundle went unnoticed)
        raise _usage(
            "nothing to evaluate: --cases 0 and --camera-scenes 0 skip both the lighting and the camera suites; "
            "give --cases N or --camera-scenes N"
        )
    check_seed(args.seed)
    if args.object_albedo is not None and not 0.0 <= args.object_albedo < 1.0:  # NaN fails it too
        raise _usage(f"--object-albedo: expected a number in [0, 1), got {args.object_albedo!r} (0 = a black object)")
    check_hdr(args.hdr, held_out=True)
    check_out_given(args.out, "./eval/<bundle name>")
    if args.out:
        check_out("--out", Path(args.out), folder=True)


def run(args: argparse.Namespace, cfg) -> int:
    cluster.check_arguments(args)
    check_eval_arguments(args)
    if args.variant:  # a bad one was found only when the camera suites started (never with --camera-scenes 0)
        from illuminet.models.camera_eval import check_variants, parse_variant

        check_variants(cfg, [parse_variant(v) for v in args.variant])
    # every camera scene places its object once: one "anchor: placed on plane ..." line per scene
    # buried the progress (--log-level debug shows them); the level is restored after the run
    anchor_log = logging.getLogger("illuminet.runtime.stages.anchor")
    level = anchor_log.level
    if logging.getLogger().getEffectiveLevel() > logging.DEBUG:
        anchor_log.setLevel(logging.WARNING)
    try:
        return _run(args, cfg)
    finally:
        anchor_log.setLevel(level)


def _run(args: argparse.Namespace, cfg) -> int:
    from illuminet.commands.train import DEFAULT_HDR, check_out
    from illuminet.models.train import Progress
    from illuminet.runtime.assets.bundle import BundleError, load_bundle
    from illuminet.runtime.config import ConfigError

    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    if args.crosscheck:
        if args.ray is not None:
            raise _usage("--ray shards the lighting and camera suites; --crosscheck runs on this machine only")
        return _crosscheck(args, hdr)
    if args.ray is not None and args.ablation:
        raise _usage("--ablation retrains on this machine from the bundle's work folder: run it without --ray")
    from illuminet.models.eval import LABELS, Evaluator, finish, markdown, write_outputs

    spec = args.bundle or cfg.model.bundle
    suites = [s for s in args.camera_suites.split(",") if s]
    known = CAMERA_SUITES + CAMERA_SUITES_ON_REQUEST
    bad = [s for s in suites if s not in known]
    if not suites and args.camera_scenes > 0:  # ',' or '': the camera suites ran none, without a word
        raise _usage(
            f"--camera-suites {args.camera_suites!r}: expected a comma-separated list of "
            f"{', '.join(known)} (or --camera-scenes 0 to skip them)"
        )
    if bad:
        print(
            f"illuminet eval: unknown camera suite(s) {', '.join(bad)}; known: {', '.join(known)}",
            file=sys.stderr,
        )
        return 2
    cam = ev = None
    try:
        if args.camera_scenes > 0:
            from illuminet.models.camera_eval import CameraEval, parse_variant
            from illuminet.pipeline import build_stages

            cam = CameraEval(
                cfg,
                build_stages,
                spec,
                [parse_variant(v) for v in args.variant],
                hdr or None,
                args.vertices or None,
                args.object_albedo,
            )
            cam.check(suites, args.camera_frames)
        if args.ray is None:
            ev = Evaluator(spec, hdr or None) if args.cases > 0 else None
            bundle = ev.bundle if ev is not None else cam.bundle if cam is not None else None
        else:
            bundle = cam.bundle if cam is not None else load_bundle(spec)
    except (BundleError, ConfigError, ValueError) as e:
        print(f"illuminet eval: {e}", file=sys.stderr)
        return 2
    name = bundle.name if bundle is not None else str(spec)
    out = Path(args.out or Path("eval") / name)
    check_out("--out", out, folder=True)
    if args.hdr and ev is not None and not ev.hdr:  # every held-out map unreadable (each one logged above)
        raise _usage(f"--hdr {args.hdr}: none of its held-out .hdr maps (every 4th) could be read; give readable maps")
    t0 = time.time()
    examples: dict = {}
    if args.ray is not None:
        report, examples = _sharded(args, cfg, spec, bundle, suites, hdr, cam, out)
    else:
        if hdr and ev is not None:
            print(f"# real HDR lighting from {hdr} (held-out maps: {', '.join(ev.hdr_names) or 'none'})")
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
            examples = ev.examples
        else:
            report = {"bundle": name, "suites": {}}
        if cam is not None:
            report["camera"] = cam.run(
                suites, args.camera_scenes, args.camera_frames, args.seed, progress=Progress("camera", 1)
            )
    report["eval_wall_s"] = round(time.time() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    fig = None
    if examples and not args.no_figure:
        try:
            from illuminet.models.figure import figure

            suite = "outdoor" if "outdoor" in examples else next(iter(examples))
            ex = examples[suite]
            order = ["true", "constant", "ambient", "sh_rgbd", "oracle_sh", "ours_int8"]
            names = {"true": "Ground truth", **LABELS}
            panels = [(names[m], ex[m] / 3.14159265 * ex["k"]) for m in order if m in ex]
            fig = out / "eval.png"
            figure(
                fig,
                bundle.vertices,
                bundle.faces,
                panels,
                title=f"{bundle.name}: {suite} test case (front row, back row)",
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
    if args.update_bundle and report["suites"]:
        from illuminet.models.export import finalize_bundle

        (bundle.path / "eval.json").write_text(json.dumps(report, indent=2) + "\n")
        meta = dict(bundle.meta)
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
        finalize_bundle(bundle.path, meta)
        print(f"updated {bundle.path / 'bundle.json'}")
    return 0


# ------------------------------------------------------------------------------------ --ray: shards

#: per worker process: the evaluators of the last bundles (their visibility tables take seconds)
_CACHE: dict = {}


def _cached(key, make):
    if key not in _CACHE:
        if len(_CACHE) >= 4:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = make()
    return _CACHE[key]


def _evaluator(spec: str, hdr: str | None):
    from illuminet.models.eval import Evaluator

    return _cached(("light", spec, hdr), lambda: Evaluator(spec, hdr))


def _config_digest(cfg) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode()).hexdigest()


def tune_shard(spec: str, hdr: str | None, si: int, suite: str) -> dict[str, bytes]:
    """A Ray task: the SH baseline's validation MAE per regulariser on one lighting suite."""
    from illuminet.models.eval import SH_LAMBDAS

    scores = _evaluator(spec, hdr).tune_scores(si, suite)
    return {"scores.json": json.dumps([scores[lam] for lam in SH_LAMBDAS]).encode()}


def suite_shard(
    spec: str, hdr: str | None, si: int, suite: str, lam: float, cases: int, flicker: int, smoothing: float, seed: int
) -> dict[str, bytes]:
    """A Ray task: one lighting suite (its metrics, flicker and the figure's example case)."""
    from illuminet.models.datagen import data_bytes

    ev = _evaluator(spec, hdr)
    ev.sh_lambda = lam
    res, example = ev.run_suite(si, suite, cases, flicker, smoothing=smoothing, seed=seed)
    files = {"suite.json": json.dumps(res).encode()}
    if example is not None:
        files["example.npz"] = data_bytes({k: np.asarray(v) for k, v in example.items()})
    return files


def camera_shard(
    cfg,
    spec: str,
    variants: tuple,
    hdr: str | None,
    vertices: int | None,
    suite: str,
    i: int,
    seed: int,
    frames: int,
    object_albedo: float | None = None,
) -> dict[str, bytes]:
    """A Ray task: one scene of a camera suite through every variant (:meth:`CameraEval.scene_case`)."""

    def make():
        from illuminet.models.camera_eval import CameraEval, parse_variant
        from illuminet.pipeline import build_stages

        return CameraEval(cfg, build_stages, spec, [parse_variant(v) for v in variants], hdr, vertices, object_albedo)

    cam = _cached(("camera", _config_digest(cfg), spec, variants, hdr, vertices, object_albedo), make)
    return {"case.json": json.dumps(cam.scene_case(suite, i, seed, frames)).encode()}


def _sharded(args, cfg, spec, bundle, suites, hdr, cam, out: Path):
    """The lighting and camera suites as Ray shards in ``<out>/shards``; the same report as one machine.

    Shards: ``light-tune-<suite>`` (the SH regulariser's validation cases) and ``camera-<suite>-<i>``
    (one scene) first, then ``light-<suite>`` (one lighting suite's cases and flicker, with the
    regulariser picked from all tuning shards)."""
    from contextlib import nullcontext

    from illuminet.models import eval as E
    from illuminet.models.datagen import read_data

    store = cluster.ShardStore(out / "shards")
    store.check_job(
        {
            "job": "eval",
            "bundle": str(spec),
            "cases": args.cases,
            "flicker_scenes": args.flicker_scenes,
            "seed": args.seed,
            "hdr": hdr,
            "camera_scenes": args.camera_scenes,
            "camera_frames": args.camera_frames,
            "camera_suites": suites,
            "variants": list(args.variant),
            "vertices": args.vertices,
            "object_albedo": args.object_albedo,
            "config_sha256": _config_digest(cfg),
        }
    )
    hdr_dir = hdr or None
    light: list[str] = []
    hdr_names: list[str] = []
    if args.cases > 0:
        hdr_lights, hdr_names = E.held_out_lights(hdr_dir)
        if args.hdr and not hdr_lights:  # every held-out map unreadable (each one logged above)
            raise _usage(
                f"--hdr {args.hdr}: none of its held-out .hdr maps (every 4th) could be read; give readable maps"
            )
        light = E.suites(hdr_lights)
        if hdr:
            print(f"# real HDR lighting from {hdr} (held-out maps: {', '.join(hdr_names) or 'none'})")
    first = [cluster.Shard(f"light-tune-{s}", tune_shard, (str(spec), hdr_dir, si, s)) for si, s in enumerate(light)]
    if cam is not None:
        first += [
            cluster.Shard(
                f"camera-{s}-{i:04d}",
                camera_shard,
                (cfg, str(spec), tuple(args.variant), hdr_dir, args.vertices or None, s, i, args.seed)
                + (args.camera_frames, args.object_albedo),
            )
            for s in suites
            for i in range(args.camera_scenes)
        ]
    pending = [s.key for s in first if not store.is_done(s.key)] + [
        f"light-{s}" for s in light if not store.is_done(f"light-{s}")
    ]
    ray_kw = dict(address=args.ray, workers=args.ray_workers, retries=args.ray_retries, unit="shard")
    session = cluster.ray_session(args.ray, args.ray_workers) if pending else nullcontext()
    with session:
        summary = cluster.run_shards("eval (SH tuning, camera scenes)", first, store, **ray_kw)
        cluster.finish(summary, store)
        camera_wall = summary.wall_s
        per_suite = []
        for s in light:
            lists = json.loads(store.read(f"light-tune-{s}", "scores.json"))
            per_suite.append(dict(zip(E.SH_LAMBDAS, lists)))
        lam, sh_scores = E.pick_sh_lambda(per_suite) if light else (0.0, {})
        second = [
            cluster.Shard(
                f"light-{s}",
                suite_shard,
                (str(spec), hdr_dir, si, s, lam, args.cases, args.flicker_scenes, cfg.model.temporal_smoothing)
                + (args.seed,),
                items=args.cases,
            )
            for si, s in enumerate(light)
        ]
        if second:
            summary = cluster.run_shards("eval (lighting suites)", second, store, **ray_kw)
            cluster.finish(summary, store)
    examples: dict = {}
    if light:
        report = E.report_head(bundle, hdr_names, args.cases, args.seed, lam, sh_scores)
        for s in light:
            report["suites"][s] = json.loads(store.read(f"light-{s}", "suite.json"))
            if (store.path(f"light-{s}") / "example.npz").is_file():
                arrays, _ = read_data(store.read(f"light-{s}", "example.npz"))
                examples[s] = {k: (float(v) if k == "k" else v) for k, v in arrays.items()}
        report = E.finish(report)
    else:
        report = {"bundle": bundle.name, "suites": {}}
    if cam is not None:
        cases = {
            s: [json.loads(store.read(f"camera-{s}-{i:04d}", "case.json")) for i in range(args.camera_scenes)]
            for s in suites
        }
        report["camera"] = cam.assemble(cases, args.camera_scenes, args.camera_frames, args.seed, camera_wall)
    store.remove()
    return report, examples
