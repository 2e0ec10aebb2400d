"""``illuminet bench mjpeg``: does watching the MJPEG stream slow the loop down?

Runs the streaming loop (``illuminet.runtime.stream.loop.run_loop``) on an in-memory source of 640x400
RGB-D frames with a light compositing stage, in three set-ups measured in the same run and
interleaved (so that load from other processes hits all of them alike):

* ``no sink``      -- the loop alone;
* ``0 clients``    -- with the MjpegSink attached, nobody watching;
* ``2 clients``    -- with two real HTTP clients (threads) reading ``/stream.mjpg`` over 127.0.0.1
                      and decoding nothing (they count bytes and parts, as a browser's network layer).

Throughput is 1 / the median per-frame loop time (source read + stage + sinks, from the loop's own
``total`` timing) over the repetitions; whole-run frames/s are printed too. The ratio 2 clients /
no sink is the figure with a target (>= 0.90). The stage is deliberately light (~0.1 ms), the
worst case for this ratio: in a real pipeline (tens of ms per frame) the preview's share is far
smaller. A set-up without the preview's 30 fps cap shows what encoding every frame would cost.
Nothing is read from ../shared/data.
"""

from __future__ import annotations

import argparse
import http.client
import logging
import statistics
import threading
import time

import cv2
import numpy as np

from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import COMPOSITE
from illuminet.runtime.stage import Source, Stage
from illuminet.runtime.stream.loop import run_loop
from illuminet.runtime.stream.mjpeg import BOUNDARY, MjpegSink

W, H = 640, 400


class _MemorySource(Source):
    """``n`` frames cycled from a small pool of distinct synthetic RGB-D images (no disk, no camera)."""

    name = "memory"
    live = False

    def __init__(self, n: int, pool: int = 8):
        rng = np.random.default_rng(0)
        yy, xx = np.mgrid[0:H, 0:W]
        self._pool = []
        for k in range(pool):
            # smooth gradients + texture: JPEG-compressible like a camera picture, not like noise
            base = np.stack([(xx * 255 // W + 20 * k) % 256, (yy * 255 // H), (xx + yy + 30 * k) % 256], -1)
            noise = rng.integers(0, 24, (H, W, 3))
            color = np.clip(base + noise, 0, 255).astype(np.uint8)
            depth = (1.0 + 0.5 * yy / H).astype(np.float32)
            self._pool.append((color, depth))
        self._intr = Intrinsics(500.0, 500.0, W / 2 - 0.5, H / 2 - 0.5, W, H)
        self.n = n
        self.i = 0

    def read(self) -> Frame | None:
        if self.i >= self.n:
            return None
        color, depth = self._pool[self.i % len(self._pool)]
        t = self.i * 33_333_333
        f = Frame(
            seq=self.i, t_device_ns=t, t_host_ns=time.monotonic_ns(), color=color, depth=depth, intrinsics=self._intr
        )
        self.i += 1
        return f


class _Composite(Stage):
    """A light per-frame stage standing in for the render: blends an overlay into the frame."""

    name = "composite"
    provides = (COMPOSITE,)

    def __init__(self):
        self._overlay = np.zeros((H, W, 3), np.uint8)
        cv2.circle(self._overlay, (W // 2, H // 2), 80, (200, 180, 160), -1)

    def process(self, frame: Frame) -> Frame:
        return frame.with_result(COMPOSITE, cv2.addWeighted(frame.color, 0.7, self._overlay, 0.3, 0.0))


def read_part(fp) -> int:
    """After a part's boundary line of a multipart MJPEG stream: read its headers and body, return
    the body's length in bytes."""
    length = 0
    while True:
        h = fp.readline().strip()
        if not h:
            break
        if h.lower().startswith(b"content-length:"):
            length = int(h.split(b":", 1)[1])
    return len(fp.read(length))


class _Client(threading.Thread):
    """A real HTTP client reading the MJPEG stream until stopped; counts parts and bytes."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.port = port
        self.parts = 0
        self.bytes = 0
        self.stop = threading.Event()
        self.ready = threading.Event()
        self.error: Exception | None = None

    def run(self) -> None:
        try:
            conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=5)
            conn.request("GET", "/stream.mjpg")
            resp = conn.getresponse()
            self.ready.set()
            marker = f"--{BOUNDARY}".encode()
            while not self.stop.is_set():
                line = resp.fp.readline()
                if not line:
                    break
                if line.strip() != marker:
                    continue
                self.bytes += read_part(resp.fp)
                self.parts += 1
            conn.close()
        except Exception as e:  # reported in the figures, not raised from a thread
            self.error = e
            self.ready.set()


#: set-up name -> MjpegSink max_fps (None = no sink)
MODES = {"no sink": None, "0 clients": 30.0, "2 clients": 30.0, "2 clients, no fps cap": 0.0}


def _one_run(n: int, mode: str) -> dict:
    source = _MemorySource(n)
    stages = [_Composite()]
    sinks: list = []
    clients: list[_Client] = []
    sink = None
    if MODES[mode] is not None:
        sink = MjpegSink(listen="127.0.0.1", port=0, max_fps=MODES[mode])
        sink.open()  # opened before the loop so clients can connect first; run_loop's open is a no-op then
        sinks.append(sink)
        if mode.startswith("2 clients"):
            clients = [_Client(sink.port) for _ in range(2)]
            for c in clients:
                c.start()
            for c in clients:
                c.ready.wait(5)
            # wait until the clients are registered (they count as watchers only once connected)
            deadline = time.monotonic() + 5
            while sink.stats()["clients"] < 2 and time.monotonic() < deadline:
                time.sleep(0.01)
    try:
        stats = run_loop(source, stages, sinks, install_signals=False)
    finally:
        for c in clients:
            c.stop.set()
        if sink is not None:
            sink.close()
        for c in clients:
            c.join(2)
    d = stats.to_dict()
    # per-frame loop time (source read + stage + sinks): its median ignores the moments another
    # process had the CPU, which whole-run averages on a shared machine do not
    out = {"fps": d["fps"], "frames": d["frames"], "frame_ms": d["steps"]["total"]["median_ms"]}
    if clients:
        out["client_parts"] = [c.parts for c in clients]
        out["client_errors"] = [str(c.error) for c in clients if c.error]
    if sink is not None:
        out["encoded"] = sink.stats()["encoded"]
    return out


def run(args: argparse.Namespace, cfg) -> dict:
    quick = bool(getattr(args, "quick", False))
    n = 500 if quick else 3000
    reps = 3 if quick else 5
    modes = list(MODES)
    runs: dict[str, list[dict]] = {m: [] for m in modes}
    mlog = logging.getLogger("illuminet.runtime.stream.mjpeg")
    level = mlog.level
    mlog.setLevel(logging.WARNING)  # one "serving at" line per run would drown the figures
    try:
        _one_run(100, "2 clients")  # warm-up: imports, thread start-up, first JPEG
        for r in range(reps):
            order = modes if r % 2 == 0 else modes[::-1]  # interleave to share drifting background load
            for m in order:
                runs[m].append(_one_run(n, m))
    finally:
        mlog.setLevel(level)
    result: dict = {"frames_per_run": n, "repetitions": reps, "size": f"{W}x{H}"}
    print(f"loop: in-memory {W}x{H} RGB-D source -> composite stage -> sinks; {n} frames x {reps} runs each")
    for m in modes:
        fps = [x["fps"] for x in runs[m]]
        frame_ms = statistics.median(x["frame_ms"] for x in runs[m])
        med = 1000.0 / frame_ms
        result[m] = {
            "median_fps": med,
            "median_frame_ms": frame_ms,
            "run_fps_median": statistics.median(fps),
            "run_fps_min": min(fps),
            "run_fps_max": max(fps),
        }
        extra = ""
        if m != "no sink":
            enc = [x["encoded"] for x in runs[m]]
            result[m]["median_encoded"] = statistics.median(enc)
            extra = f"; JPEGs encoded per run (median) {statistics.median(enc):.0f}"
        if m.startswith("2 clients"):
            parts = [p for x in runs[m] for p in x["client_parts"]]
            errors = [e for x in runs[m] for e in x.get("client_errors", [])]
            result[m]["median_client_frames"] = statistics.median(parts)
            result[m]["client_errors"] = errors
            extra += f"; frames each client received (median) {statistics.median(parts):.0f}"
            if errors:
                extra += f"; client errors: {errors[:2]}"
        print(
            f"  {m:<21} median {frame_ms * 1000:7.1f} us/frame = {med:7.1f} frames/s  (whole runs: median "
            f"{statistics.median(fps):.0f}, min {min(fps):.0f}, max {max(fps):.0f} frames/s){extra}"
        )
    ratio = result["2 clients"]["median_fps"] / result["no sink"]["median_fps"]
    ratio0 = result["2 clients"]["median_fps"] / result["0 clients"]["median_fps"]
    result["ratio_2_clients_vs_none"] = ratio
    result["ratio_2_clients_vs_0_clients"] = ratio0
    ratio_nocap = result["2 clients, no fps cap"]["median_fps"] / result["no sink"]["median_fps"]
    result["ratio_2_clients_no_cap_vs_none"] = ratio_nocap
    print(
        f"  ratio 2 clients / no sink: {ratio:.3f}   (2 clients / 0 clients: {ratio0:.3f}); "
        f"target >= 0.90: {'met' if ratio >= 0.90 else 'NOT met'}"
    )
    print(f"  without the 30 fps preview cap (a JPEG for every frame the encoder can take): {ratio_nocap:.3f}")
    return result
