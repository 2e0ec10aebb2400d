"""``illuminet datagen``: training data of the learned transfer for one object, as one npz file.

Example::

    illuminet datagen --object builtin:vase --samples 3000 --seed 0 --out data/vase.npz
    illuminet datagen --object builtin:vase --samples 20000 --out data/vase.npz --ray            # local Ray
    illuminet datagen --object chair.glb --samples 100000 --out data/chair.npz --ray head:6379  # a cluster

Each sample is a lighting environment (indoor, outdoor, spatially varying lamps, real HDR maps when
``--hdr`` finds them) with the plane measurement the runtime would see and the object's true OI and
shading (:mod:`illuminet.models.datagen`). Sample ``i`` is drawn from its own random stream
(``SeedSequence([seed, i])``), so the file is the same, array for array, whether one process made it
or ``--ray`` split it into shards of ``--shard-size`` samples on many machines (any shard size).

The file: ``plane`` (n, P, 4), ``scale`` (n,), ``oi`` (n, V, 3, 3), ``shading`` (n, V, 3), ``kind``
(n,) and ``meta`` (JSON as uint8: object, seed, kinds, proxy size, HDR maps, the seeding);
:func:`illuminet.models.datagen.read_data` reads it. With ``--ray`` the shards are kept in
``<out>.shards/`` until the file is written: a run that was interrupted or had failed shards
redoes only the missing ones when run again.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from illuminet import cluster
from illuminet.runtime.errors import EXIT_USAGE, IllumiNetError, JobError

log = logging.getLogger("illuminet.datagen")

KINDS = ("indoor", "outdoor", "spatial")  # spelled here so that --help needs no numpy


def register(sub) -> None:
    from illuminet.commands.train import hdr_help_default

    p = sub.add_parser(
        "datagen",
        help="generate training data for an object (one process or sharded on Ray)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--object", required=True, metavar="PATH|builtin:NAME", help="a mesh file or builtin:NAME")
    p.add_argument("--out", required=True, metavar="FILE.npz", help="the data file to write")
    p.add_argument(
        "--samples",
        type=int,
        default=3000,
        help="number of samples (default 3000); the file is built in memory and may hold at most 16 GiB "
        "(about 23 KB a sample at the default --grid and --n-proxy: at most 737206 samples)",
    )
    p.add_argument("--seed", type=int, default=0, help="data set seed, >= 0 (default 0)")
    p.add_argument("--n-proxy", type=int, default=400, help="lighting proxy vertices (default 400, as train)")
    p.add_argument("--grid", type=int, default=32, help="plane grid cells per side (default 32)")
    p.add_argument("--extent", type=float, default=1.0, metavar="M", help="plane patch size in metres (default 1)")
    p.add_argument(
        "--kinds",
        default=",".join(KINDS),
        metavar="LIST",
        help=f"comma-separated synthetic lighting kinds (default {','.join(KINDS)})",
    )
    p.add_argument(
        "--hdr",
        metavar="DIR",
        default=None,
        help="folder of .hdr maps whose training split (3 of every 4) is mixed in; default: "
        f"{hdr_help_default()} (shared/data/hdri beside the checkout) when present, '' = none",
    )
    p.add_argument("--hdr-share", type=float, default=0.25, help="share of HDR-lit samples (default 0.25)")
    p.add_argument(
        "--shard-size",
        type=int,
        default=250,
        metavar="N",
        help="samples per Ray task (default 250); the data do not depend on it",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    cluster.add_arguments(p, unit="shard of --shard-size samples")
    p.set_defaults(func=run)


def _usage(msg: str) -> JobError:
    return JobError(msg, exit_code=EXIT_USAGE)


def shard_files(spec, start: int, stop: int) -> dict[str, bytes]:
    """A Ray task: samples ``start .. stop - 1`` as ``data.npz``."""
    from illuminet.models.datagen import data_bytes

    return {"data.npz": data_bytes(spec.generate(start, stop))}


def shard_ranges(n: int, size: int) -> list[tuple[int, int]]:
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def job(spec, n: int, shard_size: int) -> list[cluster.Shard]:
    """The shards of ``n`` samples (keys: the zero-padded sample range)."""
    return [
        cluster.Shard(f"samples-{a:09d}-{b:09d}", shard_files, (spec, a, b), items=b - a)
        for a, b in shard_ranges(n, shard_size)
    ]


def merge(store: cluster.ShardStore, shards: list[cluster.Shard]):
    from illuminet.models.datagen import concat_data, read_data

    return concat_data([read_data(store.read(s.key, "data.npz"))[0] for s in shards])


def write(out: Path, arrays, meta: dict) -> None:
    from illuminet.models.datagen import data_bytes
    from illuminet.runtime.files import written_whole

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with written_whole(out) as tmp:
            tmp.write_bytes(data_bytes(arrays, meta))
    except OSError as e:  # a disk that filled up since --out was checked: one line, and no half-written file
        raise JobError(
            f"--out {out}: cannot write the data file ({e.strerror or e}); free space or choose another --out"
        ) from None


def check_data_out(out: Path) -> str | None:
    """An existing ``--out`` file is replaced only when it is an earlier datagen file (its own arrays and
    meta); anything else there (a bundle's mesh.npz, a relight result, a file that is not an npz) is
    refused before any work. Returns what is replaced (for the last line), or None."""
    if not out.exists() and not out.is_symlink():
        return None
    import zipfile

    import numpy as np

    what = None
    try:
        with np.load(out, allow_pickle=False) as z:
            if {"meta", "plane", "shading"} <= set(z.files):
                meta = json.loads(bytes(z["meta"]).decode())
                if isinstance(meta, dict) and "samples" in meta:
                    what = f"{meta['samples']} samples of {meta.get('object', 'an object')}"
    except (OSError, ValueError, zipfile.BadZipFile, KeyError, UnicodeDecodeError, RecursionError):
        what = None
    if what is None:
        raise _usage(
            f"--out {out} exists and is not a datagen data file: expected a new file name, or an earlier "
            "datagen file to replace; choose another --out (or move that file away)"
        )
    return what


def run(args: argparse.Namespace, cfg) -> int:
    from illuminet.commands.train import (
        DEFAULT_HDR,
        check_count,
        check_data_size,
        check_hdr,
        check_number,
        check_out,
        check_seed,
    )
    from illuminet.runtime.config import SCHEMA

    cluster.check_arguments(args)
    kinds = tuple(k for k in args.kinds.split(",") if k)
    if not kinds or any(k not in KINDS for k in kinds):
        raise _usage(f"--kinds {args.kinds!r}: expected a comma-separated list of {', '.join(KINDS)}")
    check_count("--samples", args.samples, 1)
    check_seed(args.seed)
    check_count("--shard-size", args.shard_size, 1)
    check_count("--n-proxy", args.n_proxy, 8)
    # the plane patch the runtime measures ([plane_light] grid and extent_m): data outside it fit no bundle
    grid, extent = SCHEMA["plane_light"]["grid"], SCHEMA["plane_light"]["extent_m"]
    check_count("--grid", args.grid, 8, int(grid.max), note=" (cells per side, as [plane_light] grid allows)")
    check_number("--extent", args.extent, extent.min, extent.max, " of metres", " (as [plane_light] extent_m allows)")
    check_number("--hdr-share", args.hdr_share, 0.0, 1.0, note=" (the share of HDR-lit samples)")
    fix = "give fewer, or make several files with different --seed (each sample's stream depends on both)"
    check_data_size("--samples", args.samples, args.grid, args.n_proxy, fix)
    out = Path(args.out)
    if out.is_dir():
        raise _usage(f"--out {out} is a folder; give the data file's name (e.g. {out / 'data.npz'})")
    check_out("--out", out, folder=False)
    replaced = check_data_out(out)
    check_hdr(args.hdr)
    hdr = args.hdr if args.hdr is not None else (str(DEFAULT_HDR) if DEFAULT_HDR.is_dir() else "")
    from illuminet.models.datagen import data_spec

    try:
        spec = data_spec(
            args.object, args.seed, args.n_proxy, args.grid, args.extent, kinds, hdr or None, args.hdr_share
        )
    except IllumiNetError:  # an unknown or unreadable object: its own one line
        raise
    except ValueError as e:
        raise _usage(str(e)) from None
    if args.hdr and not spec.hdr_lights:  # every map unreadable (each one logged above)
        raise _usage(
            f"--hdr {args.hdr}: none of its training maps (3 of every 4 .hdr files) could be read (see the "
            "warnings above); give readable Radiance .hdr maps"
        )
    meta = dict(spec.meta(), samples=args.samples)
    if hdr and not spec.hdr_lights:
        log.warning("no HDR maps found in %s; synthetic lights only", hdr)
    t0 = time.perf_counter()
    if args.ray is None:
        from illuminet.models.train import Progress

        arrays = spec.generate(0, args.samples, progress=Progress("datagen", args.samples, not args.quiet))
        wall = time.perf_counter() - t0
        write(out, arrays, meta)
        print(
            f"wrote {out}: {args.samples} samples in {wall:.1f} s ({args.samples / max(wall, 1e-9):.3g} samples/s)"
            + (f"; it replaced the earlier data there ({replaced})" if replaced else "")
        )
        return 0
    store = cluster.ShardStore(Path(str(out) + ".shards"))
    store.check_job({"job": "datagen", "shard_size": args.shard_size, **meta})
    shards = job(spec, args.samples, args.shard_size)
    summary = cluster.run_shards(
        "datagen",
        shards,
        store,
        address=args.ray,
        workers=args.ray_workers,
        retries=args.ray_retries,
        unit="sample",
        show_progress=not args.quiet,
    )
    cluster.finish(summary, store)
    write(out, merge(store, shards), meta)
    store.remove()
    print(
        f"wrote {out}: {args.samples} samples from {len(shards)} shards"
        + (f"; it replaced the earlier data there ({replaced})" if replaced else ""),
        file=sys.stdout,
    )
    return 0
