"""OAK-D source (DepthAI v3): colour + stereo depth aligned to colour, exposure metadata, IMU gravity.

This module owns everything that talks to a Luxonis OAK device. URL syntax::

    oakd://                      the first device found
    oakd://14442C10D13EABCE00    a device by MXID (device id)
    oakd://192.168.1.44          a PoE device by IP address
    oakd://?fps=30&size=640x400&queue=2&imu=1&preset=default
    oakd://?protocol=usb         search USB only: nothing is broadcast on the network

Query parameters (all optional): see :class:`OakdOptions`.

Device discovery and the network: unless told otherwise, DepthAI looks for devices on USB **and** by
a UDP broadcast (port 11491) on every network interface, to find PoE models; ``illuminet doctor``
and ``oakd://`` without a device id do that. ``protocol=usb`` (or ``[source] oakd_protocol =
"usb"``) sets ``DEPTHAI_PROTOCOL=usb`` before DepthAI's first search, and nothing is sent on the
network (:func:`select_protocol`). DepthAI reads that variable once per process, at its first search.

How it is split, so that everything but the device itself is tested on a machine without one:

* :func:`parse_url` -> :class:`OakdOptions` (pure Python).
* :func:`intrinsics_from_calibration` and :func:`imu_rotation_from_calibration` read a
  ``dai.CalibrationHandler`` (from the device's EEPROM, or a calibration JSON file on disk).
* :func:`build_sync` creates the host-side ``dai.node.Sync`` that pairs colour and depth by
  timestamp and its non-blocking output queue; it runs in a host-only pipeline too (tests feed it
  ``dai.ImgFrame`` messages built on the host).
* :class:`FrameConverter` turns a synced ``dai.MessageGroup`` (colour ``dai.ImgFrame`` + depth
  ``dai.ImgFrame``) and ``dai.IMUData`` into :class:`~illuminet.runtime.frame.Frame`; the camera
  matrix comes from each colour frame's ``ImgTransformation`` (:func:`intrinsics_from_transformation`),
  the calibration's being the fallback.
* :func:`build_device_pipeline` adds the on-device nodes (Camera CAM_A, mono cameras CAM_B/CAM_C,
  StereoDepth aligned to CAM_A, IMU); it needs a device (DepthAI refuses device nodes otherwise).
* :class:`OakdSource` ties them together and handles a lost device (clear error, or reconnection
  with exponential backoff when ``[source] reconnect`` is on).

Telemetry is off: ``DEPTHAI_TELEMETRY=0`` is set before ``depthai`` is imported; so is the upload of a
camera's firmware crash dump (``DEPTHAI_CRASHDUMP=0``, ``DEPTHAI_DISABLE_CRASHDUMP_COLLECTION=1``, unless
already set).
"""

from __future__ import annotations

import dataclasses
import datetime
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

os.environ["DEPTHAI_TELEMETRY"] = "0"  # before importing depthai: the runtime never phones home
# ... nor uploads a firmware crash dump ("... will not be saved nor uploaded to the Luxonis servers" with
# DEPTHAI_CRASHDUMP=0, libdepthaicore 3.12); a user who wants to send one sets these before starting
os.environ.setdefault("DEPTHAI_CRASHDUMP", "0")
os.environ.setdefault("DEPTHAI_DISABLE_CRASHDUMP_COLLECTION", "1")

import cv2  # noqa: E402
import depthai as dai  # noqa: E402
import numpy as np  # noqa: E402

from illuminet.hw import (  # noqa: E402
    SourceError,
    parse_query,
    query_bool,
    query_choice,
    query_float,
    query_int,
    query_size,
)
from illuminet.hw.serial_imu import ImuMatcher  # noqa: E402
from illuminet.runtime.config import Config  # noqa: E402
from illuminet.runtime.frame import Exposure, Frame, ImuSample, Intrinsics, depth_from_mm  # noqa: E402
from illuminet.runtime.stage import EndOfStream, Source  # noqa: E402

log = logging.getLogger(__name__)

COLOR_SOCKET = dai.CameraBoardSocket.CAM_A
LEFT_SOCKET = dai.CameraBoardSocket.CAM_B
RIGHT_SOCKET = dai.CameraBoardSocket.CAM_C

_PRESETS = {p.lower(): getattr(dai.node.StereoDepth.PresetMode, p) for p in dai.node.StereoDepth.PresetMode.__members__}


class OakdError(SourceError):
    """The OAK device cannot be used; the message says why and what to do."""


# ---------------------------------------------------------------------------------------- options


@dataclass(frozen=True)
class OakdOptions:
    """What ``oakd://[DEVICE]?key=value&...`` asks for.

    Attributes
    ----------
    device : str
        MXID / device id, IP address or USB port name; ``""`` = the first device found.
    fps : float
        Frame rate of all cameras (``fps=30``).
    size : (int, int)
        Colour (and aligned depth) output size ``WxH`` (``size=640x400``).
    mono_size : (int, int)
        Resolution the stereo pair runs at (``mono=640x400``); higher = finer depth, slower.
    queue : int
        Output queue length 1..4; the queue is non-blocking and keeps the newest (``queue=2``).
    imu : bool
        Read the accelerometer for gravity (``imu=1``); ignored on devices without an IMU.
    imu_rate : int
        Accelerometer report rate, Hz (``imu_rate=100``).
    preset : str
        StereoDepth preset (``preset=default``; also fast_accuracy, fast_density, face, high_detail,
        robotics, density, accuracy).
    lr_check, subpixel, extended : bool
        StereoDepth left-right check (needed for alignment), subpixel, extended disparity.
    undistort : bool
        Ask the colour camera to undistort on the device (``undistort=1``); then ``Intrinsics.dist`` is
        empty, else it carries the calibration's distortion coefficients.
    exposure_us, iso : int
        Manual exposure (both > 0) for stable photometry; 0 = auto exposure (default).
    sync_ms : float
        Largest colour/depth timestamp gap paired by the Sync node; 0 = half a frame period.
    timeout_s : float
        No frame for this long means the device is lost.
    reconnect : bool or None
        Override ``[source] reconnect`` (``reconnect=0``/``1``).
    protocol : str
        How devices are searched (``protocol=usb``): ``any`` (USB and a UDP broadcast on the
        network), ``usb``, ``tcpip``; ``""`` = ``[source] oakd_protocol``.
    """

    device: str = ""
    fps: float = 30.0
    size: tuple[int, int] = (640, 400)
    mono_size: tuple[int, int] = (640, 400)
    queue: int = 2
    imu: bool = True
    imu_rate: int = 100
    preset: str = "default"
    lr_check: bool = True
    subpixel: bool = True
    extended: bool = False
    undistort: bool = False
    exposure_us: int = 0
    iso: int = 0
    sync_ms: float = 0.0
    timeout_s: float = 5.0
    reconnect: bool | None = None
    protocol: str = ""

    @property
    def sync_threshold(self) -> datetime.timedelta:
        ms = self.sync_ms if self.sync_ms > 0 else 500.0 / self.fps
        return datetime.timedelta(milliseconds=ms)


def parse_url(url: str) -> OakdOptions:
    """``oakd://[DEVICE]?key=value&...`` -> :class:`OakdOptions`; unknown keys and bad values are refused."""
    parts = urlsplit(url)
    if parts.scheme != "oakd":
        raise ValueError(f"{url!r} is not an oakd:// URL")
    size = query_size(even=True)
    parsers = {
        "fps": query_float,
        "size": size,
        "mono": size,
        "queue": query_int(),
        "imu": query_bool,
        "imu_rate": query_int(1, 1000),  # the BMI270 / BNO086 accelerometers report up to ~500 Hz
        "preset": query_choice(*sorted(_PRESETS), lower=True),
        "lr_check": query_bool,
        "subpixel": query_bool,
        "extended": query_bool,
        "undistort": query_bool,
        "exposure_us": query_int(0, 33000),  # 0 = auto; the colour sensors' manual range is 1..33000 us
        "iso": query_int(0, 1600),  # 0 = auto; manual 100..1600
        "sync_ms": query_float,
        "timeout_s": query_float,
        "reconnect": query_bool,
        "protocol": query_choice(*PROTOCOLS, lower=True),
    }
    kw: dict[str, Any] = {"mono_size" if k == "mono" else k: v for k, v in parse_query(url, parsers).items()}
    kw["device"] = (parts.netloc + parts.path).strip("/")
    o = OakdOptions(**kw)
    if not 1 <= o.queue <= 4:
        raise ValueError(f"{url}: queue={o.queue}: expected 1..4 (frames kept; the newest wins)")
    if not 0 < o.fps <= 120:
        raise ValueError(f"{url}: fps={o.fps}: expected 0 < fps <= 120")
    if (o.exposure_us > 0) != (o.iso > 0):
        raise ValueError(
            f"{url}: manual exposure needs both exposure_us and iso (> 0), got exposure_us={o.exposure_us}, iso={o.iso}"
        )
    if o.timeout_s <= 0 or o.imu_rate <= 0:
        raise ValueError(f"{url}: timeout_s and imu_rate must be positive")
    if o.sync_ms < 0:
        raise ValueError(f"{url}: sync_ms={o.sync_ms:g}: expected >= 0 (0 = half a frame period)")
    if 0 < o.iso < 100:
        raise ValueError(f"{url}: iso={o.iso}: expected 100..1600 for manual exposure (0 = auto)")
    if o.protocol == "usb" and _is_ip(o.device):
        raise ValueError(f"{url}: protocol=usb cannot reach the network device {o.device}; drop one of them")
    return o


def _is_ip(name: str) -> bool:
    parts = name.split(".")
    return len(parts) == 4 and all(p.isdigit() and int(p) < 256 for p in parts)


# ---------------------------------------------------------------------------------------- discovery

#: how DepthAI may look for devices (``DEPTHAI_PROTOCOL``): any = USB and a UDP broadcast on the network
PROTOCOLS = ("any", "usb", "tcpip")
#: the protocol DepthAI searched with in this process (it reads DEPTHAI_PROTOCOL once, at its first search)
_searched_with: str | None = None


def select_protocol(protocol: str) -> str:
    """Make DepthAI search devices over ``protocol`` only; call before every device search.

    ``"usb"`` or ``"tcpip"`` set ``DEPTHAI_PROTOCOL`` (``usb``: nothing is broadcast on the network);
    ``"any"`` leaves DepthAI's default, or a ``DEPTHAI_PROTOCOL`` the user set. DepthAI reads the
    variable once per process, at its first search, so a later call asking for another protocol is
    refused rather than silently ignored.

    Returns
    -------
    str
        The protocol in effect.

    Raises
    ------
    OakdError
        DepthAI already searched with another protocol in this process.
    """
    global _searched_with
    if protocol not in PROTOCOLS:
        raise ValueError(f"OAK protocol {protocol!r}: expected one of {', '.join(PROTOCOLS)}")
    want = protocol if protocol != "any" else (os.environ.get("DEPTHAI_PROTOCOL", "").lower() or "any")
    if _searched_with is None:
        if protocol != "any":
            os.environ["DEPTHAI_PROTOCOL"] = protocol
        _searched_with = want
    elif _searched_with != want:
        raise OakdError(
            f"DepthAI already searched for devices over {_searched_with!r} in this process and keeps that; "
            f"protocol {want!r} needs a new process (set [source] oakd_protocol or DEPTHAI_PROTOCOL before it starts)"
        )
    return want


# ---------------------------------------------------------------------------------------- calibration


def load_calibration_file(path: str) -> dai.CalibrationHandler:
    """A ``dai.CalibrationHandler`` from a DepthAI calibration JSON (as
    ``Device.readCalibration().eepromToJsonFile`` writes)."""
    if not os.path.isfile(path):
        raise OakdError(f"DepthAI calibration file not found: {path}")
    try:
        return dai.CalibrationHandler(path)
    except RuntimeError as e:
        raise OakdError(f"{path}: not a DepthAI calibration file: {e}") from e


def intrinsics_from_calibration(
    calib: dai.CalibrationHandler,
    width: int,
    height: int,
    socket: dai.CameraBoardSocket = COLOR_SOCKET,
    undistorted: bool = False,
) -> Intrinsics:
    """Intrinsics of a camera at an output size, as the Camera node produces it.

    ``Camera.requestOutput`` resizes with ``ImgResizeMode.CROP``: scale to cover, then centre-crop;
    ``getCameraIntrinsics(..., keepAspectRatio=True)`` models exactly that.

    Parameters
    ----------
    calib : dai.CalibrationHandler
    width, height : int
        Output size.
    socket : dai.CameraBoardSocket
    undistorted : bool
        True when the device undistorts the output (then no distortion coefficients are returned).
    """
    try:
        K = np.asarray(calib.getCameraIntrinsics(socket, int(width), int(height), keepAspectRatio=True))
    except RuntimeError as e:
        raise OakdError(f"calibration has no intrinsics for {socket}: {e}") from e
    dist: tuple[float, ...] = ()
    if not undistorted:
        d = [float(x) for x in calib.getDistortionCoefficients(socket)]
        # DepthAI stores OpenCV's 14-coefficient model; keep 8 when the tilt/prism terms are all zero
        if len(d) == 14 and not any(d[8:]):
            d = d[:8]
        dist = tuple(d)
    return Intrinsics(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        width=int(width),
        height=int(height),
        dist=dist,
    )


#: colour intrinsics from the frame and from the calibration further apart than this are reported (once)
INTRINSICS_TOLERANCE = 0.03


def intrinsics_from_transformation(
    tr: dai.ImgTransformation, width: int, height: int, dist: tuple[float, ...] = ()
) -> Intrinsics | None:
    """Intrinsics of a frame from its ``ImgTransformation``; ``None`` when it carries none.

    DepthAI v3 attaches to every ``ImgFrame`` the camera matrix of the image actually produced: the
    calibration at the sensor mode the Camera node picked, then its crop and scale
    (``getIntrinsicMatrix``). That is the exact source; the calibration's
    ``getCameraIntrinsics(..., keepAspectRatio=True)`` assumes the calibrated image's field of view and
    aspect ratio, which a 16:10 output cropped from a 4:3 sensor mode does not keep. Frames built on the
    host carry an invalid, empty transformation (size 0x0): then ``None``, and the caller falls back
    to the calibration.

    Parameters
    ----------
    tr : dai.ImgTransformation
    width, height : int
        The frame's size; a transformation of another size is scaled to it.
    dist : tuple of float
        Distortion coefficients to attach (they do not change with crop and scale).
    """
    if tr is None or not tr.isValid():
        return None
    tw, th = (int(v) for v in tr.getSize())
    K = np.asarray(tr.getIntrinsicMatrix(), dtype=np.float64)
    if tw <= 0 or th <= 0 or K.shape != (3, 3) or not np.all(np.isfinite(K)) or min(K[0, 0], K[1, 1]) <= 1.0:
        return None
    intr = Intrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=tw, height=th, dist=tuple(dist))
    return intr if (tw, th) == (width, height) else intr.scaled(width, height)


def intrinsics_disagreement(a: Intrinsics, b: Intrinsics) -> float:
    """Largest relative difference between two intrinsics of the same image size: focal lengths
    relative to ``b``'s, principal point relative to the image size."""
    if (a.width, a.height) != (b.width, b.height):
        b = b.scaled(a.width, a.height)
    return max(
        abs(a.fx - b.fx) / b.fx,
        abs(a.fy - b.fy) / b.fy,
        abs(a.cx - b.cx) / a.width,
        abs(a.cy - b.cy) / a.height,
    )


def imu_rotation_from_calibration(
    calib: dai.CalibrationHandler, socket: dai.CameraBoardSocket = COLOR_SOCKET
) -> np.ndarray | None:
    """IMU -> camera rotation from the calibration's IMU extrinsics; ``None`` when it has none.

    Older factory calibrations carry no IMU extrinsics (DepthAI then raises or returns zeros); the
    caller decides what to do (see :class:`OakdSource`: no gravity unless ``imu_rotation`` is given).
    """
    try:
        T = np.asarray(calib.getImuToCameraExtrinsics(socket, True), dtype=np.float64)
    except RuntimeError:
        return None
    if T.shape != (4, 4):
        return None
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0.5:
        return None
    return R


# ---------------------------------------------------------------------------------------- conversion


def td_to_ns(td: datetime.timedelta) -> int:
    """A DepthAI timestamp (``datetime.timedelta``, microsecond resolution) -> int64 nanoseconds."""
    return ((td.days * 86_400 + td.seconds) * 1_000_000 + td.microseconds) * 1_000


def exposure_of(img: dai.ImgFrame) -> Exposure:
    """Per-frame exposure metadata of a colour ``dai.ImgFrame`` (``None`` where it reports 0)."""
    exp_us = img.getExposureTime().total_seconds() * 1e6
    iso = float(img.getSensitivity())
    ct = float(img.getColorTemperature())
    return Exposure(
        exposure_us=exp_us if exp_us > 0 else None,
        iso=iso if iso > 0 else None,
        wb_gains=None,
        color_temperature_k=ct if ct > 0 else None,
    )


def color_to_rgb(img: dai.ImgFrame) -> np.ndarray:
    """HxWx3 uint8 RGB from a colour ``dai.ImgFrame`` (BGR/RGB interleaved or planar, NV12...)."""
    bgr = img.getCvFrame()  # DepthAI converts any colour type to OpenCV's BGR
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise ValueError(f"colour frame of type {img.getType()} gave {bgr.shape} {bgr.dtype}, expected HxWx3 uint8")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def depth_to_m(img: dai.ImgFrame, size: tuple[int, int]) -> np.ndarray:
    """HxW float32 metres (0 invalid) from a RAW16 millimetre depth ``dai.ImgFrame``, at ``size`` (W, H)."""
    mm = img.getFrame()
    if mm.ndim != 2 or mm.dtype != np.uint16:
        raise ValueError(f"depth frame of type {img.getType()} gave {mm.shape} {mm.dtype}, expected HxW uint16 mm")
    if (mm.shape[1], mm.shape[0]) != tuple(size):
        # the device aligns depth to the colour camera; only the scale can differ: nearest keeps edges
        mm = cv2.resize(mm, tuple(size), interpolation=cv2.INTER_NEAREST)
    return depth_from_mm(mm)


def imu_samples_of(data: dai.IMUData) -> list[ImuSample]:
    """Accelerometer (and gyro when present) samples of a ``dai.IMUData``, device clock ns, IMU axes."""
    out = []
    for p in data.packets:
        a = p.acceleroMeter
        t = td_to_ns(a.getTimestampDevice())
        if t == 0:
            continue  # packet without an accelerometer report
        out.append(ImuSample(t_ns=t, accel=(float(a.x), float(a.y), float(a.z))))
    return out


class FrameConverter:
    """Turns synced DepthAI messages into :class:`Frame` objects; counts drops from sequence gaps.

    Parameters
    ----------
    intrinsics : Intrinsics
        Of the colour output from the calibration (depth is aligned to it): used for frames that carry
        no ``ImgTransformation``, and for the distortion coefficients. A frame's own transformation
        gives its camera matrix (:func:`intrinsics_from_transformation`); when it differs from this by
        more than :data:`INTRINSICS_TOLERANCE`, a warning says so once.
    imu : ImuMatcher, optional
        Device IMU samples (added with :meth:`add_imu`) give ``Frame.imu`` and ``Frame.gravity``.
    color_key, depth_key : str
        Names of the Sync node's inputs.
    """

    def __init__(
        self, intrinsics: Intrinsics, imu: ImuMatcher | None = None, color_key: str = "color", depth_key: str = "depth"
    ):
        self.intrinsics = intrinsics
        self.imu = imu
        self.color_key, self.depth_key = color_key, depth_key
        self.frames = 0
        self.dropped = 0
        self._last_dev_seq: int | None = None
        self._warned_intrinsics = False
        #: frames whose depth carried another camera matrix than their colour (not aligned to it)
        self.misaligned_depth = 0
        #: where the last frame's intrinsics came from: "frame" (its ImgTransformation) or "calibration"
        self.intrinsics_source = "calibration"

    def _frame_intrinsics(self, color: dai.ImgFrame, width: int, height: int) -> Intrinsics:
        calib = self.intrinsics
        if (width, height) != (calib.width, calib.height):
            calib = calib.scaled(width, height)
        intr = intrinsics_from_transformation(color.getTransformation(), width, height, calib.dist)
        if intr is None:
            self.intrinsics_source = "calibration"
            return calib
        self.intrinsics_source = "frame"
        off = intrinsics_disagreement(intr, calib)
        if off > INTRINSICS_TOLERANCE and not self._warned_intrinsics:
            self._warned_intrinsics = True
            log.warning(
                "OAK colour intrinsics at %dx%d: the frame's own (fx %.1f fy %.1f cx %.1f cy %.1f) differ from "
                "the calibration's scale-and-crop (fx %.1f fy %.1f cx %.1f cy %.1f) by %.1f %%; using the frame's "
                "(the camera picked a sensor mode with another field of view than the calibrated image)",
                width,
                height,
                intr.fx,
                intr.fy,
                intr.cx,
                intr.cy,
                calib.fx,
                calib.fy,
                calib.cx,
                calib.cy,
                100 * off,
            )
        return intr

    def _check_depth_alignment(self, depth: dai.ImgFrame, intr: Intrinsics) -> None:
        """Depth aligned to colour must carry the colour frame's camera matrix; count and warn once if not."""
        d = intrinsics_from_transformation(depth.getTransformation(), intr.width, intr.height)
        if d is None:  # no transformation (host-built frames): nothing to compare
            return
        off = intrinsics_disagreement(d, intr)
        if off <= INTRINSICS_TOLERANCE:
            return
        self.misaligned_depth += 1
        if self.misaligned_depth == 1:
            log.warning(
                "OAK depth is not aligned to the colour frame: its camera matrix scaled to %dx%d (fx %.1f fy %.1f "
                "cx %.1f cy %.1f) differs from the colour's (fx %.1f fy %.1f cx %.1f cy %.1f) by %.1f %%; planes and "
                "the object's position will be off (counted as misaligned_depth)",
                intr.width,
                intr.height,
                d.fx,
                d.fy,
                d.cx,
                d.cy,
                intr.fx,
                intr.fy,
                intr.cx,
                intr.cy,
                100 * off,
            )

    def add_imu(self, data: dai.IMUData) -> None:
        if self.imu is not None:
            for s in imu_samples_of(data):
                self.imu.add(s)

    def convert(self, group: dai.MessageGroup) -> Frame:
        """One :class:`Frame` from a Sync node's ``MessageGroup`` with colour and depth."""
        try:
            color, depth = group[self.color_key], group[self.depth_key]
        except (IndexError, KeyError):  # DepthAI raises IndexError (map::at) for a missing name
            color = depth = None
        if color is None or depth is None:
            raise ValueError(f"message group lacks {self.color_key!r} or {self.depth_key!r}")
        seq_dev = int(color.getSequenceNum())
        if self._last_dev_seq is not None and seq_dev > self._last_dev_seq + 1:
            # the non-blocking queue discarded older groups: the loop (or USB) was slower than the camera
            self.dropped += seq_dev - self._last_dev_seq - 1
        self._last_dev_seq = seq_dev
        rgb = color_to_rgb(color)
        intr = self._frame_intrinsics(color, rgb.shape[1], rgb.shape[0])
        self._check_depth_alignment(depth, intr)
        t_dev = td_to_ns(color.getTimestampDevice())
        frame = Frame(
            seq=self.frames,
            t_device_ns=t_dev,
            # DepthAI's host-synced timestamp is on the host's steady clock (= time.monotonic_ns)
            t_host_ns=td_to_ns(color.getTimestamp()),
            color=rgb,
            depth=depth_to_m(depth, (rgb.shape[1], rgb.shape[0])),
            intrinsics=intr,
            exposure=exposure_of(color),
        )
        self.frames += 1
        if self.imu is not None:
            samples, g = self.imu.match(t_dev)
            if samples:
                frame = frame.replace(imu=samples, gravity=g)
        return frame


# ---------------------------------------------------------------------------------------- pipeline


def build_sync(pipeline: dai.Pipeline, opts: OakdOptions) -> tuple[Any, Any]:
    """The host-side Sync node pairing colour and depth, and its non-blocking output queue.

    Returns
    -------
    (sync, queue)
        Link colour to ``sync.inputs["color"]`` and depth to ``sync.inputs["depth"]``. The queue holds
        ``opts.queue`` groups and, being non-blocking, discards the oldest when full (newest wins).
    """
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(opts.sync_threshold)
    sync.setRunOnHost(True)  # pairing is cheap; on the host it needs no device (and is testable)
    queue = sync.out.createOutputQueue(maxSize=opts.queue, blocking=False)
    return sync, queue


def build_device_pipeline(pipeline: dai.Pipeline, opts: OakdOptions, has_imu: bool) -> dict[str, Any]:
    """Add the on-device nodes and the host Sync; returns ``{"sync_queue", "imu_queue" (or None)}``.

    Needs a pipeline bound to a device (``dai.Pipeline(device)``): DepthAI refuses device nodes in a
    host-only pipeline.
    """
    fps = float(opts.fps)
    cam = pipeline.create(dai.node.Camera).build(COLOR_SOCKET)
    if opts.exposure_us > 0:
        cam.initialControl.setManualExposure(int(opts.exposure_us), int(opts.iso))
    color_out = cam.requestOutput(
        opts.size, type=dai.ImgFrame.Type.BGR888i, fps=fps, enableUndistortion=bool(opts.undistort)
    )
    left = pipeline.create(dai.node.Camera).build(LEFT_SOCKET)
    right = pipeline.create(dai.node.Camera).build(RIGHT_SOCKET)
    stereo = pipeline.create(dai.node.StereoDepth).build(
        left.requestOutput(opts.mono_size, fps=fps),
        right.requestOutput(opts.mono_size, fps=fps),
        presetMode=_PRESETS[opts.preset],
    )
    stereo.setLeftRightCheck(opts.lr_check)
    stereo.setSubpixel(opts.subpixel)
    stereo.setExtendedDisparity(opts.extended)
    stereo.setDepthAlign(COLOR_SOCKET)  # depth in the colour camera's view ...
    stereo.setOutputSize(*opts.size)  # ... at the colour output's size ...
    # ... with the colour output's own transformation (sensor mode, crop, scale), not the calibration's
    # guess of it. That is DepthAI v3's RVC2 path; RVC4 (OAK 4) aligns with an ImageAlign node instead,
    # not built here. Either way FrameConverter warns when depth's camera matrix differs from colour's.
    if pipeline.getDefaultDevice().getPlatform() != dai.Platform.RVC4:
        color_out.link(stereo.inputAlignTo)
    sync, sync_queue = build_sync(pipeline, opts)
    color_out.link(sync.inputs["color"])
    stereo.depth.link(sync.inputs["depth"])
    imu_queue = None
    if opts.imu and has_imu:
        imu = pipeline.create(dai.node.IMU)
        imu.enableIMUSensor(dai.IMUSensor.ACCELEROMETER_RAW, int(opts.imu_rate))
        imu.setBatchReportThreshold(1)
        imu.setMaxBatchReports(10)
        imu_queue = imu.out.createOutputQueue(maxSize=50, blocking=False)
    return {"sync_queue": sync_queue, "imu_queue": imu_queue}


# ---------------------------------------------------------------------------------------- devices


def list_devices(protocol: str = "any") -> list[dict[str, str]]:
    """OAK devices DepthAI can see: ``[{"id", "name", "state", "protocol", "platform"}]`` (for doctor).

    ``protocol``: see :func:`select_protocol` (``"any"`` broadcasts on the network to find PoE models).
    """
    select_protocol(protocol)
    out = []
    for d in dai.Device.getAllAvailableDevices():
        out.append(
            {
                "id": d.getDeviceId(),
                "name": d.name,
                "state": str(d.state).split(".")[-1],
                "protocol": str(d.protocol).split(".")[-1],
                "platform": str(d.platform).split(".")[-1],
            }
        )
    return out


def depthai_version() -> str:
    return str(dai.__version__)


# ---------------------------------------------------------------------------------------- the source


@dataclass
class OakdSession:
    """One connection: what :class:`OakdSource` reads from until the device is lost.

    Attributes
    ----------
    pipeline : dai.Pipeline
        Started; stopped on disconnect.
    queues : dict
        ``"sync_queue"`` (colour+depth message groups) and ``"imu_queue"`` (``dai.IMUData``, or None).
    converter : FrameConverter
        With the device's intrinsics and IMU matcher.
    device : dai.Device or None
        Closed on disconnect.
    device_id : str
    """

    pipeline: Any
    queues: dict
    converter: FrameConverter
    device: Any = None
    device_id: str = ""


def connect_device(opts: OakdOptions, imu_rotation: Any = None, max_skew_ms: float = 20.0) -> OakdSession:
    """Open the device, read its calibration, build and start the pipeline.

    Raises
    ------
    OakdError
        When no such device can be opened (with what DepthAI sees and how to fix access).
    """
    protocol = select_protocol(opts.protocol or "any")
    try:
        device = dai.Device(dai.DeviceInfo(opts.device)) if opts.device else dai.Device()
    except RuntimeError as e:
        try:
            found = ", ".join(d["id"] for d in list_devices(protocol)) or "none"
        except RuntimeError as e2:  # the search itself fails (no USB stack in a container)
            found = f"none (the search failed: {e2})"
        raise OakdError(
            f"cannot open OAK device {opts.device or '(first available)'}: {e}. Devices found: {found}. "
            "Check the USB cable/port (USB3 preferred) or PoE link, and on Linux the udev rule "
            '(echo \'SUBSYSTEM=="usb", ATTRS{idVendor}=="03e7", MODE="0666"\' | '
            "sudo tee /etc/udev/rules.d/80-movidius.rules; sudo udevadm control --reload-rules "
            "&& sudo udevadm trigger). `illuminet doctor` lists what DepthAI sees."
        ) from e
    try:
        device_id = device.getDeviceId()
        calib = device.readCalibration()
        intr = intrinsics_from_calibration(calib, *opts.size, undistorted=opts.undistort)
        has_imu = opts.imu and str(device.getConnectedIMU()).upper() not in ("", "NONE")
        matcher = None
        if has_imu:
            R = imu_rotation_from_calibration(calib)
            if R is None and imu_rotation is not None:
                R = np.asarray(imu_rotation, dtype=np.float64).reshape(3, 3)
            if R is None:
                log.warning(
                    "OAK %s: its calibration has no IMU-to-camera extrinsics, so gravity is not given "
                    "(a wrong axis guess would mislabel floors and walls). Set [imu] rotation "
                    "(IMU axes -> camera axes) to enable it.",
                    device_id,
                )
                has_imu = False
            else:
                matcher = ImuMatcher(max_skew_ms=max_skew_ms, rotation=R)
        pipeline = dai.Pipeline(device)
        queues = build_device_pipeline(pipeline, opts, has_imu)
        pipeline.start()
    except Exception:
        device.close()
        raise
    log.info(
        "OAK %s: %dx%d at %.0f fps, depth aligned to CAM_A, IMU %s",
        device_id,
        opts.size[0],
        opts.size[1],
        opts.fps,
        "on" if matcher else "off",
    )
    return OakdSession(
        pipeline=pipeline, queues=queues, converter=FrameConverter(intr, matcher), device=device, device_id=device_id
    )


class OakdSource(Source):
    """Live colour + aligned depth (+ gravity) from an OAK device; see the module docstring.

    Parameters
    ----------
    opts : OakdOptions
    reconnect : bool
        On a lost device, reconnect with exponential backoff (0.5 s doubling to 10 s) instead of
        ending the stream with an error. ``opts.reconnect`` overrides it.
    imu_rotation : 3x3 array-like, optional
        IMU -> colour camera rotation for devices whose calibration has no IMU extrinsics.
    max_skew_ms : float
        Largest IMU-to-frame time gap.
    connect : callable, optional
        ``connect(opts) -> OakdSession``; default :func:`connect_device`. (Tests connect a host-only
        DepthAI pipeline to exercise reading, newest-wins, timeouts and reconnection.)
    """

    name = "oakd"
    live = True

    BACKOFF_START_S = 0.5
    BACKOFF_MAX_S = 10.0

    def __init__(
        self,
        opts: OakdOptions,
        reconnect: bool = True,
        imu_rotation: Any = None,
        max_skew_ms: float = 20.0,
        connect: Any = None,
    ):
        self.opts = opts
        self.reconnect = opts.reconnect if opts.reconnect is not None else bool(reconnect)
        self.imu_rotation = imu_rotation
        self.max_skew_ms = max_skew_ms
        self._connect_fn = connect or (lambda o: connect_device(o, self.imu_rotation, self.max_skew_ms))
        self._session: OakdSession | None = None
        self._stop = threading.Event()
        self._seq = 0
        self.reconnects = 0
        self.bad_frames = 0
        self.device_id = ""
        self._dropped_before = 0
        self._misaligned_before = 0
        self._last_converter: FrameConverter | None = None

    # -- connection

    def _connect(self) -> None:
        session = self._connect_fn(self.opts)
        if self._last_converter is not None:
            self._dropped_before += self._last_converter.dropped
            self._misaligned_before += self._last_converter.misaligned_depth
        self._session, self._last_converter = session, session.converter
        self.device_id = session.device_id

    def _disconnect(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        for closer in (getattr(session.pipeline, "stop", None), getattr(session.device, "close", None)):
            if closer is None:
                continue
            try:
                closer()
            except Exception as e:  # a lost device may fail to close cleanly; nothing to do about it
                log.debug("OAK close: %s", e)

    def open(self) -> None:
        self._stop.clear()
        self._connect()

    def close(self) -> None:
        self._stop.set()
        self._disconnect()

    # -- frames

    def _next_group(self, session: OakdSession):
        q = session.queues["sync_queue"]
        imu_q = session.queues.get("imu_queue")
        deadline = time.monotonic() + self.opts.timeout_s
        while not self._stop.is_set():
            if imu_q is not None:
                for data in imu_q.tryGetAll():
                    session.converter.add_imu(data)
            groups = q.tryGetAll()
            if groups:
                return groups[-1]  # keep the newest; older ones count as drops via sequence gaps
            if time.monotonic() > deadline:
                raise OakdError(f"no frame from OAK {self.device_id} for {self.opts.timeout_s:g} s")
            if not session.pipeline.isRunning():
                raise OakdError(f"OAK {self.device_id} pipeline stopped")
            msg = q.get(datetime.timedelta(milliseconds=50))
            if msg is not None:
                rest = q.tryGetAll()
                return rest[-1] if rest else msg
        return None

    def read(self) -> Frame | None:
        """The newest colour+depth frame; blocks until one arrives. ``None`` after :meth:`close`."""
        backoff = self.BACKOFF_START_S
        while not self._stop.is_set():
            try:
                if self._session is None:
                    self._connect()
                    backoff = self.BACKOFF_START_S
                session = self._session  # close() from another thread may clear the attribute
                if session is None:
                    return None
                group = self._next_group(session)
                if group is None:
                    return None
                try:
                    frame = session.converter.convert(group)
                except ValueError as e:  # one bad frame: skip it, the stream goes on
                    self.bad_frames += 1
                    log.warning("OAK %s: skipped a bad frame: %s", self.device_id, e)
                    continue
                self._seq += 1
                return frame.replace(seq=self._seq - 1)
            except (RuntimeError, dai.MessageQueue.QueueException) as e:
                if self._stop.is_set():
                    return None
                if not self.reconnect:
                    self._disconnect()
                    raise EndOfStream(
                        f"OAK device {self.device_id or self.opts.device or '(first)'} lost: {e}. "
                        "Reconnect the cable and run again, or enable [source] reconnect."
                    ) from e
                self._disconnect()
                self.reconnects += 1
                log.warning(
                    "OAK %s lost (%s); reconnecting in %.1f s (attempt %d)",
                    self.device_id or self.opts.device,
                    e,
                    backoff,
                    self.reconnects,
                )
                if self._stop.wait(backoff):
                    return None
                backoff = min(backoff * 2, self.BACKOFF_MAX_S)
        return None

    def stats(self) -> dict[str, Any]:
        conv = self._last_converter
        return {
            "device": self.device_id,
            "dropped": self._dropped_before + (conv.dropped if conv else 0),
            "reconnects": self.reconnects,
            "bad_frames": self.bad_frames,
            "misaligned_depth": self._misaligned_before + (conv.misaligned_depth if conv else 0),
        }


def open_url(url: str, config: Config) -> OakdSource:
    """The source registry's entry point: an unopened :class:`OakdSource` for ``oakd://...``."""
    opts = parse_url(url)
    if not opts.protocol:
        opts = dataclasses.replace(opts, protocol=config.source.oakd_protocol)
    rot = config.imu.rotation
    custom_rot = None if np.allclose(np.reshape(rot, (3, 3)), np.eye(3)) else rot
    return OakdSource(
        opts, reconnect=config.source.reconnect, imu_rotation=custom_rot, max_skew_ms=config.imu.max_skew_ms
    )
