"""``illuminet bundle``: make a bundle of any mesh in seconds, shaded physically (PRT), no training.

Example::

    illuminet bundle --object chair.glb --out bundles/chair --height 0.9
    illuminet bundle --object builtin:vase --out models/bundles/vase      # add PRT to a trained bundle

Writes ``mesh.npz`` (render mesh, lighting proxy, carry mapping), ``prt.npz`` (the proxy vertices'
SH transfer vectors with self-visibility, the primary light's visibility table, one interreflection
bounce) and ``bundle.json``. Such a bundle shades from the frame's light estimate (``[model] shading
= "prt"``, the default ``"auto"`` when an estimate is present); it has no learned model. When
``--out`` already holds a bundle of the same object (e.g. one made by ``illuminet train``), its files
are kept and only the PRT tables are (re)computed for its proxy vertices. See docs/models.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from illuminet.commands.train import check_count, check_number, check_out, check_seed
from illuminet.runtime.errors import EXIT_USAGE, JobError

#: a mesh file larger than this gets a line saying it is being read (a 2M-face binary PLY is ~38 MiB)
BIG_FILE_BYTES = 8 * 2**20
#: most interreflections summed (8 converge at albedo 0.8; each one is a pass over every hit)
MAX_BOUNCES = 100
#: most transfer rays or table directions per vertex (16x the default: its tables grow as V x N)
MAX_RAYS = 65536


def register(sub) -> None:
    p = sub.add_parser(
        "bundle",
        help="make a bundle of any mesh with precomputed radiance transfer (no training)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--object",
        required=True,
        metavar="PATH|builtin:NAME",
        help="a GLB/GLTF/OBJ/PLY/STL/OFF file or builtin:vase / builtin:bowl / builtin:sphere",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="bundle folder to write (or an existing bundle of the same object to add PRT to)",
    )
    p.add_argument(
        "--height",
        type=float,
        default=None,
        metavar="M",
        help="scale the object to this height in metres (files: default 0.25; built-ins keep their size)",
    )
    p.add_argument("--up", choices=("y", "z"), default="y", help="the file's up axis (default y)")
    # 1000, not the learned model's 400: carried to the render mesh, PRT shading of the vase differs from
    # PRT on every render vertex by 3.7 % (mean) with 1000 proxy vertices, 6.9 % with 400 (docs/models.md)
    p.add_argument("--n-proxy", type=int, default=1000, help="lighting proxy vertices of a new bundle (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the proxy selection (default 0)")
    p.add_argument(
        "--albedo",
        type=float,
        default=0.8,
        help="grey albedo of the object for its interreflection (default 0.8, the renderer's "
        "albedo of meshes without colour; 0 = no bounce)",
    )
    p.add_argument(
        "--bounces",
        type=int,
        default=8,
        help="interreflections of the object onto itself summed into the PRT (default 8: converged at "
        "albedo 0.8; 1 = the single bounce of bundles made before 2026-11-28)",
    )
    # defaults: illuminet.models.prt (not imported here: --help stays fast)
    p.add_argument(
        "--transfer-rays", type=int, default=4096, help="directions of the transfer integral per vertex (default 4096)"
    )
    p.add_argument(
        "--directions",
        type=int,
        default=4096,  # models.prt.DEFAULT_TABLE_DIRECTIONS (not imported here: the CLI starts light)
        help="directions of the primary light's visibility table (default 4096, ~3 degrees apart)",
    )
    p.add_argument(
        "--render-transfer",
        action="store_true",
        help="also compute the transfer of every render vertex: the object's self-occlusion at full "
        "resolution (camera eval, vase: 5-8 %% lower shading error; ~40 s more for 9000 vertices on 2 cores)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _command(args) -> str:
    if sys.argv and "illuminet" in sys.argv[0]:
        return "illuminet " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    return f"illuminet bundle --object {args.object} --out {args.out} --seed {args.seed}"


def _usage(msg: str) -> JobError:
    """A mistake in the flags: one line ``illuminet: ...`` from ``cli.main``, exit status 2."""
    return JobError(msg, exit_code=EXIT_USAGE)


def _same_object(existing: str, spec: str) -> bool:
    if existing.startswith("builtin:") or spec.startswith("builtin:"):
        return existing == spec
    return Path(existing).resolve() == Path(spec).resolve()


def check_bundle_object(out: Path, spec: str) -> None:
    """Refuse an existing bundle in ``out`` (its metadata file present) made of another object than
    ``spec`` (``bundle`` adds PRT to it, ``train`` resumes into it: either would mix two objects)."""
    from illuminet.runtime.assets.bundle import METADATA

    try:
        existing = json.loads((out / METADATA).read_text()).get("object", "")
    except (ValueError, AttributeError) as e:  # not JSON (or not an object)
        raise _usage(f"{out / METADATA}: not valid JSON ({e}); choose another --out") from None
    if not _same_object(str(existing), spec):
        raise _usage(f"--out {out} holds a bundle of {existing!r}, not {spec!r}: choose another --out")


def _os_error(e: OSError, out: Path) -> JobError:
    """An OSError as one line, naming ``--out`` when it is about the bundle folder."""
    name = Path(e.filename) if e.filename else None
    if name is not None and (name == out or out in name.parents):
        return _usage(f"--out {out}: cannot write {name} ({e.strerror or e}): choose another --out")
    return _usage(f"{e.filename or 'a file'}: {e.strerror or e}")


def run(args: argparse.Namespace, cfg) -> int:
    if args.height is not None:
        check_number("--height", args.height, 0.001, 1000.0, " of metres", " (the object's height; 0.25 = 25 cm)")
    if not 0.0 <= args.albedo < 1.0:  # NaN fails it too
        raise _usage(f"--albedo {args.albedo}: expected a grey albedo in [0, 1) (default 0.8; 0 = no bounce)")
    check_count("--bounces", args.bounces, 1, MAX_BOUNCES, note=" (8 converges at albedo 0.8)")
    check_count("--n-proxy", args.n_proxy, 8)
    check_count("--transfer-rays", args.transfer_rays, 64, MAX_RAYS, note=" (default 4096)")
    check_count("--directions", args.directions, 64, MAX_RAYS, note=" (default 4096)")
    check_seed(args.seed)
    check_out("--out", Path(args.out), folder=True, what="a bundle")
    try:
        import scipy  # noqa: F401  (the proxy's nearest neighbours)
    except ImportError:
        print(
            "illuminet bundle: needs the bundle extra (scipy is missing): pip install 'illuminet[bundle]'",
            file=sys.stderr,
        )
        return 2
    try:
        import embreex  # noqa: F401
    except ImportError:
        print(
            "illuminet bundle: embreex is not installed: rays are cast with trimesh's own intersector, far "
            "slower (pip install 'illuminet[bundle]')",
            file=sys.stderr,
        )
    from illuminet.models.prt import add_prt, new_bundle
    from illuminet.models.train import Progress
    from illuminet.runtime.assets.bundle import METADATA, BundleError
    from illuminet.runtime.assets.objects import _WANT as MESH_WANT
    from illuminet.runtime.assets.objects import ObjectLoadError, check_mesh_path

    bars: dict[str, Progress] = {}

    def progress(step: str, done: int, total: int) -> None:
        if not args.quiet:
            unit = "vertices" if step.endswith("bounce") else "rays"  # the bounce matrix goes by columns
            bars.setdefault(step, Progress(f"prt {step}", total))(done, total, unit)

    out = Path(args.out)
    t0 = time.perf_counter()
    try:
        if (out / METADATA).is_file():
            check_bundle_object(out, args.object)
            if args.height is not None or args.up != "y":
                raise _usage(
                    f"--out {out} is an existing bundle whose mesh is kept: --height/--up apply to new bundles only"
                )
            if not args.quiet:
                print(f"adding PRT to the bundle in {out} (its mesh, proxy and models are kept)", file=sys.stderr)
            path, res = add_prt(
                out,
                args.transfer_rays,
                args.directions,
                args.albedo,
                _command(args),
                args.seed,
                progress,
                render=args.render_transfer,
                bounces=args.bounces,
            )
        else:
            if out.exists() and (not out.is_dir() or any(out.iterdir())):
                raise _usage(
                    f"--out {out} exists and is not a bundle folder (no {METADATA}): choose a new or empty folder"
                )
            if not args.object.startswith("builtin:"):
                if not args.object.strip():  # Path("") is ".": "is a directory (it holds ...)"
                    raise _usage(f"--object {args.object!r}: empty; {MESH_WANT}")
                check_mesh_path(Path(args.object), f"--object {args.object}")
                size = Path(args.object).stat().st_size
                if size > BIG_FILE_BYTES and not args.quiet:  # reading it and choosing the proxy take a while
                    print(
                        f"reading {args.object} ({size / 2**20:.0f} MiB) and choosing {args.n_proxy} lighting proxy "
                        "vertices (several seconds per million faces)",
                        file=sys.stderr,
                    )
            path, res = new_bundle(
                args.object,
                out,
                args.height,
                args.n_proxy,
                args.seed,
                args.transfer_rays,
                args.directions,
                args.albedo,
                _command(args),
                progress,
                up=args.up,
                render=args.render_transfer,
                bounces=args.bounces,
            )
    except (ObjectLoadError, BundleError) as e:
        raise _usage(str(e)) from None
    except OSError as e:
        raise _os_error(e, out) from None
    total = sum((path.parent / f).stat().st_size for f in json.loads(path.read_text())["files"]) + path.stat().st_size
    t = res.timings_s
    rt = json.loads(path.read_text()).get("prt", {}).get("render_transfer")
    extra = f" + the transfer of {rt['vertices']} render vertices" if rt else ""
    print(
        f"wrote {path}: {len(res.transfer)} proxy vertices{extra}, PRT {sum(t.values()):.1f} s "
        f"({', '.join(f'{k[:-2]} {v:.2f} s' for k, v in t.items())}), bundle {total / 1024:.0f} KiB, "
        f"total {time.perf_counter() - t0:.1f} s"
    )
    return 0
