"""The Python API: ``illuminet.open`` (a stream of processed frames) and ``illuminet.relight`` (one image).

What this module owns: the entry points a Python program uses instead of the command line. They are
reached lazily as ``illuminet.open`` / ``illuminet.relight`` / ``illuminet.render_preview``
(``illuminet/__init__.py``), so ``import illuminet`` stays fast and imports no numpy, OpenCV or GL.

Example (README, "Use from Python")::

    import illuminet

    with illuminet.open("synthetic://lamp?frames=30", max_frames=30) as stream:
        for result in stream:
            est = result.estimate                    # LightEstimate (anchor frame) or None
            if est is not None:
                print(result.frame.seq, result.estimate_json()["primaryLightDirection"])
            picture = result.composite               # HxWx3 uint8 RGB with the object, or None
"""

from __future__ import annotations

import contextlib
import os
import threading
import weakref
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from illuminet.runtime.config import SCHEMA, Config, ConfigError, apply_overrides, defaults, load
from illuminet.runtime.errors import IllumiNetError
from illuminet.runtime.frame import Exposure, Frame, Intrinsics
from illuminet.runtime.scene import ANCHOR, COMPOSITE, LIGHT, SHADING

# --------------------------------------------------------------------------------------------------
# argument checks


def _shown(v: Any, limit: int = 60) -> str:
    """``repr(v)`` on one line, cut to ``limit`` characters (an array's repr can be megabytes)."""
    from illuminet.runtime.relight import _shown as shown

    return shown(v, limit)


def _described(v: Any) -> str:
    """What ``v`` is, for a message: an array's shape and dtype, else its type and (short) repr."""
    if isinstance(v, np.ndarray):
        return f"an array of shape {v.shape} {v.dtype}"
    return f"{type(v).__name__} {_shown(v)}"


def _flag(value: Any, name: str, optional: bool = False) -> bool | None:
    """A bool argument as given (``"no"`` or ``0`` is a mistake, not ``bool()``'s truth value)."""
    if optional and value is None:
        return None
    if not isinstance(value, (bool, np.bool_)):
        expected = "True, False or None" if optional else "True or False"
        raise ValueError(f"{name}: expected {expected}, got {_described(value)}")
    return bool(value)


def _check_pixels(shape: tuple[int, ...], what: str) -> None:
    """Refuse an image of more than :data:`MAX_IMAGE_PIXELS` from its shape alone, before any copy
    (a 20000x20000 ``np.broadcast_to`` view is 12 bytes; its copy 1.2 GB)."""
    from illuminet.runtime.relight import MAX_IMAGE_PIXELS

    h, w = int(shape[0]), int(shape[1])
    if h * w > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{what}: {w}x{h} pixels is over the limit of {MAX_IMAGE_PIXELS / 1e6:g} Mpx; expected an image "
            f"of at most that size: resize it first"
        )


def _as_array(value: Any, what: str, expected: str) -> np.ndarray:
    """``np.asarray(value)`` (no copy for an array), or one ValueError naming ``what`` for a value that is
    no array at all (None, a string, a number, a dict) or that numpy cannot make one of."""
    if value is None or isinstance(value, (str, bytes, dict, int, float, complex)):
        raise ValueError(f"{what}: {expected}, got {_described(value)}")
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what}: {expected}, got {type(value).__name__}: {e}") from None


def _color(color: Any, what: str = "color") -> np.ndarray:
    """``color`` as a contiguous HxWx3 uint8 array, its shape, dtype and size checked before any copy."""
    expected = "expected a non-empty HxWx3 uint8 RGB image (numpy array)"
    shape = getattr(color, "shape", None)
    if isinstance(shape, tuple) and len(shape) == 3 and all(isinstance(n, (int, np.integer)) for n in shape):
        _check_pixels(shape, what)  # an array-like (a tensor) that knows its shape: before converting it
    a = _as_array(color, what, expected)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or a.size == 0:
        raise ValueError(f"{what}: {expected}, got {a.shape} {a.dtype}")
    _check_pixels(a.shape, what)
    return np.ascontiguousarray(a)


# --------------------------------------------------------------------------------------------------
# configuration


def _config(
    config: Config | str | os.PathLike | None, overrides: dict[str, Any], who: str = "illuminet.open()"
) -> Config:
    """Built-in defaults (``None``), a config.toml path or a Config, plus keyword overrides.

    An override key is ``section__key`` (``light__rate_hz=5``), ``"section.key"`` (through ``**{...}``),
    or a bare key that names exactly one key of the schema (``max_frames=30``). ``who`` names the
    function in the messages.
    """
    if config is not None and not isinstance(config, (Config, str, os.PathLike)):
        raise ConfigError(
            f"{who}: config: expected a Config, a config.toml path or None, got {type(config).__name__} "
            f"{_shown(config)}"
        )
    cfg = defaults() if config is None else config if isinstance(config, Config) else load(config)
    items = []
    for name, value in overrides.items():
        if "__" in name or "." in name:
            section, _, key = name.replace("__", ".", 1).partition(".")
        else:
            owners = [sec for sec, keys in SCHEMA.items() if name in keys]
            if len(owners) != 1:
                where = (
                    f"it is in sections {', '.join(owners)}; write section__{name}=..."
                    if owners
                    else "no section has it; see config.toml" + _did_you_mean(name)
                )
                raise ConfigError(f"{who}: override {name}={value!r}: {where}")
            section, key = owners[0], name
        items.append((section, key, value))
    return apply_overrides(cfg, items)


def _did_you_mean(name: str) -> str:
    """`` (did you mean timing?)`` for a key close to ``name`` (`timng`), else ''."""
    import difflib

    close = difflib.get_close_matches(name, sorted({k for keys in SCHEMA.values() for k in keys}), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


# --------------------------------------------------------------------------------------------------
# illuminet.open


@dataclass(frozen=True)
class Result:
    """One processed frame.

    Attributes
    ----------
    frame : Frame
        The frame with every stage's results (``frame.results``).
    """

    frame: Frame

    @property
    def estimate(self):
        """The room's lighting (:class:`~illuminet.runtime.scene.LightEstimate`), or None before an anchor."""
        return self.frame.results.get(LIGHT.name)

    @property
    def composite(self) -> np.ndarray | None:
        """The picture with the object drawn in (HxWx3 uint8 RGB), or None (no renderer, or no object)."""
        return self.frame.results.get(COMPOSITE.name)

    @property
    def shading(self):
        """The object's per-vertex irradiance (:class:`~illuminet.runtime.scene.ObjectShading`), or None."""
        return self.frame.results.get(SHADING.name)

    @property
    def anchor(self):
        """Where the object stands (:class:`~illuminet.runtime.scene.Anchor`), or None."""
        return self.frame.results.get(ANCHOR.name)

    def estimate_json(self) -> dict[str, Any] | None:
        """The estimate as the JSON object of docs/estimate.md (three.js / WebXR shape), or None."""
        from illuminet.runtime.stream.estimate_json import frame_estimate

        return frame_estimate(self.frame)


class StreamClosed(IllumiNetError, RuntimeError):
    """A closed :class:`Stream` was opened, iterated or read again (it cannot be: open a new one)."""


class Stream:
    """An iterator of :class:`Result` over a source, through the configured pipeline (and sinks).

    Made by :func:`open`. Frames are pulled: each ``next()`` reads one frame from the source and runs
    the stages on it, in the calling thread (a live camera's own queue keeps only the newest frames
    while the program is busy). A stage that fails on a frame follows the pipeline's policy (the
    frame keeps that stage's last good result; counted in :attr:`failures`); ``strict=True`` raises.
    The outputs of ``[output]`` (``output__video=...``, ``output__mjpeg=True``, ``--estimates``'s
    ``output__estimates=...``) get every frame, as with ``illuminet run``.
    """

    def __init__(self, url: str, cfg: Config, *, render: bool = True, strict: bool | None = None):
        self.url, self.cfg, self.render = url, cfg, render
        self.strict = cfg.logging.strict if strict is None else bool(strict)
        self.frames = 0
        self.failures: dict[str, int] = {}
        self._stack: contextlib.ExitStack | None = None
        self._source = self._chain = None
        self._sinks: list = []
        # a frame in progress and close() exclude each other: close() from another thread (a stop
        # button) waits for the frame instead of closing the stages and sinks under it
        self._busy = threading.RLock()
        self._finalizer: weakref.finalize | None = None
        # closed (close(), the end of its `with`, or its source ended): reading it again raises
        # StreamClosed, except the one next() that ends a loop another thread's close() interrupted
        self._closed = False
        self._end_pending = False
        self._reader: int | None = None  # the thread that last called next()

    def _check_open(self) -> None:
        if self._closed:
            raise StreamClosed(
                f"this stream of {self.url} is closed (its source ended, or close() or the end of its `with` "
                f"block closed it) and cannot be read again; open a new one: illuminet.open({self.url!r}, ...)"
            )

    def open(self) -> Stream:
        """Open the source, the stages and the sinks (done by ``with`` or the first ``next``).
        :class:`StreamClosed` once the stream is closed."""
        self._check_open()
        if self._stack is not None:
            return self
        from illuminet.hw import open_source
        from illuminet.pipeline import build_sinks, build_stages
        from illuminet.runtime.stage import StageChain

        stack = contextlib.ExitStack()
        try:
            source = open_source(self.url, self.cfg)
            stages = build_stages(self.cfg, render=self.render)
            sinks = build_sinks(self.cfg, source_url=self.url)
            chain = StageChain(stages, strict=self.strict, source=source)  # checks the wiring first
            stack.enter_context(source)
            for st in stages:
                stack.enter_context(st)
            for sk in sinks:
                stack.enter_context(sk)
        except BaseException:
            stack.close()
            raise
        self._stack, self._source, self._chain, self._sinks = stack, source, chain, sinks
        # a stream dropped or left open without close() (a `for` without `with`, then a break) is
        # closed when it is garbage-collected or at the latest when the interpreter exits, as a
        # generator is: the outputs are finalised (a video's index) and the sinks' threads end
        self._finalizer = weakref.finalize(self, stack.close)
        return self

    def __enter__(self) -> Stream:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def __iter__(self) -> Iterator[Result]:
        self._check_open()
        return self

    def __next__(self) -> Result:
        self._reader = threading.get_ident()
        with self._busy:
            return self._next()

    def _next(self) -> Result:
        if self._end_pending:  # closed from another thread: the loop reading it ends
            self._end_pending = False
            raise StopIteration
        self._check_open()
        self.open()
        limit = self.cfg.source.max_frames
        frame = None if limit and self.frames >= limit else self._source.read()
        if frame is None:
            self.close()
            raise StopIteration
        frame, events = self._chain.run(frame)
        for ev in events:
            self.failures[ev.key] = self.failures.get(ev.key, 0) + 1
        for sk in self._sinks:
            sk.write(frame)
        self.frames += 1
        return Result(frame)

    def close(self) -> None:
        """Close sinks, stages and source (outputs are finalised). Idempotent; from another thread it
        waits for the frame in progress, and the iteration then ends. Opening, iterating or reading
        the stream after that raises :class:`StreamClosed`."""
        with self._busy:
            stack, self._stack = self._stack, None
            if stack is not None and self._reader not in (None, threading.get_ident()):
                self._end_pending = True
            self._closed = True
            if self._finalizer is not None:
                self._finalizer.detach()
                self._finalizer = None
            if stack is not None:
                stack.close()

    @property
    def stages(self) -> list:
        """The stages (opened), e.g. for their ``stats()``."""
        return list(self._chain.stages) if self._chain is not None else []


def open(
    url: str,
    /,
    config: Config | str | os.PathLike | None = None,
    *,
    render: bool = True,  # noqa: A001
    strict: bool | None = None,
    **overrides: Any,
) -> Stream:
    """Process frames from ``url`` through the pipeline; a context-managed iterator of :class:`Result`.

    Parameters
    ----------
    url : str
        A source URL, as for ``illuminet run``: ``oakd://``, ``v4l2:///dev/video0?stereo=sbs``,
        ``replay://SESSION``, ``synthetic://lamp``...
    config : Config, path or None
        The configuration: None = built-in defaults (not ./config.toml), a config.toml path, or a
        :class:`~illuminet.runtime.config.Config`.
    render : bool
        Draw the object (``result.composite``; needs OpenGL via EGL). False: lighting only, faster.
    strict : bool, optional
        Raise on the first failing stage (default ``[logging] strict``).
    **overrides
        Configuration keys: ``section__key=value`` (``light__rate_hz=5``), a bare key that is unique
        in the schema (``max_frames=30``, ``timing="asap"``), or ``**{"section.key": value}``.

    Returns
    -------
    Stream
        Use ``with illuminet.open(...) as stream: for result in stream: ...``.

    Raises
    ------
    ConfigError
        An unknown or ambiguous override, or a bad value (the message names it).
    ValueError
        ``url`` not a string, ``render`` / ``strict`` not a bool.
    """
    if not isinstance(url, str):
        raise ValueError(
            f"url: expected a source URL string such as 'synthetic://lamp' or 'oakd://', got {_described(url)}"
        )
    render, strict = _flag(render, "render"), _flag(strict, "strict", optional=True)
    return Stream(url, _config(config, overrides), render=render, strict=strict)


# --------------------------------------------------------------------------------------------------
# illuminet.relight


def _intrinsics(intrinsics: Any, width: int, height: int) -> Intrinsics:
    """Intrinsics, a 3x3 K, or (fx, fy, cx, cy) for the colour image (scaled when made for a size of the
    same aspect ratio; another aspect ratio, a bool, an implausible focal length: refused)."""
    from illuminet.runtime.relight import check_intrinsics, fit_intrinsics

    if isinstance(intrinsics, Intrinsics):
        K = intrinsics
    else:
        if any(isinstance(x, (bool, np.bool_)) for x in np.asarray(intrinsics, dtype=object).ravel()):
            raise ValueError(f"intrinsics: expected numbers in pixels, got a bool in {intrinsics!r}")
        try:
            a = np.asarray(intrinsics, np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"intrinsics: expected numbers in pixels, got {intrinsics!r}: {e}") from None
        if a.shape == (3, 3):
            if a[1, 0] != 0 or a[2, 0] != 0 or a[2, 1] != 0 or a[2, 2] != 1:
                raise ValueError(
                    f"intrinsics: a 3x3 camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got "
                    f"{a.tolist()} (transposed?)"
                )
            if a[0, 1] != 0:
                raise ValueError(
                    f"intrinsics: the 3x3 camera matrix has skew K[0, 1]={a[0, 1]:g}; the pipeline models no "
                    f"skew: undistort/rectify the image, or pass (fx, fy, cx, cy)"
                )
            K = Intrinsics(float(a[0, 0]), float(a[1, 1]), float(a[0, 2]), float(a[1, 2]), width, height)
        elif a.shape == (4,):
            K = Intrinsics(*(float(x) for x in a), width, height)
        else:
            raise ValueError(
                f"intrinsics: expected an Intrinsics, a 3x3 camera matrix or (fx, fy, cx, cy), "
                f"got {'None' if intrinsics is None else f'an array of shape {a.shape}'}"
            )
    check_intrinsics(K)
    return fit_intrinsics(K, width, height)


def align_depth(depth: np.ndarray, color_shape: tuple[int, ...], what: str = "depth") -> np.ndarray:
    """Depth (metres, float32, or uint16 millimetres) at the colour image's size.

    Depth aligned to the colour camera but computed at another resolution (a stereo camera's 640x400
    for 1280x800 colour) is resized **nearest neighbour**: no depth is invented across an edge and
    0 (invalid) stays 0. The two must have the same aspect ratio (the same field of view); anything
    else is not aligned and is refused.
    """
    import cv2

    d = _as_array(depth, what, "expected a 2-D array of depths (a single-channel image)")
    if d.ndim != 2:
        raise ValueError(f"{what}: expected a single-channel image, got shape {d.shape}")
    _check_pixels(d.shape, what)  # before the float32 copy
    if d.size == 0:
        raise ValueError(f"{what}: empty (shape {d.shape}); expected a 2-D array of depths")
    if d.dtype.kind not in "fiu":
        raise ValueError(f"{what}: expected depths as numbers (float metres or uint16 millimetres), got {d.dtype}")
    if d.dtype == np.uint16:
        d = d.astype(np.float32) * np.float32(1e-3)
    with np.errstate(over="ignore"):  # float64 beyond float32 (1e300 for invalid): inf, invalid, without numpy's lines
        d = d.astype(np.float32, copy=False)
    h, w = color_shape[:2]
    dh, dw = d.shape
    if (dh, dw) == (h, w):
        return d
    if abs(dw / dh - w / h) > 0.01 * (w / h):
        raise ValueError(
            f"{what}: size {dw}x{dh} has another aspect ratio than the colour image {w}x{h}; "
            f"depth must be aligned to colour (same field of view, possibly another resolution)"
        )
    return cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST)


def relight(
    color: np.ndarray,
    depth: np.ndarray,
    intrinsics: Any,
    anchor_px: tuple[float, float],
    bundle: str | None = None,
    *,
    config: Config | str | os.PathLike | None = None,
    exposure: Exposure | None = None,
    precision: str | None = None,
    **overrides: Any,
):
    """Place the bundle's object at ``anchor_px`` in one RGB-D image and predict its radiance.

    Parameters
    ----------
    color : (H, W, 3) uint8 RGB
    depth : (h, w) float metres or uint16 millimetres (0 = invalid), aligned to colour; another
        resolution of the same field of view is resized nearest-neighbour (:func:`align_depth`)
    intrinsics : Intrinsics, 3x3 K or (fx, fy, cx, cy) of the colour image
    anchor_px : (x, y) colour pixel where the object stands
    bundle : object bundle (default ``[model] bundle``, e.g. ``builtin:vase``): a str or a path
    config, **overrides : as for :func:`open`
    exposure : Exposure, optional (absolute units when known)
    precision : ``"int8"`` or ``"fp32"`` ONNX chain (default ``[model] precision``)

    Returns
    -------
    RelightResult
        Arrays: ``vertices``, ``normals`` (camera frame), ``faces``, ``radiance`` (linear RGB of a
        white diffuse surface in the image's linear units), ``irradiance``, ``T_cam_obj``, ... (see
        :class:`illuminet.runtime.relight.RelightResult`; ``illuminet relight``'s npz holds the same).
        :func:`render_preview` draws it into the image.

    Raises
    ------
    ValueError
        A mistake in an argument, one line naming it: ``color`` not HxWx3 uint8 or over
        :data:`~illuminet.runtime.relight.MAX_IMAGE_PIXELS`, ``depth``, ``intrinsics``, ``anchor_px``
        not two finite numbers inside the image, ``config`` (a :class:`ConfigError`), ``exposure``.
    """
    from illuminet.runtime.relight import check_anchor_px
    from illuminet.runtime.relight import relight as _relight

    if isinstance(bundle, os.PathLike):  # a pathlib.Path was "override: [model] bundle: expected string"
        bundle = os.fspath(bundle)
    if bundle is not None and not isinstance(bundle, str):
        raise ValueError(
            f"bundle: expected builtin:NAME or a bundle folder (a str or a path), or None, got {_described(bundle)}"
        )
    color = _color(color)  # shape, dtype and size checked before the copy
    d = align_depth(depth, color.shape)
    h, w = color.shape[:2]
    K = _intrinsics(intrinsics, w, h)
    anchor = check_anchor_px(anchor_px, w, h, "anchor_px")
    cfg = _config(config, overrides, "illuminet.relight()")
    return _relight(color, d, K, anchor, cfg, bundle=bundle, exposure=exposure, precision=precision)


def render_preview(
    color: np.ndarray,
    depth: np.ndarray | None,
    intrinsics: Any,
    result,
    config: Config | str | os.PathLike | None = None,
    **overrides: Any,
) -> np.ndarray:
    """The relit object composited into the colour image (HxWx3 uint8 RGB), by the runtime's renderer.

    ``result`` is what :func:`relight` returned; the same bundle's render mesh is drawn with its
    predicted shading, cast shadow and occlusion by the real depth (as ``illuminet run`` draws it).
    Needs OpenGL via EGL (``illuminet doctor`` says whether it works). The arguments are checked as
    :func:`relight` checks them (a ValueError naming the argument) before any rendering.
    """
    from illuminet.runtime.relight import RelightResult
    from illuminet.runtime.render.gl import using
    from illuminet.runtime.render.shadow import dominant_light
    from illuminet.runtime.render.stage import RenderStage
    from illuminet.runtime.scene import ObjectShading

    if not isinstance(result, RelightResult):
        raise ValueError(
            f"result: expected the RelightResult that illuminet.relight() returned, got {_described(result)}"
        )
    color = _color(color)  # shape, dtype and size checked before the copy
    h, w = color.shape[:2]
    d = None if depth is None else align_depth(depth, color.shape)
    K = _intrinsics(intrinsics, w, h)
    cfg = _config(config, overrides, "illuminet.render_preview()")
    try:
        T = np.asarray(result.T_cam_obj, np.float64)
    except (TypeError, ValueError):
        T = np.full((0,), np.nan)
    if T.shape != (4, 4) or not np.isfinite(T).all() or not np.array_equal(T[3], [0, 0, 0, 1]):
        # a 3x3 was an IndexError traceback from the renderer, NaN "cannot convert float NaN to integer"
        raise ValueError(
            f"result.T_cam_obj: expected the finite 4x4 object-to-camera transform relight returned, got "
            f"{_described(result.T_cam_obj)}"
        )
    if str(result.bundle):  # the bundle folder relight loaded: the same object and carry
        cfg = apply_overrides(cfg, [("model", "bundle", str(result.bundle))])
    R = T[:3, :3]
    shading = ObjectShading(
        irradiance=np.asarray(result.proxy_irradiance, np.float32),
        method=result.method,
        dominant_dir=R.T @ np.asarray(result.dominant_dir, np.float64),
        dominant_share=float(result.dominant_share),
        render_irradiance=np.asarray(result.irradiance, np.float32),
    )
    stage = RenderStage(cfg)
    with using(None, cfg.render.gl_backend, cfg.render.gl_api):  # one thread at a time draws (gl.using)
        stage.open()
        try:
            irr = stage.render_irradiance(shading)
            light, share = dominant_light(shading, stage.comp.mesh.normals, irr)
            return stage.comp.draw(color, d, K.K, T, irr, float(result.exposure_scale), light, share)
        finally:
            stage.close()
