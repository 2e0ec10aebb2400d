"""The life cycle shared by every source, stage and sink (after MediaPipe's CalculatorBase), the
declared contracts between stages, and the one policy for a stage whose input is missing.

::

    open() ──▶ process(frame) ... process(frame) ──▶ close()
                one call per frame, timestamps only increase

* ``open`` acquires resources (devices, GL context, ONNX sessions); it may raise with a message
  saying what is missing and how to fix it. Configuration is given to the constructor.
* ``process`` takes a :class:`~illuminet.runtime.frame.Frame` and returns a new frame with the
  stage's results added (``frame.with_result(KEY, value)``); it never changes the input arrays.
  Raising :class:`FrameError` (or any exception) marks *this frame* failed.
* ``close`` releases everything and is safe to call twice, also after a failed ``open``.

**Contracts** (MediaPipe's ``GetContract``, DepthAI's declared node inputs/outputs): each stage
declares the result keys it ``requires`` (must be produced upstream), ``optional`` (read when present)
and ``provides`` (:class:`~illuminet.runtime.scene.ResultKey` objects from
:mod:`illuminet.runtime.scene`). :func:`check_chain` verifies a chain when the pipeline is built: a
key no earlier stage provides is an error naming both stages.

**One policy for failures and missing inputs**, applied by :class:`StageChain` (the loop, relight
and evaluation all run stages through it): a stage that raises on a frame, or whose required input
is absent on that frame (its producer failed and had no earlier result), does not contribute to that
frame; the frame carries the stage's *last good* results instead (the previous lighting rather than
none; a stage with ``hold_last_good = False``, such as the renderer whose output is this frame's
picture, contributes nothing). Each kind of failure or skip is counted and logged once.

Sources produce frames (:meth:`Source.read` returns ``None`` at end of stream); sinks consume them
(:meth:`Sink.write`). All three are context managers.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from illuminet.runtime.frame import Frame
from illuminet.runtime.scene import ResultKey

log = logging.getLogger(__name__)


class FrameError(RuntimeError):
    """Processing one frame failed; the stream can go on."""


class MissingInput(FrameError):
    """A stage was given a frame without a result it requires (see :meth:`Stage.require`)."""


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import PipelineError  # noqa: E402,F401


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


class LogOnce:
    """Logs each kind of problem once per component and counts every occurrence.

    A live stream must survive bad frames without flooding the log: the first occurrence of each
    ``kind`` is logged (warning) with the full message; later ones are only counted (``counts``).
    """

    def __init__(self, logger: logging.Logger, who: str):
        self._log = logger
        self._who = who
        self.counts: dict[str, int] = {}

    def __call__(self, kind: str, message: str) -> None:
        n = self.counts.get(kind, 0)
        self.counts[kind] = n + 1
        if n == 0:
            self._log.warning("%s: %s (logged once; further occurrences are counted in stats)", self._who, message)


class Source(_LifeCycle):
    """A stream of frames.

    Attributes
    ----------
    live : bool
        True for cameras: the loop keeps only the newest frame when it falls behind and the source
        counts what it dropped. False for replay/synthetic in ``asap`` mode: nothing is dropped.
    drop_advice : str
        Logged once by the loop when it first drops a frame of this source (a replay at recorded
        timing says how to keep every frame); empty for cameras, where dropping is the policy.
    """

    name = "source"
    live: bool = False
    drop_advice: str = ""
    #: results the source attaches to its frames (e.g. the synthetic camera's ground truth)
    provides: tuple[ResultKey, ...] = ()

    def read(self) -> Frame | None:
        """Next frame, or ``None`` at the end of the stream."""
        raise NotImplementedError


class Stage(_LifeCycle):
    """A per-frame processing step (planes, anchor, plane light, shading, render...).

    Attributes
    ----------
    requires : tuple of ResultKey
        Results that must be in the frame; :class:`StageChain` skips the stage on a frame without
        them (the policy in the module docstring). An instance may narrow or widen the class value
        in its constructor (e.g. by configuration).
    optional : tuple of ResultKey
        Results read when present; when some stage provides one, it must come earlier.
    provides : tuple of ResultKey
        Results this stage adds.
    hold_last_good : bool
        On a frame where the stage fails or is skipped, carry its last good results (True), or
        nothing (False: results that only make sense for the frame they were computed on).
    thread_bound : bool
        ``process`` must run on the thread that called ``open`` (it holds a GL context). A
        pipelined loop runs such a stage, and every stage after it, on the loop's own thread; the
        stages before it may run on a worker thread, one frame ahead.
    """

    name = "stage"
    requires: tuple[ResultKey, ...] = ()
    optional: tuple[ResultKey, ...] = ()
    provides: tuple[ResultKey, ...] = ()
    hold_last_good: bool = True
    thread_bound: bool = False

    def process(self, frame: Frame) -> Frame:
        raise NotImplementedError

    def require(self, frame: Frame, key: ResultKey) -> Any:
        """``frame``'s result ``key``, or :class:`MissingInput` naming this stage and the key."""
        value = frame.results.get(key.name)
        if value is None:
            raise MissingInput(
                f"stage {self.name!r} needs results[{key.name!r}] ({key.doc}), "
                f"which this frame lacks: put a stage that provides it before {self.name!r}"
            )
        return value


class Sink(_LifeCycle):
    """A consumer of finished frames (video file, PNGs, MJPEG server, session recorder)."""

    name = "sink"

    def write(self, frame: Frame) -> None:
        raise NotImplementedError


# ------------------------------------------------------------------------------------ contracts


def _stage_name(st: Any, default: str) -> str:
    n = getattr(st, "name", None)
    return n if isinstance(n, str) and n else default


def check_chain(stages: Sequence[Stage], source: Source | None = None) -> None:
    """Verify that every stage's ``requires`` (and present ``optional``) keys come from an earlier stage.

    Raises
    ------
    PipelineError
        Naming the consumer, the key, and the stage that provides it too late or that no stage
        provides it at all.
    """
    provided: dict[str, str] = {k.name: "the source" for k in getattr(source, "provides", ())}
    names = [_stage_name(s, f"stage{i}") for i, s in enumerate(stages)]
    for i, st in enumerate(stages):
        for key, needed in [(k, True) for k in getattr(st, "requires", ())] + [
            (k, False) for k in getattr(st, "optional", ())
        ]:
            if key.name in provided:
                continue
            later = [
                names[j]
                for j in range(i + 1, len(stages))
                if any(k.name == key.name for k in getattr(stages[j], "provides", ()))
            ]
            if later:
                raise PipelineError(
                    f"stage {names[i]!r} reads results[{key.name!r}], which stage {later[0]!r} provides only "
                    f"after it: put {later[0]!r} before {names[i]!r}"
                )
            if needed:
                raise PipelineError(
                    f"stage {names[i]!r} requires results[{key.name!r}] ({key.doc}), which no earlier stage "
                    f"provides: add the stage that produces it before {names[i]!r}"
                )
        for key in getattr(st, "provides", ()):
            provided.setdefault(key.name, names[i])


@dataclass
class StageEvent:
    """What happened to one stage on one frame when it did not contribute normally."""

    index: int
    stage: str
    kind: str  # "failed" or "skipped"
    key: str  # "stage:<name>: <ErrorType>" or "stage:<name>: missing <key>"
    error: BaseException | None


class StageChain:
    """Runs stages in order on a frame with the one failure / missing-input policy (module docstring).

    Parameters
    ----------
    stages : sequence of Stage
        Checked with :func:`check_chain` (``check=False`` skips that, for hand-made test chains).
    strict : bool
        Re-raise a stage's exception (tests, ``--strict``); a missing input then raises
        :class:`MissingInput`.
    source : Source, optional
        Its ``provides`` count as available to the first stage.
    """

    def __init__(
        self, stages: Sequence[Stage], *, strict: bool = False, source: Source | None = None, check: bool = True
    ) -> None:
        self.stages = list(stages)
        if check:
            check_chain(self.stages, source)
        self.names = [_stage_name(s, f"stage{i}") for i, s in enumerate(self.stages)]
        self.strict = strict
        self._last_good: list[dict[str, Any]] = [{} for _ in self.stages]
        self._logged: set[str] = set()

    def run(
        self,
        frame: Frame,
        on_time: Callable[[str, float], None] | None = None,
        *,
        start: int = 0,
        stop: int | None = None,
        on_cpu: Callable[[str, float], None] | None = None,
    ) -> tuple[Frame, list[StageEvent]]:
        """All stages on ``frame``; returns the finished frame and the failures/skips (usually none).

        ``on_time(stage_name, seconds)`` is called for every stage that ran (also when it failed), and
        ``on_cpu(stage_name, seconds)`` with the CPU time the calling thread spent in it (wall time
        counts waiting for the GIL and for other threads; thread CPU time does not).
        ``start``/``stop`` run only the stages ``[start:stop]`` (a pipelined loop runs the chain in
        two segments on two threads, each segment on one thread and in frame order, so every
        stage still sees every frame once, in order, with the same policy).
        """
        events: list[StageEvent] = []
        stop = len(self.stages) if stop is None else stop
        for k in range(start, stop):
            st = self.stages[k]
            missing = [key.name for key in getattr(st, "requires", ()) if frame.results.get(key.name) is None]
            if missing:
                if self.strict:
                    st.require(frame, next(key for key in st.requires if key.name in missing))
                events.append(
                    StageEvent(
                        k, self.names[k], "skipped", f"stage:{self.names[k]}: missing {', '.join(missing)}", None
                    )
                )
                frame = self._hold(k, frame)
                continue
            before = frame.results
            t0 = time.perf_counter()
            c0 = time.thread_time() if on_cpu is not None else 0.0
            try:
                out = st.process(frame)
                if not isinstance(out, Frame):
                    raise TypeError(f"process() returned {type(out).__name__}, expected a Frame")
            except Exception as e:
                if on_time is not None:
                    on_time(self.names[k], time.perf_counter() - t0)
                if on_cpu is not None:
                    on_cpu(self.names[k], time.thread_time() - c0)
                if self.strict:
                    raise
                events.append(StageEvent(k, self.names[k], "failed", f"stage:{self.names[k]}: {type(e).__name__}", e))
                frame = self._hold(k, frame)
                continue
            if on_time is not None:
                on_time(self.names[k], time.perf_counter() - t0)
            if on_cpu is not None:
                on_cpu(self.names[k], time.thread_time() - c0)
            self._last_good[k] = {key: v for key, v in out.results.items() if key not in before or before[key] is not v}
            frame = out
        return frame, events

    def _hold(self, k: int, frame: Frame) -> Frame:
        last = self._last_good[k]
        if last and getattr(self.stages[k], "hold_last_good", True):
            return frame.replace(results=MappingProxyType({**frame.results, **last}))
        return frame

    def __call__(self, frame: Frame) -> Frame:
        """Run all stages and log each new kind of failure/skip once (for callers without a loop)."""
        out, events = self.run(frame)
        for ev in events:
            if ev.key not in self._logged:
                self._logged.add(ev.key)
                log.warning(
                    "%s on frame %d%s; the frame goes on with its last good result (logged once)",
                    ev.key,
                    frame.seq,
                    f": {ev.error}" if ev.error is not None else "",
                )
        return out
