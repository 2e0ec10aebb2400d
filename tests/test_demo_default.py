"""The demo's built-in default session: committed intact, small, regenerable per seed, and what the demo runs."""

from __future__ import annotations

import filecmp
import json

import cv2
import pytest

from illuminet.cli import main
from illuminet.commands.demo import (
    DEFAULT_SESSION,
    DEFAULT_SESSION_FRAMES,
    DEFAULT_SESSION_SEED,
    default_session_source_url,
    make_default_session,
)
from illuminet.runtime.stream.session import SessionReader

#: the committed session must stay small (git history)
MAX_BYTES = 8 * 1024 * 1024


def test_default_session_is_committed_intact_and_small(capsys):
    r = SessionReader(DEFAULT_SESSION, strict=True)
    assert r.problems == [] and r.finalized and len(r) == DEFAULT_SESSION_FRAMES
    assert (r.width, r.height) == (1280, 800) and r.color_encoding == "jpeg"
    assert r.manifest["version"] == 2 and r.depth_scale == 2  # 640x400 stereo depth
    meta = r.manifest["meta"]
    assert meta["seed"] == DEFAULT_SESSION_SEED and meta["source"] == default_session_source_url()
    assert "--make-default-session" in meta["generated_by"]
    size = sum(p.stat().st_size for p in DEFAULT_SESSION.rglob("*") if p.is_file())
    assert size <= MAX_BYTES, size
    # the CLI check decodes every frame
    assert main(["replay", str(DEFAULT_SESSION), "--check"]) == 0
    out = capsys.readouterr().out
    assert "v2, 1280x800" in out and "640x400" in out and f"{DEFAULT_SESSION_FRAMES} intact frames" in out


def test_make_default_session_is_deterministic_per_seed(tmp_path):
    a = make_default_session(tmp_path / "a", seed=5, frames=1)
    b = make_default_session(tmp_path / "b", seed=5, frames=1)
    for name in ("frames.jsonl", "frames/000000.color.jpg", "frames/000000.depth.png"):
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    # not the committed session's seed: a different room
    assert not filecmp.cmp(a / "frames/000000.color.jpg", DEFAULT_SESSION / "frames/000000.color.jpg", shallow=False)
    m = json.loads((a / "manifest.json").read_text())
    assert m["meta"]["seed"] == 5 and m["depth"]["scale"] == 2
    # never overwrites: a second run into the same folder is refused
    assert main(["demo", "--make-default-session", str(a), "--seed", "5"]) == 1


def test_make_default_session_reports_progress(tmp_path, capsys, monkeypatch):
    """`illuminet demo --make-default-session DIR` renders for ~35 s (32 frames at two sizes) and
    printed nothing until its last line: it said nothing of what it was doing or how long it takes."""
    seen = []
    make_default_session(tmp_path / "a", seed=5, frames=2, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(0, 2), (1, 2), (2, 2)]
    # the command says what it renders, how many frames and about how long, before the first frame
    import illuminet.commands.demo as demo

    real = demo.make_default_session
    monkeypatch.setattr(demo, "make_default_session", lambda path, **kw: real(path, frames=1, **kw))
    assert main(["demo", "--make-default-session", str(tmp_path / "b"), "--seed", "5"]) == 0
    err = capsys.readouterr().err
    assert "rendering 1 frames of synthetic://lamp?seed=5" in err and str(tmp_path / "b") in err
    # a refused folder gets its one line, not the announcement
    assert main(["demo", "--make-default-session", str(tmp_path / "b"), "--seed", "5"]) == 1
    err = capsys.readouterr().err
    assert "rendering" not in err and len(err.strip().splitlines()) == 1


def test_committed_session_matches_the_synthetic_camera_today():
    """The fast guard of the slow test below: the shipped session had been made before the synthetic
    camera's auto exposure changed (33.3 ms / ISO 127 per frame against 25.5 ms / ISO 100 now), so
    `--make-default-session` no longer gave its bytes and nobody noticed (the slow test is opt-in).
    Frame 0 of the session's source URL must have the committed exposure and picture."""
    from illuminet.hw import open_source

    with open_source(default_session_source_url()) as src:
        f = src.read()
    first = json.loads((DEFAULT_SESSION / "frames.jsonl").read_text().splitlines()[0])
    assert first["exposure"]["exposure_us"] == pytest.approx(f.exposure.exposure_us)
    assert first["exposure"]["iso"] == pytest.approx(f.exposure.iso)
    stored = cv2.cvtColor(cv2.imread(str(DEFAULT_SESSION / first["color"])), cv2.COLOR_BGR2RGB)
    assert abs(float(stored.mean()) - float(f.color.mean())) < 1.0  # the same picture, up to JPEG


@pytest.mark.slow
def test_committed_session_is_what_the_command_makes(tmp_path):
    out = make_default_session(tmp_path / "s")
    names = sorted(p.relative_to(DEFAULT_SESSION).as_posix() for p in (DEFAULT_SESSION / "frames").iterdir())
    assert names == sorted(p.relative_to(out).as_posix() for p in (out / "frames").iterdir())
    for name in names + ["frames.jsonl"]:
        assert filecmp.cmp(DEFAULT_SESSION / name, out / name, shallow=False), name


@pytest.mark.gl
def test_demo_runs_the_default_session(tmp_path, capsys, gl):
    out = tmp_path / "new" / "demo.mp4"  # a folder that does not exist yet (as out/ in a fresh checkout)
    rc = main(["demo", "--frames", "6", "--out", str(out), "--strict"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "demo: source replay://" in text and "demo_session" in text
    assert out.is_file() and out.stat().st_size > 1000
    still = tmp_path / "new" / "demo_still.png"
    img = cv2.imread(str(still))
    assert img is not None and img.shape == (800, 1280, 3)
    assert "shading: " in text and "radiance transfer" in text  # the default: PRT lit by the estimate
    for stage in ("stage:planes", "stage:plane_light", "stage:shading", "stage:render"):
        assert stage in text
    assert "failed frames 0" in text and "render: drawn=6" in text
    assert "peak resident memory:" in text


def test_seed_without_make_default_session_is_refused(capsys):
    assert main(["demo", "--seed", "4", "--no-video", "--still", ""]) == 2
    assert "--seed 4 only applies with --make-default-session" in capsys.readouterr().err
