"""Small file-reading guards shared by the readers of user files (config, calibration).

A user may name a device or a pipe where a file is expected (``/dev/zero``, a FIFO): a reader must
neither wait for ever nor read until memory runs out.
"""

from __future__ import annotations

from pathlib import Path


class FileTooLarge(ValueError):
    """The file holds more than the reader's limit (``limit`` bytes): not a file of that kind."""

    def __init__(self, path: Path, limit: int):
        super().__init__(f"{path}: larger than {limit >> 20} MiB")
        self.path, self.limit = path, limit


def read_bounded(path: str | Path, limit: int) -> bytes:
    """The bytes of ``path``, at most ``limit`` of them; :class:`FileTooLarge` when there are more.
    ``OSError`` propagates as from ``open``."""
    with open(path, "rb") as f:
        raw = f.read(limit + 1)
    if len(raw) > limit:
        raise FileTooLarge(Path(path), limit)
    return raw
