"""Output sinks: video file, PNG sequence, lighting estimates, session recorder, null. (The MJPEG
server is in mjpeg.py.)

This module owns writing finished frames to files. Picture sinks write
``frame.results.get("composite", frame.color)`` -- the renderer's output when there is one, else the
camera picture. Videos go through PyAV (H.264, yuv420p: plays in browsers) when it is installed,
else OpenCV's FFmpeg backend. The estimates sink writes each frame's lighting estimate as one JSON
line (:mod:`illuminet.runtime.stream.estimate_json`). The session recorder writes the *input* frame
(colour, depth, metadata; never the pictures) in the format of
:mod:`illuminet.runtime.stream.session`, plus the frame's lighting estimate in the optional
``estimates.jsonl`` sidecar.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shutil
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import MappingProxyType

import cv2
import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import COMPOSITE
from illuminet.runtime.stage import Sink
from illuminet.runtime.stream.session import DEFAULT_PNG_COMPRESSION, SessionWriter

log = logging.getLogger(__name__)


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import OutputClosed, SinkError  # noqa: E402,F401


def output_picture(frame: Frame) -> np.ndarray:
    """The picture sinks show: the composite when a renderer produced one, else the camera colour (RGB)."""
    img = frame.results.get(COMPOSITE.name, frame.color)
    if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8):
        raise SinkError(
            f"results['composite'] must be an HxWx3 uint8 RGB image, got {getattr(img, 'shape', type(img))} "
            f"{getattr(img, 'dtype', '')}"
        )
    return img


class NullSink(Sink):
    """Accepts and discards frames (benchmarks, dry runs); counts them."""

    name = "null"

    def __init__(self) -> None:
        self.frames = 0

    def write(self, frame: Frame) -> None:
        self.frames += 1

    def stats(self) -> dict:
        return {"frames": self.frames}


#: container extension -> FourCC codes tried in order (first that OpenCV's FFmpeg backend opens wins).
#: mp4v (MPEG-4 part 2) is in every FFmpeg build OpenCV ships; avc1 (H.264) needs an encoder that pip
#: wheels usually lack, so it is the fallback, not the first choice. (Used when PyAV is missing.)
VIDEO_CODECS: dict[str, tuple[str, ...]] = {
    ".mp4": ("mp4v", "avc1"),
    ".m4v": ("mp4v", "avc1"),
    ".mov": ("mp4v", "avc1"),
    ".avi": ("MJPG", "XVID", "mp4v"),
    ".mkv": ("mp4v", "MJPG", "avc1"),
}
#: containers written as H.264 / yuv420p through PyAV when it is installed: what browsers (Chromium's
#: <video>), phones and every player decode; OpenCV's mp4v (MPEG-4 part 2) does not play in browsers
PYAV_CONTAINERS = (".mp4", ".m4v", ".mov", ".mkv")
#: free bytes under an OpenCV video whose file stopped growing below which the disk counts as full (a frame
#: of MJPG is tens of kB: less than this cannot take one)
VIDEO_DISK_FULL_BYTES = 64 * 1024
#: libx264 settings: "ultrafast" costs ~11 ms of CPU per 1280x800 frame on the 2-core build machine
#: (superfast ~16 ms, veryfast ~29 ms) and runs on a writer thread (PyAV releases the GIL while
#: encoding); crf 20 is visually lossless for a preview
H264_PRESET, H264_CRF = "ultrafast", 20


def pyav_available() -> bool:
    """True when PyAV (``pip install av``: FFmpeg with libx264 in its wheel) can be imported."""
    import importlib.util

    return importlib.util.find_spec("av") is not None


class _PyAvWriter:
    """H.264 (libx264, yuv420p) into an MP4/MOV/MKV container through PyAV, on its own thread.

    ``write`` only queues the picture (a bounded queue: a slow disk holds the loop back rather than
    losing frames of the file); the thread converts RGB to yuv420p and encodes. An error in the
    thread is raised by the next ``write`` or by ``close``.
    """

    def __init__(self, path: Path, size: tuple[int, int], fps: float):
        from fractions import Fraction

        import av

        # +faststart: the index (moov) goes first, so a browser plays the file while it downloads
        opts = {"movflags": "+faststart"} if path.suffix.lower() != ".mkv" else {}
        self._container = av.open(str(path), mode="w", options=opts)
        try:
            self._stream = self._container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
            self._stream.width, self._stream.height = size
            self._stream.pix_fmt = "yuv420p"
            self._stream.options = {"crf": str(H264_CRF), "preset": H264_PRESET}
        except Exception:
            self._container.close()
            raise
        self._queue: queue.Queue = queue.Queue(maxsize=4)
        self._error: BaseException | None = None
        self._n = 0
        self._thread = threading.Thread(target=self._run, name="illuminet-video-encode", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import av

        while True:
            img = self._queue.get()
            if img is None:
                return
            if self._error is not None:
                continue  # drain: the loop learns of the error on its next write
            try:
                f = av.VideoFrame.from_ndarray(img, format="rgb24")
                f.pts = self._n
                self._n += 1
                for packet in self._stream.encode(f):
                    self._container.mux(packet)
            except Exception as e:  # reported in the loop thread
                self._error = e

    def write(self, rgb: np.ndarray) -> None:
        if self._error is not None:
            raise self._error
        self._queue.put(rgb)

    def release(self) -> None:
        self._queue.put(None)
        self._thread.join()
        try:
            if self._error is None:
                for packet in self._stream.encode(None):  # flush the encoder's delayed frames
                    self._container.mux(packet)
        finally:
            self._container.close()  # writes the index: the file is playable after this
        if self._error is not None:
            raise self._error


def _even(img: np.ndarray) -> np.ndarray:
    """yuv420p needs even width and height: repeat the last row/column when odd."""
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return img
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


class VideoSink(Sink):
    """Write the output pictures to a video file: H.264 through PyAV, else OpenCV's FFmpeg backend.

    Parameters
    ----------
    path : str or Path
        ``.mp4``, ``.m4v``, ``.mov``, ``.avi`` or ``.mkv``.
    fps : float
        Frame rate written into the file.
    codecs : sequence of str, optional
        OpenCV FourCC codes to try in order (selects the OpenCV backend); default from
        :data:`VIDEO_CODECS` by extension.
    backend : {"auto", "pyav", "opencv"}
        ``auto``: PyAV's H.264 (yuv420p, plays in browsers) for :data:`PYAV_CONTAINERS` when PyAV is
        installed and no ``codecs`` are given, else OpenCV.

    Notes
    -----
    :meth:`open` checks at once that a writer can be created (a tiny probe file), so a missing codec or
    an unwritable folder is reported before the stream starts, not on the first frame. The real writer
    is created on the first frame, whose size every later frame must have. H.264 in yuv420p needs even
    sizes: an odd last row or column is repeated.
    """

    name = "video"

    def __init__(
        self, path: str | os.PathLike, fps: float = 30.0, codecs: tuple[str, ...] | None = None, backend: str = "auto"
    ):
        self.path = Path(path)
        ext = self.path.suffix.lower()
        if ext not in VIDEO_CODECS and codecs is None:
            raise SinkError(f"video {self.path}: unknown extension {ext!r}; expected one of {', '.join(VIDEO_CODECS)}")
        if backend not in ("auto", "pyav", "opencv"):
            raise SinkError(f"video {self.path}: backend must be auto, pyav or opencv, got {backend!r}")
        if not fps > 0:
            raise SinkError(f"video {self.path}: fps must be > 0, got {fps!r}")
        if backend == "pyav" and (ext not in PYAV_CONTAINERS or codecs is not None):
            raise SinkError(
                f"video {self.path}: the PyAV backend writes H.264 into {', '.join(PYAV_CONTAINERS)} "
                f"(without OpenCV FourCC codes)"
            )
        if backend == "pyav" and not pyav_available():
            raise SinkError(f"video {self.path}: PyAV is not installed; pip install av (or use backend 'opencv')")
        if backend == "auto":
            backend = "pyav" if codecs is None and ext in PYAV_CONTAINERS and pyav_available() else "opencv"
        self.backend = backend
        self.fps = float(fps)
        self.codecs = tuple(codecs) if codecs is not None else VIDEO_CODECS.get(ext, ())
        self.codec: str | None = None
        self._writer = None
        self._size: tuple[int, int] | None = None
        self.frames = 0
        self._bytes = 0  # the OpenCV writer's file size after the last write that grew it
        self._stalled = 0  # writes since then

    def _disk_full(self) -> str | None:
        """Why OpenCV's writer is losing frames, when the disk under the video is full (else None).

        ``cv2.VideoWriter.write`` reports nothing: on a full disk FFmpeg printed "Failed to write frame"
        and the run ended with exit status 0 and no sink failure, the video cut short."""
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return None
        if free >= VIDEO_DISK_FULL_BYTES:
            return None
        return (
            f"video {self.path}: the disk is full ({free} bytes free in {self.path.parent}); OpenCV's writer cannot "
            "write frames: free some space or write the video elsewhere"
        )

    def _create(self, path: Path, size: tuple[int, int]):
        if self.backend == "pyav":
            try:
                return _PyAvWriter(path, size, self.fps), "h264"
            except Exception as e:  # PyAV/FFmpeg raise their own types (av.error.*)
                raise SinkError(
                    f"video {self.path}: PyAV could not open an H.264 writer at {size[0]}x{size[1]}: "
                    f"{e}; check that the folder is writable, or write .avi (OpenCV MJPG)"
                ) from None
        tried = []
        for cc in self.codecs:
            w = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*cc), self.fps, size)
            if w.isOpened():
                return w, cc
            w.release()
            tried.append(cc)
        raise SinkError(
            f"video {self.path}: OpenCV's FFmpeg backend could not open a writer with codec(s) "
            f"{', '.join(tried)} at {size[0]}x{size[1]}; check that the folder exists and is writable, or use "
            f"another container (.avi with MJPG works in every OpenCV build)"
        )

    def open(self) -> None:
        if not self.path.parent.is_dir():
            raise SinkError(f"video {self.path}: folder {self.path.parent} does not exist")
        probe = self.path.with_name(f".{self.path.stem}.probe{self.path.suffix}")
        try:
            w, cc = self._create(probe, (64, 64))
            w.release()
        finally:
            probe.unlink(missing_ok=True)
        self.codec = cc

    def write(self, frame: Frame) -> None:
        img = output_picture(frame)
        size = (img.shape[1], img.shape[0])
        if self._writer is None:
            even = (size[0] + size[0] % 2, size[1] + size[1] % 2) if self.backend == "pyav" else size
            self._writer, self.codec = self._create(self.path, even)
            self._size = size
            log.info(
                "video %s: %dx%d at %.3g fps, codec %s (%s)",
                self.path,
                size[0],
                size[1],
                self.fps,
                self.codec,
                "PyAV" if self.backend == "pyav" else "OpenCV",
            )
        elif size != self._size:
            # VideoWriter would silently drop a frame of another size; say so instead
            raise SinkError(
                f"video {self.path}: frame {frame.seq} is {size[0]}x{size[1]}, the video is "
                f"{self._size[0]}x{self._size[1]}"
            )
        if self.backend == "pyav":
            try:
                self._writer.write(_even(img))
            except SinkError:
                raise
            except Exception as e:
                raise SinkError(f"video {self.path}: encoding failed: {type(e).__name__}: {e}") from e
        else:
            self._writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            try:
                size_now = self.path.stat().st_size
            except OSError:
                size_now = self._bytes
            if size_now > self._bytes:
                self._bytes, self._stalled = size_now, 0
            else:
                # FFmpeg buffers ~32 kB, so a small frame need not grow the file: look at the disk only
                # when the file stopped growing
                self._stalled += 1
                why = self._disk_full() if self._stalled >= 2 else None
                if why is not None:
                    raise SinkError(why)
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            w, self._writer = self._writer, None
            try:
                w.release()  # writes the container index (moov atom): the file is playable after this
            except Exception as e:
                raise SinkError(f"video {self.path}: finishing the file failed: {type(e).__name__}: {e}") from e
            why = self._disk_full() if self.backend == "opencv" else None  # PyAV raises; OpenCV is silent
            if why is not None:
                raise SinkError(f"{why} (the file's end, its index, may be missing)")

    def stats(self) -> dict:
        return {"frames": self.frames, "codec": self.codec, "backend": self.backend}


class PngSequenceSink(Sink):
    """Write each output picture as ``DIR/frame_<seq>.png`` (lossless).

    Parameters
    ----------
    directory : str or Path
        Created if missing.
    compression : int
        zlib level 0..9.
    """

    name = "png"

    def __init__(self, directory: str | os.PathLike, compression: int = 1):
        self.directory = Path(directory)
        self.compression = int(compression)
        self.frames = 0
        self._last_seq: int | None = None
        self.laps = 0  # times the sequence number did not increase: later names get "_r<laps>"

    def open(self) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SinkError(f"PNG sequence: cannot create folder {self.directory}: {e}") from None
        try:
            earlier = sum(1 for _ in self.directory.glob("frame_*.png"))
        except OSError:
            earlier = 0
        if earlier:
            # a folder reused after a longer run kept that run's last frames among this run's, unannounced
            log.warning(
                "PNG sequence %s already holds %d frame_*.png from an earlier run: this run's frames replace "
                "those of the same number and the others stay; use an empty folder to keep the runs apart",
                self.directory,
                earlier,
            )

    def write(self, frame: Frame) -> None:
        if self._last_seq is not None and frame.seq <= self._last_seq:
            # a source whose sequence numbers repeat or go back (a session's seq is not checked; only its
            # timestamps must increase) overwrote earlier PNGs: 6 frames of one seq left one file, exit 0
            self.laps += 1
            if self.laps == 1:
                log.warning(
                    "PNG sequence %s: frame seq %d does not follow %d; later files are named "
                    "frame_<seq>_r<N>.png so that none is overwritten",
                    self.directory,
                    frame.seq,
                    self._last_seq,
                )
        self._last_seq = frame.seq
        lap = f"_r{self.laps}" if self.laps else ""
        path = self.directory / f"frame_{frame.seq:06d}{lap}.png"
        bgr = cv2.cvtColor(output_picture(frame), cv2.COLOR_RGB2BGR)
        # fast filter set + Huffman-only: ~4x faster to encode than OpenCV's default, ~15 % larger
        params = [
            cv2.IMWRITE_PNG_COMPRESSION,
            self.compression,
            cv2.IMWRITE_PNG_FILTER,
            cv2.IMWRITE_PNG_FAST_FILTERS,
            cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
        ]
        # encoded in memory and written here: cv2.imwrite's libpng printed "libpng error: Write Error" three
        # times straight to descriptor 2 on a full disk, over the one line (and the loop's other threads
        # share that descriptor, so it is not silenced); a failed write also says why, and leaves no cut file
        ok, png = cv2.imencode(".png", bgr, params)
        if not ok:
            raise SinkError(f"PNG sequence: OpenCV could not encode frame {frame.seq} as PNG")
        try:
            with open(path, "wb") as f:
                f.write(png.data)
        except OSError as e:
            with contextlib.suppress(OSError):
                path.unlink()
            raise SinkError(f"PNG sequence: cannot write {path}: {e.strerror or e}") from None
        self.frames += 1

    def stats(self) -> dict:
        return {"frames": self.frames}


def _stdout_to_devnull():
    """After a broken pipe on standard output: point its descriptor at /dev/null, so that Python's own
    flush at exit does not print "Exception ignored ... BrokenPipeError" (the Python docs' recipe)."""
    import sys

    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)
    except (OSError, ValueError, AttributeError):
        pass
    return sys.stdout


#: lines a pipe, FIFO or socket given to ``--estimates`` may hold back for a reader that lags, on top of
#: the pipe's own buffer (64 kB); beyond that the oldest are dropped (``dropped_lines``)
PIPE_BACKLOG = 64
#: how long closing waits for the reader of such a pipe to take the last lines
PIPE_CLOSE_WAIT_S = 2.0


def _is_stream(fd: int) -> bool:
    """A pipe, FIFO or socket: what a reader that stops reading can block for ever."""
    import stat

    try:
        mode = os.fstat(fd).st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


class _PipeWriter:
    """Writes lines to a pipe, FIFO or socket on its own thread, so that a reader that stops reading but
    keeps the pipe open never blocks the loop (a blocked write() froze the whole stream, MJPEG too,
    and one SIGTERM could not stop it). Lines keep their order; when more than :data:`PIPE_BACKLOG`
    wait, the oldest is dropped and counted. The thread writes only when ``poll`` says the pipe has
    room, a chunk of at most ``PIPE_BUF`` bytes at a time, so it never blocks either and can always
    be stopped."""

    def __init__(self, fd: int, label: str) -> None:
        import collections

        self.fd, self.label = fd, label
        self.written = self.dropped = 0
        self.gone = False  # the reader closed its end (EPIPE)
        self._lines: collections.deque[bytes] = collections.deque()
        self._cond = threading.Condition()
        self._closing = self._abandon = False
        self._thread = threading.Thread(target=self._run, name="illuminet-estimates-writer", daemon=True)
        self._thread.start()

    def put(self, line: bytes) -> bool:
        """Queue one line; False when the reader has gone."""
        with self._cond:
            if self.gone:
                return False
            first = False
            if len(self._lines) >= PIPE_BACKLOG:
                self._lines.popleft()
                self.dropped += 1
                first = self.dropped == 1
            self._lines.append(line)
            self._cond.notify()
        if first:
            log.warning(
                "estimates %s: the reader is not keeping up; dropping the oldest lines so the stream goes on "
                "(their count, dropped_lines, is in the final statistics)",
                self.label,
            )
        return True

    def _run(self) -> None:
        import select

        poller = select.poll()
        poller.register(self.fd, select.POLLOUT)
        while True:
            with self._cond:
                while not self._lines and not self._closing:
                    self._cond.wait()
                if not self._lines:
                    return
                view = memoryview(self._lines.popleft())
            while view:
                if self._abandon:
                    with self._cond:
                        self.dropped += 1  # the line it was writing
                    return
                try:
                    if poller.poll(100):
                        view = view[os.write(self.fd, view[: select.PIPE_BUF]) :]
                except OSError as e:
                    with self._cond:
                        self.gone = True
                        self._lines.clear()
                    if not isinstance(e, (BrokenPipeError, ConnectionResetError)):
                        log.error("estimates %s: cannot write: %s; no more lines go there", self.label, e.strerror or e)
                    return
            with self._cond:
                self.written += 1

    def close(self, wait_s: float = PIPE_CLOSE_WAIT_S) -> None:
        """Let the thread write what is queued, for at most ``wait_s`` (a reader that stopped reading
        gets no more; those lines count as dropped)."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(wait_s)
        if self._thread.is_alive():
            self._abandon = True
            self._thread.join(1.0)
            with self._cond:
                self.dropped += len(self._lines)
                self._lines.clear()


class EstimateSink(Sink):
    """Write each frame's lighting estimate as one JSON line (JSONL) to a file (``--estimates FILE``).

    One object per frame that has an estimate (``results["light"]``; frames before the anchor is
    placed have none and write nothing), in the format of
    :func:`~illuminet.runtime.stream.estimate_json.estimate_dict` (``docs/estimate.md``). Lines are
    flushed as they are written, so ``tail -f FILE`` follows a live run.

    When the output is a pipe, FIFO or socket (``--estimates - | consumer``), lines go out on a writer
    thread (:class:`_PipeWriter`): a reader that stops reading never blocks the loop; it loses the
    oldest lines instead (``dropped_lines``), and closing waits for it at most
    :data:`PIPE_CLOSE_WAIT_S`. A regular file gets every line.

    Parameters
    ----------
    path : str or Path
        The file; ``-`` writes to standard output. An existing file is replaced.
    """

    name = "estimates"

    def __init__(self, path: str | os.PathLike):
        self.path = str(path)
        self._fh = None
        self._pipe: _PipeWriter | None = None
        self._pipe_gone = False
        self.frames = 0
        self.written = 0
        self.dropped = 0

    def open(self) -> None:
        if self.path == "-":
            import sys

            if sys.stdout is None:  # started with stdout closed (>&-): every frame failed "write() before open()"
                raise SinkError("estimates -: standard output is closed; give a file (--estimates FILE) instead")
            self._fh = sys.stdout
            self._start_pipe("-")
            return
        p = Path(self.path)
        if not p.parent.is_dir():
            raise SinkError(f"estimates {p}: folder {p.parent} does not exist")
        try:
            self._fh = open(p, "wb", buffering=0)  # unbuffered: each line goes out whole in write()
        except OSError as e:
            raise SinkError(f"estimates {p}: cannot write: {e.strerror or e}") from None
        self._whole = 0  # the file's length up to its last whole line
        self._error = None
        self._start_pipe(str(p))

    def _start_pipe(self, label: str) -> None:
        try:
            fd = self._fh.fileno()
        except (OSError, ValueError, AttributeError):  # not a real file (a test's StringIO)
            return
        if _is_stream(fd):
            self._fh.flush()
            self._pipe = _PipeWriter(fd, label)

    def write(self, frame: Frame) -> None:
        from illuminet.runtime.stream.estimate_json import frame_estimate, to_line

        if self._fh is None:
            raise RuntimeError("EstimateSink.write() before open()")
        self.frames += 1
        d = frame_estimate(frame)
        if d is None:
            return
        if self._pipe is not None:
            if not self._pipe.put(to_line(d).encode("utf-8") + b"\n"):
                self._reader_gone()
            return
        if self.path != "-":
            self._write_whole(to_line(d).encode("utf-8") + b"\n")
            self.written += 1
            return
        try:
            self._fh.write(to_line(d) + "\n")
            self._fh.flush()
        except BrokenPipeError:
            if self.path != "-":
                raise
            self._fh = _stdout_to_devnull()
            raise OutputClosed("estimates -: the reader of standard output has gone; the run ends") from None
        self.written += 1

    def _reader_gone(self) -> None:
        """The pipe's reader has closed its end: the run ends (once), as a Unix filter's does."""
        if self._pipe_gone:
            return
        self._pipe_gone = True
        if self.path == "-":
            self._fh = _stdout_to_devnull()
            raise OutputClosed("estimates -: the reader of standard output has gone; the run ends")
        raise OutputClosed(f"estimates {self.path}: its reader has gone; the run ends")

    def _write_whole(self, data: bytes) -> None:
        """Write one line to the file whole or not at all: a full disk (or a file size limit) that
        stops it half-way left a torn JSON line at the end of the file; it is cut back to the last
        whole line, and the error raised (the loop counts the frame as missing from this output)."""
        fh = self._fh
        try:
            view = memoryview(data)
            while view:
                view = view[fh.write(view) :]
        except OSError as e:
            try:
                fh.truncate(self._whole)
                fh.seek(self._whole)
            except OSError:  # a device (/dev/full) has no length to cut back
                pass
            self._error = e
            raise
        self._whole += len(data)
        self._error = None

    def close(self) -> None:
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            pipe.close()
            self.written, self.dropped = pipe.written, pipe.dropped
            if pipe.gone and self.path == "-" and not self._pipe_gone:
                _stdout_to_devnull()  # no "BrokenPipeError" noise from Python's flush at exit
        fh, self._fh = self._fh, None
        if fh is not None and self.path != "-":
            try:
                fh.close()
            except OSError as e:
                self._error = e
            if self._error is not None:  # the last lines were lost to a full disk: name the file
                e, self._error = self._error, None
                raise SinkError(f"estimates {self.path}: cannot write the last lines: {e.strerror or e}") from None

    def stats(self) -> dict:
        pipe = self._pipe
        if pipe is not None:
            return {"frames": self.frames, "estimates": pipe.written, "dropped_lines": pipe.dropped}
        return {"frames": self.frames, "estimates": self.written, "dropped_lines": self.dropped}


class SessionRecorderSink(Sink):
    """Record the input frames (colour, depth, metadata) as a session, off the loop thread.

    When a frame carries a lighting estimate (``results["light"]``) it is appended to the session's
    optional ``estimates.jsonl`` sidecar after the frame itself is committed
    (:meth:`~illuminet.runtime.stream.session.SessionWriter.append_estimate`), so a replay can be
    compared with what the live run estimated.

    Images are compressed on a small encoder pool (OpenCV's encoders release the GIL, so this uses the
    second core) and committed in order by one writer thread (files, fsync, index line). The queue is
    bounded: when the disk or the CPU is slower than the stream the loop waits (back-pressure) rather
    than silently losing frames of a recording; a live source's flow limiter then drops frames *before*
    the stages, where drops are counted.

    Parameters
    ----------
    path : str or Path
        New session folder.
    source : str
        Source URL stored in the manifest.
    color, jpeg_quality, png_compression, fsync
        See :class:`~illuminet.runtime.stream.session.SessionWriter`.
    queue_size : int
        Frames that may wait for the writer thread.
    encoders : int
        Threads compressing frames in parallel.
    """

    name = "record"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        source: str = "",
        color: str = "raw",
        jpeg_quality: int = 95,
        png_compression: int = DEFAULT_PNG_COMPRESSION,
        fsync: bool = True,
        queue_size: int = 8,
        encoders: int = 2,
    ):
        self.path = Path(path)
        self._writer_args = dict(
            source=source, color=color, jpeg_quality=jpeg_quality, png_compression=png_compression, fsync=fsync
        )
        self._queue_size = queue_size
        self._encoders = max(1, int(encoders))
        self._writer: SessionWriter | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._unreported = 0  # frames that failed since the last error write() raised
        self.lost = 0  # frames the writer thread could not commit

    def open(self) -> None:
        self._writer = SessionWriter(self.path, **self._writer_args)
        self._pool = ThreadPoolExecutor(max_workers=self._encoders, thread_name_prefix="illuminet-session-encode")
        self._queue = queue.Queue(maxsize=self._queue_size)
        self._thread = threading.Thread(target=self._run, name="illuminet-session-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fut, estimate = item
            try:
                i = self._writer.commit(fut.result())  # in submission order: the index stays in frame order
                if estimate is not None:
                    self._writer.append_estimate(i, estimate)
            except BaseException as e:  # reported on the next write() in the loop thread
                self._error = e
                self._unreported += 1
                self.lost += 1

    def write(self, frame: Frame) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            n, self._unreported = self._unreported, 0
            more = f" ({n} frames not recorded since the last report)" if n > 1 else ""
            raise SinkError(f"session recorder {self.path}: {err}{more}") from err
        estimate = None
        if frame.results:
            from illuminet.runtime.stream.estimate_json import frame_estimate

            estimate = frame_estimate(frame)  # a small dict: the sidecar line
            # only the input is recorded: drop results so the queue does not keep render buffers alive
            frame = frame.replace(results=MappingProxyType({}))
        self._queue.put((self._pool.submit(self._writer.encode, frame), estimate))

    @property
    def frames(self) -> int:
        return self._writer.count if self._writer is not None else 0

    def close(self) -> None:
        """Write the frames still queued, then finalise the manifest. Idempotent."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._writer is not None:
            try:
                self._writer.close()
            except OSError as e:  # a full disk: the line named neither the session nor what still replays
                if (self.path / "manifest.json").is_file():
                    left = f"the {self._writer.count} frames committed still replay"
                else:
                    left = "no manifest was written, so nothing replays"
                raise SinkError(
                    f"session recorder {self.path}: cannot finalise the manifest: {e.strerror or e}; {left} "
                    f"(illuminet replay {self.path} --check)"
                ) from None
            log.info("session %s: %d frames recorded", self.path, self._writer.count)
            if self._error is not None:
                # frames still queued at the end that failed: only logged before, so a recording that
                # lost them (a disk full while draining the queue) ended with exit status 0
                err, self._error = self._error, None
                n, self._unreported = self._unreported, 0
                raise SinkError(
                    f"session recorder {self.path}: {n} frame(s) queued at the end were not recorded: {err}"
                ) from err

    def stats(self) -> dict:
        return {"frames": self.frames, "lost": self.lost}
