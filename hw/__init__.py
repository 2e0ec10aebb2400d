"""Frame sources, chosen by URL (after pySerial's ``serial_for_url``).

``open_source("replay://runs/s1?timing=asap")`` looks the scheme up in :data:`SCHEMES`, imports
that module of this package by name and calls its ``open_url(url, config)``, which returns an
unopened :class:`~illuminet.runtime.stage.Source`. hw/ is the only place that imports ``depthai``,
``cv2.VideoCapture`` or ``serial``; everything else sees the Source interface.
"""

from __future__ import annotations

import importlib
import math
import re
from collections.abc import Callable, Mapping
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from illuminet.runtime.config import Config, defaults
from illuminet.runtime.errors import EXIT_USAGE, IllumiNetError, SourceError, SourceURLError
from illuminet.runtime.stage import Source

#: URL scheme -> module of this package implementing ``open_url(url: str, config: Config) -> Source``
SCHEMES: dict[str, str] = {
    "replay": "replay",
    "synthetic": "synthetic",
    "oakd": "oakd",
    "v4l2": "v4l2",
}


# ------------------------------------------------------------------------------- URL queries
# Every source parses its ``?key=value&...`` with :func:`parse_query` and the value parsers below,
# so keys, spellings and error messages are the same for all of them.

#: spellings accepted for boolean URL query values (``?loop=1``, ``?reconnect=false``)
URL_TRUE = ("1", "true", "yes", "on")
URL_FALSE = ("0", "false", "no", "off")


def parse_query(
    url: str, parsers: Mapping[str, Callable[[str], Any]], error: Callable[[str], Exception] = SourceURLError
) -> dict[str, Any]:
    """The query of a source URL as ``{key: parsed value}``, for the keys present.

    Parameters
    ----------
    url : str
        The whole URL (named in every message).
    parsers : mapping
        Every key the source knows -> a function parsing its value, raising ``ValueError("expected
        ...")`` for a bad one (:func:`query_bool`, :func:`query_int`, :func:`query_float`,
        :func:`query_size`, :func:`query_choice`, ``str``).
    error : exception class
        What to raise (the source's own error type). An :class:`IllumiNetError` gets exit status 2: a
        malformed URL is a usage mistake.

    Raises
    ------
    error
        ``URL: unknown parameter 'KEY'; known: ...`` or ``URL: KEY='VALUE': expected ...``.
    """
    out: dict[str, Any] = {}
    for key, value in parse_qsl(urlsplit(url).query, keep_blank_values=True):
        parse = parsers.get(key)
        if parse is None:
            raise _usage(error(f"{url}: unknown parameter {key!r}; known: {', '.join(parsers)}"))
        try:
            out[key] = parse(value)  # a repeated key: the last one wins
        except ValueError as e:
            raise _usage(error(f"{url}: {key}={value!r}: {e}")) from None
    return out


def _usage(exc: Exception) -> Exception:
    """``exc`` marked as a usage mistake (exit status 2) when it is one of this project's errors."""
    if isinstance(exc, IllumiNetError):
        exc.exit_code = EXIT_USAGE
    return exc


def query_bool(value: str) -> bool:
    """``1/true/yes/on`` or ``0/false/no/off`` (any case)."""
    t = value.strip().lower()
    if t in URL_TRUE:
        return True
    if t in URL_FALSE:
        return False
    raise ValueError("expected 0/1 (or true/false, yes/no, on/off)")


def _range_text(lo, hi) -> str:
    if lo is not None and hi is not None:
        return f" in {lo}..{hi}"
    if lo is not None:
        return f" >= {lo}"
    return f" <= {hi}" if hi is not None else ""


def query_int(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """A parser of integers in ``[lo, hi]`` (either bound optional)."""

    def parse(value: str) -> int:
        try:
            v = int(value)
        except ValueError:
            raise ValueError(f"expected an integer{_range_text(lo, hi)}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ValueError(f"expected an integer{_range_text(lo, hi)}")
        return v

    return parse


def query_float(value: str) -> float:
    """A finite number."""
    try:
        v = float(value)
    except ValueError:
        raise ValueError("expected a number") from None
    if not math.isfinite(v):
        raise ValueError("expected a finite number")
    return v


def query_size(lo: int = 1, hi: int | None = None, even: bool = False) -> Callable[[str], tuple[int, int]]:
    """A parser of ``WIDTHxHEIGHT`` with each side in ``[lo, hi]`` (and even, when asked)."""

    def parse(value: str) -> tuple[int, int]:
        m = re.fullmatch(r"\s*(\d+)\s*x\s*(\d+)\s*", value.lower())
        if not m:
            raise ValueError("expected WIDTHxHEIGHT, e.g. 640x400")
        w, h = int(m.group(1)), int(m.group(2))
        if w < lo or h < lo or (hi is not None and (w > hi or h > hi)) or (even and (w % 2 or h % 2)):
            raise ValueError("expected WIDTHxHEIGHT with " + ("even " if even else "") + f"sides{_range_text(lo, hi)}")
        return w, h

    return parse


def query_choice(*choices: str, lower: bool = False) -> Callable[[str], str]:
    """A parser accepting one of ``choices`` (case-insensitive with ``lower=True``, returned lower-case)."""

    def parse(value: str) -> str:
        v = value.lower() if lower else value
        if v not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}")
        return v

    return parse


def open_source(url: str, config: Config | None = None) -> Source:
    """Create the source for ``url`` (not yet opened; use it as a context manager)."""
    try:
        scheme = urlsplit(url).scheme
    except ValueError as e:  # "Invalid IPv6 URL": an unbalanced '[' in the host part
        raise SourceURLError(f"source {url!r} is not a URL: {e}") from None
    if not scheme:
        raise SourceURLError(f"source {url!r} has no scheme; expected one of " + ", ".join(f"{s}://" for s in SCHEMES))
    if scheme not in SCHEMES:
        raise SourceURLError(
            f"unknown source scheme {scheme!r} in {url!r}; expected one of " + ", ".join(f"{s}://" for s in SCHEMES)
        )
    try:
        module = importlib.import_module(f"{__name__}.{SCHEMES[scheme]}")
    except ModuleNotFoundError as e:  # e.g. oakd:// without the depthai package installed
        raise SourceError(
            f"source {url!r} needs the Python package {e.name!r}, which is not installed (pip install {e.name})"
        ) from e
    try:
        return module.open_url(url, config if config is not None else defaults())
    except IllumiNetError:
        raise
    except ValueError as e:
        # the sources' own checks of a URL's values raise ValueError("URL: key=value: expected ...")
        raise SourceURLError(str(e)) from e
