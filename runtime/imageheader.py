"""Image dimensions from an image file's header, read before anything is decoded.

A decoder allocates the full image the header claims: a 1 MB PNG that says 20000x20000 costs
OpenCV seconds and gigabytes before the caller can refuse it. The session reader and ``relight``
therefore read the size from the header (PNG ``IHDR``, JPEG ``SOFn``; for ``relight`` also the other
formats OpenCV decodes: BMP, TIFF, WebP, GIF, PNM/PFM, Sun raster, JPEG 2000, Radiance HDR) -- a few
bytes -- and refuse an image of the wrong or an absurd size first. Only the standard library is used.
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
    """``(width, height)`` from a PNG or JPEG header, or ``None`` when ``data`` starts with neither (the
    session reader's frames are PNG or JPEG; :func:`image_size_of_file` reads the other formats too).

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


def _other_size(b: bytes, read_at) -> tuple[int, int] | None:
    """The size in a BMP, TIFF, WebP, GIF, PNM/PFM, Sun raster, JPEG 2000 or Radiance HDR header (a 3 MB
    run-length BMP or a 1 MB deflated TIFF said 20000x20000: 2.4 GB and 20 s in OpenCV before relight refused
    it); ``read_at(offset, n)`` reads the file beyond ``b`` (a TIFF's directory may lie at its end)."""
    try:
        if b.startswith(b"BM") and len(b) >= 26:
            if struct.unpack_from("<I", b, 14)[0] == 12:  # BITMAPCOREHEADER: 16-bit sizes
                w, h = struct.unpack_from("<HH", b, 18)
            else:
                w, h = struct.unpack_from("<ii", b, 18)
            return abs(int(w)), abs(int(h))
        if b[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            return _tiff_size(b[:2] == b"II", b[2:4] in (b"+\x00", b"\x00+"), read_at)
        if b.startswith(b"RIFF") and b[8:12] == b"WEBP" and len(b) >= 30:
            kind = b[12:16]
            if kind == b"VP8 ":
                w, h = struct.unpack_from("<HH", b, 26)
                return w & 0x3FFF, h & 0x3FFF
            if kind == b"VP8L":
                bits = struct.unpack_from("<I", b, 21)[0]
                return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
            if kind == b"VP8X":
                return int.from_bytes(b[24:27], "little") + 1, int.from_bytes(b[27:30], "little") + 1
            return None
        if b[:6] in (b"GIF87a", b"GIF89a") and len(b) >= 10:
            return struct.unpack_from("<HH", b, 6)
        if len(b) >= 2 and b[0:1] == b"P" and b[1:2] in b"123456Ff":
            return _pnm_size(b)
        if b.startswith(b"\x59\xa6\x6a\x95") and len(b) >= 12:  # Sun raster
            return struct.unpack_from(">II", b, 4)
        if b.startswith(b"\x00\x00\x00\x0cjP  \r\n\x87\n"):  # JPEG 2000 (JP2): the ihdr box, height first
            i = b.find(b"ihdr")
            return struct.unpack_from(">II", b, i + 4)[::-1] if i > 0 else None
        if b.startswith(b"\xff\x4f\xff\x51") and len(b) >= 24:  # JPEG 2000 codestream: SIZ, minus the offsets
            xs, ys, xo, yo = struct.unpack_from(">IIII", b, 8)
            return xs - xo, ys - yo
        if b.startswith((b"#?RADIANCE", b"#?RGBE")):
            end = b.find(b"\n\n")
            line = b[end + 2 : b.find(b"\n", end + 2)].split() if end >= 0 else []
            if len(line) == 4 and line[0][1:] in (b"Y", b"X") and line[2][1:] in (b"X", b"Y"):
                a, c = int(line[1]), int(line[3])
                return (c, a) if line[0][1:] == b"Y" else (a, c)
    except (struct.error, KeyError, ValueError, OverflowError):
        return None
    return None


def _pnm_size(b: bytes) -> tuple[int, int] | None:
    """Width and height, the first two numbers after a PNM/PFM magic (``#`` comments skipped)."""
    nums: list[int] = []
    for line in b[2:4096].split(b"\n"):
        for tok in line.split(b"#", 1)[0].split():
            nums.append(int(tok))
            if len(nums) == 2:
                return nums[0], nums[1]
    return None


def _tiff_size(little: bool, big: bool, read_at) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) of a TIFF's (or BigTIFF's) first directory."""
    e = "<" if little else ">"
    if big:
        (ifd,) = struct.unpack(e + "Q", read_at(8, 8))
        (n,) = struct.unpack(e + "Q", read_at(ifd, 8))
        entries, size, at = read_at(ifd + 8, 20 * min(n, 4096)), 20, 12
    else:
        (ifd,) = struct.unpack(e + "I", read_at(4, 4))
        (n,) = struct.unpack(e + "H", read_at(ifd, 2))
        entries, size, at = read_at(ifd + 2, 12 * min(n, 4096)), 12, 8
    dims = {}
    for i in range(0, len(entries) - size + 1, size):
        tag, typ = struct.unpack_from(e + "HH", entries, i)
        if tag in (256, 257):
            dims[tag] = struct.unpack_from(e + {3: "H", 4: "I", 16: "Q"}[typ], entries, i + at)[0]
    return (int(dims[256]), int(dims[257])) if len(dims) == 2 else None


def image_size_of_file(path: str | os.PathLike) -> tuple[int, int] | None:
    """The size in a file's header: PNG or JPEG (:func:`image_size` of its first :data:`HEADER_BYTES`
    bytes), or BMP, TIFF (its directory read where it lies), WebP, GIF, PNM/PFM, Sun raster, JPEG 2000,
    Radiance HDR; ``None`` for another format. Raises ``OSError`` as ``open``."""
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)

        def read_at(offset: int, n: int) -> bytes:
            f.seek(offset)
            return f.read(n)

        return image_size(head) or _other_size(head, read_at)


__all__ = ["image_size", "image_size_of_file", "HEADER_BYTES", "PNG_SIGNATURE"]
