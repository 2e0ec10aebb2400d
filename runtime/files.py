"""Small file guards shared by the readers and writers of user files.

A user may name a device or a pipe where a file is expected (``/dev/zero``, a FIFO): a reader must
neither wait for ever nor read until memory runs out (:func:`read_bounded`). An output written in
place and cut short (a kill, a full disk) replaces the previous file with half of one: writers write
beside it and move the result into place (:func:`written_whole`).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
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


@contextlib.contextmanager
def written_whole(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary name beside ``path`` (hidden, same suffix: an encoder picks its format by it) to write
    in the block; moved onto ``path`` when the block ends, removed when it raises. A reader sees the old
    file or the new one, never half of one; a failed write leaves nothing behind. (No fsync: the
    session recorder and the cluster's shard store sync theirs.)"""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
