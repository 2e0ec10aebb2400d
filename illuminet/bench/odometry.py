"""``illuminet bench odometry``: camera odometry per 640x400 frame, and the world-locked anchor's drift.

Frames: the synthetic camera orbiting the object (``synthetic://indoor?seed=0&frames=40&path=orbit``:
+-25 degrees of swing and 5 cm of bobbing in 40 frames, i.e. up to ~4 degrees and ~10 cm per frame),
played forwards and backwards (a continuous path) so that the timing has enough samples.

Prints
    * ``odometry``: :meth:`Odometry.update` alone, wall and process-CPU median / p99 (target <= 3 ms
      median);
    * ``anchor (world lock)``: :class:`AnchorStage` with ``lock = "world"`` (odometry constrained by the
      anchor plane, matching and re-snapping), same figures;
    * the drift of the world-locked anchor against the ground-truth camera poses over the path:
      the largest distance (cm) and yaw change (degrees) of the object's world pose from where it was
      placed, and the same for ``lock = "camera"`` for comparison.
    * with ``--look N``: a user looking around outdoors (``synthetic://outdoor?path=look``: at the object,
      the view raised to the horizon, one full turn in place, back down; 300 frames, 150 with
      ``--quick``) on the evaluation's first N outdoor scenes with their held-out HDR maps (the sky and
      the far grass have no depth: the turn is tracked by the bearings, docs/planes.md): per scene the
      object's distance and yaw from where it was placed at the end and at most, lost frames and the
      frames tracked as a turn in place. Needs the HDR maps (``../shared/data/hdri``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from illuminet.runtime.config import Config, ConfigError, apply_overrides
from illuminet.runtime.scene import ODOMETRY
from illuminet.runtime.stream.timing import Samples

URL = "synthetic://indoor?seed=0&frames=40&path=orbit"


def anchor_drift(frames, cfg: Config) -> dict:
    """Run PlaneStage + AnchorStage over ``frames`` (with ``results["synthetic_gt"]``); the object's drift
    in the true world frame: max distance (m) and max yaw change (degrees) from the first frame, plus the
    odometry states seen and the AnchorStage's time per frame."""
    from illuminet.runtime.stages.anchor import AnchorStage
    from illuminet.runtime.stages.odometry import invert
    from illuminet.runtime.stages.planes import PlaneStage

    ps, an = PlaneStage(cfg), AnchorStage(cfg)
    W0 = None
    dist, yaw, states = [], [], []
    t_wall, t_cpu = Samples("anchor"), Samples("anchor:cpu")
    for f in frames:
        f = ps.process(f)
        t0, c0 = time.perf_counter(), time.process_time()
        f = an.process(f)
        t_wall.add(time.perf_counter() - t0)
        t_cpu.add(time.process_time() - c0)
        W = invert(f.results["synthetic_gt"]["T_cam_world"]) @ f.results["anchor"].T_cam_obj
        if W0 is None:
            W0 = W
        dist.append(float(np.linalg.norm(W[:3, 3] - W0[:3, 3])))
        z0, z1 = W0[:3, 2], W[:3, 2]
        # yaw: the object's +Z (which lies in the floor) against where it pointed when placed
        yaw.append(float(np.degrees(np.arccos(np.clip(z0 @ z1 / (np.linalg.norm(z0) * np.linalg.norm(z1)), -1, 1)))))
        o = f.results.get(ODOMETRY.name)
        states.append(("turn" if o.rotation_only else o.state) if o is not None else "-")
    return {
        "max_drift_m": max(dist),
        "final_drift_m": dist[-1],
        "max_yaw_deg": max(yaw),
        "final_yaw_deg": yaw[-1],
        "lost_frames": states.count("lost"),
        "rotation_frames": states.count("turn"),
        "stage": t_wall.summary(),
        "stage_cpu": t_cpu.summary(),
        "stats": an.stats(),
    }


def load_frames(cfg: Config, url: str = URL) -> list:
    from illuminet.hw import open_source

    frames = []
    with open_source(url, cfg) as src:
        while (f := src.read()) is not None:
            frames.append(f)
    return frames


def check_args(args: argparse.Namespace, cfg: Config) -> int:
    """``--look`` (``illuminet bench`` calls this before any benchmark runs)."""
    look = int(getattr(args, "look", 0) or 0)
    if look < 0:
        raise ConfigError(f"--look: expected a number of scenes >= 0, got {look}")
    return look


def run(args: argparse.Namespace, cfg: Config) -> dict:
    """Time the odometry and report the world-locked anchor's drift (module docstring)."""
    from illuminet.runtime.stages.odometry import Odometry

    quick = bool(getattr(args, "quick", False))
    look = check_args(args, cfg)
    frames = load_frames(cfg)
    path = frames + frames[-2:0:-1]  # forwards then backwards: a continuous camera path
    reps = 1 if quick else 4
    print(
        f"# frames: {URL}, {frames[0].size[0]}x{frames[0].size[1]}, {reps * len(path)} timed frames "
        f"(CPU shared with other processes: wall figures are upper bounds)"
    )
    od = Odometry()
    wall, cpu = Samples("odometry"), Samples("odometry:cpu")
    states = []
    for _ in range(reps):
        for f in path:
            t0, c0 = time.perf_counter(), time.process_time()
            r = od.update(f)
            wall.add(time.perf_counter() - t0)
            cpu.add(time.process_time() - c0)
            states.append(r.state)
    out = {"source": URL, "frames": len(states)}
    sw, sc = wall.summary(), cpu.summary()
    out["odometry"], out["odometry_cpu"] = sw, sc
    print(f"{'odometry':20s} median {sw['median_ms']:6.2f} ms   p99 {sw['p99_ms']:6.2f} ms   (target <= 3 ms median)")
    print(
        f"{'odometry (CPU)':20s} median {sc['median_ms']:6.2f} ms   p99 {sc['p99_ms']:6.2f} ms   "
        f"lost {states.count('lost')}/{len(states)}  inliers (last) {od.last.inliers}"
    )
    for lock in ("world", "camera"):
        d = anchor_drift(frames, apply_overrides(cfg, [("anchor", "lock", lock)]))
        out[f"anchor_{lock}"] = {k: v for k, v in d.items() if k != "stats"}
        st = d["stage"]
        print(
            f"{'anchor (' + lock + ' lock)':20s} median {st['median_ms']:6.2f} ms   p99 {st['p99_ms']:6.2f} ms   "
            f"(CPU {d['stage_cpu']['median_ms']:.2f} ms)  drift over the orbit: max {100 * d['max_drift_m']:.2f} cm, "
            f"yaw max {d['max_yaw_deg']:.2f} deg  (world-lock target <= 2 cm, <= 2 deg)  lost {d['lost_frames']}"
        )
    if look > 0:
        out["look"] = look_around(cfg, look, 150 if quick else 300, getattr(args, "hdr", None))
    return out


def look_around(cfg: Config, scenes: int, frames: int, hdr_dir: str | Path | None = None) -> list[dict] | None:
    """The world-locked anchor over a look-around on the evaluation's first ``scenes`` outdoor scenes
    (module docstring); None (and a line saying why) without the held-out HDR maps in ``hdr_dir``
    (default: ``shared/data/hdri`` beside the checkout)."""
    from illuminet.commands.train import DEFAULT_HDR
    from illuminet.models.camera_eval import SEED_BASE
    from illuminet.models.datagen import hdr_maps

    hdr = Path(hdr_dir) if hdr_dir else DEFAULT_HDR
    maps = hdr_maps(str(hdr), "test") if hdr.is_dir() else []
    if not maps:
        print(
            f"look-around: skipped (no held-out HDR maps in {hdr}: the outdoor sky comes from them; "
            "--hdr DIR names their folder)"
        )
        return None
    rows = []
    for i in range(scenes):
        url = f"synthetic://outdoor?seed={SEED_BASE + i}&frames={frames}&path=look&hdr={maps[i % len(maps)]}"
        d = anchor_drift(load_frames(cfg, url), apply_overrides(cfg, [("anchor", "lock", "world")]))
        row = {"url": url, **{k: v for k, v in d.items() if k not in ("stats", "stage", "stage_cpu")}}
        rows.append(row)
        print(
            f"look-around scene {i} ({frames} frames, one full turn): object {100 * d['final_drift_m']:.1f} cm and "
            f"{d['final_yaw_deg']:.1f} deg from where it was placed at the end (max {100 * d['max_drift_m']:.1f} cm, "
            f"{d['max_yaw_deg']:.1f} deg); lost {d['lost_frames']}, turn in place {d['rotation_frames']}",
            flush=True,
        )
    return rows


if __name__ == "__main__":  # pragma: no cover - `illuminet bench odometry` is the entry point
    from illuminet.runtime.config import defaults

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    run(a, defaults())
