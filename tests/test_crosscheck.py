"""The ground truth against the path tracer Mitsuba 3 (an optional dependency, never imported by the
runtime or at import time of the package)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from illuminet.cli import main
from illuminet.models.crosscheck import CrosscheckUnavailable, load_mitsuba, run_crosscheck

from .conftest import REPO


def test_without_mitsuba_the_crosscheck_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba -> ImportError
    with pytest.raises(CrosscheckUnavailable, match=r"pip install 'illuminet\[groundtruth\]'"):
        load_mitsuba()
    assert main(["eval", "--crosscheck", "--crosscheck-scenes", "lamp_room"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "illuminet[groundtruth]" in err[0]


def test_mitsuba_is_not_imported_by_the_runtime_or_the_package():
    code = (
        "import sys\n"
        "import illuminet.cli, illuminet.pipeline, illuminet.models.camera_eval, illuminet.models.crosscheck\n"
        "from illuminet.cli import build_parser\n"
        "build_parser()\n"
        "from illuminet.hw.synthetic import open_url\n"
        "from illuminet.runtime.assets.objects import load_object\n"
        "src = open_url('synthetic://lamp?seed=1&size=160x100&frames=1')\n"
        "src.read()\n"
        "src.scene.true_object_shading(load_object('builtin:sphere', 'proxy'), src.scene.default_anchor())\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit')]\n"
        "assert not bad, bad\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]


@pytest.mark.slow
def test_ground_truth_with_bounce_agrees_with_the_path_tracer():
    pytest.importorskip("mitsuba")
    rep = run_crosscheck(("lamp_room",), vertices=150, spp=1024)
    r = rep["scenes"]["lamp_room"]
    # the in-house indirect light carries as much light as Mitsuba's, bounce by bounce
    assert 0.9 < r["indirect_ratio_vs_all"] < 1.1, r
    assert 0.9 < r["indirect_ratio_one_bounce"] < 1.1, r
    # per vertex: within Mitsuba's own noise plus a few per cent, far better than direct light alone
    assert r["rel_err_with_bounce"] < r["mitsuba_noise"] + 0.08, r
    assert r["rel_err_with_bounce"] < 0.3 * r["rel_err_direct_only"], r
    assert r["rel_err_with_bounce_down"] < 0.3 * r["rel_err_direct_only_down"], r
