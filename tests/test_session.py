"""Recorded sessions: round trip, crash safety under a real kill -9, and every bad-session case."""

from __future__ import annotations

import json
import os
import signal
import textwrap

import cv2
import numpy as np
import pytest

from illuminet.runtime.frame import Exposure, ImuSample
from illuminet.runtime.stream.session import (
    FORMAT_NAME,
    CorruptFrame,
    SessionError,
    SessionReader,
    SessionWriter,
    safe_relpath,
)

from ._sessions import H, W, complete_lines, frames, make_session, same_frame, spawn, wait_for_lines


def _index(path):
    return path / "frames.jsonl"


def _lines(path):
    return _index(path).read_text().splitlines()


def _rewrite_line(path, k, **changes):
    lines = _lines(path)
    d = json.loads(lines[k])
    d.update(changes)
    lines[k] = json.dumps(d)
    _index(path).write_text("\n".join(lines) + "\n")


def _set_manifest(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m.update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


# ---------------------------------------------------------------------------------- round trip


def test_round_trip_is_bit_exact_with_all_metadata(tmp_path):
    fs = frames(4)
    imu = (
        ImuSample(t_ns=5, accel=(0.1, -9.8, 0.2), gyro=(0.01, 0.0, -0.02)),
        ImuSample(t_ns=6, accel=(0.0, -9.7, 0.1)),
    )
    fs[1] = fs[1].replace(
        imu=imu, exposure=Exposure(exposure_us=1000.0, iso=200.0, wb_gains=(1.9, 1.0, 1.6), color_temperature_k=4200.0)
    )
    fs[2] = fs[2].replace(depth=None, gravity=None)
    with SessionWriter(tmp_path / "s", source="test://x", color="png") as w:
        for f in fs:
            w.append(f)
    r = SessionReader(tmp_path / "s", strict=True)
    assert r.problems == [] and r.finalized and len(r) == 4
    assert r.manifest["format"] == FORMAT_NAME and r.manifest["version"] == 1
    assert r.manifest["source"] == "test://x" and r.manifest["frame_count"] == 4
    got = list(r)
    for a, b in zip(fs, got):
        assert same_frame(a, b)
        assert b.color.dtype == np.uint8 and b.color.shape == (H, W, 3)
    assert got[1].imu == imu and got[1].exposure == fs[1].exposure
    assert got[2].depth is None and got[2].gravity is None
    assert np.allclose(got[0].gravity, [0, 1, 0])
    assert all(isinstance(f.t_device_ns, int) for f in got)
    # the colour file is an ordinary RGB PNG: any viewer shows the right colours
    png = cv2.imread(str(tmp_path / "s" / "frames" / "000000.color.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(png[..., ::-1], fs[0].color)
    depth = cv2.imread(str(tmp_path / "s" / "frames" / "000000.depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and np.array_equal(depth, np.rint(fs[0].depth * 1000).astype(np.uint16))


def test_default_colour_encoding_is_raw_and_lossless(tmp_path):
    fs = frames(3)
    with SessionWriter(tmp_path / "s") as w:
        for f in fs:
            w.append(f)
    r = SessionReader(tmp_path / "s", strict=True)
    assert r.color_encoding == "raw" and r.manifest["color"] == {"encoding": "raw", "channels": "RGB"}
    assert (tmp_path / "s" / "frames" / "000000.color.rgb").stat().st_size == W * H * 3
    assert all(same_frame(a, b) for a, b in zip(fs, r))


@pytest.mark.parametrize("color", ["raw", "jpeg"])
def test_other_colour_encodings(tmp_path, color):
    fs = make_session(tmp_path / "s", 3, color=color, jpeg_quality=90)
    r = SessionReader(tmp_path / "s", strict=True)
    for a, b in zip(fs, r):
        assert np.array_equal(a.depth, b.depth)  # depth is always lossless
        if color == "raw":
            assert np.array_equal(a.color, b.color)
        else:
            assert np.abs(a.color.astype(int) - b.color.astype(int)).mean() < 4.0


def test_intrinsics_change_is_recorded_per_frame(tmp_path):
    fs = frames(2)
    k2 = fs[1].intrinsics.scaled(W, H).__class__(fx=99.0, fy=98.0, cx=30.0, cy=20.0, width=W, height=H)
    fs[1] = fs[1].replace(intrinsics=k2)
    with SessionWriter(tmp_path / "s") as w:
        for f in fs:
            w.append(f)
    got = list(SessionReader(tmp_path / "s", strict=True))
    assert got[0].intrinsics == fs[0].intrinsics and got[1].intrinsics == k2


def test_writer_refuses_bad_input(tmp_path):
    fs = frames(3)
    w = SessionWriter(tmp_path / "s")
    w.append(fs[1])
    with pytest.raises(SessionError, match="does not increase"):
        w.append(fs[0])
    small = frames(1, w=32, h=24)[0].replace(t_device_ns=fs[2].t_device_ns)
    with pytest.raises(SessionError, match="32x24 but the session is 64x48"):
        w.append(small)
    # a looped replay of a session stamped near 2**63 went past it: written, then skipped by every reader
    with pytest.raises(SessionError, match=r"t_device_ns 9223372036854775808 is outside 0..2\*\*63-1 ns"):
        w.append(fs[2].replace(t_device_ns=2**63))
    with pytest.raises(SessionError, match=r"t_host_ns -1 is outside"):
        w.append(fs[2].replace(t_host_ns=-1))
    w.close()
    with pytest.raises(SessionError, match="closed"):
        w.append(fs[2])
    with pytest.raises(SessionError, match="already contains a session"):
        SessionWriter(tmp_path / "s")
    with pytest.raises(ValueError, match="colour encoding"):
        SessionWriter(tmp_path / "t", color="webp")
    assert len(SessionReader(tmp_path / "s", strict=True)) == 1


def test_writer_refuses_a_folder_that_holds_other_files(tmp_path):
    """`illuminet record URL sessions` (the folder of the user's sessions, or `.`) made that folder a
    session: its frames/, index and manifest among the user's files, the sessions in it now inside a
    recording. A new or empty folder (or the empty frames/ of a recording killed before its first
    frame) is what a session goes into."""
    fs = frames(1)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(SessionError, match=r"mine: the folder is not empty \(it holds notes.txt\); choose a new"):
        SessionWriter(tmp_path / "mine")
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]  # nothing added
    (tmp_path / "empty").mkdir()
    (tmp_path / "killed" / "frames").mkdir(parents=True)
    for name in ("empty", "killed"):
        with SessionWriter(tmp_path / name) as w:
            w.append(fs[0])
        assert len(SessionReader(tmp_path / name, strict=True)) == 1


# ---------------------------------------------------------------------------------- crash safety

_WRITER = textwrap.dedent(
    """
    import sys
    from illuminet.bench.replay import numpy_rgbd_frames
    from illuminet.runtime.stream.session import SessionWriter
    w = SessionWriter(sys.argv[1], source="test://kill", fsync=False, color=sys.argv[2])
    for f in numpy_rgbd_frames(100000, 64, 48):   # records until killed
        w.append(f)
    """
)


@pytest.mark.parametrize("attempt, color", [(0, "raw"), (1, "png"), (2, "raw")])
def test_kill_9_mid_recording_keeps_every_complete_frame(tmp_path, attempt, color):
    """A REAL SIGKILL of a process appending frames: replay returns exactly the completed frames."""
    path = tmp_path / "s"
    proc = spawn(["-c", _WRITER, str(path), color])
    try:
        wait_for_lines(_index(path), 6 + 7 * attempt, proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    n_complete = complete_lines(_index(path))
    r = SessionReader(path)  # not strict: an interrupted recording is expected to have warnings
    assert not r.finalized
    assert len(r) == n_complete >= 6
    # nothing reported but the missing finalisation and possibly the torn last line
    assert all("not finalised" in p or "torn" in p for p in r.problems), r.problems
    expected = frames(n_complete)
    for k, f in enumerate(r):
        assert same_frame(expected[k], f), f"frame {k} differs after kill -9"


@pytest.mark.slow
def test_kill_9_at_many_random_moments(tmp_path):
    """Stress: 25 SIGKILLs at random moments (with fsync on); every complete frame always replays."""
    import random
    import time

    rnd = random.Random(1)
    for k in range(25):
        path = tmp_path / f"s{k}"
        proc = spawn(["-c", _WRITER.replace("fsync=False", "fsync=True"), str(path), ("raw", "png")[k % 2]])
        try:
            wait_for_lines(_index(path), 1, proc)
            time.sleep(rnd.uniform(0.0, 0.3))
        finally:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        n_complete = complete_lines(_index(path))
        r = SessionReader(path)
        assert len(r) == n_complete
        assert all("not finalised" in p or "torn" in p for p in r.problems), r.problems
        expected = frames(n_complete)
        assert all(same_frame(expected[i], f) for i, f in enumerate(r))


def test_kill_before_first_frame_is_reported(tmp_path):
    (tmp_path / "s" / "frames").mkdir(parents=True)
    with pytest.raises(SessionError, match=r"manifest.json: missing.*killed before its first"):
        SessionReader(tmp_path / "s")


# ---------------------------------------------------------------------------------- bad sessions


def test_not_a_folder(tmp_path):
    with pytest.raises(SessionError, match="not a session folder"):
        SessionReader(tmp_path / "nope")


def test_manifest_not_json(tmp_path):
    make_session(tmp_path / "s", 2)
    (tmp_path / "s" / "manifest.json").write_text("{not json")
    with pytest.raises(SessionError, match=r"manifest.json: not valid JSON"):
        SessionReader(tmp_path / "s")
    (tmp_path / "s" / "manifest.json").write_text("[" * 100000 + "]" * 100000)  # was a RecursionError
    with pytest.raises(SessionError, match=r"manifest.json: JSON nested too deeply"):
        SessionReader(tmp_path / "s")


def test_manifest_json_that_python_refuses_is_one_session_error(tmp_path):
    # json refuses ints of over 4300 digits with a bare ValueError, past the JSONDecodeError handler:
    # a traceback instead of the file's name
    make_session(tmp_path / "s", 2)
    (tmp_path / "s" / "manifest.json").write_text('{"width": ' + "9" * 5000 + "}")
    with pytest.raises(SessionError, match=r"manifest.json: not valid JSON \(.*4300 digits"):
        SessionReader(tmp_path / "s")


def test_unknown_version_is_named(tmp_path):
    make_session(tmp_path / "s", 2)
    _set_manifest(tmp_path / "s", version=99)
    with pytest.raises(SessionError, match=r"unknown session format version 99.*reads version\(s\) 1"):
        SessionReader(tmp_path / "s")


def test_wrong_format_name(tmp_path):
    make_session(tmp_path / "s", 2)
    _set_manifest(tmp_path / "s", format="something-else")
    with pytest.raises(SessionError, match=r"key 'format': expected 'illuminet-session', got 'something-else'"):
        SessionReader(tmp_path / "s")


@pytest.mark.parametrize(
    "key, value, expect",
    [
        ("width", "640", r"key 'width': expected int, got str"),
        ("height", 0, r"key 'height': expected a positive int"),
        ("intrinsics", {"fx": 1}, r"key 'intrinsics'"),
        ("color", {"encoding": "webp"}, r"color.encoding': expected one of"),
        ("depth", {"encoding": "float32"}, r"key 'depth': expected encoding 'png16'"),
        # read loosely before: "false" made the session finalised, "32" skipped the frame-count check,
        # "BGR" replayed red and blue swapped, 2.0 passed as version 2
        ("finalized", "false", r"key 'finalized': expected bool, got str 'false'"),
        ("frame_count", "2", r"key 'frame_count': expected int, got str '2'"),
        ("color", {"encoding": "png", "channels": "BGR"}, r"key 'color.channels': expected 'RGB', got 'BGR'"),
        ("version", 1.0, r"unknown session format version 1.0"),
    ],
)
def test_bad_manifest_keys(tmp_path, key, value, expect):
    make_session(tmp_path / "s", 2)
    _set_manifest(tmp_path / "s", **{key: value})
    with pytest.raises(SessionError, match=expect):
        SessionReader(tmp_path / "s")


def test_missing_index(tmp_path):
    make_session(tmp_path / "s", 2)
    _index(tmp_path / "s").unlink()
    with pytest.raises(SessionError, match=r"frames.jsonl: missing"):
        SessionReader(tmp_path / "s")


def _check_skips(path, bad_k, expect, n=6):
    """Frame ``bad_k`` is skipped with ``expect`` named; the others replay; strict refuses."""
    r = SessionReader(path)
    assert len(r) == n - 1
    assert any(expect in p for p in r.problems), r.problems
    assert [f.seq for f in r] == [k for k in range(n) if k != bad_k]
    with pytest.raises(SessionError, match="invalid session"):
        SessionReader(path, strict=True)
    return r


def test_missing_frame_file(tmp_path):
    make_session(tmp_path / "s", 6)
    (tmp_path / "s" / "frames" / "000002.depth.png").unlink()
    r = _check_skips(tmp_path / "s", 2, "missing file")
    assert any("000002.depth.png" in p and "line 3" in p for p in r.problems)


def test_truncated_frame(tmp_path):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000003.color.png"
    p.write_bytes(p.read_bytes()[:1000])
    _check_skips(tmp_path / "s", 3, "truncated frame")


def test_file_larger_than_index_says(tmp_path):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000001.depth.png"
    p.write_bytes(p.read_bytes() + b"extra")
    _check_skips(tmp_path / "s", 1, "size mismatch")


def test_image_size_differs_from_manifest(tmp_path):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000004.color.png"
    ok, buf = cv2.imencode(".png", np.zeros((H // 2, W, 3), np.uint8))
    p.write_bytes(buf.tobytes())
    _rewrite_line(tmp_path / "s", 4, color_bytes=int(buf.size))
    r = SessionReader(tmp_path / "s", strict=True)  # the index is consistent; decoding finds it
    with pytest.raises(CorruptFrame, match=r"size mismatch: image is 64x24, the manifest says 64x48"):
        r.read(4)
    assert any("size mismatch" in p for p in r.check())


def test_raw_colour_of_wrong_length(tmp_path):
    make_session(tmp_path / "s", 6, color="raw")
    p = tmp_path / "s" / "frames" / "000002.color.rgb"
    p.write_bytes(p.read_bytes()[:-3])
    _rewrite_line(tmp_path / "s", 2, color_bytes=W * H * 3 - 3)
    _check_skips(tmp_path / "s", 2, "a raw 64x48 RGB frame has 9216")


def test_undecodable_png(tmp_path):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000005.depth.png"
    p.write_bytes(b"\0" * p.stat().st_size)  # same size: only decoding can tell
    r = SessionReader(tmp_path / "s", strict=True)
    with pytest.raises(CorruptFrame, match=r"000005.depth.png is not a decodable PNG"):
        r.read(5)


def test_torn_last_index_line(tmp_path):
    make_session(tmp_path / "s", 6)
    data = _index(tmp_path / "s").read_bytes()
    _index(tmp_path / "s").write_bytes(data[: len(data) - 40])  # cut inside the last line
    r = SessionReader(tmp_path / "s")
    assert len(r) == 5
    assert any("line 6 is torn" in p for p in r.problems), r.problems
    assert [f.seq for f in r] == [0, 1, 2, 3, 4]


def test_malformed_middle_line(tmp_path):
    make_session(tmp_path / "s", 6)
    lines = _lines(tmp_path / "s")
    lines[2] = lines[2][:30]
    _index(tmp_path / "s").write_text("\n".join(lines) + "\n")
    r = _check_skips(tmp_path / "s", 2, "malformed index line")
    assert any("line 3" in p for p in r.problems)


def test_an_index_line_with_a_5000_digit_int_is_one_skipped_frame(tmp_path):
    # json raises ValueError (not JSONDecodeError) for it: it ended the whole replay with a traceback
    make_session(tmp_path / "s", 6)
    lines = _lines(tmp_path / "s")
    lines[2] = lines[2].replace('"seq":2', '"seq":' + "9" * 5000)
    assert "9" * 5000 in lines[2]
    _index(tmp_path / "s").write_text("\n".join(lines) + "\n")
    r = _check_skips(tmp_path / "s", 2, "malformed index line (ValueError")
    assert any("line 3" in p for p in r.problems)


def test_a_frame_path_with_a_lone_surrogate_is_one_skipped_frame(tmp_path):
    # "\ud800" is valid JSON but no file name: resolving it raised UnicodeEncodeError, a traceback
    make_session(tmp_path / "s", 6)
    lines = _lines(tmp_path / "s")
    lines[3] = lines[3].replace('"frames/000003.color.png"', '"frames/\\ud800.png"')
    _index(tmp_path / "s").write_text("\n".join(lines) + "\n")
    _check_skips(tmp_path / "s", 3, "is not a valid file name")


def test_estimates_sidecar_json_that_python_refuses_is_skipped(tmp_path, caplog):
    make_session(tmp_path / "s", 3)
    (tmp_path / "s" / "estimates.jsonl").write_text(
        "[" * 100_000 + "\n" + '{"i": ' + "9" * 5000 + ', "estimate": {}}\n{"i": 1, "estimate": {"a": 1}}\n'
    )
    r = SessionReader(tmp_path / "s")
    assert r.estimates() == {1: {"a": 1}}
    assert "2 line(s) of estimates.jsonl skipped" in caplog.text


def test_missing_key_in_index_line(tmp_path):
    make_session(tmp_path / "s", 6)
    lines = _lines(tmp_path / "s")
    d = json.loads(lines[1])
    del d["t_device_ns"]
    lines[1] = json.dumps(d)
    _index(tmp_path / "s").write_text("\n".join(lines) + "\n")
    _check_skips(tmp_path / "s", 1, "missing key 't_device_ns'")


@pytest.mark.parametrize(
    "key, value, expect",
    [
        ("exposure", [1, 2], "key 'exposure'"),
        ("exposure", {"iso": "high"}, "key 'exposure'"),
        ("gravity", [0, 1], "key 'gravity': expected a list of 3 numbers"),
        ("imu", [{"t_ns": 1, "accel": [0, 0]}], r"imu\[0\].accel: expected a list of 3 numbers"),
        ("intrinsics", [1, 2], "key 'intrinsics'"),
        ("color_bytes", "big", "key 'color_bytes': expected int, got str"),
    ],
)
def test_bad_metadata_in_an_index_line(tmp_path, key, value, expect):
    import re

    make_session(tmp_path / "s", 6)
    _rewrite_line(tmp_path / "s", 4, **{key: value})
    r = SessionReader(tmp_path / "s")
    assert [f.seq for f in r] == [0, 1, 2, 3, 5]
    assert any(re.search(expect, p) and "line 5" in p for p in r.problems), r.problems


def test_timestamp_going_backwards(tmp_path):
    fs = make_session(tmp_path / "s", 6)
    _rewrite_line(tmp_path / "s", 3, t_device_ns=fs[1].t_device_ns)
    _check_skips(tmp_path / "s", 3, "does not increase")


def test_frame_count_disagrees_with_index(tmp_path):
    make_session(tmp_path / "s", 6)
    _set_manifest(tmp_path / "s", frame_count=9)
    r = SessionReader(tmp_path / "s")
    assert len(r) == 6 and any("frame_count is 9" in p for p in r.problems)


@pytest.mark.parametrize(
    "bad", ["../outside.png", "frames/../../outside.png", "/etc/hostname", "C:/x.png", "frames\\..\\..\\x.png"]
)
def test_frame_path_escaping_the_folder_is_refused(tmp_path, bad):
    make_session(tmp_path / "s", 6)
    outside = tmp_path / "outside.png"
    outside.write_bytes((tmp_path / "s" / "frames" / "000002.color.png").read_bytes())
    _rewrite_line(tmp_path / "s", 2, color=bad)
    r = _check_skips(tmp_path / "s", 2, "escapes the session folder")
    assert any(repr(bad) in p for p in r.problems)


def test_symlink_out_of_the_folder_is_refused(tmp_path):
    make_session(tmp_path / "s", 6)
    p = tmp_path / "s" / "frames" / "000001.color.png"
    target = tmp_path / "elsewhere.png"
    target.write_bytes(p.read_bytes())
    p.unlink()
    p.symlink_to(target)
    _check_skips(tmp_path / "s", 1, "resolves outside the session folder")


def test_an_estimates_sidecar_symlinked_out_of_the_folder_is_not_read(tmp_path, caplog):
    # "nothing in the folder can make the reader open a file outside it": the sidecar was followed
    make_session(tmp_path / "s", 3)
    outside = tmp_path / "elsewhere.jsonl"
    outside.write_text('{"i": 1, "estimate": {"from": "outside"}}\n')
    (tmp_path / "s" / "estimates.jsonl").symlink_to(outside)
    assert SessionReader(tmp_path / "s").estimates() == {}
    assert "estimates.jsonl not read" in caplog.text and "resolves outside the session folder" in caplog.text


def test_manifest_index_path_escaping_is_refused(tmp_path):
    make_session(tmp_path / "s", 2)
    _set_manifest(tmp_path / "s", index="../frames.jsonl")
    with pytest.raises(SessionError, match=r"key 'index': path '../frames.jsonl' escapes"):
        SessionReader(tmp_path / "s")


def test_safe_relpath_accepts_plain_relative_paths(tmp_path):
    assert safe_relpath(tmp_path, "frames/000001.color.png", "x") == tmp_path / "frames" / "000001.color.png"
    for bad in ("", None, 3):
        with pytest.raises(SessionError, match="expected a relative path"):
            safe_relpath(tmp_path, bad, "x")


def test_no_pickle_in_the_format():
    import illuminet.runtime.stream.session as S

    src = open(S.__file__).read()
    assert "pickle" not in src.replace("no pickle", "").replace("No pickle", "")
    assert "allow_pickle" not in src and "np.load(" not in src
