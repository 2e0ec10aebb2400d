"""Intrinsic calibration of one camera from ChArUco detections (pinhole or fisheye lens model).

This module owns :func:`calibrate_intrinsics` (``cv2.calibrateCameraExtended`` for the pinhole
model, ``cv2.fisheye.calibrate`` for fisheye lenses) with the input checks calibration needs (one
image size, enough views, enough non-collinear corners per view), optional fixing of parameter
groups around a starting guess (needed when there are few or similar views, e.g. checking a factory
calibration), and :func:`evaluate_intrinsics`, which measures how well *given* intrinsics explain
the detections (per-view board pose by PnP, then reprojection RMS): the way to compare two
calibrations on the same images.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import CalibrationError, CameraCalib
from illuminet.calibration.charuco import Detection

log = logging.getLogger(__name__)

#: parameter groups that ``fix`` may name
FIXABLE = ("focal", "aspect", "principal_point", "distortion", "tangential")
#: distortion sets of the pinhole model: name -> number of coefficients
PINHOLE_DIST = {"none": 0, "standard": 5, "rational": 8}

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    camera : CameraCalib
        The calibrated camera (``rms_px`` filled in).
    rms_px : float
        Reprojection RMS over all corners of all views, pixels.
    per_view_rms : list of float
        Reprojection RMS per view (same order as ``paths``).
    paths : list of str
        The views used.
    rvecs, tvecs : list of ndarray
        Board pose per view (board -> camera), metres.
    fixed : tuple of str
        Parameter groups held at the guess.
    std : dict of str to float
        Standard deviations of fx, fy, cx, cy (pinhole only; empty for fisheye).
    """

    camera: CameraCalib
    rms_px: float
    per_view_rms: list[float]
    paths: list[str]
    rvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    tvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    fixed: tuple[str, ...] = ()
    std: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: model, size, K, distortion, RMS, fixed groups, standard deviations."""
        K = self.camera.K
        s = (
            f"{self.camera.model} {self.camera.width}x{self.camera.height}: fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} "
            f"cx={K[0, 2]:.2f} cy={K[1, 2]:.2f} dist={np.round(self.camera.dist, 5).tolist()} "
            f"rms={self.rms_px:.3f} px over {len(self.paths)} views"
        )
        if self.fixed:
            s += f" (fixed: {', '.join(self.fixed)})"
        if self.std:
            s += " std: " + " ".join(f"{k}={v:.2f}" for k, v in self.std.items())
        return s


def _check_sizes(dets: Sequence[Detection]) -> tuple[int, int]:
    sizes = sorted({d.image_size for d in dets})
    if len(sizes) > 1:
        by = {s: [d.path or "?" for d in dets if d.image_size == s] for s in sizes}
        listing = "; ".join(f"{w}x{h}: {', '.join(p[:3])}" for (w, h), p in by.items())
        raise CalibrationError(f"views have different image sizes ({listing}); calibrate one resolution at a time")
    return sizes[0]


def usable_views(dets: Sequence[Detection], spec: BoardSpec, min_corners: int) -> list[Detection]:
    """Views with at least ``min_corners`` corners that are not all on one line."""
    board = spec.cv_board()
    out = []
    for d in dets:
        if len(d) < min_corners:
            continue
        if board.checkCharucoCornersCollinear(d.ids.reshape(-1, 1)):
            log.info("%s: corners are collinear, view skipped", d.path)
            continue
        out.append(d)
    return out


def calibrate_intrinsics(
    dets: Sequence[Detection],
    spec: BoardSpec,
    model: str = "pinhole",
    *,
    dist_model: str = "standard",
    guess: CameraCalib | None = None,
    fix: Sequence[str] = (),
    min_views: int | None = None,
    min_corners: int | None = None,
) -> IntrinsicsResult:
    """Calibrate one camera's intrinsics from board detections.

    Parameters
    ----------
    dets : sequence of Detection
        From :func:`~illuminet.calibration.charuco.detect_files`; all of one image size.
    spec : BoardSpec
        The board that was photographed.
    model : str
        ``"pinhole"`` or ``"fisheye"``.
    dist_model : str
        Pinhole only: ``"none"``, ``"standard"`` (k1 k2 p1 p2 k3) or ``"rational"`` (+ k4 k5 k6).
    guess : CameraCalib, optional
        Starting intrinsics (e.g. a factory calibration); required to ``fix`` anything but the
        aspect ratio or tangential distortion.
    fix : sequence of str
        Parameter groups (:data:`FIXABLE`) held at the guess.
    min_views : int, optional
        Fewest usable views accepted. Default: 4 when everything is estimated, 1 when some group
        is fixed (checking a known calibration).
    min_corners : int, optional
        Fewest corners per usable view (default 6 pinhole, 8 fisheye).

    Raises
    ------
    CalibrationError
        Mixed image sizes, too few usable views, a bad ``fix`` name, a guess of another size, or an
        optimisation that fails to converge.
    """
    if model not in ("pinhole", "fisheye"):
        raise CalibrationError(f"model: expected 'pinhole' or 'fisheye', got {model!r}")
    bad = [f for f in fix if f not in FIXABLE]
    if bad:
        raise CalibrationError(f"fix: unknown parameter group(s) {bad}; expected some of {FIXABLE}")
    if not dets:
        raise CalibrationError("no views with the board: nothing to calibrate")
    size = _check_sizes(dets)
    if guess is not None:
        if guess.size != size:
            raise CalibrationError(
                f"the starting intrinsics are for {guess.width}x{guess.height}, the images are {size[0]}x{size[1]}"
            )
        if guess.model != model:
            raise CalibrationError(f"the starting intrinsics use the {guess.model} model, asked for {model}")
    elif any(f in fix for f in ("focal", "principal_point", "distortion")):
        raise CalibrationError(f"fixing {', '.join(fix)} needs starting intrinsics (--guess FILE)")
    if dist_model not in PINHOLE_DIST:
        raise CalibrationError(f"dist_model: expected one of {tuple(PINHOLE_DIST)}, got {dist_model!r}")
    min_corners = min_corners or (8 if model == "fisheye" else 6)
    views = usable_views(dets, spec, min_corners)
    if min_views is None:
        min_views = 1 if any(f in fix for f in ("focal", "principal_point", "distortion")) else 4
    if len(views) < min_views:
        raise CalibrationError(
            f"too few views: {len(views)} usable view(s) of the board (of {len(dets)} with the board, each needing "
            f">= {min_corners} non-collinear corners), need at least {min_views}; capture more views at "
            "different angles and distances (`illuminet calibrate capture`)"
        )
    obj = [d.object_points(spec).astype(np.float64) for d in views]
    img = [d.corners.astype(np.float64) for d in views]
    if model == "fisheye":
        return _fisheye(views, obj, img, size, guess, tuple(fix))
    return _pinhole(views, obj, img, size, guess, tuple(fix), dist_model)


def _pinhole(views, obj, img, size, guess, fix, dist_model) -> IntrinsicsResult:
    n_dist = PINHOLE_DIST[dist_model]
    flags = 0
    if dist_model == "rational":
        flags |= cv2.CALIB_RATIONAL_MODEL
    if guess is not None:
        K0 = guess.K.copy()
        D0 = np.zeros(max(n_dist, 5))
        gd = np.asarray(guess.dist, float).ravel()
        D0[: min(len(gd), len(D0))] = gd[: len(D0)]
        if len(gd) > 8 and dist_model != "none":
            # a 12/14-coefficient guess (DepthAI) is cut to the model asked for: say so
            log.warning("starting distortion has %d coefficients; using the first %d", len(gd), len(D0))
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    else:
        w, h = size
        f0 = 0.8 * max(w, h)
        K0 = np.array([[f0, 0, (w - 1) / 2], [0, f0, (h - 1) / 2], [0, 0, 1.0]])
        D0 = np.zeros(max(n_dist, 5))
    if "focal" in fix:
        flags |= cv2.CALIB_FIX_FOCAL_LENGTH
    if "aspect" in fix:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if "principal_point" in fix:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if "tangential" in fix:
        flags |= cv2.CALIB_FIX_TANGENT_DIST if guess is not None else cv2.CALIB_ZERO_TANGENT_DIST
    if "distortion" in fix or n_dist == 0:
        flags |= (
            cv2.CALIB_FIX_K1
            | cv2.CALIB_FIX_K2
            | cv2.CALIB_FIX_K3
            | cv2.CALIB_FIX_K4
            | cv2.CALIB_FIX_K5
            | cv2.CALIB_FIX_K6
            | cv2.CALIB_FIX_TANGENT_DIST
        )
        if n_dist == 0:
            D0[:] = 0.0
    try:
        rms, K, D, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
            [o.astype(np.float32) for o in obj],
            [i.astype(np.float32) for i in img],
            size,
            K0,
            D0,
            flags=flags,
            criteria=_CRITERIA,
        )
    except cv2.error as e:
        raise CalibrationError(f"pinhole calibration failed ({len(views)} views): {e.err or e}") from None
    D = np.asarray(D, float).ravel()[: n_dist if n_dist else 0]
    if n_dist == 5 and len(D) < 5:
        D = np.pad(D, (0, 5 - len(D)))
    std_in = np.asarray(std_in).ravel()
    std = {k: float(v) for k, v in zip(("fx", "fy", "cx", "cy"), std_in[:4])}
    cam = CameraCalib(size[0], size[1], np.asarray(K, float), D, "pinhole", float(rms))
    _check_sane(cam, rms)
    return IntrinsicsResult(
        cam,
        float(rms),
        [float(v) for v in np.asarray(per_view).ravel()],
        [d.path for d in views],
        list(rvecs),
        list(tvecs),
        fix,
        std,
    )


def _fisheye(views, obj, img, size, guess, fix) -> IntrinsicsResult:
    if "distortion" in fix and guess is not None:
        # cv2.fisheye.calibrate's CALIB_FIX_K* set the coefficients to zero (not to the guess), so a
        # fixed non-zero distortion is handled by our own small solver
        return _fisheye_fixed_distortion(views, obj, img, size, guess, fix)
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
    if guess is not None:
        K0 = guess.K.copy()
        D0 = np.zeros((4, 1))
        gd = np.asarray(guess.dist, float).ravel()[:4]
        D0[: len(gd), 0] = gd
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    else:
        w, h = size
        # equidistant model: the image half-diagonal at ~90 degrees off axis is a fair start
        f0 = 0.5 * np.hypot(w, h) / (np.pi / 2)
        K0 = np.array([[f0, 0, (w - 1) / 2], [0, f0, (h - 1) / 2], [0, 0, 1.0]])
        D0 = np.zeros((4, 1))
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    if "focal" in fix:
        flags |= cv2.CALIB_FIX_FOCAL_LENGTH
    if "principal_point" in fix:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    if "distortion" in fix:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4
    # OpenCV 5's fisheye.calibrate accepts (1, N, 3) / (1, N, 2) per view (not (N, 1, 3))
    o = [x.reshape(1, -1, 3) for x in obj]
    i = [x.reshape(1, -1, 2) for x in img]
    try:
        rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(o, i, size, K0, D0, flags=flags, criteria=_CRITERIA)
    except cv2.error as e:
        raise CalibrationError(
            f"fisheye calibration failed ({len(views)} views): {e.err or e}; fisheye calibration needs views "
            "that fill the image corners, or a starting guess (--guess) with some parameters fixed"
        ) from None
    if "distortion" in fix and guess is not None:
        D = D0  # the fixed coefficients are the guess's (OpenCV may report them as zeros)
    per_view = []
    for oo, ii, rv, tv in zip(o, i, rvecs, tvecs):
        proj, _ = cv2.fisheye.projectPoints(oo, rv, tv, K, D)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - ii.reshape(-1, 2)) ** 2, axis=1)))))
    cam = CameraCalib(size[0], size[1], np.asarray(K, float), np.asarray(D, float).ravel(), "fisheye", float(rms))
    _check_sane(cam, rms)
    return IntrinsicsResult(cam, float(rms), per_view, [d.path for d in views], list(rvecs), list(tvecs), fix)


def _fisheye_fixed_distortion(views, obj, img, size, guess, fix) -> IntrinsicsResult:
    """Fisheye intrinsics with the distortion held at ``guess``: variable projection.

    The free intrinsics (fx, fy, and cx, cy unless fixed) are fitted by Levenberg-Marquardt with a
    numerical Jacobian; for every trial the 6 pose parameters of each view are re-solved by PnP, so
    the problem stays tiny (at most 4 unknowns) whatever the number of views.
    """
    D = np.zeros((4, 1))
    D[: min(4, len(guess.dist)), 0] = np.asarray(guess.dist, float).ravel()[:4]
    K0 = guess.K.copy()
    free = [] if "focal" in fix else ([(0, 0)] if "aspect" in fix else [(0, 0), (1, 1)])
    if "principal_point" not in fix:
        free += [(0, 2), (1, 2)]
    o = [x.reshape(-1, 1, 3) for x in obj]
    i = [x.reshape(-1, 1, 2) for x in img]
    poses = [None] * len(o)

    def make_K(p):
        K = K0.copy()
        for (r, c), v in zip(free, p):
            K[r, c] = v
        if "aspect" in fix and "focal" not in fix:
            K[1, 1] = p[0] * K0[1, 1] / K0[0, 0]
        return K

    def residuals(p, keep=False):
        K = make_K(p)
        res, out_poses = [], []
        for k, (oo, ii) in enumerate(zip(o, i)):
            if poses[k] is None:
                ok, rv, tv = cv2.fisheye.solvePnP(oo, ii, K, D, criteria=_CRITERIA)
            else:
                ok, rv, tv = cv2.fisheye.solvePnP(
                    oo,
                    ii,
                    K,
                    D,
                    rvec=poses[k][0].copy(),
                    tvec=poses[k][1].copy(),
                    useExtrinsicGuess=True,
                    criteria=_CRITERIA,
                )
            proj, _ = cv2.fisheye.projectPoints(oo, rv, tv, K, D)
            res.append((proj - ii).ravel())
            out_poses.append((rv, tv))
        if keep:
            poses[:] = out_poses
        return np.concatenate(res), out_poses

    p = np.array([K0[r, c] for r, c in free], float)
    r, _ = residuals(p, keep=True)
    lam = 1e-3
    for _ in range(50):
        if len(p) == 0:
            break
        J = np.empty((len(r), len(p)))
        for j in range(len(p)):
            dp = np.zeros_like(p)
            dp[j] = 1e-3
            J[:, j] = (residuals(p + dp)[0] - r) / 1e-3
        A, g = J.T @ J, J.T @ r
        step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-9), -g)
        r_new, _ = residuals(p + step)
        if r_new @ r_new < r @ r:
            p = p + step
            r, _ = residuals(p, keep=True)
            lam = max(lam / 10, 1e-7)
            if np.abs(step).max() < 1e-6:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    K = make_K(p)
    r, ps = residuals(p, keep=True)
    per_view, start = [], 0
    for oo in o:
        n = 2 * len(oo)
        per_view.append(float(np.sqrt(np.mean(r[start : start + n] ** 2) * 2)))
        start += n
    rms = float(np.sqrt(np.mean(r**2) * 2))
    cam = CameraCalib(size[0], size[1], K, D.ravel(), "fisheye", rms)
    _check_sane(cam, rms)
    return IntrinsicsResult(cam, rms, per_view, [d.path for d in views], [q[0] for q in ps], [q[1] for q in ps], fix)


def _check_sane(cam: CameraCalib, rms: float) -> None:
    K = cam.K
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.isfinite(rms):
        raise CalibrationError(f"calibration diverged (K={K.tolist()}, rms={rms}); use more and more varied views")
    if rms > 2.0:
        log.warning(
            "reprojection RMS %.2f px is high: wrong board size/legacy flag, motion blur, or a lens "
            "model that does not fit (try --model fisheye or --dist rational)",
            rms,
        )


@dataclass
class Evaluation:
    """How well fixed intrinsics explain detections (see :func:`evaluate_intrinsics`)."""

    rms_px: float
    per_view_rms: list[float]
    paths: list[str]
    rvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    tvecs: list[np.ndarray] = field(repr=False, default_factory=list)


def board_pose(det: Detection, spec: BoardSpec, cam: CameraCalib) -> tuple[np.ndarray, np.ndarray, float]:
    """Board pose (rvec, tvec, board -> camera, metres) in one view with given intrinsics, and its RMS.

    Pinhole: ``cv2.solvePnP`` (iterative, refined). Fisheye: ``cv2.fisheye.solvePnP``.
    """
    if det.image_size != cam.size:
        raise CalibrationError(
            f"{det.path or 'view'}: image is {det.image_size[0]}x{det.image_size[1]}, intrinsics are for "
            f"{cam.width}x{cam.height}"
        )
    obj = det.object_points(spec).astype(np.float64).reshape(-1, 1, 3)
    img = det.corners.astype(np.float64).reshape(-1, 1, 2)
    if cam.model == "fisheye":
        D = np.zeros((4, 1))
        D[: min(4, len(cam.dist)), 0] = np.asarray(cam.dist, float).ravel()[:4]
        ok, rv, tv = cv2.fisheye.solvePnP(obj, img, cam.K, D, flags=cv2.SOLVEPNP_ITERATIVE, criteria=_CRITERIA)
        proj, _ = cv2.fisheye.projectPoints(obj, rv, tv, cam.K, D)
    else:
        ok, rv, tv = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            rv, tv = cv2.solvePnPRefineLM(obj, img, cam.K, cam.dist, rv, tv)
        proj, _ = cv2.projectPoints(obj, rv, tv, cam.K, cam.dist)
    if not ok:
        raise CalibrationError(f"{det.path or 'view'}: board pose could not be estimated")
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
    return np.asarray(rv, float).ravel(), np.asarray(tv, float).ravel(), rms


def evaluate_intrinsics(dets: Sequence[Detection], spec: BoardSpec, cam: CameraCalib) -> Evaluation:
    """Reprojection RMS of ``cam`` on the detections, each view's board pose solved by PnP.

    This compares calibrations fairly on the same images: only the 6 pose parameters per view are
    fitted, the intrinsics are taken as given.
    """
    if not dets:
        raise CalibrationError("no views to evaluate")
    errs, sq, n, rvecs, tvecs = [], 0.0, 0, [], []
    for d in dets:
        rv, tv, rms = board_pose(d, spec, cam)
        errs.append(rms)
        sq += rms**2 * len(d)
        n += len(d)
        rvecs.append(rv)
        tvecs.append(tv)
    return Evaluation(float(np.sqrt(sq / n)), errs, [d.path for d in dets], rvecs, tvecs)
