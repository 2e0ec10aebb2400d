"""``synthetic://`` — a simulated RGB-D camera in a lit scene, with ground truth for evaluation.

URL
    ``synthetic://SCENE?seed=N&size=WxH&frames=N&path=static|orbit[&hdr=PATH][&table=0|1][&lights=N]``
    (``width=W&height=H`` is accepted for ``size``)

    SCENE
        ``indoor``  a room (floor, four walls, ceiling; a table unless ``table=0``) lit by the
        random ``indoor`` environment of :mod:`illuminet.runtime.lighting`.
        ``outdoor`` a ground plane and a building facade behind the object, under a sun and sky
        (analytic, or the median cut of an HDR map when ``hdr=PATH`` is given; the sky seen in the
        picture is then the map itself). Normalised to 300-2500 units of horizontal irradiance.
        ``lamp``    a dim room plus one strong warm lamp 0.35-0.7 m from the object (near light:
        strong falloff over the floor).
        ``spatial`` a room lit by the spatially-varying environment; ``scene.object_positions``
        lists its 3-5 object positions, ``default_anchor(position=k)`` stands on one of them.
    seed      every random choice (room, lights, textures, camera, noise) follows from it
    size      ``640x400`` (default) or ``1280x800`` (OAK-D mono-like: fx = fy = 800 at 1280x800),
              other sizes scale the same intrinsics
    frames    frames before the end of the stream (default 60)
    path      ``static`` (default: a fixed camera, frames differ only by noise) or ``orbit``
              (the camera swings +-25 deg around the object and bobs 5 cm, one period per run)

What a frame holds
    ``color``: the scene's radiance (Lambertian, direct light only: ``albedo * E / pi``), times the
    auto exposure's scale ``k = exposure_s * ISO / 100`` (``Exposure.scale``, so dividing linear
    pixels by it gives scene-referred radiance), plus sensor noise (shot + read, growing with ISO),
    clipped, sRGB-encoded to 8 bits. No white balance is applied (``wb_gains = (1, 1, 1)``).
    ``depth``: float32 metres aligned to colour, quantised like a stereo camera (baseline 7.5 cm,
    1/8 px disparity), Gaussian disparity noise (depth noise grows with z^2), holes at depth edges
    and in a few random blobs, invalid below 0.35 m and beyond 12 m. ``gravity``: unit vector of
    gravity in camera coordinates. ``results["synthetic_gt"]``: frame index and ``T_cam_world``.

Ground truth (``source.scene``, a :class:`SyntheticScene`)
    ``lights`` (world frame: floor y = 0, +Y up, metres), ``lights_cam(frame)``, ``planes``,
    ``occluders``, ``true_object_shading(mesh, T_cam_obj, frame=0)`` (per-vertex irradiance with
    self-shadowing and occlusion by the table/facade/ground), ``true_plane_irradiance(points_cam,
    normal_cam, frame=0)``, ``default_anchor(frame=0, position=0)``.

Speed: the irradiance of every plane is computed once per scene on a 1-2 cm grid; a frame is a
ray-plane intersection, two table lookups per pixel (albedo tile, irradiance grid) and noise drawn
from a per-scene bank at a random offset (so consecutive frames get different noise without
drawing a million Gaussians per frame). With the static path the geometry is cached as well.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

from illuminet.runtime import lighting as L
from illuminet.runtime.frame import Exposure, Frame, Intrinsics
from illuminet.runtime.odometry import invert
from illuminet.runtime.scene import Plane
from illuminet.runtime.stage import Source

SCENES = ("indoor", "outdoor", "lamp", "spatial")
PATHS = ("static", "orbit")

#: OAK-D-like colour intrinsics at 1280x800 (mono sensors' field of view: ~77 deg horizontal).
OAKD_INTRINSICS_1280 = Intrinsics(fx=800.0, fy=800.0, cx=639.5, cy=399.5, width=1280, height=800)

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


class SyntheticError(ValueError):
    """A ``synthetic://`` URL is invalid; the message names the parameter and what was expected."""


# ------------------------------------------------------------------------------------ textures


def _periodic_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth value noise of ``size``^2 that tiles seamlessly, from a ``cells``^2 random lattice."""
    import cv2

    base = rng.random((cells, cells)).astype(np.float32)
    pad = np.pad(base, 2, mode="wrap")
    scale = size / cells
    big = cv2.resize(pad, (int(round(pad.shape[1] * scale)), int(round(pad.shape[0] * scale))),
                     interpolation=cv2.INTER_CUBIC)
    o = int(round(2 * scale))
    return big[o : o + size, o : o + size]


def _fractal(rng: np.random.Generator, size: int, octaves=(4, 16, 64), weights=(0.5, 0.3, 0.2)) -> np.ndarray:
    n = sum(w * _periodic_noise(rng, size, c) for c, w in zip(octaves, weights))
    return (n - n.mean()) / (n.std() + 1e-6)


def make_albedo_tile(kind: str, rng: np.random.Generator, size: int = 512) -> tuple[np.ndarray, float]:
    """A seamless albedo tile (size x size x 3, linear, in [0.02, 0.95]) and its period in metres.

    Kinds: ``wood`` (planks), ``tiles``, ``carpet``, ``paint`` (walls), ``ceiling``, ``concrete``,
    ``grass``, ``brick``, ``tabletop``.
    """
    s = size
    yy, xx = np.mgrid[0:s, 0:s].astype(np.float32) / s
    if kind == "wood":
        period, planks = 1.0, 8
        plank = np.floor(yy * planks).astype(int)
        tint = rng.uniform(0.75, 1.25, planks)[plank]
        grain = np.repeat(_fractal(rng, s, (2, 8, 32))[:1], s, axis=0) * 0.3 + _fractal(rng, s) * 0.15
        base = np.array([0.42, 0.27, 0.15]) * rng.uniform(0.7, 1.4)
        a = base * (tint * (1 + 0.25 * grain))[..., None]
        gap = (np.mod(yy * planks, 1.0) < 0.02)
        a[gap] *= 0.35
    elif kind == "tiles":
        period, n = 1.0, 4
        base = np.array(rng.uniform(0.45, 0.8, 3))
        base = base * 0.3 + base.mean() * 0.7
        cell = (np.floor(yy * n) * n + np.floor(xx * n)).astype(int)
        tint = rng.uniform(0.9, 1.1, n * n)[cell]
        a = base * (tint * (1 + 0.05 * _fractal(rng, s)))[..., None]
        grout = (np.mod(yy * n, 1.0) < 0.015) | (np.mod(xx * n, 1.0) < 0.015)
        a[grout] = 0.35
    elif kind == "carpet":
        period = 0.5
        base = rng.uniform(0.12, 0.45, 3)
        a = base * (1 + 0.15 * _fractal(rng, s, (8, 64, 256), (0.3, 0.3, 0.4)))[..., None]
    elif kind == "paint":
        period = 2.0
        base = rng.uniform(0.55, 0.8) * np.array([1.0, 1.0, 1.0]) * rng.uniform(0.92, 1.08, 3)
        a = base * (1 + 0.02 * _fractal(rng, s, (2, 8, 32)))[..., None]
    elif kind == "ceiling":
        period = 2.0
        a = np.full((s, s, 3), 0.8) * (1 + 0.01 * _fractal(rng, s))[..., None]
    elif kind == "concrete":
        period, n = 2.0, 2
        base = rng.uniform(0.2, 0.4) * np.array([1.0, 0.98, 0.95])
        a = base * (1 + 0.12 * _fractal(rng, s, (8, 32, 128)))[..., None]
        joint = (np.mod(yy * n, 1.0) < 0.006) | (np.mod(xx * n, 1.0) < 0.006)
        a[joint] *= 0.5
    elif kind == "grass":
        period = 1.0
        base = np.array([0.08, 0.16, 0.04]) * rng.uniform(0.8, 1.3)
        a = base * (1 + 0.3 * _fractal(rng, s, (4, 64, 256), (0.3, 0.3, 0.4)))[..., None]
    elif kind == "brick":
        period = 1.0
        rows, cols = 15, 4
        r = np.floor(yy * rows).astype(int)
        shift = (r % 2) * 0.5 / cols
        c = np.floor(np.mod(xx + shift, 1.0) * cols).astype(int)
        tint = rng.uniform(0.8, 1.2, (rows, cols))[r, c]
        base = np.array([0.45, 0.2, 0.12]) * rng.uniform(0.8, 1.2)
        a = base * (tint * (1 + 0.1 * _fractal(rng, s)))[..., None]
        mortar = (np.mod(yy * rows, 1.0) < 0.12) | (np.mod((xx + shift) * cols, 1.0) < 0.03)
        a[mortar] = 0.5
    elif kind == "tabletop":
        period = 1.0
        base = np.array([0.6, 0.45, 0.3]) * rng.uniform(0.8, 1.2)
        grain = np.repeat(_fractal(rng, s, (2, 8, 32))[:1], s, axis=0)
        a = base * (1 + 0.12 * grain)[..., None]
    else:
        raise ValueError(f"unknown albedo kind {kind!r}")
    return np.clip(a, 0.02, 0.95).astype(np.float32), period


# -------------------------------------------------------------------------------------- planes


@dataclass
class SyntheticPlane:
    """An axis-aligned textured rectangle in the world frame (floor y = 0, +Y up, metres).

    Points with ``x[axis] == coord``; the lit (front) side faces ``normal`` (``sign`` along axis).
    ``lo``/``hi`` bound the two other axes (``axes``), ``inf`` for unbounded ground.
    """

    name: str
    label: str  # "floor", "wall", "ceiling", "table", "ground"
    axis: int
    coord: float
    sign: float
    axes: tuple[int, int]
    lo: np.ndarray
    hi: np.ndarray
    albedo_tile: np.ndarray
    albedo_period_m: float
    irradiance_grid: np.ndarray | None = None  # (nu, nv, 3)
    shadow_edge: np.ndarray | None = None  # (nu, nv) bool: cells along hard shadow edges of strong lights
    strong_lights: np.ndarray | None = None  # indices of the lights whose shadow edges are exact
    grid_lo: np.ndarray | None = None
    grid_cell_m: float = 0.01

    @property
    def normal(self) -> np.ndarray:
        n = np.zeros(3)
        n[self.axis] = self.sign
        return n

    @property
    def albedo_mean(self) -> np.ndarray:
        """Mean linear albedo (RGB) of the texture."""
        return self.albedo_tile.reshape(-1, 3).mean(0).astype(np.float64)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Mask of world points (on the plane) inside the rectangle."""
        a, b = self.axes
        return (p[..., a] >= self.lo[0]) & (p[..., a] <= self.hi[0]) & (p[..., b] >= self.lo[1]) & (p[..., b] <= self.hi[1])


@dataclass
class Occluder:
    """Something that blocks light: an axis-aligned rectangle, or (``axes=None``) a whole plane."""

    axis: int
    coord: float
    axes: tuple[int, int] | None = None
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None

    def blocks(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether the segments p -> q cross this occluder. p: (..., 3), q broadcastable."""
        pa, qa = p[..., self.axis] - self.coord, q[..., self.axis] - self.coord
        cross = (pa * qa) < 0
        if self.axes is None:
            return cross
        with np.errstate(divide="ignore", invalid="ignore"):
            s = pa / (pa - qa)
        a, b = self.axes
        # only the two in-plane coordinates of the crossing point are needed
        xa = p[..., a] + s * (q[..., a] - p[..., a])
        xb = p[..., b] + s * (q[..., b] - p[..., b])
        return cross & (xa >= self.lo[0]) & (xa <= self.hi[0]) & (xb >= self.lo[1]) & (xb <= self.hi[1])


def _room_planes(rng, lo, hi, floor_kind):
    mk = make_albedo_tile
    planes = [SyntheticPlane("floor", "floor", 1, lo[1], +1.0, (0, 2), lo[[0, 2]], hi[[0, 2]], *mk(floor_kind, rng))]
    paint = mk("paint", rng)
    for name, axis, side in (("wall_x0", 0, 0), ("wall_x1", 0, 1), ("wall_z0", 2, 0), ("wall_z1", 2, 1)):
        others = (1, 2) if axis == 0 else (0, 1)
        coord = lo[axis] if side == 0 else hi[axis]
        planes.append(SyntheticPlane(name, "wall", axis, coord, +1.0 if side == 0 else -1.0, others,
                                     lo[list(others)], hi[list(others)], *paint))
    planes.append(SyntheticPlane("ceiling", "ceiling", 1, hi[1], -1.0, (0, 2), lo[[0, 2]], hi[[0, 2]], *mk("ceiling", rng)))
    return planes


# --------------------------------------------------------------------------------------- scene


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 T_world_cam of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([r, d, f])
    T[:3, 3] = eye
    return T


@dataclass
class SyntheticScene:
    """Everything that defines a synthetic scene; the ground truth evaluators read.

    All geometry is in the world frame: floor (or ground) y = 0, +Y up, metres. The default object
    frame coincides with the world frame at ``object_positions[0]`` (the origin unless spatial).
    """

    kind: str
    seed: int
    lights: L.PointLights
    planes: list[SyntheticPlane]
    occluders: list[Occluder]
    object_positions: np.ndarray
    intrinsics: Intrinsics
    poses: list[np.ndarray]  # T_world_cam per frame
    sky: "_Sky | None" = None
    room: tuple[np.ndarray, np.ndarray] | None = None
    hdr_path: str | None = None
    info: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ poses and frames
    def T_cam_world(self, frame: int = 0) -> np.ndarray:
        """4x4 transform world -> camera for ``frame``."""
        return invert(self.poses[frame % len(self.poses)])

    def lights_cam(self, frame: int = 0) -> L.PointLights:
        """The lights in the camera frame of ``frame`` (OpenCV axes)."""
        T = self.T_cam_world(frame)
        return self.lights.transformed(T[:3, :3], T[:3, 3])

    def default_anchor(self, frame: int = 0, position: int = 0) -> np.ndarray:
        """4x4 T_cam_obj of an object standing upright on the floor at ``object_positions[position]``."""
        T_wo = np.eye(4)
        T_wo[:3, 3] = self.object_positions[position]
        return self.T_cam_world(frame) @ T_wo

    def planes_cam(self, frame: int = 0) -> list[Plane]:
        """The bounded planes in view as :class:`~illuminet.runtime.scene.Plane` (camera frame)."""
        T = self.T_cam_world(frame)
        out = []
        for i, p in enumerate(self.planes):
            n = T[:3, :3] @ p.normal
            x0 = np.zeros(3)
            x0[p.axis] = p.coord
            x0[list(p.axes)] = np.where(np.isfinite(p.lo + p.hi), (p.lo + p.hi) / 2, 0.0)
            c = T[:3, :3] @ x0 + T[:3, 3]
            off = -float(n @ c)
            if off < 0:  # the camera is behind it
                continue
            area = float(np.prod(np.minimum(p.hi - p.lo, 1e3)))
            out.append(Plane(id=i, normal=n, offset=off, centroid=c, area_m2=area,
                             label={"ground": "floor", "ceiling": "other"}.get(p.label, p.label)))
        return out

    # ------------------------------------------------------------------ ground truth
    def occlusion(self, points_world: np.ndarray, lights: L.PointLights | None = None) -> np.ndarray:
        """(P, N) visibility in {0, 1} of the scene lights from world points, by the scene's occluders."""
        lp = (self.lights if lights is None else lights).positions
        p = np.asarray(points_world, float).reshape(-1, 3)
        vis = np.ones((p.shape[0], lp.shape[0]))
        for occ in self.occluders:
            vis[occ.blocks(p[:, None, :] + 1e-6 * np.array([0, 1.0, 0]), lp[None, :, :])] = 0.0
        return vis

    def true_plane_irradiance(self, points_cam: np.ndarray, normal_cam: np.ndarray, frame: int = 0) -> np.ndarray:
        """Irradiance (P, 3) at camera-frame points with a camera-frame normal (one (3,) or (P, 3))."""
        pts = np.asarray(points_cam, float).reshape(-1, 3)
        nrm = np.broadcast_to(np.asarray(normal_cam, float).reshape(-1, 3), pts.shape)
        Tw = self.poses[frame % len(self.poses)]
        pw = pts @ Tw[:3, :3].T + Tw[:3, 3]
        return L.irradiance(pts, nrm, self.lights_cam(frame), self.occlusion(pw))

    def albedo_at(self, points_cam: np.ndarray, frame: int = 0, tol: float = 0.01) -> np.ndarray:
        """True linear albedo (P, 3) at camera-frame points on the scene's planes; NaN off every plane.

        A point belongs to the first plane within ``tol`` metres of it and inside its bounds.
        """
        pts = np.asarray(points_cam, float).reshape(-1, 3)
        Tw = self.poses[frame % len(self.poses)]
        pw = pts @ Tw[:3, :3].T + Tw[:3, 3]
        out = np.full((pts.shape[0], 3), np.nan)
        todo = np.ones(pts.shape[0], bool)
        for p in self.planes:
            on = todo & (np.abs(pw[:, p.axis] - p.coord) <= tol) & p.contains(pw)
            if not on.any():
                continue
            S = p.albedo_tile.shape[0]
            k = S / p.albedo_period_m
            a, b = p.axes
            ia = np.floor(pw[on, a] * k).astype(np.int64) % S
            ib = np.floor(pw[on, b] * k).astype(np.int64) % S
            out[on] = p.albedo_tile[ia, ib]
            todo &= ~on
        return out

    def object_lights(self, T_cam_obj: np.ndarray, frame: int = 0) -> L.PointLights:
        """The scene lights in the object frame of an object at ``T_cam_obj`` (seen in ``frame``)."""
        T_obj_world = invert(self.poses[frame % len(self.poses)] @ np.asarray(T_cam_obj, float))
        return self.lights.transformed(T_obj_world[:3, :3], T_obj_world[:3, 3])

    def true_object_oi(self, mesh, T_cam_obj: np.ndarray, visibility: bool = True, frame: int = 0,
                       points: np.ndarray | None = None, normals: np.ndarray | None = None) -> np.ndarray:
        """Ground-truth OI (V, 3, 3) in the object frame; see :meth:`true_object_shading`."""
        pts, nrm, lights, vis = self._object_terms(mesh, T_cam_obj, visibility, frame, points, normals)
        return L.oi_point_lights(pts, nrm, lights, vis)

    def true_object_shading(self, mesh, T_cam_obj: np.ndarray, visibility: bool = True, frame: int = 0,
                            points: np.ndarray | None = None, normals: np.ndarray | None = None) -> np.ndarray:
        """Ground-truth irradiance (V, 3) on the mesh's vertices, scene-referred linear RGB.

        Parameters
        ----------
        mesh : trimesh.Trimesh in the object frame
        T_cam_obj : 4x4 pose of the object in the camera frame of ``frame``
        visibility : include self-shadowing (exact ray casts) and occlusion by the scene
            (table, facade, ground); False = every light in front of a vertex counts
        frame : which frame's camera ``T_cam_obj`` refers to
        points, normals : evaluate here instead of the mesh's vertices / vertex normals
        """
        pts, nrm, lights, vis = self._object_terms(mesh, T_cam_obj, visibility, frame, points, normals)
        return L.irradiance(pts, nrm, lights, vis)

    def _object_terms(self, mesh, T_cam_obj, visibility, frame, points, normals):
        from illuminet.runtime.visibility import exact_visibility

        pts = np.asarray(mesh.vertices if points is None else points, float)
        nrm = np.asarray(mesh.vertex_normals if normals is None else normals, float)
        lights = self.object_lights(T_cam_obj, frame)
        vis = None
        if visibility:
            T_wo = self.poses[frame % len(self.poses)] @ np.asarray(T_cam_obj, float)
            pw = pts @ T_wo[:3, :3].T + T_wo[:3, 3]
            vis = exact_visibility(mesh, pts, lights, normals=nrm).astype(float) * self.occlusion(pw)
        return pts, nrm, lights, vis


@dataclass
class _Sky:
    """Radiance of rays that leave the scene: an HDR map (rotated, scaled) or an analytic sky."""

    hdr: np.ndarray | None
    yaw_deg: float
    scale: float
    zenith: np.ndarray
    horizon: np.ndarray
    ground: np.ndarray

    def radiance(self, d: np.ndarray) -> np.ndarray:
        if self.hdr is None:
            up = np.clip(d[:, 1:2], 0.0, 1.0)
            sky = self.horizon + (self.zenith - self.horizon) * np.sqrt(up)
            return np.where(d[:, 1:2] >= 0, sky, self.ground).astype(np.float32)
        dm = d @ L.rotation_y(self.yaw_deg)  # world -> map: R^T d, written as d R
        H, W = self.hdr.shape[:2]
        theta = np.arccos(np.clip(dm[:, 1], -1, 1))
        phi = np.arctan2(dm[:, 0], -dm[:, 2])
        v = np.minimum((theta / np.pi * H).astype(np.int64), H - 1)
        u = np.minimum(((phi / np.pi + 1.0) * 0.5 * W).astype(np.int64), W - 1)
        return (self.hdr[v, u] * self.scale).astype(np.float32)


def _camera_poses(rng, kind, target, n_frames, path, room):
    """T_world_cam per frame: a camera 1.1-1.6 m high, 1.0-1.8 m from the object, looking at it."""
    for _ in range(200):
        h = rng.uniform(1.1, 1.6) if kind != "spatial" else rng.uniform(1.5, 1.9)
        dist = rng.uniform(1.0, 1.8)
        az = rng.uniform(0, 2 * np.pi)
        eye = target + np.array([dist * np.sin(az), h, dist * np.cos(az)])
        if room is None:
            break
        lo, hi = room
        margin = 0.45  # the orbit swings up to +-25 deg: keep it inside the room
        if np.all(eye[[0, 2]] > lo[[0, 2]] + margin) and np.all(eye[[0, 2]] < hi[[0, 2]] - margin) and eye[1] < hi[1] - 0.2:
            break
    else:
        raise RuntimeError("could not place the camera inside the room")
    # look a little past the object so it sits in the lower half of the picture
    aim = target + np.array([-0.35 * np.sin(az), 0.05, -0.35 * np.cos(az)])
    poses = []
    for i in range(max(n_frames, 1)):
        if path == "static":
            poses.append(_look_at(eye, aim))
            continue
        ph = 2 * np.pi * i / max(n_frames, 1)
        a = az + np.deg2rad(25.0) * np.sin(ph)
        e = target + np.array([dist * np.sin(a), h + 0.05 * np.sin(2 * ph), dist * np.cos(a)])
        if room is not None:
            e[[0, 2]] = np.clip(e[[0, 2]], room[0][[0, 2]] + 0.2, room[1][[0, 2]] - 0.2)
        poses.append(_look_at(e, target + np.array([-0.35 * np.sin(a), 0.05, -0.35 * np.cos(a)])))
    return poses


def _lamp_lights(rng):
    ambient, lo, hi = L.sample_indoor_scene(rng)
    ambient = ambient.scaled(rng.uniform(0.05, 0.15))
    r = rng.uniform(0.35, 0.7)
    a = rng.uniform(0, 2 * np.pi)
    pos = np.array([r * np.cos(a), rng.uniform(0.3, 0.7), r * np.sin(a)])
    e = L.color_temperature_rgb(rng.uniform(2400, 3000))
    lamp = L.PointLights(pos[None], e[None])
    # lamp alone gives 30-100 units of horizontal irradiance at the object
    e0 = L.irradiance(np.zeros((1, 3)), np.array([[0, 1.0, 0]]), lamp)[0] @ L._LUMA
    lamp = lamp.scaled(rng.uniform(30, 100) / e0)
    return lamp.concatenated(ambient), lo, hi


def build_scene(kind: str, seed: int, size: tuple[int, int] = (640, 400), frames: int = 60,
                path: str = "static", hdr: str | None = None, table: bool | None = None,
                n_lights: int = 32) -> SyntheticScene:
    """Create a synthetic scene (deterministic in ``seed``); see the module docstring for kinds."""
    if kind not in SCENES:
        raise SyntheticError(f"synthetic scene must be one of {', '.join(SCENES)}, got {kind!r}")
    if path not in PATHS:
        raise SyntheticError(f"synthetic path must be one of {', '.join(PATHS)}, got {path!r}")
    rng = np.random.default_rng([seed, SCENES.index(kind)])
    intr = OAKD_INTRINSICS_1280.scaled(*size)
    positions = np.zeros((1, 3))
    room = None
    occluders: list[Occluder] = []
    sky = None
    use_table = False
    info: dict = {}
    if kind in ("indoor", "lamp", "spatial"):
        if kind == "indoor":
            lights, lo, hi = L.sample_indoor_scene(rng, n_lights)
        elif kind == "lamp":
            lights, lo, hi = _lamp_lights(rng)
        else:
            lights, positions, lo, hi = L.sample_spatial_room(rng, n_lights)
        room = (lo, hi)
        planes = _room_planes(rng, lo, hi, rng.choice(["wood", "tiles", "carpet"]))
        use_table = (kind == "indoor") if table is None else bool(table)
    else:
        if hdr:
            img = L.load_hdr(hdr)
            yaw = rng.uniform(0, 360)
            raw = L.hdr_lights(img, n_lights, rotation_deg=yaw, distance=L.OUTDOOR_DISTANCE)
            e_h = L.irradiance(np.zeros((1, 3)), np.array([[0, 1.0, 0]]), raw)[0] @ L._LUMA
            scale = float(np.exp(rng.uniform(np.log(300), np.log(2500))) / max(e_h, 1e-9))
            lights = raw.scaled(scale)
            sky = _Sky(img, yaw, scale, None, None, None)
            info["hdr"] = str(hdr)
        else:
            lights = L.sample_lights("outdoor", rng, n_lights)
            sky_e = lights.intensities[1:].sum(0) / L.OUTDOOR_DISTANCE**2
            base = sky_e / np.pi  # radiance of a uniform sky giving that irradiance
            sky = _Sky(None, 0.0, 1.0, (base * [0.6, 0.8, 1.3]).astype(np.float32),
                       (base * [1.3, 1.3, 1.2]).astype(np.float32), (base * 0.3).astype(np.float32))
        ground = rng.choice(["concrete", "grass"])
        inf = np.array([np.inf, np.inf])
        planes = [SyntheticPlane("ground", "ground", 1, 0.0, +1.0, (0, 2), -inf, inf, *make_albedo_tile(ground, rng))]
        occluders.append(Occluder(1, 0.0))  # light from below the horizon cannot pass the ground
    poses = _camera_poses(rng, kind, positions[0], frames, path, room)
    if room is not None and use_table:
        _add_table(rng, room, positions, poses, planes, occluders, info)
    if kind == "outdoor":
        # put the facade behind the object as seen from the camera, facing the camera
        cam = poses[0][:3, 3]
        dx, dz = -cam[0], -cam[2]
        axis = 0 if abs(dx) > abs(dz) else 2
        sign = -np.sign(dx if axis == 0 else dz)
        coord = -sign * rng.uniform(2.5, 4.0)
        others = (1, 2) if axis == 0 else (0, 1)
        w = rng.uniform(6.0, 12.0)
        lo2 = np.array([0.0, -w / 2]) if axis == 0 else np.array([-w / 2, 0.0])
        hi2 = np.array([rng.uniform(4, 8), w / 2]) if axis == 0 else np.array([w / 2, rng.uniform(4, 8)])
        planes.append(SyntheticPlane("facade", "wall", axis, coord, sign, others, lo2, hi2, *make_albedo_tile("brick", rng)))
        occluders.append(Occluder(axis, coord, others, lo2, hi2))
    scene = SyntheticScene(kind, seed, lights, planes, occluders, positions, intr, poses, sky, room, hdr, info)
    for p in scene.planes:
        _bake_irradiance(scene, p, poses)
    return scene


def _add_table(rng, room, positions, poses, planes, occluders, info) -> None:
    """A 1.2 x 0.8 m table top, 0.72 m high, inside the room, at least 30 cm from every object
    position and never hiding an object from the camera along the path."""
    lo, hi = room
    tw, td = 1.2, 0.8
    eyes = np.array([T[:3, 3] for T in poses[:: max(1, len(poses) // 8)]])
    targets = np.concatenate([positions + [0, 0.01, 0], positions + [0, 0.26, 0]])
    for _ in range(200):
        c = rng.uniform(lo[[0, 2]] + 0.7, hi[[0, 2]] - 0.7)
        gap = np.abs(c - positions[:, [0, 2]]) - [tw / 2 + 0.3, td / 2 + 0.3]
        occ = Occluder(1, 0.72, (0, 2), c - [tw / 2, td / 2], c + [tw / 2, td / 2])
        hides = occ.blocks(eyes[:, None, :], targets[None, :, :]).any()
        if np.all(gap.max(axis=1) > 0) and not hides:
            break
    else:
        info["table_centre"] = None  # no place found: the room goes without a table
        return
    planes.append(SyntheticPlane("table", "table", 1, 0.72, +1.0, (0, 2), occ.lo, occ.hi, *make_albedo_tile("tabletop", rng)))
    occluders.append(occ)
    info["table_centre"] = c.tolist()


def _bake_irradiance(scene: SyntheticScene, p: SyntheticPlane, poses) -> None:
    """Irradiance of plane ``p`` on a grid (1 cm, coarser for planes over 10 m; unbounded ground: 10 m
    around the camera path, beyond which it is clamped — the depth camera's range ends at 12 m)."""
    lo, hi = p.lo.copy(), p.hi.copy()
    if not np.all(np.isfinite(lo)):
        # unbounded ground: bake what the camera can see, up to the depth limit, around the path
        cams = np.array([T[:3, 3] for T in poses])
        lo = np.array([cams[:, 0].min() - 10, cams[:, 2].min() - 10])
        hi = np.array([cams[:, 0].max() + 10, cams[:, 2].max() + 10])
    ext = hi - lo
    cell = max(0.01, float(ext.max()) / 1000.0)
    nu, nv = int(np.ceil(ext[0] / cell)) + 1, int(np.ceil(ext[1] / cell)) + 1
    # irradiance is smooth: evaluate on a coarser lattice and upsample (bilinear) to the cell grid
    import cv2

    step = 4
    cu, cv_ = (nu - 1) // step + 2, (nv - 1) // step + 2
    gu = lo[0] + np.arange(cu) * cell * step
    gv = lo[1] + np.arange(cv_) * cell * step
    pts = np.zeros((cu, cv_, 3))
    pts[..., p.axis] = p.coord
    pts[..., p.axes[0]] = gu[:, None]
    pts[..., p.axes[1]] = gv[None, :]
    pts = pts.reshape(-1, 3)
    vis = scene.occlusion(pts + 1e-4 * p.normal)
    e = L.irradiance(pts, np.tile(p.normal, (pts.shape[0], 1)), scene.lights, vis).reshape(cu, cv_, 3)
    vis = vis.reshape(cu, cv_, -1).astype(bool)
    # cell j of the fine grid lies at lattice coordinate j / step (exact, unlike cv2.resize's centres)
    mu = np.broadcast_to((np.arange(nu, dtype=np.float32) / step)[:, None], (nu, nv))
    mv = np.broadcast_to((np.arange(nv, dtype=np.float32) / step)[None, :], (nu, nv))
    big = cv2.remap(e.astype(np.float32), np.ascontiguousarray(mv), np.ascontiguousarray(mu), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    # shadow edges are not smooth: where the visibility of a light that matters (> 5 % of the
    # plane's brightest irradiance) changes between lattice nodes, evaluate every fine cell exactly
    # (only a band along those edges, so it stays cheap)
    lp = scene.lights.positions
    d = lp[None, :, :] - pts[:, None, :]
    r2 = (d * d).sum(-1)
    per_light = np.maximum((d @ p.normal) / r2**1.5, 0).max(0) * (scene.lights.intensities @ L._LUMA)
    strong = per_light > 0.05 * max(float(e.reshape(-1, 3).max(0) @ L._LUMA), 1e-12)
    vs = vis[..., strong]
    edge = np.zeros((cu - 1, cv_ - 1), bool)
    for a, b in ((0, 1), (1, 0), (1, 1)):
        edge |= np.any(vs[:-1, :-1] != vs[a : cu - 1 + a, b : cv_ - 1 + b], axis=2)
    ia = np.minimum(np.arange(nu) // step, cu - 2)
    ib = np.minimum(np.arange(nv) // step, cv_ - 2)
    edge_fine = edge[ia][:, ib]
    # the renderer computes the light exactly at pixels in these cells: sharp shadow edges
    # instead of a staircase of cells
    p.shadow_edge = edge_fine
    p.strong_lights = np.flatnonzero(strong)
    fine = np.argwhere(edge_fine)
    normal = p.normal
    for s in range(0, fine.shape[0], 20000):
        f = fine[s : s + 20000]
        q = np.zeros((f.shape[0], 3))
        q[:, p.axis] = p.coord
        q[:, p.axes[0]] = lo[0] + f[:, 0] * cell
        q[:, p.axes[1]] = lo[1] + f[:, 1] * cell
        ve = scene.occlusion(q + 1e-4 * normal)
        big[f[:, 0], f[:, 1]] = L.irradiance(q, np.tile(normal, (q.shape[0], 1)), scene.lights, ve)
    p.irradiance_grid = big.astype(np.float32)
    p.grid_lo = lo
    p.grid_cell_m = cell


# -------------------------------------------------------------------------------------- renderer


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
            np.stack([((u - intr.cx) / intr.fx).ravel(), ((v - intr.cy) / intr.fy).ravel(), np.ones(u.size, np.float32)])
        )  # (3, N)
        self.planes = []
        for p in scene.planes:
            S = p.albedo_tile.shape[0]
            if S & (S - 1):
                raise ValueError(f"albedo tiles must be a power of two in size, got {S}")
            self.planes.append(dict(
                axis=p.axis, coord=np.float32(p.coord), sign=p.sign, axes=p.axes,
                bounded=bool(np.isfinite(p.lo).all() and (scene.room is None or p.label == "table")),
                lo=p.lo.astype(np.float32), hi=p.hi.astype(np.float32),
                S=S, k=np.float32(S / p.albedo_period_m), albedo=p.albedo_tile.reshape(-1, 3),
                grid=(p.irradiance_grid / np.float32(np.pi)).astype(np.float32).reshape(-1, 3),
                edge=p.shadow_edge.reshape(-1) if p.shadow_edge is not None and p.shadow_edge.any() else None,
                strong=L.PointLights(scene.lights.positions[p.strong_lights], scene.lights.intensities[p.strong_lights])
                if p.strong_lights is not None and len(p.strong_lights) else None,
                gshape=p.irradiance_grid.shape[:2], glo=p.grid_lo.astype(np.float32),
                ginv=np.float32(1.0 / p.grid_cell_m),
            ))
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
            t = (p["coord"] - o[ax]) * inv[ax]
            ok = t > 0
            ok &= t < best_t
            if p["bounded"]:
                a, b = p["axes"]
                xa = o[a] + t * d[a]
                xb = o[b] + t * d[b]
                ok &= (xa >= p["lo"][0]) & (xa <= p["hi"][0]) & (xb >= p["lo"][1]) & (xb <= p["hi"][1])
            np.copyto(best_t, t, where=ok)
            np.copyto(best_i, np.int8(i), where=ok)
        res = (best_i, best_t, d, o)
        self._cache = (key, res)
        return res

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
        sigma = np.sqrt(np.maximum(x, 0) * (gain / FULL_WELL_E) + (READ_NOISE_E * gain / FULL_WELL_E) ** 2 + ADC_NOISE**2)
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
        return frame.with_result("synthetic_gt", {"frame": i, "T_cam_world": invert(T_wc)})

    def read(self) -> Frame | None:
        if self._i >= self.frames:
            return None
        f = self.render(self._i)
        self._i += 1
        return f


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
    disp = np.round((disp + np.float32(DISPARITY_NOISE_PX) * noise) / np.float32(DISPARITY_STEP_PX)) * np.float32(DISPARITY_STEP_PX)
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


def _parse_size(s: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in s.lower().split("x"))
    except ValueError:
        raise SyntheticError(f"synthetic size must be WIDTHxHEIGHT like 640x400, got {s!r}") from None
    if not (32 <= w <= 4096 and 32 <= h <= 4096):
        raise SyntheticError(f"synthetic size {s!r} out of range (32..4096 per side)")
    return w, h


_PARAMS = ("seed", "size", "width", "height", "frames", "path", "hdr", "table", "lights")


def open_url(url: str, config=None) -> SyntheticSource:
    """Create the synthetic source for ``synthetic://SCENE?...`` (see the module docstring)."""
    parts = urlsplit(url)
    if parts.scheme != "synthetic":
        raise SyntheticError(f"not a synthetic:// URL: {url!r}")
    kind = (parts.netloc or parts.path.strip("/")) or "indoor"
    q = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(q) - set(_PARAMS))
    if unknown:
        raise SyntheticError(f"{url!r}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(_PARAMS)}")

    def one(name, default):
        return q[name][-1] if name in q else default

    def integer(name, default, lo, hi):
        v = one(name, None)
        if v is None:
            return default
        try:
            iv = int(v)
        except ValueError:
            raise SyntheticError(f"{url!r}: {name} must be an integer, got {v!r}") from None
        if not lo <= iv <= hi:
            raise SyntheticError(f"{url!r}: {name} must be in [{lo}, {hi}], got {iv}")
        return iv

    seed = integer("seed", 0, 0, 2**31 - 1)
    frames = integer("frames", 60, 1, 10_000_000)
    n_lights = integer("lights", 32, 1, 1024)
    table = one("table", None)
    if table is not None and table not in ("0", "1"):
        raise SyntheticError(f"{url!r}: table must be 0 or 1, got {table!r}")
    hdr = one("hdr", None)
    if hdr is not None and kind != "outdoor":
        raise SyntheticError(f"{url!r}: hdr= applies to the outdoor scene only")
    if hdr is not None and not Path(hdr).is_file():
        raise SyntheticError(f"{url!r}: HDR map not found: {hdr}")
    size = one("size", None)
    if size is None and ("width" in q or "height" in q):  # width=640&height=400 spelling
        size = f"{one('width', '640')}x{one('height', '400')}"
    scene = build_scene(kind, seed, _parse_size(size or "640x400"), frames, one("path", "static"),
                        hdr or None, None if table is None else table == "1", n_lights)
    return SyntheticSource(scene, frames, url)
