"""``illuminet bench render``: render + composite of one frame at 1280x800 (moderngl, EGL).

The scene is made here, without the synthetic camera, so that the figure is the renderer's alone:
a textured 1280x800 floor picture with its depth, the built-in vase 1.0 m from the camera, lit by
a directional light plus ambient whose predicted direction jitters by about a degree per frame
(the shadow is redrawn when the smoothed direction has moved more than 1 degree), the full
:class:`~illuminet.runtime.render.stage.RenderStage` (carry, dominant light, shadow, occlusion test, MSAA,
read-back, paste into a copy of the frame). Prints wall-clock and CPU-time median / p99 per frame
(CPU time includes llvmpipe's worker threads, and is the steadier figure on a shared machine).
"""

from __future__ import annotations

import time

import numpy as np

from illuminet.runtime.config import apply_overrides
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import ANCHOR, PLANE_LIGHT, SHADING, Anchor, ObjectShading, PlaneLight
from illuminet.runtime.stream.timing import Samples

W, H = 1280, 800
TARGET_MS = 10.0


def _scene(seed: int = 0):
    """Camera pose, colour and depth of a floor seen from 1.0 m at 35 degrees."""
    import cv2

    intr = Intrinsics(fx=800.0, fy=800.0, cx=639.5, cy=399.5, width=W, height=H)
    a = np.radians(35.0)
    pos = np.array([0.0, np.sin(a), np.cos(a)])
    z = -pos / np.linalg.norm(pos)
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T_obj_cam = np.eye(4)
    T_obj_cam[:3, :3] = np.stack([x, y, z], axis=1)
    T_obj_cam[:3, 3] = pos
    T = np.linalg.inv(T_obj_cam)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones((H, W))], axis=-1)
    d = rays @ T_obj_cam[:3, :3].T
    t = -pos[1] / d[..., 1]
    depth = np.where(t > 0, t, 0.0).astype(np.float32)
    rng = np.random.default_rng(seed)
    noise = cv2.resize(rng.random((50, 80)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    color = np.clip(np.stack([120 + 60 * noise, 110 + 50 * noise, 95 + 40 * noise], -1), 0, 255).astype(np.uint8)
    return intr, T, color, depth


def run(args, cfg) -> dict:
    from illuminet.runtime.assets.objects import load_object
    from illuminet.runtime.render.gl import get_context, renderer_name
    from illuminet.runtime.render.stage import RenderStage

    quick = bool(getattr(args, "quick", False))
    n = 40 if quick else 200
    cfg = apply_overrides(cfg, [])
    intr, T, color, depth = _scene()
    mesh = load_object("builtin:vase")
    st = RenderStage(cfg, mesh=mesh)
    st.open()
    normals = st.comp.mesh.normals
    pl = PlaneLight(
        vertices=np.zeros((1, 3)),
        normals=np.zeros((1, 3)),
        irradiance=np.zeros((1, 3)),
        mask=np.ones(1, bool),
        confidence=np.ones(1),
        grid=1,
        exposure_scale=0.25,
    )
    frames = []
    rng = np.random.default_rng(1)
    for i in range(16):  # a light whose predicted direction jitters by ~1 degree, as a prediction does
        d = np.array([-np.cos(np.radians(40.0)), np.sin(np.radians(40.0)), 0.3]) + rng.normal(0, 0.015, 3)
        d /= np.linalg.norm(d)
        irr = (2.0 * np.maximum(normals @ d, 0.0)[:, None] * np.array([1.0, 0.95, 0.85]) + 0.4).astype(np.float32)
        f = Frame(seq=i, t_device_ns=i, t_host_ns=i, color=color, depth=depth, intrinsics=intr)
        f = f.with_result(ANCHOR, Anchor(T_cam_obj=T, plane_id=0)).with_result(PLANE_LIGHT, pl)
        frames.append(
            f.with_result(SHADING, ObjectShading(irradiance=irr, method="bench", dominant_dir=d, dominant_share=0.7))
        )
    for f in frames[:3]:
        st.process(f)
    wall, cpu = Samples("wall"), Samples("cpu")
    for i in range(n):
        f = frames[i % len(frames)]
        t0, c0 = time.perf_counter(), time.process_time()
        st.process(f)
        wall.add(time.perf_counter() - t0)
        cpu.add(time.process_time() - c0)
    info = st.comp.info
    stats = st.stats()
    st.close()
    w, c = wall.summary(), cpu.summary()
    print(
        f"renderer: {renderer_name(get_context())}; object builtin:vase ({st_vertices(mesh)} vertices), "
        f"antialias {stats.get('antialias')}, shadow map {cfg.render.shadow_map}, "
        f"crop {info.crop[2]}x{info.crop[3]} px"
    )
    print(
        f"render+composite 1280x800: wall median {w['median_ms']:.2f} ms, p99 {w['p99_ms']:.2f} ms; "
        f"CPU median {c['median_ms']:.2f} ms, p99 {c['p99_ms']:.2f} ms  (target <= {TARGET_MS:.0f} ms median; "
        f"{n} frames, shadow redraws {stats.get('shadow_redraws')})"
    )
    return {
        "wall": w,
        "cpu": c,
        "crop": list(info.crop),
        "frames": n,
        "antialias": stats.get("antialias"),
        "shadow_redraws": stats.get("shadow_redraws"),
        "shadow_map": cfg.render.shadow_map,
        "target_ms": TARGET_MS,
    }


def st_vertices(mesh) -> int:
    return int(len(mesh.vertices))
