"""The simulated RGB-D sensor (exposure, noise, stereo-like depth) and the ``synthetic://`` source."""

from __future__ import annotations

import collections
import math
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from illuminet.hw import parse_query, query_bool, query_choice, query_int, query_size
from illuminet.hw.synthetic.scene import (
    DEFAULT_BOUNCES,
    MAX_BOUNCES,
    PATHS,
    ROOM_LABELS,
    SyntheticError,
    SyntheticScene,
    build_scene,
)
from illuminet.runtime.frame import Exposure, Frame
from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.scene import SYNTHETIC_GT
from illuminet.runtime.stage import Source
from illuminet.runtime.stages.odometry import invert

STEREO_BASELINE_M = 0.075
DISPARITY_NOISE_PX = 0.08
DISPARITY_STEP_PX = 1.0 / 8.0
MIN_DEPTH_M, MAX_DEPTH_M = 0.35, 12.0
FRAME_PERIOD_NS = 33_333_333

# Sensor: electrons per unit of linear signal at ISO 100, read noise (e-), ADC noise (linear)
FULL_WELL_E = 4000.0
READ_NOISE_E = 3.0
ADC_NOISE = 0.0005
AE_TARGET = 0.18
EXPOSURE_US_RANGE = (100.0, 33_333.0)
ISO_RANGE = (100.0, 1600.0)

_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
_SRGB_LUT_SIZE = 4096


class _Renderer:
    """Turns a scene and a camera pose into radiance and clean depth images (float32).

    Everything is axis-aligned, so a ray meets plane i at ``t = (coord - o[axis]) / d[axis]`` with
    ``d`` scaled to unit camera z (``t`` is then the depth). Work is float32 on contiguous rows.
    """

    def __init__(self, scene: SyntheticScene):
        self.scene = scene
        intr = scene.intrinsics
        u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32), np.arange(intr.height, dtype=np.float32))
        self.rays_cam = np.ascontiguousarray(
            np.stack(
                [((u - intr.cx) / intr.fx).ravel(), ((v - intr.cy) / intr.fy).ravel(), np.ones(u.size, np.float32)]
            )
        )  # (3, N)
        self.planes = []
        for p in scene.planes:
            S = p.albedo_tile.shape[0]
            if S & (S - 1):
                raise ValueError(f"albedo tiles must be a power of two in size, got {S}")
            self.planes.append(
                dict(
                    axis=p.axis,
                    coord=np.float32(p.coord),
                    sign=p.sign,
                    axes=p.axes,
                    # a room's own planes close a box: whatever ray meets one inside its bounds
                    bounded=bool(np.isfinite(p.lo).all() and (scene.room is None or p.label not in ROOM_LABELS)),
                    lo=p.lo.astype(np.float32),
                    hi=p.hi.astype(np.float32),
                    S=S,
                    k=np.float32(S / p.albedo_period_m),
                    albedo=p.albedo_tile.reshape(-1, 3),
                    grid=(p.irradiance_grid / np.float32(np.pi)).astype(np.float32).reshape(-1, 3),
                    edge=p.shadow_edge.reshape(-1) if p.shadow_edge is not None and p.shadow_edge.any() else None,
                    strong=L.PointLights(
                        scene.lights.positions[p.strong_lights], scene.lights.intensities[p.strong_lights]
                    )
                    if p.strong_lights is not None and len(p.strong_lights)
                    else None,
                    gshape=p.irradiance_grid.shape[:2],
                    glo=p.grid_lo.astype(np.float32),
                    ginv=np.float32(1.0 / p.grid_cell_m),
                )
            )
        self._cache: tuple[bytes, tuple] | None = None
        self._last: tuple[bytes, tuple] | None = None

    def geometry(self, T_world_cam: np.ndarray):
        """(plane index per pixel or -1, depth per pixel, world ray directions (3, N), origin)."""
        key = T_world_cam.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        R = T_world_cam[:3, :3].astype(np.float32)
        o = T_world_cam[:3, 3].astype(np.float32)
        rc = self.rays_cam
        # (3, N) world direction with unit camera z, so t is the depth (written out: numpy's
        # matmul of a 3x3 by a 3xN array is several times slower than three fused rows)
        d = R[:, 0:1] * rc[0] + R[:, 1:2] * rc[1] + R[:, 2:3]
        with np.errstate(divide="ignore"):
            inv = np.float32(1.0) / d
        n = d.shape[1]
        best_t = np.full(n, np.inf, np.float32)
        best_i = np.full(n, -1, np.int8)
        for i, p in enumerate(self.planes):
            ax = p["axis"]
            if p["sign"] * (o[ax] - p["coord"]) <= 0:  # one-sided: the camera is behind it
                continue
            sel = self._footprint(p, T_world_cam) if p["bounded"] else None
            if sel is not None and sel.size == 0:  # out of view
                continue
            dd, iv = (d, inv) if sel is None else (d[:, sel], inv[:, sel])
            bt = best_t if sel is None else best_t[sel]
            t = (p["coord"] - o[ax]) * iv[ax]
            ok = t > 0
            ok &= t < bt
            if p["bounded"]:
                a, b = p["axes"]
                xa = o[a] + t * dd[a]
                xb = o[b] + t * dd[b]
                ok &= (xa >= p["lo"][0]) & (xa <= p["hi"][0]) & (xb >= p["lo"][1]) & (xb <= p["hi"][1])
            if sel is None:
                np.copyto(best_t, t, where=ok)
                np.copyto(best_i, np.int8(i), where=ok)
            else:
                hit = sel[ok]
                best_t[hit] = t[ok]
                best_i[hit] = np.int8(i)
        res = (best_i, best_t, d, o)
        self._cache = (key, res)
        return res

    def _footprint(self, p: dict, T_world_cam: np.ndarray) -> np.ndarray | None:
        """Pixels whose rays can meet a bounded rectangle: its projected bounding box (a small
        box face covers a few per cent of the picture; a cluttered room has ~20 of them), or
        ``None`` (test every pixel) when the rectangle reaches behind the camera."""
        intr = self.scene.intrinsics
        a, b = p["axes"]
        c = np.zeros((4, 3))
        c[:, p["axis"]] = p["coord"]
        c[:, a] = [p["lo"][0], p["lo"][0], p["hi"][0], p["hi"][0]]
        c[:, b] = [p["lo"][1], p["hi"][1], p["lo"][1], p["hi"][1]]
        cam = (c - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]  # world -> camera: R^T (x - t)
        if np.any(cam[:, 2] <= 1e-3):
            return None if np.any(cam[:, 2] > 1e-3) else np.zeros(0, np.int64)
        u = intr.fx * cam[:, 0] / cam[:, 2] + intr.cx
        v = intr.fy * cam[:, 1] / cam[:, 2] + intr.cy
        u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, intr.width)
        v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, intr.height)
        if u0 >= u1 or v0 >= v1:
            return np.zeros(0, np.int64)
        return (np.arange(v0, v1)[:, None] * intr.width + np.arange(u0, u1)[None, :]).ravel()

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radiance (N, 3) float32 and clean depth (N,) float32 (0 where nothing is hit).

        The light is static, so for an unchanged pose (static path) the last result is reused.
        Callers must not modify the returned arrays.
        """
        key = T_world_cam.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        idx, depth, d, o = self.geometry(T_world_cam)
        n = idx.shape[0]
        rad = np.empty((n, 3), np.float32)
        order = np.argsort(idx, kind="stable")  # group pixels by plane once, instead of a mask per plane
        bounds = np.searchsorted(idx[order], np.arange(-1, len(self.planes) + 1))
        for i, p in enumerate(self.planes):
            sel = order[bounds[i + 1] : bounds[i + 2]]
            if sel.size == 0:
                continue
            t = depth[sel]
            a, b = p["axes"]
            xa = o[a] + t * d[a, sel]
            xb = o[b] + t * d[b, sel]
            S = p["S"]
            m = S - 1
            # floor, not truncation: texel -1 is S - 1 (a tile repeats the same on both sides of 0)
            ti = (np.floor(xa * p["k"]).astype(np.int32) & m) * S + (np.floor(xb * p["k"]).astype(np.int32) & m)
            alb = np.take(p["albedo"], ti, axis=0)
            gu, gv = p["gshape"]
            fa = (xa - p["glo"][0]) * p["ginv"]
            fb = (xb - p["glo"][1]) * p["ginv"]
            ga = np.clip((fa + np.float32(0.5)).astype(np.int32), 0, gu - 1)
            gb = np.clip((fb + np.float32(0.5)).astype(np.int32), 0, gv - 1)
            flat = ga * gv + gb
            e = np.take(p["grid"], flat, axis=0)
            if p["edge"] is not None:
                sharp = np.flatnonzero(np.take(p["edge"], flat))
                if sharp.size and p["strong"] is not None:
                    # a hard shadow edge crosses the cell: move the strong lights' contribution
                    # from the cell's node (where the grid is exact) to the pixel itself
                    nrm = np.zeros(3)
                    nrm[p["axis"]] = p["sign"]
                    q = np.empty((2 * sharp.size, 3), np.float64)
                    q[:, p["axis"]] = p["coord"]
                    q[: sharp.size, a] = xa[sharp]
                    q[: sharp.size, b] = xb[sharp]
                    q[sharp.size :, a] = p["glo"][0] + ga[sharp] / p["ginv"]
                    q[sharp.size :, b] = p["glo"][1] + gb[sharp] / p["ginv"]
                    vis = self.scene.occlusion(q + 1e-4 * nrm, p["strong"])
                    es = L.irradiance(q, np.broadcast_to(nrm, q.shape), p["strong"], vis)
                    e[sharp] += ((es[: sharp.size] - es[sharp.size :]) / np.pi).astype(np.float32)
            alb *= e
            rad[sel] = alb
        miss = order[: bounds[1]]
        if miss.size:
            sky = self.scene.sky
            if sky is None:
                rad[miss] = 0.0
            else:
                dm = d[:, miss].T
                rad[miss] = sky.radiance(dm / np.linalg.norm(dm, axis=1, keepdims=True))
        out = (rad, np.where(idx >= 0, depth, np.float32(0.0)))
        self._last = (key, out)
        return out


# ----------------------------------------------------------------------------------- the source


def _choose_exposure(mean_radiance_luma: float) -> Exposure:
    """Auto exposure: expose the mean luminance to 18 % grey, longest time first, then ISO."""
    k = AE_TARGET / max(mean_radiance_luma, 1e-12)
    t_s = np.clip(k, EXPOSURE_US_RANGE[0] * 1e-6, EXPOSURE_US_RANGE[1] * 1e-6)
    iso = np.clip(100.0 * k / t_s, *ISO_RANGE)
    exposure_us = float(np.round(t_s * 1e6))
    return Exposure(exposure_us=exposure_us, iso=float(np.round(iso, 1)), wb_gains=(1.0, 1.0, 1.0))


class SyntheticSource(Source):
    """A simulated RGB-D camera (see the module docstring). Not live: nothing is dropped.

    Attributes
    ----------
    scene : SyntheticScene
        Lights, planes, poses and the ground-truth functions.
    """

    name = "synthetic"
    provides = (SYNTHETIC_GT,)
    live = False

    def __init__(self, scene: SyntheticScene, frames: int, url: str = ""):
        self.scene = scene
        self.frames = int(frames)
        self.url = url
        self._renderer: _Renderer | None = None
        self._i = 0
        seed = scene.seed
        rng = np.random.default_rng([seed, 99])
        intr = scene.intrinsics
        npx = intr.width * intr.height
        # noise bank: 4 frames of Gaussians; each frame reads a window at a random offset
        self._bank = rng.standard_normal(npx * 3 * 4 + 4, dtype=np.float32)
        self._lut = (np.rint(np.clip(_srgb_encode(np.linspace(0, 1, _SRGB_LUT_SIZE)), 0, 1) * 255)).astype(np.uint8)

    def open(self) -> None:
        if self._renderer is None:
            self._renderer = _Renderer(self.scene)

    def close(self) -> None:
        self._renderer = None

    def stats(self) -> dict:
        return {"frames": self._i, "scene": self.scene.kind, "seed": self.scene.seed}

    def render(self, i: int) -> Frame:
        """Frame ``i`` of the run (deterministic: the same for a given seed and index)."""
        if self._renderer is None:
            self.open()
        sc = self.scene
        intr = sc.intrinsics
        H, W = intr.height, intr.width
        T_wc = sc.poses[i % len(sc.poses)]
        rad, depth = self._renderer.render(T_wc)
        rng = np.random.default_rng([sc.seed, 7, i])
        # auto exposure on a subsample of the picture (as a camera's AE statistics grid does)
        mean = float(np.mean(rad[::61] @ _LUMA))
        exp = _choose_exposure(mean)
        k = np.float32(exp.scale)
        gain = np.float32(exp.iso / 100.0)
        x = rad * k
        sigma = np.sqrt(
            np.maximum(x, 0) * (gain / FULL_WELL_E) + (READ_NOISE_E * gain / FULL_WELL_E) ** 2 + ADC_NOISE**2
        )
        off = int(rng.integers(0, self._bank.size - x.size))
        x = x + sigma * self._bank[off : off + x.size].reshape(x.shape)
        q = np.clip(x * np.float32(_SRGB_LUT_SIZE - 1) + np.float32(0.5), 0, _SRGB_LUT_SIZE - 1).astype(np.int32)
        color = self._lut[q].reshape(H, W, 3)
        # its own window of the bank, so depth noise is independent of the colour noise
        off_d = int(rng.integers(0, self._bank.size - H * W))
        depth_img = _stereo_depth(depth.reshape(H, W), intr.fx, rng, self._bank, off_d)
        down = T_wc[:3, :3].T @ np.array([0.0, -1.0, 0.0])
        frame = Frame(
            seq=i,
            t_device_ns=i * FRAME_PERIOD_NS,
            t_host_ns=time.monotonic_ns(),
            color=color,
            depth=depth_img,
            intrinsics=intr,
            exposure=exp,
            gravity=down,
        )
        return frame.with_result(SYNTHETIC_GT, {"frame": i, "T_cam_world": invert(T_wc)})

    def read(self) -> Frame | None:
        if self._i >= self.frames:
            return None
        f = self.render(self._i)
        self._i += 1
        return f


#: distinct frames a live synthetic camera renders at open() and then plays in a loop
LIVE_CYCLE = 32


class LiveSyntheticSource(SyntheticSource):
    """``synthetic://SCENE?live=1&fps=N``: the synthetic camera as a live camera, on its own clock.

    The frames are rendered once at :meth:`open` (at most :data:`LIVE_CYCLE` distinct ones, played
    in a loop), so the camera's pace does not depend on the host's rendering speed. From the first
    :meth:`read` on (the loop's start, after the stages opened) a thread delivers frame ``i`` at
    ``start + i / fps`` (no drift; a late frame is delivered at once) into a
    non-blocking queue of ``queue`` frames that drops the oldest when full, as an OAK-D's output
    queue does; :meth:`read` blocks for a frame and returns the newest, counting the older ones it
    skips. Every delivered frame has its own ``seq``, ``t_device_ns = i / fps`` and ``t_host_ns`` =
    the host's monotonic clock when it was delivered (its capture time, for the loop's latency).
    ``stats()`` counts ``delivered`` and ``dropped`` (by the queue or skipped by read) and
    ``queue_max``: the queue never holds more than ``queue`` frames, however slow the reader.
    """

    name = "synthetic-live"
    live = True

    def __init__(self, scene: SyntheticScene, frames: int, url: str = "", fps: float = 30.0, queue: int = 2):
        super().__init__(scene, frames, url)
        if not fps > 0:
            raise SyntheticError(f"{url!r}: fps must be > 0, got {fps!r}")
        self.fps = float(fps)
        self.queue = int(queue)
        self._cycle: list[Frame] = []
        self._q: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._finished = False
        self.delivered = 0
        self.dropped = 0
        self.queue_max = 0

    def _ensure_cycle(self) -> None:
        if not self._cycle:
            SyntheticSource.open(self)
            self._cycle = [SyntheticSource.render(self, i) for i in range(min(self.frames, LIVE_CYCLE))]

    def open(self) -> None:
        self._ensure_cycle()
        self._stop.clear()
        self._finished = False
        self._q.clear()
        self.delivered = self.dropped = self.queue_max = 0
        self._thread = None  # started by the first read(): the stages' opening (GL, models) is not the run

    def _start(self) -> None:
        self._thread = threading.Thread(target=self._produce, name="illuminet-synthetic-live", daemon=True)
        self._thread.start()

    def _produce(self) -> None:
        period_ns = int(round(1e9 / self.fps))
        t0 = time.monotonic_ns()
        for i in range(self.frames):
            delay = t0 + i * period_ns - time.monotonic_ns()
            if delay > 0 and self._stop.wait(delay * 1e-9):
                break
            if self._stop.is_set():
                break
            base = self._cycle[i % len(self._cycle)]
            f = base.replace(seq=i, t_device_ns=i * period_ns, t_host_ns=time.monotonic_ns())
            with self._cond:
                if len(self._q) >= self.queue:
                    self._q.popleft()  # non-blocking queue: the oldest frame goes
                    self.dropped += 1
                self._q.append(f)
                self.delivered += 1
                self.queue_max = max(self.queue_max, len(self._q))
                self._cond.notify_all()
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def read(self) -> Frame | None:
        """The newest delivered frame (older ones waiting are dropped); blocks until one arrives.

        ``None`` at the end of the stream or after :meth:`close`. The first call starts the camera's clock.
        """
        if self._thread is None and not self._stop.is_set():
            self._start()
        with self._cond:
            while not self._q and not self._finished and not self._stop.is_set():
                self._cond.wait(0.1)
            if not self._q:
                return None
            f = self._q.pop()
            self.dropped += len(self._q)
            self._q.clear()
            self._i = f.seq + 1
            return f

    def render(self, i: int) -> Frame:
        """Frame ``i`` as delivered (the cycle's frame ``i % LIVE_CYCLE``, host time now)."""
        self._ensure_cycle()
        return self._cycle[i % len(self._cycle)].replace(seq=i, t_host_ns=time.monotonic_ns())

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        super().close()

    def stats(self) -> dict:
        with self._cond:
            return {
                **super().stats(),
                "fps": self.fps,
                "delivered": self.delivered,
                "dropped": self.dropped,
                "queue_max": self.queue_max,
            }


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _stereo_depth(z: np.ndarray, fx: float, rng: np.random.Generator, bank: np.ndarray, off: int) -> np.ndarray:
    """Clean depth -> stereo-like depth: disparity noise and quantisation, edge holes, blobs, range."""
    import cv2

    fb = np.float32(fx * STEREO_BASELINE_M)
    valid = (z > MIN_DEPTH_M) & (z < MAX_DEPTH_M)
    with np.errstate(divide="ignore"):
        disp = np.where(valid, fb / np.maximum(z, 1e-6), 0).astype(np.float32)
    noise = bank[off : off + z.size].reshape(z.shape)
    step = np.float32(DISPARITY_STEP_PX)
    disp = np.round((disp + np.float32(DISPARITY_NOISE_PX) * noise) / step) * step
    # holes where depth jumps (occlusion / matching failure at edges), dilated a few pixels
    jump = np.zeros_like(valid)
    dz = np.abs(np.diff(z, axis=1)) > 0.04 * z[:, 1:]
    jump[:, 1:] |= dz
    jump[:, :-1] |= dz
    dzy = np.abs(np.diff(z, axis=0)) > 0.04 * z[1:]
    jump[1:] |= dzy
    jump[:-1] |= dzy
    if jump.any():
        jump = cv2.dilate(jump.astype(np.uint8), np.ones((3, 5), np.uint8)).astype(bool)
    # a few blobs where matching fails (specular spots, low texture)
    blobs = np.zeros(z.shape, np.uint8)
    for _ in range(int(rng.integers(2, 6))):
        c = (int(rng.integers(0, z.shape[1])), int(rng.integers(0, z.shape[0])))
        cv2.circle(blobs, c, int(rng.integers(2, max(3, z.shape[1] // 80))), 1, -1)
    ok = valid & ~jump & (blobs == 0) & (disp > 0)
    with np.errstate(divide="ignore"):
        out = np.where(ok, fb / np.maximum(disp, 1e-6), 0).astype(np.float32)
    out[(out < MIN_DEPTH_M) | (out > MAX_DEPTH_M)] = 0
    return out


#: the parameters of ``synthetic://SCENE?...`` and their parsers (sizes: 32..4096 per side)
_PARAMS = {
    "seed": query_int(0, 2**31 - 1),
    "size": query_size(32, 4096),
    "width": query_int(32, 4096),
    "height": query_int(32, 4096),
    "frames": query_int(1, 10_000_000),
    "path": query_choice(*PATHS),
    "hdr": str,
    "table": query_bool,
    "lights": query_int(1, 1024),
    "bounce": query_int(0, MAX_BOUNCES),
    "boxes": query_int(0, 12),
    "position": query_int(0, 1000),
    "live": query_bool,
    "fps": query_int(1, 1000),
    "queue": query_int(1, 4),
}


#: most work the scene's bake may take: lights x (1 + occluders) x sqrt(pixels / 640x400). Baking the
#: ground truth (irradiance with shadows) costs ~0.04 s per unit on a 2-core machine, so a scene within
#: it starts in seconds; beyond it a URL like lights=1024&boxes=12&size=4096x4096 stalled for minutes
MAX_BAKE_WORK = 512


def bake_work(kind: str, lights: int, boxes: int | None, table: bool | None, size: tuple[int, int]) -> float:
    """The bake cost of a scene in :data:`MAX_BAKE_WORK` units (an upper estimate from its parameters)."""
    n_boxes = boxes if boxes is not None else (4 if kind == "cluttered" else 0)
    n_table = 1 if (table if table is not None else kind in ("indoor", "cluttered")) else 0  # as build_scene
    return lights * (1 + n_boxes + n_table) * math.sqrt(size[0] * size[1] / (640 * 400))


def open_url(url: str, config=None) -> SyntheticSource:
    """Create the synthetic source for ``synthetic://SCENE?...`` (see the module docstring)."""
    parts = urlsplit(url)
    if parts.scheme != "synthetic":
        raise SyntheticError(f"not a synthetic:// URL: {url!r}")
    kind = (parts.netloc or parts.path.strip("/")) or "indoor"
    q = parse_query(url, _PARAMS, error=SyntheticError)
    boxes = q.get("boxes")
    hdr = q.get("hdr")
    if hdr is not None and kind != "outdoor":
        raise SyntheticError(f"{url!r}: hdr= applies to the outdoor scene only")
    if hdr is not None and Path(hdr).is_dir():
        maps = sorted(Path(hdr).glob("*.hdr"))
        example = f" (e.g. hdr={maps[0]})" if maps else ""
        raise SyntheticError(f"{url!r}: hdr={hdr} is a folder; expected one HDR map file (.hdr or .exr){example}")
    if hdr is not None and not Path(hdr).is_file():
        # a relative path is from the current folder (the docs' ../shared/... assume a checkout beside shared/)
        where = "" if Path(hdr).is_absolute() else f" (relative to the current folder: {Path(hdr).resolve()})"
        raise SyntheticError(
            f"{url!r}: HDR map not found: {hdr}{where}; expected an .hdr or .exr file, or no hdr= for the "
            "scene's own sun and sky"
        )
    size = q.get("size") or (q.get("width", 640), q.get("height", 400))  # or the width=640&height=400 spelling
    frames = q.get("frames", 60)
    work = bake_work(kind, q.get("lights", 32), boxes, q.get("table"), size)
    if work > MAX_BAKE_WORK:
        raise SyntheticError(
            f"{url!r}: lights={q.get('lights', 32)} with {boxes if boxes is not None else 'the default'} boxes at "
            f"{size[0]}x{size[1]} would take minutes to build (ground-truth work {work:.0f}, at most "
            f"{MAX_BAKE_WORK}: lights x (1 + boxes + table) x sqrt(pixels / 640x400)); use fewer lights or boxes, "
            "or a smaller size"
        )
    scene = build_scene(
        kind,
        q.get("seed", 0),
        size,
        frames,
        q.get("path", "static"),
        hdr or None,
        q.get("table"),
        q.get("lights", 32),
        q.get("bounce", DEFAULT_BOUNCES),
        boxes,
        q.get("position", 0),
    )
    if q.get("live"):
        return LiveSyntheticSource(scene, frames, url, fps=q.get("fps", 30), queue=q.get("queue", 2))
    if "fps" in q or "queue" in q:
        raise SyntheticError(f"{url!r}: fps= and queue= apply to a live camera only (add live=1)")
    return SyntheticSource(scene, frames, url)
