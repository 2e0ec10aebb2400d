"""GL calls that let other Python threads run while the driver works.

moderngl holds the GIL through every GL call (its extension never calls ``PyEval_SaveThread``), and
on Mesa's llvmpipe a draw call does the vertex processing and binning in the calling thread: the
object's draw holds the GIL for ~5 ms per frame, during which the pipelined loop's front thread
(planes, odometry...) cannot run a line of Python. ctypes releases the GIL for the duration of a
foreign call, so the calls that take the time -- the draws (``glDrawElements`` of the object and of its shadow
map, ``glDrawArrays`` of the screen passes, which wait for the rasteriser when they read what the
previous pass drew) and the ``glFinish`` before a read-back -- are made through ctypes here, on the
same (current) context, with the programs and vertex arrays moderngl made.

Only for an EGL context (the default headless backend; the functions come from
``eglGetProcAddress``): :func:`gl_nogil` returns None elsewhere and the caller uses moderngl's own
calls. The output is the same; ``ILLUMINET_GL_NOGIL=0`` switches it off.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

GL_TRIANGLES = 0x0004
GL_TRIANGLE_STRIP = 0x0005
GL_UNSIGNED_INT = 0x1405


class GLNoGil:
    """``glUseProgram``, ``glBindVertexArray``, ``glDrawElements``, ``glFinish`` called through ctypes."""

    def __init__(self, get_proc, egl_current) -> None:
        u, i, p = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p

        def fn(name: str, *args):
            addr = get_proc(name.encode())
            if not addr:
                raise OSError(f"eglGetProcAddress({name}) returned NULL")
            return ctypes.CFUNCTYPE(None, *args)(addr)

        self._use_program = fn("glUseProgram", u)
        self._bind_vao = fn("glBindVertexArray", u)
        self._draw_elements = fn("glDrawElements", u, i, u, p)
        self._draw_arrays = fn("glDrawArrays", u, i, i)
        self._finish = fn("glFinish")
        self._egl_current = egl_current

    def current(self) -> bool:
        """Whether an EGL context is current on this thread (else these calls would go nowhere)."""
        return bool(self._egl_current())

    def draw_triangles(self, program_glo: int, vao_glo: int, count: int, first: int) -> None:
        """``vao.render(TRIANGLES, vertices=count, first=first)`` of an indexed (uint32) vertex array."""
        self._use_program(program_glo)
        self._bind_vao(vao_glo)
        self._draw_elements(GL_TRIANGLES, count, GL_UNSIGNED_INT, ctypes.c_void_p(4 * first))
        self._bind_vao(0)

    def draw_strip(self, program_glo: int, vao_glo: int, count: int = 4) -> None:
        """``vao.render(TRIANGLE_STRIP)`` of a non-indexed vertex array of ``count`` vertices (a quad)."""
        self._use_program(program_glo)
        self._bind_vao(vao_glo)
        self._draw_arrays(GL_TRIANGLE_STRIP, 0, count)
        self._bind_vao(0)

    def finish(self) -> None:
        """Wait for the GPU (llvmpipe's threads) without holding the GIL."""
        self._finish()


_cached: GLNoGil | None | bool = False


def gl_nogil() -> GLNoGil | None:
    """The ctypes GL entry points when the current context is EGL's, else None (cached per process)."""
    global _cached
    if os.environ.get("ILLUMINET_GL_NOGIL", "1") == "0":
        return None
    if _cached is False:
        _cached = None
        try:
            name = ctypes.util.find_library("EGL") or "libEGL.so.1"
            egl = ctypes.CDLL(name)
            egl.eglGetProcAddress.restype = ctypes.c_void_p
            egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
            egl.eglGetCurrentContext.restype = ctypes.c_void_p
            _cached = GLNoGil(egl.eglGetProcAddress, egl.eglGetCurrentContext)
        except (OSError, AttributeError) as e:  # no libEGL: moderngl's own calls
            log.debug("GL calls without the GIL unavailable: %s", e)
    if _cached is not None and not _cached.current():
        return None
    return _cached
