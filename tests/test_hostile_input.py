"""Mistaken and hostile input (issue 13, classes 1, 2 and 7): one clear line, never a traceback or a hang.

Class 1: every user mistake reaches ``illuminet.cli.main`` as an :class:`IllumiNetError` and is
printed as exactly one stderr line naming the key, URL or file, with exit status 2 (usage,
configuration) or 1 (run-time failure). Class 2: nothing a session or URL contains makes the
program wait for minutes or build huge tables. Class 7: output paths are checked before a run starts.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest

from illuminet.cli import main
from illuminet.runtime import errors
from illuminet.runtime.stream.session import SessionReader

from . import _sessions
from ._sessions import make_session
from .conftest import REPO, relight_argv

# (argv, exit status, text the one line must contain); paths under "{tmp}" are made per test
BAD_INPUTS = [
    (["run", "synthetic://unknown"], 2, "'unknown'"),
    (["run", "synthetic://indoor?frames=abc"], 2, "frames='abc'"),
    (["run", "synthetic://indoor?frames=0"], 2, "frames='0'"),
    (["run", "synthetic://indoor?colour=1"], 2, "unknown parameter 'colour'"),
    (["run", "oakd://?fps=abc"], 2, "oakd://?fps=abc"),
    (["run", "oakd://?fps=1000"], 2, "fps"),
    (["run", "v4l2:///dev/null"], 1, "v4l2:///dev/null"),
    (["run", "v4l2:///dev/null?stereo=maybe"], 2, "stereo='maybe'"),
    (["run", "webcam://0"], 2, "'webcam'"),
    (["run", "no-scheme-at-all"], 2, "no scheme"),
    # an unbalanced '[' made urlsplit raise "Invalid IPv6 URL" in the replay-folder check: a traceback
    (["run", "synthetic://["], 2, "is not a URL: Invalid IPv6 URL"),
    (["run", "replay://["], 2, "is not a URL: Invalid IPv6 URL"),
    (["--set", "output.port=70000", "run", "synthetic://indoor"], 2, "[output] port"),
    (["--set", "output.port=-1", "run", "synthetic://indoor"], 2, "[output] port"),
    (["--set", "plane_light.grid=0", "run", "synthetic://indoor"], 2, "[plane_light] grid"),
    (["--set", "render.object_scale=nan", "run", "synthetic://indoor"], 2, "[render] object_scale"),
    (["--set", "render.object_scale=inf", "run", "synthetic://indoor"], 2, "[render] object_scale"),
    (["--set", "render.object_scale=1e-282", "run", "synthetic://indoor"], 2, "[render] object_scale"),  # fuzz
    (["--set", "light.rate_hz=2.2e-309", "run", "synthetic://indoor"], 2, "[light] rate_hz"),  # fuzz: 1e9/rate = inf
    (["--set", "imu.rotation=[1,0,0,0,1,0,0,0,nan]", "run", "synthetic://indoor"], 2, "[imu] rotation"),
    (["--set", "render.msaa=64", "run", "synthetic://indoor"], 2, "[render] msaa"),
    (["--set", "planes.smoothing=1.5", "run", "synthetic://indoor"], 2, "[planes] smoothing"),
    (["--set", "model.bundle={tmp}/no-bundle", "run", "synthetic://indoor"], 2, "no-bundle"),
    (["--set", "model.bundle=builtin:nope", "run", "synthetic://indoor"], 2, "builtin:nope"),
    (["--set", "model.bundle=", "run", "synthetic://indoor"], 2, "[model] bundle is empty"),  # was "." + 2 lines
    (["--config", "{tmp}/bad.toml", "run", "synthetic://indoor"], 2, "bad.toml: [render] msaa"),
    (["--config", "{tmp}/missing.toml", "run", "synthetic://indoor"], 2, "missing.toml"),
    (["--config", "{tmp}/binary.toml", "run", "synthetic://indoor"], 2, "binary.toml: not a text file"),
    (["--config", "{tmp}", "run", "synthetic://indoor"], 2, "is a folder, not a config file"),
    (["eval", "--cases", "-1"], 2, "--cases -1: expected a count >= 0"),
    (["eval", "--camera-scenes", "-3"], 2, "--camera-scenes -3"),
    (["record", "synthetic://indoor?frames=1", "/proc/no-session-here"], 1, "cannot create the session folder"),
    (["record", "synthetic://indoor?frames=1", ""], 2, "OUT is empty"),  # recorded nothing, exit 0
    (["run", "synthetic://indoor", "--fps", "inf", "--video", "{tmp}/v.mp4"], 2, "[output] fps"),
    (["run", "synthetic://indoor", "--fps", "0", "--video", "{tmp}/v.mp4"], 2, "[output] fps"),
    # class 7: output paths, checked before the source opens
    (["run", "synthetic://indoor", "--stats-json", "{tmp}/missing/dir/x.json"], 2, "missing/dir/x.json"),
    (["run", "synthetic://indoor", "--video", "{tmp}/missing/v.mp4"], 2, "missing/v.mp4"),
    (["run", "synthetic://indoor", "--estimates", "{tmp}/missing/e.jsonl"], 2, "missing/e.jsonl"),
    (["run", "synthetic://indoor", "--stats-json", "{tmp}"], 2, "is a folder"),
    (["run", "synthetic://indoor", "--png-dir", "{tmp}/afile/pngs"], 2, "afile"),
    (["replay", "{tmp}/no-session"], 1, "no-session"),
    # two outputs on one path: the one closed last replaced the other (the estimates lost), exit status 0
    (["run", "synthetic://indoor", "--video", "{tmp}/x.mp4", "--estimates", "{tmp}/x.mp4"], 2, "also the path of"),
    (["run", "synthetic://indoor", "--estimates", "{tmp}/s.json", "--stats-json", "{tmp}/./s.json"], 2, "also the"),
    (["run", "synthetic://indoor", "--png-dir", "{tmp}/o", "--estimates", "{tmp}/o"], 2, "{tmp}/o is also the path"),
    # a NUL byte (TOML "\u0000", URL %00) reached os calls: "ValueError: embedded null byte" tracebacks
    (
        ["run", "synthetic://indoor", "--set", 'output.video="a\\u0000.mp4"'],
        2,
        "[output] video: 'a\\x00.mp4' contains a NUL",
    ),
    (
        ["run", "synthetic://indoor", "--set", 'output.png_dir="p\\u0000"'],
        2,
        "[output] png_dir: 'p\\x00' contains a NUL",
    ),
    (["run", "synthetic://indoor", "--set", 'output.allowed_hosts=["h\\u0000"]'], 2, "[output] allowed_hosts"),
    (["run", "replay://{tmp}/s%00x"], 2, "the session path contains a NUL byte (%00)"),
]

# the offline jobs (bundle, datagen, train, eval): every flag refused before any mesh, data or JAX work
_BUNDLE = ["bundle", "--object", "builtin:sphere", "--out", "{tmp}/b", "--quiet"]
_DATAGEN = ["datagen", "--object", "builtin:sphere", "--out", "{tmp}/dg.npz", "--samples", "2", "--quiet"]
_TRAIN = ["train", "--object", "builtin:sphere", "--preset", "tiny", "--out", "{tmp}/t", "--quiet"]
_TRAIN_CAT = ["train", "--preset", "tiny", "--hdr", "", "--out", "{tmp}/t", "--quiet", "--objects"]
_EVAL = ["eval", "--no-figure", "--cases", "1", "--camera-scenes", "0", "--out", "{tmp}/ev"]
BAD_INPUTS += [
    (_BUNDLE + ["--height", "inf"], 2, "--height inf: expected a finite number of metres from 0.001 to 1000"),
    (_BUNDLE + ["--height", "nan"], 2, "--height nan"),
    (_BUNDLE + ["--seed", "-1"], 2, "--seed -1: expected a seed from 0 to 2**63-1"),
    (_BUNDLE + ["--n-proxy", "0"], 2, "--n-proxy 0: expected a count >= 8"),
    (_BUNDLE + ["--transfer-rays", "100000000"], 2, "--transfer-rays 100000000: expected a count from 64 to 65536"),
    (_BUNDLE + ["--directions", "8"], 2, "--directions 8"),
    (_BUNDLE + ["--bounces", "0"], 2, "--bounces 0: expected a count from 1 to 100"),
    (_BUNDLE + ["--albedo", "1"], 2, "--albedo 1.0: expected a grey albedo in [0, 1)"),
    (_BUNDLE + ["--out", "{tmp}/afile/b"], 2, "--out {tmp}/afile/b: {tmp}/afile is a file, not a folder"),
    (_DATAGEN + ["--extent", "inf"], 2, "--extent inf: expected a finite number of metres from 0.01 to 100"),
    (_DATAGEN + ["--extent", "0"], 2, "--extent 0.0"),
    (_DATAGEN + ["--grid", "100000"], 2, "--grid 100000: expected a count from 8 to 512"),
    (_DATAGEN + ["--n-proxy", "0"], 2, "--n-proxy 0: expected a count >= 8"),
    (_DATAGEN + ["--seed", "-1"], 2, "--seed -1"),
    (_DATAGEN + ["--seed", str(2**64)], 2, f"--seed {2**64}"),
    (_DATAGEN + ["--hdr-share", "nan"], 2, "--hdr-share nan: expected a finite number from 0 to 1"),
    (_DATAGEN + ["--out", "{tmp}/afile/dg.npz"], 2, "{tmp}/afile is a file, not a folder"),
    (_DATAGEN + ["--hdr", "{tmp}/nothing"], 2, "--hdr {tmp}/nothing: no such folder; expected a folder of Radiance"),
    (_DATAGEN + ["--hdr", "{tmp}"], 2, "--hdr {tmp}: the folder holds no .hdr maps"),
    (_TRAIN + ["--batch", "0"], 2, "--batch 0: expected a count >= 1"),
    (_TRAIN + ["--n-proxy", "0"], 2, "--n-proxy 0: expected a count >= 8"),
    (_TRAIN + ["--seed", "-1"], 2, "--seed -1: expected a seed"),
    (_TRAIN + ["--n-train", "0"], 2, "--n-train 0: expected a count >= 1"),
    (_TRAIN + ["--n-val", "0"], 2, "--n-val 0: expected a count >= 1"),
    (_TRAIN + ["--epochs-gan", "-1"], 2, "--epochs-gan -1: expected a count >= 0"),
    (_TRAIN + ["--epochs-gae", "-1"], 2, "--epochs-gae -1"),
    (_TRAIN + ["--unroll", "-1"], 2, "--unroll -1"),
    (_TRAIN + ["--hdr", "{tmp}/afile"], 2, "--hdr {tmp}/afile: is a file, not a folder"),
    (_TRAIN + ["--hdr", "{tmp}/nothing"], 2, "--hdr {tmp}/nothing: no such folder"),
    # maps with no readable header: train set up, warned "synthetic lights only" and trained without them
    (_TRAIN + ["--hdr", "{tmp}/hdr3"], 2, "--hdr {tmp}/hdr3: none of its training maps (3 of every 4 .hdr files) has"),
    (_TRAIN + ["--out", "{tmp}/afile"], 2, "--out {tmp}/afile: is a file, expected a folder"),
    # a folder that holds something else (was filled with bundle.json, mesh.npz, *.onnx and work/, exit 0)
    (_TRAIN + ["--out", "{tmp}"], 2, "--out {tmp} holds afile, bad.toml, binary.toml and 2 more: expected a new"),
    (_TRAIN_CAT + ["builtin:sphere", "--out", "{tmp}/hdr3"], 2, "--out {tmp}/hdr3 holds a.hdr, b.hdr, c.hdr: expected"),
    # blank lists: '' trained builtin:vase into the --out root, ',,' was "0 objects: 0 trained", exit 0
    (_TRAIN_CAT + [""], 2, "--objects '': the list names no objects; expected a folder of mesh files"),
    (_TRAIN_CAT + [",,"], 2, "--objects ',,': the list names no objects"),
    (_TRAIN + ["--object", " "], 2, "--object ' ': expected a mesh file or builtin:NAME"),
    # absurd sample counts: ran until killed, memory growing
    (_TRAIN + ["--n-train", "100000000"], 2, "--n-train 100000000: the samples would take about 718 GB"),
    (_DATAGEN + ["--samples", "10000000000"], 2, "--samples 10000000000: the samples would take about 233 TB"),
    # no upper bound: ran for years (datagen and train refuse such counts with a size estimate)
    (_EVAL + ["--cases", "1000000000"], 2, "--cases 1000000000: the run would take about 11.4 years here"),
    (_EVAL + ["--flicker-scenes", "1000000000"], 2, "--flicker-scenes 1000000000: the run would take about"),
    (_EVAL + ["--camera-scenes", "100000"], 2, "--camera-scenes 100000: the run would take about 38.2 days"),
    (_EVAL + ["--camera-scenes", "8", "--camera-frames", "10000000"], 2, "--camera-frames 10000000: the run would"),
    # a bad --variant was checked only when the camera suites started: with --camera-scenes 0, exit 0
    (_EVAL + ["--variant", "x"], 2, "--variant 'x': expected NAME:section.key=value"),
    (_EVAL + ["--variant", "a:render.msaa=64"], 2, "--variant a: override: [render] msaa: expected int in 0..16"),
    (_EVAL + ["--variant", "ours:render.msaa=4"], 2, "--variant names must be unique and not one of ours"),
    (_EVAL + ["--out", "{tmp}/afile"], 2, "--out {tmp}/afile: is a file, expected a folder"),
    (_EVAL + ["--hdr", "{tmp}/nothing"], 2, "--hdr {tmp}/nothing: no such folder"),
    (_EVAL + ["--hdr", "{tmp}/afile"], 2, "--hdr {tmp}/afile: is a file, not a folder"),
    (_EVAL + ["--hdr", "{tmp}"], 2, "--hdr {tmp}: the folder holds no .hdr maps"),
    (_EVAL + ["--hdr", "{tmp}/hdr3"], 2, "holds 3 .hdr map(s), but eval uses only the held-out ones"),
    (_EVAL + ["--seed", "-1"], 2, "--seed -1"),
    (_EVAL + ["--camera-frames", "1"], 2, "--camera-frames 1: expected a count >= 2"),
    (_EVAL + ["--camera-scenes", "1", "--camera-suites", ","], 2, "--camera-suites ',': expected a comma-separated"),
    (_EVAL + ["--object-albedo", "nan"], 2, "--object-albedo: expected a number in [0, 1), got nan"),
    (_EVAL + ["--crosscheck-spp", "0"], 2, "--crosscheck-spp 0"),
    (_EVAL + ["--crosscheck-bounces", "-1"], 2, "--crosscheck-bounces -1: expected a count from 0 to 16"),
    # a folder that cannot be written: datagen's was a FileNotFoundError traceback after the samples were made,
    # train's an "[Errno 2]" without the flag after setting up
    (_DATAGEN + ["--out", "/proc/dg.npz"], 2, "--out /proc/dg.npz: cannot write files there (No such file"),
    (_TRAIN + ["--out", "/proc/t"], 2, "--out /proc/t: cannot write files there"),
    (_EVAL + ["--out", "/proc/ev"], 2, "--out /proc/ev: cannot write files there"),
    # an empty --out read as none: the job ran and wrote ./bundles/<object> or ./eval/<bundle>, exit 0
    (_TRAIN + ["--out", ""], 2, "--out '': the path is empty; expected a folder: name one, or leave --out out"),
    (_EVAL + ["--out", " "], 2, "--out ' ': the path is empty; expected a folder"),
    # a pipe where a file is read waited for a writer for ever
    (["--config", "{tmp}/hdrpipe/config.toml", "config"], 2, "config.toml: not a regular file (a pipe or device?)"),
    (_DATAGEN + ["--hdr", "{tmp}/hdrpipe"], 2, "--hdr {tmp}/hdrpipe: none of its training maps"),
    # a name over 255 bytes: pathlib's exists() raised "OSError: [Errno 36] File name too long", a traceback
    (["--config", "{tmp}/" + "c" * 300, "config"], 2, "c" * 300 + ": the path is too long for this system"),
    (["record", "synthetic://indoor?frames=1", "{tmp}/" + "s" * 300], 2, "the path is too long for this system"),
    (["run", "synthetic://indoor", "--png-dir", "{tmp}/" + "p" * 300], 2, "the path is too long for this system"),
    (_DATAGEN + ["--out", "{tmp}/" + "d" * 300 + ".npz"], 2, "the path is too long for this system"),
]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("argv,code,expect", BAD_INPUTS, ids=[" ".join(a) for a, _, _ in BAD_INPUTS])
def test_a_mistake_is_one_line_with_its_exit_status(tmp_path, capsys, argv, code, expect):
    (tmp_path / "bad.toml").write_text("[render]\nmsaa = 64\n")
    (tmp_path / "binary.toml").write_bytes(b"\x89PNG\r\n\x1a\n\xf1\xff")
    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "hdr3").mkdir()
    for name in "abc":  # three maps: none of them is held out for eval (every 4th is)
        (tmp_path / "hdr3" / f"{name}.hdr").write_bytes(b"#?RADIANCE\n")
    (tmp_path / "hdrpipe").mkdir()  # pipes: reading one waited for a writer for ever
    os.mkfifo(tmp_path / "hdrpipe" / "a.hdr")
    os.mkfifo(tmp_path / "hdrpipe" / "config.toml")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    t0 = time.monotonic()
    assert main(argv) == code
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("illuminet: ") and expect.replace("{tmp}", str(tmp_path)) in lines[0], lines[0]
    # refused up front: nothing was run (no synthetic scene was built, no statistics file)
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "missing").exists()
    # nor was an output of the offline jobs begun
    assert not any((tmp_path / p).exists() for p in ("b", "dg.npz", "t", "ev")), sorted(tmp_path.iterdir())


def test_record_leaves_no_cut_frame_file_when_a_write_fails(tmp_path):
    """An RLIMIT_FSIZE smaller than one frame left a cut frames/000000.color.rgb that no index line names."""
    import resource

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (20480, 20480))

    out = tmp_path / "rec"
    r = subprocess.run(
        [sys.executable, "-m", "illuminet", "record", "synthetic://indoor?frames=2", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=small_files,
    )
    assert r.returncode == 1 and "File too large" in r.stderr, r.stderr
    assert sorted(p.name for p in (out / "frames").iterdir()) == []


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device that is always full)")
def test_a_manifest_write_on_a_full_disk_leaves_no_tmp_file(tmp_path):
    """A full disk left manifest.json.tmp beside the session's manifest."""
    from illuminet.runtime.stream import session

    os.symlink("/dev/full", tmp_path / "manifest.json.tmp")  # every write to it: No space left on device
    with pytest.raises(OSError, match="No space left"):
        session._atomic_write_json(tmp_path / "manifest.json", {"frames": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_datagen_leaves_no_half_written_file_when_the_disk_fills(tmp_path, monkeypatch):
    import errno
    import os

    from illuminet.commands import datagen

    def full(*a):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(errors.JobError, match=r"--out .*dg.npz: cannot write the data file \(No space left"):
        datagen.write(tmp_path / "dg.npz", {}, {})
    assert list(tmp_path.iterdir()) == []  # its temporary file was left behind


def test_an_oversized_hdr_map_is_a_warning_not_a_traceback(tmp_path, capsys, caplog):
    # its header's 100000 x 100000 pixels made OpenCV raise cv2.error (CV_IO_MAX_IMAGE_PIXELS): exit 1
    (tmp_path / "hdr").mkdir()
    big = tmp_path / "hdr" / "big.hdr"
    big.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 100000\n" + b"abcd" * 100)
    argv = _DATAGEN + ["--n-proxy", "16", "--hdr", "{tmp}/hdr", "--hdr-share", "1"]
    assert main([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "cv2.error" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("illuminet: ")]
    assert len(lines) == 1 and f"--hdr {tmp_path}/hdr: none of its training maps" in lines[0], err
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "big.hdr" in r.getMessage()]
    assert len(warned) == 1 and "header claims 100000 x 100000 pixels" in warned[0], caplog.text
    assert not (tmp_path / "dg.npz").exists()


def test_a_gl_backend_that_cannot_start_is_one_line():
    # in a fresh process: the test process's GL tests share one context, which would hide the failure
    env = _sessions.env()
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    p = subprocess.run(
        [sys.executable, "-m", "illuminet", "--set", "render.gl_backend=default", "run"]
        + ["synthetic://indoor?size=64x48", "--max-frames", "1"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("illuminet:")]
    assert p.returncode == 1 and len(lines) == 1 and "OpenGL" in lines[0], p.stderr
    assert "Traceback" not in p.stderr


def test_debug_log_level_shows_the_traceback(capsys):
    assert main(["--log-level", "debug", "run", "synthetic://unknown"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("illuminet: ")


def test_every_error_class_derives_from_the_one_base():
    from illuminet.hw import SourceError
    from illuminet.hw.synthetic.scene import SyntheticError
    from illuminet.hw.v4l2 import V4l2Error
    from illuminet.runtime.assets.bundle import BundleError
    from illuminet.runtime.assets.objects import ObjectLoadError
    from illuminet.runtime.config import ConfigError
    from illuminet.runtime.render.gl import GLError
    from illuminet.runtime.stage import PipelineError
    from illuminet.runtime.stream.session import CorruptFrame, SessionError
    from illuminet.runtime.stream.sinks import SinkError

    classes = [SourceError, SyntheticError, V4l2Error, BundleError, ObjectLoadError, ConfigError, GLError]
    classes += [PipelineError, SessionError, CorruptFrame, SinkError, errors.OutputPathError]
    for cls in classes:
        assert issubclass(cls, errors.IllumiNetError), cls
    # the built-in bases they had before stay, so older `except ValueError` code keeps working
    assert issubclass(ConfigError, ValueError) and issubclass(SourceError, RuntimeError)
    assert issubclass(SyntheticError, ValueError) and issubclass(GLError, RuntimeError)
    assert ConfigError("x").exit_code == 2 and SinkError("x").exit_code == 1
    assert SourceError("x", exit_code=2).exit_code == 2


# ---------------------------------------------------------------------------------- class 2: hangs


def _rewrite_index(session, change):
    index = session / "frames.jsonl"
    lines = [json.loads(ln) for ln in index.read_text().splitlines()]
    for k, d in enumerate(lines):
        change(k, d)
    index.write_text("".join(json.dumps(d) + "\n" for d in lines))


def test_replay_with_recorded_timing_does_not_sleep_through_a_timestamp_jump(tmp_path, capsys):
    from illuminet.hw.replay import ReplaySource

    make_session(tmp_path / "s", 6)
    century = 100 * 365 * 86400 * 10**9

    def jump(k, d):
        if k >= 3:
            d["t_device_ns"] += century

    _rewrite_index(tmp_path / "s", jump)
    t0 = time.monotonic()
    with ReplaySource(tmp_path / "s", timing="recorded") as src:
        got = []
        while (f := src.read()) is not None:
            got.append(f)
    assert len(got) == 6
    assert time.monotonic() - t0 < 3.0  # 6 frames at 30 fps, the jump counted as one period
    # --check reports the jump (and so exits 1) instead of saying OK
    assert main(["replay", str(tmp_path / "s"), "--check"]) == 1
    out = capsys.readouterr().out
    assert "timestamp jumps" in out and "line 4" in out, out


def test_a_timestamp_of_2_to_the_64_is_a_problem_not_a_crash(tmp_path, capsys):
    make_session(tmp_path / "s", 4)

    def huge(k, d):
        if k == 2:
            d["t_device_ns"] = 2**64

    _rewrite_index(tmp_path / "s", huge)
    r = SessionReader(tmp_path / "s")
    assert len(r) == 3 and any("2**63-1" in p for p in r.problems), r.problems
    assert main(["replay", str(tmp_path / "s"), "--check"]) == 1
    assert "outside 0..2**63-1" in capsys.readouterr().out
    t0 = time.monotonic()
    assert main(["replay", str(tmp_path / "s"), "--timing", "recorded"]) == 0
    assert time.monotonic() - t0 < 60


def test_synthetic_frames_n_is_lazy(tmp_path):
    from illuminet.hw import open_source

    tracemalloc.start()
    t0 = time.monotonic()
    try:
        src = open_source("synthetic://indoor?seed=0&size=64x48&frames=10000000&path=orbit")
        elapsed = time.monotonic() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    poses = src.scene.poses
    assert len(poses) == 10_000_000
    assert elapsed < 20 and peak < 300e6  # the eager list was 10M 4x4 arrays: ~2 GB and minutes
    # on demand, the same path as a short one at the same phase: frame i of N is at phase i/N
    short = open_source("synthetic://indoor?seed=0&size=64x48&frames=10&path=orbit").scene.poses
    import numpy as np

    np.testing.assert_allclose(poses[5_000_000], short[5])
    assert len(poses[::2_500_000]) == 4
    with pytest.raises(IndexError):
        poses[10_000_000]


# ---------------------------------------------------------------- class 3: one bad frame, not a crash


def _png_header(w: int, h: int) -> bytes:
    """The first 33 bytes of an RGB PNG claiming ``w x h`` (signature and IHDR chunk), no pixel data."""
    import struct
    import zlib

    chunk = b"IHDR" + struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))


def _damage_frame_1(session, how):
    """Make frame 1's colour file hostile: a 65535x65535 header, a symlink loop, or a NUL in its path."""
    lines = [json.loads(ln) for ln in (session / "frames.jsonl").read_text().splitlines()]
    d = lines[1]
    p = session / d["color"]
    if how == "huge":
        data = _png_header(65535, 65535) + b"\0" * 64
        p.write_bytes(data)
        d["color_bytes"] = len(data)
    elif how == "loop":
        p.unlink()
        p.symlink_to(p.name)
    else:
        d["color"] += "\x00.png"
    (session / "frames.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))


@pytest.mark.parametrize("how", ["huge", "loop", "nul"])
def test_a_hostile_frame_is_skipped_and_counted(tmp_path, capsys, how):
    from illuminet.hw.replay import ReplaySource

    s = tmp_path / "s"
    make_session(s, 4)
    _damage_frame_1(s, how)
    # --check reports it, one problem line, no traceback
    assert main(["replay", str(s), "--check"]) == 1
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    assert "1 problem(s)" in out and "line 2" in out, out
    # the replay (decoder threads included) skips it and plays the other three
    with ReplaySource(s, timing="asap") as src:
        got = []
        while (f := src.read()) is not None:
            got.append(f)
        assert len(got) == 3
        corrupt = src.stats().get("corrupt", 0) + len(src.session.problems)
    assert corrupt == 1


def test_a_huge_header_is_refused_before_decoding(tmp_path):
    # swapped in after the index was validated: the decoder thread meets it; refused from its header
    # (a decoder would allocate 12 GiB for 65535x65535 RGB) and counted as one corrupt frame
    from illuminet.hw.replay import ReplaySource
    from illuminet.runtime.stream.session import CorruptFrame

    s = tmp_path / "s"
    make_session(s, 4)
    r = SessionReader(s)
    e = r.entries[2]
    data = _png_header(20000, 20000)
    e.color.write_bytes(data + b"\0" * (e.color_bytes - len(data)))
    with pytest.raises(
        CorruptFrame, match="image is 20000x20000, the manifest says 64x48 .read from its header; not decoded"
    ):
        r.read(2)
    tracemalloc.start()
    with ReplaySource(s, timing="asap") as src:
        n = sum(1 for _ in iter(src.read, None))
        assert src.stats()["corrupt"] == 1
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert n == 3 and peak < 200e6


def test_a_manifest_symlinked_out_of_the_session_is_refused(tmp_path, capsys):
    s = tmp_path / "s"
    make_session(s, 2)
    outside = tmp_path / "elsewhere.json"
    (s / "manifest.json").rename(outside)
    (s / "manifest.json").symlink_to(outside)
    with pytest.raises(errors.SessionError, match="outside the session folder"):
        SessionReader(s)
    assert main(["replay", str(s), "--check"]) == 1
    err = capsys.readouterr().err
    assert "outside the session folder" in err and "Traceback" not in err


# ------------------------------------------------------------ class 4: plausible-looking garbage


@pytest.mark.parametrize(
    "key,value",
    # width 0 divided by zero in every stage, -64 mirrored fx, 480 for 48-pixel-high pictures stretched fy
    [
        ("fx", float("nan")),
        ("fy", 0.0),
        ("fx", 1e300),
        ("cx", float("inf")),
        ("width", 0),
        ("width", -64),
        ("height", 480),
    ],
)
def test_implausible_session_intrinsics_are_refused(tmp_path, capsys, key, value):
    s = tmp_path / "s"
    make_session(s, 3)
    m = json.loads((s / "manifest.json").read_text())
    m["intrinsics"][key] = value
    (s / "manifest.json").write_text(json.dumps(m))  # json writes NaN / Infinity, as a hand edit could
    with pytest.raises(errors.SessionError, match=f"'intrinsics.{key}'"):
        SessionReader(s)
    assert main(["replay", str(s), "--check"]) == 1
    err = capsys.readouterr().err
    assert f"intrinsics.{key}" in err and "Traceback" not in err
    assert main(["replay", str(s)]) == 1  # not "every frame failed" with exit status 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("illuminet")]
    assert len(lines) == 1 and f"intrinsics.{key}" in lines[0], lines


def test_session_messages_say_what_is_there(tmp_path):
    """Three messages that misled: a folder in place of manifest.json was "missing"; a folder named like a
    frame image was a "truncated frame" of 4096 bytes; width 10^12 in both the manifest and its
    intrinsics read "1000000000000x800 does not describe the 1000000000000x800 pictures"."""
    s = tmp_path / "s"
    make_session(s, 3)
    (s / "manifest.json").rename(tmp_path / "m.json")
    (s / "manifest.json").mkdir()
    with pytest.raises(errors.SessionError, match="manifest.json: is a folder; expected the session's manifest"):
        SessionReader(s)
    (s / "manifest.json").rmdir()
    (tmp_path / "m.json").rename(s / "manifest.json")
    frame = next(p for p in sorted((s / "frames").iterdir()) if p.name.startswith("000001"))
    frame.unlink()
    frame.mkdir()
    reader = SessionReader(s)  # the other frames still read; the folder is named as one
    assert any(f"{frame} is a folder; expected the frame's image file" in p for p in reader.problems), reader.problems
    m = json.loads((s / "manifest.json").read_text())
    m["width"] = m["intrinsics"]["width"] = 10**12
    (s / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(errors.SessionError, match="1000000000000x48 is not a camera's image size"):
        SessionReader(s)


@pytest.mark.parametrize(
    "key,value,expect",
    [
        ("gravity", [float("nan"), 1.0, 0.0], "'gravity'"),
        ("gravity", [0.0, 0.0, 0.0], "'gravity'"),
        ("exposure", {"exposure_us": float("inf")}, "'exposure.exposure_us'"),
        ("intrinsics", {"fx": 0, "fy": 50, "cx": 32, "cy": 24, "width": 64, "height": 48}, "'intrinsics.fx'"),
    ],
)
def test_implausible_frame_metadata_is_a_reported_problem(tmp_path, capsys, key, value, expect):
    s = tmp_path / "s"
    make_session(s, 4)

    def poison(k, d):
        if k == 1:
            d[key] = value

    _rewrite_index(s, poison)
    r = SessionReader(s)
    assert len(r) == 3 and any(expect in p for p in r.problems), r.problems
    with pytest.raises(errors.SessionError, match=expect):
        SessionReader(s, strict=True)
    assert main(["replay", str(s), "--check"]) == 1
    assert expect in capsys.readouterr().out


def test_a_bundle_with_nan_mesh_arrays_is_refused_naming_the_array(tmp_path, capsys):
    import shutil

    import numpy as np

    from illuminet.models.export import finalize_bundle
    from illuminet.runtime.assets.bundle import FILES, load_bundle

    d = tmp_path / "vase"
    shutil.copytree(load_bundle("builtin:vase").path, d, ignore=shutil.ignore_patterns("work"))
    with np.load(d / FILES["mesh"]) as z:
        arr = {k: z[k] for k in z.files}
    arr["vertices"] = np.full_like(arr["vertices"], np.nan)
    np.savez_compressed(d / FILES["mesh"], **arr)
    finalize_bundle(d, json.loads((d / "bundle.json").read_text()))  # checksums agree: only the values are bad
    with pytest.raises(errors.BundleError, match="array 'vertices' has .* non-finite"):
        load_bundle(d)
    assert main(["--set", f"model.bundle={d}", "run", "synthetic://indoor?frames=1"]) == 2
    err = capsys.readouterr().err
    assert "'vertices'" in err and "Traceback" not in err


# ------------------------------------------------------ class 5: malformed bundles and relight inputs

BAD_BUNDLE_JSON = [
    (lambda m: [m], "expected a JSON object, got a list"),
    (lambda m: {k: v for k, v in m.items() if k != "vertices"}, "missing key 'vertices'"),
    (lambda m: {**m, "plane": {**m["plane"], "pool": 0}}, "key 'plane.pool'"),
    (lambda m: {**m, "files": {**m["files"], "mesh.npz": "abc"}}, "key 'files.mesh.npz'"),
    (lambda m: {**m, "vertices": {"render": "many", "proxy": 400}}, "key 'vertices.render'"),
]


@pytest.mark.parametrize("edit,expect", BAD_BUNDLE_JSON, ids=[e for _, e in BAD_BUNDLE_JSON])
def test_a_malformed_bundle_json_is_one_line_naming_the_key(tmp_path, capsys, edit, expect):
    import shutil

    from illuminet.runtime.assets.bundle import load_bundle

    d = tmp_path / "b"
    shutil.copytree(load_bundle("builtin:vase").path, d, ignore=shutil.ignore_patterns("work"))
    meta = json.loads((d / "bundle.json").read_text())
    (d / "bundle.json").write_text(json.dumps(edit(meta)))
    with pytest.raises(errors.BundleError, match=expect.replace(".", r"\.")):
        load_bundle(d)
    assert main(["--set", f"model.bundle={d}", "run", "synthetic://indoor?frames=1"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and expect in lines[0], lines


@pytest.mark.parametrize("text, expect", [('{"format": ' + "9" * 5000 + "}", "4300 digits")], ids=["huge-int"])
def test_a_bundle_json_python_cannot_parse_is_one_line(tmp_path, capsys, text, expect):
    # json raised a bare ValueError for an int of over 4300 digits, past the JSONDecodeError handler
    d = tmp_path / "b"
    d.mkdir()
    (d / "bundle.json").write_text(text)
    assert main(["--set", f"model.bundle={d}", "run", "synthetic://indoor?frames=1"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "bundle.json: not valid JSON" in lines[0] and expect in lines[0], lines


def _relight_inputs(tmp_path):
    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "c.png"), np.full((48, 64, 3), 128, np.uint8))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((48, 64), 2000, np.uint16))
    np.savez(tmp_path / "npz.npy", depth=np.ones((48, 64), np.float32))  # writes npz.npy.npz
    (tmp_path / "npz.npy.npz").rename(tmp_path / "npz.npy")
    (tmp_path / "huge.png").write_bytes(_png_header(20000, 20000) + b"\0" * 4096)
    (tmp_path / "adir").mkdir()
    (tmp_path / "K_nan.json").write_text('{"fx": NaN, "fy": 60, "cx": 32, "cy": 24}')
    (tmp_path / "K_list.json").write_text("[60, 60, 32, 24]")
    (tmp_path / "K_missing.json").write_text('{"fx": 60, "fy": 60, "cx": 32}')
    (tmp_path / "K_zero.json").write_text('{"fx": 60, "fy": 60, "cx": 32, "cy": 24, "width": 0, "height": 48}')
    np.save(tmp_path / "empty.npy", np.ones((0, 0), np.float32))
    np.save(tmp_path / "mm.npy", np.full((48, 64), 2000.0))  # millimetres where .npy means metres
    np.save(tmp_path / "nan.npy", np.full((48, 64), np.nan, np.float32))
    np.save(tmp_path / "neg.npy", np.full((48, 64), -2.0, np.float32))
    np.save(tmp_path / "inf.npy", np.full((48, 64), np.inf, np.float32))
    k = '"fx": 60, "fy": 60, "cx": 32, "cy": 24'
    (tmp_path / "K_aspect.json").write_text(f'{{{k}, "width": 640, "height": 48}}')
    (tmp_path / "K_bool.json").write_text('{"fx": true, "fy": 60, "cx": 32, "cy": 24}')
    (tmp_path / "K_huge.json").write_text(f'{{{k}, "width": 1e30, "height": 1e30}}')
    (tmp_path / "K_half.json").write_text(f'{{{k}, "width": 1280}}')
    (tmp_path / "K_inf.json").write_text(f'{{{k}, "width": 1e400, "height": 1e400}}')
    noise = np.random.default_rng(0).integers(0, 256, (48, 64, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "c.jpg"), noise)
    jpg = (tmp_path / "c.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(jpg[: len(jpg) // 2])  # libjpeg decoded it half grey, exit 0
    np.savez(tmp_path / "d.npz", depth=np.ones((48, 64), np.float32))
    np.save(tmp_path / "mm1.npy", np.full((48, 64), 0.001, np.float32))  # millimetres divided twice
    cv2.imwrite(str(tmp_path / "d65535.png"), np.full((48, 64), 65535, np.uint16))
    (tmp_path / "K_deep.json").write_text('{"fx": ' + "[" * 100000 + "]" * 100000 + "}")
    (tmp_path / "empty.png").write_bytes(b"")
    cv2.imwrite(str(tmp_path / "lin.hdr"), np.full((48, 64, 3), 0.2, np.float32))  # linear: read as 8-bit sRGB
    np.save(tmp_path / "d3.npy", np.ones((48, 64, 2)))
    np.save(tmp_path / "d1.npy", np.ones(3072, np.float32))
    np.save(tmp_path / "dc.npy", np.ones((48, 64), np.complex64))
    with open(tmp_path / "big.npy", "wb") as f:  # a complete 8000x8000 float64 array: 512 MB read, then copied
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (8000, 8000)})
        f.truncate(f.tell() + 8000 * 8000 * 8)  # sparse: no disk space used


BAD_RELIGHT = [
    ({"--depth": "{tmp}/adir"}, "--depth {tmp}/adir: is a folder"),
    ({"--depth": "{tmp}/npz.npy"}, "an .npz archive"),
    ({"--out": "{tmp}/missing/r.npz"}, "folder {tmp}/missing does not exist"),
    ({"--color": "{tmp}/huge.png"}, "header says 20000x20000"),
    ({"--depth": "{tmp}/huge.png"}, "header says 20000x20000"),
    ({"--color": "{tmp}/nothing.png"}, "no such file"),
    ({"--intrinsics": "60,0,32,24"}, "expected finite fx, fy > 0"),
    ({"--intrinsics": "{tmp}/K_nan.json"}, "got fx=nan"),
    ({"--intrinsics": "{tmp}/K_list.json"}, "expected a JSON object with fx, fy, cx, cy in pixels, got list"),
    ({"--intrinsics": "{tmp}/K_missing.json"}, "got no cy"),
    ({"--intrinsics": "{tmp}/K_zero.json"}, "width and height must be > 0"),
    ({"--intrinsics": "{tmp}/huge.png"}, "not JSON"),
    ({"--preview": "{tmp}/p.xyz"}, "--preview {tmp}/p.xyz: .xyz is not an image format"),
    ({"--preview": "{tmp}/p"}, "--preview {tmp}/p: no extension"),
    ({"--depth": "{tmp}/empty.npy"}, "--depth {tmp}/empty.npy: empty (shape (0, 0))"),
    ({"--intrinsics": "{tmp}/K_aspect.json"}, "made for a 640x48 image but the colour image is 64x48"),
    ({"--intrinsics": "{tmp}/K_bool.json"}, "--intrinsics {tmp}/K_bool.json: fx is true; expected a number"),
    ({"--intrinsics": "{tmp}/K_huge.json"}, "1e+30x1e+30 is over 100000 pixels a side"),
    ({"--intrinsics": "{tmp}/K_half.json"}, "has width but not height; give both"),
    # 1e400 is inf to JSON: "width and height must be > 0 pixels, got infxinf"
    ({"--intrinsics": "{tmp}/K_inf.json"}, "width and height must be finite, got infxinf; expected the image size"),
    ({"--exposure": "0,0"}, "--exposure 0,0: the exposure time must be a finite number"),
    ({"--exposure": "nan,100"}, "--exposure nan,100: the exposure time must be a finite number"),
    ({"--exposure": "-5,100"}, "--exposure -5,100: the exposure time must be"),
    ({"--exposure": "8000,0"}, "--exposure 8000,0: the ISO must be"),
    ({"--exposure": "1e308,1e308"}, "--exposure 1e308,1e308: the exposure time must be"),
    ({"--exposure": ""}, "--exposure: expected 2 comma-separated numbers"),
    ({"--depth": "{tmp}/mm.npy"}, "--depth {tmp}/mm.npy: median depth 2000 m looks like millimetres"),
    ({"--depth": "{tmp}/nan.npy"}, "--depth {tmp}/nan.npy: no valid depth: none of its 3072 values"),
    ({"--depth": "{tmp}/neg.npy"}, "(3072 negative)"),
    ({"--depth": "{tmp}/inf.npy"}, "(3072 infinite)"),
    ({"--intrinsics": "1e30,1e30,32,24"}, "--intrinsics 1e30,1e30,32,24: fx=1e+30 pixels for an image 64 px wide"),
    ({"--intrinsics": "1e-9,1e-9,32,24"}, "--intrinsics 1e-9,1e-9,32,24: fx=1e-09 pixels"),
    # a missing intrinsics file was "expected 4 comma-separated numbers, got 'nope.json'"
    ({"--intrinsics": "{tmp}/nope.json"}, "--intrinsics {tmp}/nope.json: no such file; expected a JSON file"),
    ({"--color": "{tmp}/cut.jpg"}, "--color {tmp}/cut.jpg: the JPEG is cut short"),
    ({"--color": "/dev/null"}, "--color /dev/null: not a regular file"),  # was "no such file"
    ({"--intrinsics": "/dev/null"}, "--intrinsics /dev/null: not a regular file"),  # "expected 4 ... numbers"
    ({"--depth": "{tmp}/d.npz"}, "--depth {tmp}/d.npz: an .npz archive; expected one float array"),
    ({"--depth": "{tmp}/empty.png"}, "--depth {tmp}/empty.png: cannot read an image from it (empty, cut short"),
    # what the planes stage refused with a warning, then "no real plane observed under the anchor pixel"
    ({"--depth": "{tmp}/mm1.npy"}, "--depth {tmp}/mm1.npy: depth median is 0.0010 m: too small for a room"),
    ({"--depth": "{tmp}/d65535.png"}, "--depth {tmp}/d65535.png: depth median is 65.535 m"),
    ({"--intrinsics": "60,60,-500,24"}, "principal point cx=-500, cy=24 is outside the 64x48 image"),
    ({"--intrinsics": "{tmp}/K_deep.json"}, "--intrinsics {tmp}/K_deep.json: JSON nested too deeply"),  # traceback
    ({"--anchor": "64,10"}, "--anchor 64,10: (64, 10) is outside the 64x48 image"),  # was "anchor pixel"
    ({"--preview": "{tmp}/c.png"}, "--preview {tmp}/c.png: is the --color input file"),  # replaced the photo
    ({"--out": "{tmp}/d.npz", "--depth": "{tmp}/d.npz"}, "--out {tmp}/d.npz: is the --depth input file"),
    ({"--color": "{tmp}/lin.hdr"}, "--color {tmp}/lin.hdr: a Radiance HDR image (linear floating-point)"),
    ({"--depth": "{tmp}/big.npy"}, "--depth {tmp}/big.npy: the array header says 8000x8000 pixels, over the limit"),
    # refused from the header: a (200000000,) or (8000, 8000, 2) array was read whole first (1.6 GB, 15 s)
    ({"--depth": "{tmp}/d3.npy"}, "--depth {tmp}/d3.npy: the array header says float64 with shape (48, 64, 2)"),
    ({"--depth": "{tmp}/d1.npy"}, "--depth {tmp}/d1.npy: the array header says float32 with shape (3072,); expected"),
    ({"--depth": "{tmp}/dc.npy"}, "--depth {tmp}/dc.npy: the array header says complex64 with shape (48, 64)"),
    # an empty path is ".", the current folder: "--color : is a folder"; an empty --preview was skipped, exit 0
    ({"--color": ""}, "--color '': an empty file name"),
    ({"--depth": " "}, "--depth ' ': an empty file name"),
    ({"--out": ""}, "--out '': an empty file name"),
    ({"--preview": ""}, "--preview '': an empty file name"),
    ({"--intrinsics": ""}, "--intrinsics '': empty; expected four numbers FX,FY,CX,CY or a JSON file"),
]


@pytest.mark.parametrize("change,expect", BAD_RELIGHT, ids=[e for _, e in BAD_RELIGHT])
def test_bad_relight_inputs_are_one_line_each(tmp_path, capsys, change, expect):
    _relight_inputs(tmp_path)
    argv = relight_argv(tmp_path, change)
    t0 = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - t0 < 10  # refused from the header, not after decoding 400 Mpx
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and expect.replace("{tmp}", str(tmp_path)) in lines[0], lines
    assert not list(tmp_path.glob("r.npz*")) and not (tmp_path / "missing").exists()  # nothing written


def _headers(w, h):
    """A header of each format OpenCV decodes besides PNG and JPEG claiming ``w`` x ``h``, without pixels."""
    import struct

    bmp = b"BM" + struct.pack("<IHHI", 54, 0, 0, 54) + struct.pack("<IiiHHIIiiII", 40, w, h, 1, 24, 0, 0, 0, 0, 0, 0)
    ifd = [(256, 4, w), (257, 4, h), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 8), (277, 3, 1), (279, 4, 16)]
    tif = b"II*\x00" + struct.pack("<I", 24) + b"\0" * 16 + struct.pack("<H", len(ifd))
    for t, k, v in ifd:
        tif += struct.pack("<HHII", t, k, 1, v) if k == 4 else struct.pack("<HHIHH", t, k, 1, v, 0)
    webp = b"RIFF" + struct.pack("<I", 22) + b"WEBPVP8X" + struct.pack("<I", 10) + b"\0" * 4
    webp += (w - 1).to_bytes(3, "little") + (h - 1).to_bytes(3, "little")
    return {
        "bmp": bmp,
        "tif": tif + b"\0\0\0\0",
        "webp": webp,
        "gif": b"GIF89a" + struct.pack("<HH", w, h) + b"\0\0\0",
        "ppm": b"P6\n# a comment\n%d %d\n255\n" % (w, h),
        "hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (h, w),
        "ras": b"\x59\xa6\x6a\x95" + struct.pack(">IIIIIII", w, h, 24, 0, 1, 0, 0),
    }


@pytest.mark.parametrize("ext", list(_headers(1, 1)))
@pytest.mark.parametrize("flag", ["--color", "--depth"])
def test_an_image_of_another_format_claiming_gigapixels_is_refused_from_its_header(tmp_path, capsys, ext, flag):
    """Only PNG and JPEG headers were read: a 3 MB run-length BMP or a 1 MB deflated TIFF of 20000x20000 took
    2.4 GB and 16-28 s in OpenCV before relight refused it (as not aligned with the depth)."""
    _relight_inputs(tmp_path)
    (tmp_path / f"big.{ext}").write_bytes(_headers(20000, 20000)[ext] + b"\0" * 4096)
    assert main(relight_argv(tmp_path, {flag: "{tmp}/big." + ext})) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"{flag} {tmp_path}/big.{ext}: the image header says 20000x20000 pixels" in lines[0]


def test_the_header_sizes_of_images_opencv_writes_are_read_right(tmp_path):
    import cv2
    import numpy as np

    from illuminet.runtime.imageheader import image_size_of_file

    img = np.random.default_rng(0).integers(0, 256, (37, 53, 3), np.uint8)
    for ext in ("bmp", "tif", "webp", "ppm", "pgm", "pfm", "hdr", "ras", "jp2", "png", "jpg"):
        p = tmp_path / f"x.{ext}"
        a = img.astype(np.float32) / 255 if ext in ("hdr", "pfm") else img[..., 0] if ext == "pgm" else img
        assert cv2.imwrite(str(p), a), ext
        assert image_size_of_file(p) == (53, 37), ext
    assert cv2.imwrite(str(tmp_path / "d.tif"), np.zeros((37, 53), np.uint16))  # a 16-bit depth TIFF
    assert image_size_of_file(tmp_path / "d.tif") == (53, 37)
    for ext, data in _headers(640, 360).items():  # and the headers written by hand above
        (tmp_path / f"h.{ext}").write_bytes(data)
        assert image_size_of_file(tmp_path / f"h.{ext}") == (640, 360), ext


def test_a_damaged_image_is_one_line_without_opencv_log_lines(tmp_path, capfd):
    """OpenCV logs its own decoder errors on the process's stderr: a BMP cut short printed two to five
    ``[ERROR:0@0.1] global loadsave.cpp ...`` lines around relight's one."""
    import struct

    _relight_inputs(tmp_path)
    w = h = 3000
    head = struct.pack("<IHHI", 54 + w * h * 3, 0, 0, 54) + struct.pack(
        "<IiiHHIIiiII", 40, w, h, 1, 24, 0, 0, 0, 0, 0, 0
    )
    (tmp_path / "cut.bmp").write_bytes(b"BM" + head + b"\0" * 4096)
    capfd.readouterr()
    assert main(relight_argv(tmp_path, {"--color": "{tmp}/cut.bmp"})) == 2
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"--color {tmp_path}/cut.bmp: cannot read an image from it" in lines[0], err


# --------------------------------------------------------------------- class 6: server hardening


def _http(port: int, raw: bytes, timeout: float = 5.0) -> tuple[int, bytes]:
    """Send ``raw`` on a fresh connection; (status, whole answer until the server closes or times out)."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(raw)
        data = b""
        try:
            while chunk := s.recv(65536):
                data += chunk
                if b"\r\n\r\n" in data and b"Content-Length" in data.split(b"\r\n\r\n")[0]:
                    head, body = data.split(b"\r\n\r\n", 1)
                    n = int(head.split(b"Content-Length: ")[1].split(b"\r\n")[0])
                    if len(body) >= n:
                        break
        except TimeoutError:
            pass
    status = int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/") else 0
    return status, data


def _get(port: int, host: str | None, path: str = "/stats.json", version: str = "HTTP/1.1", extra: str = "") -> int:
    head = f"GET {path} {version}\r\n" + (f"Host: {host}\r\n" if host is not None else "") + extra
    return _http(port, (head + "Connection: close\r\n\r\n").encode())[0]


def test_host_header_must_name_this_server(tmp_path):
    """DNS rebinding: a page at evil.example resolving to 127.0.0.1 must not read /stats.json."""
    import socket

    from illuminet.runtime.stream.mjpeg import MjpegSink

    me = socket.gethostname()
    with MjpegSink(port=0, allowed_hosts=["ar-box.example"]) as sink:
        p = sink.port
        for host in [
            f"127.0.0.1:{p}",
            "localhost",
            f"LOCALHOST:{p}",
            f"[::1]:{p}",
            "192.168.1.20:8080",
            me,
            f"{me.split('.')[0]}.local:{p}",
            "ar-box.example",
            "ar-box.example.",
            "viewer.localhost",
        ]:
            assert _get(p, host) == 200, host
        for host in [
            "evil.example",
            f"evil.example:{p}",
            "localhost.evil.example",
            "127.0.0.1.evil.example",
            "",
            "a:b:c",
            "[::1",
            "user@127.0.0.1",
            "ar-box.example.evil",
        ]:
            status, data = _http(p, f"GET /stats.json HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            assert status in (400, 421) and b'"sink"' not in data, (host, data[:200])
        status, data = _http(p, f"GET /estimate.json HTTP/1.1\r\nHost: evil.example:{p}\r\n\r\n".encode())
        assert status == 421 and b"allowed_hosts" in data
        assert _get(p, None) == 400  # HTTP/1.1 needs a Host
        assert _get(p, None, version="HTTP/1.0") == 200  # HTTP/1.0 may omit it: no browser does
        assert _get(p, "127.0.0.1", extra="Host: evil.example\r\n") == 400  # two Host headers
        st = sink.status()["sink"]
        assert st["refused_host"] >= 8
    with MjpegSink(port=0, allowed_hosts=["*"]) as sink:
        assert _get(sink.port, "evil.example") == 200


def test_connections_are_capped_with_a_503_and_a_flood_is_survived():
    import socket
    import threading as th

    from illuminet.runtime.stream.mjpeg import LISTEN_BACKLOG, MjpegSink

    with MjpegSink(port=0, max_clients=3) as sink:
        p = sink.port
        assert sink._server.request_queue_size == LISTEN_BACKLOG > 5
        streams = []
        for _ in range(3):  # three stream clients hold every slot
            s = socket.create_connection(("127.0.0.1", p), timeout=5)
            s.sendall(b"GET /stream.mjpg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert s.recv(12).startswith(b"HTTP/1.1 200")
            streams.append(s)
        t0 = time.monotonic()
        status, data = _http(p, b"GET /stats.json HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert status == 503 and b"Retry-After" in data and time.monotonic() - t0 < 3
        # a flood of connections: threads stay bounded, none hangs, the server still answers
        threads_before = th.active_count()
        flood = [socket.create_connection(("127.0.0.1", p), timeout=5) for _ in range(150)]
        assert th.active_count() <= threads_before + 2
        for s in flood:
            s.close()
        streams.pop().close()
        deadline = time.monotonic() + 5
        while sink.connections >= 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert _get(p, "127.0.0.1") == 200  # a freed slot serves again
        assert sink.status()["sink"]["refused_busy"] >= 2
        for s in streams:
            s.close()


def test_an_empty_listen_address_is_refused(capsys):
    from illuminet.runtime.stream.mjpeg import MjpegSink

    for value in ["", "  "]:
        assert main(["run", "synthetic://indoor", "--mjpeg", "--listen", value]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and "[output] listen" in lines[0] and "0.0.0.0" in lines[0], lines
        with pytest.raises(ValueError, match="listen address is empty"):
            MjpegSink(listen=value)
    assert main(["--set", "output.max_clients=0", "run", "synthetic://indoor"]) == 2
    assert main(["--set", 'output.allowed_hosts=[""]', "run", "synthetic://indoor"]) == 2
    assert "[output] allowed_hosts" in capsys.readouterr().err


def test_usb_only_oak_search_sends_nothing_on_the_network():
    """DepthAI's default search broadcasts on UDP 11491 (loopback included); protocol=usb sends nothing."""
    import socket

    from illuminet.hw import oakd

    assert oakd.parse_url("oakd://?protocol=usb").protocol == "usb"
    with pytest.raises(ValueError, match="protocol=usb cannot reach the network device"):
        oakd.parse_url("oakd://192.168.1.44?protocol=usb")
    assert oakd.open_url("oakd://", _sessions_cfg("usb")).opts.protocol == "usb"
    assert oakd.open_url("oakd://?protocol=tcpip", _sessions_cfg("usb")).opts.protocol == "tcpip"
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        listener.bind(("", 11491))
    except OSError as e:
        pytest.skip(f"UDP port 11491 is in use here: {e}")
    listener.settimeout(0.3)
    # each in a fresh process: DepthAI reads DEPTHAI_PROTOCOL once, at its first search
    code = (
        "import sys\nfrom illuminet.hw import oakd\ntry:\n    oakd.list_devices(sys.argv[1])\n"
        "except RuntimeError as e:\n    print('search failed:', e)\n"
    )
    got = {}
    try:
        for proto in ("usb", "any"):
            env = _sessions.env()
            env.pop("DEPTHAI_PROTOCOL", None)
            subprocess.run([sys.executable, "-c", code, proto], cwd=REPO, env=env, timeout=120, capture_output=True)
            packets = []
            try:
                while True:
                    packets.append(listener.recvfrom(64)[0])
            except TimeoutError:
                pass
            got[proto] = packets
    finally:
        listener.close()
    if not got["any"]:
        pytest.skip("no DepthAI discovery broadcast reached the loopback listener here (no broadcast route)")
    assert got["usb"] == [], got
    # and asking for another protocol after the first search is refused, not silently ignored
    oakd._searched_with = None
    try:
        assert oakd.select_protocol("any") in ("any", "usb", "tcpip")
        with pytest.raises(errors.SourceError, match="needs a new process"):
            oakd.select_protocol("tcpip" if oakd._searched_with != "tcpip" else "usb")
    finally:
        oakd._searched_with = None


def _sessions_cfg(protocol: str):
    from illuminet.runtime.config import apply_overrides, defaults

    return apply_overrides(defaults(), [("source", "oakd_protocol", protocol)])


def test_a_mesh_file_with_a_nan_vertex_is_refused_not_patched(tmp_path, capsys):
    """trimesh's processing silently dropped the faces of a NaN vertex, so `bundle --object` made a
    bundle of a mesh with a hole; the file is now refused, naming it."""
    import numpy as np
    import trimesh

    m = trimesh.creation.icosphere(1)
    v = m.vertices.copy()
    v[3] = np.nan
    obj = tmp_path / "nan.obj"
    lines = [f"v {x[0]!r} {x[1]!r} {x[2]!r}" for x in v.tolist()] + [
        f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces
    ]
    obj.write_text("\n".join(lines))
    assert main(["bundle", "--object", str(obj), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert f"{obj}: 1 vertex/vertices with non-finite coordinates" in err and "used by 5 face(s)" in err, err
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize(
    "far, expect",
    [
        ((1e200, 0.0, 0.0), "1 vertex/vertices lie 1e+200 units from the origin"),  # overflowed into a traceback
        ((1e7, 0.0, 0.0), "the mesh is 1e+07 units long but only 2 across"),  # a stray vertex: nothing left
    ],
)
def test_a_mesh_file_with_a_vertex_far_off_is_one_line(tmp_path, capsys, far, expect):
    import trimesh

    m = trimesh.creation.icosphere(1)
    lines = [f"v {x[0]!r} {x[1]!r} {x[2]!r}" for x in m.vertices.tolist()] + [f"v {far[0]!r} {far[1]!r} {far[2]!r}"]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces] + [f"f 1 2 {len(m.vertices) + 1}"]
    obj = tmp_path / "far.obj"
    obj.write_text("\n".join(lines))
    assert main(["bundle", "--object", str(obj), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert f"{obj}: {expect}" in err and "Traceback" not in err, err
    assert not (tmp_path / "b").exists()


def test_datagen_replaces_only_its_own_earlier_data(tmp_path, capsys):
    """--out naming an existing file that datagen did not write (a bundle's mesh.npz, a relight result, a
    text file) is refused and the file kept; an earlier datagen file is replaced, and the last line says
    so. (It overwrote any file without a word.)"""
    out = tmp_path / "dg.npz"
    np.savez(out, vertices=np.zeros((3, 3)))  # someone else's npz
    argv = [a.replace("{tmp}", str(tmp_path)) for a in _DATAGEN] + ["--n-proxy", "16", "--hdr", ""]
    before = out.read_bytes()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {out} exists and is not a datagen data file" in err and "Traceback" not in err, err
    assert out.read_bytes() == before
    out.write_text("notes")
    assert main(argv) == 2 and out.read_text() == "notes"
    capsys.readouterr()
    out.unlink()
    assert main(argv) == 0
    assert "replaced" not in capsys.readouterr().out
    assert main(argv) == 0
    assert "it replaced the earlier data there (2 samples of builtin:sphere)" in capsys.readouterr().out


@pytest.mark.parametrize("flag", ["--cases", "--flicker-scenes"])
def test_an_eval_count_that_would_run_for_years_is_refused_at_once(tmp_path, flag):
    """`eval --cases 1000000000` ran for years (nothing written until the end); refused in seconds now,
    with the estimate, before a bundle is loaded."""
    argv = ["eval", "--no-figure", "--camera-scenes", "0", "--out", str(tmp_path / "ev"), flag, "1000000000"]
    r = subprocess.run([sys.executable, "-m", "illuminet", *argv], cwd=REPO, capture_output=True, text=True, timeout=20)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert f"{flag} 1000000000: the run would take about" in lines[0] and "expected at most" in lines[0]
    assert not (tmp_path / "ev").exists()
