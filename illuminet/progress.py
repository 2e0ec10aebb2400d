"""The live one-line status of ``illuminet run / replay / record / demo`` on a terminal, and of the
offline jobs run as shards on Ray (``datagen / train --objects / eval --ray``).

What this module owns: :class:`StatusLine`, fed by the streaming loop's ``on_stats`` callback
(:meth:`~illuminet.runtime.stream.loop.LoopStats.snapshot` every half second), which redraws one line
on standard error -- frames, fps, drops, failed frames, sink failures, elapsed time; with
``formatter=``:func:`format_job` the same line shows a job's shards (:mod:`illuminet.cluster`). It draws only
when standard error is a terminal (``TERM`` not ``dumb``): piped or redirected output stays exactly
as before (the end-of-run table only). Log records printed while the line is shown first clear it,
so messages never end up glued to the status.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any, TextIO


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty() and os.environ.get("TERM", "") != "dumb"
    except (AttributeError, ValueError):  # closed or not a real stream
        return False


class StatusLine:
    """One status line, redrawn in place (``\\r`` + erase to the end of the line).

    Parameters
    ----------
    stream : text stream
        Default standard error.
    enabled : bool, optional
        Default: only when ``stream`` is a terminal.
    formatter : callable, optional
        ``formatter(snap) -> str``; default :meth:`format` (the streaming loop's snapshot).

    Use as the loop's ``on_stats`` callback and :meth:`close` it before printing anything else::

        status = StatusLine()
        try:
            run_loop(..., on_stats=status.update, stats_interval_s=0.5)
        finally:
            status.close()
    """

    def __init__(self, stream: TextIO | None = None, enabled: bool | None = None, formatter=None):
        self.stream = stream if stream is not None else sys.stderr
        if formatter is not None:
            self.format = formatter  # e.g. format_job: the line of a sharded job
        self.enabled = _is_terminal(self.stream) if enabled is None else bool(enabled)
        self._shown = False
        self._filter: logging.Filter | None = None
        if self.enabled:
            line = self

            class _ClearFirst(logging.Filter):
                def filter(self, record: logging.LogRecord) -> bool:
                    line.clear()  # the record is printed on a clean line; the next update redraws
                    return True

            self._filter = _ClearFirst()
            for h in logging.getLogger().handlers:
                h.addFilter(self._filter)

    @staticmethod
    def format(snap: dict[str, Any]) -> str:
        """The line for one :meth:`LoopStats.snapshot`."""
        fps = snap.get("fps_recent") or snap.get("fps") or 0.0
        parts = [
            f"frames {snap.get('frames', 0)}",
            f"{fps:.1f} fps",
            f"dropped {snap.get('dropped', 0)}",
            f"failed {snap.get('failed_frames', 0)}",
        ]
        if snap.get("sink_failures"):
            parts.append(f"sink failures {snap['sink_failures']}")
        parts.append(f"{snap.get('elapsed_s', 0.0):.1f} s")
        return "  ".join(parts)

    def update(self, snap: dict[str, Any]) -> None:
        """Redraw the line (a no-op when disabled)."""
        if not self.enabled:
            return
        try:
            self.stream.write("\r" + self.format(snap) + "\x1b[K")
            self.stream.flush()
            self._shown = True
        except (OSError, ValueError):  # the terminal went away: stop drawing, never fail the run
            self.enabled = False

    def clear(self) -> None:
        """Erase the line (before other output)."""
        if self._shown:
            try:
                self.stream.write("\r\x1b[K")
                self.stream.flush()
            except (OSError, ValueError):
                self.enabled = False
            self._shown = False

    def close(self) -> None:
        """Erase the line and stop clearing before log records. Idempotent."""
        self.clear()
        if self._filter is not None:
            for h in logging.getLogger().handlers:
                h.removeFilter(self._filter)
            self._filter = None


def format_job(snap: dict[str, Any]) -> str:
    """The line of a job run as shards: ``name: finished/total shards, running, failed, retried, items,
    elapsed`` (the snapshot :func:`illuminet.cluster.run_shards` makes after every event)."""
    return "  ".join(
        [
            f"{snap['name']}: {snap['finished']}/{snap['total']} shards",
            f"{snap['running']} running",
            f"{snap['failed']} failed",
            f"{snap['retried']} retried",
            f"{snap['items']} {snap['unit']}s",
            f"{snap['elapsed_s']:.1f} s",
        ]
    )
