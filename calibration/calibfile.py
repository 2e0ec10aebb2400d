"""The calibration file: a versioned, documented JSON format, and its in-memory form.

This module owns :class:`Calibration` (cameras, an optional stereo pair with its rectification, an
optional photometric response curve) and reading/writing it. ``v4l2://`` and ``replay://`` sources
load it with :func:`load_calibration`; every ``illuminet calibrate`` command writes it with
:func:`save_calibration`. The format is specified in ``docs/calibration.md``; in short::

    {
      "format": "illuminet-calibration",
      "version": 1,
      "cameras": {
        "left":  {"width": 640, "height": 400, "model": "pinhole",
                  "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [k1, k2, p1, p2, k3, ...],
                  "rms_px": 0.21},
        "right": {...}
      },
      "stereo": {"left": "left", "right": "right",
                 "R": [[...], [...], [...]], "T": [tx, ty, tz], "baseline_m": 0.075, "rms_px": 0.3,
                 "rectification": {"R1": ..., "R2": ..., "P1": ..., "P2": ..., "Q": ...}},
      "photometric": {"response_lut": "response.npy"},
      "color_camera": "left",
      "meta": {"created": "...", "tool": "illuminet calibrate stereo", ...}
    }

Conventions: OpenCV's. ``K`` in pixels for an image of ``width`` x ``height``; ``dist`` are OpenCV's
coefficients for ``model`` ``pinhole`` (4, 5, 8, 12 or 14 of them: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4
[tx ty]]]]) or the 4 of ``cv2.fisheye`` (k1..k4) for ``fisheye``. ``R``, ``T`` map a point from the
left camera's frame to the right camera's: ``X_right = R @ X_left + T``, metres (as
``cv2.stereoCalibrate`` returns them). The rectification is ``cv2.stereoRectify``'s output for the
stored image size; it is informative (``HostStereo`` recomputes it when absent).

Resolution: a calibration belongs to one image size. :meth:`Calibration.check_size` refuses another
size; :meth:`Calibration.scaled_to` rescales it when the aspect ratio is the same (binning or a
resize: focal lengths and principal point scale, distortion coefficients do not change because they
act on normalised coordinates), and refuses a different aspect ratio (a crop: the principal point
would be unknown).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from illuminet.runtime.frame import Intrinsics

FORMAT_NAME = "illuminet-calibration"
FORMAT_VERSION = 1
MODELS = ("pinhole", "fisheye")
#: numbers of distortion coefficients OpenCV accepts per model
DIST_COUNTS = {"pinhole": (0, 4, 5, 8, 12, 14), "fisheye": (0, 4)}


class CalibrationError(ValueError):
    """A calibration file, a calibration input or a calibration result is unusable; the message says
    which file/key/value and what was expected."""


@dataclass(frozen=True)
class CameraCalib:
    """Intrinsics of one camera.

    Parameters
    ----------
    width, height : int
        Image size the calibration refers to.
    K : (3, 3) ndarray
        Camera matrix in pixels.
    dist : (N,) ndarray
        Distortion coefficients for ``model`` (see module docstring).
    model : str
        ``"pinhole"`` (OpenCV's standard/rational model) or ``"fisheye"`` (``cv2.fisheye``).
    rms_px : float or None
        Reprojection RMS of the calibration that produced it, when known.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    model: str = "pinhole"
    rms_px: float | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return (self.width, self.height)

    def intrinsics(self) -> Intrinsics:
        """As the runtime's :class:`~illuminet.runtime.frame.Intrinsics` (distortion kept for pinhole;
        fisheye coefficients are not OpenCV pinhole ones, so they are left out: undistort first)."""
        dist = tuple(float(x) for x in self.dist) if self.model == "pinhole" else ()
        return Intrinsics(
            fx=float(self.K[0, 0]),
            fy=float(self.K[1, 1]),
            cx=float(self.K[0, 2]),
            cy=float(self.K[1, 2]),
            width=int(self.width),
            height=int(self.height),
            dist=dist,
        )

    def scaled_to(self, width: int, height: int) -> CameraCalib:
        """This camera at another resolution of the same aspect ratio (see module docstring)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        # pixel centres: x_new + 0.5 = (x_old + 0.5) * s
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return replace(self, width=int(width), height=int(height), K=K)

    def to_dict(self) -> dict:
        """The ``cameras.NAME`` object of the file format."""
        d = {
            "width": int(self.width),
            "height": int(self.height),
            "model": self.model,
            "K": np.asarray(self.K, float).tolist(),
            "dist": np.asarray(self.dist, float).ravel().tolist(),
        }
        if self.rms_px is not None:
            d["rms_px"] = float(self.rms_px)
        return d


@dataclass(frozen=True)
class StereoCalib:
    """A calibrated stereo pair: which cameras, and the pose of the right camera in the left one.

    Parameters
    ----------
    left, right : str
        Names of the two cameras in :attr:`Calibration.cameras`.
    R : (3, 3) ndarray
        Rotation with ``X_right = R @ X_left + T``.
    T : (3,) ndarray
        Translation in metres, same convention.
    rms_px : float or None
        Stereo reprojection RMS when known.
    rectification : dict of str to ndarray, optional
        ``R1, R2, P1, P2, Q`` from ``cv2.stereoRectify`` at the cameras' stored size.
    """

    left: str
    right: str
    R: np.ndarray
    T: np.ndarray
    rms_px: float | None = None
    rectification: Mapping[str, np.ndarray] | None = None

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, metres."""
        return float(np.linalg.norm(self.T))

    def to_dict(self) -> dict:
        """The ``stereo`` object of the file format."""
        d: dict[str, Any] = {
            "left": self.left,
            "right": self.right,
            "R": np.asarray(self.R, float).tolist(),
            "T": np.asarray(self.T, float).ravel().tolist(),
            "baseline_m": self.baseline_m,
        }
        if self.rms_px is not None:
            d["rms_px"] = float(self.rms_px)
        if self.rectification:
            d["rectification"] = {k: np.asarray(v, float).tolist() for k, v in self.rectification.items()}
        return d


@dataclass(frozen=True)
class Calibration:
    """Everything one calibration file holds.

    Parameters
    ----------
    cameras : dict of str to CameraCalib
        By name (``"left"``, ``"right"``, ``"color"``, or DepthAI socket names ``"CAM_B"`` ...).
    stereo : StereoCalib or None
        The stereo pair used for depth, when there is one.
    color_camera : str
        The camera whose image frames carry (depth is aligned to it). Defaults to the stereo left
        camera, else the only camera.
    response_lut : str or None
        Path of a (256, 3) camera response LUT (``.npy``) from ``illuminet calibrate photometric``,
        resolved against the calibration file's folder when relative.
    meta : dict
        Free-form provenance (tool, creation time, source files, notes).
    path : Path or None
        The file it was loaded from (for error messages and relative paths); not saved.
    """

    cameras: Mapping[str, CameraCalib]
    stereo: StereoCalib | None = None
    color_camera: str = ""
    response_lut: str | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        where = str(self.path) if self.path else "<calibration>"
        if not self.cameras:
            raise CalibrationError(f"{where}: a calibration needs at least one camera")
        if self.stereo is not None:
            for side in ("left", "right"):
                name = getattr(self.stereo, side)
                if name not in self.cameras:
                    raise CalibrationError(
                        f"{where}: stereo.{side} names camera {name!r}, but cameras are {sorted(self.cameras)}"
                    )
        if not self.color_camera:
            default = self.stereo.left if self.stereo else sorted(self.cameras)[0]
            object.__setattr__(self, "color_camera", default)
        elif self.color_camera not in self.cameras:
            raise CalibrationError(
                f"{where}: color_camera {self.color_camera!r} is not one of the cameras {sorted(self.cameras)}"
            )

    # -- access -------------------------------------------------------------------------------------
    @property
    def color(self) -> CameraCalib:
        """The colour camera's calibration."""
        return self.cameras[self.color_camera]

    def camera(self, name: str) -> CameraCalib:
        """One camera by name, with an error listing the known names."""
        try:
            return self.cameras[name]
        except KeyError:
            raise CalibrationError(f"{self._where()}: no camera {name!r}; cameras are {sorted(self.cameras)}") from None

    def require_stereo(self) -> StereoCalib:
        """The stereo pair, or a clear error when the file has none."""
        if self.stereo is None:
            raise CalibrationError(
                f"{self._where()}: has no 'stereo' section (cameras: {sorted(self.cameras)}); "
                "run `illuminet calibrate stereo` or import a DepthAI calibration with a stereo pair"
            )
        return self.stereo

    def _where(self) -> str:
        return str(self.path) if self.path else "<calibration>"

    # -- resolution ---------------------------------------------------------------------------------
    def check_size(self, width: int, height: int, camera: str | None = None) -> None:
        """Raise :class:`CalibrationError` unless ``camera`` (default: the colour camera) was calibrated
        at ``width`` x ``height``; the message says whether :meth:`scaled_to` can adapt it."""
        cam = self.camera(camera or self.color_camera)
        if (cam.width, cam.height) == (int(width), int(height)):
            return
        hint = (
            "same aspect ratio: use Calibration.scaled_to(w, h) to rescale it"
            if _same_aspect(cam.width, cam.height, width, height)
            else "different aspect ratio (a crop?): calibrate at this resolution"
        )
        raise CalibrationError(
            f"{self._where()}: camera {camera or self.color_camera!r} is calibrated for "
            f"{cam.width}x{cam.height}, but images are {int(width)}x{int(height)} ({hint})"
        )

    def scaled_to(self, width: int, height: int) -> Calibration:
        """This calibration for images of ``width`` x ``height``.

        Every camera of the colour camera's size is rescaled (the stereo pair shares one sensor
        mode). Refused with :class:`CalibrationError` when the aspect ratio differs.
        """
        base = self.color
        if (base.width, base.height) == (int(width), int(height)):
            return self
        if not _same_aspect(base.width, base.height, width, height):
            raise CalibrationError(
                f"{self._where()}: calibrated for {base.width}x{base.height} (aspect "
                f"{base.width / base.height:.4f}), cannot be used for {int(width)}x{int(height)} (aspect "
                f"{width / height:.4f}): a different aspect ratio means a crop with an unknown principal "
                "point; calibrate at this resolution"
            )
        cams = {
            n: (c.scaled_to(width, height) if (c.width, c.height) == (base.width, base.height) else c)
            for n, c in self.cameras.items()
        }
        stereo = self.stereo
        if stereo is not None:
            # the stored rectification is for the old size; HostStereo recomputes it
            stereo = replace(stereo, rectification=None)
        meta = dict(self.meta) | {"scaled_from": [base.width, base.height]}
        return replace(self, cameras=cams, stereo=stereo, meta=meta)

    # -- serialisation ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The whole file as a JSON-ready dict (format name and version first)."""
        d: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "cameras": {n: c.to_dict() for n, c in self.cameras.items()},
            "color_camera": self.color_camera,
        }
        if self.stereo is not None:
            d["stereo"] = self.stereo.to_dict()
        if self.response_lut:
            d["photometric"] = {"response_lut": str(self.response_lut)}
        d["meta"] = dict(self.meta)
        return d

    def response_lut_path(self) -> Path | None:
        """Absolute path of the response LUT (relative paths are relative to the calibration file)."""
        if not self.response_lut:
            return None
        p = Path(self.response_lut)
        if not p.is_absolute() and self.path is not None:
            p = self.path.parent / p
        return p


def _same_aspect(w0: int, h0: int, w1: int, h1: int) -> bool:
    # one pixel of rounding either way (e.g. 1920x1080 -> 640x360 exactly; 1280x720 -> 426x240 not)
    return abs(w0 * h1 - w1 * h0) <= max(w0, w1)


# ---------------------------------------------------------------------------------------------------
# parsing with errors that name the file and the key


def _matrix(where: str, key: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {key}: expected numbers of shape {shape}, got {value!r}") from None
    if a.shape != shape:
        raise CalibrationError(f"{where}: {key}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: {key}: contains non-finite values")
    return a


def _get(where: str, d: Mapping[str, Any], key: str, prefix: str, types: tuple[type, ...]) -> Any:
    if not isinstance(d, Mapping):
        raise CalibrationError(
            f"{where}: {prefix.rstrip('.') or 'top level'}: expected an object, got {type(d).__name__}"
        )
    if key not in d:
        raise CalibrationError(f"{where}: missing key {prefix + key!r}")
    v = d[key]
    if not isinstance(v, types) or isinstance(v, bool) and bool not in types:
        names = " or ".join(t.__name__ for t in types)
        raise CalibrationError(f"{where}: {prefix + key}: expected {names}, got {type(v).__name__} {v!r}")
    return v


def _opt_number(where: str, d: Mapping[str, Any], key: str, prefix: str, what: str) -> float | None:
    """``d[key]`` as a finite float >= 0, or None when absent or null."""
    v = d.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise CalibrationError(
            f"{where}: {prefix + key}: expected {what}, a number >= 0 (or null), got {type(v).__name__} {v!r}; "
            "correct it in the file, or remove the key"
        )
    return float(v)


#: the largest image side a calibration may describe (pixels)
MAX_SIDE = 100_000
#: the field of view (degrees, per axis) focal lengths must give for the image size (as relight's intrinsics)
FOV_RANGE_DEG = (0.5, 179.0)
#: the largest stereo translation (metres, per axis): a camera pair, not two buildings
MAX_BASELINE_M = 100.0


def camera_from_dict(d: Mapping[str, Any], where: str = "<calibration>", prefix: str = "") -> CameraCalib:
    """Parse one ``cameras.NAME`` object (see the module docstring)."""
    w = _get(where, d, "width", prefix, (int,))
    h = _get(where, d, "height", prefix, (int,))
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{where}: {prefix}width/height: expected positive sizes, got {w}x{h}")
    if w > MAX_SIDE or h > MAX_SIDE:
        raise CalibrationError(
            f"{where}: {prefix}width/height: {w}x{h} is over {MAX_SIDE} pixels a side, not a camera image; expected "
            "the image size in pixels the camera was calibrated at"
        )
    model = d.get("model", "pinhole")
    if model not in MODELS:
        raise CalibrationError(f"{where}: {prefix}model: expected one of {MODELS}, got {model!r}")
    K = _matrix(where, prefix + "K", _get(where, d, "K", prefix, (list,)), (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[2, :2] != 0) or K[1, 0] != 0:
        raise CalibrationError(
            f"{where}: {prefix}K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}"
        )
    if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
        raise CalibrationError(
            f"{where}: {prefix}K: principal point ({K[0, 2]:g}, {K[1, 2]:g}) is outside the {w}x{h} image; "
            "expected pixels inside it, usually near the centre"
        )
    lo, hi = FOV_RANGE_DEG
    for f, side, name in ((K[0, 0], w, "fx"), (K[1, 1], h, "fy")):
        fov = math.degrees(2.0 * math.atan(side / (2.0 * f)))
        if not lo <= fov <= hi:
            raise CalibrationError(
                f"{where}: {prefix}K: {name}={f:g} pixels for an image {side} px across is a {fov:.3g} deg field "
                f"of view; expected focal lengths in pixels giving {lo:g}-{hi:g} deg"
            )
    dist_raw = d.get("dist", [])
    if not isinstance(dist_raw, list):
        raise CalibrationError(f"{where}: {prefix}dist: expected a list of numbers, got {dist_raw!r}")
    dist = _matrix(where, prefix + "dist", dist_raw, (len(dist_raw),))
    if len(dist) not in DIST_COUNTS[model]:
        raise CalibrationError(
            f"{where}: {prefix}dist: model {model!r} takes {DIST_COUNTS[model]} coefficients, got {len(dist)}"
        )
    rms = _opt_number(where, d, "rms_px", prefix, "the reprojection RMS in pixels")
    return CameraCalib(width=w, height=h, K=K, dist=dist, model=model, rms_px=rms)


def calibration_from_dict(d: Mapping[str, Any], where: str = "<calibration>", path: Path | None = None) -> Calibration:
    """Parse a whole calibration object, checking the format name and version first."""
    if not isinstance(d, Mapping):
        raise CalibrationError(f"{where}: expected a JSON object at the top level, got {type(d).__name__}")
    fmt = d.get("format")
    if fmt != FORMAT_NAME:
        hint = ""
        if "cameraData" in d:
            hint = " (this looks like a DepthAI calibration: convert it with `illuminet calibrate import-depthai`)"
        raise CalibrationError(f"{where}: format: expected {FORMAT_NAME!r}, got {fmt!r}{hint}")
    ver = d.get("version")
    if ver != FORMAT_VERSION:
        raise CalibrationError(f"{where}: version: this build reads version {FORMAT_VERSION}, file has {ver!r}")
    cams_raw = _get(where, d, "cameras", "", (dict,))
    if not cams_raw:
        raise CalibrationError(f"{where}: cameras: expected at least one camera, got none")
    cams = {n: camera_from_dict(c, where, f"cameras.{n}.") for n, c in cams_raw.items()}
    stereo = None
    if d.get("stereo") is not None:
        s = d["stereo"]
        left = _get(where, s, "left", "stereo.", (str,))
        right = _get(where, s, "right", "stereo.", (str,))
        R = _matrix(where, "stereo.R", _get(where, s, "R", "stereo.", (list,)), (3, 3))
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise CalibrationError(
                f"{where}: stereo.R: expected a rotation matrix (orthonormal, det +1), got {R.tolist()}"
            )
        T = _matrix(where, "stereo.T", _get(where, s, "T", "stereo.", (list,)), (3,))
        if np.abs(T).max() > MAX_BASELINE_M:  # 1e300 overflowed |T| (a numpy warning) and loaded
            raise CalibrationError(
                f"{where}: stereo.T: {T.tolist()} is over {MAX_BASELINE_M:g} m; expected the translation between the "
                "two cameras in metres"
            )
        if np.linalg.norm(T) <= 0:
            raise CalibrationError(f"{where}: stereo.T: expected a non-zero translation in metres, got {T.tolist()}")
        baseline = _opt_number(where, s, "baseline_m", "stereo.", "the baseline |T| in metres")
        if baseline is not None and not math.isclose(baseline, float(np.linalg.norm(T)), rel_tol=1e-3):
            raise CalibrationError(
                f"{where}: stereo.baseline_m {s['baseline_m']} disagrees with |stereo.T| = {np.linalg.norm(T):.6g} m"
            )
        rect = None
        if s.get("rectification"):
            shapes = {"R1": (3, 3), "R2": (3, 3), "P1": (3, 4), "P2": (3, 4), "Q": (4, 4)}
            r = s["rectification"]
            rect = {
                k: _matrix(where, f"stereo.rectification.{k}", _get(where, r, k, "stereo.rectification.", (list,)), sh)
                for k, sh in shapes.items()
            }
        rms = _opt_number(where, s, "rms_px", "stereo.", "the stereo reprojection RMS in pixels")
        stereo = StereoCalib(left=left, right=right, R=R, T=T, rms_px=rms, rectification=rect)
    color = d.get("color_camera")
    if color is not None and not isinstance(color, str):
        raise CalibrationError(
            f"{where}: color_camera: expected the name of one of the cameras {sorted(cams)} as a string, got "
            f"{type(color).__name__} {color!r}; correct it in the file, or remove the key"
        )
    meta = d.get("meta")
    if meta is not None and not isinstance(meta, dict):
        text = repr(meta)
        raise CalibrationError(
            f'{where}: meta: expected an object of notes (such as {{"tool": ...}}) or null, got '
            f"{type(meta).__name__} {text if len(text) <= 60 else text[:57] + '...'}; correct it in the file, "
            "or remove the key"
        )
    lut = None
    if d.get("photometric"):
        lut = _get(where, d["photometric"], "response_lut", "photometric.", (str,))
    return Calibration(
        cameras=cams,
        stereo=stereo,
        color_camera=color or "",
        response_lut=lut,
        meta=dict(meta or {}),
        path=path,
    )


#: largest calibration file read (bytes; ours are a few kB, DepthAI's EEPROM exports tens of kB): a bound,
#: so that a device such as /dev/zero given as the file is refused instead of read until memory runs out
MAX_CALIBRATION_BYTES = 16 << 20


def read_calibration_text(path: Path) -> str:
    """The UTF-8 text of a calibration file, read up to :data:`MAX_CALIBRATION_BYTES`.

    Raises ``OSError`` / ``UnicodeDecodeError`` as ``Path.read_text`` does, :class:`CalibrationError` when
    the file is larger."""
    from illuminet.runtime.files import FileTooLarge, read_bounded

    try:
        raw = read_bounded(path, MAX_CALIBRATION_BYTES)
    except FileTooLarge as e:
        raise CalibrationError(
            f"{e}, not a calibration file (or an endless stream such as a device); expected a calibration JSON"
        ) from None
    return raw.decode("utf-8")


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file written by :func:`save_calibration` (or by hand, per the spec).

    Raises
    ------
    CalibrationError
        File missing, not JSON, wrong format/version, or a key missing or of the wrong shape; the
        message names the file and the key.
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO: reading it waited for ever
        raise CalibrationError(f"{path}: not a regular file (a folder, pipe or device); expected a calibration JSON")
    try:
        text = read_calibration_text(path)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file; expected a calibration JSON") from None
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read calibration file: {e}") from None
    try:
        data = json.loads(text)
    except ValueError as e:  # also an int of over 4300 digits, which json raises as a bare ValueError
        raise CalibrationError(f"{path}: not valid JSON: {e}") from None
    except RecursionError:
        raise CalibrationError(f"{path}: JSON nested too deeply to be a calibration file") from None
    return calibration_from_dict(data, str(path), path=path)


def save_calibration(calib: Calibration, path: str | Path) -> Path:
    """Write ``calib`` as JSON (format name + version first). Adds ``meta.created`` when missing.

    Returns the path written.
    """
    path = Path(path)
    d = calib.to_dict()
    d["meta"].setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d, indent=2) + "\n", encoding="utf-8")
    return path
