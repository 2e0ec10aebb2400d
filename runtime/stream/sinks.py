"""Output sinks: video file, PNG sequence, session recorder, null. (The MJPEG server is in mjpeg.py.)

This module owns writing finished frames to files. Picture sinks write
``frame.results.get("composite", frame.color)`` -- the renderer's output when there is one, else the
camera picture -- converting RGB to OpenCV's BGR. The session recorder writes the *input* frame
(colour, depth, metadata; never the results) in the format of :mod:`illuminet.runtime.stream.session`.
"""

from __future__ import annotations

import logging
import os
import queue
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


class SinkError(RuntimeError):
    """An output cannot be opened or written; the message names the path and what to do."""


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
#: wheels usually lack, so it is the fallback, not the first choice.
VIDEO_CODECS: dict[str, tuple[str, ...]] = {
    ".mp4": ("mp4v", "avc1"),
    ".m4v": ("mp4v", "avc1"),
    ".mov": ("mp4v", "avc1"),
    ".avi": ("MJPG", "XVID", "mp4v"),
    ".mkv": ("mp4v", "MJPG", "avc1"),
}


class VideoSink(Sink):
    """Write the output pictures to a video file with OpenCV's FFmpeg backend.

    Parameters
    ----------
    path : str or Path
        ``.mp4``, ``.m4v``, ``.mov``, ``.avi`` or ``.mkv``.
    fps : float
        Frame rate written into the file.
    codecs : sequence of str, optional
        FourCC codes to try in order; default from :data:`VIDEO_CODECS` by extension.

    Notes
    -----
    :meth:`open` checks at once that a writer can be created (a tiny probe file), so a missing codec or
    an unwritable folder is reported before the stream starts, not on the first frame. The real writer
    is created on the first frame, whose size every later frame must have.
    """

    name = "video"

    def __init__(self, path: str | os.PathLike, fps: float = 30.0, codecs: tuple[str, ...] | None = None):
        self.path = Path(path)
        ext = self.path.suffix.lower()
        if codecs is None:
            if ext not in VIDEO_CODECS:
                raise SinkError(
                    f"video {self.path}: unknown extension {ext!r}; expected one of {', '.join(VIDEO_CODECS)}"
                )
            codecs = VIDEO_CODECS[ext]
        if not fps > 0:
            raise SinkError(f"video {self.path}: fps must be > 0, got {fps!r}")
        self.fps = float(fps)
        self.codecs = tuple(codecs)
        self.codec: str | None = None
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def _create(self, path: Path, size: tuple[int, int]) -> tuple[cv2.VideoWriter, str]:
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
            self._writer, self.codec = self._create(self.path, size)
            self._size = size
            log.info("video %s: %dx%d at %.3g fps, codec %s", self.path, size[0], size[1], self.fps, self.codec)
        elif size != self._size:
            # VideoWriter would silently drop a frame of another size; say so instead
            raise SinkError(f"video {self.path}: frame {frame.seq} is {size[0]}x{size[1]}, the video is "
                            f"{self._size[0]}x{self._size[1]}")
        self._writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()  # writes the container index (moov atom): the file is playable after this
            self._writer = None

    def stats(self) -> dict:
        return {"frames": self.frames, "codec": self.codec}


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

    def open(self) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SinkError(f"PNG sequence: cannot create folder {self.directory}: {e}") from None

    def write(self, frame: Frame) -> None:
        path = self.directory / f"frame_{frame.seq:06d}.png"
        bgr = cv2.cvtColor(output_picture(frame), cv2.COLOR_RGB2BGR)
        # fast filter set + Huffman-only: ~4x faster to encode than OpenCV's default, ~15 % larger
        params = [cv2.IMWRITE_PNG_COMPRESSION, self.compression, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FAST_FILTERS,
                  cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
        if not cv2.imwrite(str(path), bgr, params):
            raise SinkError(f"PNG sequence: OpenCV could not write {path} (disk full or not writable?)")
        self.frames += 1

    def stats(self) -> dict:
        return {"frames": self.frames}


class SessionRecorderSink(Sink):
    """Record the input frames (colour, depth, metadata) as a session, off the loop thread.

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
        self._writer_args = dict(source=source, color=color, jpeg_quality=jpeg_quality,
                                 png_compression=png_compression, fsync=fsync)
        self._queue_size = queue_size
        self._encoders = max(1, int(encoders))
        self._writer: SessionWriter | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def open(self) -> None:
        self._writer = SessionWriter(self.path, **self._writer_args)
        self._pool = ThreadPoolExecutor(max_workers=self._encoders, thread_name_prefix="illuminet-session-encode")
        self._queue = queue.Queue(maxsize=self._queue_size)
        self._thread = threading.Thread(target=self._run, name="illuminet-session-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            fut = self._queue.get()
            if fut is None:
                return
            try:
                self._writer.commit(fut.result())  # in submission order: the index stays in frame order
            except BaseException as e:  # reported on the next write() in the loop thread
                self._error = e

    def write(self, frame: Frame) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise SinkError(f"session recorder {self.path}: {err}") from err
        # only the input is recorded: drop results so the queue does not keep render buffers alive
        if frame.results:
            frame = frame.replace(results=MappingProxyType({}))
        self._queue.put(self._pool.submit(self._writer.encode, frame))

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
            self._writer.close()
            if self._error is not None:
                log.error("session recorder %s: last frame failed: %s", self.path, self._error)
            log.info("session %s: %d frames recorded", self.path, self._writer.count)

    def stats(self) -> dict:
        return {"frames": self.frames}
