"""Serial IMU: a documented ASCII line protocol, a background reader, and matching samples to frames.

This module owns everything about an IMU on a serial port (a microcontroller with an accelerometer,
wired over USB-serial or UART): the wire protocol (:func:`format_line` writes it, :class:`LineParser`
reads it), the port reader (:class:`SerialImu`, opened with ``serial.serial_for_url`` so pySerial's
``loop://`` and other URL handlers work like a device), and :class:`ImuMatcher`, which attaches the
samples nearest in time and a low-passed gravity direction to each frame. :class:`ImuStage` wraps
both as a pipeline stage configured by the ``[imu]`` section.

Line protocol (version 1)
-------------------------
One sample per line, NMEA-style, ASCII::

    $IMU,<t_ns>,<ax>,<ay>,<az>,<gx>,<gy>,<gz>*<CS>\\r\\n
    $IMU,<t_ns>,<ax>,<ay>,<az>*<CS>\\r\\n                 (accelerometer only)

* ``t_ns``: integer nanoseconds of the sender's monotonic clock (any epoch; it must only increase).
* ``ax, ay, az``: specific force in m/s^2 in the IMU's axes (at rest it points *up*: a level board
  with z up reads about ``0, 0, +9.81``). Decimal numbers, e.g. ``-0.0123`` or ``9.81e0``.
* ``gx, gy, gz``: angular rate in rad/s (optional as a group).
* ``CS``: two hex digits (either case), the XOR of every byte between ``$`` and ``*`` (exclusive),
  as in NMEA 0183. Lines end in ``\\r\\n`` (a bare ``\\n`` is accepted).
* Lines longer than :data:`MAX_LINE` bytes, lines with a bad checksum, a wrong field count or
  unparsable numbers are counted and skipped. After garbage (noise, a partial line after the reader
  starts mid-stream, another protocol) the parser resynchronises on the next ``$``.

Plausibility
------------
A checksum only proves that the line arrived as it was sent, not that its values are physical. Lines
whose values no IMU reports are skipped and counted (``implausible``): a timestamp that is not an
integer in 0..2**63-1, an acceleration component beyond :data:`MAX_ACCEL` (32 g) or a rate beyond
:data:`MAX_GYRO` (4000 deg/s). Timestamps must advance like the host's clock: a line whose ``t_ns``
is not after the last accepted one, or runs ahead of it by more than :data:`MAX_CLOCK_LEAD_S` beyond
the time that passed on this host, is skipped and counted (``time_rejected``), so one far-future
line cannot stop the reader from accepting the lines after it. A sender that really restarted its
clock is followed once :data:`RESYNC_LINES` consecutive lines agree with each other on the new
timeline (``clock_resyncs``). With ``clock="host"`` a ``t_ns`` later than this host's clock (plus
:data:`MAX_CLOCK_LEAD_S`) is never accepted.

Clocks
------
``clock="device"`` (default): the sender's ``t_ns`` is mapped onto this host's
``time.monotonic_ns()`` by an offset estimated from arrival times (the smallest ``arrival - t_ns``
seen over the last :data:`OFFSET_WINDOW_S` seconds: transport delay only ever adds, so the minimum
is the best estimate, and the sliding window follows slow clock drift). ``clock="host"``: ``t_ns``
already is this host's monotonic clock (a simulator on the same machine). Frames are matched by
their ``t_host_ns``.
"""

from __future__ import annotations

import collections
import logging
import math
import re
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import serial
import serial.tools.list_ports

from illuminet.runtime.config import Config, ConfigError
from illuminet.runtime.errors import SourceError
from illuminet.runtime.frame import Frame, ImuSample
from illuminet.runtime.stage import LogOnce, Stage

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
TALKER = b"IMU"
#: longest line accepted, bytes (a full line with 7 fields of 20 characters is ~160)
MAX_LINE = 256
#: window of the clock-offset minimum filter, seconds
OFFSET_WINDOW_S = 10.0
#: pySerial's loop:// (and small USB FIFOs) block on large writes without a reader: write this much at a time
WRITE_CHUNK = 1024
#: standard gravity, m/s^2
G = 9.80665
#: largest acceleration component accepted, m/s^2 (32 g: beyond every consumer MEMS range; 16 g parts saturate below)
MAX_ACCEL = 32 * G
#: largest angular-rate component accepted, rad/s (4000 deg/s: the widest consumer gyro range)
MAX_GYRO = 70.0
#: a sender's clock may run ahead of this host's by at most this much between two accepted lines, s
MAX_CLOCK_LEAD_S = 1.0
#: this many consecutive lines that agree with each other, but not with the accepted timeline, start a new one
RESYNC_LINES = 20
#: largest timestamp, ns (signed 64-bit, as every clock API holds it)
MAX_T_NS = 2**63 - 1

_T_NS = re.compile(rb"[0-9]{1,19}")
# decimal numbers (nan and inf parse, to be refused as non-finite with that reason)
_NUMBER = re.compile(rb"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?|nan|inf|infinity)", re.IGNORECASE)


class ImuProtocolError(ValueError):
    """One line of the serial IMU protocol is malformed (the message says how)."""


class SerialImuError(SourceError, OSError):
    """The serial IMU's port cannot be opened (exit status 1); an ``OSError`` as before."""


class ImuImplausible(ImuProtocolError):
    """A well-formed line whose values no IMU reports (a timestamp out of range, |a| beyond 32 g, ...)."""


def check_plausible(accel: Sequence[float], gyro: Sequence[float] | None = None, where: str = "") -> None:
    """Raise :class:`ImuImplausible` unless every value is finite and within :data:`MAX_ACCEL` / :data:`MAX_GYRO`."""
    checks = (("acceleration", accel, MAX_ACCEL, "m/s^2"), ("angular rate", gyro, MAX_GYRO, "rad/s"))
    for name, vals, limit, unit in checks:
        if vals is None:
            continue
        for v in vals:
            if not (math.isfinite(v) and abs(v) <= limit):
                raise ImuImplausible(
                    f"{where}{name} {list(vals)!r} is not physical: each component must be finite and within "
                    f"+-{limit:g} {unit}"
                )


# ---------------------------------------------------------------------------------------- protocol


def checksum(payload: bytes) -> int:
    """NMEA-style XOR of all bytes of ``payload`` (the text between ``$`` and ``*``)."""
    cs = 0
    for b in payload:
        cs ^= b
    return cs


def _num(x: float) -> str:
    # repr-like shortest text that round-trips a float32-precision sensor value
    return f"{float(x):.7g}"


def format_line(t_ns: int, accel: Sequence[float], gyro: Sequence[float] | None = None) -> bytes:
    """One protocol line (with checksum and CRLF) for a sample.

    Parameters
    ----------
    t_ns : int
        Sender clock, nanoseconds.
    accel : 3 floats
        Specific force, m/s^2, IMU axes.
    gyro : 3 floats, optional
        Angular rate, rad/s.

    Returns
    -------
    bytes
        e.g. ``b"$IMU,1000,0,0,9.81*4A\\r\\n"``.
    """
    if len(accel) != 3 or (gyro is not None and len(gyro) != 3):
        raise ValueError(f"format_line: accel and gyro need 3 values each, got {accel!r} and {gyro!r}")
    fields = [TALKER.decode(), str(int(t_ns))] + [_num(v) for v in accel]
    if gyro is not None:
        fields += [_num(v) for v in gyro]
    payload = ",".join(fields).encode("ascii")
    return b"$" + payload + b"*" + f"{checksum(payload):02X}".encode() + b"\r\n"


def parse_line(line: bytes) -> ImuSample:
    """Parse one protocol line (with or without the line ending) into an :class:`ImuSample` (IMU axes).

    Raises
    ------
    ImuProtocolError
        Naming what is wrong: start, checksum, talker, field count or a number.
    """
    line = line.strip()
    if not line.startswith(b"$"):
        raise ImuProtocolError(f"line does not start with '$': {line[:40]!r}")
    star = line.rfind(b"*")
    if star < 0 or len(line) - star - 1 != 2:
        raise ImuProtocolError(f"line has no '*XX' checksum at its end: {line[:60]!r}")
    payload, cs_text = line[1:star], line[star + 1 :]
    try:
        cs = int(cs_text, 16)
    except ValueError:
        raise ImuProtocolError(f"checksum {cs_text!r} is not two hex digits") from None
    if cs != checksum(payload):
        raise ImuProtocolError(f"checksum mismatch: line says {cs:02X}, payload XOR is {checksum(payload):02X}")
    fields = payload.split(b",")
    if fields[0] != TALKER:
        raise ImuProtocolError(f"unknown sentence {fields[0]!r}; expected {TALKER!r}")
    if len(fields) not in (5, 8):
        raise ImuProtocolError(
            f"expected 4 fields (t_ns, ax, ay, az) or 7 (… gx, gy, gz) after IMU, got {len(fields) - 1}"
        )
    if not _T_NS.fullmatch(fields[1]):
        raise ImuProtocolError(f"timestamp {fields[1][:24]!r} is not an integer number of nanoseconds")
    bad = [f for f in fields[2:] if not _NUMBER.fullmatch(f)]
    if bad:
        raise ImuProtocolError(f"a field is not a number: {bad[0][:24]!r}")
    t_ns = int(fields[1])
    vals = [float(f) for f in fields[2:]]
    if not all(math.isfinite(v) for v in vals):
        raise ImuImplausible(f"non-finite value in {vals}")
    if t_ns > MAX_T_NS:
        raise ImuImplausible(f"timestamp {t_ns} is beyond 2**63-1 ns")
    gyro = tuple(vals[3:6]) if len(vals) == 6 else None
    check_plausible(vals[0:3], gyro)
    return ImuSample(t_ns=t_ns, accel=(vals[0], vals[1], vals[2]), gyro=gyro)


class LineParser:
    """Incremental parser: feed it bytes as they arrive, get the good samples; counts what it skipped.

    Attributes
    ----------
    good, bad_checksum, malformed, implausible, overlong, garbage_bytes : int
        Counters: samples parsed; lines skipped for a checksum mismatch, for any other format error,
        for values no IMU reports (:class:`ImuImplausible`), for exceeding :data:`MAX_LINE`; bytes
        discarded while looking for the next ``$``.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.good = 0
        self.bad_checksum = 0
        self.malformed = 0
        self.implausible = 0
        self.overlong = 0
        self.garbage_bytes = 0
        self.last_error = ""

    def feed(self, data: bytes) -> list[ImuSample]:
        """Add received bytes; return the samples completed by them, in order."""
        self._buf += data
        out: list[ImuSample] = []
        buf = self._buf
        while True:
            start = buf.find(b"$")
            if start < 0:
                self.garbage_bytes += len(buf)
                buf.clear()
                break
            if start > 0:
                self.garbage_bytes += start
                del buf[:start]
            end = buf.find(b"\n")
            nxt = buf.find(b"$", 1)
            # a '$' before the line end means the line was cut (e.g. a reset mid-line): resync there
            if nxt >= 0 and (end < 0 or nxt < end):
                self.malformed += 1
                self.last_error = f"truncated line {bytes(buf[: min(nxt, 40)])!r}"
                del buf[:nxt]
                continue
            if end < 0:
                if len(buf) > MAX_LINE:
                    self.overlong += 1
                    self.last_error = f"line longer than {MAX_LINE} bytes"
                    del buf[:1]  # drop this '$'; the search resumes at the next one
                    continue
                break  # wait for more bytes
            line = bytes(buf[: end + 1])
            del buf[: end + 1]
            if len(line) > MAX_LINE:
                self.overlong += 1
                self.last_error = f"line longer than {MAX_LINE} bytes"
                continue
            try:
                out.append(parse_line(line))
                self.good += 1
            except ImuProtocolError as e:
                if isinstance(e, ImuImplausible):
                    self.implausible += 1
                elif "checksum mismatch" in str(e):
                    self.bad_checksum += 1
                else:
                    self.malformed += 1
                self.last_error = str(e)
        return out

    def counters(self) -> dict[str, int]:
        return {
            "good": self.good,
            "bad_checksum": self.bad_checksum,
            "malformed": self.malformed,
            "implausible": self.implausible,
            "overlong": self.overlong,
            "garbage_bytes": self.garbage_bytes,
        }


def write_samples(port: Any, samples: Iterable[ImuSample], chunk: int = WRITE_CHUNK) -> int:
    """Write samples in the protocol to an open pySerial port (or any object with ``write``).

    Writes at most ``chunk`` bytes per call: pySerial's ``loop://`` blocks on writes over its 4096-byte
    queue while nobody reads, and small microcontroller FIFOs behave alike.

    Returns
    -------
    int
        Bytes written.
    """
    data = b"".join(format_line(s.t_ns, s.accel, s.gyro) for s in samples)
    for i in range(0, len(data), chunk):
        port.write(data[i : i + chunk])
    return len(data)


# ---------------------------------------------------------------------------------------- matching


def rotation_from_list(values: Sequence[float], where: str = "[imu] rotation") -> np.ndarray:
    """A 3x3 IMU->camera rotation from 9 row-major numbers, checked to be a proper rotation."""
    r = np.asarray(values, dtype=np.float64)
    if r.size != 9:
        raise ValueError(f"{where}: expected 9 numbers (row-major 3x3 rotation), got {r.size}: {list(values)!r}")
    r = r.reshape(3, 3)
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
        raise ValueError(
            f"{where}: {r.tolist()} is not a rotation (R R^T must be I and det(R) = +1); "
            "it maps IMU axes to camera axes (x right, y down, z forward)"
        )
    return r


@dataclass(frozen=True)
class _Entry:
    t_ns: int
    sample: ImuSample  # in camera axes
    lowpass: np.ndarray  # low-passed specific force in camera axes at this time


class ImuMatcher:
    """Keeps recent IMU samples and attaches the ones nearest a frame's time, plus gravity.

    Thread-safe: a reader thread calls :meth:`add`, the loop calls :meth:`attach`.

    Parameters
    ----------
    max_skew_ms : float
        Largest gap between a frame's time and the nearest sample; beyond it the frame gets no IMU data.
    rotation : 3x3 array-like, optional
        IMU axes -> camera axes (OpenCV: x right, y down, z forward). Identity by default.
    tau_s : float
        Time constant of the low-pass filter that separates gravity from motion in the accelerometer.
    keep_s : float
        How much history to keep.
    """

    def __init__(self, max_skew_ms: float = 20.0, rotation: Any = None, tau_s: float = 0.3, keep_s: float = 2.0):
        if max_skew_ms <= 0:
            raise ValueError(f"ImuMatcher: max_skew_ms must be > 0, got {max_skew_ms!r}")
        if tau_s < 0:
            raise ValueError(f"ImuMatcher: tau_s must be >= 0, got {tau_s!r}")
        self.max_skew_ns = int(max_skew_ms * 1e6)
        self.rotation = np.eye(3) if rotation is None else rotation_from_list(np.ravel(rotation), "ImuMatcher rotation")
        self.tau_ns = tau_s * 1e9
        self.keep_ns = int(keep_s * 1e9)
        self._lock = threading.Lock()
        self._entries: collections.deque[_Entry] = collections.deque()
        self._lp: np.ndarray | None = None
        self._last_t: int | None = None
        self._stale_run = 0
        self.matched = 0
        self.unmatched = 0
        self.out_of_order = 0
        self.implausible = 0
        self.timeline_resets = 0

    def add(self, sample: ImuSample) -> None:
        """Add one sample (IMU axes, ``t_ns`` on the frames' clock). Older-than-last samples are dropped.

        Values no IMU reports (non-finite, beyond :data:`MAX_ACCEL` / :data:`MAX_GYRO`) are dropped and
        counted (``implausible``): one such sample would otherwise hold the low-passed gravity at
        zero for minutes. When :data:`RESYNC_LINES` samples in a row are more than ``keep_s`` older
        than the newest one accepted, that one was the outlier (a far-future timestamp) or the clock
        restarted: the history is dropped and the new timeline followed (``timeline_resets``).
        """
        try:
            check_plausible(sample.accel, sample.gyro)
        except ImuImplausible:
            with self._lock:
                self.implausible += 1
            return
        acc = self.rotation @ np.asarray(sample.accel, dtype=np.float64)
        gyro = None if sample.gyro is None else tuple(float(v) for v in self.rotation @ np.asarray(sample.gyro))
        cam = ImuSample(t_ns=int(sample.t_ns), accel=(float(acc[0]), float(acc[1]), float(acc[2])), gyro=gyro)
        with self._lock:
            if self._last_t is not None and cam.t_ns <= self._last_t:
                self.out_of_order += 1  # timestamps must only increase (a resync or a sender reset)
                self._stale_run = self._stale_run + 1 if cam.t_ns < self._last_t - self.keep_ns else 0
                if self._stale_run < RESYNC_LINES:
                    return
                self.timeline_resets += 1  # the newest accepted sample was the outlier: follow the others
                self._entries.clear()
                self._lp = self._last_t = None
            self._stale_run = 0
            if self._lp is None or self.tau_ns == 0:
                lp = acc
            else:
                # first-order low-pass with the real sample spacing (robust to jitter and gaps)
                a = 1.0 - math.exp(-(cam.t_ns - self._last_t) / self.tau_ns)
                lp = self._lp + a * (acc - self._lp)
            self._lp, self._last_t = lp, cam.t_ns
            self._entries.append(_Entry(cam.t_ns, cam, lp))
            while self._entries and self._entries[0].t_ns < cam.t_ns - self.keep_ns:
                self._entries.popleft()

    def match(self, t_ns: int) -> tuple[tuple[ImuSample, ...], np.ndarray | None]:
        """Samples within ``max_skew`` of ``t_ns`` (camera axes) and the gravity unit vector there.

        Gravity is the low-passed specific force of the sample nearest ``t_ns``, negated (at rest the
        accelerometer measures the reaction to gravity, pointing up) and normalised; ``None`` when no
        sample is within ``max_skew`` or the filtered force is ~0 (free fall).
        """
        with self._lock:
            entries = list(self._entries)
        near = [e for e in entries if abs(e.t_ns - t_ns) <= self.max_skew_ns]
        if not near:
            self.unmatched += 1
            return (), None
        best = min(near, key=lambda e: abs(e.t_ns - t_ns))
        n = float(np.linalg.norm(best.lowpass))
        if n < 1e-6:
            return tuple(e.sample for e in near), None
        self.matched += 1
        return tuple(e.sample for e in near), (-best.lowpass / n).astype(np.float32)

    def attach(self, frame: Frame) -> Frame:
        """``frame`` with ``imu`` and ``gravity`` set from the samples nearest ``frame.t_host_ns``.

        A frame that already carries gravity (e.g. from the OAK-D's own IMU) is returned unchanged.
        """
        if frame.gravity is not None:
            return frame
        samples, g = self.match(frame.t_host_ns)
        if not samples:
            return frame
        return frame.replace(imu=samples, gravity=g)


class _OffsetClock:
    """Maps a sender clock to host monotonic ns by a sliding-window minimum of (arrival - sent)."""

    def __init__(self, window_s: float = OFFSET_WINDOW_S):
        self.window_ns = int(window_s * 1e9)
        self._hist: collections.deque[tuple[int, int]] = collections.deque()  # (arrival, offset) increasing offset

    def to_host(self, t_dev: int, arrival: int) -> int:
        off = arrival - t_dev
        h = self._hist
        while h and h[-1][1] >= off:  # monotonic deque: keeps the window minimum at the front
            h.pop()
        h.append((arrival, off))
        while h[0][0] < arrival - self.window_ns:
            h.popleft()
        return t_dev + h[0][1]


class _TimeGate:
    """Accepts a line's timestamp only when it advances like the host's clock since the last accepted one.

    ``accept(t, arrival)``: True when ``t`` is after the last accepted timestamp and ahead of it by at
    most the host time that passed plus ``lead_ns`` (transport delay only makes lines arrive later,
    never earlier, so a sender clock running ahead of the host's is a bad line). Rejected lines that
    agree with each other form a candidate timeline; ``resync_lines`` of them in a row replace the
    accepted timeline (:attr:`resynced` is then set until read), which follows a sender that really
    restarted its clock while one far-off line never moves it.
    """

    def __init__(self, lead_s: float = MAX_CLOCK_LEAD_S, resync_lines: int = RESYNC_LINES):
        self.lead_ns = int(lead_s * 1e9)
        self.resync_lines = int(resync_lines)
        self._last: tuple[int, int] | None = None
        self._cand: tuple[int, int] | None = None
        self._cand_n = 0
        self.rejected = 0
        self.resyncs = 0
        self.resynced = False

    def _follows(self, ref: tuple[int, int], t: int, arrival: int) -> bool:
        return 0 < t - ref[0] <= (arrival - ref[1]) + self.lead_ns

    def accept(self, t: int, arrival: int) -> bool:
        if self._last is None or self._follows(self._last, t, arrival):
            self._last, self._cand, self._cand_n = (t, arrival), None, 0
            return True
        if self._cand is not None and self._follows(self._cand, t, arrival):
            self._cand_n += 1
        else:
            self._cand_n = 1
        self._cand = (t, arrival)
        if self._cand_n >= self.resync_lines:
            self._last, self._cand, self._cand_n = (t, arrival), None, 0
            self.resyncs += 1
            self.resynced = True
            return True
        self.rejected += 1
        return False


# ---------------------------------------------------------------------------------------- the port


class SerialImu:
    """Reads the protocol from a serial port in a background thread and feeds an :class:`ImuMatcher`.

    Parameters
    ----------
    url : str
        Anything ``serial.serial_for_url`` takes: ``/dev/ttyUSB0``, ``COM3``, ``loop://``,
        ``socket://127.0.0.1:7000``, ``rfc2217://...``. A leading ``serial://`` is stripped
        (``serial:///dev/ttyACM0``, ``serial://loop://``), and ``?baud=N`` in it sets the baud rate.
    baudrate : int
        Used unless the URL has ``?baud=``.
    matcher : ImuMatcher, optional
        Where samples go; a default one is created.
    clock : {"device", "host"}
        See the module docstring.
    port : serial.SerialBase, optional
        Use this already-open port (tests share one ``loop://`` port between writer and reader).
    """

    def __init__(
        self,
        url: str,
        baudrate: int = 115200,
        matcher: ImuMatcher | None = None,
        clock: str = "device",
        port: Any = None,
    ):
        if clock not in ("device", "host"):
            raise ValueError(f"SerialImu clock must be 'device' or 'host', got {clock!r}")
        self.url, self.baudrate = parse_serial_url(url, baudrate)
        self.matcher = matcher if matcher is not None else ImuMatcher()
        self.clock = clock
        self.parser = LineParser()
        self._clock = _OffsetClock()
        self._gate = _TimeGate()
        self._log = LogOnce(log, f"serial IMU {self.url}")
        self.future_host_time = 0
        self._port = port
        self._own_port = port is None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.read_errors = 0
        self.last_sample: ImuSample | None = None

    def open(self) -> None:
        """Open the port (unless one was given) and start the reader thread."""
        if self._thread is not None:
            return
        if self._port is None:
            try:
                self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.05)
            except (serial.SerialException, ValueError) as e:
                raise SerialImuError(
                    f"serial IMU: cannot open {self.url!r} at {self.baudrate} baud: {e}. "
                    "Check the device path (`illuminet doctor` lists serial ports) and that you may "
                    "access it (on Linux: be in the 'dialout' group)."
                ) from e
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="illuminet-serial-imu", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        port = self._port
        while not self._stop.is_set():
            try:
                n = port.in_waiting
                data = port.read(n if n > 0 else 1)  # read(1) waits up to the port timeout
            except (serial.SerialException, OSError) as e:
                self.read_errors += 1
                log.error("serial IMU %s: read failed (%s); stopping the IMU reader", self.url, e)
                return
            if not data:
                continue
            arrival = time.monotonic_ns()
            for s in self.parser.feed(data):
                self._accept(s, arrival)

    def _accept(self, s: ImuSample, arrival: int) -> None:
        """Check one parsed sample's timestamp (see the module docstring), map it to the host clock, add it."""
        if self.clock == "host" and s.t_ns > arrival + self._gate.lead_ns:
            self.future_host_time += 1  # stamped later than now on this host's own clock: never valid
            self._log("future", f"a line's host timestamp {s.t_ns} is ahead of this host's clock ({arrival}); skipped")
            return
        if not self._gate.accept(s.t_ns, arrival):
            self._log(
                "time",
                f"a line's timestamp {s.t_ns} does not follow the previous ones (not after them, or ahead of "
                f"this host's clock by more than {MAX_CLOCK_LEAD_S:g} s); skipped",
            )
            return
        if self._gate.resynced:  # the sender restarted its clock: the old offset no longer applies
            self._gate.resynced = False
            self._clock = _OffsetClock()
            log.warning("serial IMU %s: the sender's clock restarted; following the new timeline", self.url)
        t = s.t_ns if self.clock == "host" else self._clock.to_host(s.t_ns, arrival)
        s = ImuSample(t_ns=t, accel=s.accel, gyro=s.gyro)
        self.last_sample = s
        self.matcher.add(s)

    def close(self) -> None:
        """Stop the reader and close the port (if this object opened it). Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._own_port and self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None

    def stats(self) -> dict[str, Any]:
        d = dict(self.parser.counters())
        d.update(
            matched=self.matcher.matched,
            unmatched=self.matcher.unmatched,
            out_of_order=self.matcher.out_of_order,
            time_rejected=self._gate.rejected + self.future_host_time,
            clock_resyncs=self._gate.resyncs,
            read_errors=self.read_errors,
        )
        return d

    def __enter__(self) -> SerialImu:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def parse_serial_url(url: str, baudrate: int = 115200) -> tuple[str, int]:
    """``serial://PORT_OR_URL?baud=N`` -> (what ``serial_for_url`` takes, baud rate).

    ``serial:///dev/ttyUSB0?baud=921600`` -> ``("/dev/ttyUSB0", 921600)``; ``serial://loop://`` ->
    ``("loop://", baudrate)``; a URL without ``serial://`` is passed through (``/dev/ttyACM0``,
    ``loop://``). Other query parameters are left for pySerial's own URL handlers.
    """
    if not url:
        raise ValueError("serial IMU URL is empty; expected e.g. serial:///dev/ttyUSB0?baud=115200 or loop://")
    rest = url[len("serial://") :] if url.startswith("serial://") else url
    if "?" in rest:
        base, query = rest.split("?", 1)
        keep = []
        for item in query.split("&"):
            k, _, v = item.partition("=")
            if k == "baud":
                try:
                    baudrate = int(v)
                except ValueError:
                    raise ValueError(f"serial URL {url!r}: baud must be an integer, got {v!r}") from None
            elif item:
                keep.append(item)
        rest = base + ("?" + "&".join(keep) if keep else "")
    if not rest:
        raise ValueError(f"serial URL {url!r} names no port; expected e.g. serial:///dev/ttyUSB0")
    if baudrate <= 0:
        raise ValueError(f"serial URL {url!r}: baud rate must be positive, got {baudrate}")
    return rest, int(baudrate)


def list_ports() -> list[dict[str, str]]:
    """Serial ports on this machine: ``[{"device", "description", "hwid"}]`` (for ``illuminet doctor``)."""
    return [
        {"device": p.device, "description": p.description or "", "hwid": p.hwid or ""}
        for p in serial.tools.list_ports.comports()
    ]


# ---------------------------------------------------------------------------------------- the stage


class ImuStage(Stage):
    """Pipeline stage: attaches serial-IMU samples and gravity to each frame (``[imu]`` config).

    Put it first in the stage list. Frames that already carry gravity (OAK-D's IMU) pass unchanged.
    """

    name = "imu"

    def __init__(self, reader: SerialImu):
        self.reader = reader

    @classmethod
    def from_config(cls, cfg: Config) -> ImuStage | None:
        """The stage for ``[imu] url``, or ``None`` when no serial IMU is configured."""
        sec = cfg.imu
        if not sec.url:
            return None
        try:
            matcher = ImuMatcher(
                max_skew_ms=sec.max_skew_ms, rotation=rotation_from_list(sec.rotation), tau_s=sec.gravity_tau_s
            )
            return cls(SerialImu(sec.url, baudrate=sec.baudrate, matcher=matcher, clock=sec.clock))
        except ValueError as e:  # a malformed URL or a rotation that is not one: a configuration mistake
            raise ConfigError(f"[imu] {'rotation' if 'rotation' in str(e) else 'url'}: {e}") from None

    def open(self) -> None:
        self.reader.open()

    def process(self, frame: Frame) -> Frame:
        return self.reader.matcher.attach(frame)

    def close(self) -> None:
        self.reader.close()

    def stats(self) -> dict[str, Any]:
        return self.reader.stats()
