"""Offline jobs on Ray (illuminet/cluster.py): shards on a local Ray instance give the single-machine
result, a killed worker or a failing shard is retried, reported and resumed, and nothing imports Ray
without ``--ray``.

The Ray tests share one local instance (2 CPUs, no dashboard) for the module and shut it down at the
end; they skip when Ray is not installed (``pip install 'illuminet[cluster]'``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from illuminet import cluster
from illuminet.commands import datagen as datagen_cmd

from ._sessions import env

#: a tiny data set: 4 shards of 3 samples (seconds of work; Ray's start-up dominates)
N, SHARD = 12, 3


@pytest.fixture(scope="module")
def spec():
    from illuminet.models.datagen import data_spec

    return data_spec("builtin:bowl", seed=7, n_proxy=32, kinds=("indoor", "outdoor", "spatial"))


@pytest.fixture(scope="module")
def single(spec):
    """The single-machine path's arrays (one process, no Ray)."""
    return spec.generate(0, N)


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'illuminet[cluster]')")
    from ray import cloudpickle

    # the test's own shard functions travel by value: workers need not import the tests package
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        object_store_memory=100 * 1024 * 1024,
        logging_level="warning",
        log_to_driver=False,
    )
    try:
        yield ray
    finally:
        ray.shutdown()
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def _same(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k


def _run(shards, store, retries=2):
    return cluster.run_shards("datagen", shards, store, retries=retries, unit="sample", show_progress=False)


@pytest.mark.timeout(180)
def test_four_shards_on_local_ray_equal_the_single_machine_run(local_ray, spec, single, tmp_path):
    shards = datagen_cmd.job(spec, N, SHARD)
    assert len(shards) == 4
    store = cluster.ShardStore(tmp_path / "shards")
    summary = _run(shards, store)
    assert summary.complete and (summary.done, summary.failed, summary.retried, summary.items) == (4, 0, 0, N)
    merged = datagen_cmd.merge(store, shards)
    _same(merged, single)  # byte-identical arrays, whatever the split
    assert "4 shards: 4 done, 0 failed, 0 retried" in summary.line()
    # a restarted run finds every shard done and runs nothing
    again = _run(shards, store)
    assert (again.skipped, again.done) == (4, 0)


def _die_once(marker: str, spec, start: int, stop: int) -> dict:
    """Kill this worker process on the first attempt of the shard (the marker file remembers)."""
    if not os.path.exists(marker):
        with open(marker, "w") as f:
            f.write(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return datagen_cmd.shard_files(spec, start, stop)


@pytest.mark.timeout(180)
def test_a_worker_killed_mid_task_is_retried_and_the_output_is_identical(local_ray, spec, single, tmp_path):
    shards = datagen_cmd.job(spec, N, SHARD)
    marker = tmp_path / "killed-once"
    victim = shards[1]
    shards[1] = cluster.Shard(victim.key, _die_once, (str(marker), *victim.args), victim.items)
    store = cluster.ShardStore(tmp_path / "shards")
    summary = _run(shards, store)
    assert marker.is_file() and int(marker.read_text()) != os.getpid()  # a worker really died
    assert summary.complete and summary.retried == 1 and summary.failed == 0
    _same(datagen_cmd.merge(store, shards), single)


def _fails(spec, start: int, stop: int) -> dict:
    raise RuntimeError(f"no light for samples {start}..{stop}")


@pytest.mark.timeout(180)
def test_a_failing_shard_is_retried_then_reported_and_a_rerun_redoes_only_it(local_ray, spec, single, tmp_path):
    shards = datagen_cmd.job(spec, N, SHARD)
    bad = shards[2]
    broken = list(shards)
    broken[2] = cluster.Shard(bad.key, _fails, bad.args, bad.items)
    store = cluster.ShardStore(tmp_path / "shards")
    summary = _run(broken, store, retries=1)
    assert not summary.complete
    assert (summary.done, summary.failed, summary.retried) == (3, 1, 1)
    assert "RuntimeError: no light for samples 6..9" in summary.errors[bad.key]
    assert "no light" in (store.root / cluster.ERRORS / f"{bad.key}.txt").read_text()
    with pytest.raises(cluster.JobFailed, match="run the same command again") as e:
        cluster.finish(summary, store, stream=open(os.devnull, "w"))
    assert e.value.exit_code == 1
    # what was written stays; the rerun computes the failed shard only
    kept = {s.key: (store.path(s.key) / "data.npz").stat().st_mtime_ns for s in shards if s is not bad}
    again = _run(shards, store)
    assert (again.skipped, again.done, again.failed) == (3, 1, 0) and again.complete
    assert kept == {k: (store.path(k) / "data.npz").stat().st_mtime_ns for k in kept}
    assert not (store.root / cluster.ERRORS / f"{bad.key}.txt").exists()
    _same(datagen_cmd.merge(store, shards), single)


def _eval_report(path) -> dict:
    import json

    r = json.loads(path.read_text())
    r.pop("eval_wall_s", None)
    if "camera" in r:
        r["camera"].pop("wall_s", None)
    return r


def _single_machine_eval(args: list[str], out) -> dict:
    """``illuminet eval`` without Ray, in a process with one BLAS thread: what a Ray task has (Ray sets
    OMP_NUM_THREADS=1 for a 1-CPU task); with more threads, BLAS sums the camera suites' least-squares
    fits in another order and the last bits of those metrics differ (docs/cluster.md)."""
    e = env()
    e["OMP_NUM_THREADS"] = "1"
    r = subprocess.run(
        [sys.executable, "-m", "illuminet", "eval", *args, "--out", str(out)],
        capture_output=True,
        text=True,
        env=e,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return _eval_report(out / "eval.json")


EVAL_CAMERA = ["--bundle", "builtin:bowl", "--cases", "0", "--camera-suites", "lamp,cluttered"]
EVAL_CAMERA += ["--camera-scenes", "1", "--camera-frames", "2", "--vertices", "60", "--no-figure", "--hdr", ""]


@pytest.mark.timeout(300)
def test_camera_eval_on_ray_gives_the_single_machine_metrics(local_ray, tmp_path):
    from illuminet.cli import main

    single = _single_machine_eval(EVAL_CAMERA, tmp_path / "single")
    assert main(["eval", *EVAL_CAMERA, "--out", str(tmp_path / "ray"), "--ray"]) == 0
    assert _eval_report(tmp_path / "ray" / "eval.json") == single  # every metric exactly equal
    assert not (tmp_path / "ray" / "shards").exists()  # merged, then removed


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_lighting_and_camera_eval_on_ray_give_the_single_machine_report(local_ray, tmp_path):
    from illuminet.cli import main

    args = ["--bundle", "builtin:vase", "--cases", "2", "--flicker-scenes", "1", "--camera-scenes", "2"]
    args += ["--camera-frames", "2", "--camera-suites", "indoor,lamp", "--vertices", "100", "--no-figure", "--hdr", ""]
    single = _single_machine_eval(args, tmp_path / "single")
    assert main(["eval", *args, "--out", str(tmp_path / "ray"), "--ray"]) == 0
    assert _eval_report(tmp_path / "ray" / "eval.json") == single


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_catalogue_trained_on_ray_gives_the_same_bundles(local_ray, tmp_path):
    pytest.importorskip("jax")
    pytest.importorskip("onnx")
    from illuminet.cli import main

    args = ["train", "--objects", "builtin:bowl,builtin:sphere", "--preset", "tiny", "--hdr", "", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "single")]) == 0
    assert main([*args, "--out", str(tmp_path / "ray"), "--ray"]) == 0
    for name in ("bowl", "sphere"):
        a, b = tmp_path / "single" / name, tmp_path / "ray" / name
        for f in ("transfer_fp32.onnx", "transfer_int8.onnx"):
            assert (a / f).read_bytes() == (b / f).read_bytes(), (name, f)
        with np.load(a / "mesh.npz") as za, np.load(b / "mesh.npz") as zb:
            assert all(np.array_equal(za[k], zb[k]) for k in za.files)
        assert (b / "work" / "log.jsonl").is_file() and (b / "bundle.json").is_file()
    # a rerun finds both bundles and trains nothing
    assert main([*args, "--out", str(tmp_path / "ray"), "--ray"]) == 0


def test_store_refuses_another_jobs_folder_and_half_written_shards_are_not_done(tmp_path):
    store = cluster.ShardStore(tmp_path / "s")
    store.check_job({"job": "datagen", "seed": 1})
    store.check_job({"job": "datagen", "seed": 1})  # the same job: fine
    with pytest.raises(cluster.ShardStoreError, match="different seed"):
        store.check_job({"job": "datagen", "seed": 2})
    (tmp_path / "s" / "k").mkdir()
    (tmp_path / "s" / "k" / "data.npz").write_bytes(b"partial")  # a crash before the marker
    assert not store.is_done("k")
    store.write("k", {"data.npz": b"full", "sub/x.json": b"{}"}, {"seconds": 1})
    assert store.is_done("k") and store.read("k", "data.npz") == b"full"
    assert not [p for p in (tmp_path / "s").rglob("*") if ".tmp-" in p.name]
    with pytest.raises(ValueError):
        store.write("k2", {"../escape": b""})


def test_the_jobs_progress_line_and_summary():
    import io

    from illuminet.progress import StatusLine, format_job

    out = io.StringIO()
    line = StatusLine(out, enabled=True, formatter=format_job)
    snap = {"name": "datagen", "unit": "sample", "finished": 3, "total": 8, "running": 2}
    line.update({**snap, "failed": 0, "retried": 1, "items": 750, "elapsed_s": 12.34})
    line.close()
    assert "datagen: 3/8 shards  2 running  0 failed  1 retried  750 samples  12.3 s" in out.getvalue()
    s = cluster.JobSummary("datagen", "sample", total=8, skipped=2, done=6, retried=1, items=1500, wall_s=10.0)
    s.task_s = 19.0
    assert s.complete and s.line().endswith(
        "8 shards: 6 done (+2 from an earlier run), 0 failed, 1 retried, wall 10.0 s, 1500 samples at 150 "
        "samples/s, tasks busy 19.0 s (1.90 in parallel on average)"
    )


def test_a_catalogue_is_a_folder_a_list_file_or_specs(tmp_path):
    from illuminet.commands.train import catalogue

    shop = tmp_path / "shop"
    (shop / "sub").mkdir(parents=True)
    for name in ("chair.obj", "lamp.GLB", "notes.txt", "sub/cup.ply"):
        (shop / name).write_text("")
    assert catalogue(str(shop)) == [("chair", str(shop / "chair.obj")), ("lamp", str(shop / "lamp.GLB"))]
    listing = shop / "list.txt"
    listing.write_text("builtin:vase  # the shipped one\n\nsub/cup.ply\n")
    assert catalogue(str(listing)) == [("vase", "builtin:vase"), ("cup", str(shop / "sub" / "cup.ply"))]
    assert catalogue("builtin:bowl, builtin:sphere") == [("bowl", "builtin:bowl"), ("sphere", "builtin:sphere")]
    for bad, msg in (
        ("builtin:teapot", "unknown built-in object"),
        (str(shop / "missing.obj"), "no such mesh file"),
        (f"{shop / 'chair.obj'},{shop / 'sub'}/../chair.obj", "same folder"),
        ("", "the list names no objects"),  # was Path('') = the current folder: or --objects '' trained a vase
        (",,", "the list names no objects"),  # was "0 objects: 0 trained", exit 0
        (" , ", "the list names no objects"),
    ):
        with pytest.raises(cluster.JobError, match=msg) as e:
            catalogue(bad)
        assert e.value.exit_code == 2


def test_train_refuses_a_bundle_of_another_configuration(tmp_path):
    import json

    from illuminet.commands.train import _trained
    from illuminet.models.train import make_config

    tcfg = make_config("tiny", object="builtin:bowl", seed=0)
    (tmp_path / "bowl").mkdir()
    assert not _trained(tmp_path / "bowl", tcfg)
    meta = {"training": {"config": json.loads(json.dumps(tcfg.to_dict()))}}
    (tmp_path / "bowl" / "bundle.json").write_text(json.dumps(meta))
    assert _trained(tmp_path / "bowl", tcfg)  # done: skipped by a rerun
    with pytest.raises(cluster.JobError, match=r"another configuration \(epochs_gae\): delete it"):
        _trained(tmp_path / "bowl", make_config("tiny", object="builtin:bowl", seed=0, epochs_gae=3))


def test_train_out_must_be_new_empty_or_its_own_output(tmp_path):
    # train wrote bundle.json, mesh.npz, *.onnx and work/ into any folder, package sources included
    import json

    from illuminet.commands.train import check_bundle_out, check_catalogue_out

    from .conftest import REPO

    check_bundle_out(tmp_path / "new", "builtin:bowl")
    (tmp_path / "empty").mkdir()
    check_bundle_out(tmp_path / "empty", "builtin:bowl")
    own = tmp_path / "cat" / "bowl"  # an interrupted run: no bundle.json yet
    (own / "work").mkdir(parents=True)
    for name in ("work/data_train.npz", "work/gae_plane.npz", "work/log.jsonl", "mesh.npz", ".mesh.npz.tmp-12"):
        (own / name).write_bytes(b"")
    check_bundle_out(own, "builtin:bowl")
    (own / "bundle.json").write_text(json.dumps({"object": "builtin:bowl"}))
    check_bundle_out(own, "builtin:bowl")
    check_bundle_out(REPO / "models" / "bundles" / "vase", "builtin:vase")  # the shipped bundle: retrained in place
    check_catalogue_out(tmp_path / "cat", [("bowl", "builtin:bowl"), ("sphere", "builtin:sphere")])
    check_catalogue_out(REPO / "models" / "bundles", [("vase", "builtin:vase")])
    for folder, spec, msg in (
        (own, "builtin:vase", "holds a bundle of 'builtin:bowl', not 'builtin:vase'"),
        (REPO / "runtime", "builtin:bowl", r"holds .*__init__\.py"),  # a package source folder
        (REPO / "models", "builtin:bowl", r"holds .*__init__\.py"),
    ):
        with pytest.raises(cluster.JobError, match=msg) as e:
            check_bundle_out(folder, spec)
        assert e.value.exit_code == 2 and "choose another --out" in str(e.value)
    (own / "work" / "notes.txt").write_text("mine")
    with pytest.raises(cluster.JobError, match="holds work/notes.txt: expected a new or empty folder"):
        check_bundle_out(own, "builtin:bowl")
    with pytest.raises(cluster.JobError, match="holds bowl/: expected a new or empty folder, or one holding only"):
        check_catalogue_out(tmp_path / "cat", [("bowl", "builtin:bowl")])
    (own / "work" / "notes.txt").unlink()
    (tmp_path / "cat" / "keep.txt").write_text("mine")
    with pytest.raises(cluster.JobError, match="holds keep.txt: expected a new or empty folder"):
        check_catalogue_out(tmp_path / "cat", [("bowl", "builtin:bowl")])
    (tmp_path / "cat" / "keep.txt").unlink()
    with pytest.raises(cluster.JobError, match="bowl holds a bundle of 'builtin:bowl', not 'builtin:vase'"):
        check_catalogue_out(tmp_path / "cat", [("bowl", "builtin:vase")])


_NO_RAY = """
import sys
from illuminet.cli import main
rc = main(sys.argv[1:])
assert 'ray' not in sys.modules, 'ray was imported'
print('no-ray-ok', rc)
"""


@pytest.mark.timeout(120)
def test_without_ray_flag_nothing_imports_ray(tmp_path):
    out = tmp_path / "d.npz"
    args = ["datagen", "--object", "builtin:bowl", "--samples", "3", "--n-proxy", "16", "--hdr", "", "--quiet"]
    r = subprocess.run(
        [sys.executable, "-c", _NO_RAY, *args, "--out", str(out)],
        capture_output=True,
        text=True,
        env=env(),
        timeout=110,
    )
    assert r.returncode == 0 and "no-ray-ok 0" in r.stdout, r.stderr
    assert out.is_file()


_RAY_MISSING = """
import sys
sys.modules['ray'] = None  # as if Ray were not installed: `import ray` raises ImportError
from illuminet.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.timeout(120)
def test_ray_flag_without_ray_installed_says_how_to_install_it(tmp_path):
    args = ["datagen", "--object", "builtin:bowl", "--samples", "3", "--n-proxy", "16", "--hdr", "", "--ray"]
    r = subprocess.run(
        [sys.executable, "-c", _RAY_MISSING, *args, "--out", str(tmp_path / "d.npz")],
        capture_output=True,
        text=True,
        env=env(),
        timeout=110,
    )
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("illuminet:")]
    assert lines == [lines[0]] and "pip install 'illuminet[cluster]'" in lines[0], r.stderr
