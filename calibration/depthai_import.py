"""Import of a DepthAI factory (EEPROM) calibration JSON into our :class:`Calibration`.

This module owns the conversion of the JSON that DepthAI exports (``CalibrationHandler.eepromToJsonFile``;
``version`` 7 files such as an OAK-D Pro's) by plain JSON parsing: ``calibration/`` must not import
``depthai``. What is read:

* ``cameraData``: a list of ``[socket, {...}]`` pairs; per camera ``width``, ``height``,
  ``intrinsicMatrix`` (3x3, pixels at that size), ``distortionCoeff`` (14 OpenCV rational + thin
  prism + tilt coefficients for ``cameraType`` 0 = perspective; the first 4 are ``cv2.fisheye``'s
  k1..k4 for ``cameraType`` 1 = fisheye), and ``extrinsics`` (``rotationMatrix``, ``translation`` in
  **centimetres**, ``toCameraSocket``: ``X_to = R @ X_this + T``; ``toCameraSocket`` -1 = none).
* ``stereoRectificationData``: which sockets form the stereo pair (left/right).

Cameras are named after DepthAI's sockets (``CAM_A`` = 0 (usually RGB), ``CAM_B`` = 1 (left mono),
``CAM_C`` = 2 (right mono), ...). The stereo pose between any two cameras is found by chaining the
extrinsics links (inverting where needed), converted to metres.
"""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from illuminet.calibration.calibfile import (
    Calibration,
    CalibrationError,
    CameraCalib,
    StereoCalib,
    read_calibration_text,
)

CAMERA_TYPES = {0: "pinhole", 1: "fisheye"}


def socket_name(socket: int) -> str:
    """DepthAI socket number -> name (0 -> ``CAM_A``)."""
    return "CAM_" + chr(ord("A") + int(socket))


def _mat(where: str, key: str, v: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {key}: expected numbers of shape {shape}, got {v!r}") from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: {key}: expected finite numbers of shape {shape}, got shape {a.shape}")
    return a


#: the most a translation component may be, in centimetres (a camera module is centimetres across;
#: 1e300 gave an overflow warning and a written calibration of an absurd baseline)
MAX_TRANSLATION_CM = 10_000.0
#: the largest image side a camera entry may claim (pixels)
MAX_SIDE = 100_000
#: DepthAI sockets are CAM_A..CAM_Z
MAX_SOCKET = 25


def _shown(v: Any) -> str:
    r = " ".join(repr(v).split())
    return r if len(r) <= 60 else r[:57] + "..."


def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _int(where: str, key: str, v: Any, lo: int, hi: int, what: str) -> int:
    """``v`` as a whole number in ``lo..hi`` (a JSON ``1280.0`` counts), else one line naming ``key``:
    ``int()`` of a string, None, a list or infinity was a traceback, of ``1280.7`` a silent truncation,
    and True was socket 1."""
    if not (_is_real(v) and np.isfinite(v) and float(v).is_integer() and lo <= v <= hi):
        raise CalibrationError(f"{where}: {key}: expected {what} (a whole number from {lo} to {hi}), got {_shown(v)}")
    return int(v)


def _socket(where: str, key: str, v: Any) -> int:
    return _int(where, key, v, 0, MAX_SOCKET, "a camera socket number")


def _xyz(where: str, key: str, d: Any) -> np.ndarray:
    if not isinstance(d, dict) or not all(k in d for k in "xyz"):
        raise CalibrationError(f"{where}: {key}: expected an object with x, y, z, got {d!r}")
    for k in "xyz":
        v = d[k]
        if not (_is_real(v) and np.isfinite(v) and abs(v) <= MAX_TRANSLATION_CM):
            raise CalibrationError(
                f"{where}: {key}.{k}: expected a finite number of centimetres within +-{MAX_TRANSLATION_CM:g}, "
                f"got {_shown(v)}"
            )
    return np.array([float(d["x"]), float(d["y"]), float(d["z"])])


def parse_depthai(
    data: dict,
    where: str = "<depthai json>",
    left_socket: int | None = None,
    right_socket: int | None = None,
    path: Path | None = None,
) -> Calibration:
    """Convert a parsed DepthAI calibration dict; see :func:`import_depthai`."""
    if not isinstance(data, dict) or "cameraData" not in data:
        raise CalibrationError(f"{where}: missing key 'cameraData': not a DepthAI calibration export")
    cams: dict[str, CameraCalib] = {}
    links: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    entries = data["cameraData"]
    if not isinstance(entries, list) or not entries:
        raise CalibrationError(f"{where}: cameraData: expected a non-empty list of [socket, camera] pairs")
    sockets: list[int] = []
    for n, entry in enumerate(entries):
        sock, cam, link = _parse_camera(where, f"cameraData[{n}]", entry)
        if sock in sockets:  # the second silently replaced the first
            raise CalibrationError(
                f"{where}: cameraData[{n}]: socket {sock} appears twice (cameraData[{sockets.index(sock)}] too); "
                "expected one entry per camera socket"
            )
        cams[socket_name(sock)] = cam
        sockets.append(sock)
        if link is not None:
            to, R, T = link
            links.setdefault(sock, []).append((to, R, T))
            links.setdefault(to, []).append((sock, R.T, -R.T @ T))
    rect = data.get("stereoRectificationData") or {}
    if not isinstance(rect, dict):  # a list was an AttributeError traceback
        raise CalibrationError(
            f"{where}: stereoRectificationData: expected an object with leftCameraSocket and rightCameraSocket, "
            f"got {_shown(rect)}"
        )
    left_from = "--left-socket" if left_socket is not None else "stereoRectificationData.leftCameraSocket"
    right_from = "--right-socket" if right_socket is not None else "stereoRectificationData.rightCameraSocket"
    if left_socket is None and rect.get("leftCameraSocket") is not None:
        left_socket = _socket(where, left_from, rect["leftCameraSocket"])
    if right_socket is None and rect.get("rightCameraSocket") is not None:
        right_socket = _socket(where, right_from, rect["rightCameraSocket"])
    if left_socket is not None and left_socket == right_socket:
        raise CalibrationError(
            f"{where}: stereo left and right are the same socket {left_socket} ({left_from}, {right_from}): "
            f"a stereo pair needs two cameras; choose two different sockets of {sockets}"
        )
    stereo = None
    meta = {
        "tool": "illuminet calibrate import-depthai",
        "source_file": str(path) if path else where,
        "depthai": {k: data.get(k) for k in ("productName", "boardName", "boardRev", "batchName", "version")},
    }
    if left_socket is not None and right_socket is not None and left_socket in sockets and right_socket in sockets:
        pose = _chain(links, int(left_socket), int(right_socket))
        if pose is None:
            raise CalibrationError(f"{where}: no extrinsics chain links socket {left_socket} to socket {right_socket}")
        R, T = pose
        if not np.linalg.norm(T) > 0:
            raise CalibrationError(
                f"{where}: the extrinsics put socket {left_socket} and socket {right_socket} at the same place "
                "(0 mm baseline): not a stereo pair; check the sockets (--left-socket/--right-socket) or the file"
            )
        stereo = StereoCalib(socket_name(left_socket), socket_name(right_socket), R, T)
        meta["depthai_stereo_rectification"] = {
            k: rect[k] for k in ("rectifiedRotationLeft", "rectifiedRotationRight") if k in rect
        }
    elif left_socket is not None or right_socket is not None:
        missing = [s for s in (left_socket, right_socket) if s is not None and s not in sockets]
        if missing:
            raise CalibrationError(f"{where}: stereo socket(s) {missing} not in cameraData (sockets {sockets})")
        # one side given and the file names no pair: writing no stereo pair without a word left the user
        # to find out at the first stereo run
        lone, other = (
            ("--left-socket", "--right-socket") if right_socket is None else ("--right-socket", "--left-socket")
        )
        raise CalibrationError(
            f"{where}: {lone} given but the other camera of the pair is not known (the file names no "
            f"stereoRectificationData): give {other} too (sockets here: {sockets})"
        )
    return Calibration(cameras=cams, stereo=stereo, meta=meta)


def _parse_camera(where: str, key: str, entry) -> tuple[int, CameraCalib, tuple[int, np.ndarray, np.ndarray] | None]:
    """One ``cameraData`` entry: (socket, intrinsics, (to socket, R, T in metres) or None without extrinsics)."""
    if not (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], int) and isinstance(entry[1], dict)):
        raise CalibrationError(f"{where}: {key}: expected [socket number, {{camera}}], got {str(entry)[:80]}")
    sock, c = entry
    sock = _socket(where, f"{key}[0]", sock)
    for k in ("width", "height", "intrinsicMatrix", "distortionCoeff"):
        if k not in c:
            raise CalibrationError(f"{where}: {key}: missing key {k!r}")
    ctype = c.get("cameraType", 0)
    if not (_is_real(ctype) and ctype in CAMERA_TYPES):
        raise CalibrationError(
            f"{where}: {key}.cameraType: expected 0 (perspective) or 1 (fisheye), got {_shown(ctype)}"
        )
    model = CAMERA_TYPES[int(ctype)]
    w = _int(where, f"{key}.width", c["width"], 1, MAX_SIDE, "the image width in pixels")
    h = _int(where, f"{key}.height", c["height"], 1, MAX_SIDE, "the image height in pixels")
    K = _mat(where, f"{key}.intrinsicMatrix", c["intrinsicMatrix"], (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{where}: {key}.intrinsicMatrix: focal lengths must be positive, got {K.tolist()}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CalibrationError(
            f"{where}: {key}.intrinsicMatrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
        )
    if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
        raise CalibrationError(
            f"{where}: {key}.intrinsicMatrix: principal point ({K[0, 2]:g}, {K[1, 2]:g}) is outside the {w}x{h} "
            f"image; expected pixels inside it"
        )
    coeffs = c["distortionCoeff"]
    if not isinstance(coeffs, list):
        raise CalibrationError(f"{where}: {key}.distortionCoeff: expected a list of numbers, got {_shown(coeffs)}")
    D = _mat(where, f"{key}.distortionCoeff", coeffs, (len(coeffs),))
    if model == "fisheye":
        if len(D) < 4:
            raise CalibrationError(f"{where}: {key}.distortionCoeff: fisheye needs 4 coefficients, got {len(D)}")
        D = D[:4]
    elif len(D) not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{where}: {key}.distortionCoeff: expected 4/5/8/12/14 coefficients, got {len(D)}")
    ex = c.get("extrinsics") or {}
    if not isinstance(ex, dict):  # a list was an AttributeError traceback
        raise CalibrationError(
            f"{where}: {key}.extrinsics: expected an object with rotationMatrix, translation, toCameraSocket, "
            f"got {_shown(ex)}"
        )
    to = ex.get("toCameraSocket", -1)
    if to != -1:
        to = _socket(where, f"{key}.extrinsics.toCameraSocket", to)  # -1: none
    link = None
    if to >= 0:
        R = _mat(where, f"{key}.extrinsics.rotationMatrix", ex.get("rotationMatrix"), (3, 3))
        if abs(np.linalg.det(R) - 1.0) > 1e-3:
            raise CalibrationError(
                f"{where}: {key}.extrinsics.rotationMatrix: not a rotation (det {np.linalg.det(R):.4f})"
            )
        T = _xyz(where, f"{key}.extrinsics.translation", ex.get("translation")) / 100.0  # cm -> m
        link = (to, R, T)
    return sock, CameraCalib(w, h, K, D, model), link


def _chain(links, a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, T) with X_b = R @ X_a + T, by breadth-first search over the extrinsics links."""
    q = deque([(a, np.eye(3), np.zeros(3))])
    seen = {a}
    while q:
        s, R, T = q.popleft()
        if s == b:
            return R, T
        for to, Rl, Tl in links.get(s, []):
            if to not in seen:
                seen.add(to)
                q.append((to, Rl @ R, Rl @ T + Tl))
    return None


def import_depthai(path: str | Path, left_socket: int | None = None, right_socket: int | None = None) -> Calibration:
    """Read a DepthAI calibration JSON file into a :class:`Calibration`.

    Parameters
    ----------
    path : path
        The JSON file.
    left_socket, right_socket : int, optional
        The stereo pair; default: ``stereoRectificationData``'s left/right sockets.

    Raises
    ------
    CalibrationError
        Unreadable file, not JSON, not a DepthAI calibration, or malformed entries (the message
        names the file and the key).
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO: reading it waited for ever
        raise CalibrationError(
            f"{path}: not a regular file (a folder, pipe or device); expected a DepthAI calibration JSON export"
        )
    try:
        data = json.loads(read_calibration_text(path))
    except FileNotFoundError:
        raise CalibrationError(f"{path}: DepthAI calibration file not found") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file; expected a DepthAI calibration JSON export") from None
    except OSError as e:
        raise CalibrationError(f"{path}: cannot read it: {e.strerror or e}") from None
    except json.JSONDecodeError as e:
        raise CalibrationError(f"{path}: not valid JSON: {e}") from None
    except RecursionError:  # [[[[...]]]] thousands deep: a traceback from the JSON decoder
        raise CalibrationError(
            f"{path}: JSON nested too deeply to be a calibration; expected a DepthAI calibration JSON export"
        ) from None
    except CalibrationError:  # larger than a calibration file: already says so
        raise
    except ValueError as e:  # an int of over 4300 digits: json raises a bare ValueError (a traceback)
        raise CalibrationError(f"{path}: not valid JSON: {e}") from None
    return parse_depthai(data, str(path), left_socket, right_socket, path=path)
