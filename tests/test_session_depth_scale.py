"""Session format version 2: depth stored at 1/k of the colour size, upsampled nearest on replay."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from illuminet.hw import open_source
from illuminet.runtime.config import defaults
from illuminet.runtime.stream.session import CorruptFrame, SessionError, SessionReader, SessionWriter

from ._sessions import H, W, frames, make_session


def _set_manifest(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m.update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


def _nearest_up(mm: np.ndarray, k: int) -> np.ndarray:
    return np.repeat(np.repeat(mm, k, axis=0), k, axis=1)


def test_depth_scale_round_trip_is_nearest_and_keeps_holes(tmp_path):
    fs = frames(3)
    # a hole on a stored sample (top-left of its 2x2 block) must stay a hole over the whole block
    d = fs[0].depth.copy()
    d[10, 20] = 0.0
    fs[0] = fs[0].replace(depth=d)
    with SessionWriter(tmp_path / "v2", source="test://x", color="png", depth_scale=2, meta={"seed": 7}) as w:
        for f in fs:
            w.append(f)
    r = SessionReader(tmp_path / "v2", strict=True)
    assert r.problems == [] and r.manifest["version"] == 2
    assert r.manifest["depth"] == {"encoding": "png16", "unit": "mm", "scale": 2}
    assert r.manifest["meta"] == {"seed": 7} and r.depth_scale == 2
    stored = cv2.imread(str(tmp_path / "v2" / "frames" / "000000.depth.png"), cv2.IMREAD_UNCHANGED)
    assert stored.shape == (H // 2, W // 2) and stored.dtype == np.uint16
    for f, g in zip(fs, r):
        assert g.depth.shape == (H, W) and g.depth.dtype == np.float32
        assert np.array_equal(g.color, f.color)  # colour is untouched by the depth scale
        mm = np.rint(f.depth[::2, ::2] * 1000.0).astype(np.uint16)
        np.testing.assert_array_equal(g.depth, _nearest_up(mm, 2).astype(np.float32) * np.float32(1e-3))
    first = r.read(0)
    assert (first.depth[10:12, 20:22] == 0).all()
    assert r.check() == []


def test_scale_one_still_writes_version_1(tmp_path):
    make_session(tmp_path / "s", n=2, depth_scale=1)
    m = json.loads((tmp_path / "s" / "manifest.json").read_text())
    assert m["version"] == 1 and "scale" not in m["depth"]


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_writer_refuses_bad_depth_scale(tmp_path, bad):
    with pytest.raises(ValueError, match="depth_scale: expected an int >= 1"):
        SessionWriter(tmp_path / "s", depth_scale=bad)


def test_writer_refuses_a_scale_that_does_not_divide_the_size(tmp_path):
    w = SessionWriter(tmp_path / "s", depth_scale=5)  # 64x48: 64 is not a multiple of 5
    with pytest.raises(SessionError, match=r"depth_scale 5 does not divide the (colour|depth) size 64x48"):
        w.append(frames(1)[0])
    w.close()


def test_writer_refuses_bad_depth_compression_and_meta(tmp_path):
    with pytest.raises(ValueError, match="depth_png_compression"):
        SessionWriter(tmp_path / "a", depth_png_compression=10)
    with pytest.raises(ValueError, match="meta"):
        SessionWriter(tmp_path / "b", meta={"x": object()})


@pytest.mark.parametrize(
    "scale, version, message",
    [
        (3, 2, r"'depth.scale': 3 does not divide the image size 64x48"),
        (0, 2, r"'depth.scale': expected an int >= 1, got 0"),
        (2.0, 2, r"'depth.scale': expected an int >= 1, got 2.0"),
        ("2", 2, r"'depth.scale': expected an int >= 1, got '2'"),
        (2, 1, r"'depth.scale' needs format version 2, the manifest says version 1"),
    ],
)
def test_reader_names_a_bad_depth_scale(tmp_path, scale, version, message):
    make_session(tmp_path / "s", n=2, depth_scale=2)
    m = json.loads((tmp_path / "s" / "manifest.json").read_text())
    _set_manifest(tmp_path / "s", version=version, depth=dict(m["depth"], scale=scale))
    with pytest.raises(SessionError, match=message):
        SessionReader(tmp_path / "s")


def test_depth_file_at_the_wrong_scale_is_a_corrupt_frame(tmp_path):
    make_session(tmp_path / "s", n=3, depth_scale=2)
    # replace frame 1's depth with a full-size PNG: the index size must match too, so rewrite both
    p = tmp_path / "s" / "frames" / "000001.depth.png"
    ok, buf = cv2.imencode(".png", np.full((H, W), 1500, np.uint16))
    p.write_bytes(buf.tobytes())
    lines = (tmp_path / "s" / "frames.jsonl").read_text().splitlines()
    d = json.loads(lines[1])
    d["depth_bytes"] = len(buf)
    lines[1] = json.dumps(d)
    (tmp_path / "s" / "frames.jsonl").write_text("\n".join(lines) + "\n")
    r = SessionReader(tmp_path / "s")
    with pytest.raises(
        CorruptFrame, match=r"size mismatch: image is 64x48, the manifest says 64x48 / depth.scale 2 = 32x24"
    ):
        r.read(1)
    assert len(r.check()) == 1


def test_replay_source_delivers_depth_at_colour_size(tmp_path):
    make_session(tmp_path / "s", n=4, depth_scale=2)
    with open_source(f"replay://{tmp_path / 's'}?timing=asap", defaults()) as src:
        got = [src.read() for _ in range(4)]
        assert src.read() is None
    assert all(f.depth.shape == f.color.shape[:2] == (H, W) for f in got)
    assert all((f.depth[::2, ::2] == f.depth[1::2, 1::2]).all() for f in got)
