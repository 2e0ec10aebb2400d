"""MJPEG over HTTP: a sink that serves the composited stream and a small live status page.

This module owns the HTTP preview server. Routes::

    GET /             HTML page: the stream plus live figures (fps, drops, stage times)
    GET /stream.mjpg  multipart/x-mixed-replace MJPEG stream (browsers, VLC, ffplay, headsets)
    GET /stats.json   the figures the page polls: the sink's own counters + ``stats()`` if given

How a frame travels, and why the loop never waits for a client::

    loop thread ── write(frame) ──▶ newest-frame slot (a reference, O(1); a newer frame replaces it)
                                          │
    encoder thread ◀──────────────────────┘ encodes the newest frame ONCE (only while clients watch)
          │
          └──▶ latest JPEG (bytes, sequence number) ──▶ client thread 1 ── socket
                                                    └─▶ client thread 2 ── socket ...

* JPEG encoding happens at most once per frame whatever the number of clients, not at all while
  nobody watches, and at most ``max_fps`` times a second (default 30: a viewer's display rate).
  It runs in its own thread (``cv2.imencode`` releases the GIL), so the loop only pays for storing
  a reference.
* Each client thread sends the latest encoded frame it has not sent yet. A slow client simply skips
  frames: it never holds the encoder or the loop back.
* The server binds 127.0.0.1 by default. ``listen="0.0.0.0"`` serves the local network (a headset);
  there is no authentication, so only do that on a network you trust.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import cv2
import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import COMPOSITE
from illuminet.runtime.stage import Sink

log = logging.getLogger(__name__)

BOUNDARY = "illuminetframe"

_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>IllumiNet-edge</title>
<style>
 body { font-family: system-ui, sans-serif; background: #111; color: #ddd; margin: 0; }
 main { display: flex; flex-wrap: wrap; gap: 1em; padding: 1em; }
 img { max-width: 100%; height: auto; background: #000; }
 table { border-collapse: collapse; font-variant-numeric: tabular-nums; }
 td, th { padding: 0.15em 0.6em; text-align: right; border-bottom: 1px solid #333; }
 td:first-child, th:first-child { text-align: left; }
 #err { color: #f88; }
</style></head>
<body><main>
<div><img id="stream" src="/stream.mjpg" alt="live stream"></div>
<div>
 <h3>Live</h3>
 <table id="summary"></table>
 <h3>Stage times (median, ms)</h3>
 <table id="stages"></table>
 <p id="err"></p>
</div>
</main>
<script>
function row(k, v) { return "<tr><td>" + k + "</td><td>" + v + "</td></tr>"; }
function fmt(v) { return (typeof v === "number") ? (Number.isInteger(v) ? v : v.toFixed(2)) : JSON.stringify(v); }
async function poll() {
  try {
    const r = await fetch("/stats.json", {cache: "no-store"});
    const s = await r.json();
    const loop = s.loop || {};
    let h = row("output fps", fmt(s.sink.fps));
    for (const k of ["fps_recent", "fps", "frames", "dropped", "failed_frames", "sink_failures"]) {
      if (k in loop) h += row(k, fmt(loop[k]));
    }
    h += row("clients", s.sink.clients) + row("frames encoded", s.sink.encoded);
    for (const [k, v] of Object.entries(loop.source || {})) h += row("source " + k, fmt(v));
    document.getElementById("summary").innerHTML = h;
    let t = "";
    for (const [k, v] of Object.entries(loop.stages_ms || {})) t += row(k, fmt(v));
    document.getElementById("stages").innerHTML = t;
    document.getElementById("err").textContent = loop.error || "";
  } catch (e) {
    document.getElementById("err").textContent = "stats unavailable: " + e;
  }
}
poll(); setInterval(poll, 1000);
</script>
</body></html>
"""


class _Hub:
    """Shared state between the loop (``offer``), the encoder thread and the client threads.

    One lock, two conditions: ``frame_cond`` wakes the encoder (a new frame while someone watches),
    ``cond`` wakes the client threads (a new JPEG). The loop notifies only when the encoder is
    actually waiting for a frame, so a fast loop does not wake a thread (and fight it for the GIL)
    on every frame.
    """

    def __init__(self, quality: int, max_fps: float = 0.0):
        self.quality = int(quality)
        self.min_interval = 1.0 / max_fps if max_fps > 0 else 0.0
        self.lock = threading.Lock()
        self.cond = threading.Condition(self.lock)        # new JPEG -> client threads
        self.frame_cond = threading.Condition(self.lock)  # new frame / new client -> encoder
        self.closed_event = threading.Event()
        self.pending: np.ndarray | None = None  # newest RGB image not yet encoded
        self.pending_seq = 0
        self.jpeg: bytes | None = None
        self.jpeg_seq = 0
        self.clients = 0
        self.closed = False
        self.encoder_waiting = False
        self.offered = 0
        self.encoded = 0
        self.sent = 0
        self._times: collections.deque[float] = collections.deque(maxlen=60)

    def offer(self, rgb: np.ndarray) -> None:
        with self.lock:
            self.pending = rgb
            self.pending_seq += 1
            self.offered += 1
            self._times.append(time.monotonic())
            if self.encoder_waiting and self.clients > 0:
                self.frame_cond.notify()

    def fps(self) -> float:
        with self.lock:
            t = list(self._times)
        if len(t) < 2 or t[-1] <= t[0]:
            return 0.0
        return (len(t) - 1) / (t[-1] - t[0])

    def encoder(self) -> None:
        """Encoder thread: encode the newest offered image once, while at least one client watches."""
        last = 0
        params = [int(cv2.IMWRITE_JPEG_QUALITY), self.quality]
        next_time = 0.0
        while True:
            # the preview rate cap: a viewer needs no more than its display rate, and the CPU saved
            # stays with the loop (the newest frame at the next slot is encoded; the rest skipped)
            wait = next_time - time.monotonic()
            if wait > 0 and self.closed_event.wait(wait):
                return
            with self.lock:
                self.encoder_waiting = True
                while not self.closed and (self.pending_seq == last or self.clients == 0):
                    self.frame_cond.wait(0.5)
                self.encoder_waiting = False
                if self.closed:
                    return
                img, last = self.pending, self.pending_seq
                self.pending = None  # drop the reference: the loop's frame can be freed
            if img is None:
                continue
            next_time = time.monotonic() + self.min_interval
            try:
                ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), params)
            except cv2.error as e:  # a bad image must not kill the server
                log.warning("MJPEG: could not encode a %s %s image: %s", img.shape, img.dtype, e)
                continue
            if not ok:
                continue
            with self.lock:
                self.jpeg, self.jpeg_seq = buf.tobytes(), last
                self.encoded += 1
                self.cond.notify_all()

    def next_jpeg(self, after: int, timeout: float) -> tuple[bytes | None, int]:
        """The latest JPEG newer than ``after`` (waits up to ``timeout``); (None, after) on timeout/close."""
        with self.cond:
            deadline = time.monotonic() + timeout
            while not self.closed and (self.jpeg is None or self.jpeg_seq == after):
                left = deadline - time.monotonic()
                if left <= 0:
                    return None, after
                self.cond.wait(left)
            if self.closed:
                return None, after
            return self.jpeg, self.jpeg_seq

    def add_client(self, delta: int) -> None:
        with self.lock:
            self.clients += delta
            self.frame_cond.notify()

    def close(self) -> None:
        with self.lock:
            self.closed = True
            self.cond.notify_all()
            self.frame_cond.notify_all()
        self.closed_event.set()


def _make_handler(sink: MjpegSink):
    hub = sink._hub

    class Handler(BaseHTTPRequestHandler):
        server_version = "IllumiNet-MJPEG/1"
        protocol_version = "HTTP/1.1"
        timeout = 30  # idle keep-alive connections (the page's stats polling) are closed after this

        def log_message(self, fmt: str, *args: Any) -> None:  # route to logging, not stderr
            log.debug("MJPEG %s: " + fmt, self.address_string(), *args)

        def _send_bytes(self, body: bytes, ctype: str, status: HTTPStatus = HTTPStatus.OK) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802 (http.server naming)
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                self._send_bytes(_PAGE.encode(), "text/html; charset=utf-8")
            elif path == "/stats.json":
                body = json.dumps(sink.status(), default=str).encode()
                self._send_bytes(body, "application/json")
            elif path == "/stream.mjpg":
                self._stream()
            else:
                self._send_bytes(b"not found; try / or /stream.mjpg or /stats.json\n",
                                 "text/plain; charset=utf-8", HTTPStatus.NOT_FOUND)

        def _stream(self) -> None:
            self.close_connection = True
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            # a client that stops reading for this long is dropped rather than kept forever
            self.connection.settimeout(sink.client_timeout_s)
            hub.add_client(+1)
            seq = 0
            try:
                while True:
                    jpeg, new_seq = hub.next_jpeg(seq, timeout=0.5)
                    if hub.closed:
                        return
                    if jpeg is None:
                        continue
                    seq = new_seq
                    head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                            f"Content-Length: {len(jpeg)}\r\n\r\n").encode()
                    self.wfile.write(head + jpeg + b"\r\n")
                    self.wfile.flush()
                    with hub.cond:
                        hub.sent += 1
            except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
                return  # the client went away (or stalled): normal for a preview stream
            finally:
                hub.add_client(-1)

    return Handler


class MjpegSink(Sink):
    """Serve the stream as MJPEG over HTTP with a live status page (see the module docstring).

    Parameters
    ----------
    listen : str
        Bind address. ``"127.0.0.1"`` (default) is this machine only; ``"0.0.0.0"`` the local network.
    port : int
        TCP port; 0 picks a free one (read :attr:`port` after :meth:`open`).
    stats : callable, optional
        Returns a JSON-serialisable dict of loop figures shown on the page, e.g. the streaming loop's
        ``LoopStats.snapshot`` (keys used by the page: ``fps``, ``fps_recent``, ``frames``,
        ``dropped``, ``failed_frames``, ``stages_ms``, ``source``; others are passed through).
    quality : int
        JPEG quality 1..100.
    max_fps : float
        Most frames per second encoded for the clients (0 = every frame the loop writes). The
        stream shows the newest frame at each slot; frames between slots are skipped, not queued.
    client_timeout_s : float
        A client that accepts no data for this long is disconnected.

    Attributes
    ----------
    port : int
        The port actually bound (after :meth:`open`).
    url : str
        ``http://HOST:PORT/`` of the page (after :meth:`open`).
    """

    name = "mjpeg"

    def __init__(self, listen: str = "127.0.0.1", port: int = 8080,
                 stats: Callable[[], dict[str, Any]] | None = None, quality: int = 80,
                 client_timeout_s: float = 10.0, max_fps: float = 30.0):
        if not (1 <= int(quality) <= 100):
            raise ValueError(f"MjpegSink quality must be within 1..100, got {quality!r}")
        if not (0 <= int(port) <= 65535):
            raise ValueError(f"MjpegSink port must be within 0..65535, got {port!r}")
        self.listen = str(listen)
        self.port = int(port)
        self.stats_fn = stats
        self.client_timeout_s = float(client_timeout_s)
        if max_fps < 0:
            raise ValueError(f"MjpegSink max_fps must be >= 0 (0 = no cap), got {max_fps!r}")
        self._quality = int(quality)
        self.max_fps = float(max_fps)
        self._hub = _Hub(self._quality, self.max_fps)
        self._server: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.listen in ("0.0.0.0", "") else self.listen
        return f"http://{host}:{self.port}/"

    def open(self) -> None:
        """Bind the port and start the server and encoder threads."""
        if self._server is not None:
            return
        self._hub = _Hub(self._quality, self.max_fps)
        try:
            server = ThreadingHTTPServer((self.listen, self.port), _make_handler(self))
        except OSError as e:
            raise OSError(
                f"MJPEG server cannot listen on {self.listen}:{self.port}: {e.strerror or e}. "
                f"Pick another port ([output] port, or 0 for any free one) or stop what uses it."
            ) from e
        server.daemon_threads = True  # client threads never keep the process alive
        self._server = server
        self.port = server.server_address[1]
        self._threads = [
            threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2},
                             name="illuminet-mjpeg-http", daemon=True),
            threading.Thread(target=self._hub.encoder, name="illuminet-mjpeg-encoder", daemon=True),
        ]
        for t in self._threads:
            t.start()
        if self.listen in ("0.0.0.0", "", "::"):
            log.info("MJPEG server on all interfaces, port %d: open http://<this machine's address>:%d/ "
                     "on the headset (locally %s)", self.port, self.port, self.url)
        else:
            log.info("MJPEG stream at %sstream.mjpg (status page %s)", self.url, self.url)

    def write(self, frame: Frame) -> None:
        """Offer ``frame.results["composite"]`` (or the camera colour) to the clients; O(1)."""
        if self._server is None:
            raise RuntimeError("MjpegSink.write() before open()")
        img = frame.results.get(COMPOSITE.name, frame.color)
        if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8):
            raise ValueError(
                "MjpegSink expects results['composite'] (or colour) as an HxWx3 uint8 RGB array, got "
                f"{getattr(img, 'shape', type(img))} {getattr(img, 'dtype', '')}"
            )
        self._hub.offer(img)

    def status(self) -> dict[str, Any]:
        """What ``/stats.json`` returns: ``{"sink": {...}, "loop": stats() or {}}``."""
        hub = self._hub
        with hub.cond:
            sink = {"frames": hub.offered, "encoded": hub.encoded, "sent": hub.sent, "clients": hub.clients}
        sink["fps"] = round(hub.fps(), 2)
        loop: dict[str, Any] = {}
        if self.stats_fn is not None:
            try:
                loop = dict(self.stats_fn())
            except Exception as e:  # the page must keep working while the loop misbehaves
                loop = {"error": f"stats() failed: {type(e).__name__}: {e}"}
        return {"sink": sink, "loop": loop}

    def stats(self) -> dict[str, Any]:
        hub = self._hub
        return {"clients": hub.clients, "encoded": hub.encoded, "sent": hub.sent, "port": self.port}

    def close(self) -> None:
        """Stop serving: clients are disconnected, threads end, the port is released. Idempotent."""
        server, self._server = self._server, None
        self._hub.close()
        if server is not None:
            server.shutdown()
            server.server_close()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
