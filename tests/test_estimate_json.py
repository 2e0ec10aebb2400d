"""The lighting estimate as JSON: conventions (three.js / WebXR), the schema, the JSONL sink, the
session sidecar and the MJPEG server's estimate endpoints (a real HTTP client)."""

from __future__ import annotations

import http.client
import json
import threading
import time

import jsonschema
import numpy as np
import pytest

from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import LIGHT, LightEstimate
from illuminet.runtime.sh import SH_A_HAT, sh9
from illuminet.runtime.stream.estimate_json import (
    estimate_dict, estimate_from_dict, frame_estimate, load_schema, to_line,
)
from illuminet.runtime.stream.mjpeg import MjpegSink
from illuminet.runtime.stream.session import ESTIMATES, SessionReader, SessionWriter
from illuminet.runtime.stream.sinks import EstimateSink, SessionRecorderSink

from ._sessions import frames

INTR = Intrinsics(500.0, 500.0, 319.5, 199.5, 640, 400)
SCHEMA = load_schema()


def _estimate(direction=(0.6, 0.8, 0.0), primary=(2.0, 1.5, 1.0), k=0.05, pos=None) -> LightEstimate:
    rng = np.random.default_rng(3)
    sh = rng.normal(0, 0.3, (9, 3))
    sh[0] = [3.0, 2.5, 2.0]
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.4, 2.0]
    return LightEstimate(
        sh9=sh, primary_dir=None if direction is None else np.array(direction) / np.linalg.norm(direction),
        primary_rgb=np.array(primary), primary_pos=None if pos is None else np.array(pos),
        confidence={"ambient": 0.8, "direction": 0.7, "intensity": 0.5, "colour": 0.9, "position": 0.0},
        observed={"planes": np.int64(2), "plane_labels": ["floor", "wall"], "shadow": None,
                  "env_coverage": np.float32(0.4), "emitters": 1, "cues": ["near_light"]},
        exposure_scale=k, method="scene", T_cam_obj=T)


def _three_irradiance(coeffs27: list[float], n: np.ndarray) -> np.ndarray:
    """three.js's ``shGetIrradianceAt`` (lights_pars_begin.glsl.js, r187), transcribed: the irradiance a
    LightProbe with these coefficients gives a surface with normal n."""
    c = np.asarray(coeffs27).reshape(9, 3)
    x, y, z = n
    return (c[0] * 0.886227 + c[1] * 2.0 * 0.511664 * y + c[2] * 2.0 * 0.511664 * z + c[3] * 2.0 * 0.511664 * x
            + c[4] * 2.0 * 0.429043 * x * y + c[5] * 2.0 * 0.429043 * y * z + c[6] * (0.743125 * z * z - 0.247708)
            + c[7] * 2.0 * 0.429043 * x * z + c[8] * 0.429043 * (x * x - y * y))


def test_sh_is_threejs_lightprobe_radiance_in_camera_linear_units():
    est = _estimate()
    d = estimate_dict(est, seq=7, t_device_ns=1_500_000_000, t_host_ns=99, intrinsics=INTR)
    jsonschema.validate(d, SCHEMA)
    assert len(d["sphericalHarmonicsCoefficients"]) == 27
    # a three.js LightProbe fed these 27 floats gives the estimate's own irradiance x exposure_scale
    for n in np.random.default_rng(0).normal(size=(20, 3)):
        n /= np.linalg.norm(n)
        ours = (sh9(n[None]) @ est.sh9)[0] * est.exposure_scale
        assert np.allclose(_three_irradiance(d["sphericalHarmonicsCoefficients"], n), ours, rtol=1e-4, atol=1e-6)
    p = d["primaryLightDirection"]
    assert p["w"] == 0 and np.allclose([p["x"], p["y"], p["z"]], [0.6, 0.8, 0.0], atol=1e-6)
    i = d["primaryLightIntensity"]
    assert i["w"] == 1 and np.allclose([i["x"], i["y"], i["z"]], np.array([2.0, 1.5, 1.0]) * 0.05)
    assert d["hasPrimaryLight"] is True and d["primaryLightPosition"] is None
    assert d["frameId"] == 7 and d["timestamp"] == 1.5 and d["timestampNs"] == {"device": 1_500_000_000, "host": 99}
    assert d["camera"] == {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 199.5, "width": 640, "height": 400}
    assert d["coordinateFrame"]["up"] == [0.0, 1.0, 0.0] and d["coordinateFrame"]["T_cam_obj"][3] == 0.1
    assert d["observed"]["planes"] == 2 and d["observed"]["env_coverage"] == pytest.approx(0.4)
    # ARCore-like colour correction: the mean light's colour with green = 1, a = its luminance / pi
    mean_px = (est.sh9[0] * 0.282095 * 0.05 + np.array([2.0, 1.5, 1.0]) * 0.05 / 4) / np.pi
    cc = d["colorCorrection"]
    assert np.allclose([cc["r"], cc["g"], cc["b"]], mean_px / mean_px[1], rtol=1e-5)
    assert cc["a"] == d["ambientIntensity"] == pytest.approx(mean_px @ [0.2126, 0.7152, 0.0722], rel=1e-5)


def test_no_primary_light_near_light_position_and_round_trip():
    d = estimate_dict(_estimate(direction=None), seq=1, t_device_ns=0)
    jsonschema.validate(d, SCHEMA)
    assert d["hasPrimaryLight"] is False and d["primaryLightIntensity"]["x"] == 0.0
    assert d["primaryLightDirection"] == {"x": 0.0, "y": 1.0, "z": 0.0, "w": 0.0}
    assert d["camera"] is None and d["timestampNs"]["host"] is None
    est = _estimate(pos=(0.3, 0.9, -0.2))
    d = estimate_dict(est, seq=2, t_device_ns=5)
    jsonschema.validate(d, SCHEMA)
    assert d["primaryLightPosition"] == {"x": 0.3, "y": 0.9, "z": -0.2, "w": 1.0}
    back = estimate_from_dict(json.loads(to_line(d)))
    assert np.allclose(back.sh9, est.sh9, rtol=1e-5, atol=1e-6)
    assert np.allclose(back.primary_rgb, est.primary_rgb, rtol=1e-5)
    assert np.allclose(back.T_cam_obj, est.T_cam_obj) and back.method == "scene"


def test_schema_rejects_what_it_should():
    d = estimate_dict(_estimate(), seq=1, t_device_ns=0)
    for bad in ({"sphericalHarmonicsCoefficients": [0.0] * 26}, {"primaryLightDirection": {"x": 0, "y": 1, "z": 0, "w": 1}},
                {"confidence": dict(d["confidence"], ambient=1.5)}, {"extra": 1}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(dict(d, **bad), SCHEMA)
    nan = _estimate()
    nan.sh9[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        estimate_dict(nan, seq=1, t_device_ns=0)


def _with_light(f: Frame, est: LightEstimate | None = None) -> Frame:
    return f.with_result(LIGHT, est if est is not None else _estimate())


def test_jsonl_sink_writes_one_valid_line_per_frame_with_an_estimate(tmp_path):
    fs = frames(5)
    path = tmp_path / "est.jsonl"
    with EstimateSink(path) as sink:
        for k, f in enumerate(fs):
            sink.write(_with_light(f) if k != 2 else f)  # frame 2: no estimate (no anchor yet)
        assert sink.stats() == {"frames": 5, "estimates": 4}
    lines = path.read_text().splitlines()
    assert [json.loads(x)["frameId"] for x in lines] == [0, 1, 3, 4]
    for x in lines:
        jsonschema.validate(json.loads(x), SCHEMA)
    from illuminet.runtime.stream.sinks import SinkError

    with pytest.raises(SinkError, match="does not exist"):
        EstimateSink(tmp_path / "no" / "x.jsonl").open()


def test_recorder_writes_the_estimates_sidecar_and_the_reader_tolerates_its_absence(tmp_path):
    fs = frames(6)
    with SessionRecorderSink(tmp_path / "s", fsync=False) as sink:
        for k, f in enumerate(fs):
            sink.write(_with_light(f, _estimate(k=0.01 * (k + 1))) if k % 2 else f)
    r = SessionReader(tmp_path / "s", strict=True)
    assert r.manifest["version"] == 1  # the sidecar changes no format version: old readers still read it
    est = r.estimates()
    assert sorted(est) == [1, 3, 5]
    assert est[3]["frameId"] == 3 and est[3]["exposureScale"] == pytest.approx(0.04)
    jsonschema.validate(est[5], SCHEMA)
    # a torn last line (a kill while writing it) and junk are skipped, the rest stays
    with open(tmp_path / "s" / ESTIMATES, "ab") as fh:
        fh.write(b'{"i": 0, "estimate": {"fram')
    assert sorted(SessionReader(tmp_path / "s").estimates()) == [1, 3, 5]
    # a session recorded without estimates: an empty mapping, no problem reported
    with SessionWriter(tmp_path / "plain", fsync=False) as w:
        w.append(fs[0])
    r = SessionReader(tmp_path / "plain", strict=True)
    assert r.estimates() == {} and r.problems == []


def _get(port: int, path: str) -> tuple[int, dict, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    conn.request("GET", path)
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, {k.lower(): v for k, v in r.getheaders()}, body


def _sse_events(port: int, n: int, timeout: float = 5.0) -> list[tuple[int, dict]]:
    """Read ``n`` events from /estimates with a plain HTTP client: (id, parsed data) each."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    conn.request("GET", "/estimates")
    r = conn.getresponse()
    assert r.status == 200 and r.getheader("Content-Type").startswith("text/event-stream")
    assert r.getheader("Access-Control-Allow-Origin") == "*"
    out, ev = [], {}
    try:
        while len(out) < n:
            line = r.fp.readline()
            assert line, "event stream ended early"
            line = line.decode().rstrip("\n")
            if not line:
                if "data" in ev:
                    out.append((int(ev["id"]), json.loads(ev["data"])))
                ev = {}
                continue
            if line.startswith(":"):
                continue
            k, _, v = line.partition(": ")
            ev[k] = v
    finally:
        conn.close()
    return out


def test_mjpeg_server_serves_the_estimate_as_json_and_server_sent_events():
    fs = frames(200)
    with MjpegSink(port=0, max_fps=0) as sink:
        status, _, body = _get(sink.port, "/estimate.json")
        assert status == 200 and json.loads(body) is None  # before the first estimate
        stop = threading.Event()

        def feed():
            for f in fs:
                if stop.is_set():
                    return
                sink.write(_with_light(f))
                time.sleep(0.005)

        t = threading.Thread(target=feed, daemon=True)
        t.start()
        try:
            events = _sse_events(sink.port, 5)
            ids = [i for i, _ in events]
            assert ids == sorted(ids) and len(set(ids)) == 5  # newest first-come, never repeated
            for i, d in events:
                assert d["frameId"] == i
                jsonschema.validate(d, SCHEMA)
            status, head, body = _get(sink.port, "/estimate.json")
            assert status == 200 and head["access-control-allow-origin"] == "*"
            latest = json.loads(body)
            assert latest["frameId"] >= ids[-1]
            s = json.loads(_get(sink.port, "/stats.json")[2])
            assert s["estimate"]["schema"] == "illuminet-light-estimate" and s["sink"]["estimates_sent"] >= 5
            status, head, body = _get(sink.port, "/light_estimate.schema.json")
            assert status == 200 and json.loads(body) == SCHEMA
        finally:
            stop.set()
            t.join(5)


def test_sse_rate_cap_skips_to_the_newest():
    fs = frames(400)
    with MjpegSink(port=0, max_fps=10) as sink:
        stop = threading.Event()

        def feed():
            for f in fs:
                if stop.is_set():
                    return
                sink.write(_with_light(f))
                time.sleep(0.002)

        t = threading.Thread(target=feed, daemon=True)
        t.start()
        try:
            t0 = time.perf_counter()
            events = _sse_events(sink.port, 5)
            dt = time.perf_counter() - t0
        finally:
            stop.set()
            t.join(5)
    ids = [i for i, _ in events]
    assert dt >= 0.35  # 5 events at <= 10 per second
    assert min(np.diff(ids)) >= 2  # frames between the slots were skipped, not queued


def test_frame_estimate_is_none_without_a_light_result():
    f = frames(1)[0]
    assert frame_estimate(f) is None
    assert frame_estimate(_with_light(f))["frameId"] == f.seq
