"""The synthetic scene: rooms, planes, occluders, lights and camera paths, and its ground truth
(see the package docstring)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from illuminet.hw.synthetic.textures import make_albedo_tile
from illuminet.runtime.errors import SourceURLError
from illuminet.runtime.frame import Intrinsics
from illuminet.runtime.groundtruth import lighting as L
from illuminet.runtime.scene import Plane
from illuminet.runtime.stages.odometry import invert

SCENES = ("indoor", "outdoor", "lamp", "spatial", "cluttered")
PATHS = ("static", "orbit", "look")
#: diffuse inter-reflections baked into a scene unless the URL says otherwise (``bounce=N``)
DEFAULT_BOUNCES = 8
MAX_BOUNCES = 16
#: the planes that enclose a room (closed box: the renderer need not test their bounds)
ROOM_LABELS = ("floor", "wall", "ceiling")

#: OAK-D-like colour intrinsics at 1280x800 (mono sensors' field of view: ~77 deg horizontal).
OAKD_INTRINSICS_1280 = Intrinsics(fx=800.0, fy=800.0, cx=639.5, cy=399.5, width=1280, height=800)


class SyntheticError(SourceURLError):
    """A ``synthetic://`` URL is invalid; the message names the parameter and what was expected."""


@dataclass
class SyntheticPlane:
    """An axis-aligned textured rectangle in the world frame (floor y = 0, +Y up, metres).

    Points with ``x[axis] == coord``; the lit (front) side faces ``normal`` (``sign`` along axis).
    ``lo``/``hi`` bound the two other axes (``axes``), ``inf`` for unbounded ground.
    """

    name: str
    label: str  # "floor", "wall", "ceiling", "table", "ground", "box" (a face of a clutter box)
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
    direct_grid: np.ndarray | None = None  # (nu, nv, 3) direct light alone when bounces were added
    lattice: object | None = None  # bounce.Lattice: radiosity patches (when bounces were baked)

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
        return (
            (p[..., a] >= self.lo[0])
            & (p[..., a] <= self.hi[0])
            & (p[..., b] >= self.lo[1])
            & (p[..., b] <= self.hi[1])
        )


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


@dataclass
class BoxOccluder:
    """A solid axis-aligned box (furniture, a crate) that blocks light: corners ``lo``, ``hi``."""

    lo: np.ndarray
    hi: np.ndarray

    def blocks(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether the segments p -> q pass through the box (slab test). p: (..., 3), q broadcastable."""
        p, q = np.broadcast_arrays(np.asarray(p, float), np.asarray(q, float))
        shape = p.shape[:-1]
        p, q = p.reshape(-1, 3), q.reshape(-1, 3)
        alive = np.arange(p.shape[0])
        t0 = np.zeros(p.shape[0])
        t1 = np.ones(p.shape[0])
        # one axis at a time, keeping only the segments still crossing every slab so far: most
        # segments miss a small box in the first horizontal slab already
        for ax in (0, 2, 1):
            pa = p[alive, ax]
            da = q[alive, ax] - pa
            da[da == 0] = 1e-30  # parallel: inside the slab for all t, or never
            a = (self.lo[ax] - pa) / da
            b = (self.hi[ax] - pa) / da
            lo_t = np.maximum(t0[alive], np.minimum(a, b))
            hi_t = np.minimum(t1[alive], np.maximum(a, b))
            keep = lo_t < hi_t
            alive = alive[keep]
            t0[alive], t1[alive] = lo_t[keep], hi_t[keep]
        out = np.zeros(p.shape[0], bool)
        out[alive] = True
        return out.reshape(shape)


def _room_planes(rng, lo, hi, floor_kind):
    mk = make_albedo_tile
    planes = [SyntheticPlane("floor", "floor", 1, lo[1], +1.0, (0, 2), lo[[0, 2]], hi[[0, 2]], *mk(floor_kind, rng))]
    paint = mk("paint", rng)
    for name, axis, side in (("wall_x0", 0, 0), ("wall_x1", 0, 1), ("wall_z0", 2, 0), ("wall_z1", 2, 1)):
        others = (1, 2) if axis == 0 else (0, 1)
        coord = lo[axis] if side == 0 else hi[axis]
        planes.append(
            SyntheticPlane(
                name,
                "wall",
                axis,
                coord,
                +1.0 if side == 0 else -1.0,
                others,
                lo[list(others)],
                hi[list(others)],
                *paint,
            )
        )
    planes.append(
        SyntheticPlane("ceiling", "ceiling", 1, hi[1], -1.0, (0, 2), lo[[0, 2]], hi[[0, 2]], *mk("ceiling", rng))
    )
    return planes


# --------------------------------------------------------------------------------------- scene


#: SyntheticPlane labels as runtime.scene.Plane labels (a box's top is a table, its sides walls)
_CAM_LABELS = {"ground": "floor", "ceiling": "other"}


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
    occluders: list  # Occluder | BoxOccluder
    object_positions: np.ndarray
    intrinsics: Intrinsics
    poses: Sequence[np.ndarray]  # T_world_cam per frame (a CameraPath, computed on demand)
    sky: _Sky | None = None
    room: tuple[np.ndarray, np.ndarray] | None = None
    hdr_path: str | None = None
    info: dict = field(default_factory=dict)
    bounces: int = 0  # diffuse inter-reflections baked by bake() (0 = direct light only)

    def bake(self, bounces: int = DEFAULT_BOUNCES) -> None:
        """Precompute the light on every plane: direct light on a fine grid, then ``bounces`` diffuse
        inter-reflections between the planes (:mod:`~illuminet.hw.synthetic.bounce`)."""
        from illuminet.hw.synthetic import bounce as B

        if not 0 <= int(bounces) <= MAX_BOUNCES:
            raise SyntheticError(f"bounces must be in [0, {MAX_BOUNCES}], got {bounces}")
        for p in self.planes:
            p.direct_grid, p.lattice = None, None
            _bake_irradiance(self, p, self.poses)
        B.bake(self, int(bounces))
        self.bounces = int(bounces)

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
            out.append(
                Plane(
                    id=i,
                    normal=n,
                    offset=off,
                    centroid=c,
                    area_m2=area,
                    label=_CAM_LABELS.get(p.label, p.label)
                    if p.label != "box"
                    else ("table" if p.axis == 1 else "wall"),
                )
            )
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

    def true_plane_irradiance(
        self, points_cam: np.ndarray, normal_cam: np.ndarray, frame: int = 0, indirect: bool = True
    ) -> np.ndarray:
        """Irradiance (P, 3) at camera-frame points with a camera-frame normal (one (3,) or (P, 3)).

        Direct light exactly, plus (``indirect`` and ``bounces > 0``) the baked inter-reflection: read
        from the plane's radiosity lattice for points on a plane facing along ``normal``, gathered
        over the hemisphere (:meth:`indirect_irradiance`) elsewhere.
        """
        pts = np.asarray(points_cam, float).reshape(-1, 3)
        nrm = np.broadcast_to(np.asarray(normal_cam, float).reshape(-1, 3), pts.shape)
        Tw = self.poses[frame % len(self.poses)]
        pw = pts @ Tw[:3, :3].T + Tw[:3, 3]
        e = L.irradiance(pts, nrm, self.lights_cam(frame), self.occlusion(pw))
        if indirect and self.bounces > 0:
            nw = nrm @ Tw[:3, :3].T
            which = self._plane_of(pw, normals_world=nw)
            for j in np.unique(which[which >= 0]):
                p, on = self.planes[j], which == j
                e[on] += p.lattice.sample(p.lattice.bounce, pw[on, p.axes[0]], pw[on, p.axes[1]])
            off = which < 0
            if off.any():
                e[off] += self.indirect_irradiance(pw[off], nw[off])
        return e

    def indirect_irradiance(
        self, points_world: np.ndarray, normals_world: np.ndarray, n_directions: int | None = None
    ) -> np.ndarray:
        """Irradiance (P, 3) that the planes' inter-reflected light gives world points with world
        normals (nothing blocks but the planes; bounces 1..``bounces``); zeros when ``bounces == 0``."""
        from illuminet.hw.synthetic import bounce as B
        from illuminet.runtime.groundtruth.hemisphere import HemisphereVisibility

        pts = np.asarray(points_world, float).reshape(-1, 3)
        if self.bounces == 0:
            return np.zeros((pts.shape[0], 3))
        hv = HemisphereVisibility(None, pts, normals_world, n_directions or B.OBJECT_DIRECTIONS, eps=B.EPS)
        return hv.irradiance(B.object_radiance(self, hv.origins(), hv.directions))

    def _plane_of(self, pw: np.ndarray, tol: float = 0.01, normals_world: np.ndarray | None = None) -> np.ndarray:
        """Index of the first plane within ``tol`` of each world point and inside its bounds (-1: none);
        with normals, only a plane whose front faces that way counts."""
        which = np.full(pw.shape[0], -1)
        for j, p in enumerate(self.planes):
            on = (which < 0) & (np.abs(pw[:, p.axis] - p.coord) <= tol) & p.contains(pw)
            if normals_world is not None:
                on &= normals_world @ p.normal > 0.99
            which[on] = j
        return which

    def albedo_at(self, points_cam: np.ndarray, frame: int = 0, tol: float = 0.01) -> np.ndarray:
        """True linear albedo (P, 3) at camera-frame points on the scene's planes; NaN off every plane.

        A point belongs to the first plane within ``tol`` metres of it and inside its bounds.
        """
        pts = np.asarray(points_cam, float).reshape(-1, 3)
        Tw = self.poses[frame % len(self.poses)]
        pw = pts @ Tw[:3, :3].T + Tw[:3, 3]
        out = np.full((pts.shape[0], 3), np.nan)
        which = self._plane_of(pw, tol)
        for j, p in enumerate(self.planes):
            on = which == j
            if not on.any():
                continue
            S = p.albedo_tile.shape[0]
            k = S / p.albedo_period_m
            a, b = p.axes
            ia = np.floor(pw[on, a] * k).astype(np.int64) % S
            ib = np.floor(pw[on, b] * k).astype(np.int64) % S
            out[on] = p.albedo_tile[ia, ib]
        return out

    def object_lights(self, T_cam_obj: np.ndarray, frame: int = 0) -> L.PointLights:
        """The scene lights in the object frame of an object at ``T_cam_obj`` (seen in ``frame``)."""
        T_obj_world = invert(self.poses[frame % len(self.poses)] @ np.asarray(T_cam_obj, float))
        return self.lights.transformed(T_obj_world[:3, :3], T_obj_world[:3, 3])

    def true_object_oi(
        self,
        mesh,
        T_cam_obj: np.ndarray,
        visibility: bool = True,
        frame: int = 0,
        points: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        indirect: bool = True,
    ) -> np.ndarray:
        """Ground-truth OI (V, 3, 3) in the object frame; see :meth:`true_object_shading`.

        The indirect light's share is its vector irradiance ``integral L(w) w dw`` (so that the OI's
        dot with the normal is still the irradiance)."""
        T_cam_obj = self.rest_on_support(mesh, T_cam_obj, frame)
        pts, nrm, lights, vis = self._object_terms(mesh, T_cam_obj, visibility, frame, points, normals)
        oi = L.oi_point_lights(pts, nrm, lights, vis)
        if indirect and self.bounces > 0:
            hv, rad = self._object_indirect(mesh, T_cam_obj, visibility, frame, pts, nrm)
            oi = oi + hv.vector_irradiance(rad)
        return oi

    def true_object_shading(
        self,
        mesh,
        T_cam_obj: np.ndarray,
        visibility: bool = True,
        frame: int = 0,
        points: np.ndarray | None = None,
        normals: np.ndarray | None = None,
        indirect: bool = True,
        object_albedo: float = 0.0,
    ) -> np.ndarray:
        """Ground-truth irradiance (V, 3) on the mesh's vertices, scene-referred linear RGB.

        Parameters
        ----------
        mesh : trimesh.Trimesh in the object frame (may be ``None`` with ``points``, ``normals`` and
            ``visibility=False``)
        T_cam_obj : 4x4 pose of the object in the camera frame of ``frame``
        visibility : include self-shadowing (exact ray casts) and occlusion by the scene
            (table, facade, ground, boxes); False = every light in front of a vertex counts
        frame : which frame's camera ``T_cam_obj`` refers to
        points, normals : evaluate here instead of the mesh's vertices / vertex normals
        indirect : add the light the planes inter-reflect (``bounces`` of them, baked with the scene;
            with ``visibility`` the object hides planes from itself and its shadow darkens the plane
            it stands on); False = direct light only
        object_albedo : grey albedo of the object itself (0 = black: it only blocks light). With
            ``visibility`` and a mesh, the light the object reflects onto itself is added, every
            bounce of it (:func:`~illuminet.hw.synthetic.bounce.object_gather`): a white vase's
            inside and the underside of its lip are lit by the vase too
        """
        T_cam_obj = self.rest_on_support(mesh, T_cam_obj, frame)
        pts, nrm, lights, vis = self._object_terms(mesh, T_cam_obj, visibility, frame, points, normals)
        e = L.irradiance(pts, nrm, lights, vis)
        if indirect and self.bounces > 0:
            hv, rad = self._object_indirect(mesh, T_cam_obj, visibility, frame, pts, nrm)
            e = e + hv.irradiance(rad)
        if object_albedo > 0 and visibility and mesh is not None:
            from illuminet.hw.synthetic import bounce as B

            # the room's light on every mesh vertex is the source the bounces start from
            on_mesh = B.on_mesh_vertices(mesh, pts, nrm)
            e_mesh = e if on_mesh else self.true_object_shading(mesh, T_cam_obj, frame=frame, indirect=indirect)
            e = e + B.object_light(mesh, pts, nrm, e_mesh, object_albedo, on_mesh=on_mesh)
        return e

    def rest_on_support(self, mesh, T_cam_obj: np.ndarray, frame: int = 0) -> np.ndarray:
        """``T_cam_obj`` lifted onto the plane the object stands on when its mesh sinks into it.

        A placement a fraction of a millimetre low (the tracked plane's noise; a tilt of 0.1 deg lowers
        the edge of a 10 cm base by 0.2 mm) put the base under the floor, where the down-facing
        vertices' rays started below the floor, left the room downwards and gathered the sky under it:
        the base of a vase on an outdoor scene went from 0 to ~300 units of irradiance, and the PRT
        oracle's MAE from 0.027 to 0.037-0.050, for 0.1 mm. A real object rests on the floor. The
        support is the up-facing plane within 2 cm of the object's origin that contains it (as for its
        cast shadow); an object above it, or on none, is left where it is."""
        if mesh is None:
            return T_cam_obj
        T_cw = self.poses[frame % len(self.poses)]
        T_wo = T_cw @ np.asarray(T_cam_obj, float)
        j = self.support_plane(T_wo[:3, 3])
        if j is None:
            return T_cam_obj
        coord = self.planes[j].coord
        low = float((np.asarray(mesh.vertices, float) @ T_wo[1, :3] + T_wo[1, 3]).min())
        if low >= coord - 1e-7:  # on it (up to float rounding of an object placed exactly on it) or above
            return T_cam_obj
        T_wo = T_wo.copy()
        T_wo[1, 3] += coord - low + 1e-6
        return invert(T_cw) @ T_wo

    def support_plane(self, origin_world: np.ndarray) -> int | None:
        """Index of the plane an object with its origin at ``origin_world`` stands on: the up-facing
        plane within 2 cm of it that contains it (None: it stands on none)."""
        o = np.asarray(origin_world, float)
        for j, p in enumerate(self.planes):
            if p.axis == 1 and p.sign > 0 and abs(p.coord - o[1]) < 0.02 and bool(p.contains(o[None])[0]):
                return j
        return None

    def _object_terms(self, mesh, T_cam_obj, visibility, frame, points, normals):
        from illuminet.runtime.groundtruth.visibility import exact_visibility

        pts = np.asarray(mesh.vertices if points is None else points, float)
        nrm = np.asarray(mesh.vertex_normals if normals is None else normals, float)
        lights = self.object_lights(T_cam_obj, frame)
        vis = None
        if visibility:
            T_wo = self.poses[frame % len(self.poses)] @ np.asarray(T_cam_obj, float)
            pw = pts @ T_wo[:3, :3].T + T_wo[:3, 3]
            vis = exact_visibility(mesh, pts, lights, normals=nrm).astype(float) * self.occlusion(pw)
        return pts, nrm, lights, vis

    def _object_indirect(self, mesh, T_cam_obj, visibility, frame, pts, nrm):
        """(HemisphereVisibility in the object frame, radiance (V, n, 3) arriving along its rays)."""
        from illuminet.hw.synthetic import bounce as B

        T_wo = self.poses[frame % len(self.poses)] @ np.asarray(T_cam_obj, float)
        hv = object_hemisphere(mesh if visibility else None, pts, nrm)
        R = T_wo[:3, :3]
        origins = hv.origins() @ R.T + T_wo[:3, 3]
        dirs = hv.directions @ R.T.astype(np.float32)
        shadow = B.support_shadow(self, mesh, T_wo) if visibility and mesh is not None else None
        return hv, B.object_radiance(self, origins, dirs, shadow)


_OBJECT_HEMISPHERES: dict = {}


def object_hemisphere(mesh, pts: np.ndarray, nrm: np.ndarray):
    """The :class:`~illuminet.runtime.groundtruth.hemisphere.HemisphereVisibility` (object frame) with
    which the ground truth gathers indirect light at ``pts``, cached per geometry (a few seconds of
    ray casts for a 9000-vertex mesh; the evaluation asks for the same mesh in every scene and uses
    it for the PRT oracle too). ``mesh=None``: nothing blocks."""
    from illuminet.hw.synthetic.bounce import EPS, OBJECT_DIRECTIONS
    from illuminet.runtime.groundtruth.hemisphere import HemisphereVisibility

    parts = [pts, nrm] + ([np.asarray(mesh.vertices), np.asarray(mesh.faces)] if mesh is not None else [])
    key = hash(tuple(np.ascontiguousarray(a).tobytes() for a in parts))
    hv = _OBJECT_HEMISPHERES.get(key)
    if hv is None:
        hv = HemisphereVisibility(mesh, pts, nrm, OBJECT_DIRECTIONS, eps=EPS)
        if len(_OBJECT_HEMISPHERES) >= 4:
            _OBJECT_HEMISPHERES.pop(next(iter(_OBJECT_HEMISPHERES)))
        _OBJECT_HEMISPHERES[key] = hv
    return hv


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
        if (
            np.all(eye[[0, 2]] > lo[[0, 2]] + margin)
            and np.all(eye[[0, 2]] < hi[[0, 2]] - margin)
            and eye[1] < hi[1] - 0.2
        ):
            break
    else:
        raise RuntimeError("could not place the camera inside the room")
    return CameraPath(eye, az, dist, h, target, n_frames, path, room)


class CameraPath(Sequence):
    """T_world_cam of every frame of a synthetic camera path, computed when asked for.

    A ``synthetic://...?frames=N`` stream may be allowed millions of frames; precomputing N 4x4
    poses would stall start-up and take gigabytes, so a pose is made from its index on demand
    (indexing and slicing work as on the list this replaces).
    """

    def __init__(self, eye, az, dist, h, target, n_frames, path, room):
        self.eye, self.az, self.dist, self.h = eye, az, dist, h
        self.target, self.path, self.room = target, path, room
        self.n = max(int(n_frames), 1)
        # look a little past the object so it sits in the lower half of the picture
        self._static = _look_at(eye, target + np.array([-0.35 * np.sin(az), 0.05, -0.35 * np.cos(az)]))

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self._pose(k) for k in range(*i.indices(self.n))]
        i = int(i)
        if i < 0:
            i += self.n
        if not 0 <= i < self.n:
            raise IndexError(f"frame {i} outside the path of {self.n} frames")
        return self._pose(i)

    def _pose(self, i: int) -> np.ndarray:
        if self.path == "static":
            return self._static.copy()
        if self.path == "look":
            return self._look(i)
        target, dist, h, room = self.target, self.dist, self.h, self.room
        ph = 2 * np.pi * i / self.n
        a = self.az + np.deg2rad(25.0) * np.sin(ph)
        e = target + np.array([dist * np.sin(a), h + 0.05 * np.sin(2 * ph), dist * np.cos(a)])
        if room is not None:
            e[[0, 2]] = np.clip(e[[0, 2]], room[0][[0, 2]] + 0.2, room[1][[0, 2]] - 0.2)
        return _look_at(e, target + np.array([-0.35 * np.sin(a), 0.05, -0.35 * np.cos(a)]))

    #: the ``look`` path's phases, as shares of the frames: at the object, raising the view to the
    #: horizon, one full turn in place, lowering it, at the object again
    LOOK_PHASES = (0.15, 0.1, 0.5, 0.1)

    def _look(self, i: int) -> np.ndarray:
        """A user looking around once: from the object up to the horizon, a full turn, back down."""
        t = (i + 0.5) / self.n
        a0, a1, a2, a3 = np.cumsum(self.LOOK_PHASES)

        def smooth(u):
            u = min(max(u, 0.0), 1.0)
            return u * u * (3 - 2 * u)

        fwd = self._static[:3, 2]  # the static view's forward axis in the world (T_world_cam's third column)
        pitch0 = float(np.arcsin(np.clip(fwd[1], -1, 1)))
        yaw0 = float(np.arctan2(fwd[0], fwd[2]))
        if t < a0 or t >= a3:
            return self._static.copy()
        if t < a1:
            pitch, yaw = pitch0 + (LOOK_PITCH - pitch0) * smooth((t - a0) / (a1 - a0)), yaw0
        elif t < a2:
            pitch, yaw = LOOK_PITCH, yaw0 + 2 * np.pi * smooth((t - a1) / (a2 - a1))
        else:
            pitch, yaw = LOOK_PITCH + (pitch0 - LOOK_PITCH) * smooth((t - a2) / (a3 - a2)), yaw0
        d = np.array([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)])
        return _look_at(self.eye, self.eye + d)


#: the ``look`` path's view during the turn: this far above the horizon (radians)
LOOK_PITCH = np.deg2rad(5.0)


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


def _cluttered_lights(rng, n_lights):
    """The indoor environment dimmed to 20-40 % plus one key light (a ceiling spot or a tall lamp
    1.6-2.4 m high, 0.8-2 m to the side) giving 10-40 units: boxes cast clear shadows on the floor."""
    ambient, lo, hi = L.sample_indoor_scene(rng, max(n_lights - 1, 1))
    ambient = ambient.scaled(rng.uniform(0.2, 0.4))
    for _ in range(100):
        r, a = rng.uniform(0.8, 2.0), rng.uniform(0, 2 * np.pi)
        pos = np.array([r * np.cos(a), min(rng.uniform(1.6, 2.4), hi[1] - 0.1), r * np.sin(a)])
        if np.all(pos[[0, 2]] > lo[[0, 2]] + 0.2) and np.all(pos[[0, 2]] < hi[[0, 2]] - 0.2):
            break
    key = L.PointLights(pos[None], L.color_temperature_rgb(rng.uniform(2700, 4500))[None])
    e0 = L.irradiance(np.zeros((1, 3)), np.array([[0, 1.0, 0]]), key)[0] @ L._LUMA
    return key.scaled(rng.uniform(10, 40) / e0).concatenated(ambient), lo, hi


def build_scene(
    kind: str,
    seed: int,
    size: tuple[int, int] = (640, 400),
    frames: int = 60,
    path: str = "static",
    hdr: str | None = None,
    table: bool | None = None,
    n_lights: int = 32,
    bounce: int = DEFAULT_BOUNCES,
    boxes: int | None = None,
    position: int = 0,
) -> SyntheticScene:
    """Create a synthetic scene (deterministic in ``seed``); see the module docstring for kinds.

    ``bounce`` diffuse inter-reflections are baked (0 = direct light only). ``boxes`` closed boxes stand
    on the floor around the object (:func:`_add_boxes`): real objects that cast shadows onto the floor
    and, from some lights, onto the object (default: 2-4 in ``cluttered``, none elsewhere). They come
    from their own random stream, so the rest of the scene is the same with and without them.
    ``position`` picks the object position the camera frames (``object_positions[position % count]``;
    only ``spatial`` has more than one): an AR user looks at where the object stands.
    """
    if kind not in SCENES:
        raise SyntheticError(f"synthetic scene must be one of {', '.join(SCENES)}, got {kind!r}")
    if path not in PATHS:
        raise SyntheticError(f"synthetic path must be one of {', '.join(PATHS)}, got {path!r}")
    rng = np.random.default_rng([seed, SCENES.index(kind)])
    intr = OAKD_INTRINSICS_1280.scaled(*size)
    positions = np.zeros((1, 3))
    room = None
    occluders: list = []
    sky = None
    use_table = False
    info: dict = {}
    if kind in ("indoor", "lamp", "spatial", "cluttered"):
        if kind == "indoor":
            lights, lo, hi = L.sample_indoor_scene(rng, n_lights)
        elif kind == "lamp":
            lights, lo, hi = _lamp_lights(rng)
        elif kind == "cluttered":
            lights, lo, hi = _cluttered_lights(rng, n_lights)
        else:
            lights, positions, lo, hi = L.sample_spatial_room(rng, n_lights)
        room = (lo, hi)
        planes = _room_planes(rng, lo, hi, rng.choice(["wood", "tiles", "carpet"]))
        use_table = (kind in ("indoor", "cluttered")) if table is None else bool(table)
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
            sky = _Sky(
                None,
                0.0,
                1.0,
                (base * [0.6, 0.8, 1.3]).astype(np.float32),
                (base * [1.3, 1.3, 1.2]).astype(np.float32),
                (base * 0.3).astype(np.float32),
            )
        ground = rng.choice(["concrete", "grass"])
        inf = np.array([np.inf, np.inf])
        planes = [SyntheticPlane("ground", "ground", 1, 0.0, +1.0, (0, 2), -inf, inf, *make_albedo_tile(ground, rng))]
        occluders.append(Occluder(1, 0.0))  # light from below the horizon cannot pass the ground
    poses = _camera_poses(rng, kind, positions[int(position) % len(positions)], frames, path, room)
    if room is not None and use_table:
        _add_table(rng, room, positions, poses, planes, occluders, info)
    box_rng = np.random.default_rng([seed, SCENES.index(kind), 17])  # the boxes' own stream
    n_boxes = (int(box_rng.integers(2, 5)) if kind == "cluttered" else 0) if boxes is None else int(boxes)
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
        planes.append(
            SyntheticPlane("facade", "wall", axis, coord, sign, others, lo2, hi2, *make_albedo_tile("brick", rng))
        )
        occluders.append(Occluder(axis, coord, others, lo2, hi2))
    if n_boxes > 0:
        _add_boxes(box_rng, n_boxes, intr, room, positions, poses, planes, occluders, info)
    scene = SyntheticScene(kind, seed, lights, planes, occluders, positions, intr, poses, sky, room, hdr, info)
    scene.bake(bounce)
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
    planes.append(
        SyntheticPlane("table", "table", 1, 0.72, +1.0, (0, 2), occ.lo, occ.hi, *make_albedo_tile("tabletop", rng))
    )
    occluders.append(occ)
    info["table_centre"] = c.tolist()


def _add_boxes(rng, n, intr, room, positions, poses, planes, occluders, info) -> None:
    """``n`` closed boxes standing on the floor (15-50 cm wide, 15-70 cm high), 0.5-1.8 m from the
    first object position, in view of the first camera, apart from each other and from the object,
    and never hiding an object from the camera along the path. Each box is five rectangles (top and
    four sides, facing out) that are drawn, and one :class:`BoxOccluder` that blocks light.
    ``info["boxes"]`` lists (lo, hi) corners;
    fewer than ``n`` when no place is found."""
    eyes = np.array([T[:3, 3] for T in poses[:: max(1, len(poses) // 8)]])
    targets = np.concatenate([positions + [0, 0.01, 0], positions + [0, 0.26, 0]])
    T_cw = invert(poses[0])
    kinds = ("paint", "tabletop", "wood", "concrete")
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(200 * n):
        if len(boxes) == n:
            break
        half = rng.uniform(0.075, 0.25, 2)
        h = rng.uniform(0.15, 0.7)
        r, a = rng.uniform(0.5, 1.8), rng.uniform(0, 2 * np.pi)
        c = positions[0, [0, 2]] + r * np.array([np.cos(a), np.sin(a)])
        lo, hi = np.array([c[0] - half[0], 0.0, c[1] - half[1]]), np.array([c[0] + half[0], h, c[1] + half[1]])
        if room is not None and (
            np.any(lo[[0, 2]] < room[0][[0, 2]] + 0.2) or np.any(hi[[0, 2]] > room[1][[0, 2]] - 0.2)
        ):
            continue
        # clear of the objects (30 cm) and of the other boxes (10 cm)
        if np.any(np.max(np.abs(c - positions[:, [0, 2]]) - half, axis=1) < 0.3):
            continue
        if any(np.all(lo[[0, 2]] < h2[[0, 2]] + 0.1) and np.all(hi[[0, 2]] > l2[[0, 2]] - 0.1) for l2, h2 in boxes):
            continue
        # in view of the first camera: its top centre projects inside the picture
        pc = T_cw[:3, :3] @ np.array([c[0], h, c[1]]) + T_cw[:3, 3]
        if pc[2] <= 0.4 or not (
            0 <= intr.fx * pc[0] / pc[2] + intr.cx < intr.width and 0 <= intr.fy * pc[1] / pc[2] + intr.cy < intr.height
        ):
            continue
        faces = _box_faces(lo, hi)
        if any(f.blocks(eyes[:, None, :], targets[None, :, :]).any() for f in faces):
            continue
        boxes.append((lo, hi))
        tile = make_albedo_tile(kinds[int(rng.integers(len(kinds)))], rng)
        for k, f in enumerate(faces):
            planes.append(
                SyntheticPlane(
                    f"box{len(boxes) - 1}_{k}",
                    "box",
                    f.axis,
                    f.coord,
                    -1.0 if k % 2 else 1.0,
                    f.axes,
                    f.lo,
                    f.hi,
                    *tile,
                )
            )
        occluders.append(BoxOccluder(lo, hi))  # one solid: a slab test instead of five faces
    info["boxes"] = [(lo.tolist(), hi.tolist()) for lo, hi in boxes]


def _box_faces(lo: np.ndarray, hi: np.ndarray) -> list[Occluder]:
    """The five faces of a box on the floor: top, then -x, +x, -z, +z sides (outward sign: +, -, +, -, +)."""
    return [
        Occluder(1, hi[1], (0, 2), lo[[0, 2]], hi[[0, 2]]),
        Occluder(0, lo[0], (1, 2), lo[[1, 2]], hi[[1, 2]]),
        Occluder(0, hi[0], (1, 2), lo[[1, 2]], hi[[1, 2]]),
        Occluder(2, lo[2], (0, 1), lo[[0, 1]], hi[[0, 1]]),
        Occluder(2, hi[2], (0, 1), lo[[0, 1]], hi[[0, 1]]),
    ]


def _bake_irradiance(scene: SyntheticScene, p: SyntheticPlane, poses) -> None:
    """Irradiance of plane ``p`` on a grid (1 cm, coarser for planes over 10 m; unbounded ground: 10 m
    around the camera path, beyond which it is clamped — the depth camera's range ends at 12 m)."""
    lo, hi = p.lo.copy(), p.hi.copy()
    if not np.all(np.isfinite(lo)):
        # unbounded ground: bake what the camera can see, up to the depth limit, around the path
        # the extent of the camera path: every pose of a short path, an even sample of a long one
        cams = np.array([T[:3, 3] for T in poses[:: max(1, len(poses) // 4096)]])
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
    big = cv2.remap(
        e.astype(np.float32),
        np.ascontiguousarray(mv),
        np.ascontiguousarray(mu),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
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
