"""The browser pages in a real browser: Playwright driving Debian's Chromium (WebGL by SwiftShader).

The stream page shows frames and its overlay without console errors; the three.js viewer receives
the real pipeline's estimates over the real Server-Sent Events endpoint; its rendering follows the
light from left to right; the H.264 MP4 plays in a <video> element. Skipped (reason in pytest's
header) where Playwright or Chromium is missing; ~15-25 s in all on the 2-core build machine.
"""

from __future__ import annotations

import functools
import http.server
import threading
import time

import cv2
import numpy as np
import pytest

from illuminet.runtime.scene import LIGHT, LightEstimate
from illuminet.runtime.stream.mjpeg import MjpegSink

from ._sessions import frames

pytestmark = pytest.mark.browser


class _Feeder:
    """Writes frames carrying a fixed-shape lighting estimate into the sink, like the loop does.

    ``direction`` (unit vector towards the light, anchor frame) may be changed while it runs;
    ``T_cam_obj`` is the anchor pose the estimates carry; ``grey`` makes the camera picture uniform.
    """

    def __init__(
        self, sink: MjpegSink, direction=(-1.0, 0.6, 0.2), period: float = 0.03, T_cam_obj=None, grey: int | None = None
    ):
        self.sink, self.period = sink, period
        self.direction = np.asarray(direction, float)
        self.T = np.eye(4) if T_cam_obj is None else np.asarray(T_cam_obj, float)
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.frame = frames(1, w=320, h=240)[0]
        if grey is not None:
            self.frame = self.frame.replace(color=np.full_like(self.frame.color, grey))

    def _run(self):
        i = 0
        sh = np.zeros((9, 3))
        sh[0] = 0.5  # a dim, uniform ambient: the primary light makes the difference between the sides
        while not self.stop.is_set():
            d = self.direction / np.linalg.norm(self.direction)
            est = LightEstimate(
                sh9=sh,
                primary_dir=d,
                primary_rgb=np.array([3.0, 2.9, 2.7]),
                exposure_scale=1.0,
                T_cam_obj=self.T,
                method="test",
            )
            f = self.frame.replace(seq=i, t_device_ns=(i + 1) * 33_000_000)
            self.sink.write(f.with_result(LIGHT, est))
            i += 1
            time.sleep(self.period)

    def __enter__(self):
        self.t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.t.join(2)


def _shot(page) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_GRAYSCALE).astype(float)


def test_stream_page_shows_frames_and_the_light_overlay(page):
    with MjpegSink(port=0) as sink, _Feeder(sink):
        page.goto(f"http://127.0.0.1:{sink.port}/")
        # the <img> decodes MJPEG frames: its natural size is the stream's
        page.wait_for_function("document.getElementById('stream').naturalWidth === 320", timeout=10000)
        page.wait_for_function("document.getElementById('lightinfo').textContent.includes('elevation')", timeout=10000)
        fit = page.evaluate("getComputedStyle(document.getElementById('stream')).objectFit")
        assert fit == "contain"
        page.keyboard.press("o")  # the overlay toggles
        assert page.evaluate("document.getElementById('overlay').classList.contains('hidden')")
        img = _shot(page)
        assert img.std() > 1.0  # a picture, not an empty page
    assert page.problems == []


def test_stream_page_says_when_the_server_stops_backs_off_and_reopens_the_stream(page):
    """The server going away froze the picture silently while /stats.json was fetched twice a second
    forever; when it came back the <img> stayed frozen (an ended MJPEG stream fires no event)."""
    sink = MjpegSink(port=0)
    sink.open()
    port = sink.port
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    with _Feeder(sink):
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function("document.getElementById('lightinfo').textContent.includes('elevation')", timeout=10000)
        assert page.evaluate("document.getElementById('conn').hidden")
    sink.close()
    page.wait_for_function("!document.getElementById('conn').hidden", timeout=5000)
    assert "not answering" in page.evaluate("document.getElementById('conn').textContent")
    n = len(requests)
    page.wait_for_timeout(4500)
    polls = [u for u in requests[n:] if u.endswith("/stats.json")]
    assert 1 <= len(polls) <= 4, polls  # backing off (1, 2, 4 s), not 9 tries at 0.5 s
    sink2 = MjpegSink(port=port)  # the server is back (same port)
    sink2.open()
    try:
        with _Feeder(sink2):
            page.wait_for_function("document.getElementById('conn').hidden", timeout=10000)
            assert _wait(lambda: sink2.status()["sink"]["clients"] == 1)  # the stream was reopened
            page.wait_for_function("document.getElementById('stream').complete", timeout=5000)
    finally:
        sink2.close()
    # the failed fetches while it was down are the browser's own console lines, nothing else (a request in
    # flight when the server stopped is reset, later ones refused, or closed unanswered)
    down = ("ERR_CONNECTION_REFUSED", "ERR_CONNECTION_RESET", "ERR_EMPTY_RESPONSE")
    assert [p for p in page.problems if not any(k in p for k in down)] == []


def test_stream_page_says_when_the_stream_stops_while_the_server_stays_up_and_reopens_it(page):
    """The source ending or stalling while the server stayed up froze the picture with nothing said
    (/stats.json still answered, so the page thought all was well)."""
    with MjpegSink(port=0) as sink:
        requests: list[str] = []
        page.on("request", lambda r: requests.append(r.url))
        with _Feeder(sink):
            page.goto(f"http://127.0.0.1:{sink.port}/")
            page.wait_for_function("document.getElementById('stream').naturalWidth === 320", timeout=10000)
            assert page.evaluate("document.getElementById('conn').hidden")
        # the frames stop; the server answers on
        page.wait_for_function("!document.getElementById('conn').hidden", timeout=8000)
        line = page.evaluate("document.getElementById('conn').textContent")
        assert "no new frame" in line and "picture has stopped" in line and "Checking again" in line, line
        n = len(requests)
        with _Feeder(sink):  # frames again: the line goes and the stream is reopened
            page.wait_for_function("document.getElementById('conn').hidden", timeout=10000)
            assert any("/stream.mjpg?t=" in u for u in requests[n:]), requests[n:]
    assert page.problems == []


def test_stream_page_overlay_fits_a_phone_and_shows_server_text_as_text(page):
    """The overlay (~650 px tall) ran off a landscape phone's screen with no way to scroll (body
    overflow: hidden); strings from /stats.json were inserted as HTML."""
    page.set_viewport_size({"width": 667, "height": 375})
    stats = {"fps": 30.0, "frames": 10, "stages_ms": {f"stage{i}": 1.0 for i in range(8)}, "source": {"<b>x</b>": 1}}
    with MjpegSink(port=0, stats=lambda: stats) as sink, _Feeder(sink):
        page.goto(f"http://127.0.0.1:{sink.port}/")
        page.wait_for_function("document.getElementById('stages').textContent.includes('stage7')", timeout=10000)
        box = page.evaluate(
            "(() => { const o = document.getElementById('overlay'), r = o.getBoundingClientRect();"
            " return [r.bottom, innerHeight, o.scrollHeight > o.clientHeight, getComputedStyle(o).overflowY]; })()"
        )
        assert box[0] <= box[1] and box[2] and box[3] == "auto", box
        assert "source <b>x</b>" in page.evaluate("document.getElementById('summary').textContent")
    assert page.problems == []


def _wait(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def _side_ratio(img: np.ndarray) -> float:
    """Mean brightness of the model's left half over its right half (the model stands in the middle)."""
    h, w = img.shape
    rows = slice(int(0.2 * h), int(0.8 * h))
    left = img[rows, int(0.32 * w) : int(0.5 * w)].mean()
    right = img[rows, int(0.5 * w) : int(0.68 * w)].mean()
    return left / max(right, 1e-6)


def test_viewer_rendering_follows_the_light_from_left_to_right(page):
    """Fixed estimates flow through the real SSE endpoint; the lit side of the model follows the light."""
    with MjpegSink(port=0) as sink, _Feeder(sink, direction=(-1.0, 0.6, 0.2)) as feeder:
        page.goto(f"http://127.0.0.1:{sink.port}/viewer?ui=0")
        page.wait_for_function(
            "window.illuminetViewer && illuminetViewer.modelLoaded && illuminetViewer.estimates >= 3", timeout=20000
        )
        page.wait_for_function("illuminetViewer.rendered > 3")
        left_lit = _shot(page)
        feeder.direction = np.array([1.0, 0.6, 0.2])
        page.wait_for_function("illuminetViewer.last.primaryLightDirection.x > 0.5", timeout=10000)
        n = page.evaluate("illuminetViewer.rendered")
        page.wait_for_function(f"illuminetViewer.rendered > {n + 2}")
        right_lit = _shot(page)
        state = page.evaluate("illuminetViewer")
    a, b = _side_ratio(left_lit), _side_ratio(right_lit)
    assert a > 1.2 and b < 1 / 1.2, (a, b)
    assert np.abs(left_lit - right_lit).mean() > 3.0
    assert state["errors"] == [] and page.problems == []


def test_viewer_over_the_camera_picture_draws_the_model_where_the_anchor_projects(page):
    """?background=1: the camera stream behind, the model drawn from the camera's pose and intrinsics."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # object +Y up = camera -Y; the camera looks at the object
    T[:3, 3] = [0.15, 0.12, 1.2]  # the anchor: right of and below the image centre, 1.2 m away
    with MjpegSink(port=0) as sink, _Feeder(sink, direction=(0.0, 1.0, 0.3), T_cam_obj=T, grey=40) as feeder:
        page.goto(f"http://127.0.0.1:{sink.port}/viewer?background=1&ui=0")
        page.wait_for_function(
            "window.illuminetViewer && illuminetViewer.modelLoaded && illuminetViewer.estimates >= 3"
            " && document.querySelector('#stage img').naturalWidth === 320",
            timeout=20000,
        )
        n = page.evaluate("illuminetViewer.rendered")
        page.wait_for_function(f"illuminetViewer.rendered > {n + 2}")
        img = _shot(page)
        K = feeder.frame.intrinsics

    # the page is the picture's size (320x240 viewport, same aspect): pixels map 1:1
    def project(p):
        x = T[:3, :3] @ p + T[:3, 3]
        return K.fx * x[0] / x[2] + K.cx, K.fy * x[1] / x[2] + K.cy

    u, v = project(np.array([0.0, 0.12, 0.0]))  # the vase's middle (0.26 m tall)
    assert img[int(v), int(u)] > 100  # the lit white vase over the dark grey picture
    bright = img > 100
    ys, xs = np.nonzero(bright)
    assert abs(np.median(xs) - u) < 12 and abs(np.median(ys) - v) < 25
    u0, v0 = project(np.zeros(3))
    assert ys.max() <= v0 + 4  # it stands on the anchor: nothing of it below its base
    assert 35 < img[5:40, 5:40].mean() < 45  # elsewhere: the camera picture (grey 40), shown through
    assert page.problems == []


def test_viewer_bad_query_parameters_fall_back_to_the_defaults_with_a_note(page):
    """`/viewer?exposure=abc` drew a black canvas (NaN exposure) and said nothing; a bad tonemap, ui or
    background was silently taken as something else."""
    with MjpegSink(port=0) as sink, _Feeder(sink):
        base = f"http://127.0.0.1:{sink.port}/viewer"
        wait = "window.illuminetViewer && illuminetViewer.modelLoaded && illuminetViewer.rendered > 3"
        page.goto(base + "?ui=0")
        page.wait_for_function(wait, timeout=20000)
        good = _shot(page)
        page.goto(base + "?exposure=abc&tonemap=bogus&ui=2&background=yes")
        page.wait_for_function(wait, timeout=20000)
        text = page.evaluate("document.getElementById('status').textContent")
        page.add_style_tag(content="#status { visibility: hidden !important }")  # the picture alone
        page.wait_for_timeout(200)
        bad = _shot(page)
    for note in (
        "?exposure=abc: expected a number > 0; using exposure=1",
        "?tonemap=bogus: expected neutral, aces, agx, none; using tonemap=neutral",
        "?ui=2: expected 1 or 0; using ui=true",
        "?background=yes: expected 1 or 0; using background=false",
    ):
        assert note in text, text
    assert abs(bad.mean() - good.mean()) < 3 and bad.max() > 100, (bad.mean(), good.mean(), bad.max())
    assert page.problems == []


def test_viewer_keeps_a_model_error_on_screen_with_the_servers_reason(page):
    """A /model.glb the server cannot make: the error line was overwritten by the next estimate's figures
    (and named only the status code)."""
    with MjpegSink(port=0) as sink, _Feeder(sink):

        def broken():
            raise ValueError("broken mesh file")

        sink.model_bytes = broken
        page.goto(f"http://127.0.0.1:{sink.port}/viewer")
        page.wait_for_function("window.illuminetViewer && illuminetViewer.estimates >= 5", timeout=20000)
        text = page.evaluate("document.getElementById('status').textContent")
        state = page.evaluate("illuminetViewer")
    assert "could not load the model" in text and "broken mesh file" in text, text
    assert "estimates" in text  # the live figures still show below it
    assert not state["modelLoaded"] and any("broken mesh file" in e for e in state["errors"])
    assert [p for p in page.problems if "500" not in p] == []  # only the browser's line for the 500


def test_viewer_says_when_estimates_stop_and_retries_a_refused_event_stream(page):
    """A 503 (a busy server) on /estimates made EventSource give up for good: "waiting for estimates…"
    for ever. After the server went away the last figures stayed up as if live."""
    answers = []

    def first_refused(route):
        answers.append(route.request.url)
        if len(answers) == 1:
            route.fulfill(status=503, body="busy", headers={"Retry-After": "2"})
        else:
            route.continue_()

    sink = MjpegSink(port=0)
    sink.open()
    try:
        with _Feeder(sink):
            page.route("**/estimates", first_refused)
            page.goto(f"http://127.0.0.1:{sink.port}/viewer")
            page.wait_for_function("window.illuminetViewer && illuminetViewer.estimates >= 3", timeout=20000)
            assert page.evaluate("illuminetViewer.reconnects") == 1 and len(answers) >= 2
            page.unroute("**/estimates")
    finally:
        sink.close()
    page.wait_for_function("document.getElementById('status').textContent.includes('connection to the server is lost')")
    assert [p for p in page.problems if "503" not in p and "ERR_CONNECTION_REFUSED" not in p] == []


def test_viewer_without_webgl_says_so(page):
    """No WebGL (disabled, blocklisted GPU): the page said "loading…" for ever."""
    page.add_init_script(
        "const gc = HTMLCanvasElement.prototype.getContext;"
        "HTMLCanvasElement.prototype.getContext = function (t, ...a) {"
        " return /webgl/.test(t) ? null : gc.call(this, t, ...a); };"
    )
    with MjpegSink(port=0) as sink:
        page.goto(f"http://127.0.0.1:{sink.port}/viewer?ui=0")
        page.wait_for_function("document.getElementById('status').textContent.includes('WebGL is not available')")
        assert page.evaluate("getComputedStyle(document.getElementById('status')).display") != "none"


def test_viewer_status_line_wraps_within_a_phone_screen(page):
    page.set_viewport_size({"width": 320, "height": 568})
    with MjpegSink(port=0) as sink, _Feeder(sink):
        page.goto(f"http://127.0.0.1:{sink.port}/viewer")
        page.wait_for_function("window.illuminetViewer && illuminetViewer.estimates >= 2", timeout=20000)
        right = page.evaluate("document.getElementById('status').getBoundingClientRect().right")
    assert right <= 320, right  # the figures ran past the right edge (white-space: pre)
    assert page.problems == []


def test_viewer_receives_the_pipelines_estimates(page, tmp_path):
    """The real chain (planes -> anchor -> plane light -> light) on the default session -> MJPEG sink -> SSE."""
    from illuminet.commands.demo import default_source_url
    from illuminet.hw import open_source
    from illuminet.pipeline import build_stages
    from illuminet.runtime.config import apply_overrides, defaults
    from illuminet.runtime.stream.loop import run_loop

    cfg = apply_overrides(defaults(), [("source", "timing", "asap")])
    sink = MjpegSink(port=0)
    stop = threading.Event()
    source = open_source(default_source_url(), cfg)
    done = []
    t = threading.Thread(
        target=lambda: done.append(
            run_loop(source, build_stages(cfg, render=False), [sink], stop_event=stop, max_frames=400)
        ),
        daemon=True,
    )
    t.start()
    try:
        deadline = time.monotonic() + 20
        while sink._server is None and time.monotonic() < deadline:
            time.sleep(0.05)
        page.goto(f"http://127.0.0.1:{sink.port}/viewer")
        page.wait_for_function("window.illuminetViewer && illuminetViewer.estimates >= 10", timeout=40000)
        state = page.evaluate(
            "({n: illuminetViewer.estimates, id: illuminetViewer.frameId, "
            "method: illuminetViewer.last.method, loaded: illuminetViewer.modelLoaded})"
        )
    finally:
        stop.set()
        t.join(20)
    assert state["n"] >= 10 and state["id"] >= 9 and state["method"] == "scene"
    assert done and done[0].failed_frames == 0
    assert page.problems == []


def test_h264_mp4_plays_in_a_video_element(page, tmp_path):
    pytest.importorskip("av", reason="PyAV writes the H.264 MP4")
    from illuminet.runtime.stream.sinks import VideoSink

    fs = frames(15, w=320, h=240)
    with VideoSink(tmp_path / "clip.mp4", fps=15) as sink:
        for f in fs:
            sink.write(f)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}"
        (tmp_path / "v.html").write_text(
            '<!doctype html><link rel="icon" href="data:,"><video id="v" src="clip.mp4" muted playsinline></video>'
        )
        page.goto(base + "/v.html")
        page.wait_for_function("document.getElementById('v').readyState >= 1", timeout=10000)
        size = page.evaluate(
            "[document.getElementById('v').videoWidth, document.getElementById('v').videoHeight,"
            " document.getElementById('v').duration]"
        )
        # it decodes, not only parses: playing advances the clock
        page.evaluate("document.getElementById('v').play()")
        page.wait_for_function("document.getElementById('v').currentTime > 0.2", timeout=10000)
    finally:
        server.shutdown()
        server.server_close()
    assert size[:2] == [320, 240] and size[2] == pytest.approx(1.0, abs=0.1)
    assert page.problems == []
