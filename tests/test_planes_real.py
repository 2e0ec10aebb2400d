"""Planes on real OAK-D RGB-D frames (../shared/data/oakd_rgbd): the ground and the raised plate.

The recordings (6 devices x 10 frames, 640x360, uint16 mm depth aligned to colour) look down ~0.7 m
at a green ground with a raised white plate. Their depth is integer-disparity quantised (steps of
~17 mm at 0.7 m), so ``[planes] inlier_threshold_m = 0.045`` is used (a threshold smaller than a
step splits the ground into one plane per depth level). Intrinsics were not recorded; the data's
README gives fx = fy ~ 500-525, cx ~ 320, cy ~ 180.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from illuminet.runtime.config import apply_overrides, defaults
from illuminet.runtime.frame import Frame, Intrinsics, depth_from_mm
from illuminet.runtime.stages.anchor import AnchorStage
from illuminet.runtime.stages.plane_light import PlaneLightStage
from illuminet.runtime.stages.planes import PlaneStage

pytestmark = pytest.mark.shared_data

INTR = Intrinsics(512.0, 512.0, 319.5, 179.5, 640, 360)


def _frames(root: Path):
    for dev in sorted((root / "oakd_rgbd").iterdir()):
        for k in ("01", "05", "10"):
            d = dev / k
            if (d / "depth.png").is_file():
                depth = cv2.imread(str(d / "depth.png"), cv2.IMREAD_UNCHANGED)
                color = cv2.cvtColor(cv2.imread(str(d / "color.png")), cv2.COLOR_BGR2RGB)
                yield (
                    f"{dev.name}/{k}",
                    Frame(seq=0, t_device_ns=0, t_host_ns=0, color=color, depth=depth_from_mm(depth), intrinsics=INTR),
                )


def _cfg(**planes):
    return apply_overrides(
        defaults(), [("planes", "inlier_threshold_m", 0.045)] + [("planes", k, v) for k, v in planes.items()]
    )


def _ground_and_plate(planes):
    ground = max(planes, key=lambda p: p.area_m2)
    centre = [p for p in planes if p is not ground and p.inlier_mask[170:190, 310:330].mean() > 0.5]
    return ground, (centre[0] if centre else None)


def test_ground_and_plate_are_two_parallel_planes(shared_data, capsys):
    rows = []
    for name, frame in _frames(shared_data):
        planes = PlaneStage(_cfg()).process(frame).results["planes"]
        ground, plate = _ground_and_plate(planes)
        assert plate is not None, f"{name}: no plate found under the image centre ({len(planes)} planes)"
        ang = float(np.degrees(np.arccos(np.clip(abs(ground.normal @ plate.normal), -1, 1))))
        sep = float(ground.distance(plate.centroid))  # plate centroid above the ground
        rows.append((name, ang, sep, ground.offset, plate.offset))
    a = np.array([r[1] for r in rows])
    s = np.array([r[2] for r in rows])
    with capsys.disabled():
        print("\n  frame                        angle(deg)  plate above ground (m)")
        for name, ang, sep, *_ in rows:
            print(f"  {name:28s} {ang:8.2f}   {sep:8.4f}")
        print(
            f"  angle median {np.median(a):.2f} max {a.max():.2f} deg; "
            f"offset median {np.median(s) * 1000:.1f} mm (range {s.min() * 1000:.1f}-{s.max() * 1000:.1f})"
        )
    assert len(rows) == 18
    # Both found in every frame and one above the other by the same amount on every device.
    assert np.all((s > 0.10) & (s < 0.20)) and s.max() - s.min() < 0.015
    # Parallel: the recordings' ground is itself not planar to better than ~2-3 deg (fitting its left
    # and right halves separately differs by that much), so the per-frame bound is looser than the
    # 2 deg target; the median meets it. See docs/planes.md.
    assert np.median(a) <= 2.1, a
    assert a.max() <= 4.0, a


def test_plane_light_samples_the_real_plate(shared_data):
    """An 8x8 grid over the middle of the real plate: observed, finite, near-uniform."""
    cfg = apply_overrides(
        _cfg(),
        [
            ("anchor", "mode", "pixel"),
            ("anchor", "pixel", [290, 175]),
            ("plane_light", "grid", 8),
            ("plane_light", "extent_m", 0.09),
        ],
    )
    name, frame = next(_frames(shared_data))
    out = PlaneLightStage(cfg).process(AnchorStage(cfg).process(PlaneStage(cfg).process(frame)))
    a, pl = out.results["anchor"], out.results["plane_light"]
    _, plate = _ground_and_plate(out.results["planes"])
    assert a.plane_id == plate.id and not a.synthetic
    assert pl.exposure_source == "plane"  # these recordings carry no exposure metadata
    # ~45 % of the plate's pixels are clipped at 255 (white squares): clipped samples carry no
    # radiance and are dropped, so some cells fall below half coverage and are not observed
    assert pl.observed.mean() > 0.5, pl.observed.mean()
    e = pl.irradiance[pl.observed]
    assert np.all(np.isfinite(e)) and np.all(e > 0)
    lum = e @ [0.2126, 0.7152, 0.0722]
    # the plate's random black/white pattern averages out over cells: cell-to-cell spread is small
    assert np.std(lum) / np.mean(lum) < 0.15


@pytest.mark.parametrize("threshold", [0.03, 0.045])
def test_a_pixel_anchor_on_the_ground_stands_upright_on_it(shared_data, threshold):
    """Pixels on the ground near the picture's borders, where the stereo depth is worst (the left band
    measured ~0.95 m on ground 0.72 m away, a fitted phantom plane tilted 60 deg: the vase lay on its
    side). The object stands upright on the ground or the plate: a floor or table."""
    for name, frame in _frames(shared_data):
        for px in ([120, 300], [40, 60], [600, 330]):
            cfg = apply_overrides(
                _cfg(inlier_threshold_m=threshold), [("anchor", "mode", "pixel"), ("anchor", "pixel", px)]
            )
            out = AnchorStage(cfg).process(PlaneStage(cfg).process(frame))
            a, planes = out.results["anchor"], out.results["planes"]
            ground = max(planes, key=lambda p: p.area_m2)
            chosen = [p for p in planes if p.id == a.plane_id]
            assert chosen and chosen[0].label in ("floor", "table"), (name, px, [p.label for p in planes])
            tilt = float(np.degrees(np.arccos(np.clip(a.R[:, 1] @ ground.normal, -1, 1))))
            assert tilt < 5.0, (name, px, tilt)
