"""The demo's default session looks lit by its lamp: the vase is lit from the lamp's side, tinted by the
lamp's warm light, and its shadow falls away from the lamp (checked against the session's known light)."""

from __future__ import annotations

import numpy as np
import pytest

from illuminet.commands.demo import DEFAULT_SESSION, default_session_source_url, demo_stages
from illuminet.hw import open_source
from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.scene import ANCHOR, COMPOSITE, LIGHT, SHADING
from illuminet.runtime.stage import StageChain

LUMA = np.array([0.2126, 0.7152, 0.0722])
FRAMES = 16


def _lamp_in_object_frame(frame_index: int, T_cam_obj: np.ndarray) -> np.ndarray:
    """The session's lamp (its strongest light) in the object frame, from the synthetic scene that
    recorded it (same URL, same seed)."""
    from illuminet.hw.synthetic import open_url

    src = open_url(default_session_source_url())
    lo = src.scene.object_lights(T_cam_obj, frame_index)
    return lo.positions[int(np.argmax(lo.intensities @ LUMA))]


@pytest.mark.gl
def test_default_session_vase_is_lit_tinted_and_shadowed_by_the_lamp(gl):
    cfg = apply_overrides(defaults(), [("source", "timing", "asap")])
    stages = demo_stages(cfg)
    src = open_source(f"replay://{DEFAULT_SESSION}?timing=asap", cfg)
    with src:
        for s in stages:
            s.open()
        try:
            chain = StageChain(stages, source=src, strict=True)
            for _ in range(FRAMES):
                f = chain(src.read())
        finally:
            for s in stages:
                s.close()
    anchor, est, shading = f.results[ANCHOR.name], f.results[LIGHT.name], f.results[SHADING.name]
    lamp = _lamp_in_object_frame(f.seq, anchor.T_cam_obj)
    d_true = lamp - np.array([0.0, 0.1, 0.0])
    d_true /= np.linalg.norm(d_true)
    # 1. the estimate points at the lamp
    assert est.primary_dir is not None
    ang = np.degrees(np.arccos(np.clip(float(est.primary_dir @ d_true), -1, 1)))
    assert ang < 25.0, ang
    # 2. the vase is lit from the lamp's side: vertices facing the lamp (horizontally) are much brighter
    #    than those facing away, which still get the room's ambient light (not black)
    stage = next(s for s in stages if s.name == "shading")
    normals = stage.bundle.proxy_normals
    h = np.array([d_true[0], 0.0, d_true[2]])
    h /= np.linalg.norm(h)
    lum = shading.irradiance @ LUMA
    towards, away = lum[normals @ h > 0.5].mean(), lum[normals @ h < -0.5].mean()
    assert towards > 2.0 * away, (towards, away)
    assert away > 0.0
    # 3. tinted by the warm lamp (2400-3000 K): a white vase comes out warm
    mean = shading.irradiance.mean(0)
    assert mean[0] > 1.25 * mean[2], mean
    # 4. the cast shadow falls away from the lamp: on the floor 0.2 m from the vase, the side away
    #    from the lamp is darkened by the composite, the lamp's side is not
    comp = f.results[COMPOSITE.name].astype(np.float64)
    K = f.intrinsics.scaled(*f.size).K if (f.intrinsics.width, f.intrinsics.height) != f.size else f.intrinsics.K

    def darkening(p_obj):
        pc = anchor.R @ p_obj + anchor.t
        u, v, _ = (K @ pc) / pc[2]
        u, v = int(round(u)), int(round(v))
        a = comp[v - 3 : v + 4, u - 3 : u + 4].mean()
        b = f.color[v - 3 : v + 4, u - 3 : u + 4].astype(np.float64).mean()
        return a / max(b, 1e-6)

    shadow_side = darkening(-0.2 * h)
    lamp_side = darkening(0.2 * h)
    assert shadow_side < 0.9 and lamp_side > 0.97, (shadow_side, lamp_side)
