"""The lighting estimate as JSON: conventions (three.js / WebXR), the schema, the JSONL sink, the
session sidecar and the MJPEG server's estimate endpoints (a real HTTP client)."""

from __future__ import annotations

import http.client
import json
import threading
import time

import cv2
import jsonschema
import numpy as np
import pytest

from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import LIGHT, LightEstimate
from illuminet.runtime.sh import sh9
from illuminet.runtime.stream.estimate_json import (
    estimate_dict,
    estimate_from_dict,
    frame_estimate,
    load_schema,
    to_line,
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
        sh9=sh,
        primary_dir=None if direction is None else np.array(direction) / np.linalg.norm(direction),
        primary_rgb=np.array(primary),
        primary_pos=None if pos is None else np.array(pos),
        confidence={"ambient": 0.8, "direction": 0.7, "intensity": 0.5, "colour": 0.9, "position": 0.0},
        observed={
            "planes": np.int64(2),
            "plane_labels": ["floor", "wall"],
            "shadow": None,
            "env_coverage": np.float32(0.4),
            "emitters": 1,
            "cues": ["near_light"],
        },
        exposure_scale=k,
        method="scene",
        T_cam_obj=T,
    )


def _three_irradiance(coeffs27: list[float], n: np.ndarray) -> np.ndarray:
    """three.js's ``shGetIrradianceAt`` (lights_pars_begin.glsl.js, r187), transcribed: the irradiance a
    LightProbe with these coefficients gives a surface with normal n."""
    c = np.asarray(coeffs27).reshape(9, 3)
    x, y, z = n
    return (
        c[0] * 0.886227
        + c[1] * 2.0 * 0.511664 * y
        + c[2] * 2.0 * 0.511664 * z
        + c[3] * 2.0 * 0.511664 * x
        + c[4] * 2.0 * 0.429043 * x * y
        + c[5] * 2.0 * 0.429043 * y * z
        + c[6] * (0.743125 * z * z - 0.247708)
        + c[7] * 2.0 * 0.429043 * x * z
        + c[8] * 0.429043 * (x * x - y * y)
    )


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
    # a position without a primary light was exported (9 of 30 lines in an attack's run): a client
    # would place a point light there
    assert (
        estimate_dict(_estimate(direction=None, pos=(0.3, 0.9, -0.2)), seq=3, t_device_ns=6)["primaryLightPosition"]
        is None
    )
    back = estimate_from_dict(json.loads(to_line(d)))
    assert np.allclose(back.sh9, est.sh9, rtol=1e-5, atol=1e-6)
    assert np.allclose(back.primary_rgb, est.primary_rgb, rtol=1e-5)
    assert np.allclose(back.T_cam_obj, est.T_cam_obj) and back.method == "scene"


def test_schema_rejects_what_it_should():
    d = estimate_dict(_estimate(), seq=1, t_device_ns=0)
    for bad in (
        {"sphericalHarmonicsCoefficients": [0.0] * 26},
        {"primaryLightDirection": {"x": 0, "y": 1, "z": 0, "w": 1}},
        {"confidence": dict(d["confidence"], ambient=1.5)},
        {"extra": 1},
    ):
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
        assert sink.stats() == {"frames": 5, "estimates": 4, "dropped_lines": 0}
    lines = path.read_text().splitlines()
    assert [json.loads(x)["frameId"] for x in lines] == [0, 1, 3, 4]
    for x in lines:
        jsonschema.validate(json.loads(x), SCHEMA)
    from illuminet.runtime.stream.sinks import SinkError

    with pytest.raises(SinkError, match="does not exist"):
        EstimateSink(tmp_path / "no" / "x.jsonl").open()


def test_estimates_to_a_closed_stdout_is_refused_at_open(monkeypatch):
    # `illuminet run ... --estimates - >&-`: sys.stdout is None, and each frame failed with the
    # misleading "EstimateSink.write() before open()"
    import sys

    from illuminet.runtime.stream.sinks import SinkError

    monkeypatch.setattr(sys, "stdout", None)
    with pytest.raises(SinkError, match=r"estimates -: standard output is closed; give a file"):
        EstimateSink("-").open()


def test_estimates_piped_into_a_reader_that_leaves_ends_the_run():
    """``run LIVE --estimates - | head -1``: the run ends when its reader has gone (a live camera ran for
    ever, every frame a sink failure), exit 0, one log line, no BrokenPipeError noise at exit."""
    import subprocess
    import sys

    argv = [sys.executable, "-m", "illuminet", "run", "synthetic://lamp?frames=100000&size=160x100", "--estimates", "-"]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = p.stdout.readline()
    p.stdout.close()  # what head does after its line
    try:
        err = p.stderr.read().decode()
        rc = p.wait(timeout=120)
    finally:
        p.kill()
    assert json.loads(first)["schema"] == "illuminet-light-estimate"
    assert rc == 0, err
    assert "the reader of standard output has gone; the run ends" in err
    assert "Traceback" not in err and "Exception ignored" not in err and "BrokenPipe" not in err, err


def test_an_estimates_file_on_a_full_disk_names_the_file_at_close():
    # the last lines' flush raised a bare OSError: the run's last line was "illuminet: [Errno 28] No space
    # left on device", naming no output
    from illuminet.runtime.stream.sinks import SinkError

    sink = EstimateSink("/dev/full")
    sink.open()
    with pytest.raises(OSError):  # each frame's line fails (the loop counts it as a sink failure)
        sink.write(_with_light(frames(1)[0]))
    with pytest.raises(SinkError, match=r"estimates /dev/full: cannot write the last lines: No space left"):
        sink.close()


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
    with open(tmp_path / "s" / ESTIMATES, "ab") as fh:  # a line nested too deeply was a RecursionError
        fh.write(b"\n" + b"[" * 100000 + b"]" * 100000 + b"\n")
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


def test_pages_static_files_and_model_are_served_and_traversal_is_refused():
    with MjpegSink(port=0, viewer_model="builtin:bowl") as sink:
        status, head, body = _get(sink.port, "/viewer")
        assert status == 200 and head["content-type"].startswith("text/html")
        assert b'"three": "/static/three/three.module.js"' in body and b"/static/viewer.js" in body
        for rel in (
            "viewer.js",
            "three/three.module.js",
            "three/three.core.js",
            "three/addons/loaders/GLTFLoader.js",
            "three/addons/controls/OrbitControls.js",
            "three/LICENSE",
            "three/VERSION",
        ):
            status, head, body = _get(sink.port, "/static/" + rel)
            assert status == 200 and len(body) > 100, rel
            if rel.endswith(".js"):
                assert head["content-type"].startswith("text/javascript"), rel
        for bad in (
            "/static/../mjpeg.py",
            "/static/three/../../viewer.py",
            "/static/%2e%2e/mjpeg.py",
            "/static/.hidden",
            "/static//etc/passwd",
        ):
            assert _get(sink.port, bad)[0] == 404, bad
        status, head, body = _get(sink.port, "/model.glb")
        assert status == 200 and head["content-type"] == "model/gltf-binary" and body[:4] == b"glTF"
        import io

        import trimesh

        scene = trimesh.load(io.BytesIO(body), file_type="glb")
        lo, hi = scene.bounds
        assert abs(lo[1]) < 1e-6 and 0.05 < hi[1] < 0.5  # standing on y = 0, +Y up, metres
        # smooth normals are in the file (without them glTF viewers shade flat)
        n = int.from_bytes(body[12:16], "little")
        gltf = json.loads(body[20 : 20 + n])
        assert "NORMAL" in gltf["meshes"][0]["primitives"][0]["attributes"]


def test_camera_stream_is_the_picture_without_the_object():
    f = frames(1, w=160, h=120)[0]
    comp = np.zeros_like(f.color)
    comp[..., 2] = 255
    with MjpegSink(port=0) as sink:
        sink.write(f.with_result("composite", comp))
        out = {}
        for src in ("composite", "camera"):
            conn = http.client.HTTPConnection("127.0.0.1", sink.port, timeout=5)
            conn.request("GET", "/stream.mjpg" + ("?source=camera" if src == "camera" else ""))
            r = conn.getresponse()
            assert r.status == 200
            data = b""
            while data.count(b"\xff\xd9") < 1:
                data += r.fp.read1(65536)
            jpg = data[data.index(b"\xff\xd8") : data.index(b"\xff\xd9") + 2]
            out[src] = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            conn.close()
        assert _get(sink.port, "/stream.mjpg?source=nope")[0] == 400
    assert out["composite"][..., 2].mean() > 240
    assert np.abs(out["camera"].astype(int) - f.color.astype(int)).mean() < 8


def test_bad_viewer_model_is_refused_before_the_server_starts(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "nope.glb"))
    (tmp_path / "m.fbx").write_bytes(b"x")
    with pytest.raises(ValueError, match="unknown mesh format '.fbx'"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "m.fbx"))
    with pytest.raises(ValueError, match="unknown built-in object"):
        MjpegSink(port=0, viewer_model="builtin:teapot")
    # files that exist but hold nothing to draw: refused now, not a 500 at the first /model.glb
    (tmp_path / "empty.obj").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.obj: the file is empty \\(0 bytes\\)"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "empty.obj"))
    # a folder was "no such file", an empty or cut GLB "index 0 is out of bounds": said as what they are
    (tmp_path / "models").mkdir()
    with pytest.raises(ValueError, match="'.*models': is a directory"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "models"))
    (tmp_path / "cut.glb").write_bytes(b"glTF\x02\x00\x00\x00\x00\x10\x00\x00" + b"\x00" * 20)
    with pytest.raises(ValueError, match="cut.glb: truncated GLB file: 32 bytes, its header declares 4096"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "cut.glb"))
    (tmp_path / "bad.glb").write_bytes(b"glTF\x02\x00\x00\x00\x0c\x00\x00\x00")
    with pytest.raises(ValueError, match="'.*bad.glb': not a readable glTF binary"):
        MjpegSink(port=0, viewer_model=str(tmp_path / "bad.glb"))


def test_viewer_model_with_texture_coordinates_and_no_material_is_drawn_grey(tmp_path):
    """An OBJ with texture coordinates and no material file (Keenan Crane's spot, many scans) gets trimesh's
    default material, whose image needs Pillow: `demo --mjpeg --viewer-model spot.obj` died at start with a
    ModuleNotFoundError traceback. With no texture image of its own it is the renderer's grey, as a plain mesh."""
    import trimesh

    from illuminet.runtime.stream.viewer import model_glb

    lines = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "vt 0 0", "vt 1 0", "vt 0 1", "vt 1 1"]
    lines += ["f 1/1 3/3 2/2", "f 1/1 2/2 4/4", "f 1/1 4/4 3/3", "f 2/2 3/3 4/4"]
    (tmp_path / "uv.obj").write_text("\n".join(lines) + "\n")
    glb = model_glb(str(tmp_path / "uv.obj"), 1.0)
    assert glb[:4] == b"glTF"
    scene = trimesh.load(trimesh.util.wrap_as_stream(glb), file_type="glb", force="scene")
    (mesh,) = scene.geometry.values()
    assert len(mesh.faces) == 4


@pytest.mark.gl
def test_replay_reproduces_the_recorded_estimates(tmp_path, gl, capsys):
    """run --record --estimates on the default session, then replay the recording: the estimates of the
    JSONL file, the session's sidecar and the replay agree exactly (timestamps on the host aside)."""
    from illuminet.cli import main
    from illuminet.commands.demo import DEFAULT_SESSION

    src = f"replay://{DEFAULT_SESSION}?timing=asap"
    rc = main(
        [
            "--log-level",
            "warning",
            "--set",
            "output.record_fsync=false",
            "run",
            src,
            "--max-frames",
            "6",
            "--record",
            str(tmp_path / "rec"),
            "--estimates",
            str(tmp_path / "live.jsonl"),
        ]
    )
    assert rc == 0, capsys.readouterr()
    rc = main(
        [
            "--log-level",
            "warning",
            "replay",
            str(tmp_path / "rec"),
            "--timing",
            "asap",
            "--estimates",
            str(tmp_path / "replay.jsonl"),
        ]
    )
    assert rc == 0, capsys.readouterr()

    def load(path):
        out = [json.loads(x) for x in path.read_text().splitlines()]
        return [dict(d, timestampNs=d["timestampNs"]["device"]) for d in out]

    live, again = load(tmp_path / "live.jsonl"), load(tmp_path / "replay.jsonl")
    sidecar = SessionReader(tmp_path / "rec").estimates()
    assert len(live) == 6 and [d["frameId"] for d in live] == list(range(6))
    assert again == live
    assert [dict(sidecar[i], timestampNs=sidecar[i]["timestampNs"]["device"]) for i in range(6)] == live
    capsys.readouterr()
    assert main(["replay", str(tmp_path / "rec"), "--check"]) == 0
    assert "lighting estimates: 6 of 6 frames (estimates.jsonl)" in capsys.readouterr().out


def test_record_refuses_estimates_it_cannot_make(tmp_path, capsys):
    from illuminet.cli import main

    assert main(["record", "synthetic://indoor", str(tmp_path / "r"), "--estimates", str(tmp_path / "e.jsonl")]) == 2
    assert "use `illuminet run SOURCE --record OUT --estimates FILE`" in capsys.readouterr().err


def test_an_estimates_file_on_a_full_disk_keeps_only_whole_lines(tmp_path):
    """A file that reaches its size limit (RLIMIT_FSIZE: what a full disk does to a write) ended with a
    torn line, half a JSON object that its reader choked on; a line is written whole or not at all."""
    import resource
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys\n"
        "from tests._sessions import frames\n"
        "from tests.test_estimate_json import _with_light\n"
        "from illuminet.runtime.stream.sinks import EstimateSink, SinkError\n"
        "sink = EstimateSink(sys.argv[1]); sink.open(); fails = 0\n"
        "for f in frames(20):\n"
        "    try:\n"
        "        sink.write(_with_light(f))\n"
        "    except OSError:\n"
        "        fails += 1\n"
        "try:\n"
        "    sink.close()\n"
        "except SinkError as e:\n"
        "    print(e, file=sys.stderr)\n"
        "print(fails, sink.stats()['estimates'])\n"
    )
    path = tmp_path / "est.jsonl"
    limit = 10_000  # a few lines of ~1.4 kB: the limit falls inside a line

    def small_disk():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    p = subprocess.run(
        [sys.executable, "-c", code, str(path)],
        cwd=Path(__file__).resolve().parents[1],
        preexec_fn=small_disk,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    fails, written = map(int, p.stdout.split())
    data = path.read_bytes()
    assert 0 < len(data) <= limit and data.endswith(b"\n"), data[-80:]
    lines = data.decode().splitlines()
    assert [json.loads(x)["frameId"] for x in lines] == list(range(written))
    assert fails == 20 - written > 0
    assert f"estimates {path}: cannot write the last lines: File too large" in p.stderr


def _pipe_as_stdout(monkeypatch):
    """``--estimates -`` piped into a consumer: sys.stdout is the write end of an os.pipe; returns its read end."""
    import os
    import sys

    r, w = os.pipe()
    monkeypatch.setattr(sys, "stdout", os.fdopen(w, "w"))
    return r


def _read_all(fd: int) -> bytes:
    import os

    out = b""
    while chunk := os.read(fd, 1 << 16):
        out += chunk
    return out


def test_estimates_to_a_pipe_whose_reader_stops_reading_do_not_block_the_loop(monkeypatch):
    """``run LIVE --estimates - | consumer`` where the consumer stops reading but keeps the pipe open:
    the loop blocked in write() once the pipe's 64 kB were full, freezing the whole stream (MJPEG too),
    and close() blocked for ever. Lines are now dropped (oldest first, counted) and close is bounded."""
    import os

    r = _pipe_as_stdout(monkeypatch)
    fs = [_with_light(f) for f in frames(300)]  # ~1.4 kB each: far more than the pipe holds
    sink = EstimateSink("-")
    sink.open()
    done = {}

    def loop():
        for f in fs:
            sink.write(f)
        t0 = time.monotonic()
        sink.close()
        done["close_s"] = time.monotonic() - t0

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    t.join(30)
    try:
        assert not t.is_alive(), "the loop blocked writing to a pipe nobody reads"
        assert done["close_s"] < 5
        st = sink.stats()
        assert st["frames"] == 300 and st["dropped_lines"] > 0
        assert st["estimates"] + st["dropped_lines"] == 300
        sys_stdout_w = __import__("sys").stdout
        sys_stdout_w.close()  # the test's end of the pipe; the reader then sees what got through
        lines = _read_all(r).decode().splitlines()
    finally:
        os.close(r)
    ids = [json.loads(x)["frameId"] for x in lines]  # every line whole, in order
    assert len(ids) == st["estimates"] and ids == sorted(set(ids)) and set(ids) <= set(range(300))


def test_estimates_to_a_pipe_whose_reader_keeps_up_keep_every_line_in_order(monkeypatch):
    import os
    import sys

    r = _pipe_as_stdout(monkeypatch)
    got = []
    reader = threading.Thread(target=lambda: got.append(_read_all(r)), daemon=True)
    reader.start()
    fs = [_with_light(f) for f in frames(300)]
    sink = EstimateSink("-")
    sink.open()
    for f in fs:
        sink.write(f)
        time.sleep(0.002)  # a live stream's pace; the reader keeps up
    sink.close()
    sys.stdout.close()
    reader.join(10)
    os.close(r)
    assert sink.stats() == {"frames": 300, "estimates": 300, "dropped_lines": 0}
    assert [json.loads(x)["frameId"] for x in got[0].decode().splitlines()] == list(range(300))


def test_a_run_whose_estimates_reader_stops_reading_stops_at_one_sigterm(tmp_path):
    """``illuminet run LIVE --estimates - --video V | consumer``, the consumer stalled: the stream froze
    and one SIGTERM (a service manager's stop) did nothing, so the SIGKILL after it left the video
    unfinished. Now the stream goes on, the SIGTERM ends it, the video is finalised."""
    import fcntl
    import signal
    import subprocess
    import sys

    video = tmp_path / "v.mp4"
    argv = [sys.executable, "-m", "illuminet", "run", "synthetic://lamp?frames=100000&size=160x100"]
    argv += ["--estimates", "-", "--video", str(video)]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    errs: list[bytes] = []
    drain = threading.Thread(target=lambda: errs.extend(p.stderr), daemon=True)
    drain.start()
    try:
        fcntl.fcntl(p.stdout.fileno(), 1031, 4096)  # F_SETPIPE_SZ: the smallest pipe, full after a few lines
        deadline = time.monotonic() + 60
        while not int.from_bytes(fcntl.ioctl(p.stdout.fileno(), 0x541B, b"\0\0\0\0"), sys.byteorder):  # FIONREAD
            assert time.monotonic() < deadline and p.poll() is None, b"".join(errs).decode()
            time.sleep(0.1)
        deadline = time.monotonic() + 15  # the stream goes on past the full pipe, and drops lines
        while not any(b"not keeping up" in x for x in errs) and time.monotonic() < deadline:
            time.sleep(0.1)
        p.send_signal(signal.SIGTERM)
        try:
            rc = p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            raise AssertionError("one SIGTERM did not stop a run whose estimates reader stalled") from None
    finally:
        p.kill()
        p.wait()
    drain.join(10)
    err = b"".join(errs).decode()
    assert rc == 0, err
    assert "ended: stopped" in err and "Traceback" not in err, err
    assert "not keeping up" in err and "dropped_lines=" in err, err
    cap = cv2.VideoCapture(str(video))
    assert cap.isOpened() and cap.read()[0], "the video was not finalised"
