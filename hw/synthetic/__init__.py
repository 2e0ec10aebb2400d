"""``synthetic://`` — a simulated RGB-D camera in a lit scene, with ground truth for evaluation.

URL
    ``synthetic://SCENE?seed=N&size=WxH&frames=N&path=static|orbit|look[&hdr=PATH][&table=0|1][&lights=N][&bounce=N][&boxes=N][&position=K]``
    (``width=W&height=H`` is accepted for ``size``)

    SCENE
        ``indoor``  a room (floor, four walls, ceiling; a table unless ``table=0``) lit by the
        random ``indoor`` environment of :mod:`illuminet.runtime.groundtruth.lighting`.
        ``outdoor`` a ground plane and a building facade behind the object, under a sun and sky
        (analytic, or the median cut of an HDR map when ``hdr=PATH`` is given; the sky seen in the
        picture is then the map itself). Normalised to 300-2500 units of horizontal irradiance.
        ``lamp``    a dim room plus one strong warm lamp 0.35-0.7 m from the object (near light:
        strong falloff over the floor).
        ``spatial`` a room lit by the spatially-varying environment; ``scene.object_positions``
        lists its 3-5 object positions, ``default_anchor(position=k)`` stands on one of them;
        ``position=K`` makes the camera frame ``object_positions[K % count]`` (default 0).
    seed      every random choice (room, lights, textures, camera, noise) follows from it
    size      ``640x400`` (default) or ``1280x800`` (OAK-D mono-like: fx = fy = 800 at 1280x800),
              other sizes scale the same intrinsics
    frames    frames before the end of the stream (default 60)
    path      ``static`` (default: a fixed camera, frames differ only by noise), ``orbit``
              (the camera swings +-25 deg around the object and bobs 5 cm, one period per run) or
              ``look`` (a user looking around once: 15 % of the frames at the object, the view raised
              to 5 deg above the horizon, one full turn in place over half the frames, lowered, back
              at the object; docs/eval.md has what the odometry and the estimate make of it)
    boxes     ``N`` boxes (0-12; default 2-4 in ``cluttered``, else 0) standing on the floor 0.5-1.8 m
              around the object, in view,
              never hiding it: real objects casting shadows (``scene.info["boxes"]`` lists them)

What a frame holds
    ``color``: the scene's radiance (Lambertian: ``albedo * E / pi``, E the direct light plus 8 bounces
    between the planes by default, ``bounce=N``; :mod:`~illuminet.hw.synthetic.bounce`), times the
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

from illuminet.hw.synthetic.scene import (
    OAKD_INTRINSICS_1280,
    PATHS,
    SCENES,
    SyntheticError,
    SyntheticScene,
    build_scene,
)
from illuminet.hw.synthetic.source import SyntheticSource, open_url
from illuminet.hw.synthetic.textures import make_albedo_tile

__all__ = [
    "PATHS",
    "SCENES",
    "OAKD_INTRINSICS_1280",
    "SyntheticError",
    "SyntheticScene",
    "SyntheticSource",
    "build_scene",
    "make_albedo_tile",
    "open_url",
]
