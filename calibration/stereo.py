"""Stereo: calibrating a pair from ChArUco views, rectification, and host stereo depth.

This module owns :func:`calibrate_stereo` (the pose of the right camera in the left one, from views
where both cameras see the board) and :class:`HostStereo`, which turns a raw left/right pair from a
V4L2 stereo camera into the rectified left colour image and a depth map in metres aligned to it:
rectification maps are built once (``cv2.stereoRectify`` + ``cv2.initUndistortRectifyMap``, or the
``cv2.fisheye`` variants), then per pair ``cv2.StereoSGBM`` on both views, the ximgproc
weighted-least-squares filter (``createDisparityWLSFilter`` + ``createRightMatcher``) and its
confidence map to mark unreliable pixels invalid (0).

Speed: matching runs at a reduced resolution (``scale``, default 0.5) because SGBM's cost grows with
width x height x disparities; the depth is brought back to full size by nearest-neighbour so that
no depth is invented between a foreground and a background.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import Calibration, CalibrationError, CameraCalib, StereoCalib
from illuminet.calibration.charuco import Detection
from illuminet.runtime.frame import Intrinsics

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------------
# stereo calibration

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass
class StereoResult:
    """Outcome of :func:`calibrate_stereo`: the pair (with rectification when horizontal) and its fit."""

    stereo: StereoCalib
    rms_px: float
    pairs: list[tuple[str, str]]
    per_pair_rms: list[float]

    def summary(self) -> str:
        """One line: baseline, T, rotation angle, RMS, number of pairs."""
        T = np.asarray(self.stereo.T).ravel()
        ang = float(np.degrees(np.linalg.norm(cv2.Rodrigues(np.asarray(self.stereo.R))[0])))
        return (
            f"stereo {self.stereo.left}->{self.stereo.right}: baseline {self.stereo.baseline_m * 1000:.2f} mm, "
            f"T = [{T[0]:.5f}, {T[1]:.5f}, {T[2]:.5f}] m, rotation {ang:.3f} deg, rms {self.rms_px:.3f} px "
            f"over {len(self.pairs)} pairs"
        )


def pair_views(left: Sequence[Detection], right: Sequence[Detection]) -> list[tuple[Detection, Detection]]:
    """Pair left and right views of the same instant.

    Files are paired by name once the words ``left``/``right`` (and ``l``/``r`` prefixes such as
    ``left_0001``) are removed; when names do not pair up, by sorted order if the counts match.
    """

    def key(d: Detection) -> str:
        n = Path(d.path).stem.lower()
        for w in ("left", "right", "cam_b", "cam_c"):
            n = n.replace(w, "")
        return n.strip("_-. ")

    lk = {key(d): d for d in left}
    rk = {key(d): d for d in right}
    common = sorted(set(lk) & set(rk))
    if common and len(lk) == len(left) and len(rk) == len(right):
        return [(lk[k], rk[k]) for k in common]
    if len(left) != len(right):
        raise CalibrationError(
            f"cannot pair {len(left)} left with {len(right)} right views: name them alike (left_0001.png / "
            "right_0001.png) or give the same number of images in the same order"
        )
    return list(zip(sorted(left, key=lambda d: d.path), sorted(right, key=lambda d: d.path)))


def _common_corners(pairs, spec: BoardSpec, left: CameraCalib, right: CameraCalib, min_common: int):
    """Board points and their pixels in both images for every pair with at least ``min_common``
    corners seen by both cameras: (object points, left pixels, right pixels, (left path, right path)) lists."""
    obj, pl, pr, used = [], [], [], []
    for dl, dr in pairs:
        for d, cam, side in ((dl, left, "left"), (dr, right, "right")):
            if d.image_size != cam.size:
                raise CalibrationError(
                    f"{d.path}: {side} image is {d.image_size[0]}x{d.image_size[1]}, its intrinsics are for "
                    f"{cam.width}x{cam.height}"
                )
        common, il, ir = np.intersect1d(dl.ids, dr.ids, return_indices=True)
        if len(common) < min_common:
            continue
        obj.append(spec.corner_points()[common].astype(np.float64))
        pl.append(dl.corners[il].astype(np.float64))
        pr.append(dr.corners[ir].astype(np.float64))
        used.append((dl.path, dr.path))
    return obj, pl, pr, used


def _solve_pinhole(obj, pl, pr, left: CameraCalib, right: CameraCalib):
    """(R, T, rms px, per-pair rms px) from OpenCV's stereo calibration with the intrinsics fixed."""
    try:
        rms, _, _, _, _, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
            [o.astype(np.float32) for o in obj],
            [p.astype(np.float32) for p in pl],
            [p.astype(np.float32) for p in pr],
            left.K,
            left.dist,
            right.K,
            right.dist,
            left.size,
            np.eye(3),
            np.zeros((3, 1)),
            flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=_CRITERIA,
        )
    except cv2.error as e:
        raise CalibrationError(f"stereo calibration failed ({len(obj)} pairs): {e.err or e}") from None
    per = [float(np.sqrt(np.mean(np.square(v)))) for v in np.asarray(per_view).reshape(len(obj), -1)]
    return R, T, rms, per


def _solve_fisheye(obj, pl, pr, left: CameraCalib, right: CameraCalib):
    """(R, T, rms px, per-pair rms px) for fisheye lenses, errors measured through the fisheye model.

    cv2.fisheye.stereoCalibrate (OpenCV 5.0) fails when views have different numbers of points,
    which partial ChArUco views always do. With the intrinsics fixed, the fisheye lens can be taken
    out exactly: undistort to normalised rays, then solve the pose with the pinhole stereoCalibrate
    on a distortion-free virtual camera of the same focal length.
    """
    D1 = left.dist.reshape(4, 1).astype(np.float64)
    D2 = right.dist.reshape(4, 1).astype(np.float64)
    f = float(left.K[0, 0])
    Kv = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]])
    nl = [cv2.fisheye.undistortPoints(p.reshape(-1, 1, 2), left.K, D1).reshape(-1, 2) * f for p in pl]
    nr = [cv2.fisheye.undistortPoints(p.reshape(-1, 1, 2), right.K, D2).reshape(-1, 2) * f for p in pr]
    try:
        _, _, _, _, _, R, T, _, _, rvecs, tvecs, _ = cv2.stereoCalibrateExtended(
            [o.astype(np.float32) for o in obj],
            [p.astype(np.float32) for p in nl],
            [p.astype(np.float32) for p in nr],
            Kv,
            np.zeros(5),
            Kv,
            np.zeros(5),
            left.size,
            np.eye(3),
            np.zeros((3, 1)),
            flags=cv2.CALIB_FIX_INTRINSIC,
            criteria=_CRITERIA,
        )
    except cv2.error as e:
        raise CalibrationError(f"fisheye stereo calibration failed ({len(obj)} pairs): {e.err or e}") from None
    per, sq, n = [], 0.0, 0
    for o, a, b, rv, tv in zip(obj, pl, pr, rvecs, tvecs):
        Rl = cv2.Rodrigues(rv)[0]
        rv2 = cv2.Rodrigues(R @ Rl)[0]
        tv2 = R @ np.asarray(tv).reshape(3, 1) + np.asarray(T).reshape(3, 1)
        p1, _ = cv2.fisheye.projectPoints(o.reshape(-1, 1, 3), rv, tv, left.K, D1)
        p2, _ = cv2.fisheye.projectPoints(o.reshape(-1, 1, 3), rv2, tv2, right.K, D2)
        e = np.concatenate([p1.reshape(-1, 2) - a, p2.reshape(-1, 2) - b])
        per.append(float(np.sqrt(np.mean(np.sum(e**2, axis=1)))))
        sq += float(np.sum(e**2))
        n += len(e)
    return R, T, float(np.sqrt(sq / n)), per


def calibrate_stereo(
    left_dets: Sequence[Detection],
    right_dets: Sequence[Detection],
    spec: BoardSpec,
    left: CameraCalib,
    right: CameraCalib,
    names: tuple[str, str] = ("left", "right"),
    min_pairs: int = 3,
    min_common: int = 6,
) -> StereoResult:
    """Pose of the right camera in the left one from simultaneous views, intrinsics held fixed.

    Parameters
    ----------
    left_dets, right_dets : sequence of Detection
        Board detections in the left and right images (paired by :func:`pair_views`).
    left, right : CameraCalib
        Intrinsics of both cameras (from :func:`~illuminet.calibration.intrinsics.calibrate_intrinsics`).
    names : (str, str)
        Camera names written into the result.
    min_pairs, min_common : int
        Fewest usable pairs, and fewest corners seen by both cameras in a pair.

    Raises
    ------
    CalibrationError
        Sizes that do not match the intrinsics, too few pairs with enough common corners, mixed
        lens models, or an optimisation failure.
    """
    if left.model != right.model:
        raise CalibrationError(f"stereo calibration needs one lens model, got {left.model} and {right.model}")
    pairs = pair_views(left_dets, right_dets)
    obj, pl, pr, used = _common_corners(pairs, spec, left, right, min_common)
    if len(used) < min_pairs:
        raise CalibrationError(
            f"too few stereo pairs: {len(used)} pair(s) where both cameras see >= {min_common} common corners "
            f"(of {len(pairs)} pairs), need at least {min_pairs}"
        )
    solve = _solve_fisheye if left.model == "fisheye" else _solve_pinhole
    R, T, rms, per = solve(obj, pl, pr, left, right)
    R = np.asarray(R, float)
    T = np.asarray(T, float).ravel()
    st = StereoCalib(names[0], names[1], R, T, rms_px=float(rms))
    T_ok = abs(T[0]) >= abs(T[1]) and T[0] < 0
    if T_ok:
        rect = rectify(left, right, st)
        st = replace(st, rectification=rect.as_dict())
    else:
        log.warning("stereo pair is not a horizontal left/right pair (T = %s m): no rectification stored", T.tolist())
    return StereoResult(st, float(rms), used, per)


# ---------------------------------------------------------------------------------------------------
# rectification


@dataclass(frozen=True)
class Rectification:
    """Rectification of a stereo pair for one image size (OpenCV ``stereoRectify`` outputs)."""

    size: tuple[int, int]
    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray

    @property
    def baseline_m(self) -> float:
        """Baseline along the rectified x axis, metres (P2[0,3] = -fx * B)."""
        return float(-self.P2[0, 3] / self.P2[0, 0])

    def as_dict(self) -> dict[str, np.ndarray]:
        """``{"R1", "R2", "P1", "P2", "Q"}`` as stored in :attr:`StereoCalib.rectification`."""
        return {"R1": self.R1, "R2": self.R2, "P1": self.P1, "P2": self.P2, "Q": self.Q}


def rectify(
    left: CameraCalib,
    right: CameraCalib,
    stereo: StereoCalib,
    alpha: float = 0.0,
    fisheye_balance: float = 0.0,
    fisheye_fov_scale: float = 1.0,
) -> Rectification:
    """Rectification of a horizontal stereo pair (principal points made equal: ``CALIB_ZERO_DISPARITY``).

    Parameters
    ----------
    left, right : CameraCalib
        Both at the same image size and of the same model.
    stereo : StereoCalib
        ``X_right = R @ X_left + T``; the right camera must be to the right (``T[0] < 0``).
    alpha : float
        Pinhole: 0 keeps only valid pixels (zoomed in), 1 keeps all source pixels (black borders).
    fisheye_balance, fisheye_fov_scale : float
        Fisheye: ``cv2.fisheye.stereoRectify``'s balance (0 = crop to valid, 1 = keep all) and
        divisor of the new focal length.
    """
    if left.size != right.size:
        raise CalibrationError(
            f"stereo cameras {stereo.left!r} {left.width}x{left.height} and {stereo.right!r} "
            f"{right.width}x{right.height} differ in size; rectification needs one image size"
        )
    if left.model != right.model:
        raise CalibrationError(
            f"stereo cameras {stereo.left!r} ({left.model}) and {stereo.right!r} ({right.model}) use "
            "different lens models; host stereo needs both pinhole or both fisheye"
        )
    T = np.asarray(stereo.T, float).reshape(3)
    if abs(T[0]) < abs(T[1]):
        raise CalibrationError(
            f"stereo baseline T={T.tolist()} m is mostly vertical; host stereo matches along rows and "
            "needs a horizontal pair (rotate the images by 90 degrees and recalibrate)"
        )
    if T[0] > 0:
        raise CalibrationError(
            f"stereo T={T.tolist()} m puts camera {stereo.right!r} to the LEFT of {stereo.left!r} "
            "(expected T[0] < 0 for X_right = R X_left + T): left and right are swapped"
        )
    size = left.size
    R = np.asarray(stereo.R, float)
    if left.model == "fisheye":
        R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(
            left.K,
            _fisheye_d(left.dist),
            right.K,
            _fisheye_d(right.dist),
            size,
            R,
            T.reshape(3, 1),
            cv2.CALIB_ZERO_DISPARITY,
            balance=fisheye_balance,
            fov_scale=fisheye_fov_scale,
        )
    else:
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
            left.K,
            left.dist,
            right.K,
            right.dist,
            size,
            R,
            T.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY,
            alpha=alpha,
        )
    return Rectification(size=size, R1=R1, R2=R2, P1=P1, P2=P2, Q=Q)


def _fisheye_d(dist: np.ndarray) -> np.ndarray:
    d = np.zeros(4) if len(dist) == 0 else np.asarray(dist, float).ravel()[:4]
    return d.reshape(4, 1)


def rectify_maps(
    cam: CameraCalib, R: np.ndarray, P: np.ndarray, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-point remap tables (``CV_16SC2``) taking ``cam``'s raw image to the rectified one."""
    size = size or cam.size
    if cam.model == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(cam.K, _fisheye_d(cam.dist), R, P, size, cv2.CV_16SC2)
    return cv2.initUndistortRectifyMap(cam.K, cam.dist, R, P, size, cv2.CV_16SC2)


# ---------------------------------------------------------------------------------------------------
# host stereo depth


class HostStereo:
    """Depth from a raw stereo pair on the host: rectify, SGBM left+right, WLS filter, metres.

    Parameters
    ----------
    calib : Calibration
        With a ``stereo`` section. When ``image_size`` differs from the calibrated size the
        calibration is rescaled (same aspect ratio only, see :meth:`Calibration.scaled_to`).
    image_size : (int, int), optional
        (width, height) of the raw images that :meth:`compute` will get; default: calibrated size.
    scale : float
        Matching resolution relative to the image (0.5 = half width and height: ~4x faster SGBM).
    min_depth_m : float
        Nearest depth to measure; sets SGBM's disparity range (rounded up to a multiple of 16).
    num_disparities : int, optional
        Overrides the range derived from ``min_depth_m`` (at matching resolution, multiple of 16).
    block_size : int
        SGBM block size (odd).
    wls_lambda, wls_sigma : float
        WLS smoothness strength and edge sensitivity (OpenCV's defaults 8000 and 1.5).
    min_confidence : float
        WLS confidence (0..255) below which a pixel is marked invalid; the WLS filter fills
        occlusions and textureless areas with plausible but unmeasured values, which must not reach
        the plane fitting as depth.
    max_depth_m : float
        Depth beyond this is marked invalid (disparity of a fraction of a pixel).
    alpha, fisheye_balance : float
        Passed to :func:`rectify`.
    """

    def __init__(
        self,
        calib: Calibration,
        image_size: tuple[int, int] | None = None,
        *,
        scale: float = 0.5,
        min_depth_m: float = 0.35,
        num_disparities: int | None = None,
        block_size: int = 5,
        wls_lambda: float = 8000.0,
        wls_sigma: float = 1.5,
        min_confidence: float = 96.0,
        max_depth_m: float = 15.0,
        alpha: float = 0.0,
        fisheye_balance: float = 0.0,
    ):
        st = calib.require_stereo()
        left, right = calib.camera(st.left), calib.camera(st.right)
        if image_size is not None and tuple(image_size) != left.size:
            calib = calib.scaled_to(*image_size)
            st = calib.require_stereo()
            left, right = calib.camera(st.left), calib.camera(st.right)
        if not 0.1 <= scale <= 1.0:
            raise ValueError(f"HostStereo scale must be in [0.1, 1], got {scale}")
        if block_size < 1 or block_size % 2 == 0:
            raise ValueError(f"HostStereo block_size must be a positive odd number, got {block_size}")
        self.calibration = calib
        self.size = left.size
        rect = None
        if st.rectification is not None and alpha == 0.0 and fisheye_balance == 0.0:
            r = st.rectification
            rect = Rectification(self.size, *(np.asarray(r[k], float) for k in ("R1", "R2", "P1", "P2", "Q")))
        if rect is None:
            rect = rectify(left, right, st, alpha=alpha, fisheye_balance=fisheye_balance)
        self.rectification = rect
        self._map_l = rectify_maps(left, rect.R1, rect.P1, self.size)
        self._map_r = rectify_maps(right, rect.R2, rect.P2, self.size)
        self.scale = float(scale)
        w, h = self.size
        self._small = (max(16, int(round(w * scale))), max(16, int(round(h * scale))))
        self._sx = self._small[0] / w  # exact ratio used for the disparity -> depth conversion
        self.fx_rect = float(rect.P1[0, 0])
        self.baseline_m = rect.baseline_m
        if num_disparities is None:
            d_max = self.fx_rect * self._sx * self.baseline_m / max(min_depth_m, 1e-3)
            num_disparities = int(np.ceil(d_max / 16.0)) * 16
        num_disparities = int(min(max(16, num_disparities), 16 * ((self._small[0] - 1) // 16)))
        if num_disparities % 16:
            raise ValueError(f"num_disparities must be a multiple of 16, got {num_disparities}")
        self.num_disparities = num_disparities
        self.min_confidence = float(min_confidence)
        self.max_depth_m = float(max_depth_m)
        ch = 1  # grey matching: colour adds cost and little on stereo cameras (often mono sensors)
        self._left_matcher = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=num_disparities,
            blockSize=block_size,
            P1=8 * ch * block_size**2,
            P2=32 * ch * block_size**2,
            disp12MaxDiff=1,
            uniquenessRatio=10,
            speckleWindowSize=0,
            speckleRange=0,
            preFilterCap=63,
            mode=cv2.StereoSGBM_MODE_SGBM_3WAY,
        )
        self._right_matcher = cv2.ximgproc.createRightMatcher(self._left_matcher)
        self._wls = cv2.ximgproc.createDisparityWLSFilter(self._left_matcher)
        self._wls.setLambda(float(wls_lambda))
        self._wls.setSigmaColor(float(wls_sigma))
        self.intrinsics = Intrinsics(
            fx=float(rect.P1[0, 0]),
            fy=float(rect.P1[1, 1]),
            cx=float(rect.P1[0, 2]),
            cy=float(rect.P1[1, 2]),
            width=int(w),
            height=int(h),
            dist=(),
        )
        self.last_confidence: np.ndarray | None = None

    def rectify_pair(self, left_bgr: np.ndarray, right_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Remap both raw images to the rectified geometry (same channels as given)."""
        self._check(left_bgr, "left")
        self._check(right_bgr, "right")
        lr = cv2.remap(left_bgr, self._map_l[0], self._map_l[1], cv2.INTER_LINEAR)
        rr = cv2.remap(right_bgr, self._map_r[0], self._map_r[1], cv2.INTER_LINEAR)
        return lr, rr

    def _check(self, img: np.ndarray, side: str) -> None:
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim not in (2, 3):
            raise ValueError(
                f"HostStereo: {side} image must be a uint8 HxW or HxWx3 array, got "
                f"{getattr(img, 'shape', type(img))} {getattr(img, 'dtype', '')}"
            )
        if (img.shape[1], img.shape[0]) != self.size:
            raise CalibrationError(
                f"HostStereo: {side} image is {img.shape[1]}x{img.shape[0]}, but the stereo calibration is "
                f"for {self.size[0]}x{self.size[1]} (create HostStereo with image_size=(w, h) to rescale)"
            )

    def disparity(self, left_rect_gray: np.ndarray, right_rect_gray: np.ndarray) -> np.ndarray:
        """WLS-filtered disparity at matching resolution, float32 pixels of that resolution, 0 = invalid."""
        if self._sx != 1.0:
            gl = cv2.resize(left_rect_gray, self._small, interpolation=cv2.INTER_AREA)
            gr = cv2.resize(right_rect_gray, self._small, interpolation=cv2.INTER_AREA)
        else:
            gl, gr = left_rect_gray, right_rect_gray
        dl = self._left_matcher.compute(gl, gr)
        dr = self._right_matcher.compute(gr, gl)
        filt = self._wls.filter(dl, gl, disparity_map_right=dr)
        conf = self._wls.getConfidenceMap()
        self.last_confidence = conf
        disp = filt.astype(np.float32) * np.float32(1.0 / 16.0)
        bad = (conf < self.min_confidence) | (disp <= 0.0)
        # the left band narrower than the disparity range has no match in the right image
        bad[:, : self.num_disparities] = True
        disp[bad] = 0.0
        return disp

    def compute(self, left_bgr: np.ndarray, right_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One raw pair -> (rectified left image RGB uint8, depth float32 metres aligned to it, 0 = invalid).

        Parameters
        ----------
        left_bgr, right_bgr : ndarray
            Raw (unrectified) images of the calibrated size, BGR uint8 as OpenCV delivers (or grey).
        """
        self._check(left_bgr, "left")
        self._check(right_bgr, "right")
        # only the left image is needed in colour: the right one is converted to grey before the
        # remap (a third of the work)
        lr = cv2.remap(left_bgr, self._map_l[0], self._map_l[1], cv2.INTER_LINEAR)
        gl = lr if lr.ndim == 2 else cv2.cvtColor(lr, cv2.COLOR_BGR2GRAY)
        r_gray = right_bgr if right_bgr.ndim == 2 else cv2.cvtColor(right_bgr, cv2.COLOR_BGR2GRAY)
        gr = cv2.remap(r_gray, self._map_r[0], self._map_r[1], cv2.INTER_LINEAR)
        disp = self.disparity(gl, gr)
        fb = np.float32(self.fx_rect * self._sx * self.baseline_m)
        with np.errstate(divide="ignore"):
            depth = np.where(disp > 0.0, fb / np.maximum(disp, 1e-6), 0.0).astype(np.float32)
        depth[depth > self.max_depth_m] = 0.0
        if self._sx != 1.0:
            depth = cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST)
        rgb = cv2.cvtColor(lr, cv2.COLOR_GRAY2RGB) if lr.ndim == 2 else cv2.cvtColor(lr, cv2.COLOR_BGR2RGB)
        return rgb, depth
