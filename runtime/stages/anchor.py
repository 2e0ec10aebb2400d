"""Where the virtual object stands: the ``AnchorStage`` and the object frame on a plane.

What this module owns
    * Choosing the anchor plane and point, by ``[anchor] mode``:

      ``auto``   the largest horizontal plane (``floor``/``table`` label) under the image centre
                 (a quarter of the cloud samples within ~12 pixels are its inliers), else the
                 largest horizontal plane; the point is where the central ray meets it, or (when
                 the centre is not on it) the ray through its inlier pixel nearest the image
                 centre. The choice is sticky: the same plane ID is kept while it is tracked.
      ``pixel``  the colour-image pixel ``[anchor] pixel``: its ray hits the plane under it (the
                 plane whose inliers contain it, else the nearest plane the ray meets).
      ``point``  the 3D camera-frame point ``[anchor] point`` projected onto the nearest plane.

    * The object frame (:func:`object_frame`): origin on the plane, +Y = plane normal (up), +Z =
      the direction from the origin towards the camera projected onto the plane, X = Y x Z
      (right-handed). It depends only on the plane and the origin, so with a steady camera the
      object does not spin from frame to frame. When the camera looks straight down the plane
      (the projection is shorter than 10 % of the distance) the camera's image-down axis projected
      onto the plane is used instead.
    * The synthetic plane (after the paper): when no plane is usable, a floor 1.2 m below the camera
      along gravity (or along the camera's +y when there is no gravity), with the origin 1.5 m in
      front of the camera (the optical axis projected on that floor); ``Anchor.synthetic`` is True,
      ``plane_id`` is -1 and :meth:`AnchorStage.stats` counts these frames.
    * The lock, by ``[anchor] lock``:

      ``world``  (default) the anchor is chosen once (by ``mode``, on the first frame with a
                 usable plane), stored in world coordinates, and carried by the camera odometry
                 (:class:`~illuminet.runtime.stages.odometry.Odometry`) every frame: ``T_cam_obj =
                 T_cam_world @ T_world_obj``. It is then re-snapped onto the tracked anchor plane
                 (origin projected along the plane normal, +Y = the tracked normal, +Z = the
                 carried +Z projected onto the plane), so it never floats or sinks, and its yaw
                 stays fixed in the world. The anchor plane's tracked normal and offset also pin
                 roll, pitch and height in the odometry. When the plane is not seen the carried
                 pose is used as is; when tracking is lost the last pose is held (the object stays
                 where it was relative to the camera, on the plane when the plane is seen) and
                 tracking restarts from there. Until the first real plane is found, the synthetic
                 plane is used camera-relative as in ``camera`` mode. :meth:`AnchorStage.reanchor`
                 asks for a new placement on the next frame. ``results["odometry"]``
                 (:class:`~illuminet.runtime.stages.odometry.OdometryResult`) is written every frame.
      ``camera`` the anchor is chosen again every frame in camera coordinates (sticky plane
                 choice, smoothed origin): the object follows the camera (no odometry).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from illuminet.runtime.config import Config
from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import ANCHOR, ODOMETRY, PLANES, REPLAY_POSITION, Anchor, Plane
from illuminet.runtime.stage import LogOnce, Stage
from illuminet.runtime.stages.odometry import Odometry, invert

log = logging.getLogger(__name__)

#: Synthetic floor: this far below the camera, origin this far in front (metres).
SYNTHETIC_HEIGHT_M = 1.2
SYNTHETIC_DISTANCE_M = 1.5
#: Plane ID of the synthetic plane.
SYNTHETIC_ID = -1
HORIZONTAL = ("floor", "table")
#: ``mode = "pixel"`` off a floor or table: where the pixel's ray meets the floor farther than this
#: fraction behind the depth the pixel shows, the floor there is hidden (behind a wall)
SUPPORT_BEHIND = 0.05
#: ... and where it meets the floor farther than this (metres) from the floor seen nearest to the pixel,
#: the object would stand on a part of the plane nobody saw (the table top's plane extended across the
#: room): it stands at that nearest seen point instead
SUPPORT_GAP_M = 0.15
LOCKS = ("world", "camera")
#: World lock: a tracked plane is taken as the anchor plane when its normal is within this angle of
#: the carried object's up axis and the carried origin is this close to it (when its ID changed).
MATCH_DEG = 10.0
MATCH_M = 0.08
#: World lock on a looped replay: camera poses kept from the first lap, per position in the recording
#: (its first frames: a lap's first frame may be dropped at recorded timing), and how far (frames) from
#: a kept position a new lap's first frame may start and still take that pose.
LAP_POSES = 64
LAP_NEAR = 5


def object_frame(normal: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """4x4 ``T_cam_obj`` for an object standing at ``origin`` on a plane with ``normal`` (camera frame).

    +Y is the normal, +Z points from the origin towards the camera within the plane, X = Y x Z.
    """
    y = np.asarray(normal, np.float64)
    y = y / np.linalg.norm(y)
    o = np.asarray(origin, np.float64)
    v = -o  # towards the camera
    zp = v - (v @ y) * y
    if np.linalg.norm(zp) < 0.1 * max(np.linalg.norm(v), 1e-9):
        # camera looks (almost) straight down the normal: use its image-down axis on the plane
        cam_down = np.array([0.0, 1.0, 0.0])
        zp = cam_down - (cam_down @ y) * y
        if np.linalg.norm(zp) < 1e-6:
            cam_fwd = np.array([0.0, 0.0, -1.0])
            zp = cam_fwd - (cam_fwd @ y) * y
    z = zp / np.linalg.norm(zp)
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, o
    return T


def snap_to_plane(T_cam_obj: np.ndarray, plane: Plane) -> np.ndarray:
    """``T_cam_obj`` moved onto ``plane``: origin projected along the normal, +Y = the normal, +Z = the
    old +Z projected onto the plane (so the yaw is kept), X = Y x Z."""
    y = np.asarray(plane.normal, np.float64)
    y = y / np.linalg.norm(y)
    o = T_cam_obj[:3, 3] - float(plane.distance(T_cam_obj[:3, 3])) * y
    z = T_cam_obj[:3, 2] - (T_cam_obj[:3, 2] @ y) * y
    if np.linalg.norm(z) < 1e-6:  # the carried frame lies on its side: fall back to facing the camera
        return object_frame(y, o)
    z /= np.linalg.norm(z)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = np.cross(y, z), y, z, o
    return T


def plane_to_world(normal: np.ndarray, offset: float, T_cam_world: np.ndarray) -> tuple[np.ndarray, float]:
    """A camera-frame plane ``n . x + d = 0`` in world coordinates (``x_cam = R x_world + t``)."""
    n = np.asarray(normal, np.float64)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    return R.T @ n, float(offset + n @ t)


def synthetic_plane(gravity: np.ndarray | None) -> tuple[Plane, np.ndarray]:
    """The synthetic floor and the anchor origin on it (module docstring)."""
    g = None
    if gravity is not None:
        g = np.asarray(gravity, np.float64)
        ng = np.linalg.norm(g)
        g = g / ng if np.isfinite(ng) and ng > 1e-6 else None
    if g is None:
        g = np.array([0.0, 1.0, 0.0])  # camera assumed level: gravity along image-down
    up = -g
    fwd = np.array([0.0, 0.0, 1.0])
    fwd_h = fwd - (fwd @ up) * up
    if np.linalg.norm(fwd_h) < 1e-6:  # camera looks straight down: take its image-up axis
        fwd_h = np.array([0.0, -1.0, 0.0]) - (np.array([0.0, -1.0, 0.0]) @ up) * up
    fwd_h /= np.linalg.norm(fwd_h)
    origin = SYNTHETIC_HEIGHT_M * g + SYNTHETIC_DISTANCE_M * fwd_h
    plane = Plane(
        id=SYNTHETIC_ID, normal=up, offset=SYNTHETIC_HEIGHT_M, centroid=origin.copy(), area_m2=0.0, label="synthetic"
    )
    return plane, origin


def _pixel_ray(frame: Frame, u: float, v: float) -> np.ndarray:
    intr = frame.intrinsics
    w, h = frame.size
    if (intr.width, intr.height) != (w, h):
        intr = intr.scaled(w, h)
    return np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])


def _covers(p: Plane, u: float, v: float, radius: int = 3, min_fraction: float = 0.25) -> bool:
    """Whether plane ``p`` lies under pixel (u, v): at least ``min_fraction`` of the cloud samples within
    ``radius`` samples around it are its inliers.

    A neighbourhood, not the single pixel: one hole or one noisy sample at the pixel must not move
    the anchor (the origin would then jump to the nearest inlier and back from frame to frame).
    """
    m, s = p.cloud_mask, max(1, p.cloud_stride)
    if m is None and p.inlier_mask is not None:
        m, s = p.inlier_mask[::4, ::4], 4
    if m is None:
        return False
    i, j = int(round(v / s)), int(round(u / s))
    if not (0 <= i < m.shape[0] and 0 <= j < m.shape[1]):
        return False
    win = m[max(0, i - radius) : i + radius + 1, max(0, j - radius) : j + radius + 1]
    return win.size > 0 and float(win.mean()) >= min_fraction


def _measured_depth(frame: Frame, u: float, v: float, radius: int = 2) -> float | None:
    """Median of the valid depth (metres) around colour pixel (u, v), or None (no depth there)."""
    d = frame.depth
    if d is None:
        return None
    w, h = frame.size
    dh, dw = d.shape[:2]
    i, j = int(round(v * dh / max(h, 1))), int(round(u * dw / max(w, 1)))
    win = np.asarray(d[max(0, i - radius) : i + radius + 1, max(0, j - radius) : j + radius + 1], np.float64)
    if d.dtype == np.uint16:
        win = win * 0.001
    win = win[np.isfinite(win) & (win > 0)]
    return float(np.median(win)) if win.size else None


def _nearest_inlier_pixel(p: Plane, u: float, v: float) -> tuple[float, float] | None:
    """The inlier pixel of ``p`` nearest to (u, v), using the low-resolution cloud mask."""
    m, s = p.cloud_mask, max(1, p.cloud_stride)
    if m is None and p.inlier_mask is not None:
        m, s = p.inlier_mask[::8, ::8], 8
    if m is None:
        return None
    ii, jj = np.nonzero(m)
    if ii.size == 0:
        return None
    k = int(np.argmin((jj * s - u) ** 2 + (ii * s - v) ** 2))
    return float(jj[k] * s), float(ii[k] * s)


class AnchorStage(Stage):
    """Chooses where the object stands; writes ``results["anchor"]`` (:class:`Anchor`).

    Reads ``results["planes"]`` (from :class:`~illuminet.runtime.stages.planes.PlaneStage`).

    ``[anchor] lock = "world"`` (default): the object is placed once and carried by the camera
    odometry (module docstring); ``results["odometry"]``
    (:class:`~illuminet.runtime.stages.odometry.OdometryResult`) is written as well, and :meth:`stats`
    has ``placements``, ``carried_frames`` and the odometry's own stats (``state``, ``lost_frames``,
    ``resets``, ``inliers``). ``lock = "camera"``: the anchor is chosen every frame and its origin
    is smoothed over frames with ``[planes] smoothing`` (jumps over 10 cm are taken at once).
    """

    #: how the warnings name ``mode = "pixel"``'s pixel: the configuration key, unless the caller gave the
    #: pixel another way (relight: its anchor argument, ``--anchor`` / ``anchor_px``)
    pixel_name = "[anchor] pixel"

    name = "anchor"
    requires = (PLANES,)
    optional = (REPLAY_POSITION,)
    provides = (ANCHOR,)  # + ODOMETRY with [anchor] lock = "world" (set in __init__)
    JUMP_M = 0.10

    def __init__(self, cfg: Config):
        a = cfg.anchor
        if a.mode not in ("auto", "pixel", "point"):
            raise ValueError(f"[anchor] mode: expected one of auto, pixel, point, got {a.mode!r}")
        self.mode = a.mode
        self.pixel = (float(a.pixel[0]), float(a.pixel[1]))
        self.point = np.array(a.point, np.float64)
        self.smoothing = float(cfg.planes.smoothing)
        self._warn = LogOnce(log, "anchor")
        self._plane_id: int | None = None
        self._origin: np.ndarray | None = None
        self.frames = 0
        self.synthetic_frames = 0
        self.state = "none"  # "plane" or "synthetic" ("carried" in world lock when the plane is not seen)
        self.plane: Plane | None = None  # the anchor plane of the last frame (synthetic one included)
        lock = getattr(a, "lock", "world")
        if lock not in LOCKS:
            raise ValueError(f"[anchor] lock: expected one of {', '.join(LOCKS)}, got {lock!r}")
        self.lock = lock
        self.odometry: Odometry | None = Odometry(still_px=float(a.still_px)) if lock == "world" else None
        self.provides = (ANCHOR, ODOMETRY) if self.odometry is not None else (ANCHOR,)
        self._T_world_obj: np.ndarray | None = None  # world lock: the placed object
        self._plane_world: tuple[np.ndarray, float] | None = None  # world lock: its plane, world frame
        self.placements = 0
        self.carried_frames = 0
        self._lap: int | None = None  # looped replay: the lap of the last frame, and the first lap seen
        self._first_lap: int | None = None
        self._lap_poses: dict[int, np.ndarray] = {}  # first lap: position in the recording -> T_cam_world
        self.lap_restarts = 0

    # -- choosing the plane and the point
    def _choose(self, frame: Frame, planes: tuple[Plane, ...]) -> tuple[Plane, np.ndarray] | None:
        if not planes:
            return None
        w, h = frame.size
        if self.mode == "point":
            p = min(planes, key=lambda q: abs(q.distance(self.point)))
            return p, self.point - p.distance(self.point) * p.normal
        if self.mode == "pixel":
            u, v = self.pixel
            if not (0 <= u < w and 0 <= v < h):
                self._warn(
                    "pixel_outside",
                    f"{self.pixel_name} = [{u:g}, {v:g}] is outside the {w}x{h} image; using the image centre",
                )
                u, v = (w - 1) / 2.0, (h - 1) / 2.0
            ray = _pixel_ray(frame, u, v)
            under = [p for p in planes if _covers(p, u, v)]
            support = [p for p in under if p.label in HORIZONTAL]
            if not support:
                stand = self._support_near(frame, planes, under, u, v, ray)
                if stand is not None:
                    return stand
            hits = [(p, x) for p in (support or under or planes) if (x := p.intersect(ray)) is not None]
            if not hits:
                return None
            return min(hits, key=lambda px: px[1][2])
        # auto
        horiz = [p for p in planes if p.label in HORIZONTAL]
        if not horiz:
            return None
        u, v = (w - 1) / 2.0, (h - 1) / 2.0
        prev = [p for p in horiz if p.id == self._plane_id]
        if prev:
            p = prev[0]
        else:
            centre = [p for p in horiz if _covers(p, u, v)]
            p = max(centre or horiz, key=lambda q: q.area_m2)
        if not _covers(p, u, v):
            near = _nearest_inlier_pixel(p, u, v)
            if near is not None:
                u, v = near
        x = p.intersect(_pixel_ray(frame, u, v))
        if x is None:
            x = np.asarray(p.centroid, np.float64) - p.distance(p.centroid) * p.normal
        return p, x

    def _support_near(
        self, frame: Frame, planes: tuple[Plane, ...], under: list[Plane], u: float, v: float, ray: np.ndarray
    ) -> tuple[Plane, np.ndarray] | None:
        """``mode = "pixel"`` on a pixel that no floor or table covers: the floor or table nearest to it
        in the picture, where the pixel's ray meets it when that point continues the plane seen nearest
        to the pixel (a gap of bad depth), else (the point lies behind the surface the pixel shows, a
        wall, or far from any of the plane that was seen) at the plane's inlier pixel nearest to it.
        The object stands; a wall, a slope, or a phantom plane fitted to noisy depth (a stereo camera's
        left border band on the real OAK-D recordings: a vase on its side) cannot hold it. None when
        no floor or table is tracked (the pixel's own plane is used, as before)."""
        horiz = [p for p in planes if p.label in HORIZONTAL]
        near = [(p, q) for p in horiz if (q := _nearest_inlier_pixel(p, u, v)) is not None]
        if not near:
            return None
        p, q = min(near, key=lambda pq: (pq[1][0] - u) ** 2 + (pq[1][1] - v) ** 2)
        edge = p.intersect(_pixel_ray(frame, *q))
        if edge is None:
            return None
        x = p.intersect(ray)
        seen = _measured_depth(frame, u, v)
        if (
            x is None
            or np.linalg.norm(x - edge) > SUPPORT_GAP_M
            or (seen is not None and x[2] > seen * (1.0 + SUPPORT_BEHIND))
        ):
            x, where = edge, f"at its inlier pixel nearest to it ({q[0]:g}, {q[1]:g})"
        else:
            where = "under the pixel"
        labels = "/".join(sorted({q.label for q in under}))
        on = f"a plane labelled {labels}" if labels else "no tracked plane"
        self._warn(
            "pixel_not_support",
            f"{self.pixel_name} = [{u:g}, {v:g}] lies on {on}, not on a floor or table: the object stands "
            f"on the {p.label} (plane {p.id}) {where}; point the pixel at a floor or table to choose the place",
        )
        return p, x

    def reanchor(self) -> None:
        """World lock: place the object again (by ``[anchor] mode``) on the next frame."""
        self._T_world_obj = None
        self._plane_world = None
        self._plane_id = None

    def process(self, frame: Frame) -> Frame:
        self.frames += 1
        planes = self.require(frame, PLANES)
        if self.odometry is not None:
            return self._process_world(frame, tuple(planes))
        return self._process_camera(frame, tuple(planes))

    def _synthetic(self, frame: Frame) -> tuple[Plane, np.ndarray]:
        plane, origin = synthetic_plane(frame.gravity)
        self.synthetic_frames += 1
        if self.state != "synthetic":
            log.info(
                "anchor: no usable %s plane; using a synthetic floor %.1f m below the camera",
                "horizontal" if self.mode == "auto" else "",
                SYNTHETIC_HEIGHT_M,
            )
        self.state = "synthetic"
        return plane, origin

    def _process_world(self, frame: Frame, planes: tuple[Plane, ...]) -> Frame:
        """World lock (module docstring): place once, then carry by odometry and re-snap onto the plane."""
        tracked = [p for p in planes if p.id == self._plane_id] if self._T_world_obj is not None else []
        plane_cam = (tracked[0].normal, tracked[0].offset) if tracked and self._plane_world is not None else None
        rp = frame.results.get(REPLAY_POSITION.name)
        if rp is not None:
            self._new_lap(int(rp[0]), int(rp[1]))
        odo = self.odometry.update(frame, plane_cam, self._plane_world if plane_cam is not None else None)
        if rp is not None and self._lap == self._first_lap and 0 <= rp[1] < LAP_POSES:
            self._lap_poses.setdefault(int(rp[1]), odo.T_cam_world.copy())
        T_cw = odo.T_cam_world
        if self._T_world_obj is None:
            chosen = self._choose(frame, planes)
            if chosen is None:
                plane, origin = self._synthetic(frame)
                self.plane = plane
                anchor = Anchor(T_cam_obj=object_frame(plane.normal, origin), plane_id=plane.id, synthetic=True)
                return frame.with_result(ANCHOR, anchor).with_result(ODOMETRY, odo)
            plane, origin = chosen
            T_cam_obj = object_frame(plane.normal, origin)
            self._T_world_obj = invert(T_cw) @ T_cam_obj
            self._plane_world = plane_to_world(plane.normal, plane.offset, T_cw)
            self.placements += 1
            log.info(
                "anchor: placed on plane %d (%s) at %s m (camera frame), locked to the world",
                plane.id,
                plane.label,
                np.array2string(origin, precision=2),
            )
        else:
            T_pred = T_cw @ self._T_world_obj
            plane = tracked[0] if tracked else self._match(planes, T_pred)
            if plane is None:
                # the plane is not seen: keep the carried pose (it is on the plane up to the odometry drift)
                self.carried_frames += 1
                self.state = "carried"
                anchor = Anchor(T_cam_obj=T_pred, plane_id=self._plane_id if self._plane_id is not None else -1)
                return frame.with_result(ANCHOR, anchor).with_result(ODOMETRY, odo)
            if plane.id != self._plane_id:
                # the tracker gave the plane a new ID: take its world parameters from the current pose
                self._plane_world = plane_to_world(plane.normal, plane.offset, T_cw)
            T_cam_obj = snap_to_plane(T_pred, plane)
        self._plane_id = plane.id
        self.state = "plane"
        self.plane = plane
        anchor = Anchor(T_cam_obj=T_cam_obj, plane_id=plane.id, synthetic=False)
        return frame.with_result(ANCHOR, anchor).with_result(ODOMETRY, odo)

    def _new_lap(self, lap: int, pos: int) -> None:
        """A looped replay starting its recording again: the camera is back where the first lap saw it
        at this position, so tracking restarts from that pose. Tracking across the jump instead (the
        recording's end to its start) left ~1 mm of drift per lap, which a replay looped for an hour
        adds up to metres: the object slid across the room."""
        if self._lap is None:
            self._lap = self._first_lap = lap
            return
        if lap == self._lap:
            return
        self._lap = lap
        near = [k for k in self._lap_poses if abs(k - pos) <= LAP_NEAR]
        if not near:
            return  # the first lap kept no pose near here: track across the jump as with a camera
        k = min(near, key=lambda k: abs(k - pos))
        self.odometry.reset(pose=self._lap_poses[k])
        self.lap_restarts += 1
        log.debug("anchor: replay lap %d: tracking restarts from the first lap's pose at frame %d", lap, k)

    def _match(self, planes: tuple[Plane, ...], T_pred: np.ndarray) -> Plane | None:
        """The tracked plane the carried object stands on: normal near its up axis, origin near the plane."""
        up, o = T_pred[:3, 1], T_pred[:3, 3]
        best, best_d = None, MATCH_M
        for p in planes:
            if float(np.dot(p.normal, up)) < np.cos(np.radians(MATCH_DEG)):
                continue
            d = abs(float(p.distance(o)))
            if d < best_d:
                best, best_d = p, d
        return best

    def _process_camera(self, frame: Frame, planes: tuple[Plane, ...]) -> Frame:
        """Camera lock: choose the anchor again every frame, in camera coordinates."""
        chosen = self._choose(frame, planes)
        if chosen is None:
            plane, origin = self._synthetic(frame)
            self._plane_id = None
            self._origin = None
            synthetic = True
        else:
            plane, origin = chosen
            if (
                plane.id != self._plane_id
                or self._origin is None
                or np.linalg.norm(origin - self._origin) > self.JUMP_M
            ):
                self._origin = origin
            else:
                o = self.smoothing * self._origin + (1.0 - self.smoothing) * origin
                self._origin = o - plane.distance(o) * plane.normal  # keep it on the plane
            origin = self._origin
            self._plane_id = plane.id
            self.state = "plane"
            synthetic = False
        self.plane = plane
        anchor = Anchor(T_cam_obj=object_frame(plane.normal, origin), plane_id=plane.id, synthetic=synthetic)
        return frame.with_result(ANCHOR, anchor)

    def stats(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "state": self.state,
            "synthetic_frames": self.synthetic_frames,
            "plane_id": self._plane_id if self._plane_id is not None else SYNTHETIC_ID,
            "lock": self.lock,
            "placements": self.placements,
            "carried_frames": self.carried_frames,
            "replay_lap_restarts": self.lap_restarts,
            "odometry": self.odometry.stats() if self.odometry is not None else None,
            "warnings": dict(self._warn.counts),
        }
