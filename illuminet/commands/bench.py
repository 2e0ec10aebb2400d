"""``illuminet bench [NAME ...]``: benchmarks that print their figures (medians, p99, ratios).

Each benchmark lives in a module ``illuminet.bench.<name>`` with ``run(args, cfg) -> dict`` that
prints its figures and returns them; ``--json PATH`` writes all results. Speed targets are checked
here, not in timed unit tests. Benchmarks say when they read ../shared/data.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
from pathlib import Path

#: benchmark name -> one-line description (module illuminet.bench.<name>)
BENCHES: dict[str, str] = {
    "replay": "replay throughput of a 640x400 RGB-D session through a null sink (raw and PNG colour)",
    "mjpeg": "loop throughput with two MJPEG clients attached vs none (ratio)",
    "synthetic": "synthetic camera: render time of a 640x400 RGB-D frame; visibility precomputation",
    "planes": "plane detection + tracking + plane illumination per 640x400 frame",
    "odometry": "RGB-D camera odometry per 640x400 frame; drift of the world-locked anchor over an orbit",
    "render": "render + composite at 1280x800 (moderngl)",
    "transfer": "the object's shading per frame: the int8 ONNX chain (plane -> shading) and PRT "
    "(light estimate -> shading)",
    "light": "the per-frame lighting estimate (one estimate, and per frame at [light] rate_hz)",
    "stereo": "host stereo depth (SGBM + WLS) per 640x400 pair",
    "demo": "the whole demo pipeline end to end, serial vs pipelined: per-stage timing, frame rate, "
    "capture-to-output latency, CPU per frame, peak memory",
    "live": "a live synthetic camera faster than the pipeline: dropped frames, latency per quarter of the run",
    "shadows": "light direction from real shadows: accuracy on synthetic box scenes, full search and local refine",
    "soak": "memory over a long run: the demo pipeline in real time with MJPEG and estimate clients attached; "
    "RSS slope in MB/min after warm-up (--minutes N, default 30; only when named)",
}
#: benchmarks that run only when named (``illuminet bench`` alone skips them: they take many minutes)
ON_REQUEST = ("soak",)


def register(sub) -> None:
    names = list(BENCHES)
    p = sub.add_parser(
        "bench",
        help="run benchmarks and print their figures",
        description="Benchmarks: " + "; ".join(f"{n}: {BENCHES[n]}" for n in names),
    )
    p.add_argument(
        "names",
        nargs="*",
        metavar="NAME",
        help=f"which to run (default: all but {', '.join(ON_REQUEST)}): {', '.join(names)}",
    )
    p.add_argument("--quick", action="store_true", help="fewer repetitions (smoke test)")
    p.add_argument("--json", metavar="PATH", help="also write all figures as JSON")
    p.add_argument("--size", metavar="WxH", help="demo, live: output (camera) size (demo: 1280x800, live: 640x400)")
    p.add_argument(
        "--pipeline",
        metavar="MODES",
        help="demo, live: loop modes to run, comma-separated, alternating (default demo: serial,threads; "
        "live: the [loop] pipeline setting)",
    )
    p.add_argument("--frames", type=int, metavar="N", help="demo: frames per run (default 150; --quick 30)")
    p.add_argument("--rounds", type=int, metavar="N", help="demo: runs per mode, alternating (default 2; --quick 1)")
    p.add_argument("--fps", metavar="LIST", help="live: camera frame rates, comma-separated (default 60,120)")
    p.add_argument("--seconds", type=float, metavar="S", help="live: seconds per camera rate (default 10; --quick 3)")
    p.add_argument(
        "--look",
        type=int,
        metavar="N",
        help="odometry: also a look-around (one full turn in place) on the evaluation's first N outdoor scenes "
        "(needs the held-out HDR maps, --hdr; default 0)",
    )
    p.add_argument(
        "--hdr",
        metavar="DIR",
        help="odometry --look: folder of the HDR maps (default: shared/data/hdri beside the checkout)",
    )
    p.add_argument("--minutes", type=float, metavar="N", help="soak: how long to stream (default 30; with --quick 0.5)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace, cfg) -> int:
    names = args.names or [n for n in BENCHES if n not in ON_REQUEST]
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(
            f"illuminet bench: unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(BENCHES)}",
            file=sys.stderr,
        )
        return 2
    for flag, expected in (
        ("--json", "a file path for the figures"),
        ("--size", "WxH such as 640x400"),
        ("--pipeline", "serial, threads or auto, comma-separated"),
        ("--fps", "comma-separated frame rates such as 60,120"),
        ("--hdr", "a folder of HDR maps"),
    ):
        value = getattr(args, flag[2:], None)
        if value is not None and not value.strip():  # was read as not given: the default, silently
            print(
                f"illuminet bench: {flag} {value!r} is empty; expected {expected}, or leave {flag} out for the default",
                file=sys.stderr,
            )
            return 2
    # every benchmark's flags, named or not, before the header: each checked its own only when it
    # started, after the benchmarks before it had run (or never, when it was not named)
    for n in BENCHES:
        check = getattr(importlib.import_module(f"illuminet.bench.{n}"), "check_args", None)
        if check is not None:
            check(args, cfg)
    if args.json is not None:
        # checked before the benchmarks run: a bad path found at the end lost their figures' JSON
        out = Path(args.json)
        parent = out.parent if str(out.parent) else Path(".")
        why = (
            "it is a folder"
            if out.is_dir()
            else f"folder {parent} does not exist"
            if not parent.is_dir()
            else f"folder {parent} is not writable"
            if not os.access(parent, os.W_OK)
            else ""
        )
        if why:
            print(
                f"illuminet bench: --json {args.json}: {why}; expected a file path in an existing folder",
                file=sys.stderr,
            )
            return 2
    print(f"# machine: {platform.machine()} {os.cpu_count()} cores, python {platform.python_version()}")
    results = {}
    for n in names:
        print(f"\n== {n}: {BENCHES[n]}")
        results[n] = importlib.import_module(f"illuminet.bench.{n}").run(args, cfg)
    if args.json is not None:
        try:
            with open(args.json, "w") as f:
                json.dump(results, f, indent=2)
        except OSError as e:  # checked at the start; the folder went away during the run
            print(f"illuminet bench: --json {args.json}: cannot write: {e.strerror or e}", file=sys.stderr)
            return 1
        print(f"\nwrote {args.json}")
    return 0
