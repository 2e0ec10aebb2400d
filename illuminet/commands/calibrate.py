"""``illuminet calibrate board|capture|intrinsics|stereo|photometric|import-depthai``.

Thin command-line wrappers around :mod:`illuminet.calibration`; every command that produces a
calibration writes the versioned JSON format of :mod:`illuminet.calibration.calibfile` (spec in
docs/calibration.md). Errors of the input (no board found, too few views, mixed image sizes, a
calibration for another resolution) are reported as one line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("illuminet.calibrate")


def _board_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("board (or --board FILE written by `calibrate board`)")
    g.add_argument("--board", metavar="JSON", help="board description file (board parameters below are ignored)")
    g.add_argument("--squares", default="11x8", metavar="XxY", help="chessboard squares across x down (default 11x8)")
    g.add_argument("--square-mm", type=float, default=20.0, help="square side, mm (default 20)")
    g.add_argument("--marker-mm", type=float, default=15.0, help="marker side, mm (default 15)")
    g.add_argument("--dictionary", default="DICT_4X4_1000", help="ArUco dictionary (default DICT_4X4_1000)")
    g.add_argument("--legacy", action="store_true", help="OpenCV < 4.6 marker layout (DepthAI boards, older prints)")
    g.add_argument(
        "--aspect",
        type=float,
        default=1.0,
        help="square height/width as shown (a board on a stretched monitor; default 1)",
    )


def _spec(args):
    from illuminet.calibration.board import BoardSpec
    from illuminet.calibration.calibfile import CalibrationError

    if getattr(args, "board", None):
        board = Path(args.board)
        want = "expected the board JSON that `illuminet calibrate board` writes next to its PDF/PNG"
        if board.is_dir():
            raise CalibrationError(f"{args.board}: cannot read board file: it is a folder; {want}")
        if not board.exists():
            raise CalibrationError(f"{args.board}: cannot read board file: no such file; {want}")
        if not board.is_file():  # a FIFO: reading it waited for ever
            raise CalibrationError(
                f"{args.board}: not a regular file (a pipe or device); expected a board file from "
                "`illuminet calibrate board`"
            )
        try:
            d = json.loads(board.read_text(encoding="utf-8"))
        except UnicodeDecodeError:  # the board's PDF or PNG
            raise CalibrationError(f"{args.board}: cannot read board file: not a text file; {want}") from None
        except (OSError, ValueError, RecursionError) as e:  # not JSON, nested too deeply
            raise CalibrationError(f"{args.board}: cannot read board file: {e}; {want}") from None
        # the file `calibrate board` writes is {"board": {...}}; the bare {...} is accepted too
        return BoardSpec.from_dict(d["board"] if isinstance(d, dict) and "board" in d else d, args.board)
    try:
        sx, sy = (int(v) for v in args.squares.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--squares: expected XxY such as 11x8, got {args.squares!r}") from None
    return BoardSpec(sx, sy, args.square_mm, args.marker_mm, args.dictionary, args.legacy, args.aspect)


def _camera_ref(ref: str):
    """``FILE[:CAMERA]`` -> (Calibration, camera name); DepthAI JSON files are imported on the fly."""
    from illuminet.calibration.calibfile import load_calibration
    from illuminet.calibration.depthai_import import import_depthai

    path, _, cam = ref.partition(":") if not Path(ref).exists() else (ref, "", "")
    try:
        if Path(path).exists() and not Path(path).is_file():
            raise OSError("not a regular file")  # a FIFO: reading it waited for ever; load_calibration says what
        text = json.loads(Path(path).read_text(encoding="utf-8"))
        is_dai = isinstance(text, dict) and "cameraData" in text
    except (OSError, ValueError, RecursionError):
        is_dai = False
    calib = import_depthai(path) if is_dai else load_calibration(path)
    return calib, cam or calib.color_camera


# ---------------------------------------------------------------------------------------------------


def cmd_board(args, cfg) -> int:
    """``calibrate board``: write the board PDF/PNG and its ``.json`` description."""
    from illuminet.calibration.board import PAGES_MM, board_image, write_pdf, write_png

    spec = _spec(args)
    out = Path(args.output)
    if out.suffix.lower() not in (".pdf", ".png"):
        print(f"illuminet calibrate board: output must end in .pdf or .png, got {out}", file=sys.stderr)
        return 2
    if args.page is not None and args.page not in (*PAGES_MM, "fit"):
        # checked for a PNG too: only write_pdf looked at it, so -o x.png --page A0x was accepted
        print(
            f"illuminet calibrate board: --page {args.page!r}: expected one of {', '.join(PAGES_MM)} or fit",
            file=sys.stderr,
        )
        return 2
    if args.page is not None and out.suffix.lower() == ".png":
        print(f"illuminet calibrate board: note: --page applies to a PDF only; {out} is a PNG, written without a page")
    side = out.with_suffix(".json")
    _check_board_sidecar(side, out)
    img = board_image(spec, dpi=args.dpi)
    if out.suffix.lower() == ".pdf":
        write_pdf(
            out, img, spec.size_mm, page=args.page or "a4", caption=spec.describe() + " - print at 100% (actual size)"
        )
    else:
        write_png(out, img, args.dpi)
    side.write_text(json.dumps({"board": spec.to_dict()}, indent=2) + "\n")
    print(
        f"wrote {out} ({spec.describe()}; {spec.size_mm[0]:g} x {spec.size_mm[1]:g} mm, "
        f"{img.shape[1]}x{img.shape[0]} px at {args.dpi:g} dpi) and {side} "
        f"(pass --board {side} to the other commands)"
    )
    print("print at 100 % (actual size), then measure one square: its size is what --square-mm must say")
    return 0


def _check_board_sidecar(side: Path, out: Path) -> None:
    """Refuse to replace ``side`` unless it is a board description an earlier ``calibrate board`` wrote
    (``-o calibration.png`` must not destroy a camera's calibration.json)."""
    from illuminet.calibration.board import BoardSpec
    from illuminet.calibration.calibfile import CalibrationError

    if not side.exists() or side.is_dir():  # a folder: writing it fails with the usual OSError line
        return
    try:
        d = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # not JSON, not UTF-8 text, nested too deeply
        d = None
    fields = set(BoardSpec.__dataclass_fields__)
    if isinstance(d, dict) and set(d) == {"board"} and isinstance(d["board"], dict) and set(d["board"]) <= fields:
        return
    raise CalibrationError(
        f"{side}: exists and is not a board description from `calibrate board` (-o {out.name} writes the "
        f"board's description there); choose another -o name, or move {side.name} away"
    )


def cmd_capture(args, cfg) -> int:
    """``calibrate capture``: open the source URL and keep diverse board views."""
    from illuminet.calibration.capture import capture_views, check_capture_options, check_output_folder
    from illuminet.hw import SourceError, open_source

    spec = _spec(args)
    check_capture_options(args.views, args.coverage, args.max_frames, args.min_novelty)
    check_output_folder(args.output)  # before the camera opens: nothing of an earlier capture is overwritten

    def show(n, v, sel):
        kept = len(sel.descriptors)
        if v.accepted or n % 30 == 0:
            print(f"frame {n}: {v.reason}; kept {kept}, coverage {sel.coverage:.0%}", flush=True)

    try:
        with open_source(args.source_url, cfg) as src:
            res = capture_views(
                src,
                args.output,
                spec,
                views=args.views,
                target_coverage=args.coverage,
                max_frames=args.max_frames,
                split=args.split,
                min_novelty=args.min_novelty,
                on_frame=show,
            )
    except (SourceError, ImportError) as e:
        print(f"illuminet calibrate capture: cannot open {args.source_url}: {e}", file=sys.stderr)
        return 2
    print(
        f"kept {len(res.files)} image(s) from {res.frames_read} frames into {args.output}; "
        f"coverage {res.coverage:.0%} (grid below, '#' = corners seen; also {Path(args.output) / 'coverage.png'})"
    )
    print(res.coverage_text)
    if res.coverage < args.coverage:
        print(
            f"coverage below {args.coverage:.0%}: capture more views near the uncovered ('.') image areas",
            file=sys.stderr,
        )
    return 0


def _write(calib, path: str) -> None:
    from illuminet.calibration.calibfile import save_calibration

    p = save_calibration(calib, path)
    print(f"wrote {p}")


def cmd_intrinsics(args, cfg) -> int:
    """``calibrate intrinsics``: one camera from images; optional comparison with a reference."""
    from illuminet.calibration.calibfile import Calibration
    from illuminet.calibration.charuco import detect_files
    from illuminet.calibration.intrinsics import calibrate_intrinsics, evaluate_intrinsics

    spec = _spec(args)
    dets = detect_files(args.images, spec)
    guess = None
    if args.guess:
        gc, name = _camera_ref(args.guess)
        guess = gc.camera(name)
    fix = [f for f in (args.fix or "").split(",") if f]
    res = calibrate_intrinsics(
        dets, spec, args.model, dist_model=args.dist, guess=guess, fix=fix, min_views=args.min_views
    )
    print(f"{len(dets)} image(s) with the board ({spec.describe()})")
    print(res.summary())
    for p, e in zip(res.paths, res.per_view_rms):
        print(f"  {Path(p).name}: {e:.3f} px")
    if args.compare:
        cc, name = _camera_ref(args.compare)
        ref = cc.camera(name)
        ev = evaluate_intrinsics(dets, spec, ref)
        ours = evaluate_intrinsics(dets, spec, res.camera)
        K0, K1 = ref.K, res.camera.K
        print(
            f"compare with {args.compare} ({name}): reprojection RMS on these images, poses re-solved: "
            f"reference {ev.rms_px:.3f} px, ours {ours.rms_px:.3f} px"
        )
        for lab, (r, c) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            print(f"  {lab}: reference {K0[r, c]:.2f}, ours {K1[r, c]:.2f} ({100 * (K1[r, c] / K0[r, c] - 1):+.2f} %)")
    if args.output:
        meta = {
            "tool": "illuminet calibrate intrinsics",
            "board": spec.to_dict(),
            "images": [str(p) for p in res.paths],
            "fixed": list(res.fixed),
        }
        _write(Calibration({args.name: res.camera}, meta=meta), args.output)
    return 0


def cmd_stereo(args, cfg) -> int:
    """``calibrate stereo``: both cameras (or given intrinsics) plus their pose and rectification."""
    from illuminet.calibration.calibfile import Calibration
    from illuminet.calibration.charuco import detect_files
    from illuminet.calibration.intrinsics import calibrate_intrinsics
    from illuminet.calibration.stereo import calibrate_stereo

    spec = _spec(args)
    dl = detect_files([args.left_dir], spec)
    dr = detect_files([args.right_dir], spec)
    if args.intrinsics:
        ic, _ = _camera_ref(args.intrinsics)
        st = ic.stereo
        lname = args.left_camera or (st.left if st else "left")
        rname = args.right_camera or (st.right if st else "right")
        left, right = ic.camera(lname), ic.camera(rname)
        print(f"intrinsics from {args.intrinsics} ({lname}, {rname})")
    else:
        rl = calibrate_intrinsics(dl, spec, args.model, dist_model=args.dist)
        rr = calibrate_intrinsics(dr, spec, args.model, dist_model=args.dist)
        print("left  " + rl.summary())
        print("right " + rr.summary())
        left, right = rl.camera, rr.camera
    res = calibrate_stereo(dl, dr, spec, left, right, min_pairs=args.min_pairs)
    print(res.summary())
    if res.stereo.rectification is not None:
        P1 = np.asarray(res.stereo.rectification["P1"])
        print(f"rectified: f = {P1[0, 0]:.2f} px, depth at 1 px disparity = {P1[0, 0] * res.stereo.baseline_m:.2f} m")
    meta = {"tool": "illuminet calibrate stereo", "board": spec.to_dict(), "pairs": [list(p) for p in res.pairs]}
    _write(Calibration({"left": left, "right": right}, stereo=res.stereo, meta=meta), args.output)
    return 0


def cmd_photometric(args, cfg) -> int:
    """``calibrate photometric``: Debevec response LUT from an exposure bracket."""
    from dataclasses import replace

    from illuminet.calibration.calibfile import load_calibration, save_calibration
    from illuminet.calibration.charuco import list_images, read_image
    from illuminet.calibration.photometric import (
        calibrate_response,
        check_response_options,
        exposure_times_from_names,
        save_response_lut,
    )

    check_response_options(args.samples, args.smoothness)
    files = [f for f in list_images([args.bracket_dir]) if f.name != "coverage.png"]
    times = exposure_times_from_names(files, Path(args.times) if args.times else None)
    imgs = [read_image(f) for f in files]
    lut = calibrate_response(imgs, times, samples=args.samples, smoothness=args.smoothness)
    out = save_response_lut(lut, args.output)
    print(f"{len(files)} exposures {min(times):g}..{max(times):g} s -> {out} ((256, 3) LUT, code -> linear, 255 -> 1)")
    for code in (32, 64, 128, 192):
        print(f"  code {code}: R {lut[code, 0]:.4f} G {lut[code, 1]:.4f} B {lut[code, 2]:.4f}")
    print(f'use it: [source] response_curve = "{out}" in config.toml')
    if args.calibration:
        cal = load_calibration(args.calibration)
        cal = replace(cal, response_lut=str(Path(out).resolve()))
        save_calibration(cal, args.calibration)
        print(f"added photometric.response_lut to {args.calibration}")
    return 0


def cmd_import_depthai(args, cfg) -> int:
    """``calibrate import-depthai``: DepthAI calibration JSON -> our file."""
    from illuminet.calibration.depthai_import import import_depthai

    cal = import_depthai(args.json, args.left_socket, args.right_socket)
    for n, c in cal.cameras.items():
        print(
            f"{n}: {c.model} {c.width}x{c.height} fx={c.K[0, 0]:.2f} fy={c.K[1, 1]:.2f} "
            f"cx={c.K[0, 2]:.2f} cy={c.K[1, 2]:.2f}"
        )
    if cal.stereo is not None:
        T = cal.stereo.T
        print(
            f"stereo {cal.stereo.left} -> {cal.stereo.right}: baseline {cal.stereo.baseline_m * 1000:.2f} mm, "
            f"T = [{T[0]:.5f}, {T[1]:.5f}, {T[2]:.5f}] m"
        )
    _write(cal, args.output)
    return 0


# ---------------------------------------------------------------------------------------------------


def register(sub) -> None:
    """Add ``calibrate`` and its subcommands to the ``illuminet`` parser."""
    p = sub.add_parser(
        "calibrate",
        help="camera calibration: board, capture, intrinsics, stereo, photometric, import-depthai",
        description="Camera calibration with a ChArUco board; see docs/calibration.md.",
    )
    from illuminet.cli import _global_options_after, _WithGlobalOptions

    # the global options (--config, --set, --log-level) after the subcommand too, as for every command
    csub = _WithGlobalOptions(p.add_subparsers(dest="calibrate_command", metavar="SUBCOMMAND"), _global_options_after())
    csub.required = True

    b = csub.add_parser("board", help="write a printable ChArUco board (PDF or PNG)")
    _board_args(b)
    b.add_argument("-o", "--output", default="board.pdf", help="output .pdf or .png (default board.pdf)")
    b.add_argument("--dpi", type=float, default=300.0, help="raster resolution, at most 10000 (default 300)")
    b.add_argument(
        "--page", default=None, help="PDF page: a4, a3, letter, tabloid or fit (default a4; a PNG has no page)"
    )
    b.set_defaults(func=_guard(cmd_board))

    c = csub.add_parser("capture", help="collect diverse board views from a source URL")
    c.add_argument("source_url", metavar="SOURCE_URL", help="v4l2:///dev/video0, oakd://, replay://DIR, ...")
    _board_args(c)
    c.add_argument(
        "-o", "--output", default="calib_views", help="new or empty folder for the images (default calib_views)"
    )
    c.add_argument("--views", type=int, default=25, help="views to keep (default 25)")
    c.add_argument("--coverage", type=float, default=0.8, help="image coverage to reach, 0..1 (default 0.8)")
    c.add_argument("--max-frames", type=int, default=3000, help="stop after this many frames (default 3000)")
    c.add_argument("--min-novelty", type=float, default=0.08, help="pose change needed to keep a view (default 0.08)")
    c.add_argument(
        "--split",
        choices=("none", "sbs"),
        default="none",
        help="sbs: frames are side-by-side stereo pairs, saved into left/ and right/",
    )
    c.set_defaults(func=_guard(cmd_capture))

    i = csub.add_parser("intrinsics", help="calibrate one camera from board images")
    i.add_argument("images", nargs="+", metavar="IMAGES", help="image files or folders")
    _board_args(i)
    i.add_argument("-o", "--output", help="calibration file to write")
    i.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole", help="lens model (default pinhole)")
    i.add_argument(
        "--dist",
        choices=("none", "standard", "rational"),
        default="standard",
        help="pinhole distortion: none, standard k1 k2 p1 p2 k3, rational +k4..k6 (default standard)",
    )
    i.add_argument("--guess", metavar="FILE[:CAMERA]", help="starting intrinsics (our file or a DepthAI JSON)")
    i.add_argument(
        "--fix",
        metavar="LIST",
        help="comma list held at the guess: focal, aspect, principal_point, distortion, tangential",
    )
    i.add_argument("--min-views", type=int, help="fewest views accepted (default 4, or 1 with --fix)")
    i.add_argument(
        "--compare", metavar="FILE[:CAMERA]", help="also report a reference calibration's fit on these images"
    )
    i.add_argument("--name", default="left", help="camera name in the file (default left)")
    i.set_defaults(func=_guard(cmd_intrinsics))

    s = csub.add_parser("stereo", help="calibrate a stereo pair from left/right image folders")
    s.add_argument("left_dir", metavar="LEFT_DIR")
    s.add_argument("right_dir", metavar="RIGHT_DIR")
    _board_args(s)
    s.add_argument("-o", "--output", default="stereo_calibration.json", help="calibration file to write")
    s.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole")
    s.add_argument("--dist", choices=("none", "standard", "rational"), default="standard")
    s.add_argument("--intrinsics", metavar="FILE", help="use these intrinsics instead of calibrating them here")
    s.add_argument("--left-camera", help="camera name in --intrinsics for the left camera")
    s.add_argument("--right-camera", help="camera name in --intrinsics for the right camera")
    s.add_argument("--min-pairs", type=int, default=3, help="fewest usable pairs (default 3)")
    s.set_defaults(func=_guard(cmd_stereo))

    ph = csub.add_parser("photometric", help="camera response curve from an exposure bracket (Debevec-Malik)")
    ph.add_argument("bracket_dir", metavar="BRACKET_DIR", help="images of a static scene at several exposure times")
    ph.add_argument("-o", "--output", default="response.npy", help="LUT file (.npy, default response.npy)")
    ph.add_argument(
        "--times", metavar="JSON", help='{"file name": seconds}; default: exposures.json in the folder, else file names'
    )
    ph.add_argument("--samples", type=int, default=120, help="pixel samples for Debevec, 1..1000 (default 120)")
    ph.add_argument(
        "--smoothness", type=float, default=10.0, help="Debevec lambda, above 0 and at most 1000 (default 10)"
    )
    ph.add_argument("--calibration", metavar="FILE", help="also record the LUT in this calibration file")
    ph.set_defaults(func=_guard(cmd_photometric))

    d = csub.add_parser("import-depthai", help="convert a DepthAI calibration JSON (EEPROM export) to our format")
    d.add_argument("json", metavar="JSON")
    d.add_argument("-o", "--output", default="calibration.json", help="calibration file to write")
    d.add_argument("--left-socket", type=int, help="stereo left socket (default: from stereoRectificationData)")
    d.add_argument("--right-socket", type=int, help="stereo right socket")
    d.set_defaults(func=_guard(cmd_import_depthai))


def _guard(fn):
    """Input errors become one clear line and exit code 2 (no traceback for a user mistake)."""

    def run(args, cfg) -> int:
        from illuminet.calibration.calibfile import CalibrationError

        try:
            return fn(args, cfg)
        except CalibrationError as e:
            print(f"illuminet calibrate {args.calibrate_command}: {e}", file=sys.stderr)
            return 2
        except OSError as e:  # an output file or folder that cannot be made (the inputs are checked above)
            where = e.filename if e.filename is not None else "a file"
            print(
                f"illuminet calibrate {args.calibrate_command}: {where}: {e.strerror or e}; choose a path in a "
                "folder you can write to",
                file=sys.stderr,
            )
            return 1

    return run
