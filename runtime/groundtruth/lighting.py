"""Light transport from point lights, the random lighting environments, and HDR maps as point lights.

This module owns the *ground-truth lighting*: the :class:`PointLights` type, the per-vertex overall
illumination (OI) and irradiance they produce (the definition in :mod:`illuminet.runtime.physics`),
the paper's random 32-light environments (indoor, outdoor, spatially varying), and real HDR
environment maps turned into point lights by median cut (Debevec 2008).

Frames and units
    Environments live in the **object frame**: the object stands at the origin on the plane y = 0,
    +Y up, metres. Intensities are RGB radiant intensity (W/sr, linear Rec.709 primaries); a light
    of intensity I at distance r gives irradiance I cos(theta) / r^2. Irradiance is
    *scene-referred*: a Lambertian surface of albedo rho has radiance rho E / pi, and a camera
    records ``linear_pixel = radiance * exposure_scale`` (see ``Exposure.scale``).

Brightness ranges (chosen so the synthetic camera's auto exposure lands on realistic settings)
    indoor: horizontal irradiance at the object 3-30 units (ISO 100-1600, 1/30 s);
    outdoor: sunlit horizontal irradiance about 300-2500 units (short exposures, ISO 100).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Lights closer to a vertex than this (metres) are treated as at this distance (keeps 1/r^2 finite).
MIN_LIGHT_DISTANCE = 1e-3

#: Kinds accepted by :func:`sample_lights`.
ENVIRONMENT_KINDS = ("indoor", "outdoor", "spatial")

# Approximate linear-sRGB colour of blackbody / daylight sources at a colour temperature (K),
# normalised below to unit luminance. Coarse on purpose: what matters is warm lamps vs blue sky.
_CCT_TABLE = np.array(
    [
        [1900.0, 1.00, 0.42, 0.10],
        [2700.0, 1.00, 0.60, 0.30],
        [3500.0, 1.00, 0.73, 0.47],
        [4500.0, 1.00, 0.85, 0.70],
        [5500.0, 1.00, 0.94, 0.88],
        [6500.0, 1.00, 1.00, 1.00],
        [10000.0, 0.75, 0.85, 1.00],
        [15000.0, 0.60, 0.75, 1.00],
    ]
)
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def color_temperature_rgb(kelvin: float | np.ndarray) -> np.ndarray:
    """Linear RGB of a light of colour temperature ``kelvin`` (1900-15000 K), unit luminance.

    Returns
    -------
    (..., 3) array with ``rgb @ [0.2126, 0.7152, 0.0722] == 1``.
    """
    k = np.clip(np.asarray(kelvin, dtype=np.float64), _CCT_TABLE[0, 0], _CCT_TABLE[-1, 0])
    rgb = np.stack([np.interp(k, _CCT_TABLE[:, 0], _CCT_TABLE[:, c]) for c in (1, 2, 3)], axis=-1)
    return rgb / (rgb @ _LUMA)[..., None]


@dataclass(frozen=True)
class PointLights:
    """A set of isotropic point lights.

    Parameters
    ----------
    positions : (N, 3) float64
        Positions in metres (frame given by context: object frame for environments).
    intensities : (N, 3) float64
        RGB radiant intensity, W/sr, linear. Non-negative.
    """

    positions: np.ndarray
    intensities: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3) if np.size(self.positions) else np.zeros((0, 3))
        e = np.asarray(self.intensities, dtype=np.float64)
        if e.ndim == 1 and e.size == p.shape[0]:  # grey intensities
            e = np.repeat(e[:, None], 3, axis=1)
        e = e.reshape(-1, 3) if e.size else np.zeros((0, 3))
        if p.shape != e.shape:
            raise ValueError(f"PointLights: positions {p.shape} and intensities {e.shape} must both be (N, 3)")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(e))):
            raise ValueError("PointLights: positions and intensities must be finite")
        if np.any(e < 0):
            raise ValueError(f"PointLights: intensities must be >= 0, got min {e.min()}")
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "intensities", e)

    def __len__(self) -> int:
        return self.positions.shape[0]

    def transformed(self, R: np.ndarray, t: np.ndarray | None = None) -> PointLights:
        """The lights moved by a rigid transform: ``p' = R p + t`` (intensities unchanged)."""
        R = np.asarray(R, dtype=np.float64)
        t = np.zeros(3) if t is None else np.asarray(t, dtype=np.float64).reshape(3)
        return PointLights(self.positions @ R.T + t, self.intensities.copy())

    def translated(self, t: np.ndarray) -> PointLights:
        """The lights moved by ``t`` (metres)."""
        return self.transformed(np.eye(3), t)

    def scaled(self, k: float | np.ndarray) -> PointLights:
        """The lights with intensities multiplied by ``k`` (scalar or RGB)."""
        k = np.asarray(k, dtype=np.float64)
        return PointLights(self.positions.copy(), self.intensities * k)

    def total_power(self) -> np.ndarray:
        """Total radiant power per channel, W: 4 pi sum(I) for isotropic point lights."""
        return 4.0 * np.pi * self.intensities.sum(axis=0)

    def concatenated(self, other: PointLights) -> PointLights:
        """Both sets of lights together."""
        return PointLights(
            np.concatenate([self.positions, other.positions]),
            np.concatenate([self.intensities, other.intensities]),
        )

    def to_dict(self) -> dict:
        return {"positions": self.positions.tolist(), "intensities": self.intensities.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> PointLights:
        return cls(np.asarray(d["positions"], float), np.asarray(d["intensities"], float))


# ----------------------------------------------------------------------------------- transport


def _light_terms(points: np.ndarray, normals: np.ndarray, lights: PointLights, visibility):
    """Unit directions to the lights (V,N,3), per-light weight V_j/r_j^2 masked by n.w>0 (V,N), cos (V,N)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if points.shape != normals.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} must both be (V, 3)")
    d = lights.positions[None, :, :] - points[:, None, :]
    r2 = np.maximum(np.einsum("vnx,vnx->vn", d, d), MIN_LIGHT_DISTANCE**2)
    inv_r = 1.0 / np.sqrt(r2)
    w = d * inv_r[..., None]
    cos = np.einsum("vnx,vx->vn", w, normals)
    weight = np.where(cos > 0.0, 1.0 / r2, 0.0)
    if visibility is not None:
        vis = np.asarray(visibility, dtype=np.float64)
        if vis.shape != weight.shape:
            raise ValueError(f"visibility must be (V, N) = {weight.shape} (vertices x lights), got {vis.shape}")
        weight = weight * vis
    return w, weight, cos


def oi_point_lights(
    points: np.ndarray, normals: np.ndarray, lights: PointLights, visibility: np.ndarray | None = None
) -> np.ndarray:
    """Overall illumination per vertex from point lights (definition in :mod:`~illuminet.runtime.physics`).

    ``L_c(v) = sum_j e_jc V_j(v) w_j / r_j^2`` over lights with ``n . w_j > 0``.

    Parameters
    ----------
    points, normals : (V, 3)
        Vertex positions and unit normals, same frame as ``lights``.
    lights : PointLights
    visibility : (V, N) array in [0, 1], optional
        Fraction of light j reaching vertex v (self-shadowing); ``None`` = all visible.

    Returns
    -------
    (V, 3, 3) float64: vertex, colour channel, xyz.
    """
    w, weight, _ = _light_terms(points, normals, lights, visibility)
    return np.einsum("vn,nc,vnx->vcx", weight, lights.intensities, w)


def irradiance(
    points: np.ndarray, normals: np.ndarray, lights: PointLights, visibility: np.ndarray | None = None
) -> np.ndarray:
    """Per-channel irradiance E = OI . n at each vertex, (V, 3), scene-referred linear units."""
    _, weight, cos = _light_terms(points, normals, lights, visibility)
    return (weight * np.maximum(cos, 0.0)) @ lights.intensities


def diffuse_radiance(
    points: np.ndarray,
    normals: np.ndarray,
    lights: PointLights,
    albedo: float | np.ndarray = 1.0,
    visibility: np.ndarray | None = None,
) -> np.ndarray:
    """Radiance reflected by a Lambertian surface, ``albedo * E / pi``, (V, 3)."""
    return np.asarray(albedo) * irradiance(points, normals, lights, visibility) / np.pi


# --------------------------------------------------------------------------------- directions


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit directions (Fibonacci lattice), (n, 3) float64."""
    if n < 1:
        raise ValueError(f"fibonacci_sphere: n must be >= 1, got {n}")
    i = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


def rotation_y(deg: float) -> np.ndarray:
    """3x3 rotation about +Y by ``deg`` degrees (right-handed)."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def directional_lights(directions: np.ndarray, irradiances: np.ndarray, distance: float = 50.0) -> PointLights:
    """Distant lights as far point lights.

    A directional light that gives irradiance ``E`` on a surface facing it becomes a point light
    at ``distance * d`` with intensity ``E * distance^2`` (exact at the origin; the relative error
    at a point x is about 2|x|/distance).
    """
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = np.asarray(irradiances, dtype=np.float64).reshape(-1, 3)
    return PointLights(d * distance, e * distance**2)


def uniform_environment(radiance: float | np.ndarray, n: int = 2048, distance: float = 50.0) -> PointLights:
    """A uniform environment of ``radiance`` L (RGB) from all directions, as ``n`` far lights.

    Each of the n directions carries the solid angle 4 pi / n, so an unoccluded surface receives
    irradiance ~ pi L (exact as n grows).
    """
    L = np.broadcast_to(np.asarray(radiance, dtype=np.float64), (3,))
    d = fibonacci_sphere(n)
    return directional_lights(d, np.tile(L * 4.0 * np.pi / n, (n, 1)), distance)


# ------------------------------------------------------------------------ random environments


def _loguniform(rng: np.random.Generator, lo: float, hi: float, size=None):
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size))


def _normalise_horizontal(lights: PointLights, target: float, at: np.ndarray | None = None) -> PointLights:
    """Scale so that the luminance of the horizontal irradiance (mean over ``at``) equals ``target``."""
    at = np.zeros((1, 3)) if at is None else np.asarray(at, float).reshape(-1, 3)
    up = np.tile([0.0, 1.0, 0.0], (at.shape[0], 1))
    e = irradiance(at, up, lights).mean(axis=0) @ _LUMA
    return lights.scaled(target / max(e, 1e-12))


def _room(rng: np.random.Generator):
    """A room box around the origin: (lo, hi) corners; the origin is inside, away from walls."""
    size = np.array([rng.uniform(3.0, 7.0), rng.uniform(2.4, 3.2), rng.uniform(3.0, 7.0)])
    frac = rng.uniform(0.2, 0.8, size=2)
    lo = np.array([-frac[0] * size[0], 0.0, -frac[1] * size[2]])
    return lo, lo + size


def _keep_away(p: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """True for positions at least ``radius`` from every centre and above the floor."""
    d = np.linalg.norm(p[:, None, :] - centres[None, :, :], axis=2)
    return np.all(d >= radius, axis=1) & (p[:, 1] > 0.02)


def _indoor(rng: np.random.Generator, n: int, object_size: float) -> PointLights:
    return sample_indoor_scene(rng, n, object_size)[0]


def sample_indoor_scene(
    rng: np.random.Generator, n: int = 32, object_size: float = 0.25
) -> tuple[PointLights, np.ndarray, np.ndarray]:
    """The ``"indoor"`` environment of :func:`sample_lights` together with its room.

    Returns
    -------
    lights : PointLights, object frame
    room_lo, room_hi : (3,) corners of the room box (floor at y = 0), metres
    """
    lo, hi = _room(rng)
    pos = np.zeros((0, 3))
    kinds = np.zeros(0, dtype=int)
    while pos.shape[0] < n:
        m = n - pos.shape[0]
        kind = rng.choice(3, size=m, p=[0.5, 0.3, 0.2])  # 0 ceiling, 1 lamp, 2 window/bounce on a wall
        p = rng.uniform(lo, hi, size=(m, 3))
        p[kind == 0, 1] = hi[1] - rng.uniform(0.05, 0.3, size=(kind == 0).sum())
        p[kind == 1, 1] = rng.uniform(0.4, 1.8, size=(kind == 1).sum())
        wall = kind == 2
        if wall.any():
            axis = rng.choice([0, 2], size=wall.sum())
            side = rng.integers(0, 2, size=wall.sum())
            idx = np.flatnonzero(wall)
            # 30 cm in front of the wall: a window's or a lit wall's light, not a hot spot on it
            p[idx, axis] = np.where(side == 0, lo[axis] + 0.3, hi[axis] - 0.3)
            p[idx, 1] = rng.uniform(0.8, 2.2, size=wall.sum())
        ok = _keep_away(p, np.zeros((1, 3)), 2.0 * object_size)
        pos = np.concatenate([pos, p[ok]])
        kinds = np.concatenate([kinds, kind[ok]])
    cct = np.where(
        kinds == 0,
        rng.uniform(2700, 5000, n),
        np.where(kinds == 1, rng.uniform(2300, 3500, n), rng.uniform(5500, 9000, n)),
    )
    # two decades of strength: a few lights dominate, as in real rooms
    strength = _loguniform(rng, 0.01, 1.0, n)
    lights = PointLights(pos, color_temperature_rgb(cct) * strength[:, None])
    return _normalise_horizontal(lights, _loguniform(rng, 3.0, 30.0)), lo, hi


#: Distance of the sun and sky lights in the outdoor environment, metres (|x|/D error on a 1 m floor: <1 %).
OUTDOOR_DISTANCE = 200.0


def _outdoor(rng: np.random.Generator, n: int, object_size: float) -> PointLights:
    elev_sun = np.deg2rad(rng.uniform(8.0, 75.0))
    az_sun = rng.uniform(0.0, 2.0 * np.pi)
    sun_dir = np.array([np.cos(elev_sun) * np.sin(az_sun), np.sin(elev_sun), np.cos(elev_sun) * np.cos(az_sun)])
    e_sun = _loguniform(rng, 400.0, 2000.0)  # normal irradiance of the clear sun
    overcast = rng.random() < 0.25
    sun_rgb = color_temperature_rgb(np.interp(np.rad2deg(elev_sun), [8, 30, 75], [3500, 5000, 5800]))
    sun_e = sun_rgb * e_sun * (rng.uniform(0.0, 0.1) if overcast else 1.0)
    # sky: n-1 directions above the horizon, denser near the horizon and around the sun
    m = n - 1
    dirs = np.zeros((0, 3))
    while dirs.shape[0] < m:
        d = rng.normal(size=(4 * m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[np.arcsin(np.clip(d[:, 1], -1, 1)) > np.deg2rad(3.0)]
        dirs = np.concatenate([dirs, d])
    dirs = dirs[:m]
    circumsolar = np.exp(4.0 * (dirs @ sun_dir - 1.0))
    horizon = 1.0 + 1.5 * (1.0 - dirs[:, 1])
    radiance = horizon * (1.0 + (0.5 if overcast else 3.0) * circumsolar) * _loguniform(rng, 0.7, 1.4, m)
    sky_rgb = color_temperature_rgb(rng.uniform(5500, 7000, m) if overcast else rng.uniform(8000, 15000, m))
    sky_e = sky_rgb * radiance[:, None]
    # total sky irradiance on the horizontal: 10-25 % of the clear sun's (more share when overcast)
    sky_h = (sky_e * np.maximum(dirs[:, 1:2], 0)).sum(axis=0) @ _LUMA
    share = rng.uniform(0.1, 0.25)  # drawn with or without a sky: the same stream either way
    if m > 0:  # n = 1 is the sun alone: 0 / 0 warned "divide by zero" for an empty sky
        sky_e *= e_sun * share / sky_h
    return directional_lights(np.vstack([sun_dir, dirs]), np.vstack([sun_e, sky_e]), OUTDOOR_DISTANCE)


def sample_spatial_scene(
    rng: np.random.Generator, n: int = 32, n_positions: int | None = None, object_size: float = 0.25
) -> tuple[PointLights, np.ndarray]:
    """A spatially varying scene: local lights near several object positions on the floor.

    Distribution: a room as for indoor; ``n_positions`` (default 3-5) object positions on the floor
    (y = 0) inside a 2 m x 2 m area; 80 % of the lights are local (lamps, candles, screens):
    0.3-1.5 m horizontally from a random object position at height 0.1-1.5 m, warm to neutral;
    20 % are weak ceiling lights (5 % of the local strength scale) so shadowed sides are not black.
    Every light stays at least ``1.5 * object_size`` from every object position. Strengths span
    1.5 decades; the mean horizontal irradiance over the positions is 3-30 units.

    Returns
    -------
    lights : PointLights in the scene frame (floor y = 0, +Y up, metres)
    positions : (K, 3) float64 object positions on the floor
    """
    lights, obj, _, _ = sample_spatial_room(rng, n, n_positions, object_size)
    return lights, obj


def sample_spatial_room(
    rng: np.random.Generator, n: int = 32, n_positions: int | None = None, object_size: float = 0.25
) -> tuple[PointLights, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sample_spatial_scene` plus the room box: (lights, positions, room_lo, room_hi)."""
    k = int(rng.integers(3, 6)) if n_positions is None else int(n_positions)
    lo, hi = _room(rng)
    centre = np.array([rng.uniform(lo[0] + 1.2, hi[0] - 1.2), 0.0, rng.uniform(lo[2] + 1.2, hi[2] - 1.2)])
    obj = centre + np.column_stack([rng.uniform(-1, 1, k), np.zeros(k), rng.uniform(-1, 1, k)])
    pos = np.zeros((0, 3))
    local = np.zeros(0, bool)
    while pos.shape[0] < n:
        m = n - pos.shape[0]
        is_local = rng.random(m) < 0.8
        anchor = obj[rng.integers(0, k, m)]
        r = rng.uniform(0.3, 1.5, m)
        a = rng.uniform(0, 2 * np.pi, m)
        p = anchor + np.column_stack([r * np.cos(a), rng.uniform(0.1, 1.5, m), r * np.sin(a)])
        ceil = rng.uniform(lo, hi, size=(m, 3))
        ceil[:, 1] = hi[1] - rng.uniform(0.05, 0.3, m)
        p = np.where(is_local[:, None], p, ceil)
        ok = _keep_away(p, obj, 1.5 * object_size) & np.all((p >= lo) & (p <= hi), axis=1)
        pos = np.concatenate([pos, p[ok]])
        local = np.concatenate([local, is_local[ok]])
    cct = np.where(local, rng.uniform(2200, 4500, n), rng.uniform(3500, 5000, n))
    strength = _loguniform(rng, 0.03, 1.0, n) * np.where(local, 1.0, 0.05)
    lights = PointLights(pos, color_temperature_rgb(cct) * strength[:, None])
    return _normalise_horizontal(lights, _loguniform(rng, 3.0, 30.0), at=obj), obj, lo, hi


def sample_lights(kind: str, rng: np.random.Generator, n: int = 32, object_size: float = 0.25) -> PointLights:
    """``n`` random point lights in the object frame (object at the origin on y = 0, +Y up).

    Distributions (all documented in docs/lighting.md):

    ``"indoor"``
        A room 3-7 m x 3-7 m x 2.4-3.2 m high containing the object (not within 20 % of a wall).
        Each light is a ceiling fixture (50 %, 5-30 cm under the ceiling, 2700-5000 K), a lamp
        (30 %, 0.4-1.8 m high, 2300-3500 K) or window/bounce light on a wall (20 %, 0.8-2.2 m
        high, 5500-9000 K). Strengths are log-uniform over two decades (a few lights dominate);
        the whole set is scaled so that the horizontal irradiance at the object is 3-30 units.
    ``"outdoor"``
        One sun (elevation 8-75 deg, any azimuth, 3500-5800 K with elevation, normal irradiance
        400-2000 units; in 25 % of scenes overcast: the sun drops to 0-10 %) plus ``n - 1`` sky
        lights above 3 deg elevation, brighter near the horizon and around the sun, 8000-15000 K
        (5500-7000 K overcast), together 10-25 % of the clear sun's horizontal irradiance. All are
        far point lights at :data:`OUTDOOR_DISTANCE`.
    ``"spatial"``
        One object position of :func:`sample_spatial_scene`, lights expressed relative to it.

    Lights never come closer than ``2 * object_size`` (1.5x for spatial) to the object's origin
    and never lie below the floor.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"sample_lights: rng must be a numpy Generator, got {type(rng).__name__}")
    if n < 1:
        raise ValueError(f"sample_lights: n must be >= 1, got {n}")
    if kind == "indoor":
        return _indoor(rng, n, object_size)
    if kind == "outdoor":
        return _outdoor(rng, n, object_size)
    if kind == "spatial":
        lights, obj = sample_spatial_scene(rng, n, object_size=object_size)
        return lights.translated(-obj[rng.integers(0, obj.shape[0])])
    raise ValueError(f"sample_lights: kind must be one of {', '.join(ENVIRONMENT_KINDS)}, got {kind!r}")


# ------------------------------------------------------------------------------------ HDR maps


#: The largest environment map :func:`load_hdr` reads: 16384 x 8192 pixels (a "16k" map, the largest
#: commonly published; 1.6 GB as float32 RGB). Training resamples every map to 256 x 128, so a larger
#: one gains nothing; a header claiming more is refused before any pixel is allocated.
MAX_HDR_PIXELS = 16384 * 8192


def hdr_header_size(path: str | Path) -> tuple[int, int] | None:
    """(height, width) from a Radiance ``.hdr`` header, read without decoding the pixels.

    ``None`` when the file does not start with the Radiance magic ``#?`` (an OpenEXR file, say).

    Raises
    ------
    ValueError
        Naming the file when the header has no valid resolution line, claims more than
        :data:`MAX_HDR_PIXELS` pixels, or the file is too short to hold the pixels it claims.
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO named x.hdr: opening it waited for ever
        raise ValueError(f"{path}: not a regular file (a folder, pipe or device); expected a Radiance .hdr map")
    with open(path, "rb") as f:
        head = f.read(65536)
        size = f.seek(0, 2)
    if not head.startswith(b"#?"):
        return None
    want = "expected a Radiance .hdr map"
    end = head.find(b"\n\n")
    line_end = head.find(b"\n", end + 2) if end >= 0 else -1
    if line_end < 0:
        raise ValueError(f"{path}: cannot read as an HDR image (the header has no resolution line; {want})")
    parts = head[end + 2 : line_end].split()
    axes = [p.decode("latin-1") for p in parts[0::2]]
    if len(parts) != 4 or sorted(a[1:] for a in axes) != ["X", "Y"] or any(a[:1] not in "+-" for a in axes):
        line = head[end + 2 : line_end][:40]
        raise ValueError(f"{path}: cannot read as an HDR image (bad resolution line {line!r}; {want})")
    try:
        n = {a[1]: int(v) for a, v in zip(axes, parts[1::2])}
    except ValueError:
        raise ValueError(f"{path}: cannot read as an HDR image (bad resolution line; {want})") from None
    height, width = n["Y"], n["X"]
    if height < 1 or width < 1:
        raise ValueError(f"{path}: cannot read as an HDR image (its header claims {width} x {height} pixels)")
    if height * width > MAX_HDR_PIXELS:
        raise ValueError(
            f"{path}: its header claims {width} x {height} pixels, more than the {MAX_HDR_PIXELS} (16384 x 8192) "
            "an environment map may have; downscale it (training resamples every map to 256 x 128)"
        )
    # the fewest bytes the pixels can take: run-length scanlines (8 .. 32767 wide) need 4 bytes plus two
    # per run of up to 127 values in each of 4 channels; other widths are stored flat, 4 bytes a pixel
    least = height * (4 + 8 * -(-width // 127)) if 8 <= width <= 0x7FFF else 4 * width * height
    if size - (line_end + 1) < least:
        raise ValueError(
            f"{path}: cannot read as an HDR image (truncated: its header claims {width} x {height} pixels, "
            f"which take at least {least} bytes; the file holds {size - line_end - 1})"
        )
    return height, width


def load_hdr(path: str | Path) -> np.ndarray:
    """Read an HDR environment map (Radiance ``.hdr`` or ``.exr``) as float32 H x W x 3 linear RGB.

    A Radiance header's size is checked first (:func:`hdr_header_size`): a map over
    :data:`MAX_HDR_PIXELS` or shorter than its pixels is refused before anything is allocated.

    Raises
    ------
    FileNotFoundError, ValueError
        Naming the file when it is missing, unreadable, too large or not a 3-channel image.
    """
    import cv2  # runtime dependency, imported here so that pure light transport does not need it

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"HDR map not found: {path}")
    hdr_header_size(path)
    try:
        img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    except cv2.error as e:  # e.g. an .exr whose header claims more pixels than OpenCV reads
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise ValueError(f"{path}: cannot read as an HDR image (OpenCV: {msg})") from None
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{path}: cannot read as an HDR image (expected a Radiance .hdr or .exr with 3 channels)")
    if not np.issubdtype(img.dtype, np.floating):  # a PNG/JPEG: display values, not linear radiance
        bits = img.dtype.itemsize * 8
        raise ValueError(
            f"{path}: {'an' if bits == 8 else 'a'} {bits}-bit image, not an HDR map (its values are display "
            "levels, not linear radiance); expected a Radiance .hdr or .exr"
        )
    rgb = np.ascontiguousarray(img[..., ::-1], dtype=np.float32)
    if not np.all(np.isfinite(rgb)) or rgb.min() < 0:
        rgb = np.nan_to_num(np.maximum(rgb, 0), nan=0.0, posinf=0.0)
    return rgb


def equirect_directions(height: int, width: int) -> np.ndarray:
    """Unit direction of each pixel centre of an equirectangular map, (H, W, 3), object frame.

    Convention: row 0 is straight up (+Y); the centre column looks along -Z; columns to the
    right turn towards +X (as seen from inside the sphere). ``theta = pi (v + 0.5) / H`` from +Y,
    ``phi = pi (2 (u + 0.5) / W - 1)``, ``d = (sin theta sin phi, cos theta, -sin theta cos phi)``.
    """
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = np.pi * (2.0 * (np.arange(width) + 0.5) / width - 1.0)
    st = np.sin(theta)[:, None]
    return np.stack(
        [
            st * np.sin(phi)[None, :],
            np.broadcast_to(np.cos(theta)[:, None], (height, width)),
            -st * np.cos(phi)[None, :],
        ],
        axis=-1,
    )


def equirect_solid_angles(height: int, width: int) -> np.ndarray:
    """Solid angle of one pixel in each row of an equirectangular map, (H,) steradians (x W sums to 4 pi)."""
    t0 = np.pi * np.arange(height) / height
    t1 = np.pi * (np.arange(height) + 1) / height
    return (2.0 * np.pi / width) * (np.cos(t0) - np.cos(t1))


def median_cut(hdr: np.ndarray, n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Median cut (Debevec 2008): an equirectangular HDR map -> ``n`` directional lights.

    The map is weighted by each pixel's solid angle; regions are split in two of equal luminance
    energy along their longer side (width measured as width x sin(theta), as Debevec does), always
    splitting the region with the most energy next (for n a power of two this equals Debevec's
    k rounds of splitting every region). Each light sits at its region's energy centroid (a unit
    direction) and carries the region's whole integral ``sum L dOmega`` per channel.

    Parameters
    ----------
    hdr : (H, W, 3) linear RGB radiance
    n : number of lights

    Returns
    -------
    directions : (n, 3) unit vectors towards the light, object frame (+Y up; see
        :func:`equirect_directions`)
    rgb : (n, 3) per-region integral of radiance over solid angle, i.e. the irradiance it gives a
        surface facing it; ``rgb.sum(0)`` equals the map's integral exactly.
    """
    hdr = np.asarray(hdr, dtype=np.float64)
    if hdr.ndim != 3 or hdr.shape[2] != 3:
        raise ValueError(f"median_cut: expected an H x W x 3 map, got {hdr.shape}")
    H, W, _ = hdr.shape
    if n < 1 or n > H * W:
        raise ValueError(f"median_cut: n must be in [1, {H * W}], got {n}")
    domega = equirect_solid_angles(H, W)
    power = hdr * domega[:, None, None]  # radiance x solid angle per pixel
    lum = power @ _LUMA
    sat = np.zeros((H + 1, W + 1))
    sat[1:, 1:] = lum.cumsum(0).cumsum(1)
    sin_row = np.sin(np.pi * (np.arange(H) + 0.5) / H)

    def energy(y0, y1, x0, x1):
        return sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0]

    # max-heap on energy; ties broken by insertion order so the result is deterministic
    heap = [(-energy(0, H, 0, W), 0, (0, H, 0, W))]
    done = []
    count = 1
    while heap and len(heap) + len(done) < n:
        neg_e, _, (y0, y1, x0, x1) = heapq.heappop(heap)
        h, w = y1 - y0, x1 - x0
        if h * w <= 1:
            done.append((y0, y1, x0, x1))
            continue
        w_eff = w * sin_row[(y0 + y1 - 1) // 2]
        split_x = (w_eff > h and w > 1) or h == 1
        e_tot = -neg_e
        if split_x:
            cum = sat[y1, x0 + 1 : x1 + 1] - sat[y0, x0 + 1 : x1 + 1] - sat[y1, x0] + sat[y0, x0]
            k = int(np.searchsorted(cum[:-1], 0.5 * e_tot)) + 1 if e_tot > 0 else w // 2
            k = min(max(k, 1), w - 1)
            parts = [(y0, y1, x0, x0 + k), (y0, y1, x0 + k, x1)]
        else:
            cum = sat[y0 + 1 : y1 + 1, x1] - sat[y0 + 1 : y1 + 1, x0] - sat[y0, x1] + sat[y0, x0]
            k = int(np.searchsorted(cum[:-1], 0.5 * e_tot)) + 1 if e_tot > 0 else h // 2
            k = min(max(k, 1), h - 1)
            parts = [(y0, y0 + k, x0, x1), (y0 + k, y1, x0, x1)]
        for p in parts:
            heapq.heappush(heap, (-energy(*p), count, p))
            count += 1
    regions = done + [r for _, _, r in sorted(heap, key=lambda t: t[1])]
    dirs_img = equirect_directions(H, W)
    directions = np.zeros((len(regions), 3))
    rgb = np.zeros((len(regions), 3))
    for i, (y0, y1, x0, x1) in enumerate(regions):
        wgt = lum[y0:y1, x0:x1]
        dsub = dirs_img[y0:y1, x0:x1]
        c = np.einsum("hw,hwx->x", wgt, dsub)
        if np.linalg.norm(c) < 1e-12:  # black region: use its geometric centre
            c = dsub.reshape(-1, 3).mean(0)
            if np.linalg.norm(c) < 1e-12:
                c = dsub[0, 0]
        directions[i] = c / np.linalg.norm(c)
        rgb[i] = power[y0:y1, x0:x1].sum(axis=(0, 1))
    return directions, rgb


def hdr_integral(hdr: np.ndarray) -> np.ndarray:
    """Integral of the map's radiance over the sphere, ``sum L dOmega`` per channel, (3,)."""
    hdr = np.asarray(hdr, dtype=np.float64)
    return np.einsum("hwc,h->c", hdr, equirect_solid_angles(*hdr.shape[:2]))


def hdr_lights(
    hdr: np.ndarray,
    n: int = 32,
    rng: np.random.Generator | None = None,
    rotation_deg: float | None = None,
    exposure: float = 1.0,
    distance: float = 50.0,
) -> PointLights:
    """An HDR map as ``n`` point lights (median cut), optionally rotated about +Y and re-exposed.

    Parameters
    ----------
    hdr : (H, W, 3) linear radiance map (see :func:`load_hdr`)
    n : number of lights
    rng : when given and ``rotation_deg`` is None, a uniformly random yaw is drawn from it (the
        paper's random rotation of real maps)
    rotation_deg : yaw about +Y in degrees (overrides ``rng``)
    exposure : multiplies all intensities (the paper's random exposure; draw it yourself, e.g.
        ``2 ** rng.uniform(-1, 1)``)
    distance : the lights are far point lights at this distance (m); intensity = E d^2 so the
        irradiance at the object's origin equals the map's (see :func:`directional_lights`).
    """
    dirs, rgb = median_cut(hdr, n)
    yaw = rotation_deg if rotation_deg is not None else (rng.uniform(0.0, 360.0) if rng is not None else 0.0)
    dirs = dirs @ rotation_y(yaw).T
    return directional_lights(dirs, rgb * float(exposure), distance)
