"""Result types that stages exchange through ``Frame.results`` (the contracts between stages).

=================  ==========================  ====================================================
``results`` key    type                        written by
=================  ==========================  ====================================================
``"planes"``       ``tuple[Plane, ...]``       plane detection + tracking
``"anchor"``       :class:`Anchor`             anchor selection (a synthetic plane when none found)
``"odometry"``     ``OdometryResult``          camera motion (world-locked anchor, runtime/odometry.py)
``"plane_light"``  :class:`PlaneLight`         plane illumination (per-vertex plane OI)
``"shading"``      :class:`ObjectShading`      transfer (learned model) or a baseline
``"composite"``    ``np.ndarray`` HxWx3 uint8  renderer: the output picture (sinks fall back to
                                               ``frame.color`` when it is absent)
=================  ==========================  ====================================================

Units follow :mod:`illuminet.runtime.physics`: irradiance is scene-referred linear RGB, i.e. the
linear pixel value divided by ``exposure_scale``; multiplying back by it (and by albedo/pi)
re-encodes in the frame's exposure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
    """

    irradiance: np.ndarray
    method: str
    oi: np.ndarray | None = None
    dominant_dir: np.ndarray | None = None
    dominant_share: float = 0.0
