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

from illuminet.calibration.calibfile import Calibration, CalibrationError, CameraCalib, StereoCalib

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


def _xyz(where: str, key: str, d: Any) -> np.ndarray:
    if not isinstance(d, dict) or not all(k in d for k in "xyz"):
        raise CalibrationError(f"{where}: {key}: expected an object with x, y, z, got {d!r}")
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
        cams[socket_name(sock)] = cam
        sockets.append(sock)
        if link is not None:
            to, R, T = link
            links.setdefault(sock, []).append((to, R, T))
            links.setdefault(to, []).append((sock, R.T, -R.T @ T))
    rect = data.get("stereoRectificationData") or {}
    left_from = "--left-socket" if left_socket is not None else "stereoRectificationData.leftCameraSocket"
    right_from = "--right-socket" if right_socket is not None else "stereoRectificationData.rightCameraSocket"
    if left_socket is None:
        left_socket = rect.get("leftCameraSocket")
    if right_socket is None:
        right_socket = rect.get("rightCameraSocket")
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
    for k in ("width", "height", "intrinsicMatrix", "distortionCoeff"):
        if k not in c:
            raise CalibrationError(f"{where}: {key}: missing key {k!r}")
    ctype = int(c.get("cameraType", 0))
    if ctype not in CAMERA_TYPES:
        raise CalibrationError(f"{where}: {key}.cameraType: expected 0 (perspective) or 1 (fisheye), got {ctype}")
    model = CAMERA_TYPES[ctype]
    w, h = int(c["width"]), int(c["height"])
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{where}: {key}: width/height must be positive, got {w}x{h}")
    K = _mat(where, f"{key}.intrinsicMatrix", c["intrinsicMatrix"], (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{where}: {key}.intrinsicMatrix: focal lengths must be positive, got {K.tolist()}")
    D = np.asarray(c["distortionCoeff"], float).ravel()
    if model == "fisheye":
        if len(D) < 4:
            raise CalibrationError(f"{where}: {key}.distortionCoeff: fisheye needs 4 coefficients, got {len(D)}")
        D = D[:4]
    elif len(D) not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{where}: {key}.distortionCoeff: expected 4/5/8/12/14 coefficients, got {len(D)}")
    ex = c.get("extrinsics") or {}
    to = int(ex.get("toCameraSocket", -1))
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
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
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
    return parse_depthai(data, str(path), left_socket, right_socket, path=path)
