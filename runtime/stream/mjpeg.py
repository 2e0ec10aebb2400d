"""MJPEG over HTTP: a sink that serves the composited stream, the lighting estimate and browser pages.

This module owns the HTTP preview server. Routes::

    GET /                     the live picture full-window (object-fit: contain) with a toggleable
                              overlay: fps, drops, stage times, the current light (direction, colour)
    GET /viewer               three.js page: a glTF model lit live by the estimate (LightProbe from the
                              SH, a shadow-casting DirectionalLight from the primary light)
    GET /stream.mjpg          multipart/x-mixed-replace MJPEG stream (browsers, VLC, ffplay, headsets);
                              ?source=camera: the camera picture without the object
    GET /estimates            the lighting estimate as Server-Sent Events, one JSON object per event
    GET /estimate.json        the latest estimate (``null`` before the first one)
    GET /stats.json           the sink's counters, ``stats()`` if given, and the latest estimate
    GET /model.glb            the viewer's model (``viewer_model``)
    GET /light_estimate.schema.json   the JSON Schema of one estimate
    GET /static/...           the pages' scripts and three.js (package data, works offline)

The estimate's JSON (``docs/estimate.md``) is made by
:func:`~illuminet.runtime.stream.estimate_json.estimate_dict`. Server-Sent Events rather than a
WebSocket: the estimate flows one way, SSE is plain HTTP (no extra dependency here, ``EventSource``
in every browser, reconnects by itself, passes proxies), and a JSON line per event is what any
engine's HTTP client can read. The estimate endpoints send ``Access-Control-Allow-Origin: *`` so a
page served elsewhere (another engine's web app) can read them.

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
  a reference. The camera picture (``?source=camera``) has its own slot and encoder, idle unless
  someone watches it.
* Each client thread sends the latest encoded frame it has not sent yet. A slow client simply skips
  frames: it never holds the encoder or the loop back.
* The estimate works the same way: the loop stores a reference to the frame's ``LightEstimate``;
  it is converted to JSON at most once per frame, only when a client asks, and each event client
  sends the newest one at most ``max_fps`` times a second.
* The server binds 127.0.0.1 by default. ``listen="0.0.0.0"`` serves the local network (a headset);
  there is no authentication, so only do that on a network you trust.

Hardening (what a hostile page or client meets):

* **Host check (DNS rebinding).** A web page on another site can make a browser send requests to
  127.0.0.1 under the page's own host name, by resolving that name to 127.0.0.1 after the page is
  loaded; the browser then lets the page read the answers. So a request is answered only when its
  ``Host`` header names this server: an IP address literal (a page cannot rebind a literal),
  ``localhost`` (and ``*.localhost``), this machine's host name (also ``NAME.local``), or a name in
  ``allowed_hosts`` (``"*"``: any). Anything else gets ``421 Misdirected Request`` with a line saying
  which key to set; an HTTP/1.1 request without a ``Host`` (or with two) gets ``400``.
* **Connection cap.** At most ``max_clients`` connections are served at once (one thread each);
  one more gets ``503 Service Unavailable`` with ``Retry-After`` from a single refusing thread and is
  closed at once, so a flood of connections cannot exhaust threads. The listen backlog is
  :data:`LISTEN_BACKLOG` (the standard library's default is 5, which drops connections under bursts).
* **Request head deadline (slowloris).** The request line and headers must arrive within
  ``head_timeout_s`` (:data:`HEAD_TIMEOUT_S`) in all, counted from the connection's start (from the
  first byte for a later request on a kept-alive connection); a client that is still sending them
  then gets ``408`` and is closed, freeing its slot. The per-read timeout alone cannot do this: a
  client sending one header line every few seconds never lets a read time out. Once the head is
  read the deadline no longer applies, so streams (MJPEG, events) run as long as their clients read.
* Idle keep-alive connections close after 30 s; a stream client that accepts nothing for
  ``client_timeout_s`` is dropped. The server serves no files other than its packaged pages.
* **Clients going away.** A client that resets or closes its connection mid-answer is normal (a
  closed tab, a reloaded page): a debug line, never a traceback. Any other error in a handler is a
  bug: logged once, as one line naming the exception type (the traceback at debug level).
"""

from __future__ import annotations

import collections
import io
import ipaddress
import json
import logging
import queue
import select
import selectors
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs

import cv2
import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import COMPOSITE, LIGHT
from illuminet.runtime.stage import LogOnce, Sink
from illuminet.runtime.stream import viewer
from illuminet.runtime.stream.estimate_json import SCHEMA_PATH, estimate_dict, to_line

log = logging.getLogger(__name__)

BOUNDARY = "illuminetframe"
#: an idle event stream sends a comment this often, so dead clients are noticed and proxies keep it open
SSE_KEEPALIVE_S = 10.0
#: connections the kernel queues before the server accepts them (socketserver's default is 5)
LISTEN_BACKLOG = 128
#: refused connections waiting for their 503; more are closed without one
REFUSE_QUEUE = 64
#: how long the refusing thread waits for a refused client's request before answering it, seconds
#: (each connection's own wait: the thread waits for all of them at once, so an idle one delays no other)
REFUSE_READ_S = 0.5
#: default total time a client has to send its request line and headers, seconds. The per-read
#: timeout (30 s, for idle keep-alive) does not bound a client that trickles one header line every
#: few seconds, and max_clients such clients would lock everyone else out (503) for as long as they
#: trickle. A real client sends its head in one packet; 10 s leaves room for a slow network.
HEAD_TIMEOUT_S = 10.0
#: how long the 408 for a head past its deadline may take to send before the connection is closed
REQUEST_TIMEOUT_SEND_S = 0.5
_REQUEST_TIMEOUT_BODY = b"the request head took too long to arrive; the connection is closed\n"
_REQUEST_TIMEOUT_MSG = (
    b"HTTP/1.1 408 Request Timeout\r\nContent-Type: text/plain; charset=utf-8\r\n"
    b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(_REQUEST_TIMEOUT_BODY), _REQUEST_TIMEOUT_BODY)
)


def host_name_of(header: str) -> str | None:
    """The host part of a ``Host`` header, lower case, without port or trailing dot; None when malformed.

    ``"LocalHost:8080"`` -> ``"localhost"``, ``"[::1]:80"`` -> ``"::1"``, ``"a:b:c"`` -> None.
    """
    h = header.strip().lower()
    if not h or any(c.isspace() or c in "/@?#\\" for c in h):
        return None
    if h.startswith("["):  # an IPv6 literal: [addr] or [addr]:port
        end = h.find("]")
        if end < 0:
            return None
        host, rest = h[1:end], h[end + 1 :]
        if rest and not (rest.startswith(":") and rest[1:].isdigit()):
            return None
        return host or None
    host, colon, port = h.partition(":")
    if colon and not port.isdigit():
        return None  # a second colon (an unbracketed IPv6 address) or a port that is not a number
    host = host.rstrip(".")
    return host or None


class HostCheck:
    """Which ``Host`` header values the server answers (see the module docstring: DNS rebinding).

    Parameters
    ----------
    listen : str
        The bound address (answered, as every IP literal is).
    allowed : iterable of str
        Further names (``[output] allowed_hosts``); ``"*"`` allows any.
    """

    def __init__(self, listen: str, allowed: Iterable[str] = ()):
        self.any = False
        names = {"localhost"}
        for n in list(allowed) + [listen]:
            if str(n).strip() == "*":
                self.any = True
                continue
            h = host_name_of(str(n)) or str(n).strip().lower().strip("[]").rstrip(".")
            if h:
                names.add(h)
        try:
            me = socket.gethostname().lower().rstrip(".")
        except OSError:  # pragma: no cover - no host name configured
            me = ""
        if me:
            short = me.split(".")[0]
            names |= {me, short, f"{short}.local"}
        self.names = frozenset(names)

    def allows(self, header: str | None) -> bool:
        if self.any:
            return True
        host = host_name_of(header or "")
        if host is None:
            return False
        if host in self.names or host.endswith(".localhost"):
            return True
        try:
            ipaddress.ip_address(host.split("%", 1)[0])  # an address literal (an IPv6 zone id allowed)
            return True
        except ValueError:
            return False


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
        self.cond = threading.Condition(self.lock)  # new JPEG -> client threads
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


class _EstimateBox:
    """The newest lighting estimate for the HTTP clients (see the module docstring).

    The loop stores a reference (``offer``: O(1), no JSON); :meth:`latest` converts it once per
    frame, on the first request, and caches the result for the other clients.
    """

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.seq = 0  # frames offered with an estimate
        self.closed = False
        self.listeners = 0
        self.sent = 0
        self._pending: tuple | None = None
        self._cached: tuple[int, dict, bytes] | None = None
        self._log = LogOnce(log, "MJPEG estimates")

    def offer(self, frame: Frame) -> None:
        est = frame.results.get(LIGHT.name)
        if est is None:
            return
        with self.cond:
            self._pending = (est, frame.seq, frame.t_device_ns, frame.t_host_ns, frame.intrinsics)
            self.seq += 1
            if self.listeners:
                self.cond.notify_all()

    def latest(self) -> tuple[int, dict | None, bytes | None]:
        """(sequence number, estimate dict, its JSON line as bytes); (0, None, None) before the first."""
        with self.cond:
            seq, pending, cached = self.seq, self._pending, self._cached
        if pending is None:
            return 0, None, None
        if cached is not None and cached[0] == seq:
            return cached
        est, fseq, t_dev, t_host, intr = pending
        try:
            d = estimate_dict(est, seq=fseq, t_device_ns=t_dev, t_host_ns=t_host, intrinsics=intr)
        except ValueError as e:  # a non-finite estimate: the clients keep the previous one
            self._log("non-finite", f"frame {fseq}: {e}; the clients keep the previous estimate")
            return cached if cached is not None else (0, None, None)
        out = (seq, d, to_line(d).encode())
        with self.cond:
            if self._cached is None or self._cached[0] < seq:
                self._cached = out
        return out

    def wait_newer(self, after: int, timeout: float) -> bool:
        """Wait up to ``timeout`` for an estimate newer than ``after``; True when there is one."""
        with self.cond:
            if self.seq == after and not self.closed:
                self.cond.wait(timeout)
            return self.seq != after and not self.closed

    def add_listener(self, delta: int) -> None:
        with self.cond:
            self.listeners += delta

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


class _HeadReader(io.RawIOBase):
    """A connection's socket as the handler's raw input, with a total deadline for the request head.

    The handler's ``rfile`` buffers this. Before each ``recv`` the socket timeout is set to the
    smaller of the per-read timeout and what is left of the deadline, so a client trickling bytes
    (or header lines) cannot stretch the head beyond the deadline however often it sends. Outside a
    head (:meth:`stop`) it is a plain reader with the per-read timeout.
    """

    def __init__(self, sock: socket.socket, read_timeout_s: float, head_timeout_s: float):
        super().__init__()
        self.sock = sock
        self.read_timeout_s = read_timeout_s
        self.head_timeout_s = head_timeout_s
        self.deadline: float | None = None
        self.arm_on_data = False  # start the deadline with the first byte that arrives
        self.expired = False  # the head's deadline passed (rather than a per-read timeout)
        self.received = 0  # bytes received for this head

    def readable(self) -> bool:
        return True

    def start(self, now: bool) -> None:
        """A request head begins: its deadline starts now, or (a kept-alive connection, whose idle wait
        for the next request is the per-read timeout's business) with its first byte."""
        self.expired, self.received = False, 0
        self.deadline = time.monotonic() + self.head_timeout_s if now else None
        self.arm_on_data = not now

    def stop(self) -> None:
        """The head is read: the deadline no longer applies (a stream may run for hours)."""
        self.deadline, self.arm_on_data = None, False

    def readinto(self, b) -> int:
        limited = False
        if self.deadline is not None:
            left = self.deadline - time.monotonic()
            if left <= 0:
                self.expired = True
                raise TimeoutError("request head deadline passed")
            limited = left < self.read_timeout_s
            self.sock.settimeout(min(self.read_timeout_s, left))
        try:
            n = self.sock.recv_into(b)
        except TimeoutError:
            self.expired = limited
            raise
        if n and self.arm_on_data:
            self.deadline, self.arm_on_data = time.monotonic() + self.head_timeout_s, False
        self.received += n
        return n


def _make_handler(sink: MjpegSink):
    box = sink._estimates

    class Handler(BaseHTTPRequestHandler):
        server_version = "IllumiNet-MJPEG/1"
        protocol_version = "HTTP/1.1"
        timeout = 30  # idle keep-alive connections (the page's stats polling) are closed after this

        def log_message(self, fmt: str, *args: Any) -> None:  # route to logging, not stderr
            log.debug("MJPEG %s: " + fmt, self.address_string(), *args)

        def setup(self) -> None:
            super().setup()
            # read through the head deadline (module docstring); a fresh connection's first head is
            # timed from now, so one that connects and trickles (or sends nothing) is bounded too
            self.rfile.close()  # the socket file setup() made: only releases its reference
            self._head = _HeadReader(self.connection, float(self.timeout), sink.head_timeout_s)
            self.rfile = io.BufferedReader(self._head)
            self._first_request = True

        def handle_one_request(self) -> None:
            self._head.start(now=self._first_request)
            self._first_request = False
            super().handle_one_request()  # a timeout ends in its ``except TimeoutError``: closed
            if self._head.expired:
                self.close_connection = True
                with sink._count_lock:
                    sink.refused_slow += 1
                sink._log(
                    "slow head",
                    f"closed a connection from {self.client_address[0]} that did not send its request head "
                    f"within {sink.head_timeout_s:g} s (a stalled or deliberately slow client); its slot is free",
                )
                if self._head.received:  # a client that sent nothing at all gets no answer, only the close
                    try:
                        self.connection.settimeout(REQUEST_TIMEOUT_SEND_S)
                        self.connection.sendall(_REQUEST_TIMEOUT_MSG)
                    except OSError:
                        pass

        def parse_request(self) -> bool:
            try:
                return super().parse_request()  # reads the headers
            finally:
                # the head is in: what follows (an answer, a stream) is not bound by its deadline, and
                # writes get the per-read timeout back rather than what was left of the deadline
                self._head.stop()
                self.connection.settimeout(self.timeout)

        def _send_bytes(
            self,
            body: bytes,
            ctype: str,
            status: HTTPStatus = HTTPStatus.OK,
            cors: bool = False,
            cache: str = "no-store",
        ) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", cache)
            if cors:
                self.send_header("Access-Control-Allow-Origin", "*")
            self.end_headers()
            self.wfile.write(body)

        def _static(self, rel: str) -> None:
            f = viewer.static_file(rel)
            if f is None:
                self._not_found()
                return
            # three.js does not change while the server runs; the pages themselves are small
            cache = "max-age=3600" if rel.startswith("three/") else "no-cache"
            self._send_bytes(f[0], f[1], cache=cache)

        def _not_found(self) -> None:
            self._send_bytes(
                b"not found; try / (stream), /viewer, /stream.mjpg, /estimates, /estimate.json or /stats.json\n",
                "text/plain; charset=utf-8",
                HTTPStatus.NOT_FOUND,
            )

        def _peer_closed(self) -> bool:
            """Whether the client closed its end (checked while a stream idles: nothing written, nothing noticed)."""
            try:
                r, _, _ = select.select([self.connection], [], [], 0)
                return bool(r) and self.connection.recv(1, socket.MSG_PEEK) == b""
            except (OSError, ValueError):
                return True

        def _host_ok(self) -> bool:
            """Answer 400/421 and return False unless the request's ``Host`` names this server."""
            hosts = self.headers.get_all("Host") or []
            if len(hosts) > 1 or (not hosts and self.request_version == "HTTP/1.1"):
                self.close_connection = True
                self._send_bytes(
                    b"an HTTP/1.1 request needs exactly one Host header\n",
                    "text/plain; charset=utf-8",
                    HTTPStatus.BAD_REQUEST,
                )
                return False
            if not hosts or sink._hosts.allows(hosts[0]):
                return True  # HTTP/1.0 without Host: not a browser, so not a rebinding page
            with sink._count_lock:
                sink.refused_host += 1
            sink._log("host", f"refused a request for Host {hosts[0][:80]!r} (not this server's name)")
            self.close_connection = True
            self._send_bytes(
                (
                    f"Host {hosts[0][:80]!r} is not a name of this server; open it by its IP address, localhost "
                    "or this machine's name, or add the name to [output] allowed_hosts\n"
                ).encode("utf-8", "replace"),
                "text/plain; charset=utf-8",
                HTTPStatus.MISDIRECTED_REQUEST,
            )
            return False

        def do_GET(self) -> None:  # noqa: N802 (http.server naming)
            if not self._host_ok():
                return
            path, _, query = self.path.partition("?")
            if path in ("/", "/index.html"):
                self._static("index.html")
            elif path in ("/viewer", "/viewer.html"):
                self._static("viewer.html")
            elif path.startswith("/static/"):
                self._static(path[len("/static/") :])
            elif path == "/stats.json":
                body = json.dumps(sink.status(), default=str).encode()
                self._send_bytes(body, "application/json", cors=True)
            elif path == "/estimate.json":
                _, _, line = box.latest()
                self._send_bytes(line if line is not None else b"null", "application/json", cors=True)
            elif path == "/estimates":
                self._events()
            elif path == "/stream.mjpg":
                src = parse_qs(query).get("source", ["composite"])[0]
                if src not in ("composite", "camera"):
                    self._send_bytes(
                        f"unknown source {src!r}; expected composite or camera\n".encode(),
                        "text/plain; charset=utf-8",
                        HTTPStatus.BAD_REQUEST,
                    )
                    return
                self._stream(sink._hub if src == "composite" else sink._camera_hub)
            elif path == "/model.glb":
                try:
                    body = sink.model_bytes()
                except Exception as e:  # a broken model file must not take the server down
                    log.error("viewer model %s: %s", sink.viewer_model, e)
                    self._send_bytes(
                        f"viewer model {sink.viewer_model}: {e}\n".encode(),
                        "text/plain; charset=utf-8",
                        HTTPStatus.INTERNAL_SERVER_ERROR,
                    )
                    return
                self._send_bytes(body, "model/gltf-binary", cache="no-cache")
            elif path == "/light_estimate.schema.json":
                self._send_bytes(SCHEMA_PATH.read_bytes(), "application/schema+json", cors=True, cache="no-cache")
            else:
                self._not_found()

        def _events(self) -> None:
            """Server-Sent Events: ``id: <frameId>`` + ``data: <estimate JSON>`` per event, newest only."""
            self.close_connection = True
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream; charset=utf-8")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.send_header("Access-Control-Allow-Origin", "*")
            self.end_headers()
            self.connection.settimeout(sink.client_timeout_s)
            box.add_listener(+1)
            seq = 0
            next_send = 0.0
            last_write = time.monotonic()
            try:
                self.wfile.write(b"retry: 1000\n\n")  # EventSource reconnects after 1 s if dropped
                self.wfile.flush()
                while True:
                    if not box.wait_newer(seq, timeout=0.5):
                        if box.closed or sink._server is None or self._peer_closed():
                            return
                        if time.monotonic() - last_write > SSE_KEEPALIVE_S:
                            self.wfile.write(b": keep-alive\n\n")
                            self.wfile.flush()
                            last_write = time.monotonic()
                        continue
                    wait = next_send - time.monotonic()
                    if wait > 0:  # the rate cap: the newest estimate at the next slot, the rest skipped
                        time.sleep(wait)
                    seq, d, line = box.latest()
                    if line is None:
                        continue
                    self.wfile.write(b"id: %d\ndata: %s\n\n" % (d["frameId"], line))
                    self.wfile.flush()
                    last_write = time.monotonic()
                    next_send = last_write + sink._hub.min_interval
                    with box.cond:
                        box.sent += 1
            except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
                return  # the client went away (or stalled)
            finally:
                box.add_listener(-1)

        def _stream(self, hub: _Hub) -> None:
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
                        if self._peer_closed():  # no frames to write: a gone client would hold its slot
                            return
                        continue
                    seq = new_seq
                    head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n").encode()
                    self.wfile.write(head + jpeg + b"\r\n")
                    self.wfile.flush()
                    with hub.cond:
                        hub.sent += 1
            except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
                return  # the client went away (or stalled): normal for a preview stream
            finally:
                hub.add_client(-1)

    return Handler


class _Server(ThreadingHTTPServer):
    """The threading HTTP server with a connection cap and a longer listen backlog (module docstring)."""

    request_queue_size = LISTEN_BACKLOG
    daemon_threads = True  # client threads never keep the process alive

    def __init__(self, address: tuple[str, int], handler: type, sink: MjpegSink):
        self.sink = sink
        self._refuse_q: queue.Queue = queue.Queue(maxsize=REFUSE_QUEUE)
        self._refuser: threading.Thread | None = None
        # wakes the refusing thread from its select() when a connection is queued or the server closes
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        # the sockets of the connections being served: server_close() shuts them down, or a kept-alive
        # connection (a page polling /stats.json) would go on being answered after close()
        self._live: set[socket.socket] = set()
        self._live_lock = threading.Lock()
        super().__init__(address, handler)  # on a failed bind this calls server_close() and raises
        self._refuser = threading.Thread(target=self._refuse_loop, name="illuminet-mjpeg-refuse", daemon=True)
        self._refuser.start()

    def process_request(self, request, client_address) -> None:
        sink = self.sink
        with sink._count_lock:
            busy = sink.connections >= sink.max_clients
            if busy:
                sink.refused_busy += 1
            else:
                sink.connections += 1
        if not busy:
            with self._live_lock:
                self._live.add(request)
            try:
                super().process_request(request, client_address)  # a thread for this connection
            except Exception:
                with self._live_lock:
                    self._live.discard(request)
                with sink._count_lock:
                    sink.connections -= 1
                raise
            return
        sink._log("busy", f"{sink.max_clients} connections are open ([output] max_clients); refusing more with 503")
        try:
            self._refuse_q.put_nowait(request)
        except queue.Full:  # a flood: no 503 for these, just the close
            self.shutdown_request(request)
            return
        self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:  # its buffer is full (it is awake anyway) or the server is closed
            pass

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._live_lock:
                self._live.discard(request)
            with self.sink._count_lock:
                self.sink.connections -= 1

    def handle_error(self, request, client_address) -> None:
        """Called for an exception out of a handler (socketserver's own prints a traceback to stderr)."""
        exc = sys.exc_info()[1]
        who = client_address[0] if isinstance(client_address, tuple) and client_address else client_address
        if isinstance(exc, (ConnectionError, TimeoutError)):  # BrokenPipe, ConnectionReset, ...: it left
            log.debug("MJPEG %s: the client went away (%s: %s)", who, type(exc).__name__, exc)
            return
        # a bug: one line per kind; the connection is closed, the server goes on
        self.sink._log(f"error {type(exc).__name__}", f"a request from {who} failed: {type(exc).__name__}: {exc}")
        log.debug("MJPEG %s: request failed", who, exc_info=exc)

    def _refuse_loop(self) -> None:
        """One thread answers every refused connection: read its request (briefly), 503, close. It
        waits for all of them at once (select), each for at most :data:`REFUSE_READ_S`: a refused
        client that sends nothing (or slowly) does not hold up the 503 of the ones after it."""
        body = b"too many connections to this server; try again shortly\n"
        msg = (
            b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
            b"Content-Length: %d\r\nRetry-After: 2\r\nConnection: close\r\n\r\n%s" % (len(body), body)
        )
        sel = selectors.DefaultSelector()
        sel.register(self._wake_r, selectors.EVENT_READ)
        waiting: dict[socket.socket, float] = {}  # refused connection -> when its 503 goes out unread

        def answer(request: socket.socket, read: bool) -> None:
            try:
                if read:  # the request: read so that closing does not reset the connection
                    request.recv(65536)
                request.send(msg)  # small: fits the socket's buffer, never waits
            except OSError:
                pass
            finally:
                sel.unregister(request)
                del waiting[request]
                self.shutdown_request(request)

        try:
            while True:
                timeout = max(0.0, min(waiting.values()) - time.monotonic()) if waiting else None
                for key, _ in sel.select(timeout):
                    if key.fileobj is not self._wake_r:
                        answer(key.fileobj, read=True)
                        continue
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except OSError:
                        pass
                    while True:
                        try:
                            request = self._refuse_q.get_nowait()
                        except queue.Empty:
                            break
                        if request is None:
                            return
                        if len(waiting) >= REFUSE_QUEUE:  # a flood: no 503 for these, just the close
                            self.shutdown_request(request)
                            continue
                        request.setblocking(False)
                        waiting[request] = time.monotonic() + REFUSE_READ_S
                        sel.register(request, selectors.EVENT_READ)
                now = time.monotonic()
                for request in [r for r, deadline in waiting.items() if deadline <= now]:
                    answer(request, read=False)
        finally:
            for request in list(waiting):
                sel.unregister(request)
                self.shutdown_request(request)
            sel.close()
            while True:  # queued after the close
                try:
                    request = self._refuse_q.get_nowait()
                except queue.Empty:
                    break
                if request is not None:
                    self.shutdown_request(request)

    def server_close(self) -> None:
        super().server_close()
        with self._live_lock:
            live = list(self._live)
        for request in live:  # wakes a handler waiting for the next request on a kept-alive connection
            try:
                request.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass  # already closed by its thread
        if self._refuser is not None:
            try:
                self._refuse_q.put_nowait(None)
            except queue.Full:
                pass
            self._wake()
            self._refuser.join(timeout=2.0)
        self._wake_r.close()
        self._wake_w.close()


class MjpegSink(Sink):
    """Serve the stream as MJPEG over HTTP, the lighting estimate as JSON / Server-Sent Events, and the
    browser pages (see the module docstring).

    Parameters
    ----------
    listen : str
        Bind address. ``"127.0.0.1"`` (default) is this machine only; ``"0.0.0.0"`` the local network.
    port : int
        TCP port; 0 picks a free one (read :attr:`port` after :meth:`open`).
    stats : callable, optional
        Returns a JSON-serialisable dict of loop figures shown on the page, e.g. the streaming loop's
        ``LoopStats.snapshot`` (keys used by the page: ``fps``, ``fps_recent``, ``frames``,
        ``dropped``, ``failed_frames``, ``latency_ms``, ``cpu_ms_per_frame``, ``pipeline``,
        ``stages_ms``, ``source``; others are passed through).
    quality : int
        JPEG quality 1..100.
    max_fps : float
        Most frames per second encoded for the clients, and most estimate events per second sent to
        each event client (0 = every frame the loop writes). The newest frame at each slot is sent;
        frames between slots are skipped, not queued.
    client_timeout_s : float
        A client that accepts no data for this long is disconnected.
    viewer_model : str
        The model ``/viewer`` draws (``/model.glb``): ``builtin:NAME`` or a mesh file
        (:func:`illuminet.runtime.stream.viewer.model_glb`); checked here, made on first request.
    object_scale : float
        ``[render] object_scale``, applied to converted viewer models.
    max_clients : int
        Connections served at once (``[output] max_clients``); more get 503 and are closed.
    allowed_hosts : iterable of str
        ``Host`` names answered besides IP literals, localhost and this machine's name
        (``[output] allowed_hosts``; ``"*"`` = any). See the module docstring.
    head_timeout_s : float
        Most seconds a client may take to send its request line and headers (:data:`HEAD_TIMEOUT_S`);
        then it gets 408 and is closed. See the module docstring.

    Attributes
    ----------
    port : int
        The port actually bound (after :meth:`open`).
    url : str
        ``http://HOST:PORT/`` of the page (after :meth:`open`).
    """

    name = "mjpeg"

    def __init__(
        self,
        listen: str = "127.0.0.1",
        port: int = 8080,
        stats: Callable[[], dict[str, Any]] | None = None,
        quality: int = 80,
        client_timeout_s: float = 10.0,
        max_fps: float = 30.0,
        viewer_model: str = "builtin:vase",
        object_scale: float = 1.0,
        max_clients: int = 32,
        allowed_hosts: Iterable[str] = (),
        head_timeout_s: float = HEAD_TIMEOUT_S,
    ):
        if not (1 <= int(quality) <= 100):
            raise ValueError(f"MjpegSink quality must be within 1..100, got {quality!r}")
        if not (0 <= int(port) <= 65535):
            raise ValueError(f"MjpegSink port must be within 0..65535, got {port!r}")
        if not str(listen).strip():
            raise ValueError(
                "MjpegSink listen address is empty; give 127.0.0.1 (this machine) or 0.0.0.0 (the local network)"
            )
        if int(max_clients) < 1:
            raise ValueError(f"MjpegSink max_clients must be >= 1, got {max_clients!r}")
        if not float(head_timeout_s) > 0:  # also refuses NaN
            raise ValueError(f"MjpegSink head_timeout_s must be > 0 seconds, got {head_timeout_s!r}")
        self.head_timeout_s = float(head_timeout_s)
        self.listen = str(listen).strip()
        self.max_clients = int(max_clients)
        self.allowed_hosts = tuple(str(h) for h in allowed_hosts)
        self._hosts = HostCheck(self.listen, self.allowed_hosts)
        self._count_lock = threading.Lock()
        self.connections = 0
        self.refused_busy = 0
        self.refused_host = 0
        self.refused_slow = 0  # connections closed at the request head deadline
        self._log = LogOnce(log, "MJPEG server")
        self.port = int(port)
        self.stats_fn = stats
        self.client_timeout_s = float(client_timeout_s)
        if max_fps < 0:
            raise ValueError(f"MjpegSink max_fps must be >= 0 (0 = no cap), got {max_fps!r}")
        viewer.check_model_spec(viewer_model)  # a wrong --viewer-model is reported before anything starts
        self.viewer_model = str(viewer_model)
        self.object_scale = float(object_scale)
        self._model: bytes | None = None
        if not self.viewer_model.startswith("builtin:"):
            # a file is loaded now (an empty or broken one is named before the run, not a 500 later)
            self._model = viewer.model_glb(self.viewer_model, self.object_scale)
        self._quality = int(quality)
        self.max_fps = float(max_fps)
        self._hub = _Hub(self._quality, self.max_fps)
        self._camera_hub = _Hub(self._quality, self.max_fps)
        self._estimates = _EstimateBox()
        self._model_lock = threading.Lock()
        self._server: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.listen in ("0.0.0.0", "") else self.listen
        return f"http://{host}:{self.port}/"

    def model_bytes(self) -> bytes:
        """The viewer's model as GLB (made once, on the first request)."""
        with self._model_lock:
            if self._model is None:
                self._model = viewer.model_glb(self.viewer_model, self.object_scale)
            return self._model

    def open(self) -> None:
        """Bind the port and start the server and encoder threads."""
        if self._server is not None:
            return
        self._hub = _Hub(self._quality, self.max_fps)
        self._camera_hub = _Hub(self._quality, self.max_fps)
        self._estimates = _EstimateBox()
        try:
            server = _Server((self.listen, self.port), _make_handler(self), self)
        except (OSError, ValueError, UnicodeError) as e:  # in use, no such address, a NUL in the name
            why = getattr(e, "strerror", None) or e
            fix = (
                "Pick another port (--port N or [output] port; 0 for any free one) or stop what uses it."
                if getattr(e, "errno", None) in (98, 48, 10048)  # EADDRINUSE (Linux, macOS, Windows)
                else "Check --listen / [output] listen: an address of this machine (127.0.0.1, 0.0.0.0 or "
                "an interface's)."
            )
            raise OSError(f"MJPEG server cannot listen on {self.listen}:{self.port}: {why}. {fix}") from e
        self._server = server
        self.port = server.server_address[1]
        self._threads = [
            threading.Thread(
                target=server.serve_forever, kwargs={"poll_interval": 0.2}, name="illuminet-mjpeg-http", daemon=True
            ),
            threading.Thread(target=self._hub.encoder, name="illuminet-mjpeg-encoder", daemon=True),
            threading.Thread(target=self._camera_hub.encoder, name="illuminet-mjpeg-encoder-camera", daemon=True),
        ]
        for t in self._threads:
            t.start()
        if self.listen in ("0.0.0.0", "", "::"):
            log.info(
                "MJPEG server on all interfaces, port %d: open http://<this machine's address>:%d/ "
                "on the headset (locally %s; viewer %sviewer)",
                self.port,
                self.port,
                self.url,
                self.url,
            )
        else:
            log.info(
                "MJPEG stream at %sstream.mjpg (page %s, lit viewer %sviewer, estimates %sestimates)",
                self.url,
                self.url,
                self.url,
                self.url,
            )

    def write(self, frame: Frame) -> None:
        """Offer ``frame.results["composite"]`` (or the camera colour), the camera colour and the
        frame's lighting estimate to the clients; O(1) (references only)."""
        if self._server is None:
            raise RuntimeError("MjpegSink.write() before open()")
        img = frame.results.get(COMPOSITE.name, frame.color)
        if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8):
            raise ValueError(
                "MjpegSink expects results['composite'] (or colour) as an HxWx3 uint8 RGB array, got "
                f"{getattr(img, 'shape', type(img))} {getattr(img, 'dtype', '')}"
            )
        self._hub.offer(img)
        self._camera_hub.offer(frame.color)
        self._estimates.offer(frame)

    def latest_estimate(self) -> dict[str, Any] | None:
        """The newest frame's estimate as its JSON object (what ``/estimate.json`` returns), or None."""
        return self._estimates.latest()[1]

    def status(self) -> dict[str, Any]:
        """What ``/stats.json`` returns: ``{"sink": {...}, "loop": stats() or {}, "estimate": {...} or None}``."""
        hub, box = self._hub, self._estimates
        with hub.cond:
            sink = {"frames": hub.offered, "encoded": hub.encoded, "sent": hub.sent, "clients": hub.clients}
        with box.cond:
            sink["estimate_clients"], sink["estimates_sent"] = box.listeners, box.sent
        sink["fps"] = round(hub.fps(), 2)
        with self._count_lock:
            sink["connections"], sink["refused_busy"], sink["refused_host"], sink["refused_slow"] = (
                self.connections,
                self.refused_busy,
                self.refused_host,
                self.refused_slow,
            )
        loop: dict[str, Any] = {}
        if self.stats_fn is not None:
            try:
                loop = dict(self.stats_fn())
            except Exception as e:  # the page must keep working while the loop misbehaves
                loop = {"error": f"stats() failed: {type(e).__name__}: {e}"}
        estimate = self.latest_estimate()
        return {"sink": sink, "loop": loop, "estimate": estimate}

    def stats(self) -> dict[str, Any]:
        hub = self._hub
        return {
            "clients": hub.clients,
            "encoded": hub.encoded,
            "sent": hub.sent,
            "port": self.port,
            "estimates_sent": self._estimates.sent,
            "refused_busy": self.refused_busy,
            "refused_host": self.refused_host,
            "refused_slow": self.refused_slow,
        }

    def close(self) -> None:
        """Stop serving: clients are disconnected, threads end, the port is released. Idempotent."""
        server, self._server = self._server, None
        self._hub.close()
        self._camera_hub.close()
        self._estimates.close()
        if server is not None:
            server.shutdown()
            server.server_close()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
