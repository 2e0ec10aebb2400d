"""The life cycle shared by every source, stage and sink (after MediaPipe's CalculatorBase).

::

    open(config) ──▶ process(frame) ... process(frame) ──▶ close()
                      one call per frame, timestamps only increase

* ``open`` acquires resources (devices, GL context, ONNX sessions); it may raise with a message
  saying what is missing and how to fix it.
* ``process`` takes a :class:`~illuminet.runtime.frame.Frame` and returns a new frame with the
  stage's result added (``frame.with_result(self.name, ...)``); it never changes the input arrays.
  Raising :class:`FrameError` (or any exception) marks *this frame* failed; the loop counts it, logs
  it once per kind, keeps the last good result, and goes on (unless strict).
* ``close`` releases everything and is safe to call twice, also after a failed ``open``.

Sources produce frames (:meth:`Source.read` returns ``None`` at end of stream); sinks consume them
(:meth:`Sink.write`). All three are context managers.
"""

from __future__ import annotations

from typing import Any

from .frame import Frame


class FrameError(RuntimeError):
    """Processing one frame failed; the stream can go on."""


class EndOfStream(Exception):
    """Raised by a source that can no longer produce frames for a reason other than a normal end."""


class _LifeCycle:
    name: str = "stage"

    def open(self) -> None:
        """Acquire resources. Default: nothing."""

    def close(self) -> None:
        """Release resources; idempotent. Default: nothing."""

    def stats(self) -> dict[str, Any]:
        """Counters this component wants shown (drops, reconnects, state...)."""
        return {}

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Source(_LifeCycle):
    """A stream of frames.

    Attributes
    ----------
    live : bool
        True for cameras: the loop keeps only the newest frame when it falls behind and the source
        counts what it dropped. False for replay/synthetic in ``asap`` mode: nothing is dropped.
    """

    name = "source"
    live: bool = False

    def read(self) -> Frame | None:
        """Next frame, or ``None`` at the end of the stream."""
        raise NotImplementedError


class Stage(_LifeCycle):
    """A per-frame processing step (planes, plane light, transfer, render...)."""

    name = "stage"

    def process(self, frame: Frame) -> Frame:
        raise NotImplementedError


class Sink(_LifeCycle):
    """A consumer of finished frames (video file, PNGs, MJPEG server, session recorder)."""

    name = "sink"

    def write(self, frame: Frame) -> None:
        raise NotImplementedError
