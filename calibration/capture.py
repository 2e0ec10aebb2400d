"""Collecting calibration views from a live source: keep only views that add something new.

This module owns :class:`ViewSelector` (accepts a detection when the board is sharp, large enough
and in a pose unlike the views already kept, and tracks which parts of the image the kept corners
cover) and :func:`capture_views`, the loop that reads frames from any
:class:`~illuminet.runtime.stage.Source` (the command line opens it with
``illuminet.hw.open_source``; calibration/ does not import hw/), detects the board, saves accepted
views as PNG files and reports coverage.

Pose diversity without intrinsics: a view is described by where the board's four outer corners
land in the image (through the board-to-image homography of its detected corners), in units of the
image diagonal. That single 8-vector changes with position, distance, in-plane rotation and tilt,
so "far from every kept view" means "a new pose".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from illuminet.calibration.board import BoardSpec
from illuminet.calibration.calibfile import CalibrationError
from illuminet.calibration.charuco import BoardDetector, Detection
from illuminet.runtime.stage import Source

log = logging.getLogger(__name__)


@dataclass
class Verdict:
    """Whether a view was kept, and why (shown to the person moving the board)."""

    accepted: bool
    reason: str
    novelty: float = 0.0


@dataclass
class ViewSelector:
    """Chooses diverse, sharp views and tracks image coverage.

    Parameters
    ----------
    spec : BoardSpec
    image_size : (int, int)
    min_corners : int
        Fewest corners for a view to count.
    min_novelty : float
        Smallest pose change (mean outer-corner displacement / image diagonal) from every kept view.
    min_sharpness : float
        Smallest variance of the Laplacian inside the board's bounding box (motion blur rejects).
    grid : (int, int)
        Coverage cells across and down.
    """

    spec: BoardSpec
    image_size: tuple[int, int]
    min_corners: int = 12
    min_novelty: float = 0.08
    min_sharpness: float = 15.0
    grid: tuple[int, int] = (8, 5)
    descriptors: list[np.ndarray] = field(default_factory=list)
    covered: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.covered = np.zeros((self.grid[1], self.grid[0]), np.int32)
        pts = self.spec.corner_points()
        w = float(self.spec.squares_x * self.spec.square_m)
        h = float(self.spec.squares_y * self.spec.square_m * self.spec.aspect)
        self._outer = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float32).reshape(-1, 1, 2)
        self._pts = pts

    def descriptor(self, det: Detection) -> np.ndarray | None:
        """Outer board corners in the image / image diagonal (8 numbers), or None if degenerate."""
        if len(det) < 4:
            return None
        H, _ = cv2.findHomography(self._pts[det.ids][:, :2], det.corners, 0)
        if H is None:
            return None
        out = cv2.perspectiveTransform(self._outer, H).reshape(-1)
        return out / float(np.hypot(*self.image_size))

    def consider(self, det: Detection, gray: np.ndarray) -> Verdict:
        """Decide about one detection; on acceptance, remember it and update coverage."""
        if det.image_size != tuple(self.image_size):
            return Verdict(False, f"image size {det.image_size} differs from {self.image_size}")
        if len(det) < self.min_corners:
            return Verdict(False, f"board not found ({len(det)} corners)" if len(det) else "no board")
        x0, y0 = np.floor(det.corners.min(axis=0)).astype(int)
        x1, y1 = np.ceil(det.corners.max(axis=0)).astype(int)
        roi = gray[max(0, y0) : y1 + 1, max(0, x0) : x1 + 1]
        sharp = float(cv2.Laplacian(roi, cv2.CV_32F).var()) if roi.size else 0.0
        if sharp < self.min_sharpness:
            return Verdict(False, f"blurred (sharpness {sharp:.0f} < {self.min_sharpness:.0f}): hold still")
        d = self.descriptor(det)
        if d is None:
            return Verdict(False, "degenerate view")
        nov = min(
            (float(np.mean(np.linalg.norm((d - k).reshape(4, 2), axis=1))) for k in self.descriptors), default=1.0
        )
        if nov < self.min_novelty:
            return Verdict(
                False,
                f"too similar to a kept view (change {nov:.2f} < {self.min_novelty:.2f}): move or tilt the board",
                nov,
            )
        self.descriptors.append(d)
        gx = np.clip((det.corners[:, 0] / self.image_size[0] * self.grid[0]).astype(int), 0, self.grid[0] - 1)
        gy = np.clip((det.corners[:, 1] / self.image_size[1] * self.grid[1]).astype(int), 0, self.grid[1] - 1)
        np.add.at(self.covered, (gy, gx), 1)
        return Verdict(True, "kept", nov)

    @property
    def coverage(self) -> float:
        """Fraction of grid cells with at least one kept corner."""
        return float((self.covered > 0).mean())

    def coverage_text(self) -> str:
        """The coverage grid as text: '#' covered, '.' not yet."""
        return "\n".join("".join("#" if c else "." for c in row) for row in self.covered)

    def coverage_image(self, base: np.ndarray | None = None) -> np.ndarray:
        """BGR picture of the coverage: covered cells tinted green over ``base`` (or grey)."""
        w, h = self.image_size
        img = np.full((h, w, 3), 64, np.uint8) if base is None else base.copy()
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        gx, gy = self.grid
        for j in range(gy):
            for i in range(gx):
                x0, x1 = i * w // gx, (i + 1) * w // gx
                y0, y1 = j * h // gy, (j + 1) * h // gy
                tint = (0, 160, 0) if self.covered[j, i] else (0, 0, 160)
                img[y0:y1, x0:x1] = (0.6 * img[y0:y1, x0:x1] + 0.4 * np.array(tint)).astype(np.uint8)
                cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (255, 255, 255), 1)
        return img


@dataclass
class CaptureResult:
    """What :func:`capture_views` kept."""

    files: list[Path]
    frames_read: int
    coverage: float
    coverage_text: str


def _split(color_rgb: np.ndarray, split: str) -> list[np.ndarray]:
    bgr = cv2.cvtColor(color_rgb, cv2.COLOR_RGB2BGR)
    if split == "none":
        return [bgr]
    if split == "sbs":
        w = bgr.shape[1] // 2
        return [bgr[:, :w], bgr[:, w : 2 * w]]
    raise CalibrationError(f"split: expected 'none' or 'sbs' (side-by-side stereo), got {split!r}")


def check_capture_options(views: int, target_coverage: float, max_frames: int, min_novelty: float) -> None:
    """Refuse values of :func:`capture_views`' options that cannot work (named by their command-line flags).

    Raises
    ------
    CalibrationError
    """
    if views < 1:
        raise CalibrationError(f"--views: expected the number of views to keep, at least 1, got {views}")
    if not (0.0 <= target_coverage <= 1.0):  # also refuses nan
        raise CalibrationError(
            f"--coverage: expected the image fraction to cover, 0..1 (such as 0.8), got {target_coverage}"
        )
    if max_frames < 1:
        raise CalibrationError(f"--max-frames: expected the most frames to read, at least 1, got {max_frames}")
    if not (0.0 <= min_novelty < math.inf):
        raise CalibrationError(f"--min-novelty: expected a pose change of 0 or more (such as 0.08), got {min_novelty}")


def check_output_folder(out_dir: str | Path) -> None:
    """Refuse an output folder that already holds files: new views would overwrite ``view_000.png``...
    and leave an earlier capture's later views beside them, mixing two captures.

    Raises
    ------
    CalibrationError
    """
    out = Path(out_dir)
    if not out.is_dir():
        return
    first = next((p for p in out.rglob("*") if not p.is_dir()), None)
    if first is not None:
        raise CalibrationError(
            f"{out}: output folder is not empty (holds {first.relative_to(out)}, from an earlier capture?); "
            "choose a new folder with -o, or empty this one"
        )


def capture_views(
    source: Source,
    out_dir: str | Path,
    spec: BoardSpec,
    *,
    views: int = 25,
    target_coverage: float = 0.8,
    max_frames: int = 3000,
    split: str = "none",
    min_novelty: float = 0.08,
    on_frame: Callable[[int, Verdict, ViewSelector], None] | None = None,
) -> CaptureResult:
    """Read frames from an opened ``source`` and save diverse board views into ``out_dir``.

    Stops when ``views`` views are kept and coverage reaches ``target_coverage``, when
    ``max_frames`` frames were read, or at the end of the stream. With ``split="sbs"`` every frame
    is a side-by-side stereo pair: both halves must show the board, and they are saved as
    ``left/view_NNN.png`` and ``right/view_NNN.png``; diversity is judged on the left half.

    Raises
    ------
    CalibrationError
        When the source ends without a single usable view (says how many frames were read), an
        option is out of range (:func:`check_capture_options`), or ``out_dir`` already holds files
        (:func:`check_output_folder`: nothing is overwritten).
    """
    check_capture_options(views, target_coverage, max_frames, min_novelty)
    check_output_folder(out_dir)
    out = Path(out_dir)
    subdirs = [out] if split == "none" else [out / "left", out / "right"]
    for d in subdirs:
        d.mkdir(parents=True, exist_ok=True)
    det = BoardDetector(spec)
    sel: ViewSelector | None = None
    files: list[Path] = []
    n = 0
    last_bgr = None
    while n < max_frames:
        frame = source.read()
        if frame is None:
            break
        n += 1
        parts = _split(frame.color, split)
        dets = [det.detect(p) for p in parts]
        if sel is None:
            sel = ViewSelector(spec, dets[0].image_size, min_novelty=min_novelty)
        if split == "sbs" and len(dets[1]) < sel.min_corners:
            v = Verdict(False, "board not seen by the right camera")
        else:
            v = sel.consider(dets[0], cv2.cvtColor(parts[0], cv2.COLOR_BGR2GRAY))
        if v.accepted:
            k = len(files) // len(subdirs)
            for d, p in zip(subdirs, parts):
                f = d / f"view_{k:03d}.png"
                cv2.imwrite(str(f), p)
                files.append(f)
            last_bgr = parts[0]
        if on_frame is not None:
            on_frame(n, v, sel)
        if len(files) // len(subdirs) >= views and sel.coverage >= target_coverage:
            break
    if sel is None or not files:
        raise CalibrationError(
            f"capture: no usable board view in {n} frame(s) ({spec.describe()}); check the board "
            "parameters, lighting and focus"
        )
    cv2.imwrite(str(out / "coverage.png"), sel.coverage_image(last_bgr))
    return CaptureResult(files, n, sel.coverage, sel.coverage_text())
