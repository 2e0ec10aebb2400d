"""``illuminet bench soak``: runs with real MJPEG and estimate clients and prints its figures (a few seconds)."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

from illuminet.bench.soak import heap_mb, rise_by_thirds, slope_mb_per_min
from illuminet.cli import main

from .conftest import REPO


def test_slope_is_the_least_squares_line_in_mb_per_minute():
    t = np.arange(0, 600, 1.0)
    assert slope_mb_per_min(t, 300 + 0.5 * t / 60) == pytest.approx(0.5)
    assert np.isnan(slope_mb_per_min(t[:2], t[:2]))


def test_rise_by_thirds_tells_a_leak_from_a_plateau_through_the_swings():
    t = np.arange(0.0, 1800.0)
    swing = 8.0 * (np.sin(t / 7.0) > 0.6)  # the allocator returning and re-taking 8 MB, often
    leak = 300 + 0.5 * t / 60 + swing
    assert rise_by_thirds(t, leak) == pytest.approx([0.5, 0.5, 0.5], abs=0.05)
    plateau = 300 + 20 * (1 - np.exp(-t / 300)) + swing
    first, second, third = rise_by_thirds(t, plateau)
    assert first > 1.5 and second < 0.4 and third < 0.05
    step = 300 + 15.0 * (t > 1500) + swing  # one late step: all of it in the last third
    assert rise_by_thirds(t, step) == pytest.approx([0.0, 0.0, 15.0 / ((1750 - 1250) / 60)], abs=0.3)
    assert np.isnan(rise_by_thirds(t[:10], leak[:10])).all()


def test_heap_figures_follow_a_real_allocation_and_its_release():
    before = heap_mb()
    if before is None:
        pytest.skip("the C library is not glibc >= 2.33 (no mallinfo2): the soak prints RSS only")
    # 64 blocks of 256 kB: below glibc's largest mmap threshold once raised, so they may come from the
    # heap or be mmapped; either way they are in use
    blocks = [np.ones(256 * 1024 // 8) for _ in range(64)]
    during = heap_mb()
    assert during[0] - before[0] >= 15.0, (before, during)
    assert during[2] >= during[0] + during[1] - 1.0  # the heap holds what is in use and what is free in it
    del blocks
    after = heap_mb()
    assert during[0] - after[0] >= 15.0, (during, after)


def test_soak_runs_briefly_and_prints_its_figures(gl, capsys):
    assert main(["bench", "soak", "--minutes", "0.1"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"RSS slope: ([+-][0-9.]+) MB/min after warm-up; target <= 0.1 MB/min", out)
    assert m, out
    frames = int(re.search(r"frames: (\d+) in", out).group(1))
    mjpeg = int(re.search(r"clients: (\d+) MJPEG frames", out).group(1))
    events = int(re.search(r"MJPEG frames \([0-9.]+ MB\), (\d+) estimate events", out).group(1))
    assert frames > 0 and mjpeg > 0 and events > 0, out
    assert re.search(r"per-frame loop time median [0-9.]+ ms, p99 [0-9.]+ ms", out)
    assert "failures: 0 " in out, out
    if heap_mb() is not None:
        assert re.search(r"where \(glibc heap, slope after warm-up, MB/min\): in use [+-][0-9.]+ \(a leak\)", out), out


def test_soak_refuses_a_bad_duration(capsys):
    for bad in ("0", "-1", "nan", "inf"):
        assert main(["bench", "soak", "--minutes", bad]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and "--minutes" in lines[0], lines


def test_bench_refuses_bad_counts_in_one_line_before_running(capsys):
    """`bench demo --frames -3` once crashed with a traceback in the table printer; `--rounds 0` was
    silently the default. Each is refused at once, naming the flag."""
    for argv in (
        ["demo", "--frames", "-3"],
        ["demo", "--rounds", "0"],
        ["odometry", "--look", "-1"],
        ["demo", "--size", "abc"],
    ):
        assert main(["bench", *argv]) == 2, argv
        out, err = capsys.readouterr()
        err = [ln for ln in err.splitlines() if ln.strip()]
        assert len(err) == 1 and argv[1] in err[0] and "expected" in err[0], (argv, err)
        if argv[1] == "--size":
            assert "# machine" not in out  # refused before the header (it came after it)


def test_bench_refuses_a_json_path_it_cannot_write_before_running(tmp_path, capsys):
    """`bench transfer --json /missing/x.json` ran the benchmark, printed its figures, then ended in a
    FileNotFoundError traceback (a folder: IsADirectoryError), losing the JSON. Refused at the start now."""
    for target, says in ((tmp_path / "missing" / "x.json", "does not exist"), (tmp_path, "it is a folder")):
        assert main(["bench", "transfer", "--quick", "--json", str(target)]) == 2
        out, err = capsys.readouterr()
        assert "# machine" not in out  # nothing ran
        err = [ln for ln in err.splitlines() if ln.strip()]
        assert len(err) == 1 and "--json" in err[0] and says in err[0], err


@pytest.mark.parametrize(
    "argv,flag",
    [
        (["--quick", "--frames", "-1"], "--frames"),  # demo's flag: replay..render ran first (over 60 s)
        (["replay", "--minutes", "-1"], "--minutes"),  # soak's flag, soak not named: silently ignored
        (["replay", "--fps", ""], "--fps"),  # '' read as not given: the default rates
        (["replay", "--json", ""], "--json"),  # '' read as not given: no JSON, exit 0
        (["replay", "--size", ""], "--size"),
        (["replay", "--pipeline", ","], "--pipeline"),
    ],
)
def test_every_bench_flag_is_checked_before_the_first_benchmark(argv, flag):
    """Each benchmark checked its own flags only when it started: `bench --quick --frames -1` ran the
    benchmarks before demo for minutes, then refused. Now refused before the header, in a few seconds."""
    r = subprocess.run(
        [sys.executable, "-m", "illuminet", "bench", *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "# machine" not in r.stdout and "==" not in r.stdout, r.stdout
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and flag in err[0] and "expected" in err[0] and "Traceback" not in r.stderr, err
