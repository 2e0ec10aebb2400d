"""Recorded sessions: the on-disk format, a crash-safe writer and a validating reader.

This module owns the session format (``illuminet-session``, versions 1 and 2). The full specification
is in ``docs/runtime.md``; in short a session is a folder::

    SESSION/
      manifest.json      format name + version, created (UTC), source URL, intrinsics, image size,
                         colour/depth encodings; rewritten atomically (``finalized`` on clean close)
      frames.jsonl       the index: one JSON object per line per *complete* frame, append-only
      frames/
        000000.color.rgb   colour, RGB: raw bytes (default, lossless) | .color.png (lossless) | .color.jpg
        000000.depth.png   depth, 16-bit PNG, millimetres, 0 = invalid (always lossless)
        ...
      estimates.jsonl    optional sidecar: the lighting estimate the recording run computed for a
                         frame, one line ``{"i": N, "estimate": {...}}`` after that frame's index line
                         (docs/estimate.md); readers without it, or older readers, ignore it

Version 2 is version 1 plus one optional manifest key, ``depth.scale`` (an integer k >= 1): the
depth images are stored at ``width/k x height/k`` -- the resolution a stereo camera such as the
OAK-D computes depth at (640x400 for 1280x800 colour) -- and the reader upsamples them (nearest
neighbour, so 0 = invalid stays invalid and no depth is invented between surfaces) back to the
colour size, which :class:`~illuminet.runtime.frame.Frame` requires. A writer writes version 1
unless it stores depth at a reduced scale, so ordinary recordings stay readable by version-1 readers;
those refuse a version-2 session by name instead of misreading it.

Crash safety
    :meth:`SessionWriter.append` writes (and fsyncs) a frame's image files *first*, then appends one
    line to ``frames.jsonl`` with a single ``write`` and fsyncs it. The index line is the commit
    point: after ``kill -9`` (or a power cut, thanks to the fsyncs) every frame whose line is complete
    replays; files without a line and a torn last line are ignored by the reader with a warning.

Validation
    :class:`SessionReader` names what is wrong -- missing manifest or file, unknown format or version,
    a torn or malformed index line, a file shorter/longer than the index says (truncated frame), an
    image whose size differs from the manifest, an undecodable image, timestamps going backwards, a
    path that would leave the session folder (absolute, ``..``, symlink out) -- and replays the intact
    frames. ``strict=True`` raises :class:`SessionError` instead. Only JSON, PNG/JPEG and raw bytes are
    read: no pickle anywhere.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import stat
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from illuminet.runtime.frame import Exposure, Frame, ImuSample, Intrinsics, depth_to_mm
from illuminet.runtime.imageheader import image_size

log = logging.getLogger(__name__)

#: value of ``manifest["format"]``
FORMAT_NAME = "illuminet-session"
#: version this build writes for ordinary sessions (depth at colour size)
FORMAT_VERSION = 1
#: version written when depth is stored at a reduced scale (manifest ``depth.scale`` > 1)
FORMAT_VERSION_DEPTH_SCALE = 2
#: versions this build reads
SUPPORTED_VERSIONS = (1, 2)
MANIFEST = "manifest.json"
INDEX = "frames.jsonl"
#: the optional sidecar of per-frame lighting estimates (no format version change: readers that do
#: not know it never open it, and a session without it is complete)
ESTIMATES = "estimates.jsonl"
FRAMES_DIR = "frames"
#: timestamps are nanoseconds in a signed 64-bit integer (what numpy and the recorder use)
MAX_TIMESTAMP_NS = 2**63 - 1
#: a jump between consecutive frames' timestamps larger than this is a gap (a corrupt or edited
#: index, a paused device), not time to wait: replay with recorded timing waits one frame period
#: instead, and ``replay --check`` reports it
MAX_FRAME_GAP_NS = 5_000_000_000
#: colour encodings: raw (uncompressed RGB bytes, lossless, default), PNG (lossless), JPEG (lossy, small)
COLOR_ENCODINGS = ("png", "jpeg", "raw")
_COLOR_EXT = {"png": ".color.png", "jpeg": ".color.jpg", "raw": ".color.rgb"}
#: default zlib level for colour PNGs. PNG settings were measured on noisy 640x400 camera-like frames
#: (docs/runtime.md has the table): colour with the fast filter set (none/sub/up, no Paeth, whose
#: un-filtering is the slowest part of decoding) and Huffman-only coding: 358 kB, encode 7 ms, decode
#: 3.4 ms, vs OpenCV's defaults 428 kB, 27 ms, 4.2 ms. Depth (16-bit) with no filter and Huffman-only:
#: 306 kB, encode 4.6 ms, decode 2.2 ms, vs 329 kB, 15 ms, 3.6 ms. Higher levels cost encode time for a few %.
DEFAULT_PNG_COMPRESSION = 1


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import SessionError  # noqa: E402,F401


class CorruptFrame(SessionError):
    """One frame of an otherwise readable session cannot be decoded (the others can still replay)."""


# --------------------------------------------------------------------------------------------------
# helpers


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _fsync_dir(path: Path) -> None:
    # the directory entry of a new/renamed file is only durable once the directory itself is synced
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


# fdatasync skips the inode's timestamps (not needed to read the data back); Linux has it, macOS not
_datasync = getattr(os, "fdatasync", os.fsync)


def _write_file(path: Path, data: bytes, fsync: bool) -> None:
    """Write ``data`` to a new ``path``; a write that fails (disk full, RLIMIT_FSIZE) removes the cut file,
    which was left behind (a cut first frame in frames/ that no index line names)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    done = False
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        if fsync:
            _datasync(fd)
        done = True
    finally:
        os.close(fd)
        if not done:
            with contextlib.suppress(OSError):
                os.unlink(path)


def _atomic_write_json(path: Path, obj: Any, fsync: bool = True) -> None:
    """Write JSON to ``path`` so that a reader sees either the old or the new file, never half of one
    (and no ``.tmp`` file is left when the write fails: a full disk left ``manifest.json.tmp``)."""
    tmp = path.with_name(path.name + ".tmp")
    _write_file(tmp, (json.dumps(obj, indent=2) + "\n").encode("utf-8"), fsync)
    try:
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if fsync:
        _fsync_dir(path.parent)


def printable(text: str) -> str:
    """``text`` with every non-printable character escaped (``\\x1b``): a session's strings reach the
    terminal in problem lines, and a file name or source holding escape sequences could clear the screen
    or print a fake "OK"."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def safe_relpath(root: Path, rel: Any, what: str) -> Path:
    """Resolve ``rel`` inside the session folder ``root`` or raise :class:`SessionError`.

    Session files name their parts by relative POSIX paths. Anything that could reach outside the
    folder is refused before it is opened: absolute paths, drive letters, backslashes, ``..``
    components, and symlinks that resolve outside ``root``.
    """
    if not isinstance(rel, str) or not rel:
        raise SessionError(f"{what}: expected a relative path inside the session folder, got {rel!r}")
    p = PurePosixPath(rel)
    if p.is_absolute() or "\\" in rel or (len(rel) > 1 and rel[1] == ":") or ".." in p.parts:
        raise SessionError(
            f"{what}: path {rel!r} escapes the session folder {root}; only relative paths without '..' are allowed"
        )
    if "\x00" in rel:
        raise SessionError(f"{what}: path {rel!r} contains a NUL byte; not a file name")
    full = root.joinpath(*p.parts)
    try:
        inside = full.resolve().is_relative_to(root.resolve())
    except UnicodeEncodeError:  # a lone surrogate ("\ud800" in the JSON) is no file name on a UTF-8 system
        raise SessionError(f"{what}: path {rel!r} is not a valid file name (not encodable as UTF-8)") from None
    except (OSError, RuntimeError) as e:  # a symlink loop (RuntimeError before Python 3.13, OSError after)
        raise SessionError(f"{what}: path {rel!r} cannot be resolved ({e}); a symlink loop?") from None
    if not inside:
        raise SessionError(f"{what}: path {rel!r} resolves outside the session folder {root} (symlink?)")
    return full


def _png_color_params(level: int) -> list[int]:
    return [
        cv2.IMWRITE_PNG_COMPRESSION,
        int(level),
        cv2.IMWRITE_PNG_FILTER,
        cv2.IMWRITE_PNG_FAST_FILTERS,
        cv2.IMWRITE_PNG_STRATEGY,
        cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
    ]


#: 16-bit depth: unfiltered Huffman-only is both smaller and faster than filtering (noise defeats filters)
_PNG_DEPTH_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_NONE,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
]
# OpenCV >= 4.10 decodes straight to RGB (saves a colour conversion per frame)
_IMREAD_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)


# --------------------------------------------------------------------------------------------------
# writer


@dataclass(frozen=True)
class EncodedFrame:
    """A frame with its image files already compressed (:meth:`SessionWriter.encode`)."""

    frame: Frame
    color: bytes
    depth: bytes | None


def session_hint(path: str | os.PathLike) -> str:
    """For a path that is not a session: ``"; the session is S: give that folder"`` when it is a file
    or folder inside session S (``S/manifest.json``, ``S/frames``), ``"; it holds the sessions a, b:
    give one of them"`` for a folder of sessions, else ``""``."""
    path = Path(path)
    for d in path.parents if path.exists() else ():
        if (d / MANIFEST).is_file():
            return f"; the session is {d}: give that folder"
    try:
        inside = sorted(c.name for c in path.iterdir() if (c / MANIFEST).is_file()) if path.is_dir() else []
    except OSError:
        inside = []
    if inside:
        listed = ", ".join(inside[:3]) + (f" and {len(inside) - 3} more" if len(inside) > 3 else "")
        return f"; it holds the session(s) {listed}: give one of them, e.g. {path / inside[0]}"
    return ""


class SessionWriter:
    """Append frames to a new session folder, crash-safely (see the module docstring).

    Parameters
    ----------
    path : str or Path
        The session folder; created. It must be new or empty: not a session (no silent overwrite), nor
        a folder holding other files (the session's would mix with them).
    source : str
        URL of the source being recorded, stored in the manifest.
    color : {"raw", "png", "jpeg"}
        Colour encoding: raw RGB bytes (default: lossless, the least CPU to write and to replay), lossless
        PNG (~40 % smaller on camera images, ~2.4x the replay CPU), or JPEG at ``jpeg_quality``.
    jpeg_quality : int
        1..100, for ``color="jpeg"``.
    png_compression : int
        zlib level 0..9 for colour PNGs (depth always uses level 1: lossless, fast).
    fsync : bool
        fsync every file and index line (durable against power loss, not only process kills). Turning
        it off keeps ``kill -9`` safety (the page cache survives the process) and saves ~ms per frame.
    depth_scale : int
        Store depth at ``1/depth_scale`` of the colour size (format version 2; 1 = at colour size,
        version 1). The stored pixel of each ``k x k`` block is its top-left one (no averaging across
        depth edges, 0 = invalid kept), which nearest-neighbour upsampling on replay puts back in place.
        The colour width and height must be multiples of it.
    depth_png_compression : int
        zlib level 0..9 of the depth PNGs (default 1: Huffman-only, fast; 9 adds LZ77 matching and is
        ~2.3x smaller on 640x400 synthetic depth, for sessions committed to a repository).
    meta : dict, optional
        JSON-serialisable description stored as the manifest's ``meta`` key (e.g. the command and seed
        that generated the session); readers ignore it.

    Notes
    -----
    The manifest is written when the first frame arrives (the intrinsics and image size come from
    it); :meth:`close` rewrites it with ``finalized: true`` and the frame count. A session killed
    before its first frame has no manifest and is reported as such.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        source: str = "",
        color: str = "raw",
        jpeg_quality: int = 95,
        png_compression: int = DEFAULT_PNG_COMPRESSION,
        fsync: bool = True,
        depth_scale: int = 1,
        depth_png_compression: int = 1,
        meta: Mapping[str, Any] | None = None,
    ):
        if color not in COLOR_ENCODINGS:
            raise ValueError(f"session colour encoding: expected one of {COLOR_ENCODINGS}, got {color!r}")
        if not (1 <= int(jpeg_quality) <= 100):
            raise ValueError(f"session jpeg_quality: expected 1..100, got {jpeg_quality!r}")
        if not (0 <= int(png_compression) <= 9):
            raise ValueError(f"session png_compression: expected 0..9, got {png_compression!r}")
        if isinstance(depth_scale, bool) or not isinstance(depth_scale, (int, np.integer)) or depth_scale < 1:
            raise ValueError(f"session depth_scale: expected an int >= 1, got {depth_scale!r}")
        if isinstance(depth_png_compression, bool) or not (0 <= int(depth_png_compression) <= 9):
            raise ValueError(f"session depth_png_compression: expected 0..9, got {depth_png_compression!r}")
        if meta is not None:
            try:
                json.dumps(meta)
            except (TypeError, ValueError) as e:
                raise ValueError(f"session meta: expected a JSON-serialisable object ({e})") from None
        self.path = Path(path)
        self.source = source
        self.color = color
        self.jpeg_quality = int(jpeg_quality)
        self.png_compression = int(png_compression)
        self.fsync = fsync
        self.depth_scale = int(depth_scale)
        # level 1: Huffman-only (fast, the recording default); higher levels: LZ77 matching too, which
        # finds the repeated millimetre values of smooth surfaces (~60 % smaller at 9, slower to encode,
        # as fast to decode), no filter either way
        self._depth_params = (
            list(_PNG_DEPTH_PARAMS)
            if int(depth_png_compression) == 1
            else [
                cv2.IMWRITE_PNG_COMPRESSION,
                int(depth_png_compression),
                cv2.IMWRITE_PNG_FILTER,
                cv2.IMWRITE_PNG_FILTER_NONE,
            ]
        )
        self.meta = None if meta is None else dict(meta)
        self.count = 0
        self._manifest: dict[str, Any] | None = None
        self._index_fd: int | None = None
        self._estimates_fd: int | None = None
        self._last_t: int | None = None
        self._closed = False
        if (self.path / MANIFEST).exists() or (self.path / INDEX).exists():
            raise SessionError(
                f"{self.path}: already contains a session; choose a new folder (recordings are never overwritten)"
            )
        # an existing folder must be empty (or hold only the empty frames/ of a recording killed before
        # its first frame): a session's files would mix with what is there, and the sessions or
        # outputs in it would end up inside a recording
        others = sorted(
            p.name
            for p in (self.path.iterdir() if self.path.is_dir() else ())
            if not (p.name == FRAMES_DIR and p.is_dir() and not any(p.iterdir()))
        )
        if others:
            listed = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
            raise SessionError(
                f"{self.path}: the folder is not empty (it holds {listed}); choose a new or empty folder "
                "for the session"
            )
        try:
            (self.path / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SessionError(
                f"{self.path}: cannot create the session folder ({e.strerror or e}); choose a folder you can write to"
            ) from None

    # -- manifest

    def _start(self, frame: Frame) -> None:
        h, w = frame.color.shape[:2]
        k = self.depth_scale
        if k > 1 and (w % k or h % k):
            raise SessionError(
                f"{self.path}: depth_scale {k} does not divide the colour size {w}x{h}; depth is stored at "
                f"an integer fraction of the colour size (e.g. 2 for 1280x800 colour and 640x400 depth)"
            )
        color: dict[str, Any] = {"encoding": self.color, "channels": "RGB"}
        if self.color == "jpeg":
            color["quality"] = self.jpeg_quality
        elif self.color == "png":
            color["compression"] = self.png_compression
        self._manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION_DEPTH_SCALE if k > 1 and frame.depth is not None else FORMAT_VERSION,
            "created": _utc_now(),
            "source": self.source,
            "width": int(w),
            "height": int(h),
            "intrinsics": frame.intrinsics.to_dict(),
            "color": color,
            "depth": (
                {"encoding": "png16", "unit": "mm", **({"scale": k} if k > 1 else {})}
                if frame.depth is not None
                else None
            ),
            "index": INDEX,
            "finalized": False,
            "frame_count": None,
            "closed": None,
        }
        if self.meta is not None:
            self._manifest["meta"] = self.meta
        # the index exists before the manifest, so a session with a manifest always has an index
        # (a kill in between leaves no manifest: reported as "killed before its first frame")
        self._index_fd = os.open(self.path / INDEX, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        _atomic_write_json(self.path / MANIFEST, self._manifest, self.fsync)  # also syncs the folder

    # -- frames

    def _encode_color(self, rgb: np.ndarray) -> bytes:
        if self.color == "raw":
            return np.ascontiguousarray(rgb).tobytes()
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)  # files hold ordinary RGB images; OpenCV wants BGR
        if self.color == "png":
            ok, buf = cv2.imencode(".png", bgr, _png_color_params(self.png_compression))
        else:
            ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise SessionError(f"{self.path}: OpenCV could not encode a {rgb.shape} colour frame as {self.color}")
        return buf.tobytes()

    def encode(self, frame: Frame) -> EncodedFrame:
        """Compress a frame's images (thread-safe: no writer state is touched).

        Lets a recorder encode several frames in parallel and commit them in order with
        :meth:`commit`; ``append(f)`` is ``commit(encode(f))``.
        """
        depth = None
        if frame.depth is not None:
            mm = depth_to_mm(frame.depth)
            k = self.depth_scale
            if k > 1:
                h, w = mm.shape
                if w % k or h % k:
                    raise SessionError(
                        f"{self.path}: depth_scale {k} does not divide the depth size {w}x{h} of frame {frame.seq}"
                    )
                mm = np.ascontiguousarray(mm[::k, ::k])  # top-left of each block: no mixing across edges
            ok, buf = cv2.imencode(".png", mm, self._depth_params)
            if not ok:
                raise SessionError(f"{self.path}: OpenCV could not encode depth of frame {frame.seq} as 16-bit PNG")
            depth = buf.tobytes()
        return EncodedFrame(frame=frame, color=self._encode_color(frame.color), depth=depth)

    def append(self, frame: Frame) -> int:
        """Write one frame; returns its index in the session. The frame is complete when this returns.

        Raises
        ------
        SessionError
            When the frame does not fit the session (different size, timestamp not increasing) or the
            writer is closed.
        """
        return self.commit(self.encode(frame))

    def commit(self, enc: EncodedFrame) -> int:
        """Write an encoded frame's files, then its index line (the commit point); returns its index."""
        frame = enc.frame
        if self._closed:
            raise SessionError(f"{self.path}: session writer is closed")
        for key in ("t_device_ns", "t_host_ns"):
            # the reader skips such a frame: written, it was lost without a word (a looped replay of a
            # session stamped near 2**63 went past it, exit status 0)
            t = getattr(frame, key)
            if not 0 <= t <= MAX_TIMESTAMP_NS:
                raise SessionError(f"{self.path}: frame {frame.seq} {key} {t} is outside 0..2**63-1 ns; not recorded")
        if self._manifest is None:
            self._start(frame)
        m = self._manifest
        h, w = frame.color.shape[:2]
        if (w, h) != (m["width"], m["height"]):
            raise SessionError(
                f"{self.path}: frame {frame.seq} is {w}x{h} but the session is {m['width']}x{m['height']}"
            )
        if self._last_t is not None and frame.t_device_ns <= self._last_t:
            raise SessionError(
                f"{self.path}: frame {frame.seq} timestamp {frame.t_device_ns} ns does not increase "
                f"(previous {self._last_t} ns)"
            )
        i = self.count
        stem = f"{FRAMES_DIR}/{i:06d}"
        entry: dict[str, Any] = {
            "i": i,
            "seq": int(frame.seq),
            "t_device_ns": int(frame.t_device_ns),
            "t_host_ns": int(frame.t_host_ns),
        }
        # 1) the frame's files, complete (and durable) before the index mentions them
        crel = stem + _COLOR_EXT[self.color]
        _write_file(self.path / crel, enc.color, self.fsync)
        entry["color"], entry["color_bytes"] = crel, len(enc.color)
        if enc.depth is not None:
            drel = stem + ".depth.png"
            _write_file(self.path / drel, enc.depth, self.fsync)
            entry["depth"], entry["depth_bytes"] = drel, len(enc.depth)
        else:
            entry["depth"], entry["depth_bytes"] = None, 0
        entry["exposure"] = frame.exposure.to_dict()
        entry["gravity"] = None if frame.gravity is None else [float(x) for x in np.asarray(frame.gravity).ravel()]
        entry["imu"] = [
            {
                "t_ns": int(s.t_ns),
                "accel": [float(x) for x in s.accel],
                "gyro": None if s.gyro is None else [float(x) for x in s.gyro],
            }
            for s in frame.imu
        ]
        if frame.intrinsics.to_dict() != m["intrinsics"]:
            entry["intrinsics"] = frame.intrinsics.to_dict()  # e.g. autofocus changed them
        # 2) the commit point: one line, one write() on an O_APPEND fd, then fsync
        line = (json.dumps(entry, separators=(",", ":")) + "\n").encode("utf-8")
        n = os.write(self._index_fd, line)
        if n != len(line):  # pragma: no cover - a full disk; the reader will see a torn line
            raise SessionError(f"{self.path}: short write to {INDEX} ({n} of {len(line)} bytes): disk full?")
        if self.fsync:
            _datasync(self._index_fd)
        self.count += 1
        self._last_t = int(frame.t_device_ns)
        return i

    def append_estimate(self, i: int, estimate: Mapping[str, Any]) -> None:
        """Append frame ``i``'s lighting estimate (a JSON object) to the ``estimates.jsonl`` sidecar.

        Call after :meth:`commit` of frame ``i``: the sidecar only names committed frames. One line,
        one ``write`` on an O_APPEND fd (fsynced like the index), so a kill leaves at most a torn
        last line, which the reader skips.
        """
        if self._closed:
            raise SessionError(f"{self.path}: session writer is closed")
        if not 0 <= int(i) < self.count:
            raise SessionError(
                f"{self.path}: estimate for frame {i}, but only frames 0..{self.count - 1} are committed"
            )
        if self._estimates_fd is None:
            self._estimates_fd = os.open(self.path / ESTIMATES, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        line = (json.dumps({"i": int(i), "estimate": estimate}, separators=(",", ":"), allow_nan=False) + "\n").encode(
            "utf-8"
        )
        os.write(self._estimates_fd, line)
        if self.fsync:
            _datasync(self._estimates_fd)

    def close(self) -> None:
        """Finalise: rewrite the manifest with the frame count and ``finalized: true``. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._estimates_fd is not None:
            os.close(self._estimates_fd)
            self._estimates_fd = None
        if self._index_fd is not None:
            os.close(self._index_fd)
            self._index_fd = None
        if self._manifest is not None:
            self._manifest.update(finalized=True, frame_count=self.count, closed=_utc_now())
            _atomic_write_json(self.path / MANIFEST, self._manifest, self.fsync)

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------------------------------
# reader


@dataclass(frozen=True)
class FrameEntry:
    """One validated index line: where the frame's files are and its metadata."""

    i: int
    line: int
    seq: int
    t_device_ns: int
    t_host_ns: int
    color: Path
    color_bytes: int
    depth: Path | None
    depth_bytes: int
    exposure: Exposure
    gravity: np.ndarray | None
    imu: tuple[ImuSample, ...]
    intrinsics: Intrinsics | None


def _need(d: Mapping[str, Any], key: str, types: tuple[type, ...], where: str) -> Any:
    if key not in d:
        raise SessionError(f"{where}: missing key {key!r}")
    v = d[key]
    if not isinstance(v, types) or (isinstance(v, bool) and bool not in types):
        names = " or ".join("null" if t is type(None) else t.__name__ for t in types)
        raise SessionError(f"{where}: key {key!r}: expected {names}, got {type(v).__name__} {v!r}")
    return v


def _vec(v: Any, n: int, where: str) -> tuple[float, ...]:
    numbers = isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    if not (numbers and len(v) == n):
        raise SessionError(f"{where}: expected a list of {n} numbers, got {v!r}")
    return tuple(float(x) for x in v)


#: largest plausible focal length, in multiples of the image's larger side (a ~0.6 degree field of view;
#: telephoto camera modules reach ~10x)
MAX_FOCAL_PER_SIDE = 100.0
#: largest image side the intrinsics may be stated at (pixels)
MAX_SIDE = 100_000
#: a gravity vector is a unit vector; a norm further from 1 than this is not one
GRAVITY_NORM_TOLERANCE = 1e-2


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(float(x))


def check_intrinsics(intr: Intrinsics, width: int, height: int, where: str) -> None:
    """Refuse intrinsics no camera has (NaN, 0, 1e300, a principal point far outside the image).

    A session with such intrinsics reads, but every frame then fails in the stages; refusing it at
    the boundary names the key instead. Raises :class:`SessionError`.
    """
    iw, ih = intr.width, intr.height
    if not (0 < iw <= MAX_SIDE and 0 < ih <= MAX_SIDE) or abs(iw * height - ih * width) > 0.01 * ih * width:
        # the stages scale the intrinsics to the picture: 0 divided by zero, a negative width mirrored
        # fx, another aspect ratio stretched one axis
        if 0 < iw <= MAX_SIDE and 0 < ih <= MAX_SIDE:
            why = f"{iw}x{ih} does not describe the {width}x{height} pictures"
        else:  # the same numbers on both sides read "1000000000000x800 does not describe 1000000000000x800"
            why = f"{iw}x{ih} is not a camera's image size (each side 1..{MAX_SIDE} pixels)"
        raise SessionError(
            f"{where}: key 'intrinsics.width'/'intrinsics.height': {why} (expected the pictures' size, or a size "
            "of the same aspect ratio the intrinsics were calibrated at)"
        )
    side = max(width, height)
    for key in ("fx", "fy"):
        v = getattr(intr, key)
        if not (np.isfinite(v) and 0.0 < v <= MAX_FOCAL_PER_SIDE * side):
            raise SessionError(
                f"{where}: key 'intrinsics.{key}': {v!r} is not a plausible focal length in pixels "
                f"(expected a finite value in (0, {MAX_FOCAL_PER_SIDE:g} x {side}])"
            )
    for key, size in (("cx", width), ("cy", height)):
        v = getattr(intr, key)
        if not (np.isfinite(v) and -size <= v <= 2 * size):
            raise SessionError(
                f"{where}: key 'intrinsics.{key}': {v!r} is not a plausible principal point for a "
                f"{width}x{height} image (expected a finite value in [-{size}, {2 * size}])"
            )
    if not all(np.isfinite(x) for x in intr.dist):
        raise SessionError(f"{where}: key 'intrinsics.dist': expected finite numbers, got {list(intr.dist)!r}")


def _check_exposure(exp: Exposure, where: str) -> None:
    for key in ("exposure_us", "iso", "color_temperature_k"):
        v = getattr(exp, key)
        if v is not None and not (np.isfinite(v) and v > 0):
            raise SessionError(f"{where}: key 'exposure.{key}': expected a finite positive number, got {v!r}")
    if exp.wb_gains is not None and not all(np.isfinite(g) and g > 0 for g in exp.wb_gains):
        raise SessionError(f"{where}: key 'exposure.wb_gains': expected finite positive gains, got {exp.wb_gains!r}")


def _longest_increasing(values: Sequence[int]) -> list[bool]:
    """Which of ``values`` form a longest strictly increasing subsequence (one of them; O(n log n))."""
    tails: list[int] = []  # tails[L]: index of the smallest last value of an increasing run of length L+1
    prev = [-1] * len(values)
    for i, v in enumerate(values):
        lo, hi = 0, len(tails)
        while lo < hi:  # first run whose last value is >= v
            mid = (lo + hi) // 2
            if values[tails[mid]] < v:
                lo = mid + 1
            else:
                hi = mid
        prev[i] = tails[lo - 1] if lo > 0 else -1
        if lo == len(tails):
            tails.append(i)
        else:
            tails[lo] = i
    keep = [False] * len(values)
    i = tails[-1] if tails else -1
    while i >= 0:
        keep[i] = True
        i = prev[i]
    return keep


class SessionReader:
    """Open and validate a recorded session; read its frames by index.

    Parameters
    ----------
    path : str or Path
        The session folder.
    strict : bool
        Raise :class:`SessionError` listing every problem instead of skipping the bad frames.

    Attributes
    ----------
    manifest : dict
        The parsed manifest.
    entries : list of FrameEntry
        The intact frames (index lines whose files exist with the recorded sizes), in order.
    problems : list of str
        Everything found wrong, one human-readable line each (empty for a clean session).
    finalized : bool
        False when the recording was not closed cleanly (crash, kill -9): the intact part replays.

    Raises
    ------
    SessionError
        When nothing can be replayed: no folder, no/unparsable manifest, unknown format or version,
        missing index; or with ``strict=True`` on any problem.
    """

    def __init__(self, path: str | os.PathLike, *, strict: bool = False):
        self.path = Path(path)
        self.strict = strict
        self.problems: list[str] = []
        # timestamp jumps over MAX_FRAME_GAP_NS: the frames are intact and replay, so these are not
        # problems of reading (strict readers accept them), but check() reports them
        self.gaps: list[str] = []
        if not self.path.is_dir():
            raise SessionError(
                f"{self.path}: not a session folder (expected a folder with {MANIFEST} and {INDEX})"
                + session_hint(self.path)
            )
        self.manifest = self._read_manifest()
        m = self.manifest
        self.width, self.height = int(m["width"]), int(m["height"])
        self.intrinsics = Intrinsics.from_dict(m["intrinsics"])
        self.color_encoding = m["color"]["encoding"]
        self.has_depth = m["depth"] is not None
        #: depth images are stored at 1/depth_scale of the colour size (format version 2)
        self.depth_scale = int(m["depth"].get("scale", 1)) if self.has_depth else 1
        self.finalized = bool(m.get("finalized", False))
        self.entries = self._read_index()
        if not self.finalized:
            self.problems.insert(
                0,
                f"{self.path}: recording was not finalised (interrupted or killed); "
                f"{len(self.entries)} complete frames are replayable",
            )
        self.problems = [printable(p) for p in self.problems]
        self.gaps = [printable(g) for g in self.gaps]
        count = m.get("frame_count")
        if self.finalized and isinstance(count, int) and count != self._index_lines:
            self.problems.append(
                f"{self.path / MANIFEST}: frame_count is {count} but {self.index_path.name} has "
                f"{self._index_lines} complete lines (index truncated or appended to after closing?)"
            )
        if self.strict and self.problems:
            raise SessionError(f"{self.path}: invalid session:\n  " + "\n  ".join(self.problems))
        if self.problems:
            shown = self.problems[:5]
            more = f"\n  ... and {len(self.problems) - 5} more" if len(self.problems) > 5 else ""
            log.warning(
                "session %s: %d problem(s); replaying the %d intact frames:\n  %s%s",
                self.path,
                len(self.problems),
                len(self.entries),
                "\n  ".join(shown),
                more,
            )

    # -- manifest

    def _read_manifest(self) -> dict[str, Any]:
        mpath = self.path / MANIFEST
        if mpath.is_symlink():
            # like every file a session names: a manifest is never followed out of the folder
            safe_relpath(self.path, MANIFEST, str(mpath))
        if mpath.is_dir():  # it exists: "missing" sent users looking for a file that is there
            raise SessionError(f"{mpath}: is a folder; expected the session's manifest file (JSON)")
        if not mpath.is_file():
            raise SessionError(
                f"{mpath}: missing; not a recorded session, or the recording was killed before its first "
                f"frame was written" + session_hint(self.path)
            )
        try:
            m = json.loads(mpath.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise SessionError(f"{mpath}: not valid JSON ({e})") from None
        except RecursionError:  # [[[[...]]]] thousands deep: a traceback from the JSON decoder
            raise SessionError(f"{mpath}: JSON nested too deeply; expected the session's manifest object") from None
        except ValueError as e:  # an int of over 4300 digits: json raises a bare ValueError (a traceback)
            raise SessionError(f"{mpath}: not valid JSON ({e})") from None
        except OSError as e:
            raise SessionError(f"{mpath}: cannot read the manifest: {e.strerror or e}") from None
        if not isinstance(m, dict):
            raise SessionError(f"{mpath}: expected a JSON object, got {type(m).__name__}")
        where = str(mpath)
        fmt = m.get("format")
        if fmt != FORMAT_NAME:
            raise SessionError(f"{where}: key 'format': expected {FORMAT_NAME!r}, got {fmt!r}")
        ver = m.get("version")
        if ver not in SUPPORTED_VERSIONS or not isinstance(ver, int) or isinstance(ver, bool):  # 2.0 passed as 2
            raise SessionError(
                f"{where}: unknown session format version {ver!r}; this build of illuminet reads version(s) "
                f"{', '.join(map(str, SUPPORTED_VERSIONS))} (a newer illuminet may read it)"
            )
        for key in ("width", "height"):
            if _need(m, key, (int,), where) <= 0:
                raise SessionError(f"{where}: key {key!r}: expected a positive int, got {m[key]!r}")
        intr = _need(m, "intrinsics", (dict,), where)
        try:
            parsed = Intrinsics.from_dict(intr)
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise SessionError(
                f"{where}: key 'intrinsics': expected fx, fy, cx, cy, width, height numbers ({e!r})"
            ) from None
        check_intrinsics(parsed, m["width"], m["height"], where)
        color = _need(m, "color", (dict,), where)
        if color.get("encoding") not in COLOR_ENCODINGS:
            raise SessionError(
                f"{where}: key 'color.encoding': expected one of {COLOR_ENCODINGS}, got {color.get('encoding')!r}"
            )
        if color.get("channels", "RGB") != "RGB":  # "BGR" replayed with red and blue swapped, silently
            raise SessionError(f"{where}: key 'color.channels': expected 'RGB', got {color.get('channels')!r}")
        # read with bool() and isinstance(int): "false" made a session finalised, "32" skipped the count check
        if "finalized" in m:
            _need(m, "finalized", (bool,), where)
        if m.get("frame_count") is not None:
            _need(m, "frame_count", (int,), where)
        depth = _need(m, "depth", (dict, type(None)), where)
        if depth is not None and (depth.get("encoding"), depth.get("unit")) != ("png16", "mm"):
            raise SessionError(f"{where}: key 'depth': expected encoding 'png16' with unit 'mm', got {depth!r}")
        if depth is not None and "scale" in depth:
            k = depth["scale"]
            if ver < FORMAT_VERSION_DEPTH_SCALE:
                raise SessionError(
                    f"{where}: key 'depth.scale' needs format version {FORMAT_VERSION_DEPTH_SCALE}, "
                    f"the manifest says version {ver}"
                )
            if isinstance(k, bool) or not isinstance(k, int) or k < 1:
                raise SessionError(f"{where}: key 'depth.scale': expected an int >= 1, got {k!r}")
            if m["width"] % k or m["height"] % k:
                raise SessionError(
                    f"{where}: key 'depth.scale': {k} does not divide the image size {m['width']}x{m['height']} "
                    f"(depth is stored at an integer fraction of the colour size)"
                )
        index = m.get("index", INDEX)
        self.index_path = safe_relpath(self.path, index, f"{where}: key 'index'")
        return m

    # -- index

    def _read_index(self) -> list[FrameEntry]:
        ipath = self.index_path
        if not ipath.is_file():
            raise SessionError(f"{ipath}: missing; the session has a manifest but no frame index")
        data = ipath.read_bytes()
        lines = data.split(b"\n")
        tail = lines.pop()  # after the last "\n": empty for a cleanly written index
        self._index_lines = len(lines)
        parsed: list[FrameEntry] = []
        problems: list[tuple[int, str]] = []
        for no, raw in enumerate(lines, start=1):
            where = f"{ipath}: line {no}"
            try:
                d = json.loads(raw.decode("utf-8"))
                if not isinstance(d, dict):
                    raise SessionError(f"{where}: expected a JSON object, got {type(d).__name__}")
                parsed.append(self._entry(d, no, where))
            except SessionError as ex:  # before ValueError: a SessionError is one
                problems.append((no, f"{ex}; frame skipped"))
            except (ValueError, RecursionError) as ex:
                # ValueError also covers an integer of over 4300 digits, which json refuses to convert
                problems.append((no, f"{where}: malformed index line ({type(ex).__name__}: {ex}); frame skipped"))
        # Timestamps must increase. One corrupt timestamp must cost one frame, not every frame after it
        # (a far-future value would otherwise make all later frames "not increase"): the frames kept
        # are the longest increasing run of timestamps, so the fewest are skipped.
        keep = _longest_increasing([e.t_device_ns for e in parsed])
        entries: list[FrameEntry] = []
        last_t: int | None = None
        for k, e in enumerate(parsed):
            where = f"{ipath}: line {e.line}"
            if not keep[k]:
                prev = "" if last_t is None else f" (previous {last_t} ns)"
                problems.append(
                    (
                        e.line,
                        f"{where}: timestamp {e.t_device_ns} ns does not increase{prev}, or is out of order "
                        "with the frames around it; frame skipped",
                    )
                )
                continue
            if last_t is not None and e.t_device_ns - last_t > MAX_FRAME_GAP_NS:
                self.gaps.append(
                    f"{where}: timestamp jumps {(e.t_device_ns - last_t) / 1e9:.6g} s after the previous frame "
                    f"(over {MAX_FRAME_GAP_NS / 1e9:g} s: a gap; replay with recorded timing waits one frame "
                    "period there)"
                )
            last_t = e.t_device_ns
            entries.append(e)
        self.problems += [m for _, m in sorted(problems, key=lambda x: x[0])]
        if tail.strip():
            self.problems.append(
                f"{ipath}: line {len(lines) + 1} is torn ({len(tail)} bytes without a line end: the recording "
                f"was interrupted while writing it); that frame is ignored"
            )
        return entries

    def _entry(self, d: Mapping[str, Any], no: int, where: str) -> FrameEntry:
        i = _need(d, "i", (int,), where)
        seq = _need(d, "seq", (int,), where)
        t_dev = _need(d, "t_device_ns", (int,), where)
        t_host = _need(d, "t_host_ns", (int,), where)
        for key, t in (("t_device_ns", t_dev), ("t_host_ns", t_host)):
            if not 0 <= t <= MAX_TIMESTAMP_NS:
                raise SessionError(f"{where}: key {key!r}: {t} is outside 0..2**63-1 ns")
        color = safe_relpath(self.path, _need(d, "color", (str,), where), f"{where}: key 'color'")
        cbytes = _need(d, "color_bytes", (int,), where)
        self._check_file(color, cbytes, f"{where}: colour")
        if self.color_encoding == "raw" and cbytes != self.width * self.height * 3:
            raise SessionError(
                f"{where}: colour {color.name}: size mismatch: {cbytes} bytes, but a raw {self.width}x{self.height} "
                f"RGB frame has {self.width * self.height * 3}"
            )
        drel = _need(d, "depth", (str, type(None)), where)
        dbytes = 0
        depth = None
        if drel is not None:
            depth = safe_relpath(self.path, drel, f"{where}: key 'depth'")
            dbytes = _need(d, "depth_bytes", (int,), where)
            self._check_file(depth, dbytes, f"{where}: depth")
        exp = d.get("exposure")
        try:
            exposure = Exposure.from_dict(exp)
        except (TypeError, ValueError, KeyError, AttributeError) as ex:
            raise SessionError(f"{where}: key 'exposure': {ex}") from None
        _check_exposure(exposure, where)
        g = d.get("gravity")
        gravity = None if g is None else np.asarray(_vec(g, 3, f"{where}: key 'gravity'"), dtype=np.float64)
        if gravity is not None:
            norm = float(np.linalg.norm(gravity)) if np.all(np.isfinite(gravity)) else float("nan")
            if not abs(norm - 1.0) <= GRAVITY_NORM_TOLERANCE:
                raise SessionError(f"{where}: key 'gravity': expected a finite unit vector, got {g!r}")
        imu = []
        for k, s in enumerate(d.get("imu") or []):
            w2 = f"{where}: imu[{k}]"
            if not isinstance(s, dict):
                raise SessionError(f"{w2}: expected an object, got {s!r}")
            imu.append(
                ImuSample(
                    t_ns=_need(s, "t_ns", (int,), w2),
                    accel=_vec(s.get("accel"), 3, f"{w2}.accel"),
                    gyro=None if s.get("gyro") is None else _vec(s["gyro"], 3, f"{w2}.gyro"),
                )
            )
        intr = None
        if d.get("intrinsics") is not None:
            try:
                intr = Intrinsics.from_dict(d["intrinsics"])
            except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as ex:
                raise SessionError(f"{where}: key 'intrinsics': {ex!r}") from None
            check_intrinsics(intr, self.width, self.height, where)
        return FrameEntry(
            i=i,
            line=no,
            seq=seq,
            t_device_ns=t_dev,
            t_host_ns=t_host,
            color=color,
            color_bytes=cbytes,
            depth=depth,
            depth_bytes=dbytes,
            exposure=exposure,
            gravity=gravity,
            imu=tuple(imu),
            intrinsics=intr,
        )

    @staticmethod
    def _check_file(path: Path, expected: int, what: str) -> None:
        try:
            st = path.stat()
        except FileNotFoundError:
            raise SessionError(f"{what}: missing file {path}") from None
        except (OSError, ValueError) as e:  # a symlink loop, permissions, a NUL byte
            raise SessionError(f"{what}: cannot read {path}: {getattr(e, 'strerror', None) or e}") from None
        if not stat.S_ISREG(st.st_mode):  # a folder's 4096 "bytes" were reported as a truncated frame
            kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file"
            raise SessionError(f"{what}: {path} is {kind}; expected the frame's image file")
        size = st.st_size
        if size != expected:
            kind = "truncated frame" if size < expected else "size mismatch"
            raise SessionError(f"{what}: {kind}: {path} has {size} bytes, the index says {expected}")

    # -- frames

    def __len__(self) -> int:
        return len(self.entries)

    def _read_bytes(self, path: Path, expected: int, what: str) -> np.ndarray:
        try:
            buf = np.fromfile(path, dtype=np.uint8)
        except FileNotFoundError:
            raise CorruptFrame(f"{what}: missing file {path}") from None
        except (OSError, ValueError) as e:  # permissions, I/O error, a symlink loop: this frame is lost,
            # the others may still read
            raise CorruptFrame(f"{what}: cannot read {path}: {getattr(e, 'strerror', None) or e}") from None
        if buf.size != expected:
            raise CorruptFrame(f"{what}: truncated frame: {path} has {buf.size} bytes, the index says {expected}")
        return buf

    def read(self, k: int) -> Frame:
        """Decode intact frame ``k`` (0-based among :attr:`entries`) into a :class:`Frame`.

        ``t_host_ns`` is the recorded host time; sources replace it with the replay time.

        Raises
        ------
        CorruptFrame
            When a file changed since validation, cannot be decoded, or has the wrong image size.
        """
        e = self.entries[k]
        where = f"{self.index_path}: line {e.line}"
        try:
            return self._decode(e, where)
        except CorruptFrame:
            raise
        except (OSError, ValueError, RuntimeError, MemoryError, cv2.error) as ex:
            # anything else one frame's files can cause is still one bad frame, never the end of a replay
            # (this runs in the replay's decoder threads)
            raise CorruptFrame(f"{where}: cannot decode the frame: {type(ex).__name__}: {ex}") from None

    def _check_header(
        self, buf: np.ndarray, path: Path, what: str, size: tuple[int, int], kind: str, says: str
    ) -> None:
        """Refuse an image whose header is not ``kind`` (PNG/JPEG) of ``size`` before decoding it.

        A decoder allocates whatever the header claims (a 65535x65535 PNG is 12 GiB), so the size is
        checked from the header's few bytes first.
        """
        got = image_size(buf[: 1 << 20].tobytes())
        if got is None:
            raise CorruptFrame(f"{what} {path} is not a decodable {kind} image (no {kind} header)")
        if got != size:
            raise CorruptFrame(
                f"{what} {path}: size mismatch: image is {got[0]}x{got[1]}, the manifest says {says} "
                f"(read from its header; not decoded)"
            )

    def _decode(self, e: FrameEntry, where: str) -> Frame:
        buf = self._read_bytes(e.color, e.color_bytes, f"{where}: colour")
        if self.color_encoding == "raw":
            color = buf.reshape(self.height, self.width, 3)
        else:
            size = (self.width, self.height)
            enc = self.color_encoding.upper()
            self._check_header(buf, e.color, f"{where}: colour", size, enc, f"{self.width}x{self.height}")
            img = cv2.imdecode(buf, _IMREAD_RGB if _IMREAD_RGB is not None else cv2.IMREAD_COLOR)
            if img is None:
                raise CorruptFrame(f"{where}: colour {e.color} is not a decodable {self.color_encoding.upper()} image")
            if img.shape[:2] != (self.height, self.width):
                raise CorruptFrame(
                    f"{where}: colour {e.color}: size mismatch: image is {img.shape[1]}x{img.shape[0]}, "
                    f"the manifest says {self.width}x{self.height}"
                )
            color = img if _IMREAD_RGB is not None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        depth = None
        if e.depth is not None:
            dbuf = self._read_bytes(e.depth, e.depth_bytes, f"{where}: depth")
            k = self.depth_scale
            scaled = f" / depth.scale {k} = {self.width // k}x{self.height // k}" if k > 1 else ""
            says = f"{self.width}x{self.height}{scaled}"
            self._check_header(dbuf, e.depth, f"{where}: depth", (self.width // k, self.height // k), "PNG", says)
            mm = cv2.imdecode(dbuf, cv2.IMREAD_UNCHANGED)
            if mm is None:
                raise CorruptFrame(f"{where}: depth {e.depth} is not a decodable PNG")
            if mm.dtype != np.uint16 or mm.ndim != 2:
                raise CorruptFrame(
                    f"{where}: depth {e.depth}: expected a 16-bit single-channel PNG (mm), got {mm.dtype} "
                    f"with shape {mm.shape}"
                )
            dh, dw = self.height // k, self.width // k
            if mm.shape != (dh, dw):
                scaled = f" / depth.scale {k} = {dw}x{dh}" if k > 1 else ""
                raise CorruptFrame(
                    f"{where}: depth {e.depth}: size mismatch: image is {mm.shape[1]}x{mm.shape[0]}, "
                    f"the manifest says {self.width}x{self.height}{scaled}"
                )
            depth = np.multiply(mm, np.float32(1e-3), dtype=np.float32)  # = depth_from_mm, in one pass
            if k > 1:
                # nearest neighbour by an exact integer factor: every stored sample fills its k x k block
                # (0 = invalid stays 0; no depth is interpolated across an edge). Converting to metres
                # first touches k^2 fewer pixels: ~1 ms less per 1280x800 frame, same values
                depth = cv2.resize(depth, (self.width, self.height), interpolation=cv2.INTER_NEAREST)
        return Frame(
            seq=e.seq,
            t_device_ns=e.t_device_ns,
            t_host_ns=e.t_host_ns,
            color=color,
            depth=depth,
            intrinsics=e.intrinsics or self.intrinsics,
            exposure=e.exposure,
            gravity=e.gravity,
            imu=e.imu,
        )

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self.entries)):
            yield self.read(k)

    def estimates(self) -> dict[int, dict[str, Any]]:
        """The recorded lighting estimates (``estimates.jsonl`` sidecar), by session frame index ``i``.

        Empty when the session has no sidecar (recorded without the light stage, by ``illuminet
        record``, or by an older version). Malformed or torn lines and lines naming no intact frame
        are skipped with a warning: the sidecar never makes a session unreadable.
        """
        path = self.path / ESTIMATES
        if not path.is_file():
            return {}
        try:  # like every file of a session: never followed out of the folder by a symlink
            safe_relpath(self.path, ESTIMATES, str(path))
        except SessionError as e:
            log.warning("session %s: %s not read: %s", self.path, ESTIMATES, e)
            return {}
        intact = {e.i for e in self.entries}
        out: dict[int, dict[str, Any]] = {}
        bad = 0
        for raw in path.read_bytes().split(b"\n"):
            if not raw.strip():
                continue
            try:
                d = json.loads(raw.decode("utf-8"))
                i, est = d["i"], d["estimate"]
            except (ValueError, RecursionError, KeyError, TypeError):  # ValueError: also a 4300-digit int
                bad += 1
                continue
            if isinstance(i, int) and not isinstance(i, bool) and i in intact and isinstance(est, dict):
                out[i] = est
            else:
                bad += 1
        if bad:
            log.warning(
                "session %s: %d line(s) of %s skipped (torn, malformed, or for no intact frame)",
                self.path,
                bad,
                ESTIMATES,
            )
        return out

    def check(self) -> list[str]:
        """Decode every frame too (slow): all problems, including undecodable images, one line each."""
        problems = list(self.problems) + list(self.gaps)
        for k in range(len(self.entries)):
            try:
                self.read(k)
            except CorruptFrame as ex:
                problems.append(printable(str(ex)))
        return problems
