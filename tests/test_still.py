"""The still-camera test (runtime/stages/still.py) on real synthetic pictures shifted by known amounts."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from illuminet.runtime.stages.still import StillTest, coarse_sample, colour_thumbnail


@pytest.fixture(scope="module")
def picture():
    from illuminet.hw.synthetic import open_url

    src = open_url("synthetic://cluttered?seed=4&frames=1")
    src.open()
    f = src.read()
    src.close()
    return np.ascontiguousarray(f.color)


def _shift(img, dx, dy=0.0):
    M = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)


def _keyed(key, still_px=0.3, **kw):
    """A test whose key is ``key`` (a frame becomes the key only when the one before looked still too)."""
    t = StillTest(still_px, **kw)
    for _ in range(2):
        assert not t.check(coarse_sample(key), lambda: colour_thumbnail(key), key.shape[1])
        t.processed()
    return t


def _still_after(key, frame, still_px=0.3):
    t = _keyed(key, still_px)
    return t.check(coarse_sample(frame), lambda: colour_thumbnail(frame), frame.shape[1])


def test_sub_threshold_shifts_are_still_and_larger_ones_are_not(picture):
    assert _still_after(picture, picture)
    assert _still_after(picture, _shift(picture, 0.1))
    assert _still_after(picture, _shift(picture, 0.0, 0.1))
    for dx, dy in ((0.6, 0.0), (0.0, 0.6), (0.5, 0.5), (2.0, 0.0), (8.0, 3.0)):
        assert not _still_after(picture, _shift(picture, dx, dy)), (dx, dy)


def test_exposure_and_noise_are_not_motion(picture):
    rng = np.random.default_rng(0)
    brighter = np.clip(picture.astype(np.float32) + 6.0, 0, 255).astype(np.uint8)
    assert _still_after(picture, brighter)
    noisy = np.clip(picture + rng.normal(0, 2.0, picture.shape), 0, 255).astype(np.uint8)
    assert _still_after(picture, noisy)


def test_a_flat_picture_never_counts_as_still():
    flat = np.full((400, 640, 3), 128, np.uint8)
    t = StillTest(0.3)
    # no texture: motion cannot be seen, so nothing is held
    assert not any(t.check(coarse_sample(flat), lambda: colour_thumbnail(flat), 640) for _ in range(4))


def test_held_frames_are_counted_and_bounded(picture):
    t = _keyed(picture, max_frames=3)
    held = [t.check(coarse_sample(picture), lambda: colour_thumbnail(picture), picture.shape[1]) for _ in range(5)]
    assert held == [True, True, True, False, False] and t.still_frames == 3
    assert not StillTest(0.0).check(coarse_sample(picture), lambda: colour_thumbnail(picture), picture.shape[1])


def test_a_moving_camera_makes_no_thumbnail(picture):
    made = []

    def thumb(img):
        made.append(1)
        return colour_thumbnail(img)

    t = StillTest(0.3)
    for k in range(6):  # 6 px a frame: the coarse pre-check says "moving" every time
        f = _shift(picture, 6.0 * k)
        assert not t.check(coarse_sample(f), lambda f=f: thumb(f), f.shape[1])
        t.processed()
    assert not made
