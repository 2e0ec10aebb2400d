"""ChArUco boards: their description, the OpenCV board object, and printable PNG/PDF files.

This module owns :class:`BoardSpec` (squares, square and marker size, dictionary, legacy layout),
its conversion to ``cv2.aruco.CharucoBoard``, rendering the board at a physical size and DPI
(``CharucoBoard.generateImage``) and a minimal PDF writer that embeds that image at its exact
physical size (a single page, the image stored losslessly with FlateDecode), so that printing at
100 % ("actual size") gives the square size that calibration assumes.

Legacy layout: OpenCV 4.6 changed where the markers sit on boards with an even number of rows
(https://github.com/opencv/opencv/issues/23152). Boards made by older tools (DepthAI's calibration
boards, for instance) need ``legacy=True``; boards printed by ``illuminet calibrate board`` use the
current layout unless told otherwise.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from illuminet.calibration.calibfile import CalibrationError

#: largest board picture :func:`board_image` renders: pixels a side and pixels in all (a 300 dpi A0 poster
#: is 9933 x 14043 px, 139 Mpx); beyond that OpenCV fails to allocate or the machine swaps
MAX_SIDE_PX = 20_000
MAX_PIXELS = 200_000_000
#: highest raster resolution accepted (printers stop at a few thousand dpi)
MAX_DPI = 10_000.0

#: page sizes in millimetres (portrait)
PAGES_MM: dict[str, tuple[float, float]] = {
    "a4": (210.0, 297.0),
    "a3": (297.0, 420.0),
    "letter": (215.9, 279.4),
    "tabloid": (279.4, 431.8),
}


def dictionary_names() -> list[str]:
    """Names of OpenCV's predefined ArUco dictionaries (``DICT_4X4_50`` ...)."""
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board's geometry.

    Parameters
    ----------
    squares_x, squares_y : int
        Number of chessboard squares across and down (at least 3 x 3).
    square_mm : float
        Side of one chessboard square in millimetres (sets the scale of stereo translations).
    marker_mm : float
        Side of the ArUco marker inside a white square, smaller than ``square_mm``.
    dictionary : str
        OpenCV predefined dictionary name, e.g. ``"DICT_4X4_1000"``.
    legacy : bool
        Marker layout of OpenCV < 4.6 (see module docstring).
    aspect : float
        Height / width of one square as actually shown (1 for a print). A board displayed on a
        monitor may be stretched: the charuco_fisheye_rig images show squares 0.972 times as high as
        wide (see docs/calibration.md). Only the corners' board coordinates use it; detection does
        not need it.
    """

    squares_x: int = 11
    squares_y: int = 8
    square_mm: float = 20.0
    marker_mm: float = 15.0
    dictionary: str = "DICT_4X4_1000"
    legacy: bool = False
    aspect: float = 1.0

    def __post_init__(self) -> None:
        if not (0.5 < self.aspect < 2.0):
            raise CalibrationError(f"board: aspect (square height / width) must be in (0.5, 2), got {self.aspect}")
        if self.squares_x < 3 or self.squares_y < 3:
            raise CalibrationError(f"board: expected at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        if not (0 < self.square_mm and math.isfinite(self.square_mm)):
            raise CalibrationError(f"board: square size must be a positive number of mm, got {self.square_mm}")
        if not (0 < self.marker_mm < self.square_mm):
            raise CalibrationError(
                f"board: marker size must be positive and smaller than the square, got marker "
                f"{self.marker_mm} mm, square {self.square_mm} mm"
            )
        if self.dictionary not in dictionary_names():
            raise CalibrationError(
                f"board: unknown dictionary {self.dictionary!r}; expected one of {', '.join(dictionary_names())}"
            )
        need = (self.squares_x * self.squares_y) // 2
        size = _dict_size(self.dictionary)
        if size is not None and need > size:
            raise CalibrationError(
                f"board: {self.squares_x}x{self.squares_y} squares need {need} markers, but "
                f"{self.dictionary} has only {size}; use a larger dictionary"
            )

    @property
    def square_m(self) -> float:
        """Square side in metres (the unit of board coordinates and stereo translations)."""
        return self.square_mm / 1000.0

    @property
    def n_corners(self) -> int:
        """Number of inner chessboard corners (the ChArUco corners)."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Physical (width, height) of the board without margins, mm."""
        return (self.squares_x * self.square_mm, self.squares_y * self.square_mm)

    def cv_dictionary(self):
        """The OpenCV ``aruco.Dictionary`` named by :attr:`dictionary`."""
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board; lengths in metres so that poses and stereo translations come out in metres."""
        b = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_mm / 1000.0, self.cv_dictionary()
        )
        b.setLegacyPattern(bool(self.legacy))
        return b

    def corner_points(self) -> np.ndarray:
        """(n_corners, 3) float32 board coordinates (metres) of the ChArUco corners, index = corner id."""
        pts = np.asarray(self.cv_board().getChessboardCorners(), np.float32).reshape(-1, 3)
        if self.aspect != 1.0:
            pts = pts * np.array([1.0, self.aspect, 1.0], np.float32)
        return pts

    def to_dict(self) -> dict:
        """Plain dict (JSON-ready), the inverse of :meth:`from_dict`."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any, where: str = "board") -> BoardSpec:
        """Board from a dict written by :meth:`to_dict`; keys left out take their defaults.

        Every key's type and range is checked; an unknown key (a typo such as ``square_mn`` would
        otherwise leave the default size in place) and a dict with none of the keys are refused.
        ``where`` (the file name) starts every message of the :class:`CalibrationError` raised.
        """
        fix = "fix it in the file, or write a new one with `illuminet calibrate board`"
        keys = ", ".join(_FIELD_KINDS)
        if not isinstance(d, dict):
            raise CalibrationError(
                f"{where}: expected a JSON object with the board keys ({keys}), got {_show(d)}; {fix}"
            )
        unknown = sorted(str(k) for k in d if k not in _FIELD_KINDS)
        if unknown:
            raise CalibrationError(
                f"{where}: unknown board key(s) {', '.join(map(repr, unknown))}; expected only {keys}; {fix}"
            )
        if not d:
            raise CalibrationError(f"{where}: no board keys; expected some of {keys}; {fix}")
        kw: dict[str, Any] = {}
        for k, v in d.items():
            kind, what = _FIELD_KINDS[k]
            if kind is int and isinstance(v, float) and v.is_integer():
                v = int(v)  # 9.0 from a JSON writer that prints every number as a float
            ok = isinstance(v, kind) if kind is bool else isinstance(v, kind) and not isinstance(v, bool)
            if not ok:
                raise CalibrationError(f"{where}: board.{k}: expected {what}, got {_show(v)}; {fix}")
            kw[k] = float(v) if isinstance(kind, tuple) else v  # square_mm 20 -> 20.0, as to_dict writes
        try:
            return cls(**kw)
        except CalibrationError as e:  # a range check of __post_init__ ("board: ..."): name the file too
            raise CalibrationError(f"{where}: {e}; {fix}") from None

    def describe(self) -> str:
        """One line for messages: squares, sizes, dictionary, layout."""
        return (
            f"ChArUco {self.squares_x}x{self.squares_y} squares of {self.square_mm:g} mm, markers "
            f"{self.marker_mm:g} mm, {self.dictionary}{' (legacy layout)' if self.legacy else ''}"
            f"{f', aspect {self.aspect:g}' if self.aspect != 1.0 else ''}"
        )


#: the keys of a board description: (type, what a message says is expected)
_FIELD_KINDS: dict[str, tuple[Any, str]] = {
    "squares_x": (int, "a whole number of squares across, at least 3"),
    "squares_y": (int, "a whole number of squares down, at least 3"),
    "square_mm": ((int, float), "a square side in mm, a number above 0"),
    "marker_mm": ((int, float), "a marker side in mm, a number above 0 and below square_mm"),
    "dictionary": (str, 'an OpenCV ArUco dictionary name such as "DICT_4X4_1000"'),
    "legacy": (bool, "true or false"),
    "aspect": ((int, float), "a square height/width, a number in (0.5, 2)"),
}


def _show(v: Any) -> str:
    text = repr(v)
    return f"{type(v).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def _dict_size(name: str) -> int | None:
    tail = name.rsplit("_", 1)[-1]
    if tail.isdigit():
        return int(tail)
    try:  # DICT_ARUCO_ORIGINAL, DICT_APRILTAG_36h11 ...: the size is not in the name
        return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0])
    except (AttributeError, cv2.error):
        return None


def board_image(spec: BoardSpec, dpi: float = 300.0, margin_mm: float = 0.0) -> np.ndarray:
    """The board rendered for printing: uint8 greyscale, each square an integer number of pixels.

    The pixel size of one square is ``round(square_mm * dpi / 25.4)``; the physical size is then
    restored exactly by the PDF writer (the image is placed at ``size_mm``), so rounding only
    resamples, never changes the printed square size.
    """
    if not (0 < dpi <= MAX_DPI):  # also refuses nan
        raise CalibrationError(f"board: --dpi must be a number in (0, {MAX_DPI:g}], got {dpi}")
    sq_px = int(round(spec.square_mm * dpi / 25.4))
    if sq_px < 8:
        raise CalibrationError(
            f"board: {spec.square_mm} mm squares at {dpi} dpi are only {sq_px} px: markers would be "
            "unreadable; raise --dpi or the square size"
        )
    margin_px = int(round(margin_mm * dpi / 25.4))
    w, h = spec.squares_x * sq_px + 2 * margin_px, spec.squares_y * sq_px + 2 * margin_px
    if max(w, h) > MAX_SIDE_PX or w * h > MAX_PIXELS:
        raise CalibrationError(
            f"board: {spec.size_mm[0]:g} x {spec.size_mm[1]:g} mm at {dpi:g} dpi would be a {w}x{h} px picture, "
            f"more than {MAX_SIDE_PX} px a side or {MAX_PIXELS / 1e6:g} Mpx; lower --dpi, --square-mm or --squares"
        )
    img = spec.cv_board().generateImage((w, h), marginSize=margin_px, borderBits=1)
    return img


def write_png(path: str | Path, img: np.ndarray, dpi: float) -> Path:
    """Write the board PNG with its DPI recorded in a pHYs chunk (so viewers print it at size)."""
    path = Path(path)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise CalibrationError(f"{path}: PNG encoding failed")
    data = bytes(buf)
    # insert pHYs (pixels per metre) right after IHDR: 8-byte signature + 25-byte IHDR chunk
    ppm = int(round(dpi / 0.0254))
    body = b"pHYs" + ppm.to_bytes(4, "big") * 2 + b"\x01"
    chunk = (9).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")
    data = data[:33] + chunk + data[33:]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def write_pdf(
    path: str | Path, img: np.ndarray, size_mm: tuple[float, float], page: str = "a4", caption: str = ""
) -> Path:
    """Write a one-page PDF with ``img`` (uint8 grey) placed centred at exactly ``size_mm``.

    Parameters
    ----------
    page : str
        A key of :data:`PAGES_MM` (portrait or landscape is chosen to fit), or ``"fit"`` for a page
        of the image size plus 10 mm margins.
    caption : str
        One line printed under the board (board parameters), ASCII.
    """
    path = Path(path)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise CalibrationError("write_pdf: expected a uint8 greyscale image")
    bw, bh = size_mm
    if page == "fit":
        pw, ph = bw + 20.0, bh + 30.0
    else:
        if page not in PAGES_MM:
            raise CalibrationError(f"board: unknown page {page!r}; expected one of {', '.join(PAGES_MM)} or 'fit'")
        pw, ph = PAGES_MM[page]
        if bw > bh:  # landscape board on a landscape page
            pw, ph = ph, pw
        if bw > pw - 10 or bh > ph - 20:
            raise CalibrationError(
                f"board: {bw:g} x {bh:g} mm does not fit on {page} ({pw:g} x {ph:g} mm with margins); "
                "use smaller squares, a larger --page, or --page fit"
            )
    pt = 72.0 / 25.4
    W, H = pw * pt, ph * pt
    iw, ih = bw * pt, bh * pt
    x0, y0 = (W - iw) / 2, (H - ih) / 2 + 5 * pt
    h, w = img.shape
    img_data = zlib.compress(np.ascontiguousarray(img).tobytes(), 9)
    text = caption.encode("ascii", "replace").replace(b"\\", b"\\\\").replace(b"(", b"\\(").replace(b")", b"\\)")
    content = (
        (f"q {iw:.4f} 0 0 {ih:.4f} {x0:.4f} {y0:.4f} cm /Im0 Do Q\nBT /F1 9 Tf {x0:.4f} {y0 - 14:.4f} Td (").encode()
        + text
        + b") Tj ET\n"
    )
    objs = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (
            f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {W:.4f} {H:.4f}] "
            f"/Resources << /XObject << /Im0 4 0 R >> /Font << /F1 6 0 R >> >> /Contents 5 0 R >>"
        ).encode(),
        (
            f"<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray "
            f"/BitsPerComponent 8 /Filter /FlateDecode /Interpolate false /Length {len(img_data)} >>\nstream\n"
        ).encode()
        + img_data
        + b"\nendstream",
        f"<< /Length {len(content)} >>\nstream\n".encode() + content + b"endstream",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica >>",
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objs, start=1):
        offsets.append(len(out))
        out += f"{i} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objs) + 1}\n0000000000 65535 f \n".encode()
    for off in offsets:
        out += f"{off:010d} 00000 n \n".encode()
    out += f"trailer\n<< /Size {len(objs) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(out))
    return path
