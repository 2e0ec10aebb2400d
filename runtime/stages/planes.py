"""Planes across frames: tracking with stable IDs, and the ``PlaneStage``.

What this module owns
    * :class:`PlaneTracker`: stable IDs across frames. Between full detections every tracked plane
      is refitted on its *predicted* inliers (points near last frame's plane with an agreeing
      normal): one distance test and one 3x3 eigen-decomposition per plane. Full detection
      (:func:`~illuminet.runtime.stages.plane_fit.detect_planes`) runs every ``redetect_every``
      frames, or at once when a track is lost.
    * :class:`PlaneStage`: writes ``results["planes"]`` (tuple of :class:`~illuminet.runtime.scene.Plane`),
      labelled floor/table/wall/other.

The per-frame maths (cloud, detection methods, fitting, labels, the bad-depth guard) is in
:mod:`illuminet.runtime.stages.plane_fit`.

Conventions: camera coordinates (OpenCV), metres; a plane is ``n . x + d = 0`` with ``|n| = 1`` and
``d > 0`` (the normal points to the camera's side).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from illuminet.runtime.config import Config
from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import PLANES, Plane
from illuminet.runtime.stage import LogOnce, Stage
from illuminet.runtime.stages.plane_fit import (
    DETECTORS,
    MIN_FRAME,
    Cloud,
    DetectParams,
    PlaneFit,
    check_depth,
    detect_planes,
    estimate_up,
    inlier_threshold,
    label_planes,
    make_cloud,
    refine,
)
from illuminet.runtime.stages.still import StillTest, coarse_sample, colour_thumbnail

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Tracking


@dataclass
class Track:
    """A tracked plane (mutable state of :class:`PlaneTracker`)."""

    id: int
    normal: np.ndarray
    offset: float
    fit: PlaneFit
    ref_inliers: int  # inlier count at the last full detection (loss test)
    age: int = 0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(4))  # per-frame change of (n, d)
    #: the last frame-to-frame change of (n, d) as fitted (camera motion included, unlike ``velocity``,
    #: which follows noise-level drift only): where tracking looks for the plane in the next frame
    motion: np.ndarray = field(default_factory=lambda: np.zeros(4))


class PlaneTracker:
    """Stable plane IDs, smoothed parameters, cheap per-frame updates (module docstring).

    Parameters
    ----------
    params : DetectParams
    method : str
        Detection method for full detections.
    redetect_every : int
        Full detection every N frames (1 = every frame).
    smoothing : float
        Smoothing of normal and offset in [0, 1): an alpha-beta filter with alpha = 1 - smoothing
        (exponential smoothing plus a velocity term). It only smooths noise: a change larger than
        :attr:`MOTION_GATE_DEG` or max(:attr:`MOTION_GATE_M`, 10 standard errors of the fit) is
        camera motion and is taken at once.
    """

    #: association gates (degrees, metres at 1 m scaled like the inlier threshold)
    MATCH_DEG = 10.0
    MATCH_OFFSET_M = 0.05
    #: smoothing applies only to changes below these (and below 10 standard errors of the fit)
    MOTION_GATE_M = 0.002
    MOTION_GATE_DEG = 0.3

    def __init__(
        self,
        params: DetectParams,
        method: str = "region",
        redetect_every: int = 30,
        smoothing: float = 0.8,
        seed: int = 0,
    ):
        if method not in DETECTORS:
            raise ValueError(f"[planes] method: expected one of {', '.join(DETECTORS)}, got {method!r}")
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"[planes] smoothing: expected a number in [0, 1), got {smoothing!r}")
        self.params = params
        self.method = method
        self.redetect_every = max(1, int(redetect_every))
        self.smoothing = float(smoothing)
        self.rng = np.random.default_rng(seed)
        self.tracks: list[Track] = []
        self._next_id = 0
        self._since_detect = 0
        self.n_detections = 0
        self.n_tracked = 0
        self.n_lost = 0

    def reset(self) -> None:
        self.tracks = []
        self._since_detect = 0

    def update(self, cloud: Cloud) -> list[Track]:
        """Track (or detect) planes in ``cloud``; returns the current tracks, largest first."""
        need = not self.tracks or self._since_detect + 1 >= self.redetect_every
        if not need:
            if self._track(cloud):
                self._since_detect += 1
                self.n_tracked += 1
                return self.tracks
            self.n_lost += 1
        self._detect(cloud)
        self._since_detect = 0
        self.n_detections += 1
        return self.tracks

    # -- per-frame update of tracked planes
    def _track(self, cloud: Cloud) -> bool:
        # A moving camera moves the planes in camera coordinates by several degrees per frame (the
        # demo's orbit: ~6 deg and 5 cm on a wall 2.3 m away), more than the inlier distance: the
        # last frame's plane then catches only part of its points and the track is lost. Each plane
        # is looked for where its last motion predicts it (constant velocity); should that fail,
        # where it was (a camera that stopped).
        if self._track_from(cloud, [self._predict(t) for t in self.tracks]):
            return True
        if any(t.motion.any() for t in self.tracks):
            return self._track_from(cloud, [(t.normal, t.offset) for t in self.tracks])
        return False

    @staticmethod
    def _predict(t: Track) -> tuple[np.ndarray, float]:
        n = t.normal + t.motion[:3]
        return n / np.linalg.norm(n), float(t.offset + t.motion[3])

    def _track_from(self, cloud: Cloud, starts: list[tuple[np.ndarray, float]]) -> bool:
        thr = self.params.inlier_threshold_m
        # Predicted inliers, each point to its nearest tracked plane (planes close together, such as
        # a plate on the ground, must not steal each other's points).
        P = cloud.points
        zthr = cloud.threshold(thr)
        best_d = np.full(cloud.shape, np.inf, np.float32)
        owner = np.full(cloud.shape, -1, np.int16)
        for k, (n, d) in enumerate(starts):
            dist = np.abs(P @ n.astype(np.float32) + np.float32(d))
            closer = dist < best_d
            best_d = np.where(closer, dist, best_d)
            owner = np.where(closer, k, owner)
        near = cloud.valid & (best_d < zthr)
        updates = []
        for k, (t, (n, d)) in enumerate(zip(self.tracks, starts)):
            fit = refine(
                cloud,
                n,
                d,
                thr,
                allowed=near & (owner == k),
                iterations=1,
                final_inliers=False,
                despeckle=False,
                use_normals=False,
            )
            if fit is None or fit.n_inliers < 0.5 * t.ref_inliers:
                return False  # lost: the caller re-detects
            if np.degrees(np.arccos(np.clip(abs(fit.normal @ t.normal), -1, 1))) > self.MATCH_DEG:
                return False
            updates.append(fit)
        for t, fit in zip(self.tracks, updates):
            self._smooth_into(t, fit)
        return True

    def _smooth_into(self, t: Track, fit: PlaneFit) -> None:
        # Alpha-beta filter on (normal, offset): alpha = 1 - smoothing weighs the new fit, and a
        # velocity term (beta = alpha^2 / (2 - alpha), Benedict-Bordner) follows slow drift
        # without the lag of plain exponential smoothing. A change beyond the noise (more than
        # 0.3 deg, or more than max(2 mm, 10 standard errors of the fitted offset) from the
        # prediction) is camera motion: taken at once, velocity cleared, so planes never lag.
        s = self.smoothing
        x_new = np.append(fit.normal, fit.offset)
        pred = np.append(t.normal, t.offset) + t.velocity
        ang = np.degrees(np.arccos(np.clip(fit.normal @ (pred[:3] / np.linalg.norm(pred[:3])), -1.0, 1.0)))
        # motion gate: a change well beyond the fit's own noise is the camera moving, not noise
        gate_d = max(self.MOTION_GATE_M, 10.0 * fit.offset_se)
        if s > 0 and ang < self.MOTION_GATE_DEG and abs(fit.offset - pred[3]) < gate_d:
            a = 1.0 - s
            b = a * a / (2.0 - a)
            r = x_new - pred
            x = pred + a * r
            t.velocity = t.velocity + b * r
            n = x[:3] / np.linalg.norm(x[:3])
            d = float(x[3])
        else:
            n, d = fit.normal, fit.offset
            t.velocity = np.zeros(4)
        t.motion = np.append(n - t.normal, float(d) - t.offset)
        t.normal, t.offset, t.fit = n, float(d), fit
        t.age += 1

    # -- full detection with association to existing tracks
    def _detect(self, cloud: Cloud) -> None:
        fits = detect_planes(cloud, self.params, self.method, self.rng)
        old = self.tracks
        pairs = []
        for i, f in enumerate(fits):
            for j, t in enumerate(old):
                ang = np.degrees(np.arccos(np.clip(f.normal @ t.normal, -1.0, 1.0)))
                doff = abs(f.offset - t.offset)
                gate = max(
                    self.MATCH_OFFSET_M,
                    3.0 * float(inlier_threshold(np.float64(f.centroid[2]), self.params.inlier_threshold_m)),
                )
                if ang < self.MATCH_DEG and doff < gate:
                    pairs.append((ang / self.MATCH_DEG + doff / gate, i, j))
        pairs.sort()
        used_f, used_t, new_tracks = set(), set(), []
        for _, i, j in pairs:
            if i in used_f or j in used_t:
                continue
            used_f.add(i)
            used_t.add(j)
            t = old[j]
            self._smooth_into(t, fits[i])
            t.ref_inliers = fits[i].n_inliers
            new_tracks.append(t)
        for i, f in enumerate(fits):
            if i not in used_f:
                new_tracks.append(Track(self._next_id, f.normal, f.offset, f, f.n_inliers))
                self._next_id += 1
        new_tracks.sort(key=lambda t: -t.fit.area_m2)
        self.tracks = new_tracks


# --------------------------------------------------------------------------------------------
# The stage


#: a still camera's planes are held only after each has been fitted this many times (with the default
#: smoothing 0.8 the first fit then weighs 0.8^10 = 11 % in the filtered plane)
HOLD_AFTER_FITS = 10


class PlaneStage(Stage):
    """Detects and tracks planes; writes ``results["planes"]`` (tuple of :class:`Plane`, largest first).

    Bad depth (see :func:`check_depth`) is logged once per kind and counted in :meth:`stats`; the
    frame goes on with the previous frame's planes (an empty tuple before the first good frame).

    A still camera (``[planes] still_px``, :class:`~illuminet.runtime.stages.still.StillTest`): once
    every plane has been fitted :data:`HOLD_AFTER_FITS` times (the temporal filter has averaged the
    depth noise down to its steady state), while the picture moved less than that since the planes
    were last fitted, the frame gets those planes again without tracking; at least every 30th frame
    is fitted, and any motion beyond the threshold is tracked at once. (Holding the first detection
    instead cost the camera eval 0.001-0.002 MAE on its 8-frame static scenes.)
    """

    name = "planes"
    provides = (PLANES,)

    def __init__(self, cfg: Config, full_masks: bool = True):
        self.cfg = cfg
        p = cfg.planes
        self.params = DetectParams.from_config(cfg)
        self.tracker = PlaneTracker(self.params, p.method, p.redetect_every, p.smoothing)
        self.full_masks = full_masks
        self._warn = LogOnce(log, "planes")
        self._last: tuple[Plane, ...] = ()
        self.frames = 0
        self.bad_frames = 0
        self.up_source = ""
        self.cloud: Cloud | None = None  # the last frame's cloud (anchor and tests read it)
        self.still = StillTest(float(p.still_px))

    def process(self, frame: Frame) -> Frame:
        self.frames += 1
        depth = frame.depth
        color = frame.color
        if self.still.enabled and depth is not None and color is not None and color.ndim == 3 and color.shape[2] == 3:
            settled = self.tracker.tracks and min(t.age for t in self.tracker.tracks) >= HOLD_AFTER_FITS
            thumb = lambda: colour_thumbnail(color)  # noqa: E731
            if self.still.check(coarse_sample(color), thumb, color.shape[1], allowed=bool(settled and self._last)):
                return frame.with_result(PLANES, self._last)  # nothing moved: the planes fitted last
        cloud = None
        if depth is None or depth.shape[0] < MIN_FRAME[1] or depth.shape[1] < MIN_FRAME[0]:
            problem = check_depth(depth)
        else:
            cloud = make_cloud(depth, frame.intrinsics)
            problem = check_depth(depth, sample=depth[:: cloud.stride, :: cloud.stride])
            if problem is None and cloud.nonfinite:
                self._warn(
                    "nonfinite",
                    f"depth has NaN/inf values ({cloud.nonfinite} of {cloud.valid.size} "
                    "sampled); they are treated as invalid (expected 0 for invalid)",
                )
        if problem is not None:
            kind, msg = problem
            self.bad_frames += 1
            self._warn(kind, f"frame {frame.seq}: {msg}; keeping the previous planes")
            self.still.reset()  # the next good frame is fitted
            return frame.with_result(PLANES, self._last)
        self.cloud = cloud
        tracks = self.tracker.update(cloud)
        up, self.up_source = estimate_up([(t.normal, t.fit.area_m2) for t in tracks], frame.gravity)
        labels = label_planes([t.normal for t in tracks], [t.offset for t in tracks], up)
        planes = []
        for t, lab in zip(tracks, labels):
            f = t.fit
            planes.append(
                Plane(
                    id=t.id,
                    normal=t.normal.copy(),
                    offset=t.offset,
                    centroid=f.centroid.copy(),
                    area_m2=f.area_m2,
                    label=lab,
                    inlier_mask=cloud.upsample_mask(f.mask) if self.full_masks else None,
                    n_inliers=f.n_inliers,
                    extent_m=f.extent_m,
                    axes=f.axes.copy(),
                    cloud_mask=f.mask,
                    cloud_stride=cloud.stride,
                )
            )
        self._last = tuple(planes)
        self.still.processed()
        return frame.with_result(PLANES, self._last)

    def stats(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "bad_depth_frames": self.bad_frames,
            "bad_depth": dict(self._warn.counts),
            "detections": self.tracker.n_detections,
            "tracked_updates": self.tracker.n_tracked,
            "tracks_lost": self.tracker.n_lost,
            "planes": len(self._last),
            "still_frames": self.still.still_frames,
            "up_from": self.up_source,
        }
