"""``illuminet train``: train an object bundle (needs the optional ``train`` extra: JAX, optax, onnx).

Example::

    illuminet train --object builtin:vase --seed 0 --preset small --out models/bundles/vase

Progress bars go to stderr, loss logs to ``<out>/work/log.jsonl``; checkpoints after every epoch in
``<out>/work`` make the same command resume after an interruption. The bundle files (mesh.npz,
transfer_fp32.onnx, transfer_int8.onnx, bundle.json) are written into ``--out`` at the end.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from pathlib import Path

log = logging.getLogger("illuminet.train")

#: where the shared reference HDR maps live relative to the project root (used when present)
DEFAULT_HDR = Path(__file__).resolve().parents[3] / "shared" / "data" / "hdri"


def register(sub) -> None:
    p = sub.add_parser(
        "train",
        help="train an object bundle (plane OI -> object shading)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--object",
        required=True,
        metavar="PATH|builtin:NAME",
        help="the virtual object: a GLB/OBJ/PLY file or builtin:vase / builtin:bowl",
    )
    p.add_argument("--out", metavar="DIR", help="bundle folder to write (default: ./bundles/<object name>)")
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace, cfg) -> int:
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
    from illuminet.models.export import write_bundle
    from illuminet.models.train import Trainer, make_config

    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    overrides = {
        k: getattr(args, k.replace("-", "_"))
        for k in (
            "n-train",
            "n-val",
            "n-proxy",
            "batch",
            "epochs-gae",
            "epochs-colour",
            "epochs-gan",
            "epochs-finetune",
            "unroll",
        )
    }
    tcfg = make_config(
        args.preset,
        object=args.object,
        seed=args.seed,
        hdr_dir=hdr,
        **{k.replace("-", "_"): v for k, v in overrides.items()},
    )
    name = args.object.split(":", 1)[1] if args.object.startswith("builtin:") else Path(args.object).stem
    out = Path(args.out or Path("bundles") / name)
    command = (
        "illuminet " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        if sys.argv and "illuminet" in sys.argv[0]
        else f"illuminet train --object {args.object} --seed {args.seed} --preset {args.preset}"
    )
    log.info(
        "training %s (preset %s, seed %d) into %s; HDR maps: %s",
        args.object,
        args.preset,
        args.seed,
        out,
        hdr or "none",
    )
    t0 = time.time()
    try:
        trainer = Trainer(tcfg, out, show_progress=not args.quiet)
        result = trainer.train()
    except (FileNotFoundError, ValueError) as e:
        print(f"illuminet train: {e}", file=sys.stderr)
        return 2
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
    print(f"wrote {path}")
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
