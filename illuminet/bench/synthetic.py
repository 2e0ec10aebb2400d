"""``illuminet bench synthetic``: the synthetic camera's frame time and the visibility precomputation.

Figures: median / p99 wall time (and median CPU time of this process, which contention from
other programs does not inflate) to render one RGB-D frame at 640x400 and 1280x800, for the static
path (geometry cached: noise, exposure, encoding and depth every frame) and the orbit path (the
camera moves: ray-plane intersection and texture lookups every frame too), for a cluttered room
(27 planes) and for a room without inter-reflection (``bounce=0``: the bounce is baked into the
planes, so it costs build time, not frame time); the time to build a scene; and the time to precompute a
:class:`~illuminet.runtime.groundtruth.visibility.VisibilityField` for a
1000-vertex object with its error against exact ray casts. Targets: <= 50 ms per 640x400 frame,
<= 10 s for the visibility precomputation. Reads no shared data.
"""

from __future__ import annotations

import time

import numpy as np

from illuminet.hw.synthetic import open_url
from illuminet.runtime.assets.objects import load_object, proxy_mesh
from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.groundtruth.visibility import VisibilityField, exact_visibility
from illuminet.runtime.stream.timing import Samples

FRAME_TARGET_MS = 50.0
VISIBILITY_TARGET_S = 10.0


def _frames(url: str, n: int) -> dict:
    t0 = time.perf_counter()
    src = open_url(url)
    src.open()
    build_s = time.perf_counter() - t0
    src.read()  # first frame: renderer set-up
    wall, cpu = Samples("wall"), []
    for _ in range(n):
        c0 = time.process_time()
        with wall.time():
            f = src.read()
        cpu.append(time.process_time() - c0)
        if f is None:
            break
    src.close()
    s = wall.summary()
    s["cpu_median_ms"] = float(np.median(cpu) * 1e3)
    s["build_s"] = build_s
    return s


def run(args, cfg) -> dict:
    quick = bool(getattr(args, "quick", False))
    n = 10 if quick else 60
    out: dict = {"frames": {}}
    cases = [
        ("indoor 640x400 static", f"synthetic://indoor?seed=0&frames={n + 2}"),
        ("indoor 640x400 orbit", f"synthetic://indoor?seed=0&frames={n + 2}&path=orbit"),
        ("outdoor 640x400 orbit", f"synthetic://outdoor?seed=0&frames={n + 2}&path=orbit"),
        # 27 planes (a room, a table, boxes): the most planes to intersect per pixel
        ("cluttered 640x400 orbit", f"synthetic://cluttered?seed=0&frames={n + 2}&path=orbit"),
        # the same room without inter-reflection: what the bounce costs (only at build time)
        ("indoor 640x400 orbit bounce=0", f"synthetic://indoor?seed=0&frames={n + 2}&path=orbit&bounce=0"),
        ("indoor 1280x800 static", f"synthetic://indoor?seed=0&frames={n // 2 + 2}&size=1280x800"),
        ("indoor 1280x800 orbit", f"synthetic://indoor?seed=0&frames={n // 2 + 2}&size=1280x800&path=orbit"),
    ]
    print(f"{'case':30s} {'median ms':>10s} {'p99 ms':>8s} {'cpu med ms':>10s} {'build s':>8s}")
    for name, url in cases:
        s = _frames(url, n if "640" in name else n // 2)
        out["frames"][name] = s
        flag = ""
        if "640x400" in name:
            flag = "ok" if s["median_ms"] <= FRAME_TARGET_MS else f"over the {FRAME_TARGET_MS:.0f} ms target"
        print(
            f"{name:30s} {s['median_ms']:10.1f} {s['p99_ms']:8.1f} {s['cpu_median_ms']:10.1f} "
            f"{s['build_s']:8.2f}  {flag}"
        )

    import importlib.util

    if not any(importlib.util.find_spec(m) for m in ("embreex", "rtree")):
        print(
            "\nvisibility field: not measured: casting rays needs Embree (embreex) or rtree, which come "
            "with the bundle extra: pip install 'illuminet[bundle]'"
        )
        return out
    mesh = proxy_mesh(load_object("builtin:vase"), 1000)
    t0 = time.perf_counter()
    field = VisibilityField(mesh, n_directions=1024)
    pre_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    lights = L.sample_lights("indoor", rng)
    t0 = time.perf_counter()
    exact_visibility(mesh, mesh.vertices, lights, normals=mesh.vertex_normals)
    exact_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    field.lookup_lights(lights)
    lookup_s = time.perf_counter() - t0
    errs = {k: field.error(L.sample_lights(k, rng)) for k in L.ENVIRONMENT_KINDS}
    out["visibility"] = {
        "vertices": int(len(mesh.vertices)),
        "directions": 1024,
        "precompute_s": pre_s,
        "exact_32_lights_s": exact_s,
        "lookup_32_lights_s": lookup_s,
        "error": errs,
    }
    flag = "ok" if pre_s <= VISIBILITY_TARGET_S else f"over the {VISIBILITY_TARGET_S:.0f} s target"
    print(
        f"\nvisibility field, builtin:vase proxy ({len(mesh.vertices)} vertices, 1024 directions): "
        f"precompute {pre_s:.2f} s  {flag}"
    )
    print(f"  exact ray casts for 32 lights: {exact_s * 1e3:.1f} ms; field lookup: {lookup_s * 1e3:.1f} ms")
    for k, e in errs.items():
        print(
            f"  error vs exact, {k:8s}: mean |soft - exact| {e['mae']:.4f}, pairs disagreeing "
            f"{e['disagree'] * 100:.2f} %, irradiance {e['irradiance_rel'] * 100:.2f} %"
        )
    return out
