"""The contracts between stages: the result types they exchange through ``Frame.results`` and the
declared keys (:class:`ResultKey`) those results live under.

Every key is declared once, here, and stages name them in their ``requires`` / ``optional`` /
``provides`` (see :mod:`illuminet.runtime.stage`); nothing else spells a results key as a string.
``docs/architecture.md`` shows the chain these keys wire together.

Units follow :mod:`illuminet.runtime.physics`: irradiance is scene-referred linear RGB, i.e. the
linear pixel value divided by ``exposure_scale``; multiplying back by it (and by albedo/pi)
re-encodes in the frame's exposure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from illuminet.runtime.sh import SH_A_HAT, sh9


@dataclass(frozen=True)
class Plane:
    """A planar region in camera coordinates: points x with ``normal . x + offset = 0``.

    ``normal`` is a unit vector pointing towards the camera side (``offset > 0``).
    ``label`` is one of ``"floor"``, ``"table"`` (horizontal, facing up), ``"wall"`` (vertical),
    ``"other"``, or ``"synthetic"`` (placed because no real plane was found).
    """

    id: int
    normal: np.ndarray
    offset: float
    centroid: np.ndarray
    area_m2: float
    label: str = "other"
    inlier_mask: np.ndarray | None = None  # HxW bool in the depth image, when available
    n_inliers: int = 0  # inliers in the downsampled cloud (see cloud_mask)
    extent_m: tuple[float, float] = (0.0, 0.0)  # size along ``axes`` (principal in-plane directions)
    axes: np.ndarray | None = None  # (2, 3) unit in-plane directions, largest extent first
    cloud_mask: np.ndarray | None = None  # inliers in the downsampled cloud (every cloud_stride-th pixel)
    cloud_stride: int = 1

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of camera-frame points (..., 3) to the plane (positive on the camera side)."""
        return np.asarray(points) @ self.normal + self.offset

    def intersect(self, ray: np.ndarray) -> np.ndarray | None:
        """Where the camera ray ``t * ray`` (t > 0) meets the plane, or ``None`` when it does not."""
        den = float(np.dot(self.normal, ray))
        if abs(den) < 1e-9:
            return None
        t = -self.offset / den
        return None if t <= 0 else t * np.asarray(ray, np.float64)


@dataclass(frozen=True)
class Anchor:
    """Where the virtual object stands.

    ``T_cam_obj`` maps object-frame points (origin on the plane, +Y along the plane normal) to camera
    coordinates: ``x_cam = R @ x_obj + t``.
    """

    T_cam_obj: np.ndarray  # 4x4
    plane_id: int
    synthetic: bool = False  # True when no plane was found and a synthetic one was placed

    @property
    def R(self) -> np.ndarray:
        return self.T_cam_obj[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.T_cam_obj[:3, 3]


@dataclass(frozen=True)
class PlaneLight:
    """Per-vertex illumination measured on one or more planes, in the object frame.

    Vertices of all planes are concatenated; ``plane_slices[i]`` selects plane i's vertices
    (``grid x grid`` each, row-major). The first plane is the anchor plane.

    Attributes
    ----------
    vertices, normals : (P, 3)
        Grid vertex positions and normals in the object frame, metres.
    irradiance : (P, 3)
        Scene-referred linear RGB irradiance E (= OI . n) at each vertex.
    mask : (P,) bool
        True where the cell was observed (not outside the image, occluded, or invalid depth).
    confidence : (P,) float in [0, 1]
        How much the value can be trusted (observation count, consistency over frames).
    exposure_scale : float
        Linear pixel = radiance * exposure_scale for this frame (absolute from metadata, or relative
        from the plane's statistics when the camera reports no exposure).
    observed : (P,) bool or None
        Cells measured in *this* frame (``mask`` also covers cells fused from earlier frames).
    exposure_source : str
        ``"metadata"`` (absolute, from :class:`~illuminet.runtime.frame.Exposure`) or ``"plane"``
        (relative, from the plane's own statistics).
    irradiance_raw : (P, 3) or None
        ``irradiance`` before the grid's smoothing (``[plane_light] smoothing_cells``): each cell's own
        fused value, texture edges and all.
    context_grid : int
        0, or C: the anchor plane also measured on a wider C x C grid (``[plane_light]
        context_extent_m``), for the light estimate's lamp search: a lamp's pool of light often lies
        half outside the grid above. Its fields, same layout and units as the grid's, unsmoothed:
    context_vertices : (C*C, 3) or None
    context_irradiance : (C*C, 3) or None
    context_mask : (C*C,) bool or None
    """

    vertices: np.ndarray
    normals: np.ndarray
    irradiance: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    grid: int
    exposure_scale: float
    plane_slices: tuple[slice, ...] = field(default_factory=tuple)
    labels: tuple[str, ...] = ()
    observed: np.ndarray | None = None
    exposure_source: str = "metadata"
    irradiance_raw: np.ndarray | None = None
    context_grid: int = 0
    context_vertices: np.ndarray | None = None
    context_irradiance: np.ndarray | None = None
    context_mask: np.ndarray | None = None


@dataclass(frozen=True)
class ObjectShading:
    """Predicted shading of the object's lighting proxy mesh.

    Attributes
    ----------
    irradiance : (V, 3)
        Scene-referred linear RGB irradiance per proxy vertex (the renderer carries it to the render
        mesh).
    oi : (V, 3, 3) or None
        OI per vertex (channel, xyz) in the object frame, when the predictor gives it.
    method : str
        What produced it, e.g. ``"model:int8"``, ``"sh"``, ``"ambient"``, ``"constant"``.
    dominant_dir : (3,) or None
        Unit direction *towards* the dominant light, object frame.
    dominant_share : float
        Share of the light that the dominant direction carries, in [0, 1] (drives shadow strength).
    render_irradiance : (R, 3) or None
        The same on every vertex of the render mesh, when the predictor shades it directly (PRT with
        the bundle's render-mesh transfer); the renderer then draws it instead of carrying
        ``irradiance``.
    """

    irradiance: np.ndarray
    method: str
    oi: np.ndarray | None = None
    dominant_dir: np.ndarray | None = None
    dominant_share: float = 0.0
    render_irradiance: np.ndarray | None = None

    def on_render_mesh(self, carry) -> np.ndarray:
        """Irradiance on the render mesh: ``render_irradiance`` when shaded there, else ``carry(irradiance)``."""
        return self.render_irradiance if self.render_irradiance is not None else carry(self.irradiance)


@dataclass(frozen=True)
class LightEstimate:
    """The room's lighting at the anchor: the product's central per-frame output.

    **Frame** (the anchor's object frame, gravity-aligned): origin on the supporting plane under the
    object, **+Y up** (against gravity, along the plane normal for a floor or table), X and Z
    horizontal (the object frame of :class:`Anchor`, right-handed), metres. ``T_cam_obj`` maps it to
    the camera.

    **Units**: scene-referred linear RGB (the linear pixel value divided by ``exposure_scale``, as
    :class:`PlaneLight`). ``sh9`` holds *irradiance* coefficients of the ambient light (everything but
    the primary light): ``E(n) = sh9_basis(n) @ sh9`` (:func:`illuminet.runtime.sh.sh9`, order
    ``[Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22]``). Radiance coefficients (what three.js's
    ``LightProbe`` and WebXR's ``sphericalHarmonicsCoefficients`` carry) are ``sh9 / A_hat`` per band:
    :meth:`radiance_sh9`.

    Attributes
    ----------
    sh9 : (9, 3)
        Ambient irradiance SH coefficients (object frame).
    primary_dir : (3,) or None
        Unit vector *towards* the primary light (object frame); None when no light dominates.
    primary_rgb : (3,)
        Irradiance the primary light gives a surface facing it at the anchor (RGB).
    primary_pos : (3,) or None
        The light's position (object frame, metres) for a near light whose falloff was observed.
    confidence : dict
        In [0, 1]: ``"ambient"``, ``"direction"``, ``"intensity"``, ``"colour"``, ``"position"``.
    observed : dict
        What the estimate saw: ``"planes"`` (count), ``"plane_labels"``, ``"shadow"`` (score or
        None), ``"env_coverage"`` (share of the sphere seen), ``"emitters"`` (count), ``"cues"`` (list
        of cue names that set the primary light).
    exposure_scale : float
        Linear pixel per unit of scene-referred radiance for the frame it was made on.
    method : str
        What produced it (e.g. ``"scene"``, ``"plane-sh"``).
    T_cam_obj : (4, 4) or None
        The anchor pose for that frame.
    """

    sh9: np.ndarray
    primary_dir: np.ndarray | None
    primary_rgb: np.ndarray
    primary_pos: np.ndarray | None = None
    confidence: dict = field(default_factory=dict)
    observed: dict = field(default_factory=dict)
    exposure_scale: float = 1.0
    method: str = ""
    T_cam_obj: np.ndarray | None = None

    def radiance_sh9(self) -> np.ndarray:
        """Ambient *radiance* SH (9, 3): the convention of three.js ``LightProbe`` / WebXR."""
        return np.asarray(self.sh9, np.float64) / SH_A_HAT[:, None]

    def total_sh9(self) -> np.ndarray:
        """Irradiance SH (9, 3) of ambient plus the primary light (the light as one SH environment)."""
        out = np.array(self.sh9, np.float64)
        if self.primary_dir is not None:
            basis = sh9(np.asarray(self.primary_dir, np.float64).reshape(1, 3))[0]
            out += (basis * SH_A_HAT)[:, None] * np.asarray(self.primary_rgb, np.float64)[None, :]
        return out

    def primary_share(self) -> float:
        """The primary light's share of the light: luminance of its irradiance over that plus the
        ambient's mean irradiance over all directions (in [0, 1]; drives the cast shadow's strength)."""
        luma = np.array([0.2126, 0.7152, 0.0722])
        p = float(np.asarray(self.primary_rgb) @ luma) if self.primary_dir is not None else 0.0
        amb = float(np.asarray(self.sh9)[0] @ luma) * 0.282095
        return float(np.clip(p / max(p + amb, 1e-12), 0.0, 1.0))


@dataclass(frozen=True)
class ResultKey:
    """A declared ``Frame.results`` key: its name, the type of its value, and what it holds.

    ``str(key)`` is the name, so ``frame.results[key.name]`` and ``frame.with_result(key, v)`` agree.
    """

    name: str
    type_name: str
    doc: str

    def __str__(self) -> str:
        return self.name


PLANES = ResultKey("planes", "tuple[Plane, ...]", "tracked planes, largest first")
ANCHOR = ResultKey("anchor", "Anchor", "where the object stands (a synthetic plane when none is found)")
ODOMETRY = ResultKey("odometry", "OdometryResult", "camera motion for the world-locked anchor")
PLANE_LIGHT = ResultKey("plane_light", "PlaneLight", "per-vertex irradiance measured on the planes")
LIGHT = ResultKey("light", "LightEstimate", "the room's lighting at the anchor: ambient SH + primary light")
SHADING = ResultKey("shading", "ObjectShading", "the object's per-vertex irradiance")
COMPOSITE = ResultKey("composite", "ndarray HxWx3 uint8", "the output picture (sinks fall back to the camera colour)")
SYNTHETIC_GT = ResultKey("synthetic_gt", "dict", "the synthetic camera's ground truth: frame index, T_cam_world")
REPLAY_POSITION = ResultKey(
    "replay_position",
    "tuple[int, int]",
    "a replay's (lap, frame index in the recording): a looped replay's camera is back at the recording's "
    "start when the lap changes",
)

#: every declared key, by name
RESULT_KEYS: dict[str, ResultKey] = {
    k.name: k for k in (PLANES, ANCHOR, ODOMETRY, PLANE_LIGHT, LIGHT, SHADING, COMPOSITE, SYNTHETIC_GT, REPLAY_POSITION)
}
