"""The error hierarchy: every mistake or failure a user can meet derives from :class:`IllumiNetError`.

``illuminet.cli.main`` catches :class:`IllumiNetError` at the top and prints its message as one line
(what, where, the fix) with :attr:`IllumiNetError.exit_code` as the exit status: 2 for usage and
configuration mistakes, 1 for failures at run time (a device lost, an output that cannot be
written). ``--log-level debug`` prints the traceback as well.

Each area keeps its own subclass, defined here so that the floor (runtime/) and every package above it
share one base; the modules that raise them re-export them under their historical import paths
(``illuminet.runtime.config.ConfigError``, ``illuminet.hw.SourceError``, ...). The subclasses also
derive from the built-in exception they replaced (``ValueError`` or ``RuntimeError``), so code that
catches those keeps working.
"""

from __future__ import annotations

#: exit status of a usage or configuration mistake (as argparse uses for a bad flag)
EXIT_USAGE = 2
#: exit status of a failure at run time
EXIT_RUNTIME = 1


class IllumiNetError(Exception):
    """Base of every error the command line reports as one line.

    Parameters
    ----------
    message : str
        One line: what went wrong, where (key, URL, file) and the fix.
    exit_code : int, optional
        Overrides the class's :attr:`exit_code` (e.g. a source error caused by a malformed URL is a
        usage mistake, exit 2, while the same class raised for a lost device is exit 1).
    """

    #: exit status the command line returns for this error
    exit_code: int = EXIT_RUNTIME

    def __init__(self, *args, exit_code: int | None = None):
        super().__init__(*args)
        if exit_code is not None:
            self.exit_code = exit_code

    def one_line(self) -> str:
        """The message with line breaks folded, as the command line prints it."""
        return " ".join(str(self).split())


class ConfigError(IllumiNetError, ValueError):
    """A configuration file, override or flag is invalid; the message names the key and what was expected."""

    exit_code = EXIT_USAGE


class OutputPathError(IllumiNetError, ValueError):
    """An output path (video, PNG folder, statistics, estimates) cannot be written; checked before a run starts."""

    exit_code = EXIT_USAGE


class SourceError(IllumiNetError, RuntimeError):
    """A frame source cannot be opened or failed while running; the message says why and what to do."""


class SourceURLError(SourceError, ValueError):
    """A source URL is malformed (unknown scheme, scene or parameter, a value out of range)."""

    exit_code = EXIT_USAGE


class SessionError(IllumiNetError, ValueError):
    """A recorded session folder is unreadable, or cannot be created."""


class BundleError(IllumiNetError, ValueError):
    """An object bundle is missing or malformed."""

    exit_code = EXIT_USAGE


class ObjectLoadError(IllumiNetError, ValueError):
    """A mesh file cannot be read as an object."""

    exit_code = EXIT_USAGE


class GLError(IllumiNetError, RuntimeError):
    """No OpenGL context could be created (no EGL, no display, no GPU driver)."""


class SinkError(IllumiNetError, RuntimeError):
    """An output (video, PNG folder, server, recording) failed."""


class OutputClosed(SinkError):
    """The reader of an output has gone for good (``--estimates -`` piped into ``head``): the run ends,
    as a Unix filter does when its reader leaves, instead of failing every frame for ever."""


class PipelineError(IllumiNetError, ValueError):
    """The stages do not fit together (a required result nobody provides)."""


class JobError(IllumiNetError, RuntimeError):
    """An offline job run as shards (``--ray``: datagen, catalogue training, evaluation sweeps): shards
    that failed after their retries (exit 1); Ray not installed, a shard folder of another job or a bad
    ``--ray-*`` value are usage mistakes (raised with ``exit_code=2``)."""


__all__ = [
    "EXIT_USAGE",
    "EXIT_RUNTIME",
    "IllumiNetError",
    "ConfigError",
    "OutputPathError",
    "SourceError",
    "SourceURLError",
    "SessionError",
    "BundleError",
    "ObjectLoadError",
    "GLError",
    "SinkError",
    "PipelineError",
    "JobError",
]
