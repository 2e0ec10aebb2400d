"""MJPEG server: a real HTTP client on 127.0.0.1 reads and decodes frames, page and stats are served."""

from __future__ import annotations

import http.client
import json
import logging
import socket
import struct
import threading
import time

import cv2
import numpy as np
import pytest

from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.stream.mjpeg import BOUNDARY, MjpegSink

W, H = 160, 100
INTR = Intrinsics(100.0, 100.0, W / 2, H / 2, W, H)


def _frame(i: int, composite: bool = False) -> Frame:
    # a colour per frame that survives JPEG: the frame index in the red channel, steps of 20
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = (i * 20) % 256
    img[..., 1] = 64
    f = Frame(seq=i, t_device_ns=i * 33_000_000, t_host_ns=i, color=img, depth=None, intrinsics=INTR)
    if composite:
        comp = img.copy()
        comp[..., 2] = 200
        f = f.with_result("composite", comp)
    return f


class _Feeder:
    """Writes frames into the sink from a thread, like the loop does, until stopped."""

    def __init__(self, sink: MjpegSink, composite: bool = False, period: float = 0.01):
        self.sink, self.composite, self.period = sink, composite, period
        self.stop = threading.Event()
        self.i = 0
        self.t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self.stop.is_set():
            self.sink.write(_frame(self.i, self.composite))
            self.i += 1
            time.sleep(self.period)

    def __enter__(self):
        self.t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.t.join(2)


def _read_parts(port: int, n: int, timeout: float = 5.0) -> list[bytes]:
    """Read ``n`` JPEG parts from /stream.mjpg with http.client, parsing the multipart framing."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    conn.request("GET", "/stream.mjpg")
    resp = conn.getresponse()
    assert resp.status == 200
    assert resp.getheader("Content-Type") == f"multipart/x-mixed-replace; boundary={BOUNDARY}"
    parts = []
    try:
        while len(parts) < n:
            line = resp.fp.readline()
            if not line:
                raise AssertionError("stream ended early")
            if line.strip() != f"--{BOUNDARY}".encode():
                continue
            headers = {}
            while True:
                h = resp.fp.readline().strip()
                if not h:
                    break
                k, v = h.decode().split(":", 1)
                headers[k.strip().lower()] = v.strip()
            assert headers["content-type"] == "image/jpeg"
            parts.append(resp.fp.read(int(headers["content-length"])))
    finally:
        conn.close()
    return parts


def test_client_reads_and_decodes_frames():
    with MjpegSink(port=0) as sink:
        assert sink.port > 0 and sink.listen == "127.0.0.1"
        with _Feeder(sink):
            parts = _read_parts(sink.port, 5)
    reds = []
    for p in parts:
        img = cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_COLOR)  # BGR
        assert img is not None and img.shape == (H, W, 3)
        assert abs(int(np.median(img[..., 1])) - 64) <= 3  # green channel survives
        reds.append(int(np.median(img[..., 2])))
    # frames advance (the client gets new frames, not one repeated): red steps by multiples of 20
    assert len(set(reds)) >= 3


def test_composite_is_preferred_over_colour():
    with MjpegSink(port=0) as sink, _Feeder(sink, composite=True):
        (p,) = _read_parts(sink.port, 1)
    img = cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_COLOR)
    assert abs(int(np.median(img[..., 0])) - 200) <= 3  # composite's blue channel, BGR order


def test_two_clients_share_one_encoding_and_a_stalled_client_does_not_block():
    with MjpegSink(port=0, client_timeout_s=2.0) as sink:
        # a client that connects and never reads: its socket buffer fills, it must not stall others
        stalled = socket.create_connection(("127.0.0.1", sink.port))
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        results: dict[int, list[bytes]] = {}

        def client(k):
            results[k] = _read_parts(sink.port, 20)

        with _Feeder(sink, period=0.005) as feeder:
            ts = [threading.Thread(target=client, args=(k,)) for k in range(2)]
            t0 = time.perf_counter()
            for t in ts:
                t.start()
            for t in ts:
                t.join(10)
            written = feeder.i
        assert all(len(results.get(k, [])) == 20 for k in range(2)), "a client did not get its frames"
        assert time.perf_counter() - t0 < 8
        st = sink.status()["sink"]
        # once per frame at most, whatever the number of clients (3 connected here)
        assert st["encoded"] <= written
        assert st["sent"] >= 40
        stalled.close()


def test_page_and_stats_json_are_served():
    calls = []

    def stats():
        calls.append(1)
        return {"fps": 29.5, "dropped": 3, "stages_ms": {"stage:planes": 4.2}}

    with MjpegSink(port=0, stats=stats) as sink:
        sink.write(_frame(1))
        conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
        conn.request("GET", "/")
        r = conn.getresponse()
        page = r.read().decode()
        assert r.status == 200 and r.getheader("Content-Type").startswith("text/html")
        assert "/stream.mjpg" in page and "/stats.json" in page
        conn.request("GET", "/stats.json")
        r = conn.getresponse()
        s = json.loads(r.read())
        assert r.status == 200
        assert s["loop"] == {"fps": 29.5, "dropped": 3, "stages_ms": {"stage:planes": 4.2}}
        assert s["sink"]["frames"] == 1 and calls
        conn.request("GET", "/nope")
        r = conn.getresponse()
        r.read()
        assert r.status == 404
        conn.close()


def test_failing_stats_callable_is_reported_not_fatal():
    def stats():
        raise RuntimeError("loop gone")

    with MjpegSink(port=0, stats=stats) as sink:
        conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
        conn.request("GET", "/stats.json")
        s = json.loads(conn.getresponse().read())
        conn.close()
    assert "loop gone" in s["loop"]["error"]


def test_close_stops_the_server_and_ends_streams():
    sink = MjpegSink(port=0)
    sink.open()
    port = sink.port
    sink.write(_frame(0))
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("GET", "/stream.mjpg")
    resp = conn.getresponse()
    assert resp.status == 200
    sink.close()
    sink.close()  # idempotent
    # the open stream ends (EOF) instead of hanging
    t0 = time.perf_counter()
    while resp.fp.readline():
        assert time.perf_counter() - t0 < 5
    conn.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


def test_close_also_ends_kept_alive_connections():
    """A page polling /stats.json holds a kept-alive connection; after close() it must not be answered
    any more (it was, by its still-running handler thread, for up to the 30 s idle timeout)."""
    sink = MjpegSink(port=0)
    sink.open()
    sink.write(_frame(0))
    conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
    conn.request("GET", "/stats.json")
    r = conn.getresponse()
    assert r.status == 200 and r.read()
    sink.close()
    t0 = time.perf_counter()
    with pytest.raises((http.client.HTTPException, OSError)):
        conn.request("GET", "/stats.json")
        conn.getresponse().read()
    assert time.perf_counter() - t0 < 2  # closed at once, not after the idle timeout
    conn.close()
    assert sink.status()["sink"]["connections"] == 0 or _wait_for(lambda: sink.status()["sink"]["connections"] == 0)


def test_bad_input_is_refused_with_a_clear_message():
    with pytest.raises(ValueError, match="quality"):
        MjpegSink(quality=0)
    with MjpegSink(port=0) as sink:
        f = _frame(0).with_result("composite", np.zeros((10, 10), np.float32))
        with pytest.raises(ValueError, match="HxWx3 uint8"):
            sink.write(f)


def test_port_in_use_names_the_port():
    with MjpegSink(port=0) as a:
        with pytest.raises(OSError, match=f"127.0.0.1:{a.port}"):
            MjpegSink(port=a.port).open()


def test_encoding_rate_is_capped_and_uncapped_follows_the_loop():
    with MjpegSink(port=0, max_fps=10) as sink:
        with _Feeder(sink, period=0.002):
            t0 = time.perf_counter()
            parts = _read_parts(sink.port, 6)
            dt = time.perf_counter() - t0
        st = sink.status()["sink"]
    assert len(parts) == 6 and dt >= 0.4  # 6 frames at <= 10 fps take at least ~0.5 s
    assert st["encoded"] <= 10 * dt + 2 and st["frames"] > 3 * st["encoded"]
    with MjpegSink(port=0, max_fps=0) as sink:
        with _Feeder(sink, period=0.01):
            _read_parts(sink.port, 10)
        assert sink.status()["sink"]["encoded"] >= 10
    with pytest.raises(ValueError, match="max_fps"):
        MjpegSink(max_fps=-1)


def _status(port: int, path: str = "/stats.json") -> int:
    """The status code of one GET on a fresh connection (503 from the refusing thread included)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        conn.request("GET", path)
        return conn.getresponse().status
    finally:
        conn.close()


def _wait_for(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_client_that_resets_its_connection_is_no_traceback(capsys, caplog):
    """A client going away (RST right after its request) is normal: at most a debug line, never a traceback."""
    caplog.set_level(logging.DEBUG, logger="illuminet.runtime.stream.mjpeg")
    with MjpegSink(port=0) as sink:
        for _ in range(32):
            s = socket.create_connection(("127.0.0.1", sink.port), timeout=5)
            s.sendall(b"GET /stats.json HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close = RST
            s.close()
        assert _wait_for(lambda: sink.connections == 0)  # every handler thread has finished
        assert _status(sink.port) == 200  # and the server still answers
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Exception occurred" not in err, err[-2000:]
    assert "Traceback" not in caplog.text and not any(r.exc_info for r in caplog.records)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text


def test_a_bug_in_a_handler_is_one_line_with_its_type(capsys, caplog):
    """A real bug in a request handler is logged once, as one line naming the exception type."""
    caplog.set_level(logging.DEBUG, logger="illuminet.runtime.stream.mjpeg")
    with MjpegSink(port=0) as sink:
        sink.status = lambda: {"x": _Unserialisable()}  # json.dumps fails inside the handler
        for _ in range(2):
            with pytest.raises((http.client.HTTPException, ConnectionError)):
                _status(sink.port)
        assert _wait_for(lambda: sink.connections == 0)
    assert "Traceback" not in capsys.readouterr().err
    assert not any(r.exc_info for r in caplog.records if r.levelno > logging.DEBUG)
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) == 1 and "_BadJson" in lines[0], lines  # logged once, naming the exception type


class _BadJson(Exception):
    pass


class _Unserialisable:
    def __str__(self):  # json.dumps(default=str) calls this
        raise _BadJson("cannot be shown")


def test_idle_refused_connections_do_not_delay_the_503_of_others():
    """The refusing thread waited up to 0.5 s for each refused connection's request in turn: eight idle
    ones queued before a real client held its 503 back for 4 s. Each now waits on its own."""
    with MjpegSink(port=0, max_clients=1) as sink:
        p = sink.port
        held = socket.create_connection(("127.0.0.1", p), timeout=5)  # takes the only slot
        assert _wait_for(lambda: sink.connections == 1)
        idle = [socket.create_connection(("127.0.0.1", p), timeout=5) for _ in range(8)]
        assert _wait_for(lambda: sink.refused_busy == 8)
        t0 = time.monotonic()
        assert _status(p) == 503
        dt = time.monotonic() - t0
        assert dt < 1.5, dt
        for s in idle:  # they get theirs too, after their own wait
            assert s.recv(4096).startswith(b"HTTP/1.1 503")
            s.close()
        held.close()


def test_a_slow_request_head_is_dropped_at_the_deadline_and_frees_its_slot():
    """Slowloris: clients trickling header lines hold every slot only until the head deadline."""
    with MjpegSink(port=0, max_clients=2, head_timeout_s=1.0) as sink:
        p = sink.port
        slow = [socket.create_connection(("127.0.0.1", p), timeout=5) for _ in range(2)]
        t0 = time.monotonic()
        for s in slow:
            s.sendall(b"GET /stats.json HTTP/1.1\r\n")
        stop = threading.Event()

        def trickle():  # one header line per 0.2 s: each read is quick, only the whole head is slow
            while not stop.wait(0.2):
                for s in slow:
                    try:
                        s.sendall(b"X-Slow: 1\r\n")
                    except OSError:
                        pass

        t = threading.Thread(target=trickle, daemon=True)
        t.start()
        try:
            assert _wait_for(lambda: sink.connections == 2)
            assert _status(p) == 503  # every slot is taken while they trickle
            for s in slow:
                data = b""
                try:
                    while chunk := s.recv(4096):
                        data += chunk
                except ConnectionResetError:  # the 408 may be lost to a header line the server never read
                    pass
                dt = time.monotonic() - t0
                assert 0.8 < dt < 1.0 + 1.5, dt  # dropped at the deadline, although it is still sending
                assert data == b"" or data.startswith(b"HTTP/1.1 408"), data[:80]
            assert _wait_for(lambda: sink.connections == 0)
            assert _status(p) == 200  # the freed slots serve a normal client while the trickle goes on
        finally:
            stop.set()
            t.join(2)
            for s in slow:
                s.close()
    with pytest.raises(ValueError, match="head_timeout_s"):
        MjpegSink(head_timeout_s=0)


def test_the_head_deadline_spares_streams_and_idle_keep_alive():
    """The deadline covers reading a request head only: not a stream's life, not the wait between requests."""
    with MjpegSink(port=0, head_timeout_s=0.5) as sink:
        with _Feeder(sink):
            conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
            conn.request("GET", "/stats.json")
            assert conn.getresponse().read()
            time.sleep(0.8)  # idle longer than the head deadline (the keep-alive timeout is 30 s)
            conn.request("GET", "/stats.json")
            assert conn.getresponse().status == 200
            conn.close()
            events = socket.create_connection(("127.0.0.1", sink.port), timeout=5)
            events.sendall(b"GET /estimates HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert events.recv(12) == b"HTTP/1.1 200"
            t0 = time.monotonic()
            parts = _read_parts(sink.port, 40)  # the stream outlives the head deadline
            assert len(parts) == 40 and time.monotonic() - t0 > 0.5
            assert sink.status()["sink"]["estimate_clients"] == 1  # the event stream is still open
            events.close()


@pytest.mark.slow
def test_bench_mjpeg_quick_runs_and_reports_a_ratio(capsys):
    import argparse

    from illuminet.bench.mjpeg import run

    res = run(argparse.Namespace(quick=True), None)
    assert res["2 clients"]["median_client_frames"] >= 1 and not res["2 clients"]["client_errors"]
    assert 0 < res["ratio_2_clients_vs_none"] < 10
    assert "ratio 2 clients / no sink" in capsys.readouterr().out
