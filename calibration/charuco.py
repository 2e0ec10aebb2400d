"""Finding a ChArUco board in images: corners with their ids, ready for calibration.

This module owns :func:`detect` (one image) and :func:`detect_files` (a set of image files, with
the checks calibration needs: readable files, one image size, the board found). Detection is
OpenCV's ``cv2.aruco.CharucoDetector`` with one addition: markers whose id appears twice (a false
detection in the background, which happens on real images of a board on a monitor) are resolved
by their fit to a board-to-image homography of the unambiguous markers, because OpenCV's corner
interpolation gives up on the whole board when an id is duplicated.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from illuminet.calibration.board import BoardSpec, dictionary_names
from illuminet.calibration.calibfile import CalibrationError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass
class Detection:
    """ChArUco corners found in one image.

    Attributes
    ----------
    image_size : (int, int)
        (width, height) of the image.
    corners : (N, 2) float32
        Sub-pixel image positions of the detected chessboard corners.
    ids : (N,) int32
        Corner ids (index into :meth:`BoardSpec.corner_points`).
    markers : int
        Number of ArUco markers found (after removing duplicates).
    path : str
        Where the image came from ("" for in-memory images).
    """

    image_size: tuple[int, int]
    corners: np.ndarray
    ids: np.ndarray
    markers: int = 0
    path: str = ""
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(len(self.ids))

    def object_points(self, spec: BoardSpec) -> np.ndarray:
        """(N, 3) float32 board coordinates (metres) of the detected corners."""
        return spec.corner_points()[self.ids]


class BoardDetector:
    """A reusable detector for one board (creating OpenCV's detector per image costs time)."""

    def __init__(self, spec: BoardSpec):
        self.spec = spec
        self.board = spec.cv_board()
        params = cv2.aruco.DetectorParameters()
        # sub-pixel marker corners help the homography that seeds corner interpolation
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._aruco = cv2.aruco.ArucoDetector(spec.cv_dictionary(), params)
        self._charuco = cv2.aruco.CharucoDetector(self.board)
        self._board_ids = set(int(i) for i in np.asarray(self.board.getIds()).ravel())
        self._marker_obj = {
            int(i): np.asarray(o, np.float32)[:, :2]
            for i, o in zip(np.asarray(self.board.getIds()).ravel(), self.board.getObjPoints())
        }

    def detect(self, image: np.ndarray, path: str = "") -> Detection:
        """Detect the board in one image (BGR, RGB or grey uint8). Zero corners when not found."""
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise CalibrationError(
                f"{path or 'image'}: expected a uint8 image, got "
                f"{getattr(image, 'shape', type(image))} {getattr(image, 'dtype', '')}"
            )
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        size = (gray.shape[1], gray.shape[0])
        mcorners, mids, _ = self._aruco.detectMarkers(gray)
        notes: list[str] = []
        if mids is None or len(mids) == 0:
            return Detection(size, np.zeros((0, 2), np.float32), np.zeros(0, np.int32), 0, path, notes)
        mids = np.asarray(mids).ravel()
        keep = [k for k, i in enumerate(mids) if int(i) in self._board_ids]
        if len(keep) < len(mids):
            notes.append(f"{len(mids) - len(keep)} marker(s) with ids not on this board ignored")
        mcorners = [mcorners[k] for k in keep]
        mids = mids[keep]
        mcorners, mids, dropped = self._resolve_duplicates(mcorners, mids)
        if dropped:
            notes.append(f"{dropped} duplicate marker detection(s) dropped")
        if len(mids) == 0:
            return Detection(size, np.zeros((0, 2), np.float32), np.zeros(0, np.int32), 0, path, notes)
        cc, ci, _, _ = self._charuco.detectBoard(gray, markerCorners=mcorners, markerIds=mids.reshape(-1, 1))
        if ci is None or len(ci) == 0:
            return Detection(size, np.zeros((0, 2), np.float32), np.zeros(0, np.int32), len(mids), path, notes)
        return Detection(
            size, np.asarray(cc, np.float32).reshape(-1, 2), np.asarray(ci, np.int32).ravel(), len(mids), path, notes
        )

    def _resolve_duplicates(self, corners, ids):
        counts = Counter(int(i) for i in ids)
        dup = {i for i, c in counts.items() if c > 1}
        if not dup:
            return corners, ids, 0
        uniq = [k for k, i in enumerate(ids) if int(i) not in dup]
        best: dict[int, tuple[float, int]] = {}
        if len(uniq) >= 4:
            src = np.concatenate([self._marker_obj[int(ids[k])] for k in uniq])
            dst = np.concatenate([np.asarray(corners[k], np.float32).reshape(4, 2) for k in uniq])
            H, _ = cv2.findHomography(src, dst, cv2.RANSAC, 10.0)
            if H is not None:
                for k, i in enumerate(ids):
                    if int(i) in dup:
                        proj = cv2.perspectiveTransform(self._marker_obj[int(i)].reshape(-1, 1, 2), H).reshape(4, 2)
                        err = float(np.linalg.norm(proj - np.asarray(corners[k]).reshape(4, 2), axis=1).mean())
                        if int(i) not in best or err < best[int(i)][0]:
                            best[int(i)] = (err, k)
        # keep a duplicate only when one candidate clearly fits the board (lens distortion makes a
        # global homography approximate, hence the generous limit relative to the marker size)
        keep = list(uniq)
        for err, k in best.values():
            side = float(np.linalg.norm(np.diff(np.asarray(corners[k]).reshape(4, 2), axis=0), axis=1).mean())
            if err < max(5.0, 0.75 * side):
                keep.append(k)
        keep.sort()
        return [corners[k] for k in keep], ids[keep], len(ids) - len(keep)


def detect(image: np.ndarray, spec: BoardSpec, path: str = "") -> Detection:
    """One-shot :meth:`BoardDetector.detect`."""
    return BoardDetector(spec).detect(image, path)


def list_images(paths: Iterable[str | Path]) -> list[Path]:
    """Expand folders into their image files (sorted); keep files as given. Errors name what is missing."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise CalibrationError(f"{p}: folder has no images ({', '.join(IMAGE_SUFFIXES)})")
            out.extend(files)
        elif p.is_file():
            out.append(p)
        else:
            raise CalibrationError(f"{p}: no such image file or folder")
    return out


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as BGR uint8 (grey files come back as 3 channels), with a clear error."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CalibrationError(f"{path}: cannot read as an image (missing, empty or not an image format)")
    return img


def suggest_dictionary(gray: np.ndarray) -> str | None:
    """When a board is not found: the predefined dictionary that finds the most markers, if any."""
    best, best_n = None, 0
    for name in dictionary_names():
        if not name.endswith("_1000") and name not in ("DICT_ARUCO_ORIGINAL", "DICT_ARUCO_MIP_36h12"):
            continue  # _50/_100/_250 are prefixes of _1000: one per family is enough (AprilTag skipped: slow)
        det = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), cv2.aruco.DetectorParameters()
        )
        _, ids, _ = det.detectMarkers(gray)
        n = 0 if ids is None else len(ids)
        if n > best_n:
            best, best_n = name, n
    return f"{best} ({best_n} markers)" if best else None


def detect_files(
    paths: Sequence[str | Path], spec: BoardSpec, min_corners: int = 6, require_all: bool = False
) -> list[Detection]:
    """Detect the board in image files; returns the usable detections (>= ``min_corners`` corners).

    Raises
    ------
    CalibrationError
        No files; unreadable file; images of different sizes (the message lists them); the board
        not found in any image (the message says which dictionary the markers seem to be from);
        with ``require_all``, any image without the board.
    """
    files = list_images(paths)
    if not files:
        raise CalibrationError("no images given")
    det = BoardDetector(spec)
    dets: list[Detection] = []
    sizes: dict[tuple[int, int], list[str]] = {}
    failed: list[str] = []
    first_gray = None
    for f in files:
        img = read_image(f)
        d = det.detect(img, str(f))
        sizes.setdefault(d.image_size, []).append(f.name)
        for n in d.notes:
            log.info("%s: %s", f, n)
        if len(d) >= min_corners:
            dets.append(d)
        else:
            failed.append(f"{f.name} ({d.markers} markers, {len(d)} corners)")
            if first_gray is None:
                first_gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if len(sizes) > 1:
        listing = "; ".join(f"{w}x{h}: {', '.join(n[:3])}{' ...' if len(n) > 3 else ''}" for (w, h), n in sizes.items())
        raise CalibrationError(f"images have different sizes ({listing}); calibrate one resolution at a time")
    if not dets:
        hint = ""
        if first_gray is not None:
            s = suggest_dictionary(first_gray)
            if s and not s.startswith(spec.dictionary + " "):
                hint = f"; markers were found with {s}: pass --dictionary accordingly"
            elif s:
                hint = "; markers were found but no corners: check --squares, --legacy and the marker/square sizes"
            else:
                hint = "; no ArUco markers at all (blurred, over-exposed, or not a ChArUco board?)"
        raise CalibrationError(
            f"board not found in any of {len(files)} image(s) ({spec.describe()}): "
            + ", ".join(failed[:5])
            + (" ..." if len(failed) > 5 else "")
            + hint
        )
    if failed:
        msg = f"board not found (fewer than {min_corners} corners) in {len(failed)} image(s): " + ", ".join(failed)
        if require_all:
            raise CalibrationError(msg)
        log.warning("%s; they are skipped", msg)
    return dets
