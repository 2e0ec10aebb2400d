"""``replay://PATH?timing=recorded|asap&loop=1&max_frames=N``: play a recorded session as a source.

This module owns replay timing. ``timing=recorded`` sleeps so frames come out at the pace their
timestamps say, and the source reports itself as *live*: the loop's flow limiter then behaves exactly as
with a camera (drops counted when the pipeline is slower). ``timing=asap`` delivers every frame as fast
as it can be decoded and drops nothing (tests, benchmarks). Decoding runs ahead on a small thread pool
(OpenCV's PNG decoder releases the GIL), which is what makes asap replay of 640x400 RGB-D fast on two
cores. With ``loop=1`` the session starts again at the end; sequence numbers and device timestamps keep
increasing across restarts (a stage never sees time go backwards).

Defaults come from the ``[source]`` section (``timing``, ``loop``, ``max_frames``); the URL query
overrides them. ``PATH`` is relative to the working directory (``replay://runs/s1``) or absolute
(``replay:///data/s1``).
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from concurrent.futures import CancelledError, ThreadPoolExecutor
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np

from illuminet.hw import SourceError, SourceURLError, parse_query, query_bool, query_choice, query_int
from illuminet.runtime.config import Config
from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import REPLAY_POSITION
from illuminet.runtime.stage import EndOfStream, Source
from illuminet.runtime.stream.session import MAX_FRAME_GAP_NS, CorruptFrame, SessionError, SessionReader

log = logging.getLogger(__name__)

TIMINGS = ("recorded", "asap")


class ReplaySource(Source):
    """Frames of a recorded session.

    Parameters
    ----------
    path : str or Path
        Session folder (see :mod:`illuminet.runtime.stream.session`).
    timing : {"recorded", "asap"}
        Follow the recorded timestamps (live-like) or go as fast as possible (drops nothing).
    loop : bool
        Start again at the end, with increasing sequence numbers and timestamps.
    max_frames : int
        End after this many frames (0 = no limit; with ``loop`` the stream is endless otherwise).
    workers : int
        Decoder threads running ahead of the loop.
    strict : bool
        Refuse a session with any problem instead of replaying its intact part.
    """

    name = "replay"
    #: every frame carries its (lap, position in the recording): with ``loop`` the world-locked anchor
    #: puts the camera back at the recording's start when a new lap begins (odometry drift does not
    #: add up lap after lap)
    provides = (REPLAY_POSITION,)

    def __init__(
        self,
        path: str | Path,
        *,
        timing: str = "recorded",
        loop: bool = False,
        max_frames: int = 0,
        workers: int = 2,
        strict: bool = False,
    ):
        if timing not in TIMINGS:
            raise SourceError(f"replay {path}: timing must be one of {', '.join(TIMINGS)}, got {timing!r}")
        if max_frames < 0:
            raise SourceError(f"replay {path}: max_frames must be >= 0, got {max_frames!r}")
        self.path = Path(path)
        self.timing = timing
        self.loop = bool(loop)
        self.max_frames = int(max_frames)
        self.workers = max(1, int(workers))
        self.strict = strict
        self.session: SessionReader | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._pending: collections.deque = collections.deque()
        self._next_pos = 0  # next session position to schedule for decoding
        self._next_round = 0  # loop round of that position
        self._emitted = 0
        self._corrupt = 0
        self._bad_in_row = 0
        self._warned: set[int] = set()  # session positions whose damage was logged (a loop meets them again)
        self._t0_wall: int | None = None
        self._closed = False
        self._closing = threading.Event()
        self._cpu_lock = threading.Lock()
        self._decode_cpu_s = 0.0
        self._decoded = 0

    @property
    def live(self) -> bool:  # type: ignore[override]
        """Recorded timing behaves like a camera (flow-limited); asap never drops."""
        return self.timing == "recorded"

    @property
    def drop_advice(self) -> str:
        """What the loop logs (once) when it drops frames of this source: the fix, for a replay."""
        if self.timing != "recorded":
            return ""
        return (
            f"replay {self.path}: the pipeline is slower than the recording, so frames are skipped to keep "
            "up with the recorded timing; to process every frame use --timing asap ([source] timing = "
            '"asap", or replay://...?timing=asap)'
        )

    def open(self) -> None:
        try:
            self.session = SessionReader(self.path, strict=self.strict)
        except SessionError as e:
            raise SourceError(f"replay: {e}") from None
        n = len(self.session)
        if n == 0:
            detail = "; ".join(self.session.problems) or "the index lists no frames"
            raise SourceError(f"replay {self.path}: no intact frame to replay ({detail})")
        e = self.session.entries
        self._first_t = e[0].t_device_ns
        gaps = np.diff([x.t_device_ns for x in e])
        self._period = int(np.median(gaps)) if gaps.size else 33_333_333
        if not 0 < self._period <= MAX_FRAME_GAP_NS:  # a session made mostly of gaps: pace at 30 fps
            self._period = 33_333_333
        for gap in self.session.gaps:
            log.warning("replay %s: %s", self.path, gap)
        # a loop round lasts the recording plus one frame period, so the restart keeps the frame rate
        self._round_ns = e[-1].t_device_ns - e[0].t_device_ns + self._period
        self._round_seq = e[-1].seq - e[0].seq + 1
        self._pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="illuminet-replay")
        self._closing.clear()
        self._closed = False
        self._pending.clear()
        self._next_pos = self._next_round = self._emitted = self._corrupt = self._bad_in_row = 0
        self._t0_wall = None
        self._t_wall = 0  # wall-clock time (monotonic ns) the previous frame was due
        self._t_prev = 0  # its device timestamp
        self._fill()

    def _fill(self) -> None:
        # keep a few frames decoding ahead; order is preserved by the deque
        n = len(self.session)
        pool = self._pool
        while pool is not None and len(self._pending) < 2 * self.workers:
            if self._next_pos >= n:
                if not self.loop:
                    return
                self._next_pos, self._next_round = 0, self._next_round + 1
            pos, rnd = self._next_pos, self._next_round
            try:
                fut = pool.submit(self._decode, pos)
            except RuntimeError:  # the pool was shut down by close() meanwhile
                return
            self._pending.append((pos, rnd, fut))
            self._next_pos += 1

    def _decode(self, pos: int) -> Frame:
        """One frame decoded on a pool thread; its thread CPU time is counted (``decode_cpu_ms``)."""
        c0 = time.thread_time()
        try:
            return self.session.read(pos)
        finally:
            dt = time.thread_time() - c0
            with self._cpu_lock:
                self._decode_cpu_s += dt
                self._decoded += 1

    def read(self) -> Frame | None:
        if self._closed or self.session is None:
            return None
        if self.max_frames and self._emitted >= self.max_frames:
            return None
        while True:
            if self._closed:  # close() from another thread (the loop stopping)
                return None
            self._fill()
            if not self._pending:
                return None
            try:
                pos, rnd, fut = self._pending.popleft()
            except IndexError:  # emptied by close() from another thread
                return None
            try:
                frame: Frame = fut.result()
            except CancelledError:  # close() cancelled the decode we were waiting for
                return None
            except CorruptFrame as e:
                self._corrupt += 1
                self._bad_in_row += 1
                # once per damaged frame: a looped replay (demo --mjpeg, --loop) meets it every round
                level = logging.DEBUG if pos in self._warned else logging.WARNING
                self._warned.add(pos)
                log.log(level, "replay %s: skipping frame: %s", self.path, e)
                if self._bad_in_row >= len(self.session):
                    raise EndOfStream(f"replay {self.path}: every frame of the session is unreadable") from None
                continue
            self._bad_in_row = 0
            break
        t_dev = frame.t_device_ns + rnd * self._round_ns
        if self.timing == "recorded":
            now = time.monotonic_ns()
            if self._t0_wall is None:
                self._t0_wall = self._t_wall = now
            else:
                # each frame is due one recorded interval after the previous one's due time (no drift),
                # but a jump over MAX_FRAME_GAP_NS (a corrupt or edited index) is a gap, not minutes to
                # centuries of waiting: it counts as one frame period (logged once per gap at open())
                step = t_dev - self._t_prev
                if not 0 <= step <= MAX_FRAME_GAP_NS:
                    step = self._period
                self._t_wall += step
            self._t_prev = t_dev
            delay = self._t_wall - now
            if delay > 0 and self._closing.wait(delay * 1e-9):
                return None  # closed while waiting
        self._emitted += 1
        frame = frame.replace(seq=frame.seq + rnd * self._round_seq, t_device_ns=t_dev, t_host_ns=time.monotonic_ns())
        return frame.with_result(REPLAY_POSITION, (rnd, pos))

    def close(self) -> None:
        self._closed = True
        self._closing.set()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._pending.clear()

    def stats(self) -> dict:
        with self._cpu_lock:
            cpu_ms = self._decode_cpu_s / self._decoded * 1e3 if self._decoded else 0.0
        return {
            "frames": self._emitted,
            "corrupt": self._corrupt,
            "session_problems": len(self.session.problems) if self.session is not None else 0,
            # CPU time the decoder threads spent per decoded frame (a camera delivers pixels instead)
            "decode_cpu_ms": round(cpu_ms, 3),
        }


def session_folder(url: str) -> Path | None:
    """The session folder a ``replay://`` URL reads (None for another scheme, no path, or no URL at
    all: ``open_source`` then says what is wrong with it)."""
    try:
        parts = urlsplit(url)
    except ValueError:  # "Invalid IPv6 URL" for an unbalanced '[' (synthetic://[): a traceback before
        return None
    path = _url_path(parts)
    # a NUL byte (%00) names no folder: open_url refuses it with its line
    return Path(path) if parts.scheme == "replay" and path and "\x00" not in path else None


def _url_path(parts) -> str:
    """The session path of a split ``replay://`` URL, ``~`` expanded (no shell expands it inside a
    URL: ``replay://~/sessions/s1`` was looked for in a folder named ``~``)."""
    path = unquote(parts.netloc + parts.path)
    return os.path.expanduser(path) if path.startswith("~") and "\x00" not in path else path


def open_url(url: str, config: Config) -> ReplaySource:
    """``replay://PATH[?timing=recorded|asap][&loop=1][&max_frames=N]`` -> unopened :class:`ReplaySource`."""
    parts = urlsplit(url)
    path = _url_path(parts)
    if not path:
        raise SourceError(f"{url}: no session path; expected replay://PATH (relative) or replay:///ABS/PATH")
    if "\x00" in path:  # %00: every file call raised "embedded null byte" as a traceback
        raise SourceURLError(f"{url}: the session path contains a NUL byte (%00); expected replay://PATH to a folder")
    src = config.source
    q = parse_query(
        url, {"timing": query_choice(*TIMINGS), "loop": query_bool, "max_frames": query_int(lo=0)}, error=SourceError
    )
    timing, loop, max_frames = q.get("timing", src.timing), q.get("loop", src.loop), q.get("max_frames", src.max_frames)
    return ReplaySource(path, timing=timing, loop=loop, max_frames=max_frames, strict=config.logging.strict)
