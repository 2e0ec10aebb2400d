"""``illuminet bench replay``: replay throughput of a 640x400 RGB-D session through a null sink.

Records a session into a temporary folder (frames from ``synthetic://indoor``; from
:func:`numpy_rgbd_frames` at other sizes than 640x400), then replays it with ``timing=asap`` through the
streaming loop into a :class:`~illuminet.runtime.stream.sinks.NullSink` several times and prints the median
frames per second (target: >= 150 on two cores) and per-step timing. Also reports the recording
(write) rate and the session size per frame.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from illuminet.runtime.config import Config
from illuminet.runtime.frame import Exposure, Frame, Intrinsics
from illuminet.runtime.stream.loop import run_loop
from illuminet.runtime.stream.session import SessionWriter
from illuminet.runtime.stream.sinks import NullSink

WIDTH, HEIGHT = 640, 400
TARGET_FPS = 150.0


def numpy_rgbd_frames(
    n: int, width: int = WIDTH, height: int = HEIGHT, seed: int = 0, fps: float = 30.0
) -> Iterator[Frame]:
    """Camera-like RGB-D frames made with numpy alone (for benchmarks and tests, not for lighting).

    Not a renderer: it gives images with the statistics that matter for storage speed -- smooth shading,
    a blocky texture, per-frame sensor noise, 8-bit quantisation -- and a depth map of a floor and a
    wall with z^2-growing noise and ~5 % holes, in uint16-millimetre steps (so a session round trip is
    bit-exact). Frame ``k`` is the same for the same ``seed`` whatever ``n`` is.
    """
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    rng0 = np.random.default_rng(seed)
    tex = rng0.random((height // 8 + 1, width // 8 + 1, 3)).astype(np.float32) * 40.0
    tex = np.repeat(np.repeat(tex, 8, 0), 8, 1)[:height, :width]
    base = np.stack([120 + 60 * np.sin(xx / 50), 100 + 40 * np.cos(yy / 40), 80 + 30 * np.sin((xx + yy) / 70)], -1)
    # floor below the horizon row, wall above: metres
    horizon = height * 0.45
    z_floor = 0.6 * height / np.maximum(yy - horizon, 1.0) + 0.8
    z = np.where(yy > horizon, np.minimum(z_floor, 4.0), 4.0).astype(np.float32)
    f = 0.9 * width
    intr = Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)
    period = int(round(1e9 / fps))
    for k in range(n):
        rng = np.random.default_rng((seed, k))
        shift = np.float32(10 * np.sin(k / 15))
        color = np.clip(base + tex + shift + rng.normal(0, 2.0, (height, width, 3)), 0, 255).astype(np.uint8)
        noise = rng.normal(0, 1.0, (height, width)).astype(np.float32) * 0.002 * z * z
        mm = np.rint((z + noise) * 1000.0)
        mm[rng.random((height, width)) < 0.05] = 0  # stereo holes
        depth = mm.astype(np.uint16).astype(np.float32) * np.float32(1e-3)
        yield Frame(
            seq=k,
            t_device_ns=1_000_000_000 + k * period,
            t_host_ns=time.monotonic_ns(),
            color=color,
            depth=depth,
            intrinsics=intr,
            exposure=Exposure(exposure_us=8000.0, iso=400.0),
            gravity=np.array([0.0, 1.0, 0.0]),
        )


def _frames(n: int, cfg: Config, width: int, height: int) -> tuple[str, Iterator[Frame]]:
    """Source frames for the benchmark session: ``synthetic://indoor`` at its 640x400, numpy ones at
    other sizes (the tests' small sessions)."""
    from illuminet.hw import open_source

    url = f"synthetic://indoor?seed=0&frames={n}"
    if (width, height) != (WIDTH, HEIGHT):
        print(f"  ({url} is {WIDTH}x{HEIGHT}, not {width}x{height}; using numpy frames)")
        return "numpy_rgbd_frames(seed=0)", numpy_rgbd_frames(n, width, height)
    src = open_source(url, cfg)
    src.open()

    def gen():
        try:
            for _ in range(n):
                f = src.read()
                if f is None:
                    return
                yield f
        finally:
            src.close()

    return url, gen()


def record_session(
    path: Path, n: int, cfg: Config, color: str = "raw", width: int = WIDTH, height: int = HEIGHT
) -> dict:
    """Write a benchmark session of ``n`` frames at ``path``; returns what was recorded and how fast."""
    origin, frames = _frames(n, cfg, width, height)
    dt = 0.0  # time in the writer only, not in making the frames
    with SessionWriter(path, source=origin, color=color) as w:
        for f in frames:
            t0 = time.perf_counter()
            w.append(f)
            dt += time.perf_counter() - t0
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return {"origin": origin, "frames": w.count, "write_fps": w.count / dt, "bytes_per_frame": size / max(w.count, 1)}


def run(args, cfg: Config) -> dict:
    """``illuminet bench replay``: 300 frames, 5 runs, the configured colour encoding (``[output]
    record_color``, raw by default) then the other lossless one for comparison (``--quick``: 60 frames,
    3 runs, configured encoding only)."""
    quick = bool(getattr(args, "quick", False))
    n, runs = (60, 3) if quick else (300, 5)
    first = cfg.output.record_color
    other = tuple(c for c in ("raw", "png") if c != first)[:1]
    return measure(n, runs, cfg, colors=(first,) if quick else (first, *other))


def _replay_runs(path: Path, runs: int) -> tuple[list[float], list[float], Any]:
    from illuminet.hw.replay import ReplaySource

    fps, cpu, last = [], [], None
    for _ in range(runs):
        src = ReplaySource(path, timing="asap")
        c0 = time.process_time()
        last = run_loop(src, [], [NullSink()], install_signals=False)
        cpu.append((time.process_time() - c0) / max(last.frames, 1))
        fps.append(last.frames / last.elapsed_s)
    return fps, cpu, last


def measure(
    n: int, runs: int, cfg: Config, width: int = WIDTH, height: int = HEIGHT, colors: tuple[str, ...] = ("raw",)
) -> dict:
    """Record ``n`` frames per colour encoding, replay each asap through a null sink ``runs`` times.

    Prints and returns the figures; the top-level keys are those of the first encoding, ``by_color``
    has every encoding's.
    """
    tmp = Path(tempfile.mkdtemp(prefix="illuminet-bench-replay-"))
    try:
        out: dict[str, Any] = {}
        for color in colors:
            path = tmp / f"session-{color}"
            rec = record_session(path, n, cfg, color=color, width=width, height=height)
            print(
                f"  session: {rec['frames']} frames {width}x{height} RGB-D from {rec['origin']}, colour {color}, "
                f"depth 16-bit PNG; {rec['bytes_per_frame'] / 1e3:.0f} kB/frame; writer: {rec['write_fps']:.1f} "
                f"frames/s (one thread, with fsync)"
            )
            fps, cpu, last = _replay_runs(path, runs)
            shutil.rmtree(path, ignore_errors=True)
            med = float(np.median(fps))
            cpu_ms = float(np.median(cpu)) * 1e3
            print(f"  [{color}] replay asap -> null sink, frames/s per run: " + ", ".join(f"{x:.1f}" for x in fps))
            print(
                f"  [{color}] median {med:.1f} frames/s (target >= {TARGET_FPS:.0f}): "
                f"{'OK' if med >= TARGET_FPS else 'BELOW TARGET'}"
            )
            # wall-clock figures depend on what else runs on the machine; CPU time per frame does not
            print(
                f"  [{color}] CPU time {cpu_ms:.2f} ms/frame (all threads): with the machine to itself that is "
                f"~{1e3 / cpu_ms:.0f} frames/s on one core, ~{2e3 / cpu_ms:.0f} on two (decoding runs on 2 threads)"
            )
            if color == colors[0]:
                print("  last run, per step:")
                print("    " + last.format_stats().replace("\n", "\n    "))
            out[color] = {
                "frames": rec["frames"],
                "width": width,
                "height": height,
                "origin": rec["origin"],
                "color": color,
                "replay_fps_runs": fps,
                "replay_fps_median": med,
                "target_fps": TARGET_FPS,
                "cpu_ms_per_frame": cpu_ms,
                "record_fps": rec["write_fps"],
                "bytes_per_frame": rec["bytes_per_frame"],
                "steps": last.to_dict()["steps"],
            }
        return {**out[colors[0]], "by_color": out}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
