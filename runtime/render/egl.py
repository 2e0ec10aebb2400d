"""A headless OpenGL ES 3.x context through EGL, made here with ctypes, for moderngl to drive.

Why this module exists
----------------------
moderngl creates its standalone contexts through glcontext, whose EGL backend binds the desktop
API (``eglBindAPI(EGL_OPENGL_API)``) and asks for a 3.3 core profile: boards whose GPU offers only
OpenGL ES 3.x (a Raspberry Pi 5's V3D: ES 3.1, desktop GL 3.1) get no context, or one on the
software rasteriser. moderngl itself can drive a context it did not create:
``mgl.create_context(context=obj)`` (moderngl 5.8 to 5.13 at least) takes any object with
``load_opengl_function(name)`` / ``load(name)``, ``__enter__``, ``__exit__`` and ``release``, the
interface of a glcontext backend. :class:`EGLContext` is such an object for an ES context.

What it does
------------
* the display: Mesa's surfaceless platform (``EGL_MESA_platform_surfaceless``: picks the GPU's render
  node itself, llvmpipe without one), every EGL device (``EGL_EXT_platform_device``: NVIDIA's
  driver), then the default display; each is tried until one gives a **hardware** renderer, else the
  first that works (software). ``GLCONTEXT_DEVICE_INDEX`` (glcontext's variable) pins one device.
* the context: ``eglBindAPI(EGL_OPENGL_ES_API)``, ES 3.2, else 3.1, else 3.0; surfaceless when the
  display supports it (``EGL_KHR_surfaceless_context``), else on a 1x1 pbuffer.
* the function loader: ``eglGetProcAddress``, then ``libGLESv2``'s symbols. moderngl loads desktop
  entry points as well; the few it calls that ES lacks get substitutes (:data:`ES_SUBSTITUTES`), the
  others a harmless no-op, so a driver without libglvnd's dispatch stubs still loads.

Only :mod:`illuminet.runtime.render.gl` uses this module (through :func:`create_gles_context`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading

log = logging.getLogger(__name__)

EGL_NO_DISPLAY = None
EGL_SUCCESS = 0x3000
EGL_NONE = 0x3038
EGL_EXTENSIONS = 0x3055
EGL_VENDOR = 0x3053
EGL_SURFACE_TYPE = 0x3033
EGL_PBUFFER_BIT = 0x0001
EGL_RENDERABLE_TYPE = 0x3040
EGL_OPENGL_ES3_BIT = 0x0040
EGL_RED_SIZE, EGL_GREEN_SIZE, EGL_BLUE_SIZE = 0x3024, 0x3023, 0x3022
EGL_WIDTH, EGL_HEIGHT = 0x3057, 0x3056
EGL_OPENGL_ES_API = 0x30A0
EGL_CONTEXT_MAJOR_VERSION = 0x3098  # = EGL_CONTEXT_CLIENT_VERSION (EGL 1.3)
EGL_CONTEXT_MINOR_VERSION = 0x30FB  # EGL 1.5 / EGL_KHR_create_context
EGL_PLATFORM_DEVICE_EXT = 0x313F
EGL_PLATFORM_SURFACELESS_MESA = 0x31DD
GL_VERSION, GL_RENDERER = 0x1F02, 0x1F01

#: GL_RENDERER substrings of software rasterisers (a hardware renderer is preferred over these)
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "swiftshader", "lavapipe", "software")

#: ES versions asked for, best first (the renderer's shaders need ES 3.0: GLSL ``300 es``)
ES_VERSIONS = ((3, 2), (3, 1), (3, 0))

_EGL_ERRORS = {
    0x3001: "EGL_NOT_INITIALIZED",
    0x3002: "EGL_BAD_ACCESS",
    0x3003: "EGL_BAD_ALLOC",
    0x3004: "EGL_BAD_ATTRIBUTE",
    0x3005: "EGL_BAD_CONFIG",
    0x3006: "EGL_BAD_CONTEXT",
    0x3008: "EGL_BAD_DISPLAY",
    0x3009: "EGL_BAD_MATCH",
    0x300C: "EGL_BAD_PARAMETER",
}


class EGLUnavailable(RuntimeError):
    """No ES 3.x context could be made; the message says what was tried and what failed."""


def is_software(renderer: str) -> bool:
    """True when ``renderer`` (GL_RENDERER) names a software rasteriser."""
    r = renderer.lower()
    return any(s in r for s in SOFTWARE_RENDERERS)


class _Lib:
    """libEGL and libGLESv2 loaded once per process, with the signatures used here."""

    _inst: _Lib | None = None
    _lock = threading.Lock()

    @classmethod
    def get(cls) -> _Lib:
        with cls._lock:
            if cls._inst is None:
                cls._inst = cls()
            return cls._inst

    def __init__(self):
        name = os.environ.get("ILLUMINET_LIBEGL") or ctypes.util.find_library("EGL") or "libEGL.so.1"
        try:
            egl = ctypes.CDLL(name)
        except OSError as e:
            raise EGLUnavailable(f"libEGL not loadable ({e})") from None
        self.egl = egl
        vp, i, u, c = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_char_p
        sigs = {
            "eglGetError": (i, []),
            "eglGetProcAddress": (vp, [c]),
            "eglQueryString": (c, [vp, i]),
            "eglGetDisplay": (vp, [vp]),
            "eglInitialize": (u, [vp, ctypes.POINTER(i), ctypes.POINTER(i)]),
            "eglBindAPI": (u, [u]),
            "eglChooseConfig": (u, [vp, vp, ctypes.POINTER(vp), i, ctypes.POINTER(i)]),
            "eglCreateContext": (vp, [vp, vp, vp, vp]),
            "eglCreatePbufferSurface": (vp, [vp, vp, vp]),
            "eglMakeCurrent": (u, [vp, vp, vp, vp]),
            "eglGetCurrentContext": (vp, []),
            "eglGetCurrentDisplay": (vp, []),
            "eglDestroyContext": (u, [vp, vp]),
            "eglDestroySurface": (u, [vp, vp]),
        }
        for fn, (res, args) in sigs.items():
            f = getattr(egl, fn)
            f.restype, f.argtypes = res, args
        self.get_platform_display = self._ext("eglGetPlatformDisplayEXT", vp, u, vp, vp)
        self.query_devices = self._ext("eglQueryDevicesEXT", u, i, vp, ctypes.POINTER(i))
        gles_name = ctypes.util.find_library("GLESv2") or "libGLESv2.so.2"
        try:
            self.gles = ctypes.CDLL(gles_name)
        except OSError:
            self.gles = None  # eglGetProcAddress alone must do (EGL_KHR_get_all_proc_addresses)

    def _ext(self, name: str, res, *args):
        p = self.egl.eglGetProcAddress(name.encode())
        return ctypes.CFUNCTYPE(res, *args)(p) if p else None

    def error(self) -> str:
        code = self.egl.eglGetError()
        return _EGL_ERRORS.get(code, hex(code))

    def client_extensions(self) -> set[str]:
        s = self.egl.eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS)
        if not s:  # EGL < 1.5 without EGL_EXT_client_extensions: EGL_BAD_DISPLAY, nothing to read
            self.egl.eglGetError()
            return set()
        return set(s.decode().split())

    def gl_proc(self, name: str) -> int:
        """Address of a GL entry point (0 when neither EGL nor libGLESv2 has it)."""
        p = self.egl.eglGetProcAddress(name.encode())
        if not p and self.gles is not None:
            f = getattr(self.gles, name, None)
            p = ctypes.cast(f, ctypes.c_void_p).value if f is not None else None
        return int(p or 0)


def _attribs(*pairs: int):
    vals = list(pairs) + [EGL_NONE]
    return (ctypes.c_int * len(vals))(*vals)


def _displays(lib: _Lib) -> list[tuple[str, int]]:
    """Candidate displays, in the order tried: (what, EGLDisplay handle)."""
    out: list[tuple[str, int]] = []
    ext = lib.client_extensions()
    pinned = os.environ.get("GLCONTEXT_DEVICE_INDEX")
    if lib.get_platform_display is not None:
        if "EGL_MESA_platform_surfaceless" in ext and pinned is None:
            d = lib.get_platform_display(EGL_PLATFORM_SURFACELESS_MESA, None, None)
            if d:
                out.append(("surfaceless platform", d))
        if "EGL_EXT_platform_device" in ext and lib.query_devices is not None:
            n = ctypes.c_int(0)
            if lib.query_devices(0, None, ctypes.byref(n)) and n.value > 0:
                devs = (ctypes.c_void_p * n.value)()
                if lib.query_devices(n.value, devs, ctypes.byref(n)):
                    idx = range(n.value) if pinned is None else [int(pinned)]
                    for k in idx:
                        if 0 <= k < n.value:
                            d = lib.get_platform_display(EGL_PLATFORM_DEVICE_EXT, devs[k], None)
                            if d:
                                out.append((f"EGL device {k}", d))
    if pinned is None:
        d = lib.egl.eglGetDisplay(None)
        if d:
            out.append(("default display", d))
    return out


class EGLContext:
    """An OpenGL ES 3.x context on one EGL display, in glcontext's backend interface.

    Use :func:`create_gles_context`, which picks the display. ``version`` is the (major, minor) ES
    version the driver gave; ``renderer`` and ``gl_version`` the driver's strings; ``display_kind``
    which candidate display it is on.
    """

    def __init__(self, lib: _Lib, display: int, display_kind: str):
        self._lib = lib
        self.dpy = display
        self.display_kind = display_kind
        self.ctx = None
        self.surface = None
        self._keep: list = []  # ctypes callbacks handed to moderngl (must outlive the context)
        self._noop = None
        egl = lib.egl
        major, minor = ctypes.c_int(0), ctypes.c_int(0)
        if not egl.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)):
            raise EGLUnavailable(f"{display_kind}: eglInitialize failed ({lib.error()})")
        self.egl_version = (major.value, minor.value)
        dext = set((egl.eglQueryString(display, EGL_EXTENSIONS) or b"").decode().split())
        self.vendor = (egl.eglQueryString(display, EGL_VENDOR) or b"?").decode()
        if not egl.eglBindAPI(EGL_OPENGL_ES_API):
            raise EGLUnavailable(f"{display_kind}: eglBindAPI(EGL_OPENGL_ES_API) failed ({lib.error()})")
        cfg = ctypes.c_void_p()
        n = ctypes.c_int(0)
        want = _attribs(
            EGL_SURFACE_TYPE,
            EGL_PBUFFER_BIT,
            EGL_RENDERABLE_TYPE,
            EGL_OPENGL_ES3_BIT,
            EGL_RED_SIZE,
            8,
            EGL_GREEN_SIZE,
            8,
            EGL_BLUE_SIZE,
            8,
        )
        if not egl.eglChooseConfig(display, want, ctypes.byref(cfg), 1, ctypes.byref(n)) or n.value < 1:
            if "EGL_KHR_no_config_context" not in dext:
                raise EGLUnavailable(f"{display_kind}: no EGL config renders OpenGL ES 3 ({lib.error()})")
            cfg = ctypes.c_void_p(None)  # EGL_NO_CONFIG_KHR: fine for a surfaceless context
        surfaceless = "EGL_KHR_surfaceless_context" in dext
        errors = []
        versions = list(ES_VERSIONS) if ("EGL_KHR_create_context" in dext or self.egl_version >= (1, 5)) else []
        attempts = [_attribs(EGL_CONTEXT_MAJOR_VERSION, a, EGL_CONTEXT_MINOR_VERSION, b) for a, b in versions]
        attempts.append(_attribs(EGL_CONTEXT_MAJOR_VERSION, 3))  # EGL 1.4: "3" gives the newest 3.x
        for attrs in attempts:
            self.ctx = egl.eglCreateContext(display, cfg, None, attrs)
            if self.ctx:
                break
            errors.append(lib.error())
        if not self.ctx:
            raise EGLUnavailable(f"{display_kind}: eglCreateContext for OpenGL ES 3.x failed ({', '.join(errors)})")
        if not surfaceless:
            if not cfg.value:
                raise EGLUnavailable(f"{display_kind}: neither a surfaceless context nor a pbuffer config")
            self.surface = egl.eglCreatePbufferSurface(display, cfg, _attribs(EGL_WIDTH, 1, EGL_HEIGHT, 1))
            if not self.surface:
                err = lib.error()
                self.release()
                raise EGLUnavailable(f"{display_kind}: eglCreatePbufferSurface failed ({err})")
        if not egl.eglMakeCurrent(display, self.surface, self.surface, self.ctx):
            err = lib.error()
            self.release()
            raise EGLUnavailable(f"{display_kind}: eglMakeCurrent failed ({err})")
        get_string = ctypes.CFUNCTYPE(ctypes.c_char_p, ctypes.c_uint)(lib.gl_proc("glGetString"))
        self.gl_version = (get_string(GL_VERSION) or b"").decode()
        self.renderer = (get_string(GL_RENDERER) or b"").decode()
        if not self.gl_version.startswith("OpenGL ES"):
            self.release()
            raise EGLUnavailable(f"{display_kind}: asked for OpenGL ES, got {self.gl_version!r}")
        ver = self.gl_version.split()[2] if len(self.gl_version.split()) > 2 else "0.0"
        try:
            self.version = tuple(int(x) for x in ver.split(".")[:2])
        except ValueError:
            self.version = (3, 0)
        self.substitutes = _substitutes(lib, self._keep)

    # -- glcontext's backend interface (what moderngl calls) ------------------------------------
    def load_opengl_function(self, name: str) -> int:
        """Address of ``name`` for moderngl's function table.

        moderngl loads the desktop API; on ES the entry points libGLESv2 does not export are not ES
        functions, and calling them sets GL_INVALID_OPERATION ("unsupported function") where the
        driver dispatches them at all. Those moderngl calls on the renderer's path get ES
        equivalents (:data:`ES_SUBSTITUTES`); the rest a no-op (glPrimitiveRestartIndex at set-up,
        glClampColor before float read-backs: ES neither restarts on that index nor clamps).
        """
        if name in self.substitutes:
            return self.substitutes[name]
        gles = self._lib.gles
        p = self._lib.gl_proc(name) if gles is None or getattr(gles, name, None) is not None else 0
        if p:
            return p
        if self._noop is None:
            self._noop = ctypes.CFUNCTYPE(None)(lambda: None)
        return int(ctypes.cast(self._noop, ctypes.c_void_p).value)

    load = load_opengl_function  # the name moderngl 5.8 calls

    def __enter__(self):
        egl = self._lib.egl
        if self.ctx and egl.eglGetCurrentContext() != self.ctx:  # the renderer calls this per pass
            egl.eglMakeCurrent(self.dpy, self.surface, self.surface, self.ctx)
        return self

    def __exit__(self, *exc):
        self._lib.egl.eglMakeCurrent(self.dpy, None, None, None)

    def release(self) -> None:
        """Destroy the context (and its pbuffer); safe to call twice. The display stays initialised."""
        egl = self._lib.egl
        if self.ctx:
            if egl.eglGetCurrentContext() == self.ctx:
                egl.eglMakeCurrent(self.dpy, None, None, None)
            egl.eglDestroyContext(self.dpy, self.ctx)
            self.ctx = None
        if self.surface:
            egl.eglDestroySurface(self.dpy, self.surface)
            self.surface = None

    def describe(self) -> str:
        egl = ".".join(str(x) for x in self.egl_version)
        return f"{self.renderer} / {self.gl_version} (EGL {egl}, {self.display_kind})"


#: desktop-only entry points (and one desktop-only query) moderngl uses on the renderer's path,
#: and the ES calls that do the same: depth clears and ranges take floats instead of doubles; a
#: depth-only framebuffer's glDrawBuffer(GL_NONE) is glDrawBuffers with one entry
ES_SUBSTITUTES = {
    "glClearDepth": "glClearDepthf",
    "glDepthRange": "glDepthRangef",
    "glDrawBuffer": "glDrawBuffers",
    "glGetIntegerv": "glGetIntegerv",
}


def _substitutes(lib: _Lib, keep: list) -> dict[str, int]:
    """ctypes shims for :data:`ES_SUBSTITUTES` (Python callbacks: a few calls per frame at most)."""
    out: dict[str, int] = {}
    f, d, u = ctypes.c_float, ctypes.c_double, ctypes.c_uint

    def shim(name, es_name, es_sig, desk_sig, body):
        p = lib.gl_proc(es_name)
        if not p:
            return
        fwd = ctypes.CFUNCTYPE(None, *es_sig)(p)
        cb = ctypes.CFUNCTYPE(None, *desk_sig)(lambda *a: body(fwd, *a))
        keep.extend([fwd, cb])
        out[name] = int(ctypes.cast(cb, ctypes.c_void_p).value)

    shim("glClearDepth", "glClearDepthf", (f,), (d,), lambda fwd, x: fwd(x))
    shim("glDepthRange", "glDepthRangef", (f, f), (d, d), lambda fwd, a, b: fwd(a, b))
    shim(
        "glDrawBuffer",
        "glDrawBuffers",
        (ctypes.c_int, ctypes.POINTER(u)),
        (u,),
        # GL_NONE or a colour attachment; anything else is moderngl restoring the "default draw
        # buffer" it read with glGetIntegerv(GL_DRAW_BUFFER), a query ES does not have (-1)
        lambda fwd, mode: fwd(1, ctypes.byref(u(mode))) if mode == 0 or 0x8CE0 <= mode <= 0x8CFF else None,
    )
    # glGetIntegerv(GL_DRAW_BUFFER) is desktop GL; ES 3.0 answers the same for GL_DRAW_BUFFER0
    # (moderngl asks before blitting, to restore the draw buffer afterwards)
    shim(
        "glGetIntegerv",
        "glGetIntegerv",
        (u, ctypes.c_void_p),
        (u, ctypes.c_void_p),
        lambda fwd, pname, ptr: fwd(0x8825 if pname == 0x0C01 else pname, ptr),
    )
    return out


def create_gles_context() -> EGLContext:
    """An ES 3.x context, current on the calling thread: on a hardware renderer when any display has
    one, else on the first display that works (software). Raises :class:`EGLUnavailable` with every
    display's failure when none works."""
    lib = _Lib.get()
    if lib.get_platform_display is None and not lib.egl.eglGetDisplay:
        raise EGLUnavailable("libEGL has neither eglGetPlatformDisplayEXT nor eglGetDisplay")
    tried: list[str] = []
    fallback: EGLContext | None = None
    for kind, dpy in _displays(lib):
        try:
            c = EGLContext(lib, dpy, kind)
        except EGLUnavailable as e:
            tried.append(str(e))
            continue
        if not is_software(c.renderer):
            if fallback is not None:
                fallback.release()
            c.__enter__()
            return c
        if fallback is None:
            fallback = c
        else:
            c.release()
        tried.append(f"{kind}: software renderer {c.renderer}")
    if fallback is not None:
        fallback.__enter__()
        log.debug("GLES: no hardware renderer (%s); using %s", "; ".join(tried), fallback.describe())
        return fallback
    raise EGLUnavailable("; ".join(tried) if tried else "no EGL display")


def gl_function(name: str, restype, *argtypes):
    """A GL entry point of the current ES context as a ctypes function (None when absent)."""
    p = _Lib.get().gl_proc(name)
    return ctypes.CFUNCTYPE(restype, *argtypes)(p) if p else None
