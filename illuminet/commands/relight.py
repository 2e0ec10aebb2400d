"""``illuminet relight``: one RGB-D image -> the placed object and its predicted radiance (npz).

Example::

    illuminet relight --color C.png --depth D.png --intrinsics 500,500,320,180 --anchor 320,250 \\
        --bundle builtin:vase --out result.npz

``--depth`` is a 16-bit PNG in millimetres (0 = invalid) or a float ``.npy`` in metres (a uint16
one: millimetres), aligned to the colour image: the same field of view, at the colour's or another
resolution (a stereo camera's 640x400 for 1280x800 colour is resized nearest-neighbour to the colour
size). ``--intrinsics`` is ``fx,fy,cx,cy`` or a JSON file with those keys (plus optional
width/height; scaled to the colour size when they differ; another aspect ratio is refused), or a
calibration file (``illuminet calibrate``'s or DepthAI's) as ``FILE[:CAMERA]``, by default its
colour camera. The npz format is documented in docs/models.md ("relight npz"); an ``--out`` name
without ``.npz`` gets it appended (numpy's rule), and the message names the file written.
``--exposure US,ISO``: exposure time in microseconds and ISO (e.g. 8000,400). ``--preview PNG`` also
writes the lit object composited into the colour image (the runtime's renderer: shading, cast
shadow, occlusion; needs OpenGL via EGL).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from pathlib import Path

import numpy as np

from illuminet.runtime.relight import MAX_IMAGE_PIXELS  # the largest image relight takes (the API's too)


def register(sub) -> None:
    p = sub.add_parser(
        "relight",
        help="predict a virtual object's radiance in one RGB-D image (npz)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--color", required=True, metavar="PNG", help="colour image (8-bit RGB, sRGB)")
    p.add_argument(
        "--depth",
        required=True,
        metavar="PNG|NPY",
        help="aligned depth: uint16 PNG in mm, or .npy float metres (0 = invalid)",
    )
    p.add_argument(
        "--intrinsics",
        required=True,
        metavar="FX,FY,CX,CY|JSON|CALIB[:CAMERA]",
        help="colour camera intrinsics: four numbers, a JSON file with fx, fy, cx, cy, or a calibration file "
        "(illuminet calibrate's or DepthAI's) and its camera (default: its colour camera)",
    )
    p.add_argument("--anchor", required=True, metavar="X,Y", help="pixel where the object stands")
    p.add_argument("--bundle", default=None, help="object bundle (default: [model] bundle)")
    p.add_argument(
        "--precision", choices=("int8", "fp32"), default=None, help="ONNX chain (default: [model] precision)"
    )
    p.add_argument(
        "--exposure",
        metavar="US,ISO",
        default=None,
        help="exposure time (microseconds) and ISO, when known (absolute units)",
    )
    p.add_argument("--out", required=True, metavar="NPZ", help="output file")
    p.add_argument("--preview", metavar="PNG", help="also write the lit object composited into the colour image")
    p.set_defaults(func=run)


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise ValueError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return vals


def _input_file(path: str, flag: str) -> Path:
    """``path`` as an existing regular file, or one line naming ``flag``."""
    p = Path(path)
    if not path.strip():  # Path("") is ".", the current folder: "--color : is a folder"
        raise ValueError(f"{flag} {path!r}: an empty file name; expected an image or array file")
    if "\x00" in path:
        raise ValueError(f"{flag} {path!r}: a NUL byte in the path; not a file name")
    if p.is_dir():
        raise ValueError(f"{flag} {path}: is a folder; expected a file")
    if p.exists() and not p.is_file():  # /dev/null, a pipe: "no such file" sent users looking for a typo
        raise ValueError(f"{flag} {path}: not a regular file (a device or pipe?); expected an image or array file")
    if not p.is_file():
        raise ValueError(f"{flag} {path}: no such file")
    return p


def _check_output(path: str, flag: str, image: bool = False) -> None:
    """Refuse an output path that cannot be written, before any work (issue 13: not after a minute);
    ``image``: also one whose extension names no image format OpenCV writes (.png, .jpg, ...)."""
    import os

    from illuminet.runtime.errors import OutputPathError

    p = Path(path)
    if not path.strip():  # Path("") is ".": "--out : is a folder"; an empty --preview was skipped, exit 0
        raise OutputPathError(f"{flag} {path!r}: an empty file name; expected a file path")
    if "\x00" in path:
        raise OutputPathError(f"{flag} {path!r}: a NUL byte in the path; not a file name")
    if p.is_dir():
        raise OutputPathError(f"{flag} {path}: is a folder; expected a file path")
    parent = p.parent
    if not parent.is_dir():
        raise OutputPathError(f"{flag} {path}: folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{flag} {path}: folder {parent} is not writable; choose another folder")
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputPathError(f"{flag} {path}: the file exists and is not writable; choose another name")
    if image:
        import cv2

        if not cv2.haveImageWriter(path):
            what = f"{p.suffix} is not an image format OpenCV can write" if p.suffix else "no extension"
            raise OutputPathError(f"{flag} {path}: {what}; expected an image file name such as preview.png (or .jpg)")


def _check_not_an_input(args: argparse.Namespace, out: str) -> None:
    """Refuse an output that is one of the inputs: ``--preview`` naming the ``--color`` image replaced the
    photograph with the composite."""
    from illuminet.runtime.errors import OutputPathError

    inputs = [("--color", args.color), ("--depth", args.depth), ("--intrinsics", args.intrinsics)]
    for oflag, opath in (("--out", out), ("--preview", args.preview)):
        for iflag, ipath in inputs:
            try:
                same = bool(opath) and os.path.isfile(ipath) and os.path.samefile(opath, ipath)
            except (OSError, ValueError):  # the output does not exist yet (or a NUL byte): no input
                same = False
            if same:
                raise OutputPathError(
                    f"{oflag} {opath}: is the {iflag} input file; writing it would replace the input: choose "
                    f"another {oflag} name"
                )


def _check_image_header(p: Path, flag: str) -> None:
    """Refuse an image (PNG, JPEG, BMP, TIFF, WebP, ...: ``image_size_of_file``) whose header claims more
    than :data:`MAX_IMAGE_PIXELS`, without decoding it."""
    from illuminet.runtime.imageheader import image_size_of_file

    size = image_size_of_file(p)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{flag} {p}: the image header says {size[0]}x{size[1]} pixels, over the limit of "
            f"{MAX_IMAGE_PIXELS / 1e6:g} Mpx; resize it first"
        )


def _check_jpeg_complete(p: Path, flag: str) -> None:
    """Refuse a JPEG cut short: libjpeg decodes it anyway, grey below the cut, with only a warning on
    stderr (a relight of the half-grey picture exited 0). A complete JPEG has its end-of-image marker
    after the last start-of-scan (the scan data cannot hold ``FF D9``: its ``FF`` bytes are stuffed)."""
    with open(p, "rb") as f:
        data = f.read()
    if not data.startswith(b"\xff\xd8"):
        return  # not a JPEG
    sos = data.rfind(b"\xff\xda")
    if sos < 0 or data.find(b"\xff\xd9", sos) < 0:
        raise ValueError(
            f"{flag} {p}: the JPEG is cut short ({len(data)} bytes, no end-of-image marker after its image data); "
            f"expected the complete file: copy or export it again"
        )


#: magic bytes of floating-point (linear HDR) image formats OpenCV reads and would squeeze into 8 bits
_FLOAT_IMAGES = ((b"#?", "a Radiance HDR"), (b"PF", "a PFM"), (b"Pf", "a PFM"), (b"\x76\x2f\x31\x01", "an OpenEXR"))


def _check_not_float_image(p: Path, flag: str) -> None:
    """Refuse a linear floating-point picture as the colour image: OpenCV reads it as 8 bits (a linear .hdr
    in [0, 1] came out 3x too dark and was taken as sRGB, a .pfm black) and relight lit the object from it."""
    with open(p, "rb") as f:
        head = f.read(4)
    for magic, kind in _FLOAT_IMAGES:
        if head.startswith(magic):
            raise ValueError(
                f"{flag} {p}: {kind} image (linear floating-point); expected an 8-bit sRGB colour image such as a "
                f"PNG or JPEG: tone-map or convert it first"
            )


def _load_npy(p: Path, flag: str) -> np.ndarray:
    with open(p, "rb") as f:
        magic = f.read(6)
    if magic != b"\x93NUMPY":
        kind = "an .npz archive" if magic.startswith(b"PK") else "not a .npy array"
        raise ValueError(f"{flag} {p}: {kind}; expected one float array in metres saved by numpy.save")
    try:  # the size from the header, before the array is read and copied to float32 (as a PNG's header)
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(f, max_header_size=1 << 16) if version in ((1, 0), (2, 0)) else ((), None, None)
    except (ValueError, OSError, EOFError, SyntaxError) as e:
        raise ValueError(f"{flag} {p}: cannot read the array header: {e}") from None
    if dtype is not None and (len(shape) != 2 or dtype.kind not in "fiu"):
        # refused from the header: a (200000000,) or (8000, 8000, 2) array was read whole first (1.6 GB, 15 s)
        raise ValueError(
            f"{flag} {p}: the array header says {dtype} with shape {shape}; expected a 2-D array of depths in metres"
        )
    if len(shape) == 2 and shape[0] * shape[1] > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{flag} {p}: the array header says {shape[1]}x{shape[0]} pixels, over the limit of "
            f"{MAX_IMAGE_PIXELS / 1e6:g} Mpx; resize it first"
        )
    try:
        a = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{flag} {p}: cannot read the array: {e}") from None
    if a.ndim != 2 or a.dtype.kind not in "fiu":
        raise ValueError(f"{flag} {p}: expected a 2-D array of depths in metres, got {a.dtype} with shape {a.shape}")
    if a.dtype == np.uint16:  # uint16 is millimetres, as in a 16-bit PNG and the Python API (was read as metres)
        from illuminet.runtime.frame import depth_from_mm

        return depth_from_mm(a)
    with np.errstate(over="ignore"):  # float64 beyond float32 (1e300 for invalid): inf, invalid, without numpy's lines
        return a.astype(np.float32)


def _imread(path: str, flags: int):
    """``cv2.imread`` without OpenCV's own log lines: a damaged TIFF or BMP printed three to five
    ``[ERROR:0@0.1] global loadsave.cpp ...`` lines around relight's one line saying what is wrong."""
    import cv2

    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        with _native_stderr_silenced():
            return cv2.imread(path, flags)
    finally:
        cv2.utils.logging.setLogLevel(level)


@contextlib.contextmanager
def _native_stderr_silenced():
    """File descriptor 2 pointed at /dev/null for the block: libpng and libjpeg write their own
    ``libpng error: Read Error`` line straight to it, past OpenCV's logging and Python's sys.stderr (a
    PNG cut short printed it above relight's one line). The relight command reads its images before
    any other thread runs; without a usable descriptor 2 nothing is changed."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _whole(v) -> int | float:
    """A JSON width/height as an int when it is whole (``640``, ``640.0``), else as given, for
    :func:`~illuminet.runtime.relight.check_intrinsics` to refuse (``640.5``, ``1e30`` stays a number)."""
    f = float(v)
    return int(f) if f.is_integer() and abs(f) <= 2**53 else f


def load_inputs(color_path: str, depth_path: str, intr: str):
    """Read colour, depth and intrinsics with errors that name the file and what was expected."""
    import cv2

    from illuminet.runtime.frame import Intrinsics, depth_from_mm
    from illuminet.runtime.relight import check_depth, check_intrinsics, fit_intrinsics

    cpath = _input_file(color_path, "--color")
    dpath = _input_file(depth_path, "--depth")
    _check_image_header(cpath, "--color")
    _check_jpeg_complete(cpath, "--color")
    _check_not_float_image(cpath, "--color")
    # the pixels as stored: the depth and the intrinsics describe the sensor's grid, and OpenCV otherwise turns
    # a JPEG by its EXIF orientation (a phone photo: colour 200x320 against depth 320x200, refused as not
    # aligned; a square one silently lit from a quarter-turned picture)
    bgr = _imread(color_path, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise ValueError(
            f"--color {color_path}: cannot read an image from it (empty, cut short, or not an image format "
            f"OpenCV reads); expected an 8-bit RGB PNG or JPEG"
        )
    color = np.ascontiguousarray(bgr[..., ::-1])
    with open(dpath, "rb") as f:
        is_npy = f.read(6) == b"\x93NUMPY"
    if is_npy or dpath.suffix.lower() in (".npy", ".npz"):  # X.NPY too; a numpy array under any name is one
        depth = _load_npy(dpath, "--depth")  # an .npz is named as one (was "cannot read an image from it")
    else:
        _check_image_header(dpath, "--depth")
        d = _imread(depth_path, cv2.IMREAD_UNCHANGED)
        if d is None:
            raise ValueError(
                f"--depth {depth_path}: cannot read an image from it (empty, cut short, or not an image format "
                f"OpenCV reads); expected a single-channel 16-bit PNG in millimetres or a .npy of float metres"
            )
        if d.dtype != np.uint16 or d.ndim != 2:
            raise ValueError(
                f"--depth {depth_path}: expected a single-channel 16-bit PNG in millimetres, "
                f"got {d.dtype} with shape {d.shape}"
            )
        depth = depth_from_mm(d)
    from illuminet.api import align_depth

    depth = align_depth(depth, color.shape, what=f"--depth {depth_path}")  # another resolution: nearest
    check_depth(depth, f"--depth {depth_path}")  # none valid, or millimetres in a .npy: named here
    h, w = depth.shape
    if not intr.strip():  # Path("") is ".": "--intrinsics : is a folder"
        raise ValueError(
            f"--intrinsics {intr!r}: empty; expected four numbers FX,FY,CX,CY or a JSON file with fx, fy, cx, cy"
        )
    if Path(intr).is_file():
        try:
            d = json.loads(Path(intr).read_text(encoding="utf-8"))
        except ValueError as e:  # not JSON, or not UTF-8 text
            raise ValueError(f"--intrinsics {intr}: not JSON ({e}); expected an object with fx, fy, cx, cy") from None
        except RecursionError:  # [[[[...]]]] thousands deep: a traceback from the JSON decoder
            raise ValueError(
                f"--intrinsics {intr}: JSON nested too deeply; expected an object with fx, fy, cx, cy"
            ) from None
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in d] if isinstance(d, dict) else None
        if missing and ("cameras" in d or "cameraData" in d):  # `illuminet calibrate`'s file, or DepthAI's
            return color, depth, _calibration_intrinsics(intr, w, h)
        if missing is None or missing:
            what = f"{type(d).__name__}" if missing is None else f"no {', '.join(missing)}"
            raise ValueError(f"--intrinsics {intr}: expected a JSON object with fx, fy, cx, cy in pixels, got {what}")
        flags = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if isinstance(d.get(k), bool)]
        if flags:
            raise ValueError(
                f"--intrinsics {intr}: {flags[0]} is {json.dumps(d[flags[0]])}; expected a number in pixels"
            )
        if ("width" in d) != ("height" in d):
            raise ValueError(
                f"--intrinsics {intr}: has {'width' if 'width' in d else 'height'} but not "
                f"{'height' if 'width' in d else 'width'}; give both (the image size it was calibrated at) or neither"
            )
        try:
            K = Intrinsics(
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                _whole(d.get("width", w)),
                _whole(d.get("height", h)),
            )
        except (TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"--intrinsics {intr}: fx, fy, cx, cy (and width, height) must be numbers: {e}") from None
        check_intrinsics(K, f"--intrinsics {intr}")
        K = fit_intrinsics(K, w, h, f"--intrinsics {intr}")  # proportional size: scaled; else refused
    elif ":" in intr and Path(intr.rpartition(":")[0]).is_file():  # FILE:CAMERA of a calibration
        K = _calibration_intrinsics(intr, w, h)
    else:
        if Path(intr).exists() or intr.lower().endswith(".json") or ("," not in intr and Path(intr).suffix):
            # a file name that is not there: "expected 4 comma-separated numbers" sent users looking in the wrong place
            what = (
                "is a folder"
                if Path(intr).is_dir()
                else "not a regular file (a pipe or device?)"
                if Path(intr).exists()
                else "no such file"
            )
            raise ValueError(
                f"--intrinsics {intr}: {what}; expected a JSON file with fx, fy, cx, cy or four numbers FX,FY,CX,CY"
            )
        fx, fy, cx, cy = _floats(intr, 4, "--intrinsics")
        K = Intrinsics(fx, fy, cx, cy, w, h)
        check_intrinsics(K, f"--intrinsics {intr}")
    return color, depth, K


def _calibration_intrinsics(intr: str, w: int, h: int):
    """``--intrinsics FILE[:CAMERA]`` naming a calibration (``illuminet calibrate``'s file or a DepthAI
    calibration JSON): that camera's (default: the file's colour camera) pinhole K, scaled to the colour
    image's size when proportional; its distortion is not applied (the image must be undistorted)."""
    from illuminet.calibration.calibfile import CalibrationError
    from illuminet.commands.calibrate import _camera_ref
    from illuminet.runtime.frame import Intrinsics
    from illuminet.runtime.relight import check_intrinsics, fit_intrinsics

    try:
        calib, name = _camera_ref(intr)
        cam = calib.camera(name)
    except CalibrationError as e:
        raise ValueError(f"--intrinsics {intr}: {e}") from None
    if cam.model != "pinhole":
        raise ValueError(
            f"--intrinsics {intr}: camera {name} is {cam.model}; expected a pinhole camera (undistort the image "
            "and give its FX,FY,CX,CY)"
        )
    K = cam.intrinsics()
    K = Intrinsics(K.fx, K.fy, K.cx, K.cy, K.width, K.height)
    check_intrinsics(K, f"--intrinsics {intr}")
    try:
        return fit_intrinsics(K, w, h, f"--intrinsics {intr}")
    except ValueError:  # its fix (width/height keys) is a JSON file's; here the camera is what to change
        path = calib.path or intr.rpartition(":")[0] or intr
        raise ValueError(
            f"--intrinsics {intr}: camera {name} is {K.width}x{K.height}, not the colour image's {w}x{h} or a "
            f"size of its aspect ratio; name the colour image's camera: {path}:CAMERA, one of "
            f"{', '.join(sorted(calib.cameras))}"
        ) from None


def run(args: argparse.Namespace, cfg) -> int:
    from illuminet.runtime.assets.bundle import BundleError
    from illuminet.runtime.frame import Exposure
    from illuminet.runtime.relight import check_anchor_px, check_exposure, npz_path, relight

    try:
        _check_output(args.out, "--out")
        out = npz_path(args.out)  # numpy writes r.out as r.out.npz: check and name that file
        if out != args.out:
            _check_output(out, "--out")
        if args.preview is not None:
            _check_output(args.preview, "--preview", image=True)
        _check_not_an_input(args, out)
        exp = None
        if args.exposure is not None:
            us, iso = _floats(args.exposure, 2, "--exposure")
            exp = Exposure(exposure_us=us, iso=iso)
            check_exposure(exp, f"--exposure {args.exposure}")
        ax, ay = _floats(args.anchor, 2, "--anchor")
        color, depth, K = load_inputs(args.color, args.depth, args.intrinsics)
        # named by its flag here (the runtime's check says "anchor pixel", which is no option of this command)
        ax, ay = check_anchor_px((ax, ay), color.shape[1], color.shape[0], f"--anchor {args.anchor}")
        res = relight(color, depth, K, (ax, ay), cfg, bundle=args.bundle, exposure=exp, precision=args.precision)
    except (ValueError, BundleError, OSError) as e:
        print(f"illuminet relight: {e}", file=sys.stderr)
        return 2
    try:
        res.save(out)
    except OSError as e:  # the folder vanished or filled up since it was checked
        print(f"illuminet relight: --out {args.out}: cannot write {out}: {e.strerror or e}", file=sys.stderr)
        return 1
    print(
        f"wrote {out}: {len(res.vertices)} vertices, method {res.method}, "
        f"{res.plane_observed:.0%} of the plane grid observed, mean radiance "
        f"{[round(float(x), 4) for x in res.radiance.mean(0)]}"  # (np.round of float32 printed 0.37700000405311584)
    )
    if args.precision and res.method != "model":
        # the flag picks the learned model's ONNX chain; a run shaded otherwise ignored it without a word
        print(
            f"illuminet relight: note: --precision {args.precision} applies to the learned model "
            f'([model] shading = "model"); this object was shaded by {res.method}, so it had no effect',
            file=sys.stderr,
        )
    if args.preview:
        import cv2

        from illuminet.api import render_preview
        from illuminet.runtime.render.gl import GLError

        try:
            pic = render_preview(color, depth, K, res, cfg)
        except GLError as e:
            print(
                f"illuminet relight: --preview needs OpenGL via EGL: {e} (illuminet doctor says what is "
                f"missing); the npz was written",
                file=sys.stderr,
            )
            return 1
        from illuminet.runtime.files import written_whole

        # a write that failed (a full disk) left a truncated picture in place of the previous one
        written, reason = True, ""
        try:
            with written_whole(args.preview) as tmp:
                if not cv2.imwrite(str(tmp), np.ascontiguousarray(pic[:, :, ::-1])):
                    raise OSError("the folder changed since it was checked, or the disk is full")
        except (cv2.error, OSError) as e:  # checked up front; an encoder that still refuses is one line too
            written, reason = False, " ".join(str(e).split())[-200:]
        if not written:
            print(
                f"illuminet relight: --preview {args.preview}: cannot write it ({reason}); the npz was written",
                file=sys.stderr,
            )
            return 1
        print(f"wrote {args.preview}: the lit object composited into the {pic.shape[1]}x{pic.shape[0]} image")
    return 0
