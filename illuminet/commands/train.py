"""``illuminet train``: train an object bundle (needs the optional ``train`` extra: JAX, optax, onnx).

Example::

    illuminet train --object builtin:vase --seed 0 --preset small --out models/bundles/vase
    illuminet train --objects catalogue/ --out bundles --ray              # one bundle per mesh, on Ray
    illuminet train --objects builtin:vase,builtin:bowl --out bundles     # one after the other

Progress bars go to stderr, loss logs to ``<out>/work/log.jsonl``; checkpoints after every epoch in
``<out>/work`` make the same command resume after an interruption. The bundle files (mesh.npz,
transfer_fp32.onnx, transfer_int8.onnx, bundle.json) are written into ``--out`` at the end.

``--objects DIR|LIST`` trains a catalogue: every mesh file of a folder, the lines of a text file
(``#`` comments; paths relative to the file) or a comma-separated list of specs, each into
``<out>/<name>`` (default ``--out``: ./bundles). Objects whose bundle is already there (same
training configuration) are skipped, so an interrupted catalogue resumes. With ``--ray`` each object
is one Ray task: it trains in a temporary folder on its worker and its bundle files (and
``work/log.jsonl``; not the checkpoints) come back to be written here, ``bundle.json`` last.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shlex
import sys
import time
from pathlib import Path

from illuminet import cluster
from illuminet.runtime.errors import EXIT_USAGE, JobError

log = logging.getLogger("illuminet.train")

#: mesh files a catalogue folder is scanned for (what runtime.assets.objects.load_object reads)
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")

#: where the shared reference HDR maps live relative to the project root (used when present)
DEFAULT_HDR = Path(__file__).resolve().parents[3] / "shared" / "data" / "hdri"


def hdr_help_default() -> str:
    """:data:`DEFAULT_HDR` for an argparse help text (the commands' help printed ``../shared/data/hdri``,
    relative to whatever folder the user was in)."""
    return str(DEFAULT_HDR).replace("%", "%%")


def register(sub) -> None:
    p = sub.add_parser(
        "train",
        help="train an object bundle (plane OI -> object shading)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--object",
        metavar="PATH|builtin:NAME",
        help="the virtual object: a GLB/OBJ/PLY file or builtin:vase / builtin:bowl",
    )
    what.add_argument(
        "--objects",
        metavar="DIR|LIST",
        help="a catalogue: a folder of mesh files, a text file of specs (one a line) or spec,spec,...; "
        "each object into <out>/<name>",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="bundle folder to write (default: ./bundles/<object name>); with --objects the catalogue "
        "folder (default ./bundles)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed for data and initialisation (default 0)")
    p.add_argument(
        "--preset",
        default="default",
        choices=("tiny", "small", "default", "gpu"),
        help="schedule: tiny (CI smoke test), small/default (CPU, <= 30 min), gpu (paper-like)",
    )
    p.add_argument(
        "--hdr",
        metavar="DIR",
        default=None,
        help=f"folder of .hdr environment maps mixed into the training lights "
        f"(default: {DEFAULT_HDR} when present; '' = none). Every 4th map is held out for eval.",
    )
    for name, typ, hlp in (
        ("n-train", int, "training samples"),
        ("n-val", int, "validation samples"),
        ("n-proxy", int, "lighting proxy vertices"),
        ("batch", int, "batch size"),
        ("epochs-gae", int, "epochs of the plane and object GAEs"),
        ("epochs-colour", int, "epochs of the colour GAE"),
        ("epochs-gan", int, "epochs of the transfer GAN"),
        ("epochs-finetune", int, "epochs of end-to-end fine-tuning (0 = paper pipeline)"),
        ("unroll", int, "unrolled discriminator steps"),
    ):
        p.add_argument(f"--{name}", type=typ, default=None, help=f"{hlp} (overrides the preset)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    cluster.add_arguments(p, unit="object of --objects")
    p.set_defaults(func=run)


_OVERRIDES = ("n-train", "n-val", "n-proxy", "batch", "epochs-gae", "epochs-colour", "epochs-gan", "epochs-finetune")
_OVERRIDES += ("unroll",)


def object_name(spec: str) -> str:
    return spec.split(":", 1)[1] if spec.startswith("builtin:") else Path(spec).stem


def _usage(msg: str) -> JobError:
    return JobError(msg, exit_code=EXIT_USAGE)


# ------------------------------------------------- flag checks shared by bundle, datagen, train, eval

#: the largest seed: numpy's SeedSequence takes any integer >= 0, JAX's PRNGKey a 64-bit one
SEED_MAX = 2**63 - 1


def check_count(flag: str, value: int, least: int, most: int | None = None, note: str = "") -> None:
    """Refuse an integer flag outside ``least .. most``: ``--flag VALUE: expected a count >= least``."""
    if value < least or (most is not None and value > most):
        want = f">= {least}" if most is None else f"from {least} to {most}"
        raise _usage(f"{flag} {value}: expected a count {want}{note}")


def check_seed(value: int, flag: str = "--seed") -> None:
    """Refuse a seed numpy or JAX cannot take (negative, or beyond 64 bits)."""
    if not 0 <= value <= SEED_MAX:
        raise _usage(f"{flag} {value}: expected a seed from 0 to 2**63-1 (e.g. {flag} 0)")


def check_number(flag: str, value: float, least: float, most: float, unit: str = "", note: str = "") -> None:
    """Refuse a float flag that is not finite or outside ``least .. most`` (NaN fails every comparison)."""
    if not (math.isfinite(value) and least <= value <= most):
        raise _usage(f"{flag} {value}: expected a finite number{unit} from {least:g} to {most:g}{note}")


#: the most bytes of samples one job may make: ``datagen`` assembles its file in memory (about twice this at
#: the end) and ``train`` keeps its training and validation sets in memory and in ``<out>/work``
DATA_MAX_BYTES = 16 * 2**30
#: float32 values of one sample besides the plane cells (4 each) and proxy vertices (12 each): scale, kind
_SAMPLE_EXTRA = 2


def sample_bytes(grid: int, n_proxy: int) -> int:
    """Bytes of one data sample: the pooled plane cells (4 floats), 12 floats per proxy vertex (OI and
    shading), the scale and the kind (see :mod:`illuminet.models.datagen`)."""
    from illuminet.runtime.stages.shading import POOL

    return 4 * ((grid // POOL) ** 2 * 4 + n_proxy * 12 + _SAMPLE_EXTRA)


def size_text(n: float) -> str:
    """``n`` bytes as a short text: 35 KB, 1.2 GB, 350 TB (powers of 1000)."""
    for unit in ("bytes", "KB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1000
    raise AssertionError


def check_data_size(flag: str, samples: int, grid: int, n_proxy: int, fix: str) -> None:
    """Refuse a sample count whose data would exceed :data:`DATA_MAX_BYTES` (before any is made)."""
    each = sample_bytes(grid, n_proxy)
    if samples * each > DATA_MAX_BYTES:
        raise _usage(
            f"{flag} {samples}: the samples would take about {size_text(samples * each)} ({size_text(each)} each at "
            f"grid {grid}, n-proxy {n_proxy}), over the {DATA_MAX_BYTES // 2**30} GiB limit: expected at most "
            f"{DATA_MAX_BYTES // each} samples; {fix}"
        )


def check_out_given(out: str | None, default: str) -> None:
    """``--out ''`` (or blanks): it read as no --out at all, so the job ran for minutes and wrote its
    folder at the default place without a word."""
    if out is not None and not out.strip():
        raise _usage(f"--out {out!r}: the path is empty; expected a folder: name one, or leave --out out for {default}")


def check_out(flag: str, out: Path, folder: bool, what: str = "files") -> None:
    """Refuse an output path that cannot be made: a file where a folder is needed (``folder``: ``out``
    itself), a file where one of its parent folders would be, or a folder that cannot be created or
    written (``/proc/x``, a read-only folder: the write failed after the work, a traceback or an
    ``[Errno 2]``). Checked before any work; the folders made to probe it are removed again."""
    if folder and out.exists() and not out.is_dir():
        raise _usage(f"{flag} {out}: is a file, expected a folder: choose a new or existing folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise _usage(f"{flag} {out}: {parent} is a file, not a folder: choose another {flag}")
            break
    made: list[Path] = []
    target = out if folder else out.parent
    try:
        for d in [*reversed(target.parents), target]:
            if not d.exists():
                d.mkdir()
                made.append(d)
        probe = target / f".illuminet-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise _usage(
            f"{flag} {out}: cannot write {what} there ({e.strerror or e}{f': {e.filename}' if e.filename else ''}); "
            f"expected a folder you can create and write: choose another {flag}"
        ) from None
    finally:
        for d in reversed(made):
            try:
                d.rmdir()
            except OSError:
                pass


def check_hdr(hdr: str | None, held_out: bool = False) -> None:
    """Refuse an explicit ``--hdr`` that is missing, a file or holds no maps (``None``: the default
    folder when present; ``''``: none). ``held_out``: eval uses only the held-out maps (every 4th)."""
    if not hdr:
        return
    from illuminet.models.datagen import hdr_maps

    folder = Path(hdr)
    want = "expected a folder of Radiance .hdr environment maps, or --hdr '' for none"
    if not folder.exists():
        raise _usage(f"--hdr {hdr}: no such folder; {want}")
    if not folder.is_dir():
        raise _usage(f"--hdr {hdr}: is a file, not a folder; {want} (e.g. --hdr {folder.parent})")
    maps = hdr_maps(folder)
    if not maps:
        other = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in (".hdr", ".exr"))
        seen = f" (only names ending in lower-case .hdr are read; found {', '.join(other[:3])})" if other else ""
        raise _usage(f"--hdr {hdr}: the folder holds no .hdr maps{seen}; {want}")
    if held_out and not hdr_maps(folder, "test"):
        raise _usage(
            f"--hdr {hdr}: holds {len(maps)} .hdr map(s), but eval uses only the held-out ones (every 4th in "
            "name order, the training never sees them): give a folder of at least 4 maps, or --hdr '' for none"
        )
    if not held_out:
        # from the headers alone (no pixels decoded): train only warned "training on synthetic lights
        # only" after its set-up when no training map could be read, although --hdr asked for maps
        from illuminet.runtime.groundtruth.lighting import hdr_header_size

        def readable(p: Path) -> bool:
            try:
                if hdr_header_size(p) is not None:
                    return True
                why = "not a Radiance file (no #? header)"
            except (OSError, ValueError) as e:
                why = str(e)
            log.warning("HDR map %s skipped: %s", p.name, why)
            return False

        if not any(readable(p) for p in hdr_maps(folder, "train")):
            raise _usage(
                f"--hdr {hdr}: none of its training maps (3 of every 4 .hdr files) has a readable Radiance "
                "header; give readable .hdr maps, or --hdr '' for none"
            )


def catalogue(arg: str) -> list[tuple[str, str]]:
    """``--objects DIR|LIST`` -> [(name, spec)]: the mesh files of a folder (sorted), the lines of a
    text file (paths relative to it) or a comma-separated list. File specs become absolute paths."""
    want = "expected a folder of mesh files, a text file of specs or spec,spec,... (e.g. builtin:vase,builtin:bowl)"
    if not arg.replace(",", "").strip():  # Path('') is the current folder: never scan it for a blank argument
        raise _usage(f"--objects {arg!r}: the list names no objects; {want}")
    src = Path(arg)
    if src.is_dir():
        specs = [str(p.resolve()) for p in sorted(src.iterdir()) if p.suffix.lower() in MESH_SUFFIXES]
        if not specs:
            raise _usage(f"--objects {arg}: the folder holds no mesh files ({', '.join(MESH_SUFFIXES)})")
    elif src.is_file() and src.suffix.lower() not in MESH_SUFFIXES:
        specs = []
        for line in src.read_text().splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            if not line.startswith("builtin:") and not Path(line).is_absolute():
                line = str((src.parent / line).resolve())
            specs.append(line)
        if not specs:
            raise _usage(f"--objects {arg}: the list names no objects")
    else:
        specs = [x.strip() for x in arg.split(",") if x.strip()]
        if not specs:
            raise _usage(f"--objects {arg!r}: the list names no objects; {want}")
        specs = [x if x.startswith("builtin:") else str(Path(x).resolve()) for x in specs]
    from illuminet.runtime.assets.objects import BUILTIN_OBJECTS

    for sp in specs:
        if sp.startswith("builtin:"):
            if sp.split(":", 1)[1] not in BUILTIN_OBJECTS:
                raise _usage(f"--objects: unknown built-in object {sp!r}; known: {', '.join(BUILTIN_OBJECTS)}")
        elif not Path(sp).is_file():
            raise _usage(f"--objects: {sp}: no such mesh file")
    names = [object_name(sp) for sp in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _usage(f"--objects: two objects would be written to the same folder ({', '.join(dup)}): rename one")
    return list(zip(names, specs))


def _command(args) -> str:
    if sys.argv and "illuminet" in sys.argv[0]:
        return "illuminet " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    what = f"--object {args.object}" if args.object else f"--objects {args.objects}"
    return f"illuminet train {what} --seed {args.seed} --preset {args.preset}"


def train_one(tcfg, out: Path, command: str, show_progress: bool = True) -> Path:
    """Train one object into the bundle folder ``out`` (resuming from ``out/work``); returns bundle.json."""
    from illuminet.models.export import write_bundle
    from illuminet.models.train import Trainer

    log.info(
        "training %s (preset %s, seed %d) into %s; HDR maps: %s",
        tcfg.object,
        tcfg.preset,
        tcfg.seed,
        out,
        tcfg.hdr_dir or "none",
    )
    t0 = time.time()
    trainer = Trainer(tcfg, out, show_progress=show_progress)
    result = trainer.train()
    train_s = time.time() - t0
    val = validation_figures(trainer, result)
    path = write_bundle(
        out, result, trainer, command=command, extra_meta={"training_wall_s": round(train_s, 1), "validation": val}
    )
    log.info(
        "bundle written: %s (training %.0f s); validation shading MAE (relative) %.4f",
        path,
        train_s,
        val["shading_mae_rel"],
    )
    return path


def train_shard(tcfg, name: str, command: str) -> dict[str, bytes]:
    """A Ray task: train one object in a temporary folder; its bundle files and ``work/log.jsonl``."""
    import tempfile

    from illuminet.runtime.assets.bundle import METADATA

    with tempfile.TemporaryDirectory(prefix=f"illuminet-train-{name}-") as tmp:
        out = Path(tmp) / name
        train_one(tcfg, out, command, show_progress=False)
        files = {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file() and p.name != METADATA}
        log_file = out / "work" / "log.jsonl"
        if log_file.is_file():
            files["work/log.jsonl"] = log_file.read_bytes()
        files[METADATA] = (out / METADATA).read_bytes()  # the completion marker: written last
    return files


def _trained(out: Path, tcfg) -> bool:
    """Whether ``out`` holds a finished bundle of ``tcfg``; a bundle of another configuration is an error."""
    import json

    from illuminet.runtime.assets.bundle import METADATA

    path = out / METADATA
    if not path.is_file():
        return False
    try:
        have = json.loads(path.read_text()).get("training", {}).get("config")
    except (OSError, ValueError, AttributeError):
        have = None
    want = json.loads(json.dumps(tcfg.to_dict()))
    if have != want:
        diff = sorted(k for k in want if not isinstance(have, dict) or have.get(k) != want[k])
        raise _usage(
            f"{out} holds a bundle trained with another configuration ({', '.join(diff) or 'not a trained bundle'}"
            "): delete it or choose another --out"
        )
    return True


#: (flag, least, what 0 means) of the preset overrides; None: the preset's value
_OVERRIDE_LEAST = {
    "n-train": (1, ""),
    "n-val": (1, ""),
    "n-proxy": (8, ""),
    "batch": (1, ""),
    "epochs-gae": (0, " (0 skips the stage)"),
    "epochs-colour": (0, " (0 skips the stage)"),
    "epochs-gan": (0, " (0 skips the stage)"),
    "epochs-finetune": (0, " (0 = the paper pipeline)"),
    "unroll": (0, " (0 = no unrolled discriminator step)"),
}


#: what train writes into a bundle folder (``illuminet bundle`` adds prt.npz, ``eval --update-bundle``
#: eval.json); ``work/`` holds its checkpoints, cached data (.npz) and log.jsonl
_OWN_FILES = frozenset({"bundle.json", "mesh.npz", "transfer_fp32.onnx", "transfer_int8.onnx", "prt.npz", "eval.json"})


def _foreign(folder: Path) -> list[str]:
    """The entries of ``folder`` that are not a bundle's files or train's own work (sorted)."""
    bad = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") and ".tmp-" in p.name:  # an interrupted atomic write
            continue
        if p.name == "work" and p.is_dir() and not p.is_symlink():
            own = (".npz", ".jsonl")
            bad += [f"work/{q.name}" for q in sorted(p.iterdir()) if not (q.is_file() and q.suffix in own)]
        elif p.name not in _OWN_FILES or not p.is_file():
            bad.append(p.name + ("/" if p.is_dir() else ""))
    return bad


def _listed(names: list[str]) -> str:
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def check_bundle_out(out: Path, spec: str | None) -> None:
    """Refuse a bundle folder that holds something else: an existing ``out`` must be empty or hold only a
    bundle (of ``spec``, when given) and train's own earlier output (``work/``). Before any work."""
    from illuminet.commands.bundle import check_bundle_object
    from illuminet.runtime.assets.bundle import METADATA

    if not out.is_dir():
        return
    bad = _foreign(out)
    if bad:
        raise _usage(
            f"--out {out} holds {_listed(bad)}: expected a new or empty folder, or one holding only a bundle and "
            "train's own earlier output: choose another --out"
        )
    if spec is not None and (out / METADATA).is_file():
        check_bundle_object(out, spec)  # the same rule as `illuminet bundle` adding PRT to it


def check_catalogue_out(root: Path, objects: list[tuple[str, str]]) -> None:
    """Refuse a catalogue folder that holds something else: an existing ``root`` may hold only bundle
    folders (those of ``objects``, ``<name>/``, checked as :func:`check_bundle_out`) and the failed
    objects' ``.errors/``."""
    if not root.is_dir():
        return
    bad = []
    for p in sorted(root.iterdir()):
        if p.name == cluster.ERRORS and p.is_dir():
            continue
        if not p.is_dir() or p.is_symlink() or _foreign(p):
            bad.append(p.name + ("/" if p.is_dir() else ""))
    if bad:
        raise _usage(
            f"--out {root} holds {_listed(bad)}: expected a new or empty folder, or one holding only the bundle "
            "folders (<out>/<name>) of train --objects: choose another --out"
        )
    for name, spec in objects:
        check_bundle_out(root / name, spec)


def check_train_arguments(args: argparse.Namespace) -> list[tuple[str, str]] | None:
    """Every flag's value and the output folder, before JAX is imported or any data is made; returns the
    catalogue of ``--objects`` (None with ``--object``)."""
    check_seed(args.seed)
    for flag in _OVERRIDES:
        value = getattr(args, flag.replace("-", "_"))
        if value is not None:
            least, note = _OVERRIDE_LEAST[flag]
            check_count(f"--{flag}", value, least, note=note)
    from illuminet.models.train import make_config

    overrides = {k.replace("-", "_"): getattr(args, k.replace("-", "_")) for k in _OVERRIDES}
    tcfg = make_config(args.preset, **{k: v for k, v in overrides.items() if v is not None})
    for flag, n in (("--n-train", tcfg.n_train), ("--n-val", tcfg.n_val)):
        fix = "give fewer (the paper-like gpu preset trains on 10000)"
        check_data_size(flag, n, tcfg.grid, tcfg.n_proxy, fix)
    check_hdr(args.hdr)
    check_out_given(args.out, "./bundles/<object>")
    if args.out:
        check_out("--out", Path(args.out), folder=True)
    if args.objects is not None:
        objects = catalogue(args.objects)
        check_catalogue_out(Path(args.out or "bundles"), objects)
        return objects
    if not args.object.strip():
        raise _usage(f"--object {args.object!r}: expected a mesh file or builtin:NAME (e.g. --object builtin:vase)")
    out = Path(args.out or Path("bundles") / object_name(args.object))
    check_out("--out", out, folder=True)
    check_bundle_out(out, args.object)
    return None


def run(args: argparse.Namespace, cfg) -> int:
    cluster.check_arguments(args)
    objects = check_train_arguments(args)
    if args.ray is None or args.ray == cluster.LOCAL:  # the training runs in this Python environment
        try:
            import jax  # noqa: F401
            import onnx  # noqa: F401
            import optax  # noqa: F401
        except ImportError as e:
            print(
                f"illuminet train: needs the training extra ({e.name} is missing): pip install 'illuminet[train]'",
                file=sys.stderr,
            )
            return 2
    from illuminet.models.train import make_config

    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    overrides = {k.replace("-", "_"): getattr(args, k.replace("-", "_")) for k in _OVERRIDES}

    def config(spec: str):
        return make_config(args.preset, object=spec, seed=args.seed, hdr_dir=hdr, **overrides)

    if objects is not None:
        return _run_catalogue(args, objects, config)
    if args.ray is not None:
        raise _usage("--ray trains a catalogue (--objects DIR|LIST), one Ray task per object; not one --object")
    out = Path(args.out or Path("bundles") / object_name(args.object))
    check_out("--out", out, folder=True)
    try:
        path = train_one(config(args.object), out, _command(args), show_progress=not args.quiet)
    except (FileNotFoundError, ValueError) as e:
        print(f"illuminet train: {e}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


def _run_catalogue(args, objects: list[tuple[str, str]], config) -> int:
    """Train every object of the catalogue into ``<out>/<name>``: one after the other, or on Ray."""
    root = Path(args.out or "bundles")
    check_out("--out", root, folder=True)
    command = _command(args)
    configs = {name: config(spec) for name, spec in objects}
    done = {name for name in configs if _trained(root / name, configs[name])}
    if done:
        print(f"catalogue: {len(done)} of {len(objects)} objects already trained in {root} (kept)", file=sys.stderr)
    if args.ray is not None:
        store = cluster.ShardStore(root, marker="bundle.json")
        shards = [cluster.Shard(name, train_shard, (configs[name], name, command)) for name, _ in objects]
        summary = cluster.run_shards(
            "train",
            shards,
            store,
            address=args.ray,
            workers=args.ray_workers,
            retries=args.ray_retries,
            unit="object",
            show_progress=not args.quiet,
        )
        cluster.finish(summary, store)
        print(f"wrote {len(objects)} bundles in {root}")
        return 0
    t0 = time.time()
    failed: dict[str, str] = {}
    trained = 0
    for name, spec in objects:
        if name in done:
            continue
        try:
            path = train_one(configs[name], root / name, command, show_progress=not args.quiet)
        except Exception as e:  # one broken mesh must not stop a catalogue of hundreds
            failed[name] = f"{type(e).__name__}: {e}"
            log.error("%s (%s): %s", name, spec, failed[name])
            continue
        trained += 1
        print(f"wrote {path}")
    wall = time.time() - t0
    print(
        f"train: {len(objects)} objects: {trained} trained"
        + (f" (+{len(done)} from an earlier run)" if done else "")
        + f", {len(failed)} failed, wall {wall:.1f} s"
    )
    if failed:
        worst = "; ".join(f"{k}: {v}" for k, v in list(failed.items())[:3])
        raise JobError(f"train: {len(failed)} of {len(objects)} objects failed ({worst}); run again to retry them")
    return 0


def validation_figures(trainer, result) -> dict:
    """Validation shading error of the JAX chain in normalised units (before export)."""
    import numpy as np

    from illuminet.models.train import predict_jax

    d = trainer.data["val"]
    _, sh = predict_jax(result, trainer.a_plane, trainer.a_obj, trainer.normals, d["plane"])
    err = np.abs(np.asarray(sh) - d["shading"])
    prior = trainer.data["train"]["shading"].mean(0)
    return {
        "shading_mae_rel": float(err.mean()),
        "constant_prior_mae_rel": float(np.abs(prior - d["shading"]).mean()),
        "n_val": int(len(d["plane"])),
    }
