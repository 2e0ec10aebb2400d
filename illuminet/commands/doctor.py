"""``illuminet doctor``: what this machine offers the runtime, and how to fix what is missing.

Checks, each reported as OK / MISSING / NONE (nothing found, optional) with the fix:

* OpenGL through EGL: the path the renderer takes (desktop GL 3.3 or OpenGL ES 3.x, [render] gl_api),
  renderer, version, vendor, why ``auto`` fell back, and whether the other API is there too -- essential
* onnxruntime: version and execution providers                                  -- essential
* OpenCV: version, ximgproc (WLS stereo filter), findPlanes, FFmpeg and V4L2 video backends
* PyAV: H.264 (libx264) for MP4 files browsers play (else videos fall back to OpenCV's mp4v)
* DepthAI: version and the OAK devices it sees (``illuminet.hw.oakd.list_devices``)
* V4L2 video devices (``illuminet.hw.v4l2.list_devices``)
* serial ports (``illuminet.hw.serial_imu.list_ports``) and the configured ``[imu] url``

Exit code 0 when the essentials work (the demo, replay and rendering need nothing else), 1 otherwise.
This module never imports ``depthai`` or ``serial`` itself: the hardware lives behind ``illuminet.hw``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

OK, MISSING, NONE = "OK", "MISSING", "NONE"


@dataclass
class Check:
    """Outcome of one check."""

    name: str
    status: str
    detail: str
    fix: str = ""
    essential: bool = False
    items: list[str] = field(default_factory=list)


def check_gl(backend: str = "egl", api: str = "auto") -> Check:
    """The OpenGL context exactly as the renderer gets it ([render] gl_backend, gl_api), and which
    path that is: desktop OpenGL or OpenGL ES, which version, renderer and backend, and why ``auto``
    fell back when it did.

    Uses the runtime's process-wide context (``illuminet.runtime.render.gl.get_context``) for the path
    itself; the other API is probed with a context of its own, released at once (the renderer makes
    its context current at every entry, so the shared one stays usable), and listed under the check.
    """
    fix = (
        "install Mesa's EGL, GLES and drivers: sudo apt-get install libegl1 libgles2 libegl-mesa0 libgl1-mesa-dri "
        "(software llvmpipe works everywhere; for a GPU, pass /dev/dri into the container)"
    )
    name = "OpenGL (EGL)" if backend == "egl" else "OpenGL"
    try:
        import moderngl
    except ImportError as e:
        return Check(name, MISSING, f"moderngl not importable: {e}", "pip install moderngl", True)
    from illuminet.runtime.render.gl import (
        GLError,
        context_info,
        create_context,
        get_context,
        make_current,
    )

    try:
        ctx = get_context(backend, api)
    except GLError as e:  # no libEGL, no driver, no device, or a shared context of another backend
        return Check(name, MISSING, f"no OpenGL context (gl_api {api}, gl_backend {backend}): {e}", fix, True)
    info = context_info(ctx)
    kind = "OpenGL ES" if info.api == "gles" else "desktop OpenGL"
    items = [f"via {info.via}; moderngl {moderngl.__version__}; [render] gl_api = {api!r}, gl_backend = {backend!r}"]
    if info.reason:
        items.append(f"why this path: {info.reason}")
    other = "gles" if info.api == "gl" else "gl"
    other_name = "OpenGL ES 3.x" if other == "gles" else "desktop OpenGL 3.3"
    try:
        probe = create_context(backend, api=other)
    except GLError as e:
        items.append(f"{other_name}: not available here ({e})")
    else:
        pi = context_info(probe)
        items.append(f"{other_name}: also available ({pi.renderer}; {pi.version}), gl_api = {other!r} picks it")
        probe.release()
    make_current(ctx)
    note = " (software rendering: fine for 640x400; a GPU renders larger frames faster)" if info.software else ""
    detail = f"{kind}: {info.renderer}; {info.version}; {ctx.info.get('GL_VENDOR', '?')}{note}"
    return Check(name, OK, detail, essential=True, items=items)


def check_onnxruntime() -> Check:
    try:
        import onnxruntime as ort
    except ImportError as e:
        return Check("onnxruntime", MISSING, f"not importable: {e}", "pip install onnxruntime", True)
    providers = ort.get_available_providers()
    if "CPUExecutionProvider" not in providers:
        return Check(
            "onnxruntime",
            MISSING,
            f"{ort.__version__} without CPUExecutionProvider ({providers})",
            "reinstall onnxruntime (pip install --force-reinstall onnxruntime)",
            True,
        )
    return Check("onnxruntime", OK, f"{ort.__version__}; providers: {', '.join(providers)}", essential=True)


def check_opencv() -> Check:
    try:
        import cv2
        from cv2 import videoio_registry
    except ImportError as e:
        return Check("OpenCV", MISSING, f"not importable: {e}", "pip install opencv-contrib-python-headless")
    has = {
        "ximgproc": hasattr(cv2, "ximgproc"),
        "findPlanes": hasattr(cv2, "findPlanes"),
        "FFmpeg": videoio_registry.hasBackend(cv2.CAP_FFMPEG),
        "V4L2": videoio_registry.hasBackend(cv2.CAP_V4L2),
    }
    detail = f"{cv2.__version__}; " + ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in has.items())
    missing = [k for k, v in has.items() if not v]
    if missing:
        fix = (
            (
                "ximgproc/findPlanes come with the contrib build: pip uninstall opencv-python "
                "opencv-python-headless; pip install opencv-contrib-python-headless"
            )
            if {"ximgproc", "findPlanes"} & set(missing)
            else ""
        )
        if "FFmpeg" in missing:
            fix += ("; " if fix else "") + "video files need OpenCV's FFmpeg backend (the PyPI wheels have it)"
        if "V4L2" in missing:
            fix += ("; " if fix else "") + "v4l2:// cameras need OpenCV's V4L2 backend (Linux PyPI wheels have it)"
        return Check("OpenCV", MISSING, detail + f" (missing: {', '.join(missing)})", fix)
    return Check("OpenCV", OK, detail)


def check_pyav() -> Check:
    """PyAV's FFmpeg with an H.264 encoder: MP4 files that browsers play (``VideoSink``)."""
    try:
        av = importlib.import_module("av")
    except ImportError as e:
        return Check(
            "PyAV (H.264 video)",
            MISSING,
            f"not importable: {e}; .mp4 files are written as MPEG-4 part 2 by OpenCV (plays in VLC, not in browsers)",
            "pip install av",
        )
    try:
        av.codec.Codec("libx264", "w")
    except Exception as e:  # av.codec.codec.UnknownCodecError and friends
        return Check(
            "PyAV (H.264 video)",
            MISSING,
            f"{av.__version__}; no libx264 encoder ({e})",
            "pip install --force-reinstall av (the PyPI wheels include libx264)",
        )
    return Check("PyAV (H.264 video)", OK, f"{av.__version__}; libx264 (MP4 as H.264, yuv420p)")


def check_depthai(protocol: str = "any") -> Check:
    """OAK devices DepthAI finds; ``protocol`` ([source] oakd_protocol): "usb" broadcasts nothing on the network."""
    try:
        oakd = importlib.import_module("illuminet.hw.oakd")
    except ImportError as e:
        return Check("DepthAI (OAK)", MISSING, f"not importable: {e}", "pip install 'depthai>=3'")
    where = {"any": "USB and the network (UDP broadcast)", "usb": "USB only", "tcpip": "the network only"}
    searched = f"searched {where.get(protocol, protocol)} ([source] oakd_protocol)"
    try:
        devices = oakd.list_devices(protocol)
    except Exception as e:  # USB stack problems surface here
        return Check(
            "DepthAI (OAK)",
            MISSING,
            f"{oakd.depthai_version()}; {searched}; device search failed: {e}",
            "check USB access (udev rule below) or run with the device's IP for PoE models",
        )
    items = [f"{d['id']}  {d['name']}  {d['state']} {d['protocol']} {d['platform']}" for d in devices]
    if not devices:
        return Check(
            "DepthAI (OAK)",
            NONE,
            f"{oakd.depthai_version()}; {searched}; no OAK device found",
            'plug the OAK in (USB3 port and cable); on Linux allow access once: echo \'SUBSYSTEM=="usb", '
            'ATTRS{idVendor}=="03e7", MODE="0666"\' | sudo tee /etc/udev/rules.d/80-movidius.rules && '
            "sudo udevadm control --reload-rules && sudo udevadm trigger; in a container pass "
            "-v /dev/bus/usb:/dev/bus/usb --device-cgroup-rule='c 189:* rmw'",
        )
    return Check("DepthAI (OAK)", OK, f"{oakd.depthai_version()}; {len(devices)} device(s): use oakd://ID", items=items)


def check_v4l2() -> Check:
    v4l2 = importlib.import_module("illuminet.hw.v4l2")
    devices = v4l2.list_devices()
    if not devices:
        return Check(
            "V4L2 cameras",
            NONE,
            "no /dev/video* device",
            "plug in a stereo UVC camera; in a container pass --device /dev/videoN; "
            "v4l2-ctl --list-devices (apt-get install v4l-utils) shows what the kernel sees",
        )
    items = [f"{d['device']}  {d['name']}" for d in devices]
    return Check(
        "V4L2 cameras",
        OK,
        f"{len(devices)} device(s); stereo only: v4l2://DEV?stereo=sbs or ?right=DEV2 with a calibration",
        items=items,
    )


def check_serial(imu_url: str) -> Check:
    sim = importlib.import_module("illuminet.hw.serial_imu")
    ports = sim.list_ports()
    items = [f"{p['device']}  {p['description']}  {p['hwid']}" for p in ports]
    configured = f"; [imu] url = {imu_url}" if imu_url else "; no serial IMU configured ([imu] url)"
    if imu_url:
        try:
            reader = sim.SerialImu(imu_url)
            reader.open()
            reader.close()
            configured += " (opens)"
        except (OSError, ValueError) as e:
            return Check(
                "serial ports",
                MISSING,
                f"{len(ports)} port(s){configured} -- cannot open: {e}",
                "check the path and permissions (Linux: sudo usermod -aG dialout $USER, log in again)",
                items=items,
            )
    if not ports:
        return Check(
            "serial ports",
            NONE,
            "no serial port" + configured,
            "a USB-serial IMU appears as /dev/ttyUSB* or /dev/ttyACM*; see docs/live.md for the protocol",
        )
    return Check("serial ports", OK, f"{len(ports)} port(s){configured}", items=items)


def run_checks(
    imu_url: str = "", gl_backend: str = "egl", gl_api: str = "auto", oakd_protocol: str = "any"
) -> list[Check]:
    """All checks, in report order; a check that crashes is reported as MISSING with the error."""
    checks: list[tuple[str, Callable[[], Check]]] = [
        ("OpenGL (EGL)", lambda: check_gl(gl_backend, gl_api)),
        ("onnxruntime", check_onnxruntime),
        ("OpenCV", check_opencv),
        ("PyAV (H.264 video)", check_pyav),
        ("DepthAI (OAK)", lambda: check_depthai(oakd_protocol)),
        ("V4L2 cameras", check_v4l2),
        ("serial ports", lambda: check_serial(imu_url)),
    ]
    out = []
    for name, fn in checks:
        try:
            out.append(fn())
        except Exception as e:  # the doctor must report, not crash
            out.append(
                Check(
                    name,
                    MISSING,
                    f"check failed: {type(e).__name__}: {e}",
                    essential=name in ("OpenGL (EGL)", "onnxruntime"),
                )
            )
    return out


def format_report(checks: list[Check]) -> str:
    lines = [
        f"illuminet doctor -- {platform.system()} {platform.machine()}, python {platform.python_version()}, "
        f"{os.cpu_count()} cores"
    ]
    for c in checks:
        lines.append(f"[{c.status:^7}] {c.name}: {c.detail}")
        lines += [f"            {it}" for it in c.items]
        if c.fix and c.status != OK:
            lines.append(f"            fix: {c.fix}")
    bad = [c.name for c in checks if c.essential and c.status != OK]
    lines.append("essentials: " + ("OK (demo, replay and rendering work)" if not bad else f"MISSING: {', '.join(bad)}"))
    return "\n".join(lines)


def register(sub) -> None:
    p = sub.add_parser(
        "doctor",
        help="check GL, onnxruntime, OpenCV, DepthAI/V4L2 cameras and serial ports",
        description=(
            "Report what this machine offers: the OpenGL path the renderer takes (desktop GL or OpenGL ES, "
            "renderer, version), onnxruntime providers, OpenCV "
            "features, OAK devices, V4L2 cameras, serial ports; with how to fix what is missing. "
            "Exit code 0 when the essentials (OpenGL via EGL, onnxruntime) work."
        ),
    )
    p.add_argument("--json", action="store_true", help="print the checks as JSON instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace, cfg) -> int:
    if getattr(args, "json", False):
        # DepthAI prints its warnings to stdout when it is imported; keep the JSON parseable
        os.environ.setdefault("DEPTHAI_LEVEL", "error")
    if cfg is not None:
        checks = run_checks(cfg.imu.url, cfg.render.gl_backend, cfg.render.gl_api, cfg.source.oakd_protocol)
    else:
        checks = run_checks()
    if getattr(args, "config_error", None):  # illuminet.cli.main: the configuration did not load
        checks.insert(
            0,
            Check(
                "configuration",
                MISSING,
                f"not loaded: {args.config_error}",
                "fix the file or key named (the checks below used the built-in defaults)",
                essential=True,
            ),
        )
    if getattr(args, "json", False):
        print(json.dumps([asdict(c) for c in checks], indent=2))
    else:
        print(format_report(checks))
    sys.stdout.flush()
    return exit_code(checks)


def exit_code(checks: list[Check]) -> int:
    """0 when every essential check is OK, else 1 (optional hardware never fails the doctor)."""
    return 0 if all(c.status == OK for c in checks if c.essential) else 1
