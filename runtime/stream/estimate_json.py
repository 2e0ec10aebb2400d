"""The lighting estimate as JSON: the one conversion every output of it uses.

This module owns the exported form of :class:`~illuminet.runtime.scene.LightEstimate` (results key
``LIGHT``): one JSON object per frame in the shape of WebXR's ``XRLightEstimate``
(``sphericalHarmonicsCoefficients``, ``primaryLightDirection``, ``primaryLightIntensity``) plus
ARCore-Environmental-HDR-like extras, the frame it belongs to, its coordinate frame and the
estimate's confidences and cues. The ``--estimates`` JSONL sink, the MJPEG server's
``/estimates`` (Server-Sent Events), ``/estimate.json`` and ``/stats.json``, the session
recorder's ``estimates.jsonl`` sidecar and the Python API all call :func:`estimate_dict`.

Every field and unit is documented in ``docs/estimate.md``; the JSON Schema that tests validate
against ships beside this module (:data:`SCHEMA_PATH`, ``light_estimate.schema.json``).

Units (the one choice that matters to a renderer): light values are in the **camera picture's
linear units** -- the estimate's scene-referred values times the frame's ``exposure_scale`` -- so
a white Lambertian surface lit by them, drawn by three.js (``LightProbe`` + ``DirectionalLight``,
no tone mapping) over the camera picture, gets the linear pixel value the camera would record.
``exposureScale`` is in the object too: divide by it to get scene-referred values back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import LIGHT, LightEstimate
from illuminet.runtime.sh import SH_A_HAT

#: the value of ``schema`` in every object; bump the version on an incompatible change
SCHEMA_NAME = "illuminet-light-estimate"
SCHEMA_VERSION = 1
#: the JSON Schema (draft 2020-12) of one object, shipped as package data
SCHEMA_PATH = Path(__file__).with_name("light_estimate.schema.json")

_LUMA = np.array([0.2126, 0.7152, 0.0722])
_Y00 = 0.282095
#: the coordinate frame every direction and position is given in (constant; see docs/estimate.md)
FRAME_DESCRIPTION = {
    "name": "anchor",
    "up": [0.0, 1.0, 0.0],
    "gravityAligned": True,
    "handedness": "right",
    "units": "m",
    "cameraAxes": "opencv",
}
#: the confidence keys a :class:`LightEstimate` carries (British ``colour``, as in the runtime)
CONFIDENCE_KEYS = ("ambient", "direction", "intensity", "colour", "position")


def _num(x: Any, digits: int = 6) -> float:
    """A finite float rounded to ``digits`` significant digits (keeps JSONL lines short)."""
    v = float(x)
    if not math.isfinite(v):
        raise ValueError(f"light estimate holds a non-finite value ({v}); it cannot be exported as JSON")
    return float(f"{v:.{digits}g}")


def _vec4(v: Any, w: float) -> dict[str, float]:
    x, y, z = (float(c) for c in np.asarray(v, np.float64).ravel()[:3])
    return {"x": _num(x), "y": _num(y), "z": _num(z), "w": float(w)}


def _plain(v: Any) -> Any:
    """JSON-safe copy of the free-form ``observed`` values (numpy scalars/arrays, tuples, None)."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _num(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.ndarray):
        return [_plain(x) for x in v.tolist()]
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return str(v)


def estimate_dict(
    est: LightEstimate,
    *,
    seq: int,
    t_device_ns: int,
    t_host_ns: int | None = None,
    intrinsics: Intrinsics | None = None,
) -> dict[str, Any]:
    """The JSON object of one frame's lighting estimate (see ``docs/estimate.md``).

    Parameters
    ----------
    est : LightEstimate
        The estimate (object frame, scene-referred units).
    seq, t_device_ns, t_host_ns : int
        The frame it belongs to (``Frame.seq`` and its timestamps).
    intrinsics : Intrinsics, optional
        The frame's camera, exported as ``camera`` (lets a renderer draw from the camera's pose).

    Returns
    -------
    dict
        JSON-serialisable; validates against :data:`SCHEMA_PATH`.
    """
    k = float(est.exposure_scale) if est.exposure_scale and est.exposure_scale > 0 else 1.0
    radiance = est.radiance_sh9() * k  # (9, 3) radiance SH, camera-linear units
    has_primary = est.primary_dir is not None
    if has_primary:
        d = np.asarray(est.primary_dir, np.float64)
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        rgb = np.maximum(np.asarray(est.primary_rgb, np.float64), 0.0) * k
    else:  # WebXR always gives a direction; with no dominant light: straight up, no intensity
        d, rgb = np.array([0.0, 1.0, 0.0]), np.zeros(3)
    # ARCore-like ambient colour correction: the mean irradiance over all orientations (ambient DC term
    # plus the primary light's average cosine, 1/4) as the value a white diffuse surface shows
    mean_e = np.asarray(est.sh9, np.float64)[0] * _Y00 * k + rgb / 4.0
    mean_px = mean_e / np.pi
    luma = float(mean_px @ _LUMA)
    g = mean_px[1] if mean_px[1] > 1e-12 else max(float(mean_px.max()), 1e-12)
    T = est.T_cam_obj
    out: dict[str, Any] = {
        "schema": SCHEMA_NAME,
        "version": SCHEMA_VERSION,
        "frameId": int(seq),
        "timestamp": _num(int(t_device_ns) * 1e-9, 15),
        "timestampNs": {"device": int(t_device_ns), "host": None if t_host_ns is None else int(t_host_ns)},
        "sphericalHarmonicsCoefficients": [_num(x) for x in radiance.ravel()],
        "primaryLightDirection": _vec4(d, 0.0),
        "primaryLightIntensity": _vec4(rgb, 1.0),
        "hasPrimaryLight": bool(has_primary),
        # no position without a primary light (a client would place a point light there)
        "primaryLightPosition": _vec4(est.primary_pos, 1.0) if has_primary and est.primary_pos is not None else None,
        "ambientIntensity": _num(luma),
        "colorCorrection": {
            "r": _num(mean_px[0] / g),
            "g": _num(mean_px[1] / g),
            "b": _num(mean_px[2] / g),
            "a": _num(luma),
        },
        "exposureScale": _num(k),
        "coordinateFrame": dict(
            FRAME_DESCRIPTION,
            T_cam_obj=(None if T is None else [_num(x) for x in np.asarray(T, np.float64).reshape(16)]),
        ),
        "camera": None
        if intrinsics is None
        else {
            "fx": _num(intrinsics.fx),
            "fy": _num(intrinsics.fy),
            "cx": _num(intrinsics.cx),
            "cy": _num(intrinsics.cy),
            "width": int(intrinsics.width),
            "height": int(intrinsics.height),
        },
        "confidence": {key: _num(np.clip(float(est.confidence.get(key, 0.0)), 0.0, 1.0)) for key in CONFIDENCE_KEYS},
        "observed": _plain(dict(est.observed)),
        "method": str(est.method),
    }
    return out


def frame_estimate(frame: Frame) -> dict[str, Any] | None:
    """:func:`estimate_dict` of ``frame.results[LIGHT]``, or None when the frame has no estimate."""
    est = frame.results.get(LIGHT.name)
    if est is None:
        return None
    return estimate_dict(
        est, seq=frame.seq, t_device_ns=frame.t_device_ns, t_host_ns=frame.t_host_ns, intrinsics=frame.intrinsics
    )


def to_line(obj: Mapping[str, Any]) -> str:
    """One compact JSON line (no spaces; ``\\n`` not included)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def estimate_from_dict(d: Mapping[str, Any]) -> LightEstimate:
    """Back from JSON to a :class:`LightEstimate` (scene-referred, object frame): for replay checks.

    Inverts :func:`estimate_dict` up to its rounding (6 significant digits).
    """
    k = float(d["exposureScale"])
    rad = np.asarray(d["sphericalHarmonicsCoefficients"], np.float64).reshape(9, 3) / k
    p = d["primaryLightDirection"]
    i = d["primaryLightIntensity"]
    pos = d.get("primaryLightPosition")
    T = d["coordinateFrame"].get("T_cam_obj")
    return LightEstimate(
        sh9=rad * SH_A_HAT[:, None],
        primary_dir=np.array([p["x"], p["y"], p["z"]]) if d["hasPrimaryLight"] else None,
        primary_rgb=np.array([i["x"], i["y"], i["z"]]) / k,
        primary_pos=None if pos is None else np.array([pos["x"], pos["y"], pos["z"]]),
        confidence=dict(d["confidence"]),
        observed=dict(d["observed"]),
        exposure_scale=k,
        method=str(d["method"]),
        T_cam_obj=None if T is None else np.asarray(T, np.float64).reshape(4, 4),
    )


def load_schema() -> dict[str, Any]:
    """The JSON Schema of one estimate object (``light_estimate.schema.json``)."""
    return json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
