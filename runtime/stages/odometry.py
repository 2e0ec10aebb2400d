"""Cheap RGB-D camera odometry: where the camera is in a fixed world frame, frame after frame.

What this module owns
    * :class:`Odometry`: the camera pose ``T_cam_world`` (``x_cam = R @ x_world + t``, 4x4) of every
      frame, in a world frame that is the camera frame of the first good frame (or of the frame
      tracking was restarted on, with the last pose carried over).
    * How (the budget is a few milliseconds on a small CPU):

      1. The colour image is turned grey and downscaled by ``DOWNSCALE`` (640x400 -> 320x200).
      2. Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) are detected there and lifted to 3D with
         the aligned depth; each becomes a *landmark* with a world position (the current pose
         applied to its camera point).
      3. Each frame, the landmarks are tracked from the previous good image with pyramidal
         Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``), started where a constant-velocity motion
         puts them (repetitive texture such as tiles otherwise lets LK lock onto the next period)
         and on a grey image scaled to the old one's mean (auto exposure changes the brightness;
         LK assumes it constant: an 8 % change once made half the tracks slide), and lifted to 3D
         again with this frame's depth (the median of 5 samples 2 pixels apart, usable only when
         they agree: corners often sit on depth edges).
      4. The pose is a robust rigid 3D-3D fit (no scale) of the landmarks' world positions to
         their camera points: RANSAC over minimal samples (all hypotheses in one batched SVD),
         then Huber-weighted Kabsch refits on the inliers (weights ~ 1/z^2: stereo depth error
         grows with z^2), then a few Gauss-Newton steps on the reprojection error of the tracked
         pixels (precise to ~0.05 px, while this frame's depth is not). Fitting the *world*
         positions (not the previous frame's points) means that drift only enters when landmarks
         are added, not every frame.
      5. With a tracked plane whose world parameters are known (the anchor plane), the plane pins
         3 of the 6 degrees of freedom exactly: ``R n_w = n_c`` (roll, pitch) and
         ``n_c . t = d_w - d_c`` (height). Only the in-plane translation and the rotation about
         the normal are fitted from the features (2D Procrustes, minimal sample of 2), which is
         much more robust on low-texture floors and removes the tilt errors that a lever arm of
         1.5 m would turn into centimetres at the object.
      6. Inlier landmarks' world positions are refined by a running mean of their observations
         (averages stereo noise); outliers are dropped; when fewer than ``MIN_FEATURES`` remain,
         new corners are detected away from the tracked ones.

    7. **A turn in place with too little depth** (a user looking around outdoors: sky, far grass, a
       window; the view holds only a few pixels in the depth range): the 3D fit has too few
       landmarks with depth, so the camera's rotation since the last tracked image is fitted to the
       tracks' bearings there and here (Wahba's problem: RANSAC over pairs, Huber refits; at least
       ``MIN_INLIER_SHARE`` of the 2D tracks must agree) and the camera centre is held. Frame to
       frame a turn moves every track by the same rotation whatever its depth, so near and far
       tracks both count, and a centre that drifted does not bend them. Corners with no depth at all
       (all 5 samples missing or beyond ``Z_MAX``; not depth edges) are tracked as *direction*
       landmarks (at most :data:`MAX_BEARINGS`, beside the point landmarks) so that they are in
       place when the depth runs out. The result says ``rotation_only``. A frame with no valid depth
       at all is a dropout (a glitch, a covered stereo pair) and is lost as before, not a turn.

    * **A still camera** (a tripod, a board on a desk) costs almost nothing: before tracking, the
      frame is compared with the last tracked one (:class:`~illuminet.runtime.stages.still.StillTest`,
      on the tracking image downscaled 4x more); when it moved less than ``still_px`` colour pixels
      the pose is held and nothing else runs (once :data:`HOLD_AFTER_TRACKS` frames have been tracked
      since tracking started: the landmarks' positions have then been averaged).
    * Tracking state: ``"ok"``, or ``"lost"`` when the frame is unusable (no colour or depth, a
      (nearly) black or flat image, no valid depth at all, or under 5 % with nothing to track a turn
      from) or too few inliers support a pose (nor a turn in place, step 7).
      While lost the last pose is held (the camera is assumed still) and the last good image and
      its landmarks are kept, so the next good frame is tracked from them (a single bad frame
      costs nothing). After ``RESET_AFTER`` good-but-untrackable frames in a row, tracking
      restarts on the current frame with the held pose: the world frame stays continuous, so an
      anchor held in world coordinates stays where it was last seen relative to the camera.

:class:`OdometryResult` is what :class:`~illuminet.runtime.stages.anchor.AnchorStage` publishes as
``results["odometry"]`` in ``[anchor] lock = "world"``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from illuminet.runtime.frame import Frame
from illuminet.runtime.stage import LogOnce
from illuminet.runtime.stages.still import STILL_PX, THUMB, StillTest, coarse_sample, thumbnail

log = logging.getLogger(__name__)

#: Grey image is downscaled by this factor before tracking (640x400 -> 320x200).
DOWNSCALE = 2
#: the still test's thumbnail from the tracking image: 1/8 of the colour size in all (still.THUMB)
STILL_FACTOR = THUMB // DOWNSCALE
#: a still camera's pose is held only after this many frames were tracked since tracking (re)started:
#: the landmarks' world positions are running means of their observations, and holding the pose of
#: the first tracked frame froze their first, noisiest estimate (a lamp test's direction moved 3 deg)
HOLD_AFTER_TRACKS = 10
#: Landmarks kept at most, and the count under which new corners are detected.
MAX_FEATURES = 160
MIN_FEATURES = 90
#: Inliers needed for a pose, in number and as a share of the tracked landmarks (fewer: "lost"; a
#: garbage image still gives LK "tracks", and a few of them agree with some pose by chance).
MIN_INLIERS = 12
MIN_INLIER_SHARE = 0.3
#: Good-but-untrackable frames in a row after which tracking restarts on the current frame.
RESET_AFTER = 3
#: RANSAC hypotheses per frame.
RANSAC_ITERS = 40
#: 3D inlier distance: INLIER_M_AT_1M * z^2 (stereo noise grows with z^2), at least INLIER_MIN_M.
INLIER_M_AT_1M = 0.01
INLIER_MIN_M = 0.01
#: Forward-backward LK check (off: it doubles the LK cost and the RANSAC rejects bad tracks anyway).
FB_MAX_PX = 1.0
FB_CHECK = False
#: Landmark world positions average at most this many observations (then a moving average).
MAX_OBS = 16
#: Scale the new grey image to the old one's mean before LK (auto exposure).
GAIN_COMPENSATION = True
#: Refine the pose on the reprojection error of the tracked pixels (Huber scale in pixels).
REPROJ_REFINE = True
HUBER_PX = 1.0
#: Fit weights 1/z^WEIGHT_POWER (stereo depth variance grows with z^4).
WEIGHT_POWER = 2
#: Depth range accepted (metres).
Z_MIN, Z_MAX = 0.2, 8.0
#: a turn in place (a user looking around; the view on sky, far grass or a window) leaves too few
#: landmarks with depth for the 3D fit: the rotation is then fitted to the tracks' bearings from the
#: held camera centre (module docstring, step 7)
ROTATION_FALLBACK = True
#: a bearing agrees with a rotation when it lands within this many colour-image pixels
ROTATION_INLIER_PX = 3.0
#: at most this many direction landmarks (corners with no depth at all: sky, far fields), tracked
#: beside the point landmarks so that a turn away from everything with depth finds them in place
MAX_BEARINGS = 60
_LK = dict(winSize=(11, 11), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03))


@dataclass(frozen=True)
class OdometryResult:
    """One frame's odometry (``results["odometry"]``).

    Attributes
    ----------
    T_cam_world : (4, 4) float64
        Camera pose: ``x_cam = T[:3, :3] @ x_world + T[:3, 3]``. Held at the last good value while lost.
    state : str
        ``"ok"`` (pose measured this frame) or ``"lost"`` (pose held).
    inliers : int
        Landmarks supporting the pose (0 when lost).
    tracked : int
        Landmarks tracked into this frame with valid depth.
    landmarks : int
        Landmarks alive after this frame (including newly detected ones).
    plane_constrained : bool
        Whether the anchor plane pinned roll, pitch and height.
    reason : str
        Why the frame is lost ("" when ok).
    rotation_only : bool
        The pose was fitted to the tracks' bearings with the camera centre held (a turn in place with
        too little depth for the 3D fit; module docstring, step 7).
    """

    T_cam_world: np.ndarray
    state: str
    inliers: int = 0
    tracked: int = 0
    landmarks: int = 0
    plane_constrained: bool = False
    reason: str = ""
    rotation_only: bool = False

    @property
    def T_world_cam(self) -> np.ndarray:
        return invert(self.T_cam_world)


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def _cross(a, b) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~15 us of overhead per call; this is per frame)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with ``R @ a = b`` (unit vectors)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v = _cross(a, b)
    c = float(a @ b)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: 180 degrees about any axis perpendicular to a
        p = _cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = _cross(a, [0.0, 1.0, 0.0])
        p /= np.linalg.norm(p)
        return 2.0 * np.outer(p, p) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K * ((1.0 - c) / (s * s))


def kabsch(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid fit (no scale): R, t minimising ``sum w |R p + t - q|^2``.

    ``P`` and ``Q`` are (..., N, 3); batched over leading axes (one SVD per batch element).
    """
    if w is None:
        w = np.ones(P.shape[:-1])
    w = w / np.sum(w, axis=-1, keepdims=True)
    pc = np.sum(P * w[..., None], axis=-2)
    qc = np.sum(Q * w[..., None], axis=-2)
    R = wahba(P - pc[..., None, :], Q - qc[..., None, :], w)  # the rotation of the centred points
    t = qc - np.einsum("...ij,...j->...i", R, pc)
    return R, t


def wahba(P: np.ndarray, Q: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted rotation of directions (Wahba's problem): R minimising ``sum w |R p - q|^2``.

    ``P`` and ``Q`` are (..., N, 3) (unit vectors, or the centred points of :func:`kabsch`); batched
    over leading axes, one SVD per batch element.
    """
    if w is None:
        w = np.ones(P.shape[:-1])
    Hm = np.einsum("...ni,...nj->...ij", P * w[..., None], Q)
    U, _, Vt = np.linalg.svd(Hm)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros(Hm.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(d == 0, 1.0, d)
    return np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)


def _irls(refit, m: np.ndarray, w: np.ndarray, thr: np.ndarray, k_min: int, iters: int = 2):
    """Refine a RANSAC consensus ``m``: weighted refits with Huber weights on the residuals.

    Stereo depth errors are heavy-tailed (most samples are right, some jump by a disparity step):
    plain least squares on the inliers is pulled by the jumps (5 mm on a static camera at 2.6 m),
    Huber weights with a scale from the median residual are not. ``refit(weights)`` returns
    (model, residuals of all points). Returns (model, inlier mask) or None.
    """
    model, res = None, None
    for _ in range(iters):
        if m.sum() < max(k_min, 3):
            return None
        r = res  # residuals of the previous refit (None on the first pass: plain weights)
        ww = np.where(m, w, 0.0)
        if r is not None:
            s = max(1.4826 * float(np.median(r[m])), 1e-3)
            ww = ww * np.minimum(1.0, 1.5 * s / np.maximum(r, 1e-12))
        model, res = refit(ww)
        m = res < thr
    return model, m


def _axis_angle(n: np.ndarray, a: float) -> np.ndarray:
    """Rotation by angle ``a`` about unit axis ``n``."""
    K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


def _refine_reprojection(
    R: np.ndarray, t: np.ndarray, Pw: np.ndarray, uv: np.ndarray, intr, n_c: np.ndarray | None, iters: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the reprojection error of the inlier landmarks (Huber, 1 px).

    The tracked pixels are precise (LK: ~0.05 px) while this frame's depth is not (stereo error
    grows with z^2 and is heavy-tailed): the 3D fit gives the start, the pixels the answer. The
    update is ``R' = dR R``, ``t' = dR t + dt``; with a plane normal ``n_c`` only the rotation about
    it and a shift perpendicular to it are free, so the plane constraint is kept exactly.
    """
    if n_c is not None:
        e1, e2 = _basis(n_c)
        k = 3
    else:
        k = 6
    fx, fy, cx, cy = intr.fx, intr.fy, intr.cx, intr.cy

    def apply(p):
        if n_c is None:
            dR = cv2.Rodrigues(p[:3].reshape(3, 1))[0]
            dt = p[3:]
        else:
            dR = _axis_angle(n_c, p[0])
            dt = p[1] * e1 + p[2] * e2
        return dR @ R, dR @ t + dt

    def resid(p):
        R_, t_ = apply(p)
        X = Pw @ R_.T + t_
        Z = np.maximum(X[:, 2], 1e-3)
        return np.concatenate([fx * X[:, 0] / Z + cx - uv[:, 0], fy * X[:, 1] / Z + cy - uv[:, 1]])

    p = np.zeros(k)
    eps = 1e-6
    for _ in range(iters):
        r = resid(p)
        J = np.empty((r.size, k))
        for j in range(k):
            dp = np.zeros(k)
            dp[j] = eps
            J[:, j] = (resid(p + dp) - r) / eps
        n = len(uv)
        e = np.hypot(r[:n], r[n:])
        w = np.minimum(1.0, HUBER_PX / np.maximum(e, 1e-9))
        w = np.concatenate([w, w])
        A = J.T @ (J * w[:, None])
        try:
            p = p + np.linalg.solve(A + 1e-9 * np.eye(k), -(J.T @ (w * r)))
        except np.linalg.LinAlgError:
            break
    return apply(p)


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to unit ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, _cross(n, e1)


class Odometry:
    """Frame-to-frame RGB-D odometry against tracked landmarks (module docstring).

    Parameters
    ----------
    seed : int
        Seed of the RANSAC sampler (deterministic results for a given input).
    still_px : float
        Hold the pose while the picture moved less than this many colour-image pixels since the last
        tracked frame (module docstring; 0 = track every frame).
    """

    def __init__(self, seed: int = 0, still_px: float = STILL_PX):
        self._rng = np.random.default_rng(seed)
        self.still = StillTest(still_px)
        self._warn = LogOnce(log, "odometry")
        self.T_cam_world = np.eye(4)
        self._grey: np.ndarray | None = None  # last good downscaled grey image
        self._pts = np.zeros((0, 2), np.float32)  # landmark pixels in it (downscaled coords)
        self._lm = np.zeros((0, 3))  # landmark world positions
        self._nobs = np.zeros(0, np.int32)
        self._inf = np.zeros(0, bool)  # landmark is a direction (a bearing with no depth), not a point
        self.state = "init"
        self.frames = 0
        self.lost_frames = 0
        self.resets = 0
        self.rotation_frames = 0  # frames whose pose is a rotation of the tracks' bearings (step 7)
        self._bad_run = 0
        self._velocity: np.ndarray | None = None  # T_cam_world(k) @ inv(T_cam_world(k-1))
        self._tracked = 0
        self.last: OdometryResult | None = None

    # -- public
    def reset(self, keep_pose: bool = True, pose: np.ndarray | None = None) -> None:
        """Forget the landmarks (the next good frame starts tracking again), keeping the pose by default;
        ``pose`` (a ``T_cam_world``) is where tracking starts again instead."""
        self._grey = None
        self._pts = np.zeros((0, 2), np.float32)
        self._lm = np.zeros((0, 3))
        self._nobs = np.zeros(0, np.int32)
        self._inf = np.zeros(0, bool)
        if pose is not None:
            self.T_cam_world = np.array(pose, np.float64)
        elif not keep_pose:
            self.T_cam_world = np.eye(4)
        self._velocity = None
        self.still.reset()
        self.state = "init"

    def update(
        self,
        frame: Frame,
        plane_cam: tuple[np.ndarray, float] | None = None,
        plane_world: tuple[np.ndarray, float] | None = None,
    ) -> OdometryResult:
        """Estimate this frame's camera pose.

        Parameters
        ----------
        frame : Frame
            Needs ``color`` and ``depth`` (aligned, metres).
        plane_cam, plane_world : (normal, offset), optional
            The same physical plane in this frame's camera coordinates (as tracked) and in world
            coordinates (``n . x + d = 0``). When both are given the plane pins roll, pitch and
            height (module docstring, step 5).

        Returns
        -------
        OdometryResult
        """
        self.frames += 1
        grey, depth, why = self._inputs(frame)
        if grey is None:
            return self._lose(why)
        low_depth = why  # too little depth to lift landmarks: only a turn in place can be tracked
        W, H = frame.size
        intr = frame.intrinsics
        if (intr.width, intr.height) != (W, H):
            intr = intr.scaled(W, H)
        if self._grey is not None and self._grey.shape != grey.shape:
            # the camera's resolution changed (reconfigured, another recording appended): the landmarks'
            # pixels and the last image belong to the old size; start again from here with the pose held
            log.info(
                "odometry: the picture changed size (%dx%d -> %dx%d); restarting tracking with the last pose",
                self._grey.shape[1] * DOWNSCALE,
                self._grey.shape[0] * DOWNSCALE,
                grey.shape[1] * DOWNSCALE,
                grey.shape[0] * DOWNSCALE,
            )
            self.resets += 1
            self._grey = None
        if low_depth and not (ROTATION_FALLBACK and self._grey is not None and len(self._pts) >= MIN_INLIERS):
            return self._lose(low_depth)
        if self._grey is None or len(self._pts) < 3:
            self._start(grey, depth, intr)
            self.still.reset()
            return self._result("ok", 0, 0, False)
        if self.still.enabled:
            coarse = coarse_sample(grey, 16 // DOWNSCALE)
            ok = self.state == "ok" and self.last is not None and self._tracked >= HOLD_AFTER_TRACKS
            if self.still.check(coarse, lambda: thumbnail(grey, STILL_FACTOR), W, allowed=ok):
                self._velocity = None  # no motion to predict from
                last = self.last
                return self._result("ok", last.inliers, last.tracked, last.plane_constrained)
        # 1. track the landmarks from the last good image
        p1, good = self._track(grey, intr)
        # 2. lift to 3D with this frame's depth and fit the pose to the landmarks
        X, valid = self._lift(p1, depth, intr)
        use = good & valid & ~self._inf
        n_track = int(use.sum())
        constrained = plane_cam is not None and plane_world is not None
        fit = self._fit(self._lm[use], X[use], plane_cam, plane_world) if n_track >= MIN_INLIERS else None
        if fit is None or fit[2].sum() < max(MIN_INLIERS, MIN_INLIER_SHARE * n_track):
            rot = self._fit_rotation(p1, good, intr) if ROTATION_FALLBACK else None
            if rot is not None:
                return self._turned(grey, depth, intr, p1, good, n_track, *rot)
            return self._not_tied(grey, depth, intr, 0 if fit is None else int(fit[2].sum()), n_track)
        R, t, inl = fit
        if REPROJ_REFINE:
            idx_in = np.nonzero(use)[0][inl]
            uv = (p1[idx_in].astype(np.float64) + 0.5) * DOWNSCALE - 0.5
            R, t = _refine_reprojection(
                R, t, self._lm[idx_in], uv, intr, np.asarray(plane_cam[0], np.float64) if constrained else None
            )
        self._bad_run = 0
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        # velocity for the next frame's LK guess (only between consecutive good frames, not across a
        # hold: that motion took several frames)
        held = self.still.run > 0
        self._tracked += 1
        self._velocity = T @ invert(self.T_cam_world) if self.state == "ok" and not held else None
        self.T_cam_world = T
        # 3. keep tracked landmarks (inliers refined, outliers dropped; untracked-but-good-2D kept)
        self._keep_landmarks(p1, X, good, np.nonzero(use)[0], inl, R, t)
        self._grey = grey
        self.still.processed()
        if len(self._pts) - int(self._inf.sum()) < MIN_FEATURES:
            self._detect(grey, depth, intr)
        return self._result("ok", int(inl.sum()), n_track, constrained)

    def _track(self, grey: np.ndarray, intr) -> tuple[np.ndarray, np.ndarray]:
        """Step 1: the landmarks' pixels in ``grey`` (downscaled, (N, 2)) and which were tracked well."""
        if GAIN_COMPENSATION:
            # auto exposure changes the brightness from frame to frame; LK assumes it constant
            m0, m1 = float(self._grey[::4, ::4].mean()), float(grey[::4, ::4].mean())
            if m1 > 1.0 and abs(m0 / m1 - 1.0) > 0.01:
                grey_lk = cv2.convertScaleAbs(grey, alpha=m0 / m1)
            else:
                grey_lk = grey
        else:
            grey_lk = grey
        p0 = self._pts.reshape(-1, 1, 2)
        # start LK where a constant-velocity motion would put the landmarks: on repetitive texture
        # (tiles) a plain search from the old position can lock onto the neighbouring period
        guess = self._predict(intr, grey.shape)
        if guess is not None:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(
                self._grey, grey_lk, p0, guess.reshape(-1, 1, 2).copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **_LK
            )
        else:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._grey, grey_lk, p0, None, **_LK)
        good = st1.ravel() == 1
        if FB_CHECK:
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(grey_lk, self._grey, p1, None, **_LK)
            fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
            good &= (st2.ravel() == 1) & (fb < FB_MAX_PX)
        p1 = p1.reshape(-1, 2)
        hs, ws = grey.shape
        good &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= ws - 1) & (p1[:, 1] <= hs - 1)
        return p1, good

    def _not_tied(self, grey: np.ndarray, depth: np.ndarray, intr, n_in: int, n_track: int) -> OdometryResult:
        """Step 2 failed (too few inliers): the frame is lost; after :data:`RESET_AFTER` such frames in a
        row, tracking restarts on this view with the held pose."""
        self._bad_run += 1
        if self._bad_run >= RESET_AFTER:
            # cannot tie this view to the landmarks: restart on it with the held pose
            self.resets += 1
            log.info(
                "odometry: lost for %d frames (%d inliers of %d tracked); restarting tracking with the last pose",
                self._bad_run,
                n_in,
                n_track,
            )
            self._start(grey, depth, intr)
            # if the next frame cannot be tied to this one either (it was garbage too), restart
            # again at once rather than waiting another RESET_AFTER frames
            self._bad_run = RESET_AFTER - 1
        return self._lose(
            f"{n_in} inliers of {n_track} tracked (need {MIN_INLIERS} and {100 * MIN_INLIER_SHARE:.0f} %)",
            tracked=n_track,
        )

    def _keep_landmarks(
        self,
        p1: np.ndarray,
        X: np.ndarray,
        good: np.ndarray,
        idx: np.ndarray,
        inl: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
    ) -> None:
        """Step 3: refine the inlier landmarks' world positions (running mean over at most
        :data:`MAX_OBS` observations), drop the outliers, keep the untracked ones that were good in 2D.

        ``idx`` indexes the landmarks the pose was fitted on, ``inl`` marks its inliers among them.
        """
        inlier_idx = idx[inl]
        outlier_idx = idx[~inl]
        Xw = (X[inlier_idx] - t) @ R  # = R^T (x - t)
        k = np.minimum(self._nobs[inlier_idx], MAX_OBS - 1).astype(np.float64)
        self._lm[inlier_idx] = (self._lm[inlier_idx] * k[:, None] + Xw) / (k[:, None] + 1.0)
        self._nobs[inlier_idx] += 1
        keep = good.copy()
        keep[outlier_idx] = False
        self._filter(p1, keep)

    def _filter(self, p1: np.ndarray, keep: np.ndarray) -> None:
        """Keep the landmarks marked ``keep``, at their tracked pixels ``p1``."""
        self._pts = p1[keep].astype(np.float32)
        self._lm = self._lm[keep]
        self._nobs = self._nobs[keep]
        self._inf = self._inf[keep]

    def _fit_rotation(self, p1: np.ndarray, good: np.ndarray, intr) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Step 7: the camera's rotation since the last tracked image, from its tracks' bearings there and
        here: (R, idx, inliers) or None, ``R`` the new ``R_cam_world`` with the centre held.

        Frame to frame, a turn in place moves every track by the same rotation whatever its depth (the
        few millimetres a hand-held camera shifts between frames make no parallax worth a pixel); the
        landmarks' world positions are not used, so a centre that drifted a few centimetres does not
        bend the bearings of near points. RANSAC over pairs (Wahba's problem, batched), then
        Huber-weighted refits on the inliers (within :data:`ROTATION_INLIER_PX`). At least
        :data:`MIN_INLIERS` and :data:`MIN_INLIER_SHARE` of the 2D tracks must agree, as for the 3D fit:
        garbage tracks do not, and a camera that moved far enough to make parallax rarely does.
        """
        idx = np.nonzero(good)[0]
        if len(idx) < MIN_INLIERS:
            return None

        def bearings(px):
            uv = (px.astype(np.float64) + 0.5) * DOWNSCALE - 0.5
            b = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], axis=1)
            return b / np.linalg.norm(b, axis=1, keepdims=True)

        b = bearings(p1[idx])
        d = bearings(self._pts[idx])
        thr = np.full(len(idx), ROTATION_INLIER_PX / max(intr.fx, intr.fy))  # a chord: the angle, in radians
        s = self._samples(len(idx), 2, RANSAC_ITERS)
        R = wahba(d[s], b[s])
        res = np.linalg.norm(d[None] @ np.swapaxes(R, 1, 2) - b[None], axis=2)
        inl = res < thr[None]
        m = inl[int(np.argmax(inl.sum(axis=1)))]

        def refit(ww):
            R_ = wahba(d, b, ww)
            return R_, np.linalg.norm(d @ R_.T - b, axis=1)

        out = _irls(refit, m, np.ones(len(idx)), thr, 2)
        if out is None or out[1].sum() < max(MIN_INLIERS, MIN_INLIER_SHARE * len(idx)):
            return None
        return out[0] @ self.T_cam_world[:3, :3], idx, out[1]

    def _turned(
        self, grey, depth, intr, p1: np.ndarray, good: np.ndarray, n_track: int, R: np.ndarray, idx, inl
    ) -> OdometryResult:
        """Step 7 accepted: the pose is rotation ``R`` about the held centre; outlier tracks are dropped
        and new corners without depth join as directions."""
        centre = -self.T_cam_world[:3, :3].T @ self.T_cam_world[:3, 3]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ centre
        held = self.still.run > 0
        self._bad_run = 0
        self._tracked += 1
        self._velocity = T @ invert(self.T_cam_world) if self.state == "ok" and not held else None
        self.T_cam_world = T
        keep = good.copy()
        keep[idx[~inl]] = False
        self._filter(p1, keep)
        self._grey = grey
        self.still.processed()
        self.rotation_frames += 1
        if self.state != "ok" or not (self.last and self.last.rotation_only):
            # once at INFO (a look around enters and leaves the turn every few seconds), then DEBUG
            log.log(
                logging.DEBUG if self.rotation_frames > 1 else logging.INFO,
                "odometry: too little depth to tie the view (%d tracks with depth); tracking the turn in place "
                "(further turns: debug log; stats()['rotation_frames'] counts them)",
                n_track,
            )
        if len(self._pts) - int(self._inf.sum()) < MIN_FEATURES:
            self._detect(grey, depth, intr)
        return self._result("ok", int(inl.sum()), n_track, False, rotation_only=True)

    def _predict(self, intr, shape) -> np.ndarray | None:
        """Landmark pixels (downscaled) under a constant-velocity pose, or None without a velocity."""
        if self._velocity is None or len(self._lm) == 0:
            return None
        T = self._velocity @ self.T_cam_world
        X = self._lm @ T[:3, :3].T + np.where(self._inf[:, None], 0.0, T[:3, 3])
        Z = X[:, 2]
        ok = Z > Z_MIN
        Zs = np.where(ok, Z, 1.0)
        u = (intr.fx * X[:, 0] / Zs + intr.cx + 0.5) / DOWNSCALE - 0.5
        v = (intr.fy * X[:, 1] / Zs + intr.cy + 0.5) / DOWNSCALE - 0.5
        g = np.stack([u, v], axis=1)
        hs, ws = shape
        ok &= (u > -8) & (v > -8) & (u < ws + 8) & (v < hs + 8)
        return np.where(ok[:, None], g, self._pts).astype(np.float32)

    def stats(self) -> dict[str, Any]:
        last = self.last
        return {
            "state": self.state,
            "frames": self.frames,
            "lost_frames": self.lost_frames,
            "resets": self.resets,
            "rotation_frames": self.rotation_frames,
            "still_frames": self.still.still_frames,
            "inliers": last.inliers if last else 0,
            "landmarks": len(self._lm),
            "warnings": dict(self._warn.counts),
        }

    # -- internals
    def _result(
        self, state: str, inliers: int, tracked: int, constrained: bool, reason: str = "", rotation_only: bool = False
    ) -> OdometryResult:
        self.state = state
        self.last = OdometryResult(
            T_cam_world=self.T_cam_world.copy(),
            state=state,
            inliers=inliers,
            tracked=tracked,
            landmarks=len(self._lm),
            plane_constrained=constrained,
            reason=reason,
            rotation_only=rotation_only,
        )
        return self.last

    def _lose(self, reason: str, tracked: int = 0) -> OdometryResult:
        self.lost_frames += 1
        if self.state != "lost":
            log.info("odometry: tracking lost (%s); holding the last pose", reason)
        return self._result("lost", 0, tracked, False, reason)

    def _inputs(self, frame: Frame) -> tuple[np.ndarray | None, np.ndarray | None, str]:
        """Downscaled grey image and the depth map, or (None, None, why) when the frame is unusable."""
        c, d = frame.color, frame.depth
        if c is None or d is None:
            self._warn("no_rgbd", "frame has no colour or no depth; odometry needs both (pose held)")
            return None, None, "no colour or depth"
        if c.ndim != 3 or c.shape[2] != 3 or d.shape[:2] != c.shape[:2]:
            self._warn("shape", f"colour {c.shape} and depth {d.shape} must be HxWx3 and HxW of the same size")
            return None, None, "colour/depth shape"
        if min(c.shape[:2]) < 32:
            self._warn("tiny", f"frame {c.shape[1]}x{c.shape[0]} is too small to track (need >= 32 px)")
            return None, None, "tiny frame"
        g = cv2.cvtColor(np.ascontiguousarray(c), cv2.COLOR_RGB2GRAY)
        h, w = g.shape
        g = cv2.resize(g, (w // DOWNSCALE, h // DOWNSCALE), interpolation=cv2.INTER_AREA)
        # flat/black image: nothing to track (a covered lens, a dropped frame)
        s = g[::4, ::4]
        if float(s.std()) < 2.0:
            return None, None, "flat or black image"
        ds = d[::8, ::8]
        with np.errstate(invalid="ignore"):
            frac = float(np.mean((ds > Z_MIN) & (ds < Z_MAX)))
        if frac == 0.0:  # a depth dropout (a glitch, a covered stereo pair), not a view of the sky
            return None, None, "no valid depth"
        if frac < 0.05:  # too little to lift landmarks; a turn in place may still be tracked (step 7)
            return g, d, f"only {100 * frac:.0f} % valid depth"
        return g, d, ""

    @staticmethod
    def _depth_samples(pts: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Full-resolution pixels (u, v) of downscaled pixels ``pts`` and their 5 depth samples (5, N)."""
        H, W = depth.shape
        u = (pts[:, 0] + 0.5) * DOWNSCALE - 0.5
        v = (pts[:, 1] + 0.5) * DOWNSCALE - 0.5
        ui = np.clip(np.round(u).astype(np.int64), 2, W - 3)
        vi = np.clip(np.round(v).astype(np.int64), 2, H - 3)
        z = np.stack([depth[vi, ui], depth[vi, ui - 2], depth[vi, ui + 2], depth[vi - 2, ui], depth[vi + 2, ui]])
        return u, v, z

    def _lift(self, pts: np.ndarray, depth: np.ndarray, intr) -> tuple[np.ndarray, np.ndarray]:
        """Camera points of downscaled pixels ``pts`` (N, 2) and whether their depth is usable."""
        u, v, z = self._depth_samples(pts, depth)
        # over: 1e30 or float32's max marking invalid depth overflowed "zc * zc" (numpy's two-line warning per
        # frame); such a corner is refused by Z_MAX anyway
        with np.errstate(invalid="ignore", over="ignore"):
            # the median of the 5 samples: stereo depth jumps by whole disparity steps at random (the
            # middle of the sorted five: np.median's bits where all five are finite, the only case
            # kept below, in a sixth of its time)
            zc = np.sort(z, axis=0)[2]
            ok = np.all((z > Z_MIN) & (z < Z_MAX), axis=0)
            # the neighbours must agree: corners often sit on depth edges, where depth is unreliable
            ok &= (z.max(axis=0) - z.min(axis=0)) < 0.02 + 0.02 * zc * zc
        zc = np.where(ok, zc, 1.0).astype(np.float64)
        X = np.stack([(u - intr.cx) / intr.fx * zc, (v - intr.cy) / intr.fy * zc, zc], axis=1)
        return X, ok

    def _start(self, grey: np.ndarray, depth: np.ndarray, intr) -> None:
        self._pts = np.zeros((0, 2), np.float32)
        self._lm = np.zeros((0, 3))
        self._nobs = np.zeros(0, np.int32)
        self._inf = np.zeros(0, bool)
        self._grey = grey
        self._bad_run = 0
        self._velocity = None
        self._tracked = 0  # frames tracked since this start (the still hold waits for HOLD_AFTER_TRACKS)
        self._detect(grey, depth, intr)

    def _detect(self, grey: np.ndarray, depth: np.ndarray, intr) -> None:
        """Add corners away from the tracked ones as landmarks at the current pose: points where the depth
        is valid, directions (step 7) where there is no depth at all (sky, far fields; not depth edges)."""
        n_inf = int(self._inf.sum())
        want = MAX_FEATURES - (len(self._pts) - n_inf)
        want_b = MAX_BEARINGS - n_inf if ROTATION_FALLBACK else 0
        if want <= 0 and want_b <= 0:
            return
        want, want_b = max(want, 0), max(want_b, 0)
        mask = np.full(grey.shape, 255, np.uint8)
        for x, y in self._pts:
            cv2.circle(mask, (int(x), int(y)), 6, 0, -1)
        c = cv2.goodFeaturesToTrack(
            grey, maxCorners=(want + want_b) * 3 // 2, qualityLevel=0.01, minDistance=7, mask=mask, blockSize=5
        )
        if c is None:
            return
        c = c.reshape(-1, 2).astype(np.float32)
        X, ok = self._lift(c, depth, intr)
        cb = c[~ok]
        c, X = c[ok][:want], X[ok][:want]
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        lm = (X - t) @ R
        inf = np.zeros(len(c), bool)
        if want_b > 0 and len(cb):
            u, v, z = self._depth_samples(cb, depth)
            with np.errstate(invalid="ignore"):
                none = np.all(~(z > Z_MIN) | (z >= Z_MAX), axis=0)  # no depth, or beyond the range, all 5
            cb, u, v = cb[none][:want_b], u[none][:want_b], v[none][:want_b]
            dc = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(len(cb))], axis=1)
            dc /= np.linalg.norm(dc, axis=1, keepdims=True)
            c, lm = np.concatenate([c, cb]), np.concatenate([lm, dc @ R])
            inf = np.concatenate([inf, np.ones(len(cb), bool)])
        self._pts = np.concatenate([self._pts, c])
        self._lm = np.concatenate([self._lm, lm])
        self._nobs = np.concatenate([self._nobs, np.ones(len(c), np.int32)])
        self._inf = np.concatenate([self._inf, inf])

    def _fit(
        self, Pw: np.ndarray, Qc: np.ndarray, plane_cam, plane_world
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Robust rigid fit ``Qc ~ R Pw + t``: (R, t, inlier mask) or None."""
        N = len(Pw)
        z = Qc[:, 2]
        thr = np.maximum(INLIER_MIN_M, INLIER_M_AT_1M * z * z)
        w = 1.0 / np.maximum(z, 0.3) ** WEIGHT_POWER
        if plane_cam is not None and plane_world is not None:
            return self._fit_plane(Pw, Qc, thr, w, plane_cam, plane_world)
        K = RANSAC_ITERS
        idx = self._samples(N, 3, K)
        R, t = kabsch(Pw[idx], Qc[idx])  # (K, 3, 3), (K, 3)
        res = np.linalg.norm(Pw[None] @ np.swapaxes(R, 1, 2) + t[:, None, :] - Qc[None], axis=2)
        inl = res < thr[None]
        best = int(np.argmax(inl.sum(axis=1)))
        m = inl[best]

        def refit(ww):
            R_, t_ = kabsch(Pw, Qc, ww)
            return (R_, t_), np.linalg.norm(Pw @ R_.T + t_ - Qc, axis=1)

        out = _irls(refit, m, w, thr, 3)
        return None if out is None else (out[0][0], out[0][1], out[1])

    def _fit_plane(self, Pw, Qc, thr, w, plane_cam, plane_world):
        """Fit with roll, pitch and height pinned by a plane: only yaw about its normal + in-plane shift."""
        n_c = np.asarray(plane_cam[0], np.float64)
        n_c = n_c / np.linalg.norm(n_c)
        n_w = np.asarray(plane_world[0], np.float64)
        n_w = n_w / np.linalg.norm(n_w)
        t_n = float(plane_world[1]) - float(plane_cam[1])  # n_c . t
        R0 = rotation_between(n_w, n_c)
        P = Pw @ R0.T
        e1, e2 = _basis(n_c)
        B = np.stack([e1, e2])  # (2, 3)
        p2, q2 = P @ B.T, Qc @ B.T
        res_n = (Qc @ n_c) - (P @ n_c) - t_n  # normal residual: independent of yaw and shift
        N = len(Pw)
        K = RANSAC_ITERS
        idx = self._samples(N, 2, K)

        def procrustes(a, b, ww):
            ww = ww / ww.sum(axis=-1, keepdims=True)
            ac = (a * ww[..., None]).sum(axis=-2)
            bc = (b * ww[..., None]).sum(axis=-2)
            a0, b0 = a - ac[..., None, :], b - bc[..., None, :]
            cr = (ww * (a0[..., 0] * b0[..., 1] - a0[..., 1] * b0[..., 0])).sum(axis=-1)
            dt = (ww * (a0[..., 0] * b0[..., 0] + a0[..., 1] * b0[..., 1])).sum(axis=-1)
            th = np.arctan2(cr, dt)
            c, s = np.cos(th), np.sin(th)
            rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
            t2 = bc - np.einsum("...ij,...j->...i", rot, ac)
            return rot, t2

        rot, t2 = procrustes(p2[idx], q2[idx], np.ones(idx.shape))
        r2 = p2[None] @ np.swapaxes(rot, 1, 2) + t2[:, None, :] - q2[None]
        res = np.sqrt((r2**2).sum(axis=2) + res_n[None] ** 2)
        inl = res < thr[None]
        m = inl[int(np.argmax(inl.sum(axis=1)))]

        def refit(ww):
            rot_, t2_ = procrustes(p2, q2, ww)
            r2_ = p2 @ rot_.T + t2_ - q2
            return (rot_, t2_), np.sqrt((r2_**2).sum(axis=1) + res_n**2)

        out = _irls(refit, m, w, thr, 2)
        if out is None:
            return None
        (rb, tb), m = out
        # rotation about n_c by the 2D angle, composed with the tilt correction
        c, s = rb[0, 0], rb[1, 0]
        Rn = (
            np.outer(n_c, n_c)
            + c * (np.eye(3) - np.outer(n_c, n_c))
            + s * np.array([[0, -n_c[2], n_c[1]], [n_c[2], 0, -n_c[0]], [-n_c[1], n_c[0], 0]])
        )
        R = Rn @ R0
        t = tb[0] * e1 + tb[1] * e2 + t_n * n_c
        return R, t, m

    def _samples(self, N: int, k: int, K: int) -> np.ndarray:
        """K random k-subsets of range(N) without repeats inside a subset (K, k)."""
        r = self._rng.random((K, N))
        return np.argpartition(r, k, axis=1)[:, :k] if N > k else np.tile(np.arange(N), (K, 1))
