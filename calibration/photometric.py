"""Photometric calibration: from camera pixels to measured light.

This module owns

* exposure and white-balance normalisation from the metadata a frame carries
  (:class:`~illuminet.runtime.frame.Exposure`): :func:`exposure_factor`, :func:`undo_white_balance`,
  :func:`normalize_exposure`. Linearisation itself (sRGB curve or a measured response LUT) is
  :func:`illuminet.runtime.physics.linearize`; the LUT file is read by
  :func:`illuminet.runtime.physics.load_response_lut` so the runtime needs nothing from here.
* the camera response curve from an exposure bracket (Debevec & Malik 1997,
  ``cv2.createCalibrateDebevec``): :func:`calibrate_response`, :func:`exposure_times_from_names`,
  :func:`save_response_lut`. The LUT has shape (256, 3) (code value x R, G, B), linear, made
  non-decreasing, and scaled so that code 255 maps to 1 in every channel (as the sRGB curve does):
  the per-channel scale of a Debevec curve is arbitrary, and this choice keeps a white-balanced
  camera white.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from illuminet.calibration.calibfile import CalibrationError
from illuminet.runtime.frame import Exposure

#: exposure the normalised values refer to: 10 ms at ISO 100 (a factor of 1 for that exposure)
REFERENCE = Exposure(exposure_us=10_000.0, iso=100.0)


def exposure_factor(exposure: Exposure, reference: Exposure = REFERENCE) -> float | None:
    """Multiplier taking linear pixel values of ``exposure`` to those of ``reference``; ``None`` when
    the frame's exposure time or ISO is unknown (callers then normalise by scene statistics)."""
    if not exposure.known or not reference.known:
        return None
    if exposure.exposure_us <= 0 or exposure.iso <= 0:
        raise ValueError(f"exposure must be positive, got {exposure.exposure_us} us at ISO {exposure.iso}")
    return float(reference.scale / exposure.scale)


def undo_white_balance(linear: np.ndarray, wb_gains: Sequence[float] | None) -> np.ndarray:
    """Divide out the camera's white-balance gains (normalised to green = 1) from linear RGB.

    The camera's AWB makes a warm lamp look white; lighting estimation wants the light's real colour,
    so the gains the camera applied are removed. ``None`` returns the input unchanged.
    """
    if wb_gains is None:
        return linear
    g = np.asarray(wb_gains, np.float32).ravel()
    if g.shape != (3,) or np.any(g <= 0) or not np.all(np.isfinite(g)):
        raise ValueError(f"wb_gains must be 3 positive numbers (R, G, B), got {wb_gains!r}")
    g = g / g[1]
    return (np.asarray(linear, np.float32) / g).astype(np.float32)


def normalize_exposure(
    linear: np.ndarray, exposure: Exposure, reference: Exposure = REFERENCE, undo_wb: bool = True
) -> tuple[np.ndarray, bool]:
    """Linear RGB of a frame -> linear RGB as if taken at ``reference`` exposure (and without AWB).

    Returns
    -------
    (array, known) : (ndarray float32, bool)
        ``known`` is False when the exposure metadata is missing; the array is then only
        white-balance-corrected (when gains are known) and not exposure-normalised.
    """
    out = undo_white_balance(linear, exposure.wb_gains) if undo_wb else np.asarray(linear, np.float32)
    f = exposure_factor(exposure, reference)
    if f is None:
        return out.astype(np.float32, copy=False), False
    return (out * np.float32(f)).astype(np.float32), True


# ---------------------------------------------------------------------------------------------------
# response curve from an exposure bracket

_UNIT = {"us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}
_RE_UNIT = re.compile(r"(\d+(?:\.\d+)?)\s*(us|µs|ms|s)(?![a-z])", re.IGNORECASE)
_RE_FRACTION = re.compile(r"(?<![\d.])1[-_/](\d+(?:\.\d+)?)(?:s)?(?![\d.])")


def exposure_time_from_name(name: str) -> float | None:
    """Exposure seconds from a file name: ``..._10ms.png``, ``e2500us.jpg``, ``0.004s``, ``1-250.png``
    (= 1/250 s). ``None`` when the name says nothing recognisable."""
    stem = Path(name).stem
    m = _RE_UNIT.search(stem)
    if m:
        return float(m.group(1)) * _UNIT[m.group(2).lower()]
    m = _RE_FRACTION.search(stem)
    if m:
        return 1.0 / float(m.group(1))
    return None


def exposure_times_from_names(paths: Sequence[Path], times_json: Path | None = None) -> list[float]:
    """Exposure seconds per file: from ``times_json`` (``{"file name": seconds}``) when given or when
    an ``exposures.json`` sits next to the images, else parsed from the names.

    Raises
    ------
    CalibrationError
        A file whose exposure cannot be found (names the file and the accepted patterns).
    """
    table: dict[str, float] = {}
    if times_json is None and paths:
        cand = Path(paths[0]).parent / "exposures.json"
        times_json = cand if cand.is_file() else None
    if times_json is not None:
        if Path(times_json).exists() and not Path(times_json).is_file():  # a FIFO: reading it waited for ever
            raise CalibrationError(
                f'{times_json}: not a regular file (a folder, pipe or device); expected an exposure table {{"file '
                'name": seconds}}'
            )
        try:
            raw = json.loads(Path(times_json).read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:  # ValueError: not JSON, or not UTF-8 text
            raise CalibrationError(f"{times_json}: cannot read exposure table: {e}") from None
        except RecursionError:  # [[[[...]]]] thousands deep: a traceback from the JSON decoder
            raise CalibrationError(
                f'{times_json}: JSON nested too deeply; expected an exposure table {{"file name": seconds}}'
            ) from None
        if not isinstance(raw, dict):
            raise CalibrationError(f'{times_json}: expected an object {{"file name": seconds}}')
        for k, v in raw.items():
            try:  # not bool (a JSON true), str, null, list or object; a huge integer overflows
                t = float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan
            except OverflowError:
                t = math.inf
            if not (0 < t < math.inf):
                raise CalibrationError(
                    f'{times_json}: "{k}": expected the exposure time in seconds as a positive number '
                    f"(such as 0.01), got {json.dumps(v)[:40]}"
                )
            table[str(k)] = t
    out = []
    for p in paths:
        p = Path(p)
        t = table.get(p.name, table.get(p.stem)) if table else None
        if t is None:
            t = exposure_time_from_name(p.name)
        if t is None or not t > 0:
            raise CalibrationError(
                f"{p}: exposure time unknown: name it like img_10ms.png, img_2500us.png, img_0.01s.png or "
                f'img_1-100.png, or list it in exposures.json ({{"{p.name}": 0.01}})'
            )
        out.append(float(t))
    return out


#: most Debevec pixel samples: the solve is a dense SVD of (samples * images + 257) x (samples + 256),
#: cubic in ``samples`` (1000 takes ~15 s; 2000 ~100 s and degenerates in float32)
MAX_SAMPLES = 1000
#: largest Debevec lambda: beyond it the smoothness term swamps the data in float32 and the curve
#: comes out wrong without any error (typical values are 1..100)
MAX_SMOOTHNESS = 1000.0


def check_response_options(samples: int, smoothness: float, image_size: tuple[int, int] | None = None) -> None:
    """Refuse Debevec parameters that cannot work (named by their command-line flags).

    ``image_size`` (width, height), when given, also checks that OpenCV can lay ``samples`` out as a
    grid on the image (it asserts otherwise).

    Raises
    ------
    CalibrationError
    """
    if not (0 < smoothness <= MAX_SMOOTHNESS):  # also refuses nan
        raise CalibrationError(
            f"--smoothness: expected the Debevec lambda, a number in (0, {MAX_SMOOTHNESS:g}] (typically 1..100), "
            f"got {smoothness}"
        )
    if not (1 <= samples <= MAX_SAMPLES):
        raise CalibrationError(f"--samples: expected 1..{MAX_SAMPLES} pixel samples (such as 120), got {samples}")
    if image_size is not None and not _sample_grid_fits(samples, *image_size):
        ok = [n for n in range(1, MAX_SAMPLES + 1) if _sample_grid_fits(n, *image_size)]
        near = min(ok, key=lambda n: abs(n - samples), default=None)
        hint = f"try --samples {near}" if near else "the images are too small for a response calibration"
        raise CalibrationError(
            f"--samples: {samples} pixel samples cannot be laid out as a grid on {image_size[0]}x{image_size[1]} "
            f"images; {hint}"
        )


def _sample_grid_fits(samples: int, w: int, h: int) -> bool:
    """Whether cv2.CalibrateDebevec (random=False) can place ``samples`` on a w x h grid (it asserts otherwise;
    photo/src/calibrate.cpp)."""
    x_points = int(math.sqrt(samples * w / h))
    return 0 < x_points <= w and 0 < samples // x_points <= h


def calibrate_response(
    images: Sequence[np.ndarray], times_s: Sequence[float], samples: int = 120, smoothness: float = 10.0
) -> np.ndarray:
    """Camera response from a static exposure bracket (Debevec-Malik), as a (256, 3) RGB LUT.

    Parameters
    ----------
    images : sequence of ndarray
        Same-size BGR uint8 images (OpenCV order) of a static scene, different exposure times.
    times_s : sequence of float
        Exposure time of each image, seconds.
    samples, smoothness : int, float
        ``cv2.createCalibrateDebevec`` parameters (pixel samples, lambda).

    Returns
    -------
    (256, 3) float32
        Linear value per code value and channel (R, G, B), non-decreasing, 255 -> 1.

    Raises
    ------
    CalibrationError
        Fewer than 3 images, mixed sizes, non-uint8 images, exposure times that do not span a
        useful range, or ``samples``/``smoothness`` out of range (:func:`check_response_options`).
    """
    if len(images) < 3:
        raise CalibrationError(f"response calibration needs at least 3 exposures, got {len(images)}")
    if len(images) != len(times_s):
        raise CalibrationError(f"{len(images)} images but {len(times_s)} exposure times")
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise CalibrationError(f"bracket images have different sizes: {sorted(shapes)}")
    if any(im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3 for im in images):
        raise CalibrationError("bracket images must be 8-bit colour (HxWx3 uint8)")
    check_response_options(samples, smoothness, (images[0].shape[1], images[0].shape[0]))
    t = np.asarray(times_s, np.float32)
    if np.any(t <= 0):
        raise CalibrationError(f"exposure times must be positive, got {t.tolist()}")
    if t.max() / t.min() < 4.0:
        raise CalibrationError(
            f"exposure times span only {t.max() / t.min():.1f}x ({t.min():g}..{t.max():g} s); a response curve "
            "needs a bracket of at least 4x (better 2-3 stops apart over 5+ images)"
        )
    cal = cv2.createCalibrateDebevec(samples=int(samples), lambda_=float(smoothness), random=False)
    resp = cal.process([np.ascontiguousarray(im) for im in images], t)  # (256, 1, 3) BGR
    lut = np.asarray(resp, np.float64).reshape(256, 3)[:, ::-1]  # -> RGB
    if not np.all(np.isfinite(lut)) or np.any(lut[128] <= 0):
        raise CalibrationError("response calibration produced a degenerate curve (is the scene static and lit?)")
    # Debevec's weights vanish at the extremes, so the curve near 255 is barely constrained; the
    # value at 255 is extrapolated from a power law fitted over codes 128..240 (log-log line).
    codes = np.arange(128, 241)
    top = np.empty(3)
    for c in range(3):
        y = np.log(np.maximum(lut[codes, c], 1e-12))
        a, b = np.polyfit(np.log(codes / 255.0), y, 1)
        top[c] = np.exp(b)  # value at code 255 (log(255/255) = 0)
    lut = lut / top
    lut = np.clip(lut, 0.0, None)
    lut[255] = np.maximum(lut[255], 1.0)
    lut = np.minimum(np.maximum.accumulate(lut, axis=0), 1.0)
    lut[0] = 0.0  # code 0 is black (Debevec leaves it arbitrary: no sample constrains it)
    return lut.astype(np.float32)


def save_response_lut(lut: np.ndarray, path: str | Path) -> Path:
    """Write a (256, 3) LUT as ``.npy`` (what :func:`illuminet.runtime.physics.load_response_lut` reads)."""
    lut = np.asarray(lut, np.float32)
    if lut.shape != (256, 3):
        raise CalibrationError(f"response LUT must have shape (256, 3), got {lut.shape}")
    path = Path(path)
    if path.suffix != ".npy":
        path = path.with_suffix(".npy")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, lut)
    return path
