"""The end-to-end camera suites of ``illuminet eval``: variants, every suite and column, the oracles."""

from __future__ import annotations

import json

import numpy as np
import pytest

from illuminet.cli import main
from illuminet.models.camera_eval import BASELINES, SUITES, parse_variant, shading_metrics
from illuminet.runtime.config import ConfigError


def test_variants_parse_with_toml_values():
    v = parse_variant('pinned:anchor.point=[0.1, 0.3, 1.5],model.shading="sh", plane_light.extra_planes=2')
    assert v.name == "pinned"
    assert v.overrides == [
        ("anchor", "point", [0.1, 0.3, 1.5]),
        ("model", "shading", "sh"),
        ("plane_light", "extra_planes", 2),
    ]
    for bad in ("nocolon", ":model.shading=sh", "x:model_shading=sh"):
        with pytest.raises(ConfigError):
            parse_variant(bad)


def test_metrics_are_blind_to_scale_only_where_they_say_so():
    rng = np.random.default_rng(0)
    t = rng.uniform(0.5, 2.0, (50, 3))
    m = shading_metrics(3.0 * t, t, k=0.2)
    assert m["mae"] < 1e-9 and m["rmse_lin"] < 1e-9 and m["mae_abs"] > 0.05


@pytest.fixture(scope="module")
def ci_run(tmp_path_factory):
    """The CI-sized run: 1 scene per suite, 3 frames, 300 vertices, one extra variant."""
    out = tmp_path_factory.mktemp("eval")
    rc = main(
        [
            "eval",
            "--bundle",
            "builtin:bowl",
            "--cases",
            "0",
            "--camera-scenes",
            "1",
            "--camera-frames",
            "3",
            "--vertices",
            "300",
            "--out",
            str(out),
            "--variant",
            "nosmooth:model.temporal_smoothing=0",
        ]
    )
    assert rc == 0
    return json.loads((out / "eval.json").read_text()), (out / "eval.md").read_text()


def test_every_suite_and_column_is_reported(ci_run, capsys):
    report, md = ci_run
    cam = report["camera"]
    assert list(cam["suites"]) == list(SUITES)
    for header in ("MAE", "RMSE", "MAE (no gain)", "angle (deg)", "chroma (deg)", "flicker"):
        assert f"| {header} |" in md
    for suite, res in cam["suites"].items():
        assert res["_scenes"]["evaluated"] == 1, suite
        for m in ("ours", "nosmooth") + BASELINES:
            r = res[m]
            for key in ("mae", "rmse", "mae_abs", "rmse_lin", "chroma"):
                assert r[key] is not None and np.isfinite(r[key]), (suite, m, key)
            assert f"| {suite} | " in md
        for m in ("model", "sh_rgbd", "oracle_sh", "oracle_prt"):
            assert res[m]["angle"] is not None, (suite, m)
        # the estimate reports no primary light when none dominates (then it has no angle)
        for m in ("ours", "nosmooth"):
            assert res[m]["angle"] is None or 0.0 <= res[m]["angle"] <= 180.0, (suite, m)
        for m in ("ours", "nosmooth", "model", "constant", "ambient", "sh_rgbd"):
            assert res[m]["flicker"] is not None, (suite, m)
        # the chain's default shading (PRT lit by the light estimate) is not the learned transfer
        assert res["ours"]["mae"] != pytest.approx(res["model"]["mae"])
        # without temporal smoothing the estimate moves more from frame to frame
        assert res["nosmooth"]["flicker"] >= res["ours"]["flicker"] - 1e-6


def test_an_oracle_is_never_worse_than_its_fitted_baseline(ci_run):
    cam = ci_run[0]["camera"]
    for suite, res in cam["suites"].items():
        # on the criterion the oracles minimise, by construction (any lambda of the fit is a candidate)
        assert res["oracle_sh"]["rmse_lin"] <= res["sh_rgbd"]["rmse_lin"] + 1e-12, suite
        assert res["oracle_prt"]["rmse_lin"] <= res["sh_rgbd_prt"]["rmse_lin"] + 1e-12, suite
        # and on the reported sRGB error too
        assert res["oracle_sh"]["mae"] <= res["sh_rgbd"]["mae"], suite
        assert res["oracle_prt"]["mae"] <= res["sh_rgbd_prt"]["mae"], suite
        # the zonal oracle is the PRT oracle on a subspace: never better on its criterion
        assert res["oracle_prt"]["rmse_lin"] <= res["oracle_prt_zonal"]["rmse_lin"] + 1e-12, suite


def test_the_zonal_basis_is_symmetric_about_up():
    from illuminet.models.camera_eval import ZONAL_BASIS
    from illuminet.runtime.sh import sh9

    rng = np.random.default_rng(0)
    w = rng.normal(size=(500, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    # rotating every direction about y leaves each zonal function unchanged
    a = 0.7
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    f, g = sh9(w) @ ZONAL_BASIS, sh9(w @ R.T) @ ZONAL_BASIS
    np.testing.assert_allclose(f, g, atol=1e-9)
    np.testing.assert_allclose(ZONAL_BASIS.T @ ZONAL_BASIS, np.eye(3), atol=1e-12)
    # and it holds the band-2 part: a light from straight above is not zonal in band 1 alone
    assert np.ptp(f[:, 2]) > 0.5


def test_a_variant_with_an_unknown_key_fails_before_any_scene(capsys):
    rc = main(["eval", "--cases", "0", "--camera-scenes", "1", "--variant", "x:model.no_such_key=false"])
    assert rc == 2
    assert "[model] unknown key 'no_such_key'" in capsys.readouterr().err


def test_the_truth_lights_the_object_by_itself_at_the_drawn_albedo(ci_run):
    report, md = ci_run
    assert report["camera"]["object_albedo"] == pytest.approx(0.8)
    assert "the object's light onto itself (albedo 0.8)" in md


def test_a_bad_object_albedo_is_one_line(capsys):
    rc = main(["eval", "--cases", "0", "--camera-scenes", "1", "--object-albedo", "1.5"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--object-albedo: expected a number in [0, 1), got 1.5" in err[0]


def test_primary_angle_counts_only_scenes_a_primary_light_dominates(ci_run):
    report, md = ci_run
    assert "| angle, primary >= 40 % (deg) |" in md and "primary light carries >= 40 %" in md
    for suite, res in report["camera"]["suites"].items():
        n = res["_primary_scenes"]
        assert n in (0, 1), suite
        for m in ("ours", "oracle_prt", "model"):
            # one scene per suite: the column is that scene's angle when its primary light dominates
            assert res[m]["angle_primary"] == (res[m]["angle"] if n else None), (suite, m)
    # a lamp 0.3-0.7 m from the object gives most of its light; 32 room lights never do
    assert report["camera"]["suites"]["lamp"]["_primary_scenes"] == 1
    assert report["camera"]["suites"]["indoor"]["_primary_scenes"] == 0


def test_primary_share_is_the_direct_share_of_the_strongest_light():
    """The lamp of a `lamp` scene: a share of the direct light, counted with the object's own shadowing."""
    import trimesh

    from illuminet.hw.synthetic.scene import build_scene
    from illuminet.models.camera_eval import primary_share

    sc = build_scene("lamp", seed=1, frames=2, bounce=0)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    mesh.apply_translation([0, 0.1, 0])
    T = sc.default_anchor(0)
    pts, nrm = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    e = sc.true_object_shading(mesh, T, frame=0, points=pts, normals=nrm)
    share = primary_share(sc, mesh, T, 0, np.array([0, 0.1, 0]), pts, nrm, e)
    direct = sc.true_object_shading(mesh, T, frame=0, points=pts, normals=nrm, indirect=False)
    luma = np.array([0.2126, 0.7152, 0.0722])
    direct_share = float((direct @ luma).sum() / (e @ luma).sum())
    # the lamp dominates a dim set of room lights: most, not all, of the direct light is the lamp's
    assert len(sc.object_lights(T, 0).positions) > 1
    assert 0.4 < share < direct_share <= 1.0 + 1e-9


def test_the_look_around_suite_is_the_outdoor_scenes_after_a_turn_and_runs_when_named(capsys):
    from illuminet.models.camera_eval import LOOK_SUITES, CameraEval
    from illuminet.pipeline import build_stages
    from illuminet.runtime.config import defaults

    ev = CameraEval(defaults(), build_stages, "builtin:bowl")
    for i in (0, 3):  # the same scenes, seeds (and maps) as the outdoor suite, seen after a look around
        assert ev.url("outdoor_look", i, 0, 300) == ev.url("outdoor", i, 0, 300) + "&path=look"
    CameraEval.check(["outdoor_look"], 3)
    assert "outdoor_look" in LOOK_SUITES and "outdoor_look" not in SUITES  # not in the default run
    assert main(["eval", "--cases", "0", "--camera-scenes", "1", "--camera-suites", "outdoor_looks"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown camera suite(s) outdoor_looks" in err[0] and "outdoor_look" in err[0]
    # the outdoor scenes with boxes casting shadows in view: the same scenes, seeds and maps
    for i in (0, 3):
        assert ev.url("outdoor_boxes", i, 0, 30) == ev.url("outdoor", i, 0, 30) + "&boxes=3"
    CameraEval.check(["outdoor_boxes"], 3)
    assert "outdoor_boxes" not in SUITES


def test_eval_with_nothing_to_evaluate_is_refused(tmp_path, capsys):
    """`eval --bundle /nope --cases 0 --camera-scenes 0` returned 0 and wrote a report with a title only."""
    rc = main(["eval", "--bundle", "/nope", "--cases", "0", "--camera-scenes", "0", "--out", str(tmp_path / "ev")])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and "nothing to evaluate" in err[0] and "--camera-scenes N" in err[0], err
    assert not (tmp_path / "ev").exists()
