"""The OpenGL context: the one place in the project that creates it, GL error checking, and the
two GL dialects the renderer speaks.

Rendering runs headless: by default a standalone **EGL** context (Mesa's llvmpipe on a machine
without a GPU, the vendor driver where there is one), so no X server or window is needed. Every
component that draws asks :func:`get_context` for the process-wide context instead of creating its
own, because moderngl objects (buffers, textures, programs) belong to the context that made them
and a second context would double driver memory for nothing (after moderngl's own
``tests/conftest.py``: one standalone context per run).

Two APIs ([render] gl_api): **desktop OpenGL 3.3 core** (moderngl's own standalone context through
glcontext), or **OpenGL ES 3.x** (what embedded GPUs such as a Raspberry Pi 5's V3D offer: ES 3.1,
desktop GL only 3.1), made by :mod:`illuminet.runtime.render.egl` and driven by the same moderngl.
``auto`` takes desktop GL when it runs on a GPU, else ES when that runs on a GPU, else desktop GL on
the software rasteriser; :func:`context_info` says which one a context is and why. The renderer's
shaders are written once in GLSL 330 and adapted to ``300 es`` by :func:`program`; the few formats
ES treats differently go through :func:`float_texture_dtype`, :func:`float_target_dtype` and
:func:`read_pixels`.

GL errors are sticky flags that the driver sets and nobody sees; :func:`check_gl` reads and clears
the flag at the points where the renderer wants to know (after setup, after each frame in strict
mode) and raises :class:`GLError` saying where it happened.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import threading
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

#: GL version the shaders are written for (GLSL 330 core)
REQUIRED_GL = 330
#: OpenGL ES version the adapted shaders need (GLSL 300 es)
REQUIRED_GLES = 300

#: backends accepted by :func:`create_context`; "default" lets moderngl choose (GLX/WGL/CGL with a display)
BACKENDS = ("egl", "default")

#: APIs accepted by :func:`create_context` ([render] gl_api)
GL_APIS = ("auto", "gl", "gles")

_lock = threading.Lock()
#: held by the thread that draws with the shared context (:func:`using`): one thread at a time
_use_lock = threading.RLock()
_use_depth = threading.local()
_shared = None
_shared_backend: str | None = None
_shared_api: str | None = None


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import GLError  # noqa: E402


@dataclass
class ContextInfo:
    """Which path a context takes (``illuminet doctor`` and the render log print it).

    ``api`` is "gl" or "gles"; ``via`` how it was made (glcontext's EGL or platform backend, or the
    ES context of :mod:`illuminet.runtime.render.egl`); ``software`` whether a software rasteriser
    draws; ``reason`` why ``auto`` chose it when it did not take desktop GL on a GPU.
    """

    api: str
    via: str
    renderer: str
    version: str
    software: bool
    reason: str = ""

    def describe(self) -> str:
        kind = "OpenGL ES" if self.api == "gles" else "desktop OpenGL"
        s = f"{kind} via {self.via}: {self.renderer}; {self.version}"
        return s + (f" ({self.reason})" if self.reason else "")


def create_context(backend: str = "egl", require: int = REQUIRED_GL, api: str = "gl"):
    """Create a new standalone (headless) moderngl context.

    Most code should call :func:`get_context` instead, which shares one context per process.

    Parameters
    ----------
    backend : {"egl", "default"}
        ``"egl"``: headless EGL (no display needed; Mesa llvmpipe without a GPU). ``"default"``:
        moderngl's platform default, which needs a display on Linux. OpenGL ES contexts are made
        through EGL only ("auto" with "default" is desktop GL only).
    require : int
        Minimum desktop GL version as moderngl writes it (330 = OpenGL 3.3 core).
    api : {"gl", "gles", "auto"}
        Desktop OpenGL, OpenGL ES 3.x, or the choice described in the module docstring.

    Raises
    ------
    GLError
        When the backend or API is unknown or no such context can be made, with what to install.
    """
    if backend not in BACKENDS:
        raise GLError(f"[render] gl_backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if api not in GL_APIS:
        raise GLError(f"[render] gl_api: expected one of {', '.join(GL_APIS)}, got {api!r}")
    try:
        import moderngl  # noqa: F401
    except ImportError as e:  # pragma: no cover - moderngl is a runtime dependency
        raise GLError(f"moderngl is not installed ({e}); install it with `pip install moderngl`") from None
    if api == "gles" and backend != "egl":
        raise GLError(
            f'[render] gl_api = "gles" needs gl_backend = "egl" (OpenGL ES is made through EGL), got {backend!r}'
        )
    if api == "auto":
        ctx = _create_auto(backend, require)
    elif api == "gles":
        ctx = _create_gles()
    else:
        ctx = _create_desktop(backend, require)
    info = context_info(ctx)
    log.debug("GL context: %s", info.describe())
    park(ctx)
    return ctx


def _create_desktop(backend: str, require: int):
    """Desktop OpenGL ``require`` core through glcontext (moderngl's standalone context)."""
    import moderngl

    kwargs = {"require": require}
    if backend == "egl":
        kwargs["backend"] = "egl"
    try:
        ctx = moderngl.create_standalone_context(**kwargs)
    except Exception as e:
        msg = str(e).replace("(0x3009)", "(EGL_BAD_MATCH: the driver offers no such desktop OpenGL core profile)")
        hint = (
            "EGL needs libEGL and a Mesa driver (Debian/Ubuntu: apt install libegl1 libgl1-mesa-dri); "
            'a GPU with only OpenGL ES 3.x takes [render] gl_api = "gles" (or "auto"); '
            'on a machine with a display, [render] gl_backend = "default" uses GLX instead'
            if backend == "egl"
            else 'the default backend needs a display (DISPLAY); headless machines should use gl_backend = "egl"'
        )
        raise GLError(
            f"cannot create an OpenGL {require // 100}.{require % 100 // 10} context "
            f"with backend {backend!r}: {msg}. {hint}"
        ) from None
    _set_info(ctx, "gl", "glcontext EGL" if backend == "egl" else "glcontext platform default")
    return ctx


def _create_gles():
    """OpenGL ES 3.x through :mod:`illuminet.runtime.render.egl`, driven by moderngl."""
    import moderngl

    from illuminet.runtime.render.egl import EGLUnavailable, create_gles_context

    try:
        native = create_gles_context()
    except EGLUnavailable as e:
        raise GLError(
            f"cannot create an OpenGL ES 3.x context through EGL: {e}. Install Mesa's EGL and GLES "
            "(Debian/Ubuntu/Raspberry Pi OS: apt install libegl1 libgles2 libegl-mesa0 libgl1-mesa-dri)"
        ) from None
    try:
        # moderngl drives a context it did not create through any object with glcontext's backend
        # interface (load / __enter__ / __exit__ / release), passed as ``context=``; moderngl >= 5.8
        ctx = moderngl.create_context(require=REQUIRED_GLES, standalone=True, context=native)
    except Exception as e:
        native.release()
        raise GLError(f"moderngl cannot drive the OpenGL ES context ({native.describe()}): {e}") from None
    _set_info(ctx, "gles", f"EGL, {native.display_kind} (illuminet.runtime.render.egl)")
    ext = ctx.extensions
    # moderngl's set-up enables desktop-only state and ctx.info queries desktop-only limits: both
    # leave GL_INVALID_ENUM behind on ES, which must not be blamed on the first frame
    ctx.error  # noqa: B018
    float_targets = {"GL_EXT_color_buffer_float", "GL_EXT_color_buffer_half_float"} & set(ext)
    if native.version < (3, 2) and not float_targets:
        ctx.release()
        raise GLError(
            f"the OpenGL ES context ({native.describe()}) cannot render to float textures "
            "(neither ES 3.2 nor GL_EXT_color_buffer_float/_half_float); the contact shadow needs one: "
            'set [render] gl_api = "gl" or update the GPU driver (Mesa)'
        )
    return ctx


def _create_auto(backend: str, require: int):
    """Desktop GL on a GPU, else ES on a GPU, else desktop GL on the software rasteriser (else ES)."""
    reasons: list[str] = []
    desk = gles = None
    try:
        desk = _create_desktop(backend, require)
    except GLError as e:
        reasons.append(f"desktop OpenGL {require // 100}.{require % 100 // 10}: {e}")
    if desk is not None and not context_info(desk).software:
        return desk
    if backend != "egl":  # the platform backend was asked for: OpenGL ES is made through EGL only
        if desk is None:
            raise GLError(reasons[0])
        return desk
    try:
        gles = _create_gles()
    except GLError as e:
        reasons.append(f"OpenGL ES: {e}")
    if gles is not None and (desk is None or not context_info(gles).software):
        why = (
            reasons[0].split(". ")[0]
            if desk is None
            else f"desktop OpenGL draws on the software rasteriser {context_info(desk).renderer}"
        )
        if desk is not None:
            desk.release()
        context_info(gles).reason = f"auto: {why}"
        return gles
    if gles is not None:
        gles.release()
    if desk is not None:
        make_current(desk)
        if gles is not None:
            context_info(desk).reason = "auto: software rendering; no GPU offers OpenGL ES 3.x either"
        return desk
    raise GLError("no OpenGL context: " + "; ".join(reasons))


def _set_info(ctx, api: str, via: str) -> ContextInfo:
    renderer = ctx.info.get("GL_RENDERER", "?")
    from illuminet.runtime.render.egl import is_software

    info = ContextInfo(api, via, renderer, ctx.info.get("GL_VERSION", "?"), is_software(renderer))
    extra = ctx.extra if isinstance(ctx.extra, dict) else {}
    extra["illuminet_gl"] = info
    ctx.extra = extra
    return info


def context_info(ctx) -> ContextInfo:
    """Which API, how made, which renderer (a context made elsewhere is described from its strings)."""
    extra = ctx.extra if isinstance(ctx.extra, dict) else {}
    info = extra.get("illuminet_gl")
    if info is None:
        es = str(ctx.info.get("GL_VERSION", "")).startswith("OpenGL ES")
        info = _set_info(ctx, "gles" if es else "gl", "a context made by the caller")
        if es:
            ctx.error  # noqa: B018  (ctx.info asks ES for desktop-only limits: GL_INVALID_ENUM)
    return info


def is_gles(ctx) -> bool:
    """True when ``ctx`` is an OpenGL ES context (shaders and formats take the ES path)."""
    return context_info(ctx).api == "gles"


def get_context(backend: str | None = None, api: str | None = None):
    """The process-wide GL context, created on first use.

    Parameters
    ----------
    backend : str or None
        Backend for the first creation (default: ``$ILLUMINET_GL_BACKEND`` or ``"egl"``). Asking
        later for a different backend than the one the shared context was made with is an error,
        because objects cannot move between contexts.
    api : str or None
        API for the first creation (default: ``$ILLUMINET_GL_API`` or ``"auto"``). Asking later for
        "gl" or "gles" when the shared context is the other one is an error; "auto" takes either.
    """
    global _shared, _shared_backend, _shared_api
    want = backend or os.environ.get("ILLUMINET_GL_BACKEND", "egl")
    want_api = api or os.environ.get("ILLUMINET_GL_API", "auto")
    with _lock:
        if _shared is None:
            _shared = create_context(want, api=want_api)
            _shared_backend = want
            _shared_api = context_info(_shared).api
        else:
            if backend is not None and backend != _shared_backend:
                raise GLError(
                    f"the shared GL context was created with backend {_shared_backend!r}; "
                    f"cannot switch to {backend!r} in the same process"
                )
            if api not in (None, "auto") and api != _shared_api:
                raise GLError(
                    f"the shared GL context is {'OpenGL ES' if _shared_api == 'gles' else 'desktop OpenGL'}; "
                    f"cannot switch to gl_api {api!r} in the same process"
                )
        make_current(_shared)
        return _shared


def release_context() -> None:
    """Release the shared context (tests and tools that want the driver's memory back)."""
    global _shared, _shared_backend, _shared_api
    with _lock:
        if _shared is not None:
            _shared.release()
        _shared, _shared_backend, _shared_api = None, None, None


def renderer_name(ctx) -> str:
    """``"llvmpipe (LLVM 15...) / 4.5 (Core Profile) Mesa ..."``: what actually draws (for reports)."""
    return f"{ctx.info.get('GL_RENDERER', '?')} / {ctx.info.get('GL_VERSION', '?')}"


# ----------------------------------------------------------------------------------- GL dialects

#: what replaces ``#version 330`` in an OpenGL ES context: GLSL ES 3.00 (ES 3.0 and later) with
#: full precision everywhere (ES fragment shaders have no default float precision, and
#: sampler2DShadow none at all)
GLES_HEADER = (
    "#version 300 es\n"
    "precision highp float;\n"
    "precision highp int;\n"
    "precision highp sampler2D;\n"
    "precision highp sampler2DShadow;\n"
)

_VERSION_LINE = re.compile(r"^\s*#version\s+330(\s+core)?[ \t]*\n")


def glsl(ctx, src: str) -> str:
    """A GLSL 330 source as ``ctx`` compiles it: unchanged for desktop GL, ``300 es`` for OpenGL ES.

    The renderer's shaders keep to the common subset (no geometry shaders, no implicit int/float
    conversions, explicit ``float(...)``), so the header is the only difference.
    """
    if not is_gles(ctx):
        return src
    src, n = _VERSION_LINE.subn(GLES_HEADER, src, count=1)
    if n != 1:
        raise ValueError("shader source must start with '#version 330' to be adapted to OpenGL ES")
    return src


def program(ctx, vertex_shader: str, fragment_shader: str):
    """``ctx.program`` with both sources adapted to the context's dialect (:func:`glsl`)."""
    return ctx.program(vertex_shader=glsl(ctx, vertex_shader), fragment_shader=glsl(ctx, fragment_shader))


def float_texture_dtype(ctx) -> tuple[str, type]:
    """(moderngl dtype, numpy dtype) of a float texture sampled with LINEAR filtering.

    32-bit float textures are filterable in desktop GL; OpenGL ES needs GL_OES_texture_float_linear
    for that (some embedded GPUs lack it), else half floats, which ES 3.0 filters everywhere.
    """
    if is_gles(ctx) and "GL_OES_texture_float_linear" not in ctx.extensions:
        return "f2", np.float16
    return "f4", np.float32


def float_target_dtype(ctx) -> tuple[str, type]:
    """(moderngl dtype, numpy dtype) of a one-channel float texture that is rendered into.

    OpenGL ES renders into 32-bit float only with ES 3.2 or GL_EXT_color_buffer_float; otherwise
    half floats (GL_EXT_color_buffer_half_float; :func:`create_context` refuses a context with neither).
    """
    if is_gles(ctx):
        ext = ctx.extensions
        es32 = ctx.version_code >= 320
        if not es32 and "GL_EXT_color_buffer_float" not in ext:
            return "f2", np.float16
    return "f4", np.float32


def depth_texture(ctx, size: tuple[int, int]):
    """``ctx.depth_texture(size)``, with storage OpenGL ES accepts.

    moderngl allocates depth textures as GL_DEPTH_COMPONENT24 with type GL_FLOAT, which desktop GL
    converts and ES refuses (GL_INVALID_OPERATION, leaving a texture without storage and the
    framebuffer INCOMPLETE_ATTACHMENT); on ES the storage is given again as 24-bit unsigned ints.
    """
    tex = ctx.depth_texture(size)
    if not is_gles(ctx):
        return tex
    import ctypes

    from illuminet.runtime.render.egl import gl_function

    ctx.error  # noqa: B018  (moderngl's refused allocation)
    GL_TEXTURE_2D, GL_TEXTURE0, GL_DEPTH_COMPONENT, GL_DEPTH_COMPONENT24, GL_UNSIGNED_INT = (
        0x0DE1,
        0x84C0,
        0x1902,
        0x81A6,
        0x1405,
    )
    u, i, vp = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
    active = gl_function("glActiveTexture", None, u)
    bind = gl_function("glBindTexture", None, u, u)
    image = gl_function("glTexImage2D", None, u, i, i, i, i, i, u, u, vp)
    active(GL_TEXTURE0 + ctx.default_texture_unit)
    bind(GL_TEXTURE_2D, tex.glo)
    image(GL_TEXTURE_2D, 0, GL_DEPTH_COMPONENT24, size[0], size[1], 0, GL_DEPTH_COMPONENT, GL_UNSIGNED_INT, None)
    check_gl(ctx, "allocating an OpenGL ES depth texture")
    return tex


def read_pixels(fbo, components: int, dtype: str = "f1", viewport=None) -> np.ndarray:
    """Read ``fbo``'s first colour attachment as an (h, w, components) array.

    Desktop GL reads any channel count; OpenGL ES guarantees only RGBA (with UNSIGNED_BYTE for
    normalised buffers, FLOAT for float ones), so ES reads four channels and keeps the first ones.
    """
    x, y, w, h = viewport if viewport is not None else (0, 0) + tuple(fbo.size)
    np_dtype = {"f1": np.uint8, "f2": np.float16, "f4": np.float32}[dtype]
    if is_gles(fbo.ctx):
        read_dtype = "f1" if dtype == "f1" else "f4"
        buf = fbo.read(viewport=(x, y, w, h), components=4, dtype=read_dtype, alignment=1)
        arr = np.frombuffer(buf, {"f1": np.uint8, "f4": np.float32}[read_dtype]).reshape(h, w, 4)
        return arr[:, :, :components].astype(np_dtype, copy=False)
    buf = fbo.read(viewport=(x, y, w, h), components=components, dtype=dtype, alignment=1)
    return np.frombuffer(buf, np_dtype).reshape(h, w, components)


def make_current(ctx) -> None:
    """Make ``ctx`` the calling thread's current GL context.

    Another standalone context created and released in the same process (``illuminet doctor``'s
    probe, a library) can leave none or a dead one current, after which every GL call fails with
    GL_INVALID_OPERATION. The renderer therefore makes its context current at each entry point;
    it costs well under a microsecond when it already is.
    """
    ctx.__enter__()


@contextlib.contextmanager
def using(ctx=None, backend: str | None = None, api: str | None = None):
    """Draw with ``ctx`` (default the shared one, :func:`get_context`) from the calling thread: one
    thread at a time, and the context let go after.

    A GL context is current on at most one thread; EGL refuses to make it current on a second thread
    while the first still holds it, and every GL call there then fails ("cannot create texture") or
    draws into nothing. Two threads rendering (two streams, ``illuminet.render_preview`` from a web
    server's worker) therefore take turns on a process-wide lock, and the outermost ``using`` makes
    the context no longer current on its thread when it ends, so that any thread can take it next.
    Re-entrant within one thread.
    """
    with _use_lock:
        depth = getattr(_use_depth, "n", 0)
        _use_depth.n = depth + 1
        try:
            if ctx is None:
                ctx = get_context(backend, api)
            make_current(ctx)
            yield ctx
        finally:
            _use_depth.n = depth
            if depth == 0:
                _let_go()


def _let_go() -> None:
    """Make no EGL context current on the calling thread (nothing for a non-EGL context)."""
    try:
        from illuminet.runtime.render.egl import _Lib

        egl = _Lib.get().egl
    except Exception:  # no libEGL: the context is GLX/WGL/CGL, which stays current on its thread
        return
    dpy = egl.eglGetCurrentDisplay()
    if dpy:
        egl.eglMakeCurrent(dpy, None, None, None)


def park(ctx) -> None:
    """Bind the context's own 1x1 framebuffer before framebuffers are released.

    moderngl re-binds "the current framebuffer" after creating a new one; if that one was released,
    the driver raises GL_INVALID_OPERATION. Standalone contexts have no screen to fall back to, so
    each context gets a tiny framebuffer that is never released, and components park on it before
    freeing their own.
    """
    extra = ctx.extra if isinstance(ctx.extra, dict) else {}
    fbo = extra.get("illuminet_park_fbo")
    if fbo is None:
        fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((1, 1))])
        extra["illuminet_park_fbo"] = fbo
        ctx.extra = extra
    fbo.use()


def check_gl(ctx, where: str) -> None:
    """Raise :class:`GLError` when the driver has an error flag set; ``where`` names the step.

    Reading the flag clears it, so each call reports only errors since the previous one.
    """
    err = ctx.error
    if err != "GL_NO_ERROR":
        raise GLError(f"OpenGL error {err} during {where}")
