"""Frame sources, chosen by URL (after pySerial's ``serial_for_url``).

``open_source("replay://runs/s1?timing=asap")`` looks the scheme up in :data:`SCHEMES`, imports
that module of this package by name and calls its ``open_url(url, config)``, which returns an
unopened :class:`~illuminet.runtime.stage.Source`. hw/ is the only place that imports ``depthai``,
``cv2.VideoCapture`` or ``serial``; everything else sees the Source interface.
"""

from __future__ import annotations

import importlib
from urllib.parse import urlsplit

from illuminet.runtime.config import Config, defaults
from illuminet.runtime.stage import Source

#: URL scheme -> module of this package implementing ``open_url(url: str, config: Config) -> Source``
SCHEMES: dict[str, str] = {
    "replay": "replay",
    "synthetic": "synthetic",
    "oakd": "oakd",
    "v4l2": "v4l2",
}


#: spellings accepted for boolean URL query values (``?loop=1``, ``?reconnect=false``)
URL_TRUE = ("1", "true", "yes", "on")
URL_FALSE = ("0", "false", "no", "off")


def url_bool(url: str, key: str, value: str) -> bool:
    """A boolean URL query value; anything else is refused naming the URL, key and value."""
    t = value.lower()
    if t in URL_TRUE:
        return True
    if t in URL_FALSE:
        return False
    raise ValueError(f"{url}: {key}={value!r}: expected 0/1 (or true/false)")


class SourceError(RuntimeError):
    """A source URL cannot be opened; the message says why and what to do."""


def open_source(url: str, config: Config | None = None) -> Source:
    """Create the source for ``url`` (not yet opened; use it as a context manager)."""
    scheme = urlsplit(url).scheme
    if not scheme:
        raise SourceError(
            f"source {url!r} has no scheme; expected one of "
            + ", ".join(f"{s}://" for s in SCHEMES)
        )
    if scheme not in SCHEMES:
        raise SourceError(
            f"unknown source scheme {scheme!r} in {url!r}; expected one of "
            + ", ".join(f"{s}://" for s in SCHEMES)
        )
    module = importlib.import_module(f"{__name__}.{SCHEMES[scheme]}")
    return module.open_url(url, config if config is not None else defaults())
