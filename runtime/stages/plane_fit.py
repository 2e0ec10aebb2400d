"""Planes from depth, one frame at a time: the point cloud, the three detection methods, labels.

What this module owns
    * :func:`make_cloud`: the organised, downsampled point cloud (about 160 x 100 points for a
      640 x 400 frame) with per-point normals that every method works on. Points keep the exact
      full-resolution pixel they came from (strided sampling, no resampling), so nothing is lost to
      interpolation and depth edges do not create "flying" points.
    * Three segmentations of that cloud into planes, selected by ``[planes] method``
      (:func:`detect_planes`):

      ``ransac``  sequential RANSAC: many 3-point hypotheses scored at once (vectorised) on a random
                  subset, with a normal-consistency test; the best plane's inliers are removed and the
                  search repeats.
      ``region``  region growing by connected components: pixels whose normal agrees with their
                  4 neighbours and whose neighbours lie on their tangent plane form smooth regions
                  (``cv2.connectedComponentsWithStats``); each large region seeds a plane that then
                  grows to every point within the inlier distance.
      ``opencv``  OpenCV 5's ``cv2.findPlanes`` (block-wise plane growing from the former rgbd
                  module) on the same cloud.

      All three share the final step (:func:`refine`): a weighted least-squares refit on the
      inliers (twice, with the inlier set recomputed), so they differ only in how they segment.
      docs/planes.md compares them on accuracy and speed and says why ``ransac`` is the default.
    * Labels: ``floor``/``table`` (horizontal, facing up), ``wall`` (vertical), ``other``, using
      gravity when the frame has it; without gravity the "up" direction is estimated (see
      :func:`estimate_up`).
    * :func:`check_depth`: the bad-depth guard (all invalid, NaN, wrong units, tiny frames).

Tracking across frames and the pipeline stage are in :mod:`illuminet.runtime.stages.planes`.

Conventions: camera coordinates (OpenCV), metres; a plane is ``n . x + d = 0`` with ``|n| = 1`` and
``d > 0`` (the normal points to the camera's side).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from illuminet.runtime.config import Config
from illuminet.runtime.frame import Intrinsics

#: Target size of the downsampled cloud (the stride is chosen so the width is about this).
CLOUD_WIDTH = 160
#: Depth outside this range (metres) is treated as invalid (stereo gives nothing useful beyond it).
MIN_DEPTH_M, MAX_DEPTH_M = 0.1, 15.0
#: Normal agreement for a point to belong to a plane (degrees).
NORMAL_TOL_DEG = 25.0
#: Horizontal / vertical tolerance for labels (degrees).
LABEL_TOL_DEG = 15.0
#: Smallest frame (width, height) the stage accepts.
MIN_FRAME = (32, 24)
#: The detection methods of ``[planes] method`` (:data:`DETECTORS`).
METHODS = ("ransac", "region", "opencv")
#: Fewest cloud points a plane is fitted on.
MIN_FIT_POINTS = 10


# --------------------------------------------------------------------------------------------
# Bad depth


def check_depth(depth: np.ndarray | None, sample: np.ndarray | None = None) -> tuple[str, str] | None:
    """Say why a depth map cannot be used, or ``None`` when it can.

    Parameters
    ----------
    depth : HxW float32 metres or None
        The frame's depth (0 = invalid).
    sample : array, optional
        A subsample of ``depth`` already taken (e.g. the strided cloud); statistics use it so the
        check costs nothing at full resolution.

    Returns
    -------
    (kind, message) or None
        ``kind`` is a short key for counting (``no_depth``, ``tiny``, ``invalid``, ``units_mm``,
        ``units_small``); ``message`` says what was expected and what was given.
    """
    if depth is None:
        return "no_depth", "frame has no depth map; planes need depth (expected HxW float32 metres)"
    h, w = depth.shape[:2]
    if w < MIN_FRAME[0] or h < MIN_FRAME[1]:
        return "tiny", f"depth map is {w}x{h}; expected at least {MIN_FRAME[0]}x{MIN_FRAME[1]} pixels"
    s = depth if sample is None else sample
    if s.size > 4096:  # statistics need a few thousand values, not the whole map
        s = s.reshape(-1)[:: s.size // 4096]
    finite = np.isfinite(s)
    valid = finite & (s > 0)
    frac = float(valid.mean()) if s.size else 0.0
    if frac < 0.01:
        n_nan, n_valid = int((~finite).sum()), int(valid.sum())
        if n_valid:
            # a sparse map (0.9 % valid) was told "all values are 0"
            return "invalid", (
                f"depth map has too few valid pixels: {n_valid} of {s.size} sampled values ({100 * frac:.2g} %), "
                "under 1 %; expected metres > 0 with 0 = invalid over at least 1 % of the map"
            )
        what = f"{n_nan} of {s.size} sampled values are NaN/inf, the rest 0" if n_nan else "all values are 0"
        return "invalid", f"depth map has no valid pixels ({what}); expected metres > 0 with 0 = invalid"
    med = float(np.median(s[valid]))
    if abs(med - 65.535) < 0.002:
        # a replay's 16-bit PNG of 65535s is already read as millimetres: the "convert mm" advice below
        # sent such users looking at a conversion they never wrote
        return "units_mm", (
            "depth median is 65.535 m, the largest value 16-bit millimetres can hold: 'no depth' seems written "
            "as 65535 (a depth PNG or a camera's invalid value); expected 0 for pixels without depth"
        )
    if med > 50.0:
        return "units_mm", (
            f"depth median is {med:.0f} 'metres': this looks like millimetres (or another x1000 unit); "
            "Frame.depth must be float32 metres (convert uint16 mm with illuminet.runtime.frame.depth_from_mm)"
        )
    if med < 0.05:
        return "units_small", (
            f"depth median is {med:.4f} m: too small for a room; Frame.depth must be float32 metres "
            "(was it divided twice, or normalised to [0, 1]?)"
        )
    return None


# --------------------------------------------------------------------------------------------
# The downsampled cloud


@dataclass
class Cloud:
    """Organised downsampled point cloud of one depth map.

    Attributes
    ----------
    points : (h, w, 3) float32
        Camera-frame points; zeros where invalid.
    valid : (h, w) bool
        Valid depth.
    stride : int
        Sample (i, j) is the full-resolution pixel (stride*i, stride*j).
    full_size : (width, height)
        Size of the depth map it came from.
    intrinsics : Intrinsics
        Full-resolution intrinsics (matching ``full_size``).
    nonfinite : int
        Sampled values that were NaN/inf (treated as invalid).

    Normals (:attr:`normals`, :attr:`normal_valid`) and fit moments are computed on first use:
    frames that only track planes never need normals.
    """

    points: np.ndarray
    valid: np.ndarray
    stride: int
    full_size: tuple[int, int]
    intrinsics: Intrinsics
    nonfinite: int = 0
    ray_grid: np.ndarray | None = field(default=None, repr=False)
    _normals: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    _moments: np.ndarray | None = field(default=None, repr=False)
    _thr: dict = field(default_factory=dict, repr=False)
    _inv_rn: np.ndarray | None = field(default=None, repr=False)

    @property
    def normals(self) -> np.ndarray:
        """(h, w, 3) float32 unit normals towards the camera (zeros where not :attr:`normal_valid`)."""
        if self._normals is None:
            self._normals = estimate_normals(self.points, self.valid)
        return self._normals[0]

    @property
    def normal_valid(self) -> np.ndarray:
        """(h, w) bool: where :attr:`normals` is defined."""
        if self._normals is None:
            self._normals = estimate_normals(self.points, self.valid)
        return self._normals[1]

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    @property
    def z(self) -> np.ndarray:
        return self.points[..., 2]

    def rays(self) -> np.ndarray:
        """(h, w, 3) un-normalised viewing rays (x/z, y/z, 1) of the samples."""
        if self.ray_grid is None:
            self.ray_grid = _rays(self.intrinsics, self.stride, self.shape)
        return self.ray_grid

    def moments(self) -> np.ndarray:
        """(h*w, 19) float32 per-point terms whose masked sums give every plane fit in one product.

        Columns: 1, x, y, x^2, xy, y^2 (ray coordinates x = X/Z, y = Y/Z), q, xq, yq (q = 1/Z), then
        X, Y, Z, XX, XY, XZ, YY, YZ, ZZ (the points), q^2 (fit residuals). float32: sums over ~10^4 points stay within
        1e-5 relative, far below the noise. Rows of invalid points are not zero (masks never
        include them). A fit on any mask is then ``mask @ moments`` (one matrix-vector product, no
        gathering of points).
        """
        if self._moments is None:
            # built column by column in a (19, N) array (each column contiguous, written in place), used
            # as its (N, 19) transpose: 4x faster to build than writing strided columns of an (N, 19)
            # array, and the masked sums (one matrix-vector product each) are faster too
            h, w = self.shape
            F = np.empty((19, h * w), np.float32)
            F[:6] = _ray_moments(self.rays()).T
            Z = self.points[..., 2].reshape(-1)
            q = F[6]
            q[:] = 0.0
            np.divide(1.0, Z, out=q, where=Z > 0)
            x, y = F[1], F[2]
            np.multiply(x, q, out=F[7])
            np.multiply(y, q, out=F[8])
            X, Y = F[9], F[10]
            np.multiply(x, Z, out=X)
            np.multiply(y, Z, out=Y)
            F[11] = Z
            np.multiply(X, X, out=F[12])
            np.multiply(X, Y, out=F[13])
            np.multiply(X, Z, out=F[14])
            np.multiply(Y, Y, out=F[15])
            np.multiply(Y, Z, out=F[16])
            np.multiply(Z, Z, out=F[17])
            np.multiply(q, q, out=F[18])
            self._moments = F.T
        return self._moments

    def threshold(self, at_1m: float) -> np.ndarray:
        """:func:`inlier_threshold` of every point (cached per value)."""
        t = self._thr.get(at_1m)
        if t is None:
            t = self._thr[at_1m] = inlier_threshold(self.z, at_1m)
        return t

    def inv_ray_norm(self) -> np.ndarray:
        """(h*w,) 1/|r| of the rays (for viewing-angle cosines)."""
        if self._inv_rn is None:
            self._inv_rn = _ray_moments(self.rays())[:, 3:6] @ np.array([1, 0, 1], np.float32)
            self._inv_rn = 1.0 / np.sqrt(self._inv_rn + 1.0)
        return self._inv_rn

    def upsample_mask(self, mask: np.ndarray) -> np.ndarray:
        """Low-resolution mask -> full-resolution HxW bool (each sample covers its stride block)."""
        w, h = self.full_size
        up = cv2.resize(mask.view(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
        return up.view(bool)


def _rays(intr: Intrinsics, stride: int, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    u = np.arange(w, dtype=np.float32) * stride
    v = np.arange(h, dtype=np.float32) * stride
    rx = (u - intr.cx) / intr.fx
    ry = (v - intr.cy) / intr.fy
    r = np.empty((h, w, 3), np.float32)
    r[..., 0] = rx[None, :]
    r[..., 1] = ry[:, None]
    r[..., 2] = 1.0
    return r


_RAY_CACHE: dict[tuple, np.ndarray] = {}
_RAYMOM_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _ray_moments(rays: np.ndarray) -> np.ndarray:
    """(h*w, 6) float32: 1, x, y, x^2, xy, y^2 of the rays (cached per ray grid)."""
    hit = _RAYMOM_CACHE.get(id(rays))
    if hit is not None and hit[0] is rays:
        return hit[1]
    r = rays.reshape(-1, 3)
    x, y = r[:, 0], r[:, 1]
    m = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1).astype(np.float32)
    if len(_RAYMOM_CACHE) > 16:
        _RAYMOM_CACHE.clear()
    _RAYMOM_CACHE[id(rays)] = (rays, m)
    return m


def cloud_stride(width: int) -> int:
    """Stride giving a cloud about :data:`CLOUD_WIDTH` wide."""
    return max(1, int(round(width / CLOUD_WIDTH)))


def make_cloud(depth: np.ndarray, intr: Intrinsics, stride: int | None = None) -> Cloud:
    """Downsample ``depth`` by striding and back-project (normals follow on demand).

    Parameters
    ----------
    depth : HxW float32 metres (0, NaN, inf = invalid)
    intr : Intrinsics
        Intrinsics of the colour camera; rescaled when they refer to another image size.
    stride : int, optional
        Sampling step; default makes the cloud about 160 points wide.
    """
    H, W = depth.shape
    if (intr.width, intr.height) != (W, H):
        intr = intr.scaled(W, H)
    s = cloud_stride(W) if stride is None else int(stride)
    z = depth[::s, ::s]
    finite = np.isfinite(z)
    nonfinite = int(z.size - finite.sum())
    if nonfinite:
        z = np.where(finite, z, 0.0).astype(np.float32)
    valid = (z > MIN_DEPTH_M) & (z < MAX_DEPTH_M)
    z = np.where(valid, z, 0.0).astype(np.float32)
    key = (intr.fx, intr.fy, intr.cx, intr.cy, s, z.shape)
    rays = _RAY_CACHE.get(key)
    if rays is None:
        if len(_RAY_CACHE) > 16:
            _RAY_CACHE.clear()
        rays = _RAY_CACHE[key] = _rays(intr, s, z.shape)
    P = rays * z[..., None]
    return Cloud(P, valid, s, (W, H), intr, nonfinite, rays)


def estimate_normals(P: np.ndarray, valid: np.ndarray, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Normals of an organised cloud: cross product of central differences of box-filtered points.

    The box filter (``window`` x ``window``, valid points only) averages stereo noise before
    differentiating; differences span two samples on each side so the baseline is long enough
    for noisy depth. Normals are oriented towards the camera.
    """
    wgt = valid.astype(np.float32)
    # Replicated borders and one-sided differences there keep normals at the image border: a band
    # without normals would let a plane annex border points on distance alone.
    ps = cv2.boxFilter(P * wgt[..., None], -1, (window, window), normalize=False, borderType=cv2.BORDER_REPLICATE)
    ws = cv2.boxFilter(wgt, -1, (window, window), normalize=False, borderType=cv2.BORDER_REPLICATE)
    pm = ps / np.maximum(ws, 1.0)[..., None]
    k = 2
    pp = cv2.copyMakeBorder(pm, k, k, k, k, cv2.BORDER_REPLICATE)
    dx = pp[k:-k, 2 * k :] - pp[k:-k, : -2 * k]
    dy = pp[2 * k :, k:-k] - pp[: -2 * k, k:-k]
    # cross product by components (float32 throughout; np.cross is slower on small arrays)
    ax, ay, az = dx[..., 0], dx[..., 1], dx[..., 2]
    bx, by, bz = dy[..., 0], dy[..., 1], dy[..., 2]
    n = np.empty_like(pm)
    n[..., 0] = ay * bz - az * by
    n[..., 1] = az * bx - ax * bz
    n[..., 2] = ax * by - ay * bx
    norm = np.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2 + n[..., 2] ** 2)
    ok = valid & (ws >= 0.6 * window * window) & (norm > 1e-12)
    # orient towards the camera: n . P < 0; invalid normals become 0
    sgn = np.where(n[..., 0] * P[..., 0] + n[..., 1] * P[..., 1] + n[..., 2] * P[..., 2] > 0, -1.0, 1.0)
    n *= (np.where(ok, sgn, 0.0) / np.maximum(norm, 1e-12))[..., None].astype(np.float32)
    return n, ok


# --------------------------------------------------------------------------------------------
# Fitting


@dataclass
class PlaneFit:
    """One plane found in a cloud (before tracking gives it an ID)."""

    normal: np.ndarray
    offset: float
    mask: np.ndarray  # (h, w) bool in the cloud
    n_inliers: int
    centroid: np.ndarray
    area_m2: float
    extent_m: tuple[float, float]
    axes: np.ndarray  # (2, 3) in-plane principal directions
    view_cos: float = 1.0  # mean |cos| between the normal and the viewing rays of the inliers
    offset_se: float = 0.0  # standard error of the offset from the fit residuals, metres


#: Largest inlier distance, metres. Far away the z^2 growth would accept the bottom of a wall as
#: floor (the junction pulls the fit); capping truncates far noise symmetrically instead.
MAX_INLIER_M = 0.08


def inlier_threshold(z: np.ndarray, at_1m: float) -> np.ndarray:
    """Point-to-plane distance accepted at depth z: grows with z^2 like stereo noise (from 0.5 m),
    capped at :data:`MAX_INLIER_M`."""
    zz = np.maximum(z, 0.5)
    return np.minimum(at_1m * zz * zz, MAX_INLIER_M)


def fit_plane(
    P: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares plane through points (orthogonal regression).

    Returns normal (towards the camera, d > 0), offset d, centroid, eigenvalues (ascending) and
    eigenvectors (columns) of the weighted scatter matrix.
    """
    P = P.astype(np.float64, copy=False)
    if weights is None:
        c = P.mean(axis=0)
        Q = P - c
        C = Q.T @ Q / len(P)
    else:
        w = weights.astype(np.float64) / weights.sum()
        c = w @ P
        Q = P - c
        C = (Q * w[:, None]).T @ Q
    evals, evecs = np.linalg.eigh(C)
    n = evecs[:, 0]
    d = -float(n @ c)
    if d < 0:
        n, d = -n, -d
    return n, d, c, evals, evecs


def fit_plane_disparity(rays: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Least-squares plane in inverse depth: 1/z = a x + b y + c over the pixels' rays (x, y, 1).

    For a plane ``n . p + d = 0`` the inverse depth is linear in the normalised image coordinates,
    ``1/z = -(n . r) / d``. Stereo noise is roughly constant in disparity (~ 1/z), and the pixel
    coordinates carry no noise, so this ordinary least squares is the maximum-likelihood fit and is
    unbiased — unlike orthogonal regression on the 3D points, which the anisotropic noise along
    the viewing rays tilts (measured: 4 mm offset bias on a floor at 1.5-5 m, 2.5 cm on a wall at 4 m).

    Returns the unit normal (towards the camera) and offset ``d > 0``, or ``None`` when the pixels
    are degenerate (collinear).
    """
    A = rays.astype(np.float64, copy=False)
    y = 1.0 / z.astype(np.float64)
    return _solve_disparity(A.T @ A, A.T @ y)


def _solve_disparity(AtA: np.ndarray, Aty: np.ndarray) -> tuple[np.ndarray, float] | None:
    try:
        abc = np.linalg.solve(AtA, Aty)
    except np.linalg.LinAlgError:  # collinear pixels: no plane
        return None
    s = np.linalg.norm(abc)
    if not np.isfinite(s) or s < 1e-9:
        return None
    return -abc / s, 1.0 / s


def _fit_moments(S: np.ndarray) -> tuple[np.ndarray, float] | None:
    """:func:`fit_plane_disparity` from summed :meth:`Cloud.moments` (``S = mask @ moments``)."""
    AtA = np.array([[S[3], S[4], S[1]], [S[4], S[5], S[2]], [S[1], S[2], S[0]]])
    return _solve_disparity(AtA, np.array([S[7], S[8], S[6]]))


def _inliers(
    cloud: Cloud,
    n: np.ndarray,
    d: float,
    thr_1m: float,
    allowed: np.ndarray | None,
    normal_cos: float | None,
    despeckle: bool = True,
) -> np.ndarray:
    n32 = n.astype(np.float32)
    dist = np.abs(cloud.points @ n32 + np.float32(d))
    ok = dist < cloud.threshold(thr_1m)  # invalid points are at the origin: dist = d > threshold
    ok &= cloud.valid
    # Points whose own normal is known must agree; points without a normal (near holes and edges)
    # are accepted on distance alone so planes reach their borders.
    if normal_cos is not None:
        ok &= (cloud.normals @ n32 > normal_cos) | ~cloud.normal_valid
    if allowed is not None:
        ok &= allowed
    return _drop_specks(ok) if despeckle else ok


def _drop_specks(mask: np.ndarray, min_size: int = 12, rel: float = 0.05) -> np.ndarray:
    """Keep the connected parts of an inlier mask that are large (>= ``min_size`` points and >= ``rel``
    of the largest part).

    Far away, noisy normals let scattered points of *other* surfaces pass the distance and normal
    tests (e.g. wall points at the height of a table top); they form specks, a real plane forms
    large connected regions (possibly several, when something stands on it).
    """
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    sizes = stats[1:, cv2.CC_STAT_AREA]
    keep = sizes >= max(min_size, rel * sizes.max())
    if keep.all():
        return mask
    lut = np.concatenate([[False], keep])
    return lut[lab]


def refine(
    cloud: Cloud,
    n: np.ndarray,
    d: float,
    thr_1m: float,
    allowed: np.ndarray | None = None,
    iterations: int = 2,
    final_inliers: bool = True,
    despeckle: bool = True,
    use_normals: bool = True,
) -> PlaneFit | None:
    """Refit a plane on its inliers ``iterations`` times (inlier set recomputed each time).

    The fit is :func:`fit_plane_disparity`; centroid, area, extent and axes come from the final
    inliers. ``allowed`` restricts which cloud points may be inliers. With ``final_inliers=False``
    the returned mask is the one the last fit used (tracking saves one pass this way).
    ``despeckle`` drops small disconnected inlier specks (see :func:`_drop_specks`);
    ``use_normals=False`` tests distance only (tracking: no normals needed). ``None`` when too few
    points remain.
    """
    normal_cos = float(np.cos(np.radians(NORMAL_TOL_DEG))) if use_normals else None
    F = cloud.moments()
    mask = mf = None
    for _ in range(iterations):
        mask = _inliers(cloud, n, d, thr_1m, allowed, normal_cos, despeckle)
        mf = mask.reshape(-1).view(np.uint8).astype(np.float32)
        S = (mf @ F).astype(np.float64)
        if S[0] < MIN_FIT_POINTS:
            return None
        nd = _fit_moments(S)
        if nd is None:
            return None
        n, d = nd
    if final_inliers:
        mask = _inliers(cloud, n, d, thr_1m, allowed, normal_cos, despeckle)
        mf = mask.reshape(-1).view(np.uint8).astype(np.float32)
        S = (mf @ F).astype(np.float64)
    cnt = int(round(S[0]))
    if cnt < MIN_FIT_POINTS:
        return None
    c = S[9:12] / cnt
    M2 = np.array([[S[12], S[13], S[14]], [S[13], S[15], S[16]], [S[14], S[16], S[17]]]) / cnt
    evals, evecs = np.linalg.eigh(M2 - np.outer(c, c))
    # Area: each sample covers stride^2 pixels; a pixel's footprint on the plane is
    # d^2 / |n . r|^3 dx dy with r = (x/z, y/z, 1) (exact for a pinhole camera).
    intr = cloud.intrinsics
    pix = (cloud.stride / intr.fx) * (cloud.stride / intr.fy)
    ndotr = np.abs(cloud.rays().reshape(-1, 3) @ n.astype(np.float32))
    np.maximum(ndotr, np.float32(1e-3), out=ndotr)
    view_cos = float(np.dot(mf, ndotr * cloud.inv_ray_norm())) / cnt
    inv = np.divide(np.float32(1.0), ndotr, out=ndotr)
    area = float(np.dot(mf, inv * inv * inv)) * d * d * pix
    # Extent along the in-plane principal axes (a uniform rectangle has variance L^2 / 12).
    ext = np.sqrt(12.0 * np.maximum(evals[1:], 0.0))
    # Standard error of the offset (for the tracker's motion gate): residual spread of the
    # inverse-depth fit, sigma_q, over sqrt(N), scaled by d^2 (d = 1/|abc|, so dd = d^2 d|abc|).
    abc = -np.asarray(n, np.float64) / d
    rss = (
        S[18]
        - 2.0 * (abc[0] * S[7] + abc[1] * S[8] + abc[2] * S[6])
        + abc @ np.array([[S[3], S[4], S[1]], [S[4], S[5], S[2]], [S[1], S[2], S[0]]]) @ abc
    )
    sigma_q = np.sqrt(max(rss, 0.0) / max(cnt - 3, 1))
    offset_se = float(d * d * sigma_q / np.sqrt(cnt))
    return PlaneFit(
        normal=np.asarray(n, np.float64),
        offset=float(d),
        mask=mask,
        n_inliers=cnt,
        centroid=c,
        area_m2=area,
        extent_m=(float(ext[1]), float(ext[0])),
        axes=evecs[:, [2, 1]].T.copy(),
        view_cos=view_cos,
        offset_se=offset_se,
    )


# --------------------------------------------------------------------------------------------
# Detection methods


@dataclass(frozen=True)
class DetectParams:
    """Parameters shared by the detection methods (from ``[planes]``)."""

    max_planes: int = 4
    min_area_m2: float = 0.02
    inlier_threshold_m: float = 0.01
    min_points: int = 60  # smallest plane in cloud samples
    hypotheses: int = 96
    score_subset: int = 3000

    @classmethod
    def from_config(cls, cfg: Config) -> DetectParams:
        p = cfg.planes
        return cls(max_planes=p.max_planes, min_area_m2=p.min_area_m2, inlier_threshold_m=p.inlier_threshold_m)


#: Planes seen more edge-on than this (angle between normal and viewing rays) are rejected: depth
#: noise along the rays of far, grazing surfaces lines up into spurious planes that nearly contain
#: the camera centre.
MAX_VIEW_ANGLE_DEG = 82.0


def _accept(fits: list[PlaneFit], fit: PlaneFit | None, params: DetectParams) -> bool:
    return (
        fit is not None
        and fit.n_inliers >= params.min_points
        and fit.area_m2 >= params.min_area_m2
        and fit.view_cos > np.cos(np.radians(MAX_VIEW_ANGLE_DEG))
    )


def detect_ransac(cloud: Cloud, params: DetectParams, rng: np.random.Generator) -> list[PlaneFit]:
    """Sequential RANSAC with vectorised hypothesis scoring (see module docstring)."""
    normal_cos = np.float32(np.cos(np.radians(NORMAL_TOL_DEG)))
    remaining = cloud.valid.copy()
    P = cloud.points.reshape(-1, 3)
    N = cloud.normals.reshape(-1, 3)
    nv = cloud.normal_valid.reshape(-1)
    thr_all = inlier_threshold(cloud.z, params.inlier_threshold_m).reshape(-1)
    fits: list[PlaneFit] = []
    failures = 0
    while len(fits) < params.max_planes and failures < 2:
        cand = np.flatnonzero(remaining.reshape(-1) & nv)
        if cand.size < params.min_points:
            break
        M = params.hypotheses
        tri = cand[rng.integers(0, cand.size, size=(M, 3))]
        a, b, c = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n, axis=1)
        good = nn > 1e-9
        n = n / np.maximum(nn, 1e-12)[:, None]
        # the hypothesis must agree with the three points' own normals (cheap pre-test)
        for idx in range(3):
            good &= np.abs(np.einsum("ij,ij->i", n, N[tri[:, idx]])) > normal_cos
        if not good.any():
            failures += 1
            continue
        n = n[good]
        d = -np.einsum("ij,ij->i", n, a[good])
        sub = cand if cand.size <= params.score_subset else cand[rng.integers(0, cand.size, params.score_subset)]
        dist = np.abs(P[sub] @ n.T + d[None, :])  # (S, M)
        agree = np.abs(N[sub] @ n.T) > normal_cos
        score = ((dist < thr_all[sub, None]) & agree).sum(axis=0)
        best = int(np.argmax(score))
        nb, db = n[best].astype(np.float64), float(d[best])
        if db < 0:
            nb, db = -nb, -db
        fit = refine(cloud, nb, db, params.inlier_threshold_m, remaining)
        if not _accept(fits, fit, params):
            failures += 1
            if fit is not None:
                remaining &= ~fit.mask  # do not draw from this small patch again
            continue
        fits.append(fit)
        remaining &= ~fit.mask
    return fits


def detect_region(cloud: Cloud, params: DetectParams, rng: np.random.Generator | None = None) -> list[PlaneFit]:
    """Region growing: smooth connected regions seed planes that grow by distance (module docstring)."""
    cos_t = np.float32(np.cos(np.radians(12.0)))
    Nrm, nv, P = cloud.normals, cloud.normal_valid, cloud.points
    thr = inlier_threshold(cloud.z, params.inlier_threshold_m)
    smooth = nv.copy()
    # right and down neighbours: normals agree and the neighbour lies on this point's tangent plane
    for sl_a, sl_b in (
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        na, nb = Nrm[sl_a], Nrm[sl_b]
        ok = np.einsum("ijk,ijk->ij", na, nb) > cos_t
        ok &= np.abs(np.einsum("ijk,ijk->ij", na, P[sl_b] - P[sl_a])) < 2.0 * thr[sl_a]
        ok &= nv[sl_a] & nv[sl_b]
        bad = ~ok
        # an edge between a and b breaks the region on both sides
        smooth[sl_a] &= ~bad
        smooth[sl_b] &= ~bad
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(smooth.view(np.uint8), connectivity=4)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1
    remaining = cloud.valid.copy()
    fits: list[PlaneFit] = []
    for lab in order:
        if len(fits) >= params.max_planes or stats[lab, cv2.CC_STAT_AREA] < params.min_points:
            break
        region = (labels == lab) & remaining
        if region.sum() < params.min_points:
            continue
        # seed plane: orthogonal regression (PCA) of the region's points, from the moments
        S = (region.reshape(-1).view(np.uint8).astype(np.float32) @ cloud.moments()).astype(np.float64)
        c = S[9:12] / S[0]
        M2 = np.array([[S[12], S[13], S[14]], [S[13], S[15], S[16]], [S[14], S[16], S[17]]]) / S[0]
        n = np.linalg.eigh(M2 - np.outer(c, c))[1][:, 0]
        d = -float(n @ c)
        if d < 0:
            n, d = -n, -d
        fit = refine(cloud, n, d, params.inlier_threshold_m, remaining)
        if not _accept(fits, fit, params):
            continue
        fits.append(fit)
        remaining &= ~fit.mask
    return fits


def detect_opencv(cloud: Cloud, params: DetectParams, rng: np.random.Generator | None = None) -> list[PlaneFit]:
    """OpenCV 5 ``cv2.findPlanes`` on the cloud, then the shared refit (module docstring).

    ``findPlanes`` needs 4-channel points (x, y, z, 0); invalid points are NaN. Its threshold is
    one fixed distance, so the inlier threshold at the cloud's median depth is used, with the
    sensor-error terms modelling growth with depth.
    """
    h, w = cloud.shape
    P4 = np.full((h, w, 4), np.nan, np.float32)
    P4[cloud.valid, :3] = cloud.points[cloud.valid]
    P4[..., 3] = 0.0
    N4 = np.zeros((h, w, 4), np.float32)
    N4[..., :3] = cloud.normals
    N4[~cloud.normal_valid, :3] = np.nan
    thr = float(params.inlier_threshold_m)
    labels, coeffs = cv2.findPlanes(
        P4,
        N4,
        block_size=max(4, w // 20),
        min_size=params.min_points,
        threshold=thr,
        sensor_error_a=0.0,
        sensor_error_b=0.0,
        sensor_error_c=thr,
    )
    if coeffs is None:
        return []
    coeffs = coeffs.reshape(-1, 4)
    remaining = cloud.valid.copy()
    fits: list[PlaneFit] = []
    # findPlanes returns planes in the order it found them (largest first)
    for k, (a, b, c, dd) in enumerate(coeffs):
        if len(fits) >= params.max_planes:
            break
        region = (labels == k) & remaining
        if region.sum() < params.min_points:
            continue
        n = np.array([a, b, c], np.float64)
        nn = np.linalg.norm(n)
        if nn < 1e-9:
            continue
        n, d = n / nn, float(dd) / nn
        if d < 0:
            n, d = -n, -d
        fit = refine(cloud, n, d, params.inlier_threshold_m, remaining)
        if not _accept(fits, fit, params):
            continue
        fits.append(fit)
        remaining &= ~fit.mask
    return fits


DETECTORS = {"ransac": detect_ransac, "region": detect_region, "opencv": detect_opencv}


def detect_planes(
    cloud: Cloud, params: DetectParams, method: str = "region", rng: np.random.Generator | None = None
) -> list[PlaneFit]:
    """Segment ``cloud`` into up to ``params.max_planes`` planes, largest first."""
    try:
        fn = DETECTORS[method]
    except KeyError:
        raise ValueError(f"[planes] method: expected one of {', '.join(DETECTORS)}, got {method!r}") from None
    fits = fn(cloud, params, rng if rng is not None else np.random.default_rng(0))
    fits.sort(key=lambda f: -f.area_m2)
    return fits


# --------------------------------------------------------------------------------------------
# Labels


def estimate_up(planes: list[tuple[np.ndarray, float]], gravity: np.ndarray | None) -> tuple[np.ndarray, str]:
    """The "up" direction in camera coordinates and where it came from.

    With gravity (unit vector pointing down): ``up = -gravity`` (``"gravity"``). Without it, the
    fallback (``"largest-up-facing"``): the normal of the plane with the largest
    ``area * (1 - n_y)`` among planes not facing image-down (n_y < 0.1) — i.e. the largest plane
    whose normal points most towards the camera's -y (image up), which is the floor or table for
    a camera held roughly level or looking down. When no plane qualifies, the camera is assumed
    level (``up = (0, -1, 0)``, ``"assumed-level"``).

    ``planes`` is a list of (normal, area_m2).
    """
    if gravity is not None:
        g = np.asarray(gravity, np.float64)
        ng = np.linalg.norm(g)
        if np.isfinite(ng) and ng > 1e-6:
            return -g / ng, "gravity"
    best, best_score = None, 0.0
    for n, area in planes:
        if n[1] < 0.1:
            score = area * (1.0 - n[1])
            if score > best_score:
                best, best_score = n, score
    if best is not None:
        return np.asarray(best, np.float64), "largest-up-facing"
    return np.array([0.0, -1.0, 0.0]), "assumed-level"


def label_planes(normals: list[np.ndarray], offsets: list[float], up: np.ndarray) -> list[str]:
    """``floor`` (lowest horizontal up-facing plane), ``table`` (other horizontal up-facing planes),
    ``wall`` (vertical), ``other``; tolerance :data:`LABEL_TOL_DEG`."""
    cos_h = np.cos(np.radians(LABEL_TOL_DEG))
    sin_v = np.sin(np.radians(LABEL_TOL_DEG))
    labels = []
    heights = []
    for n, d in zip(normals, offsets):
        c = float(np.dot(n, up))
        if c > cos_h:
            labels.append("horizontal")
            heights.append(d)  # camera height above the plane
        elif abs(c) < sin_v:
            labels.append("wall")
        else:
            labels.append("other")
    if heights:
        lowest = max(heights)
        labels = [
            ("floor" if d >= lowest - 1e-9 else "table") if lab == "horizontal" else lab
            for lab, d in zip(labels, offsets)
        ]
    return labels
