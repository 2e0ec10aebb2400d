"""Frame and camera metadata types: what every source produces and every stage reads.

A :class:`Frame` is immutable by convention: stages never change the arrays they receive; they
return a new frame with their result added (:meth:`Frame.with_result`), which copies only the
small result mapping, never the images.

Conventions (see :mod:`illuminet.runtime.physics` for the lighting ones):

* ``color`` is H x W x 3 ``uint8`` **RGB** (not OpenCV's BGR), sRGB-encoded as the camera gives it.
* ``depth`` is H x W ``float32`` metres, aligned to ``color`` (same size), 0 = invalid. Sources that
  get uint16 millimetres convert once with :func:`depth_from_mm`.
* Camera coordinates follow OpenCV: x right, y down, z forward, metres.
* Timestamps are int64 nanoseconds. ``t_device_ns`` is the sensor's clock (monotonic per source),
  ``t_host_ns`` is ``time.monotonic_ns()`` on the host when the frame arrived.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera (depth is aligned to it).

    Parameters
    ----------
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels.
    width, height : int
        Image size the intrinsics refer to.
    dist : tuple of float
        OpenCV distortion coefficients; empty when the image is already undistorted.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics for the same camera resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=int(width),
            height=int(height),
            dist=self.dist,
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self) | {"dist": list(self.dist)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Intrinsics:
        return cls(
            fx=float(d["fx"]),
            fy=float(d["fy"]),
            cx=float(d["cx"]),
            cy=float(d["cy"]),
            width=int(d["width"]),
            height=int(d["height"]),
            dist=tuple(float(x) for x in d.get("dist", ())),
        )


@dataclass(frozen=True)
class Exposure:
    """Exposure metadata of one colour frame; ``None`` where the camera does not report it.

    Parameters
    ----------
    exposure_us : float or None
        Exposure (integration) time in microseconds.
    iso : float or None
        Sensor sensitivity as ISO (DepthAI reports it directly; analogue gain g is ISO = 100 g).
    wb_gains : tuple of 3 floats or None
        White-balance gains (R, G, B) the camera applied, or ``None``.
    color_temperature_k : float or None
        Colour temperature the camera's AWB chose, when reported.
    """

    exposure_us: float | None = None
    iso: float | None = None
    wb_gains: tuple[float, float, float] | None = None
    color_temperature_k: float | None = None

    @property
    def known(self) -> bool:
        """True when time and sensitivity are both reported (absolute normalisation possible)."""
        return self.exposure_us is not None and self.iso is not None

    @property
    def scale(self) -> float | None:
        """Relative sensor response: exposure seconds x ISO/100. Pixel_linear / scale is scene-referred."""
        if not self.known:
            return None
        return (self.exposure_us * 1e-6) * (self.iso / 100.0)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if d["wb_gains"] is not None:
            d["wb_gains"] = list(d["wb_gains"])
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> Exposure:
        if not d:
            return cls()
        wb = d.get("wb_gains")
        return cls(
            exposure_us=None if d.get("exposure_us") is None else float(d["exposure_us"]),
            iso=None if d.get("iso") is None else float(d["iso"]),
            wb_gains=None if wb is None else tuple(float(x) for x in wb),
            color_temperature_k=None if d.get("color_temperature_k") is None else float(d["color_temperature_k"]),
        )


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading in the colour camera's frame (OpenCV axes).

    ``accel`` is specific force in m/s^2 (at rest it points *up*, opposite to gravity);
    ``gyro`` is angular rate in rad/s (may be ``None``).
    """

    t_ns: int
    accel: tuple[float, float, float]
    gyro: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Frame:
    """One synchronised RGB-D frame plus everything the stages added to it.

    Parameters
    ----------
    seq : int
        Sequence number from the source, increasing.
    t_device_ns, t_host_ns : int
        Device and host timestamps (int64 ns).
    color : np.ndarray
        H x W x 3 uint8 RGB, sRGB-encoded.
    depth : np.ndarray or None
        H x W float32 metres aligned to ``color``, 0 = invalid; ``None`` for colour-only frames.
    intrinsics : Intrinsics
        Of the colour image (and therefore of the aligned depth).
    exposure : Exposure
        Exposure metadata.
    gravity : np.ndarray or None
        Unit vector of gravity (pointing down) in camera coordinates, when an IMU gives it.
    imu : tuple of ImuSample
        Raw IMU samples matched to this frame (may be empty).
    results : Mapping[str, Any]
        Stage outputs by name (read-only view); add with :meth:`with_result`.
    """

    seq: int
    t_device_ns: int
    t_host_ns: int
    color: np.ndarray
    depth: np.ndarray | None
    intrinsics: Intrinsics
    exposure: Exposure = field(default_factory=Exposure)
    gravity: np.ndarray | None = None
    imu: tuple[ImuSample, ...] = ()
    results: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self) -> None:
        c = self.color
        if not (isinstance(c, np.ndarray) and c.ndim == 3 and c.shape[2] == 3 and c.dtype == np.uint8):
            raise ValueError(
                f"Frame.color must be an HxWx3 uint8 RGB array, got "
                f"{getattr(c, 'shape', type(c))} {getattr(c, 'dtype', '')}"
            )
        d = self.depth
        if d is not None:
            if not (isinstance(d, np.ndarray) and d.ndim == 2 and d.dtype == np.float32):
                raise ValueError(
                    f"Frame.depth must be an HxW float32 array in metres, got "
                    f"{getattr(d, 'shape', type(d))} {getattr(d, 'dtype', '')}"
                )
            if d.shape != c.shape[:2]:
                raise ValueError(f"Frame.depth {d.shape} must be aligned to colour {c.shape[:2]} (same size)")

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the colour image."""
        return self.color.shape[1], self.color.shape[0]

    def with_result(self, key: Any, value: Any) -> Frame:
        """A new frame sharing all arrays with this one, with ``results[str(key)] = value`` added.

        ``key`` is a :class:`~illuminet.runtime.scene.ResultKey` (or its name)."""
        name = str(key)
        res = dict(self.results)
        res[name] = value
        return dataclasses.replace(self, results=MappingProxyType(res))

    def replace(self, **changes: Any) -> Frame:
        """A new frame with some fields replaced (e.g. a source correcting depth units)."""
        return dataclasses.replace(self, **changes)


def depth_from_mm(depth_mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres (0 = invalid) -> float32 metres (0 = invalid)."""
    return depth_mm.astype(np.float32) * np.float32(1e-3)


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """float32 metres (0 or non-finite = invalid) -> uint16 millimetres, clipped to 65.535 m."""
    d = np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.rint(d * 1000.0), 0, 65535).astype(np.uint16)
