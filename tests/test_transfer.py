"""The transfer stage: plane normalisation, the ONNX chain on shipped bundles, smoothing, modes, errors."""

from __future__ import annotations

import numpy as np
import pytest

from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, Intrinsics
from illuminet.runtime.scene import ObjectShading
from illuminet.runtime.sh import sh_eval, sh_fit
from illuminet.runtime.stage import FrameError
from illuminet.runtime.stages.shading import ShadingStage, dominant_light_from_oi, preprocess_plane

from ._learn_helpers import plane_light


def _stage(**model):
    cfg = apply_overrides(defaults(), [("model", k, v) for k, v in model.items()])
    st = ShadingStage(cfg)
    st.open()
    return st


def _frame(pl):
    f = Frame(
        seq=0,
        t_device_ns=0,
        t_host_ns=0,
        color=np.zeros((4, 4, 3), np.uint8),
        depth=None,
        intrinsics=Intrinsics(1, 1, 1, 1, 4, 4),
    )
    return f.with_result("plane_light", pl)


def test_preprocess_is_scale_invariant_and_pools():
    pl = plane_light()
    x1, s1 = preprocess_plane(pl.irradiance, pl.mask, 32)
    x2, s2 = preprocess_plane(pl.irradiance * 7.0, pl.mask, 32)
    assert x1.shape == (256, 4)
    assert np.allclose(x1, x2, atol=1e-5)
    assert s2 == pytest.approx(7.0 * s1, rel=1e-5)
    # the coverage channel is the observed fraction of each 2x2 cell
    assert np.allclose(x1[:, 3] * 4, np.round(x1[:, 3] * 4))


def test_preprocess_errors_name_the_problem():
    pl = plane_light()
    with pytest.raises(ValueError, match=r"\(1024, 3\)"):
        preprocess_plane(pl.irradiance[:10], pl.mask, 32)
    with pytest.raises(ValueError, match="no observed plane cells"):
        preprocess_plane(pl.irradiance, np.zeros(1024, bool), 32)


def test_dominant_light_of_one_direction():
    d = np.array([0.3, 0.8, -0.5])
    d /= np.linalg.norm(d)
    oi = np.tile(d[None, None, :], (50, 3, 1)).astype(np.float32)
    got, share = dominant_light_from_oi(oi)
    assert np.allclose(got, d, atol=1e-5) and share == pytest.approx(1.0)


def test_sh_fit_recovers_sh_lighting():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    coef = rng.normal(size=(9, 3)) * 0.1
    coef[0] = 2.0
    e = sh_eval(coef, n)
    assert np.allclose(sh_fit(n, e), coef, atol=1e-3)


@pytest.mark.parametrize("precision", ["int8", "fp32"])
def test_stage_predicts_scaled_shading(precision):
    st = _stage(bundle="builtin:vase", precision=precision, temporal_smoothing=0.0)
    out = st.process(_frame(plane_light())).results["shading"]
    assert isinstance(out, ObjectShading)
    V = st.bundle.n_proxy
    assert out.irradiance.shape == (V, 3) and out.oi.shape == (V, 3, 3)
    assert np.isfinite(out.irradiance).all() and (out.irradiance >= 0).all()
    assert out.method == f"model:{precision}"
    assert abs(np.linalg.norm(out.dominant_dir) - 1) < 1e-4 and 0 <= out.dominant_share <= 1
    # doubling the light doubles the prediction (the network sees normalised input)
    out2 = st.process(_frame(plane_light(scale=2.0))).results["shading"]
    assert np.allclose(out2.irradiance, 2 * out.irradiance, rtol=1e-3, atol=1e-5)


def test_int8_close_to_fp32():
    a = _stage(precision="int8", temporal_smoothing=0.0).predict(plane_light())
    b = _stage(precision="fp32", temporal_smoothing=0.0).predict(plane_light())
    assert np.abs(a.irradiance - b.irradiance).mean() < 0.02 * b.irradiance.mean()


def test_temporal_smoothing_damps_changes():
    raw = _stage(temporal_smoothing=0.0)
    smooth = _stage(temporal_smoothing=0.7)
    for st in (raw, smooth):
        st.process(_frame(plane_light(seed=1)))
    r = raw.process(_frame(plane_light(scale=1.5, seed=2))).results["shading"].irradiance
    s = smooth.process(_frame(plane_light(scale=1.5, seed=2))).results["shading"].irradiance
    first = raw.predict(plane_light(seed=1)).irradiance
    assert np.abs(s - first).mean() < 0.5 * np.abs(r - first).mean()


@pytest.mark.parametrize("mode", ["constant", "ambient", "sh"])
def test_baseline_modes(mode):
    st = _stage(shading=mode, temporal_smoothing=0.0)
    out = st.process(_frame(plane_light())).results["shading"]
    assert out.method == mode
    assert out.irradiance.shape == (st.bundle.n_proxy, 3) and np.isfinite(out.irradiance).all()


def test_missing_plane_light_and_wrong_grid_are_frame_errors():
    st = _stage()
    f = Frame(
        seq=0,
        t_device_ns=0,
        t_host_ns=0,
        color=np.zeros((4, 4, 3), np.uint8),
        depth=None,
        intrinsics=Intrinsics(1, 1, 1, 1, 4, 4),
    )
    with pytest.raises(FrameError, match="plane_light"):
        st.process(f)
    with pytest.raises(FrameError, match=r"\[plane_light\] grid = 32"):
        st.process(_frame(plane_light(grid=16)))


def test_auto_falls_back_to_ambient_on_a_bad_bundle(tmp_path):
    st = _stage(bundle=str(tmp_path / "nope"), shading="auto")
    assert st.mode == "ambient"
    with pytest.raises(Exception, match="folder not found"):
        _stage(bundle=str(tmp_path / "nope"), shading="model")
