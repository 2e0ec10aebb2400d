"""Is the camera still? A cheap test that lets a stage reuse its last result on a camera that did not move.

A camera on a tripod or a board on a desk shows the same picture frame after frame; re-tracking the
landmarks (odometry) or refitting the planes then only re-measures noise. :class:`StillTest` compares
a small grey thumbnail of the frame (1/8 of the colour size) with the one of the last frame the stage
really processed (its *key*): per image quadrant, one Lucas-Kanade step of a pure translation,
``(sum g g^T)^-1 sum g dI`` with ``g`` the key's gradient, says how far the picture moved. The frame
is *still* when every textured quadrant moved less than ``still_px`` colour pixels, at least two
quadrants have texture to tell, and the picture did not change beyond that (mean |dI| after its mean
below :data:`MAX_CHANGE` grey levels: a big motion or a person walking in is not linear in the
shift). A uniform brightness change (auto exposure) is not a motion. Because the comparison is with
the key, not the previous frame, a slow creep adds up until it is processed; and at least every
``max_frames`` frames the stage processes anyway.

Costs ~0.1 ms a frame (the thumbnail and 4 2x2 solves); the stages that use it: odometry
(``[anchor] still_px``) and plane tracking (``[planes] still_px``).
"""

from __future__ import annotations

import cv2
import numpy as np

#: thumbnail = the colour image downscaled by this factor (640x400 -> 80x50)
THUMB = 8
#: default threshold: the largest quadrant translation (colour-image pixels) still counted as still
STILL_PX = 0.3
#: the largest mean |change| of the thumbnail (grey levels, after its mean) for which the test holds
MAX_CHANGE = 2.0
#: a quadrant counts when its gradient matrix's smaller eigenvalue per sample exceeds this (grey^2): with the
#: thumbnail's noise (~0.25 grey levels from a sensor's ~2) the shift is then known to ~0.13 colour pixels
MIN_TEXTURE = 0.25
#: process at least every this many frames even while the picture stays still
MAX_FRAMES = 30
#: :func:`coarse_change` above this (grey levels) is a moving camera: no thumbnail is made (the
#: synthetic camera's noise gives 1.6-2.9 on a still view, its orbit 5-16; a noisier camera only
#: loses the saving: an error here costs time, never a wrong hold)
COARSE_MAX = 4.0


def thumbnail(grey: np.ndarray, factor: int) -> np.ndarray:
    """A grey image (uint8) downscaled by ``factor`` (area average), float32, at least 8x8."""
    h, w = grey.shape[:2]
    t = cv2.resize(grey, (max(w // factor, 8), max(h // factor, 8)), interpolation=cv2.INTER_AREA)
    return t.astype(np.float32)


def colour_thumbnail(color: np.ndarray) -> np.ndarray:
    """The test's thumbnail of an RGB uint8 picture: grey, area-averaged to 1/:data:`THUMB` (a picture
    wider than 640 is first subsampled to at most 640: 0.13 ms at 640x400, 0.29 ms at 1280x800)."""
    h, w = color.shape[:2]
    k = max(1, w // 640)
    c = np.ascontiguousarray(color)
    if k > 1:
        c = cv2.resize(c, (w // k, h // k), interpolation=cv2.INTER_NEAREST)
    grey = cv2.cvtColor(c, cv2.COLOR_RGB2GRAY)
    return thumbnail(grey, max(THUMB // k, 1))


def coarse_sample(image: np.ndarray, step: int = 16) -> np.ndarray:
    """Every ``step``-th pixel of an RGB or grey uint8 picture, grey, float32 (~20 us): a pre-check
    that tells a moving camera from a possibly still one before the thumbnail is made."""
    h, w = image.shape[:2]
    s = cv2.resize(np.ascontiguousarray(image), (max(w // step, 4), max(h // step, 4)), interpolation=cv2.INTER_NEAREST)
    if s.ndim == 3:
        s = cv2.cvtColor(s, cv2.COLOR_RGB2GRAY)
    return s.astype(np.float32)


def coarse_change(a: np.ndarray | None, b: np.ndarray) -> float:
    """Mean |change| (grey levels, after its mean) between two samples of one size: two
    :func:`coarse_sample` or two thumbnails (inf without ``a``)."""
    if a is None or a.shape != b.shape:
        return float("inf")
    d = b - a
    return float(np.abs(d - d.mean()).mean())


class StillTest:
    """Whether a frame shows the same picture as the stage's key frame (module docstring).

    Per frame: :meth:`check` (True: reuse the last result), and :meth:`processed` after the stage did
    its work on a frame that was not still. A moving camera costs only the coarse pre-check: no
    thumbnail is made and no key kept while :func:`coarse_change` says the picture moves.

    Parameters
    ----------
    still_px : float
        Threshold in colour-image pixels (0 = never still).
    max_frames : int
        Frames in a row that may be still before the stage must process one.
    """

    def __init__(self, still_px: float = STILL_PX, max_frames: int = MAX_FRAMES):
        self.still_px = float(still_px)
        self.max_frames = int(max_frames)
        self.run = 0  # still frames since the key
        self.still_frames = 0  # all still frames
        self._key: tuple[np.ndarray, np.ndarray] | None = None  # (thumbnail, its gradients)
        self._coarse: np.ndarray | None = None
        self._maybe = False
        self._thumb: np.ndarray | None = None
        self._thumb_fn = None

    @property
    def enabled(self) -> bool:
        return self.still_px > 0

    def reset(self) -> None:
        """Forget the key (the next frames are processed)."""
        self.run = 0
        self._key = None
        self._coarse = None
        self._maybe = False

    def check(self, coarse: np.ndarray, thumb_fn, width: int, allowed: bool = True) -> bool:
        """Whether this frame (its :func:`coarse_sample`-like ``coarse``, ``thumb_fn()`` making its
        thumbnail when needed, colour image ``width`` pixels wide) may reuse the key's result;
        ``allowed=False``: the stage cannot reuse it now (it still follows the picture)."""
        self._maybe = coarse_change(self._coarse, coarse) < COARSE_MAX
        self._coarse = coarse
        self._thumb, self._thumb_fn = None, thumb_fn
        if not (allowed and self.enabled and self._maybe and self._key is not None and self.run < self.max_frames):
            return False
        self._thumb = thumb_fn()
        if not self._moved_less(self._thumb, width):
            return False
        self.run += 1
        self.still_frames += 1
        return True

    def processed(self) -> None:
        """The stage processed the frame of the last :meth:`check`: it becomes the key when the camera
        may be still (else no key: a moving camera makes no thumbnail)."""
        self.run = 0
        if not (self.enabled and self._maybe and self._thumb_fn is not None):
            self._key = None
            return
        t = self._thumb if self._thumb is not None else self._thumb_fn()
        g = np.zeros((2,) + t.shape, np.float32)
        g[0, :, 1:-1] = 0.5 * (t[:, 2:] - t[:, :-2])
        g[1, 1:-1, :] = 0.5 * (t[2:, :] - t[:-2, :])
        self._key = (t, g)

    def _moved_less(self, thumb: np.ndarray, width: int) -> bool:
        if self._key is None or self._key[0].shape != thumb.shape:
            return False
        key, g = self._key
        if coarse_change(key, thumb) > MAX_CHANGE:  # (after its mean: a brightness change is not a motion)
            return False
        d = thumb - key
        d -= d.mean()
        to_px = width / thumb.shape[1]  # thumbnail -> colour-image pixels
        h, w = thumb.shape
        textured = 0
        for ys in (slice(0, h // 2), slice(h // 2, h)):
            for xs in (slice(0, w // 2), slice(w // 2, w)):
                gx, gy, dq = g[0, ys, xs].ravel(), g[1, ys, xs].ravel(), d[ys, xs].ravel()
                a = np.array([[gx @ gx, gx @ gy], [gx @ gy, gy @ gy]], np.float64)
                if np.linalg.eigvalsh(a)[0] < MIN_TEXTURE * gx.size:
                    continue  # too little texture in this quadrant to tell
                textured += 1
                shift = np.linalg.solve(a, np.array([gx @ dq, gy @ dq], np.float64))
                if float(np.hypot(*shift)) * to_px >= self.still_px:
                    return False
        return textured >= 2
