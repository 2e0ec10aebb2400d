"""Test helpers of the runtime-core tests: small deterministic RGB-D sessions written with the real writer."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from illuminet.bench.replay import numpy_rgbd_frames
from illuminet.runtime.frame import Frame
from illuminet.runtime.stream.session import SessionWriter

from .conftest import REPO

W, H = 64, 48


def frames(n: int, *, fps: float = 30.0, seed: int = 0, w: int = W, h: int = H) -> list[Frame]:
    """``n`` small camera-like RGB-D frames (bit-exact through a session round trip)."""
    return list(numpy_rgbd_frames(n, w, h, seed=seed, fps=fps))


def make_session(path: Path, n: int = 8, *, fps: float = 30.0, **writer_kw) -> list[Frame]:
    """Record ``n`` frames into a new session at ``path``; returns the frames written."""
    fs = frames(n, fps=fps)
    writer_kw.setdefault("color", "png")  # most bad-session tests damage PNG files; raw is tested explicitly
    with SessionWriter(path, source="test://frames", **writer_kw) as w:
        for f in fs:
            w.append(f)
    return fs


def same_frame(a: Frame, b: Frame) -> bool:
    """Pixels and metadata equal (results and host time ignored)."""
    return (
        np.array_equal(a.color, b.color)
        and ((a.depth is None and b.depth is None) or np.array_equal(a.depth, b.depth))
        and a.t_device_ns == b.t_device_ns
        and a.seq == b.seq
        and a.exposure == b.exposure
        and a.intrinsics == b.intrinsics
    )


def env() -> dict[str, str]:
    """Environment for a subprocess that imports illuminet from this checkout."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    e["DEPTHAI_TELEMETRY"] = "0"
    return e


def spawn(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, *args], cwd=REPO, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw
    )


def complete_lines(index: Path) -> int:
    """Number of newline-terminated lines in a session index (0 when it does not exist yet)."""
    try:
        return index.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def wait_for_lines(index: Path, n: int, proc: subprocess.Popen, timeout: float = 20.0) -> int:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        k = complete_lines(index)
        if k >= n:
            return k
        if proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"recording process ended early (rc {proc.returncode}):\n{out}\n{err}")
        time.sleep(0.01)
    proc.kill()
    raise AssertionError(f"recording did not reach {n} frames in {timeout} s")


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run ``python -m illuminet ARGS`` in a fresh process (as a user would), capturing its output.

    Commands that run the full pipeline open the renderer's own GL context; running them in a child
    process keeps that context out of the test process (whose GL tests share one context).
    """
    return subprocess.run(
        [sys.executable, "-m", "illuminet", *args], cwd=REPO, env=env(), capture_output=True, text=True, timeout=timeout
    )
