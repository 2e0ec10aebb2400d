"""The render stage: the object, lit by the predicted shading, composited into each frame.

What this module owns
---------------------
* :class:`RenderStage`: the pipeline stage. Reads ``results["anchor"]``, ``results["shading"]``
  and ``results["plane_light"]`` and writes ``results["composite"]`` (H x W x 3 uint8 RGB). It
  loads the object (:mod:`illuminet.runtime.render.mesh`), carries the shading to the render
  mesh's vertices, smooths the dominant light for the shadow and hands the drawing to the
  :class:`~illuminet.runtime.render.compositor.Compositor`.

Colour (see :mod:`illuminet.runtime.physics`): the object's linear pixel value is
``albedo * E / pi * exposure_scale`` with E the scene-referred irradiance and ``exposure_scale``
the plane light's (else the frame metadata's), so the object sits in the picture with the frame's
own exposure.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from illuminet.runtime.assets.bundle import BundleError, load_bundle
from illuminet.runtime.frame import Frame
from illuminet.runtime.render.compositor import Compositor
from illuminet.runtime.render.mesh import load_render_mesh, mesh_from_bundle
from illuminet.runtime.render.shadow import dominant_light
from illuminet.runtime.scene import ANCHOR, COMPOSITE, PLANE_LIGHT, SHADING, ObjectShading
from illuminet.runtime.stage import FrameError, Stage

log = logging.getLogger(__name__)


class RenderStage(Stage):
    """Pipeline stage: the object, lit by the predicted shading, composited into the frame.

    Reads ``results["anchor"]`` (:class:`~illuminet.runtime.scene.Anchor`), ``results["shading"]``
    (:class:`~illuminet.runtime.scene.ObjectShading`, irradiance per proxy vertex) and
    ``results["plane_light"]`` (for ``exposure_scale``); writes ``results["composite"]``, an
    H x W x 3 uint8 RGB picture. Frames without an anchor or shading pass through unchanged
    (``composite`` is the camera picture) and are counted.

    Parameters
    ----------
    config : Config
        Uses [render] (object_scale, shadow, shadow_map, shadow_softness, contact_shadow,
        occlusion, depth_tolerance_m, msaa, gl_backend, gl_api) and [model] bundle.
    mesh : RenderMesh, trimesh object or path, optional
        The object to draw. Default: the render mesh of the bundle ``[model] bundle``
        (:func:`illuminet.runtime.assets.bundle.load_bundle`).
    carry : callable, optional
        ``carry(values_on_proxy) -> values_on_render_mesh``. Default: the bundle's; the identity
        when the shading already has one value per render vertex.
    ctx : moderngl.Context, optional
        GL context; default the process-wide one (:func:`illuminet.runtime.render.gl.get_context`).
    response_lut : (256, 3) array, optional
        Camera response (code -> linear) to encode with; sRGB when None.
    """

    name = "render"
    requires = (ANCHOR, SHADING)
    optional = (PLANE_LIGHT,)
    provides = (COMPOSITE,)
    hold_last_good = False  # a composite belongs to its own frame: without one, sinks show the camera picture
    thread_bound = True  # the GL context is current on the thread that opened it: a pipelined loop keeps it there

    #: exponential smoothing of the dominant light direction and share: the shadow must not flicker
    #: when the per-frame prediction jitters (0 = none)
    LIGHT_SMOOTHING = 0.7

    def __init__(
        self,
        config,
        mesh: Any = None,
        carry: Callable[[np.ndarray], np.ndarray] | None = None,
        ctx=None,
        response_lut: np.ndarray | None = None,
    ):
        self.cfg = config
        self._mesh_src = mesh
        self._carry = carry
        self._ctx = ctx
        self._response_lut = response_lut
        self.comp: Compositor | None = None
        self._light: tuple[np.ndarray | None, float] = (None, 0.0)
        self._counts = {"drawn": 0, "passed_through": 0, "no_anchor": 0, "no_shading": 0}
        self._crop_px: list[int] = []

    def open(self) -> None:
        """Create (or take) the GL context, load the object and upload it to the GPU once."""
        from illuminet.runtime.render.gl import using

        r = self.cfg.render
        with using(self._ctx, r.gl_backend, r.gl_api) as ctx:
            self._open(ctx)

    def _open(self, ctx) -> None:
        r = self.cfg.render
        mesh_src, carry = self._mesh_src, self._carry
        if mesh_src is None:
            spec = self.cfg.model.bundle
            try:
                bundle = load_bundle(spec)
            except BundleError as e:
                if not str(spec).startswith("builtin:"):
                    raise
                # the shading stage falls back to a baseline in this case; draw the same built-in
                # object from its generator so the stream still shows it
                from illuminet.runtime.assets.objects import load_object

                log.warning("%s; drawing %s from its generator, without the bundle", e, spec)
                mesh_src = load_object(spec)
            else:
                mesh_src = mesh_from_bundle(bundle)
                if carry is None:
                    carry = bundle.carry
        mesh = load_render_mesh(mesh_src)
        if r.object_scale != 1.0:
            mesh = mesh.scaled(r.object_scale)
        self._carry = carry
        self.comp = Compositor(
            ctx,
            mesh,
            msaa=r.msaa,
            shadow=r.shadow,
            shadow_map=r.shadow_map,
            occlusion=r.occlusion,
            depth_tolerance_m=r.depth_tolerance_m,
            shadow_softness=r.shadow_softness,
            contact_shadow=r.contact_shadow,
            response_lut=self._response_lut,
            antialias=r.antialias,
        )
        from illuminet.runtime.render.gl import renderer_name

        log.info(
            "render: %s, %d vertices, %d faces, antialias %s%s, GL %s",
            mesh.source,
            mesh.n_vertices,
            len(mesh.faces),
            self.comp.antialias,
            f" x{self.comp.msaa}" if self.comp.msaa else "",
            renderer_name(ctx),
        )

    def close(self) -> None:
        """Free the GPU objects (the shared context stays); safe to call twice."""
        from illuminet.runtime.render.gl import using

        if self.comp is not None:
            self._fb_final = (self.comp.framebuffer_size, self.comp.grows)  # stats() after close (reports)
            with using(self.comp.ctx):
                self.comp.release()
            self.comp = None

    def render_irradiance(self, shading: ObjectShading) -> np.ndarray:
        """The shading's irradiance carried to the render mesh's vertices, (N, 3) float32."""
        irr = np.asarray(shading.irradiance, dtype=np.float32)
        n = self.comp.mesh.n_vertices
        if irr.ndim != 2 or irr.shape[1] != 3:
            raise FrameError(f"shading irradiance must be (V, 3), got {irr.shape} (method {shading.method})")
        full = shading.render_irradiance
        if full is not None and np.shape(full) == (n, 3):  # shaded on the render mesh itself (PRT)
            out = np.asarray(full, dtype=np.float32)
        elif irr.shape[0] == 1:  # one value for the whole object (e.g. the ambient baseline without a bundle)
            out = np.repeat(irr, n, axis=0)
        elif self._carry is not None:
            out = np.asarray(self._carry(irr), dtype=np.float32)
        elif irr.shape[0] == n:
            out = irr
        else:
            raise FrameError(
                f"shading has {irr.shape[0]} vertices, the render mesh {n}, and no carry function maps "
                f"one to the other (give RenderStage a bundle or carry=)"
            )
        if out.shape != (n, 3):
            raise FrameError(f"carry returned shape {out.shape}, expected ({n}, 3)")
        return out

    def process(self, frame: Frame) -> Frame:
        from illuminet.runtime.render.gl import using

        if self.comp is None:
            raise RuntimeError("RenderStage.process called before open()")
        with using(self.comp.ctx):
            return self._process(frame)

    def _process(self, frame: Frame) -> Frame:
        anchor, shading = self.require(frame, ANCHOR), self.require(frame, SHADING)
        irr = self.render_irradiance(shading)
        scale = _exposure_scale(frame)
        d, share = dominant_light(shading, self.comp.mesh.normals, irr)
        d, share = self._smooth_light(d, share)
        intr = frame.intrinsics
        w, h = frame.size
        if (intr.width, intr.height) != (w, h):
            intr = intr.scaled(w, h)
        T = np.asarray(anchor.T_cam_obj, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise FrameError(f"anchor T_cam_obj must be a finite 4x4 matrix, got {T.shape}")
        out = self.comp.draw(frame.color, frame.depth, intr.K, T, irr, scale, d, share)
        self._counts["drawn"] += 1
        self._crop_px.append(self.comp.info.crop[2] * self.comp.info.crop[3])
        if len(self._crop_px) > 10000:
            del self._crop_px[:5000]
        return frame.with_result(COMPOSITE, out)

    def _smooth_light(self, d: np.ndarray | None, share: float) -> tuple[np.ndarray | None, float]:
        prev_d, prev_s = self._light
        a = self.LIGHT_SMOOTHING
        if d is not None and prev_d is not None:
            m = a * prev_d + (1.0 - a) * d
            nm = np.linalg.norm(m)
            d = m / nm if nm > 1e-9 else d
            share = a * prev_s + (1.0 - a) * share
        self._light = (d, share)
        return d, share

    def stats(self) -> dict[str, Any]:
        s: dict[str, Any] = dict(self._counts)
        if self.comp is not None:
            s["antialias"] = self.comp.antialias + (f"x{self.comp.msaa}" if self.comp.msaa else "")
            s["shadow_redraws"] = self.comp.shadow.redraws if self.comp.shadow is not None else 0
        fb = (
            (self.comp.framebuffer_size, self.comp.grows) if self.comp is not None else getattr(self, "_fb_final", None)
        )
        if fb is not None:
            (fw, fh), grows = fb
            s["framebuffer"] = f"{fw}x{fh}, grown {grows}x"
        if self._crop_px:
            s["crop_px_median"] = int(np.median(self._crop_px))
        d, share = self._light
        if d is not None:  # the (smoothed) dominant light of the last frame, object frame
            s["light_dir"] = [round(float(x), 2) for x in d]
            s["light_share"] = round(float(share), 2)
        return s


def _exposure_scale(frame: Frame) -> float:
    """Linear pixel per unit radiance for this frame: the plane light's, else the metadata's, else 1."""
    pl = frame.results.get(PLANE_LIGHT.name)
    if pl is not None and getattr(pl, "exposure_scale", None) is not None:
        return float(pl.exposure_scale)
    s = frame.exposure.scale
    return float(s) if s is not None else 1.0
