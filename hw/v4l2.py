"""V4L2 stereo source: a side-by-side stereo UVC camera, or two cameras, with depth computed on the host.

This module owns capturing from Linux video devices through OpenCV's ``CAP_V4L2`` backend and
turning stereo pairs into RGB-D frames. URL syntax::

    v4l2:///dev/video0?stereo=sbs                 one UVC camera delivering left|right side by side
    v4l2:///dev/video0?right=/dev/video2          two cameras (left = the URL's device)
    v4l2:///dev/video0?stereo=sbs&size=2560x720&fps=30&fourcc=MJPG&calib=rig.json

Query parameters: see :class:`V4l2Options`. Depth needs the pair's calibration file (``?calib=PATH``
or ``[source] calibration``; written by ``illuminet calibrate stereo``); it is computed by
:class:`illuminet.calibration.stereo.HostStereo` (rectify, SGBM, WLS) and aligned to the rectified
left image, which becomes the frame's colour.

A single (mono) camera is refused: the pipeline finds planes in depth, and one camera gives none.

Structure (so that everything but the device is testable with recorded frames):

* :class:`CaptureBackend` -- the interface to one device: ``open``, ``grab`` (latch a frame; cheap, so
  two devices are latched as close in time as possible), ``retrieve`` (decode it), ``close``.
  :class:`OpenCvCapture` implements it with ``cv2.VideoCapture(..., cv2.CAP_V4L2)``; tests give
  their own backend that plays numpy frames.
* :func:`split_sbs` -- one side-by-side image -> (left, right).
* :class:`StereoGrabber` -- one SBS backend or two backends -> a (left, right, timestamp) pair.
* :class:`V4l2Source` -- pairs -> :class:`~illuminet.runtime.frame.Frame` through ``HostStereo``;
  counts dropped frames from timestamp gaps, skips bad frames, reconnects with backoff.
"""

from __future__ import annotations

import glob
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol
from urllib.parse import urlsplit

import cv2
import numpy as np

from illuminet.hw import parse_query, query_bool, query_choice, query_float, query_int, query_size
from illuminet.runtime.config import Config
from illuminet.runtime.errors import SourceError
from illuminet.runtime.frame import Exposure, Frame
from illuminet.runtime.stage import EndOfStream, Source

log = logging.getLogger(__name__)


class V4l2Error(SourceError):
    """A V4L2 device or URL cannot be used; the message says why and what to do."""


MONO_REFUSAL = (
    "{url} names a single (mono) camera (no ?stereo= or ?right=): depth is required to find planes, "
    "and one camera gives none. "
    "Use a stereo camera with its calibration file (a side-by-side UVC camera: v4l2://{dev}?stereo=sbs, "
    "or two cameras: v4l2://{dev}?right=/dev/videoN; calibration via ?calib=PATH or [source] calibration, "
    "see `illuminet calibrate stereo`), an OAK-D (oakd://), or a recording (replay://PATH)."
)


# ---------------------------------------------------------------------------------------- options


@dataclass(frozen=True)
class V4l2Options:
    """What ``v4l2://DEVICE?key=value&...`` asks for.

    Attributes
    ----------
    device : str
        Left (or the side-by-side) camera: ``/dev/videoN`` (or an index ``N``).
    stereo : str
        ``"sbs"`` (one device, left|right halves), ``"pair"`` (two devices; implied by ``right=``) or
        ``""`` (mono: refused).
    right : str
        Right camera for ``stereo=pair``.
    size : (int, int) or None
        Capture size requested from the driver (the whole side-by-side image for ``sbs``).
    fps : float or None
        Frame rate requested from the driver.
    fourcc : str
        Pixel format requested, e.g. ``MJPG`` (most UVC cameras need it for high resolutions) or ``YUYV``.
    swap : bool
        ``sbs``: the left camera's image is the right half.
    calib : str
        Calibration file (overrides ``[source] calibration``).
    exposure_us : int
        Manual exposure in microseconds (0 = the camera's auto exposure); reported in ``Frame.exposure``.
    scale : float
        Stereo matching resolution relative to the image (HostStereo's ``scale``).
    reconnect : bool or None
        Override ``[source] reconnect``.
    """

    device: str
    stereo: str = ""
    right: str = ""
    size: tuple[int, int] | None = None
    fps: float | None = None
    fourcc: str = ""
    swap: bool = False
    calib: str = ""
    exposure_us: int = 0
    scale: float = 0.5
    reconnect: bool | None = None


def _fourcc(value: str) -> str:
    if len(value) != 4:
        raise ValueError("expected four characters, e.g. MJPG or YUYV")
    return value.upper()


def parse_url(url: str) -> V4l2Options:
    """``v4l2://DEVICE?...`` -> :class:`V4l2Options`; unknown keys and bad values are refused by name."""
    parts = urlsplit(url)
    if parts.scheme != "v4l2":
        raise ValueError(f"{url!r} is not a v4l2:// URL")
    device = parts.netloc + parts.path
    if not device:
        raise ValueError(f"{url}: no device; expected e.g. v4l2:///dev/video0?stereo=sbs")
    kw: dict[str, Any] = parse_query(
        url,
        {
            "stereo": query_choice("sbs", "pair"),
            "right": str,
            "size": query_size(),
            "fps": query_float,
            "fourcc": _fourcc,
            "swap": query_bool,
            "calib": str,
            "exposure_us": query_int(),
            "scale": query_float,
            "reconnect": query_bool,
        },
    )
    kw["device"] = device
    if kw.get("right") and kw.get("stereo", "pair") != "pair":
        raise ValueError(f"{url}: right= names a second camera, which contradicts stereo={kw['stereo']}")
    if kw.get("right"):
        kw["stereo"] = "pair"
    if kw.get("stereo") == "pair" and not kw.get("right"):
        raise ValueError(f"{url}: stereo=pair needs right=/dev/videoN (the right camera)")
    if kw.get("fps") is not None and kw["fps"] <= 0:
        raise ValueError(f"{url}: fps must be positive")
    if not 0.1 <= kw.get("scale", 0.5) <= 1.0:
        raise ValueError(f"{url}: scale={kw['scale']}: expected 0.1..1")
    return V4l2Options(**kw)


# ---------------------------------------------------------------------------------------- capture


class CaptureBackend(Protocol):
    """One video device. ``grab`` latches the next frame, ``retrieve`` decodes the latched one."""

    name: str

    def open(self) -> None: ...

    def grab(self) -> bool: ...

    def retrieve(self) -> tuple[np.ndarray | None, int | None]:
        """(BGR uint8 image or None, device timestamp ns or None)."""
        ...

    def close(self) -> None: ...


def _device_arg(device: str) -> int | str:
    return int(device) if device.isdigit() else device


class OpenCvCapture:
    """:class:`CaptureBackend` over ``cv2.VideoCapture(device, cv2.CAP_V4L2)``.

    The driver queue is set to one buffer so that a grab returns a recent picture rather than one
    that waited in the queue (the loop wants the newest frame, not every frame).
    """

    def __init__(
        self,
        device: str,
        size: tuple[int, int] | None = None,
        fps: float | None = None,
        fourcc: str = "",
        exposure_us: int = 0,
    ):
        self.name = device
        self.size, self.fps, self.fourcc, self.exposure_us = size, fps, fourcc, exposure_us
        self._cap: Any = None

    def open(self) -> None:
        if isinstance(_device_arg(self.name), str) and not os.path.exists(self.name):
            raise V4l2Error(f"video device {self.name} does not exist; `illuminet doctor` lists the V4L2 devices")
        cap = cv2.VideoCapture(_device_arg(self.name), cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise V4l2Error(
                f"cannot open {self.name} with V4L2: busy (another program uses it), not a capture device, "
                "or no permission (on Linux: be in the 'video' group)"
            )
        if self.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.fourcc))
        if self.size:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.size[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])
        if self.fps:
            cap.set(cv2.CAP_PROP_FPS, self.fps)
        if self.exposure_us > 0:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2_EXPOSURE_MANUAL
            cap.set(cv2.CAP_PROP_EXPOSURE, self.exposure_us / 100.0)  # UVC: units of 100 us
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if self.size:
            got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if got != tuple(self.size):
                log.warning("%s: asked for %dx%d, the driver gives %dx%d", self.name, *self.size, *got)
        self._cap = cap

    def grab(self) -> bool:
        return bool(self._cap is not None and self._cap.grab())

    def retrieve(self) -> tuple[np.ndarray | None, int | None]:
        ok, img = self._cap.retrieve()
        if not ok:
            return None, None
        ms = self._cap.get(cv2.CAP_PROP_POS_MSEC)  # the V4L2 buffer timestamp (monotonic clock)
        return img, (int(ms * 1e6) if ms and ms > 0 else None)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def split_sbs(image: np.ndarray, swap: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Split a side-by-side stereo image into (left, right) halves (views, no copy).

    Raises
    ------
    ValueError
        When the image is not HxW(x3) or its width is odd (not a side-by-side pair).
    """
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        got = getattr(image, "shape", type(image))
        raise ValueError(f"side-by-side frame must be an HxW or HxWx3 array, got {got}")
    w = image.shape[1]
    if w % 2:
        raise ValueError(f"side-by-side frame width {w} is odd: not a left|right pair (is this a mono camera?)")
    a, b = image[:, : w // 2], image[:, w // 2 :]
    return (b, a) if swap else (a, b)


class StereoGrabber:
    """Left/right pairs from one side-by-side backend or from two backends.

    With two devices both are latched (``grab``) before either is decoded (``retrieve``), which keeps
    the two exposures as close in time as the drivers allow.
    """

    def __init__(self, left: CaptureBackend, right: CaptureBackend | None = None, swap: bool = False):
        self.left, self.right, self.swap = left, right, swap

    def open(self) -> None:
        self.left.open()
        if self.right is not None:
            try:
                self.right.open()
            except Exception:
                self.left.close()
                raise

    def close(self) -> None:
        for b in (self.left, self.right):
            if b is not None:
                b.close()

    def grab(self) -> bool:
        """Latch the next pair; False when a device delivered nothing (disconnected or stalled)."""
        ok = self.left.grab()
        if self.right is not None:
            ok = self.right.grab() and ok
        return ok

    def retrieve(self) -> tuple[np.ndarray, np.ndarray, int | None]:
        """(left BGR, right BGR, device timestamp ns or None). Raises ValueError on a bad frame."""
        img, t = self.left.retrieve()
        if img is None:
            raise ValueError(f"{self.left.name}: no image in the grabbed frame")
        if self.right is None:
            left, right = split_sbs(img, self.swap)
        else:
            rimg, _ = self.right.retrieve()
            if rimg is None:
                raise ValueError(f"{self.right.name}: no image in the grabbed frame")
            left, right = img, rimg
            if left.shape != right.shape:
                raise ValueError(
                    f"left {left.shape} and right {right.shape} images differ in size; "
                    "set the same size= for both cameras"
                )
        return left, right, t


# ---------------------------------------------------------------------------------------- the source


def _host_stereo(calib_path: str, size: tuple[int, int], scale: float):
    """HostStereo for ``size`` (per-eye width, height) from a calibration file (imported when needed)."""
    from illuminet.calibration.calibfile import load_calibration
    from illuminet.calibration.stereo import HostStereo

    return HostStereo(load_calibration(calib_path), image_size=size, scale=scale)


class V4l2Source(Source):
    """Live RGB-D frames from a V4L2 stereo camera (see the module docstring).

    Parameters
    ----------
    grabber : StereoGrabber
        The devices (or any backends, e.g. recorded frames in tests).
    calib_path : str
        Stereo calibration file.
    scale : float
        HostStereo matching scale.
    reconnect : bool
        Reopen lost devices with exponential backoff instead of ending the stream.
    exposure_us : int
        Manual exposure set on the device (0 = auto: exposure unknown).
    stereo_factory : callable, optional
        ``(calib_path, (w, h), scale) -> HostStereo``; the default loads the calibration file.
    max_failures : int
        Consecutive empty grabs that mean the device is lost.
    max_bad_frames : int
        Consecutive unusable frames (see :meth:`read`) that end the stream with an error: a fault that
        hits every frame (two cameras of different sizes, a mono camera's odd-width image) is not
        transient.
    """

    name = "v4l2"
    live = True

    BACKOFF_START_S = 0.5
    BACKOFF_MAX_S = 10.0

    def __init__(
        self,
        grabber: StereoGrabber,
        calib_path: str,
        scale: float = 0.5,
        reconnect: bool = True,
        exposure_us: int = 0,
        stereo_factory: Callable[..., Any] | None = None,
        max_failures: int = 10,
        max_bad_frames: int = 30,
    ):
        self.grabber = grabber
        self.calib_path = calib_path
        self.scale = scale
        self.reconnect = reconnect
        self.exposure_us = exposure_us
        self._stereo_factory = stereo_factory or _host_stereo
        self._stereo = None
        self._stereo_size: tuple[int, int] | None = None
        self.max_failures = max_failures
        self.max_bad_frames = max_bad_frames
        self._open = False
        self._stop = threading.Event()
        # held around grab/retrieve: close() must not release the devices under a grab in progress
        # (OpenCV's V4L2 backend frees the buffers a blocked grab is using: a crash at exit)
        self._io = threading.RLock()
        self._release_after_grab = False
        self._seq = 0
        self._last_t: int | None = None
        self._period_ns: float | None = None
        self.dropped = 0
        self.bad_frames = 0
        self.reconnects = 0

    def open(self) -> None:
        self._stop.clear()
        self.grabber.open()
        self._open = True

    #: close() waits this long for a grab in progress (a stalled camera blocks one for up to 10 s);
    #: after that the reading thread releases the devices itself when its grab returns
    CLOSE_WAIT_S = 1.0

    def close(self) -> None:
        self._stop.set()
        if not self._io.acquire(timeout=self.CLOSE_WAIT_S):
            self._release_after_grab = True
            log.info("V4L2 camera %s: a grab is in progress; it is released when it returns", self.grabber.left.name)
            return
        try:
            self._release()
        finally:
            self._io.release()

    def _release(self) -> None:
        self._release_after_grab = False
        if self._open:
            self.grabber.close()
            self._open = False

    def _lost(self, why: str) -> None:
        """Handle a lost device: raise EndOfStream, or reopen with backoff until it works or close()."""
        with self._io:
            self.grabber.close()
            self._open = False
        if not self.reconnect:
            raise EndOfStream(
                f"V4L2 camera {self.grabber.left.name} lost: {why}. Reconnect it and run again, "
                "or enable [source] reconnect."
            )
        delay = self.BACKOFF_START_S
        while not self._stop.is_set():
            self.reconnects += 1
            log.warning(
                "V4L2 camera %s lost (%s); reopening in %.1f s (attempt %d)",
                self.grabber.left.name,
                why,
                delay,
                self.reconnects,
            )
            if self._stop.wait(delay):
                return
            try:
                with self._io:  # not while close() releases the devices
                    if self._stop.is_set():
                        return
                    self.grabber.open()
                    self._open = True
                self._last_t = None
                return
            except (V4l2Error, OSError, cv2.error) as e:
                why = str(e)
                delay = min(delay * 2, self.BACKOFF_MAX_S)

    def _count_drops(self, t_ns: int) -> None:
        # frames the driver delivered that nobody grabbed show up as gaps of whole frame periods
        if self._last_t is not None:
            dt = t_ns - self._last_t
            if dt > 0:
                if self._period_ns is None:
                    self._period_ns = float(dt)
                elif dt > 1.5 * self._period_ns:
                    self.dropped += int(round(dt / self._period_ns)) - 1
                else:
                    self._period_ns = 0.9 * self._period_ns + 0.1 * dt
        self._last_t = t_ns

    def read(self) -> Frame | None:
        """The next RGB-D frame (rectified left colour + aligned depth); ``None`` after :meth:`close`."""
        failures = bad_run = 0
        while not self._stop.is_set():
            if not self._open:
                self._lost("not open")
                continue
            with self._io:
                if self._stop.is_set():
                    break
                grabbed = self.grabber.grab()
                t_host = time.monotonic_ns()
                try:
                    pair = self.grabber.retrieve() if grabbed else None
                except ValueError as e:
                    pair = e
                if self._release_after_grab:  # close() gave up waiting for this grab
                    self._release()
                    break
            if not grabbed:
                failures += 1
                if failures >= self.max_failures:
                    self._lost(f"{failures} grabs in a row returned nothing")
                    failures = 0
                continue
            failures = 0
            try:
                if isinstance(pair, ValueError):
                    raise pair
                left, right, t_dev = pair
                frame = self._to_frame(left, right, t_dev, t_host)
            except ValueError as e:  # one bad frame: counted and skipped, the stream goes on
                self.bad_frames += 1
                bad_run += 1
                if bad_run >= self.max_bad_frames:
                    raise V4l2Error(
                        f"V4L2 camera {self.grabber.left.name}: {bad_run} frames in a row could not be used: {e}"
                    ) from e
                log.warning("V4L2 %s: skipped a bad frame: %s", self.grabber.left.name, e)
                continue
            return frame
        return None

    def _to_frame(self, left: np.ndarray, right: np.ndarray, t_dev: int | None, t_host: int) -> Frame:
        size = (left.shape[1], left.shape[0])
        if self._stereo is None or self._stereo_size != size:
            try:
                self._stereo = self._stereo_factory(self.calib_path, size, self.scale)
            except ValueError as e:
                if self._stereo is not None:  # one odd-sized frame of a camera that worked: skip it
                    raise ValueError(f"a {size[0]}x{size[1]} frame does not fit the calibration: {e}") from e
                # a calibration that cannot serve this camera (no stereo pair, another aspect ratio, a
                # malformed file) fails the same way on every frame: an error, not a skipped frame
                raise V4l2Error(
                    f"V4L2 camera {self.grabber.left.name}: the calibration {self.calib_path} cannot be used "
                    f"for its {size[0]}x{size[1]} images: {e}"
                ) from e
            self._stereo_size = size
        rgb, depth = self._stereo.compute(left, right)
        t = t_dev if t_dev is not None else t_host
        self._count_drops(t)
        exposure = Exposure(exposure_us=float(self.exposure_us)) if self.exposure_us > 0 else Exposure()
        seq = self._seq
        self._seq += 1
        return Frame(
            seq=seq,
            t_device_ns=int(t),
            t_host_ns=int(t_host),
            color=np.ascontiguousarray(rgb),
            depth=np.ascontiguousarray(depth, dtype=np.float32),
            intrinsics=self._stereo.intrinsics,
            exposure=exposure,
        )

    def stats(self) -> dict[str, Any]:
        return {"dropped": self.dropped, "bad_frames": self.bad_frames, "reconnects": self.reconnects}


# ---------------------------------------------------------------------------------------- registry


def open_url(url: str, config: Config) -> V4l2Source:
    """The source registry's entry point: an unopened :class:`V4l2Source` for ``v4l2://...``.

    Raises
    ------
    V4l2Error
        For a mono camera (no ``stereo=``/``right=``) or a stereo camera without a calibration file.
    """
    o = parse_url(url)
    if not o.stereo:
        raise V4l2Error(MONO_REFUSAL.format(url=url, dev=o.device))
    calib = o.calib or config.source.calibration
    if not calib:
        raise V4l2Error(
            f"{url}: depth on the host needs the stereo pair's calibration file: add ?calib=PATH or set "
            "[source] calibration (create one with `illuminet calibrate stereo`)"
        )
    if not os.path.isfile(calib):
        # a folder or a device was also "not found", sending the user looking for a file that is there
        what = "is not a file (a folder or a device?)" if os.path.exists(calib) else "not found"
        raise V4l2Error(f"{url}: calibration file {calib} {what}; expected the JSON of `illuminet calibrate stereo`")
    left = OpenCvCapture(o.device, o.size, o.fps, o.fourcc, o.exposure_us)
    right = OpenCvCapture(o.right, o.size, o.fps, o.fourcc, o.exposure_us) if o.stereo == "pair" else None
    reconnect = o.reconnect if o.reconnect is not None else config.source.reconnect
    return V4l2Source(
        StereoGrabber(left, right, swap=o.swap), calib, scale=o.scale, reconnect=reconnect, exposure_us=o.exposure_us
    )


def list_devices() -> list[dict[str, str]]:
    """V4L2 devices: ``[{"device": "/dev/video0", "name": ..., "index": "0"}]`` from /dev and sysfs.

    Reads names from ``/sys/class/video4linux`` rather than opening the devices (opening can take
    seconds and disturbs a camera another program is using).
    """
    out = []
    for dev in sorted(glob.glob("/dev/video*"), key=lambda p: (len(p), p)):
        base = os.path.basename(dev)
        name = ""
        try:
            with open(f"/sys/class/video4linux/{base}/name", encoding="utf-8", errors="replace") as f:
                name = f.read().strip()
        except OSError:
            pass
        idx = ""
        try:
            with open(f"/sys/class/video4linux/{base}/index", encoding="utf-8") as f:
                idx = f.read().strip()
        except OSError:
            pass
        out.append({"device": dev, "name": name, "index": idx})
    return out
