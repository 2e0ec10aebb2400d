"""Image dimensions from a PNG or JPEG header, read before anything is decoded.

A decoder allocates the full image the header claims: a 1 MB PNG that says 20000x20000 costs
OpenCV seconds and gigabytes before the caller can refuse it. The session reader and ``relight``
therefore read the size from the header (PNG ``IHDR``, JPEG ``SOFn``) -- a few bytes -- and refuse
an image of the wrong or an absurd size first. Only the standard library is used.
"""

from __future__ import annotations

import os
import struct

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: JPEG start-of-frame markers (baseline, progressive, lossless, ...); C4 (DHT), C8 (JPG), CC (DAC) are not
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: how much of a file :func:`image_size_of_file` reads: JPEG metadata segments (EXIF, ICC) before the
#: SOF marker are at most 64 KiB each; a header not found in this prefix counts as unknown
HEADER_BYTES = 1 << 20


def image_size(data: bytes | bytearray | memoryview) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG or JPEG header, or ``None`` when ``data`` starts with neither.

    Parameters
    ----------
    data : bytes-like
        The file's bytes (at least its beginning; the whole file is never needed).

    Returns
    -------
    tuple of int or None
        The size the header claims (not checked against the rest of the file), or ``None`` for an
        unknown format or a header cut short.
    """
    b = bytes(data[:HEADER_BYTES])
    if b.startswith(PNG_SIGNATURE):
        # the first chunk must be IHDR: length 13, type, width, height (big-endian)
        if len(b) < 24 or b[12:16] != b"IHDR":
            return None
        w, h = struct.unpack(">II", b[16:24])
        return int(w), int(h)
    if b.startswith(b"\xff\xd8"):
        pos = 2
        while pos + 4 <= len(b):
            if b[pos] != 0xFF:
                return None
            marker = b[pos + 1]
            if marker == 0xFF:  # fill byte
                pos += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
                pos += 2
                continue
            (length,) = struct.unpack(">H", b[pos + 2 : pos + 4])
            if marker in _JPEG_SOF:
                if pos + 9 > len(b):
                    return None
                h, w = struct.unpack(">HH", b[pos + 5 : pos + 9])
                return int(w), int(h)
            if marker == 0xD9 or length < 2:  # end of image before a frame header, or a broken length
                return None
            pos += 2 + length
        return None
    return None


def image_size_of_file(path: str | os.PathLike) -> tuple[int, int] | None:
    """:func:`image_size` of a file's first :data:`HEADER_BYTES` bytes (raises ``OSError`` as ``open``)."""
    with open(path, "rb") as f:
        return image_size(f.read(HEADER_BYTES))


__all__ = ["image_size", "image_size_of_file", "HEADER_BYTES", "PNG_SIGNATURE"]
