"""The OpenGL context: the one place in the project that creates it, and GL error checking.

Rendering runs headless: by default a standalone **EGL** context (Mesa's llvmpipe on a machine
without a GPU, the vendor driver where there is one), so no X server or window is needed. Every
component that draws asks :func:`get_context` for the process-wide context instead of creating its
own, because moderngl objects (buffers, textures, programs) belong to the context that made them
and a second context would double driver memory for nothing (after moderngl's own
``tests/conftest.py``: one standalone context per run).

GL errors are sticky flags that the driver sets and nobody sees; :func:`check_gl` reads and clears
the flag at the points where the renderer wants to know (after setup, after each frame in strict
mode) and raises :class:`GLError` saying where it happened.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

#: GL version the shaders are written for (GLSL 330 core)
REQUIRED_GL = 330

#: backends accepted by :func:`create_context`; "default" lets moderngl choose (GLX/WGL/CGL with a display)
BACKENDS = ("egl", "default")

_lock = threading.Lock()
_shared = None
_shared_backend: str | None = None


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import GLError  # noqa: E402,F401


def create_context(backend: str = "egl", require: int = REQUIRED_GL):
    """Create a new standalone (headless) moderngl context.

    Most code should call :func:`get_context` instead, which shares one context per process.

    Parameters
    ----------
    backend : {"egl", "default"}
        ``"egl"``: headless EGL (no display needed; Mesa llvmpipe without a GPU). ``"default"``:
        moderngl's platform default, which needs a display on Linux.
    require : int
        Minimum GL version as moderngl writes it (330 = OpenGL 3.3 core).

    Raises
    ------
    GLError
        When the backend is unknown or no context of that version can be made, with what to install.
    """
    if backend not in BACKENDS:
        raise GLError(f"[render] gl_backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    try:
        import moderngl
    except ImportError as e:  # pragma: no cover - moderngl is a runtime dependency
        raise GLError(f"moderngl is not installed ({e}); install it with `pip install moderngl`") from None
    kwargs = {"require": require}
    if backend == "egl":
        kwargs["backend"] = "egl"
    try:
        ctx = moderngl.create_standalone_context(**kwargs)
    except Exception as e:
        hint = (
            "EGL needs libEGL and a Mesa driver (Debian/Ubuntu: apt install libegl1 libgl1-mesa-dri); "
            'on a machine with a display, [render] gl_backend = "default" uses GLX instead'
            if backend == "egl"
            else 'the default backend needs a display (DISPLAY); headless machines should use gl_backend = "egl"'
        )
        raise GLError(
            f"cannot create an OpenGL {require // 100}.{require % 100 // 10} context "
            f"with backend {backend!r}: {e}. {hint}"
        ) from None
    log.debug("GL context: %s, %s", ctx.info.get("GL_RENDERER"), ctx.info.get("GL_VERSION"))
    park(ctx)
    return ctx


def get_context(backend: str | None = None):
    """The process-wide GL context, created on first use.

    Parameters
    ----------
    backend : str or None
        Backend for the first creation (default: ``$ILLUMINET_GL_BACKEND`` or ``"egl"``). Asking
        later for a different backend than the one the shared context was made with is an error,
        because objects cannot move between contexts.
    """
    global _shared, _shared_backend
    want = backend or os.environ.get("ILLUMINET_GL_BACKEND", "egl")
    with _lock:
        if _shared is None:
            _shared = create_context(want)
            _shared_backend = want
        elif backend is not None and backend != _shared_backend:
            raise GLError(
                f"the shared GL context was created with backend {_shared_backend!r}; "
                f"cannot switch to {backend!r} in the same process"
            )
        make_current(_shared)
        return _shared


def release_context() -> None:
    """Release the shared context (tests and tools that want the driver's memory back)."""
    global _shared, _shared_backend
    with _lock:
        if _shared is not None:
            _shared.release()
        _shared, _shared_backend = None, None


def renderer_name(ctx) -> str:
    """``"llvmpipe (LLVM 15...) / 4.5 (Core Profile) Mesa ..."``: what actually draws (for reports)."""
    return f"{ctx.info.get('GL_RENDERER', '?')} / {ctx.info.get('GL_VERSION', '?')}"


def make_current(ctx) -> None:
    """Make ``ctx`` the calling thread's current GL context.

    Another standalone context created and released in the same process (``illuminet doctor``'s
    probe, a library) can leave none or a dead one current, after which every GL call fails with
    GL_INVALID_OPERATION. The renderer therefore makes its context current at each entry point;
    it costs well under a microsecond when it already is.
    """
    ctx.__enter__()


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
