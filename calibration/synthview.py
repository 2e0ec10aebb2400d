"""Synthetic views with exactly known geometry: textured planes seen through a calibrated camera.

This module owns the ray-casting renderer that the calibration tests and the stereo benchmark use
to check our tools against ground truth: every pixel of a camera (pinhole with OpenCV distortion,
or fisheye) is un-distorted to its ray (``cv2.undistortPoints`` / ``cv2.fisheye.undistortPoints``
with tight iteration criteria), intersected with textured planes, and the texture is sampled
(``cv2.remap``). Supersampling (render at k x the size, then area-average) keeps corners unbiased.
Outputs are the BGR image and the true depth (camera z, metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from illuminet.calibration.calibfile import CameraCalib

if TYPE_CHECKING:
    from illuminet.calibration.board import BoardSpec
    from illuminet.calibration.calibfile import Calibration

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class TexturedPlane:
    """A rectangle in world coordinates carrying a texture.

    Texture pixel (row i, column j) covers the square at ``origin + (j + 0.5) * px * u + (i + 0.5) * px
    * v`` (centre), with ``px = pixel_m``; ``u`` and ``v`` are orthonormal (world) vectors.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: np.ndarray  # HxW or HxWx3 uint8 (BGR)
    pixel_m: float

    @property
    def normal(self) -> np.ndarray:
        """Unit normal u x v."""
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)


def pixel_rays(cam: CameraCalib) -> np.ndarray:
    """Unit-z rays (x, y, 1) of every pixel centre of ``cam``, shape (H, W, 3), float64."""
    w, h = cam.size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    if cam.model == "fisheye":
        d = np.zeros(4) if len(cam.dist) == 0 else np.asarray(cam.dist, float)[:4]
        und = cv2.fisheye.undistortPoints(pts, cam.K, d.reshape(4, 1), criteria=_CRITERIA)
    else:
        und = cv2.undistortPoints(pts, cam.K, cam.dist, criteria=_CRITERIA)
    und = und.reshape(h, w, 2)
    return np.concatenate([und, np.ones((h, w, 1))], axis=2)


def render(
    cam: CameraCalib,
    R: np.ndarray,
    t: np.ndarray,
    planes: list[TexturedPlane],
    supersample: int = 2,
    background: int = 0,
    rays: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render ``planes`` through ``cam`` at pose ``X_cam = R @ X_world + t``.

    Returns
    -------
    image : ndarray
        uint8, HxWx3 (BGR) when any texture has colour, else HxW.
    depth : ndarray
        float32 camera z in metres of the nearest plane, 0 where no plane is hit.

    ``rays`` may pass :func:`pixel_rays` of the supersampled camera, computed once for many poses.
    """
    k = int(supersample)
    big = cam.scaled_to(cam.width * k, cam.height * k) if k > 1 else cam
    if rays is None:
        rays = pixel_rays(big)  # camera frame
    h, w = rays.shape[:2]
    Rt = np.asarray(R, float).T
    C = -Rt @ np.asarray(t, float).reshape(3)
    dirs = rays @ Rt.T  # world-frame directions, camera z component is 1
    color = any(p.texture.ndim == 3 for p in planes)
    img = np.full((h, w, 3) if color else (h, w), background, np.float32)
    zbuf = np.full((h, w), np.inf, np.float64)
    for p in planes:
        n = p.normal
        denom = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((np.asarray(p.origin, float) - C) @ n) / denom
        P = C + dirs * s[..., None]
        rel = P - np.asarray(p.origin, float)
        a = (rel @ np.asarray(p.u, float)) / p.pixel_m - 0.5
        b = (rel @ np.asarray(p.v, float)) / p.pixel_m - 0.5
        th, tw = p.texture.shape[:2]
        hit = (s > 0) & (s < zbuf) & (a >= -0.5) & (b >= -0.5) & (a <= tw - 0.5) & (b <= th - 0.5)
        if not hit.any():
            continue
        tex = p.texture.astype(np.float32)
        samp = cv2.remap(
            tex, a.astype(np.float32), b.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        if color and samp.ndim == 2:
            samp = np.repeat(samp[..., None], 3, axis=2)
        img[hit] = samp[hit]
        zbuf[hit] = s[hit]
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
    if k > 1:
        img = cv2.resize(img, cam.size, interpolation=cv2.INTER_AREA)
        # depth: the sample nearest each output pixel centre (no mixing across edges)
        depth = depth[k // 2 :: k, k // 2 :: k][: cam.height, : cam.width]
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), depth


def degrade(img: np.ndarray, blur_sigma: float = 0.8, noise_sigma: float = 2.0, seed: int = 0) -> np.ndarray:
    """Optical blur (Gaussian) plus sensor noise (Gaussian, in 8-bit levels), re-quantised to uint8."""
    rng = np.random.default_rng(seed)
    f = img.astype(np.float32)
    if blur_sigma > 0:
        f = cv2.GaussianBlur(f, (0, 0), blur_sigma)
    if noise_sigma > 0:
        f = f + rng.normal(0.0, noise_sigma, f.shape).astype(np.float32)
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def random_texture(h: int, w: int, seed: int = 0, color: bool = True) -> np.ndarray:
    """Multi-scale random texture (blobs of several sizes): what stereo matching needs to find matches."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((h, w, 3 if color else 1), np.float32)
    for cell, weight in ((64, 0.35), (16, 0.35), (4, 0.3)):
        small = rng.random((max(2, h // cell + 2), max(2, w // cell + 2), acc.shape[2])).astype(np.float32)
        up = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        acc += weight * (up if up.ndim == 3 else up[..., None])
    acc = (acc - acc.min()) / max(1e-6, float(acc.max() - acc.min()))
    out = np.clip(acc * 235 + 10, 0, 255).astype(np.uint8)
    return out if color else out[..., 0]


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of an OpenCV camera at ``eye`` looking at ``target`` (y down)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # OpenCV: x right, y down; up is -y
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


@dataclass
class StereoScene:
    """A synthetic stereo pair with known geometry (see :func:`stereo_scene`)."""

    calibration: Calibration
    left: np.ndarray  # raw BGR
    right: np.ndarray
    planes: list[TexturedPlane]

    def depth_rectified(self, R1: np.ndarray, P1: np.ndarray) -> np.ndarray:
        """True depth (z of the rectified left camera, metres, 0 = nothing) for rectification R1, P1."""
        cam = self.calibration.camera(self.calibration.stereo.left)
        rect = CameraCalib(cam.width, cam.height, np.asarray(P1, float)[:3, :3], np.zeros(0))
        _, depth = render(rect, np.asarray(R1, float), np.zeros(3), self.planes, supersample=1)
        return depth


def stereo_scene(
    width: int = 640,
    height: int = 400,
    fx: float = 400.0,
    baseline_m: float = 0.075,
    seed: int = 0,
    noise: float = 1.5,
    fisheye: bool = False,
) -> StereoScene:
    """A room-like scene (back wall at 3 m, floor, a tilted panel at ~1.2 m) seen by a slightly
    imperfect stereo pair (distortion, small rotation, different principal points), like a cheap
    V4L2 stereo camera, with blur and sensor noise added. ``fisheye`` uses ``cv2.fisheye`` lenses."""
    from illuminet.calibration.calibfile import Calibration, StereoCalib

    K = np.array([[fx, 0, (width - 1) / 2 + 2.3], [0, fx * 1.001, (height - 1) / 2 - 1.7], [0, 0, 1.0]])
    K2 = K.copy()
    K2[0, 2] += 4.0
    K2[1, 2] -= 2.0
    if fisheye:
        left = CameraCalib(width, height, K, np.array([-0.02, -0.008, 0.008, -0.004]), "fisheye")
        right = CameraCalib(width, height, K2, np.array([-0.025, 0.01, -0.016, 0.006]), "fisheye")
    else:
        left = CameraCalib(width, height, K, np.array([-0.05, 0.01, 0.0002, -0.0001, 0.0]))
        right = CameraCalib(width, height, K2, np.array([-0.045, 0.008, -0.0001, 0.0002, 0.0]))
    R = cv2.Rodrigues(np.array([0.002, -0.008, 0.003]))[0]
    T = np.array([-baseline_m, 0.0004, 0.001])
    calib = Calibration({"left": left, "right": right}, StereoCalib("left", "right", R, T))
    planes = [
        TexturedPlane(
            np.array([-3.0, -2.0, 3.0]),
            np.array([1.0, 0, 0]),
            np.array([0, 1.0, 0]),
            random_texture(800, 1200, seed + 1),
            0.005,
        ),
        TexturedPlane(
            np.array([-0.3, -0.25, 1.2]),
            np.array([1.0, 0, 0]),
            np.array([0, 0.8, -0.6]),
            random_texture(250, 300, seed + 2),
            0.002,
        ),
        TexturedPlane(
            np.array([-3.0, 0.6, 0.2]),
            np.array([1.0, 0, 0]),
            np.array([0, 0, 1.0]),
            random_texture(600, 1200, seed + 3),
            0.005,
        ),
    ]
    li, _ = render(left, np.eye(3), np.zeros(3), planes)
    ri, _ = render(right, R, T, planes)
    return StereoScene(calib, degrade(li, 0.5, noise, seed + 10), degrade(ri, 0.5, noise, seed + 11), planes)


def depth_error(depth: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Relative depth error statistics where both are valid, plus coverage.

    ``median_rel`` / ``p90_rel``: |z - z_true| / z_true; ``bad_5pct``: fraction of valid pixels off by
    more than 5 %; ``valid``: fraction of pixels with true depth that got a depth.
    """
    has = truth > 0
    v = has & (depth > 0)
    if not v.any():
        return {"median_rel": float("nan"), "p90_rel": float("nan"), "bad_5pct": float("nan"), "valid": 0.0}
    rel = np.abs(depth[v] - truth[v]) / truth[v]
    return {
        "median_rel": float(np.median(rel)),
        "p90_rel": float(np.percentile(rel, 90)),
        "bad_5pct": float((rel > 0.05).mean()),
        "valid": float(v.sum() / max(1, has.sum())),
    }


def board_plane(spec: BoardSpec, dpi: float = 200.0, margin_mm: float = 15.0) -> TexturedPlane:
    """The printed board as a textured plane whose board coordinates equal world coordinates
    (origin at the board's top-left corner, x right, y down, z = 0), like ``spec.corner_points()``."""
    from illuminet.calibration.board import board_image

    tex = board_image(spec, dpi=dpi, margin_mm=margin_mm)
    sq_px = int(round(spec.square_mm * dpi / 25.4))
    px = spec.square_m / sq_px
    m = int(round(margin_mm * dpi / 25.4))
    return TexturedPlane(np.array([-m * px, -m * px, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), tex, px)


def board_poses(
    spec: BoardSpec,
    n: int,
    seed: int = 0,
    distance: tuple[float, float] = (0.35, 0.6),
    tilt: float = 0.6,
    shift: tuple[float, float] = (0.12, 0.08),
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` random board poses as camera (R, t) with ``X_cam = R X_board + t``: the board centre at
    ``distance`` metres ahead, shifted sideways, tilted up to ``tilt`` radians about x and y."""
    rng = np.random.default_rng(seed)
    c = np.array([spec.size_mm[0] / 2000.0, spec.size_mm[1] / 2000.0, 0.0])
    out = []
    for _ in range(n):
        ang = rng.uniform(-tilt, tilt, 3) * np.array([1.0, 1.0, 0.5])
        R = cv2.Rodrigues(ang)[0]
        off = np.array([rng.uniform(-shift[0], shift[0]), rng.uniform(-shift[1], shift[1]), rng.uniform(*distance)])
        out.append((R, off - R @ c))
    return out
