"""``illuminet bench soak``: runs with real MJPEG and estimate clients and prints its figures (a few seconds)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from illuminet.bench.soak import slope_mb_per_min
from illuminet.cli import main


def test_slope_is_the_least_squares_line_in_mb_per_minute():
    t = np.arange(0, 600, 1.0)
    assert slope_mb_per_min(t, 300 + 0.5 * t / 60) == pytest.approx(0.5)
    assert np.isnan(slope_mb_per_min(t[:2], t[:2]))


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


def test_soak_refuses_a_bad_duration(capsys):
    for bad in ("0", "-1", "nan", "inf"):
        assert main(["bench", "soak", "--minutes", bad]) == 2
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(lines) == 1 and "--minutes" in lines[0], lines
