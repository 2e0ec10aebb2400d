"""Configuration: the schema (types, defaults, allowed values), loading config.toml, CLI overrides.

The schema below is the single source of truth; ``config.toml`` at the repository root documents
every key and must agree with it (a test checks). Loading refuses unknown sections and keys and
wrong types with a :class:`ConfigError` that names the file, the key, the expected type and the
value given. Command-line flags override file values through :func:`apply_overrides`
(``--set section.key=value``, value in TOML syntax).
"""

from __future__ import annotations

import copy
import math
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


# defined in runtime/errors.py (one hierarchy for every error a user can meet); re-exported here
from illuminet.runtime.errors import ConfigError  # noqa: E402,F401
from illuminet.runtime.files import FileTooLarge, read_bounded  # noqa: E402


@dataclass(frozen=True)
class Field:
    """One configuration key: its type(s), default, allowed values and a one-line description."""

    types: tuple[type, ...]
    default: Any
    doc: str
    choices: tuple[Any, ...] | None = None
    length: int | None = None  # for lists: required length
    # numbers (and every element of a numeric list): inclusive bounds; ``gt`` is an exclusive lower
    # bound (a length that must be positive). Floats must always be finite: NaN passes every
    # comparison as False, so a NaN scale would otherwise slip through any range.
    min: float | None = None
    max: float | None = None
    gt: float | None = None
    # strings (and every string of a list of ``item`` = str): must not be empty or only blanks
    nonempty: bool = False
    # lists whose elements are not numbers: the element type (a list of host names: str)
    item: type | None = None
    # numbers: 0 is allowed besides the range (0 = "off" or "every frame", while a tiny positive value
    # would divide into infinity: a rate of 1e-309 Hz)
    zero_ok: bool = False

    def type_name(self) -> str:
        names = {bool: "bool", int: "int", float: "float", str: "string", list: "list"}
        s = " or ".join(names.get(t, t.__name__) for t in self.types)
        if self.item is not None:
            s += f" of {'non-empty ' if self.nonempty else ''}{names.get(self.item, self.item.__name__)}s"
        elif self.nonempty:
            s = "non-empty " + s
        if self.length is not None:
            s += f" of length {self.length}"
        if float in self.types or (list in self.types and self.length is not None):
            s += " (finite)" if list not in self.types else " (finite numbers)"
        if self.gt is not None:
            s += f" > {self.gt:g}"
            if self.max is not None:
                s += f" and <= {self.max:g}"
        elif self.min is not None and self.max is not None:
            s += f" in {self.min:g}..{self.max:g}"
        elif self.min is not None:
            s += f" >= {self.min:g}"
        elif self.max is not None:
            s += f" <= {self.max:g}"
        if self.choices is not None:
            s += " (one of " + ", ".join(repr(c) for c in self.choices) + ")"
        if self.zero_ok:
            s = "0 or " + s
        return s

    def in_range(self, v: float) -> bool:
        """Whether the number ``v`` is finite and inside this field's bounds."""
        if isinstance(v, float) and not math.isfinite(v):
            return False
        if self.zero_ok and v == 0:
            return True
        if self.gt is not None and not v > self.gt:
            return False
        if self.min is not None and not v >= self.min:
            return False
        return not (self.max is not None and not v <= self.max)


def _f(
    types,
    default,
    doc,
    choices=None,
    length=None,
    *,
    min=None,
    max=None,
    gt=None,
    nonempty=False,
    item=None,  # noqa: A002
    zero_ok=False,
) -> Field:
    if not isinstance(types, tuple):
        types = (types,)
    return Field(types, default, doc, choices, length, min, max, gt, nonempty, item, zero_ok)


#: section -> key -> Field. Keep config.toml in step with this table.
SCHEMA: dict[str, dict[str, Field]] = {
    "source": {
        "url": _f(
            str,
            "synthetic://indoor?seed=0",
            "frame source URL: oakd://, v4l2:///dev/videoN, replay://PATH, synthetic://SCENE",
        ),
        "timing": _f(str, "recorded", "replay timing", choices=("recorded", "asap")),
        "loop": _f(bool, False, "replay: start again at the end"),
        "max_frames": _f(int, 0, "stop after this many frames (0 = no limit)", min=0),
        "calibration": _f(str, "", "calibration file for v4l2:// stereo cameras (see `illuminet calibrate`)"),
        "reconnect": _f(bool, True, "live sources: reconnect with backoff when the device is lost"),
        "response_curve": _f(str, "", "camera response curve from `illuminet calibrate photometric` ('' = sRGB)"),
        "oakd_protocol": _f(
            str,
            "any",
            "how DepthAI looks for OAK devices: any (USB, and a UDP broadcast on every network for PoE "
            "models), usb (USB only: nothing is sent on the network), tcpip (network only); "
            "oakd://?protocol= overrides it",
            choices=("any", "usb", "tcpip"),
        ),
    },
    "planes": {
        "method": _f(
            str, "region", "plane segmentation (docs/planes.md compares them)", choices=("ransac", "region", "opencv")
        ),
        "redetect_every": _f(int, 30, "full re-detection every N frames (tracking in between)", min=1),
        "max_planes": _f(int, 4, "most planes kept per frame", min=1, max=64),
        "min_area_m2": _f(float, 0.02, "smallest plane kept, square metres", min=0),
        "inlier_threshold_m": _f(
            float,
            0.03,
            "distance of an inlier at 1 m; grows with z^2 like stereo noise (0.045 for integer-disparity depth)",
            min=0.0001,
            max=1,
        ),
        "smoothing": _f(float, 0.8, "temporal smoothing of plane parameters, 0 = none, <1", min=0, max=0.999),
        "still_px": _f(
            float,
            0.3,
            "keep the planes while the picture moved less than this many pixels since they were last fitted "
            "(a still camera); 0 = fit every frame",
            min=0.01,
            max=100,
            zero_ok=True,
        ),
    },
    "anchor": {
        "mode": _f(str, "auto", "where the object stands", choices=("auto", "pixel", "point")),
        "pixel": _f(list, [320, 300], "mode=pixel: colour-image pixel (x, y)", length=2, min=0, max=100_000),
        "point": _f(
            list, [0.0, 0.3, 1.5], "mode=point: 3D point in camera coordinates, metres", length=3, min=-1000, max=1000
        ),
        "lock": _f(
            str,
            "world",
            "world: placed once, then held in the room by camera odometry; camera: follows the camera",
            choices=("world", "camera"),
        ),
        "still_px": _f(
            float,
            0.3,
            "world lock: hold the pose while the picture moved less than this many pixels since the last tracked "
            "frame (a still camera costs ~0.4 ms instead of ~2.3); 0 = track every frame",
            min=0.01,
            max=100,
            zero_ok=True,
        ),
    },
    "plane_light": {
        "grid": _f(int, 32, "plane OI grid is grid x grid vertices", min=2, max=512),
        "extent_m": _f(float, 1.0, "side of the square plane patch around the anchor, metres", min=0.01, max=100),
        "fusion": _f(float, 0.9, "temporal fusion weight of the previous estimate, 0 = none", min=0, max=0.999),
        "assumed_albedo": _f(float, 0.5, "mean albedo assumed for the plane (radiance -> irradiance)", min=0.01, max=1),
        "smoothing_cells": _f(
            float,
            1.5,
            "masked Gaussian over the grid against coarse albedo texture, sigma in cells (0 = off)",
            min=0,
            max=100,
        ),
        "extra_planes": _f(
            int, 0, "also measure up to N more planes (walls first) as further PlaneLight slices", min=0, max=16
        ),
        "context_extent_m": _f(
            float,
            2.0,
            "also measure the anchor plane over this wider square for the light estimate's lamp search "
            "(PlaneLight.context_*; 0 = off)",
            min=0.1,
            max=100,
            zero_ok=True,
        ),
        "context_grid": _f(int, 64, "the wider square's grid is N x N vertices", min=2, max=512),
        "context_every": _f(
            int,
            3,
            "measure the wider square every N frames (its fusion carries it between; ~2.6 ms each)",
            min=1,
            max=1000,
        ),
    },
    "light": {
        "enabled": _f(
            bool, True, "estimate the room's lighting every frame (results['light']: ambient SH9 + primary light)"
        ),
        "environment": _f(bool, True, "use the radiance of every surface the camera sees, fused over frames"),
        "planes": _f(
            bool, True, "use the irradiance of every tracked plane (walls, tables), not only the anchor plane"
        ),
        "near_light": _f(bool, True, "fit a near lamp to the planes' irradiance falloff"),
        "emitters": _f(bool, True, "take the primary light's direction from bright emitters in view"),
        "shadows": _f(bool, True, "take the primary light's direction from real cast shadows"),
        "rate_hz": _f(
            float,
            10.0,
            "estimates per second (frames in between reuse the last one; 0 = every frame)",
            min=0.01,
            max=1000,
            zero_ok=True,
        ),
        "pipelined": _f(
            bool, True, "compute the estimate on a worker thread, collected one update later (deterministic)"
        ),
        "time_constant_s": _f(
            float,
            0.1,
            "temporal filter time constant, seconds (with the pipeline's one update of delay, a switch is "
            "followed within 0.5 s)",
            min=0,
            max=3600,
        ),
        "search_every": _f(int, 10, "frames between full near-light searches (local refinement in between)", min=1),
        "near_gradient": _f(
            bool,
            True,
            "find a lamp from the differences between the anchor grid's neighbouring cells, robust to the floor's "
            "texture (false: from the cells' values)",
        ),
        "smoothness": _f(
            float, 0.02, "Laplacian penalty on the ambient SH bands (keeps unseen directions smooth)", min=0, max=1e6
        ),
        "emitter_measured": _f(
            bool,
            True,
            "a seen emitter's irradiance is what the map measured of it (clipped: at least that, in the scene "
            "illuminant's colour), not a free fit to the planes (docs/lighting.md)",
        ),
        "unseen_illuminant": _f(
            float,
            1.0,
            "directions the camera has not seen take the scene illuminant's colour, with this weight against a "
            "seen one (0 = they take the seen surfaces' colour; docs/lighting.md)",
            min=0,
            max=100,
        ),
    },
    "model": {
        "bundle": _f(str, "builtin:vase", "object bundle: builtin:NAME or a bundle folder"),
        "precision": _f(str, "int8", "ONNX chain used at run time", choices=("int8", "fp32")),
        "shading": _f(
            str,
            "auto",
            "what drives the object's shading: PRT from the light estimate, the learned "
            "model, or a baseline (auto: prt when the frame has a light estimate and the bundle PRT, "
            "else model)",
            choices=("auto", "prt", "model", "sh", "ambient", "constant"),
        ),
        "temporal_smoothing": _f(float, 0.7, "exponential smoothing of predicted shading, 0 = none", min=0, max=0.999),
    },
    "render": {
        "object_scale": _f(float, 1.0, "extra scale applied to the object's mesh", min=0.001, max=1000),
        "shadow": _f(bool, True, "draw the object's shadow on the anchor plane"),
        "shadow_map": _f(
            int,
            512,
            "shadow map resolution, pixels (512: a redraw ~9 ms of CPU on llvmpipe, 1024 ~21 ms, same picture "
            "within 1 level under the 16-tap penumbra)",
            min=16,
            max=8192,
        ),
        "occlusion": _f(bool, True, "real geometry nearer than the object hides it"),
        "antialias": _f(
            str,
            "edge",
            "object edges: filtered silhouette (cheap), multisampling, or none",
            choices=("edge", "msaa", "off"),
        ),
        "msaa": _f(int, 4, 'samples per pixel when antialias = "msaa" (0 = off)', min=0, max=16),
        "shadow_softness": _f(float, 0.05, "shadow penumbra radius as a fraction of the object's size", min=0, max=10),
        "contact_shadow": _f(float, 0.75, "strength of the contact shadow under the object's base, 0..1", min=0, max=1),
        "depth_tolerance_m": _f(
            float, 0.03, "real depth this much nearer (at 1 m; grows with z^2) hides the object", min=0, max=10
        ),
        "gl_backend": _f(
            str,
            "egl",
            "OpenGL context: headless EGL, or the platform default (needs a display)",
            choices=("egl", "default"),
        ),
        "gl_api": _f(
            str,
            "auto",
            "OpenGL API: desktop GL 3.3 core, OpenGL ES 3.x through EGL (embedded GPUs), or auto "
            "(desktop GL on a GPU, else ES on a GPU, else desktop GL in software; `illuminet doctor` says which)",
            choices=("auto", "gl", "gles"),
        ),
    },
    "output": {
        "video": _f(str, "", "write an .mp4/.avi video here ('' = off)"),
        "png_dir": _f(str, "", "write a PNG per frame into this folder ('' = off)"),
        "record": _f(str, "", "record the input session into this folder ('' = off)"),
        "mjpeg": _f(bool, False, "serve MJPEG over HTTP with a status page"),
        "listen": _f(
            str, "127.0.0.1", "MJPEG bind address; 0.0.0.0 serves the local network (never empty)", nonempty=True
        ),
        "port": _f(int, 8080, "MJPEG port (0 = a free port the system picks)", min=0, max=65535),
        "max_clients": _f(
            int, 32, "MJPEG connections served at once; more get 503 and are closed at once", min=1, max=1024
        ),
        "allowed_hosts": _f(
            list,
            [],
            "host names the MJPEG server answers besides localhost, this machine's name and IP addresses "
            "(a Host header naming anything else gets 421: the DNS-rebinding defence); '*' = any",
            item=str,
            nonempty=True,
        ),
        "fps": _f(float, 30.0, "frame rate written into video files", min=0.1, max=1000),
        "record_color": _f(
            str,
            "raw",
            "colour encoding of recorded sessions: raw bytes (lossless, least CPU), "
            "PNG (lossless, ~40 % smaller), JPEG (lossy)",
            choices=("raw", "png", "jpeg"),
        ),
        "record_jpeg_quality": _f(int, 95, "JPEG quality 1..100 when record_color = 'jpeg'", min=1, max=100),
        "record_fsync": _f(bool, True, "fsync every recorded frame (survives power loss; kill -9 is safe either way)"),
        "estimates": _f(
            str,
            "",
            "write each frame's lighting estimate as a JSON line here ('' = off, '-' = stdout; docs/estimate.md)",
        ),
        "viewer_model": _f(
            str,
            "",
            "model the MJPEG server's /viewer page draws: a .glb/.gltf/.obj/.ply/.stl file or builtin:NAME "
            "('' = the [model] bundle's object)",
        ),
    },
    "imu": {
        "url": _f(
            str,
            "",
            "serial IMU: serial://PORT?baud=N, or any serial.serial_for_url URL (/dev/ttyUSB0, loop://); '' = none",
        ),
        "baudrate": _f(int, 115200, "serial baud rate", min=1, max=100_000_000),
        "max_skew_ms": _f(float, 20.0, "largest IMU-to-frame timestamp gap accepted", gt=0, max=10_000),
        "rotation": _f(
            list,
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "IMU axes -> camera axes (x right, y down, z forward): 3x3 rotation, row-major",
            length=9,
            min=-1,
            max=1,
        ),
        "gravity_tau_s": _f(
            float, 0.3, "time constant of the accelerometer low-pass that gives gravity, seconds", gt=0, max=3600
        ),
        "clock": _f(
            str,
            "device",
            "IMU timestamps: sender's own clock (offset estimated) or this host's monotonic clock",
            choices=("device", "host"),
        ),
    },
    "loop": {
        "pipeline": _f(
            str,
            "auto",
            "run the stages before the renderer on a worker thread, one frame ahead of rendering and the "
            "outputs (same output as serial; auto: threads with four or more CPUs; docs/runtime.md)",
            choices=("auto", "serial", "threads"),
        ),
        "depth": _f(
            int,
            1,
            "threads: most frames finished ahead of the renderer and waiting for it (more absorbs jitter, "
            "adds latency)",
            min=1,
            max=8,
        ),
        "trim_memory_s": _f(
            float,
            30.0,
            "every this many seconds hand the C heap's free pages back to the system (glibc malloc_trim; "
            "keeps a long stream's memory flat; 0 = never; docs/runtime.md)",
            min=0,
            max=86400,
        ),
        "opencv_threads": _f(
            int,
            1,
            "OpenCV's worker threads while the loop runs (process-wide; 0 = OpenCV's default, one per CPU; "
            "1 saves their spinning: ~0.8 ms of CPU a frame on 2 cores, same output; docs/runtime.md)",
            min=0,
            max=256,
        ),
    },
    "logging": {
        "level": _f(str, "info", "log level", choices=("debug", "info", "warning", "error")),
        "stats_json": _f(str, "", "write per-stage timing statistics as JSON here at the end ('' = off)"),
        "strict": _f(bool, False, "raise on the first failing frame instead of counting it (tests)"),
    },
}


class Section(Mapping[str, Any]):
    """Read-only view of one section; keys are attributes too (``cfg.planes.method``)."""

    def __init__(self, name: str, values: dict[str, Any]):
        self._name = name
        self._values = values

    def __getattr__(self, key: str) -> Any:
        try:
            return self._values[key]
        except KeyError:
            raise AttributeError(f"config section [{self._name}] has no key {key!r}") from None

    def __getitem__(self, key: str) -> Any:
        return self._values[key]

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"Section({self._name!r}, {self._values!r})"


class Config(Mapping[str, Section]):
    """A validated configuration: every section and key of :data:`SCHEMA`, defaults filled in."""

    def __init__(self, data: dict[str, dict[str, Any]], origin: str = "<defaults>"):
        self._data = data
        self.origin = origin

    def __getattr__(self, name: str) -> Section:
        if name.startswith("_") or name == "origin":
            raise AttributeError(name)
        try:
            return Section(name, self._data[name])
        except KeyError:
            raise AttributeError(f"config has no section [{name}]") from None

    def __getitem__(self, name: str) -> Section:
        return Section(name, self._data[name])

    def __iter__(self):
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return copy.deepcopy(self._data)


def defaults() -> Config:
    """The configuration with every default."""
    return Config({s: {k: copy.deepcopy(f.default) for k, f in keys.items()} for s, keys in SCHEMA.items()})


def _check_value(where: str, section: str, key: str, value: Any) -> Any:
    fld = SCHEMA[section][key]
    ok = any(isinstance(value, t) and not (t in (int, float) and isinstance(value, bool)) for t in fld.types)
    # ints are accepted where floats are expected (TOML writes 1 for 1.0)
    if not ok and float in fld.types and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if ok and fld.length is not None and len(value) != fld.length:
        ok = False
    if ok and list in fld.types and fld.item is not None and isinstance(value, list):
        ok = all(isinstance(v, fld.item) and not isinstance(v, bool) for v in value)
        if ok and fld.nonempty:
            ok = all(str(v).strip() for v in value)
    elif ok and list in fld.types and fld.length is not None:
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if ok and fld.nonempty and isinstance(value, str):
        ok = bool(value.strip())
    if ok and fld.choices is not None and value not in fld.choices:
        ok = False
    if ok and isinstance(value, (int, float)) and not isinstance(value, bool):
        ok = fld.in_range(value)
    if ok and isinstance(value, list) and fld.item is None:
        ok = all(fld.in_range(v) for v in value)
    strings = [value] if isinstance(value, str) else value if isinstance(value, list) else []
    if ok and any(isinstance(v, str) and "\x00" in v for v in strings):
        # TOML's "\u0000": no path, URL, address or name holds one, and every file call raised a
        # ValueError traceback ("embedded null byte") on it
        raise ConfigError(f"{where}: [{section}] {key}: {value!r} contains a NUL byte; expected {fld.type_name()}")
    if not ok:
        # a value that must not be empty: say what the key is for, since "" gives no hint of it
        hint = f" ({fld.doc})" if fld.nonempty else ""
        raise ConfigError(
            f"{where}: [{section}] {key}: expected {fld.type_name()}, got {type(value).__name__} {value!r}{hint}"
        )
    return value


def validate(data: Mapping[str, Any], where: str = "<config>") -> Config:
    """Validate a parsed TOML mapping against :data:`SCHEMA` and fill in defaults."""
    cfg = defaults().to_dict()
    for section, keys in data.items():
        if section not in SCHEMA and not isinstance(keys, Mapping):  # `rate_hz = 5` above every [section]
            owners = [f"[{name}]" for name, fields in SCHEMA.items() if section in fields]
            fix = f"it is a key of {' and '.join(owners)}" if owners else f"known sections: {', '.join(SCHEMA)}"
            raise ConfigError(
                f"{where}: key {section!r} = {keys!r} is outside any section; put it under its [section] line ({fix})"
            )
        if section not in SCHEMA:
            raise ConfigError(f"{where}: unknown section [{section}]; known sections: {', '.join(SCHEMA)}")
        if not isinstance(keys, Mapping):
            raise ConfigError(f"{where}: [{section}] must be a table of keys, got {type(keys).__name__} {keys!r}")
        for key, value in keys.items():
            if key not in SCHEMA[section]:
                raise ConfigError(f"{where}: [{section}] unknown key {key!r}; known keys: {', '.join(SCHEMA[section])}")
            cfg[section][key] = _check_value(where, section, key, value)
    return Config(cfg, where)


#: largest config file read (bytes); config.toml with every key documented is ~15 kB. A bound, so that
#: ``--config /dev/zero`` (or any endless stream) is refused instead of read until memory runs out
MAX_CONFIG_BYTES = 1 << 20


def load(path: str | Path | None = None) -> Config:
    """Load and validate a TOML file; ``None`` gives the defaults."""
    if path is None:
        return defaults()
    path = Path(path)
    if path.exists() and not path.is_file() and not path.is_dir():  # a FIFO: reading it waited for ever
        raise ConfigError(f"{path}: not a regular file (a pipe or device?); expected a TOML file such as config.toml")
    try:
        try:
            raw = read_bounded(path, MAX_CONFIG_BYTES)
        except FileTooLarge as e:
            raise ConfigError(
                f"{e}, not a config file (or an endless stream such as a device); expected a TOML file such as "
                "config.toml"
            ) from None
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(
            f"{path}: is a folder, not a config file (expected a TOML file such as config.toml)"
        ) from None
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"{path}: not a text file (byte {e.start} is not UTF-8); expected a TOML file such as config.toml"
        ) from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the config file ({e.strerror or e})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    except (ValueError, RecursionError) as e:  # an int of over 4300 digits; arrays nested thousands deep
        raise ConfigError(f"{path}: not valid TOML: {_unparsable(e)}") from None
    return validate(data, str(path))


def _unparsable(e: BaseException) -> str:
    """Why tomllib could not turn a value into Python (beyond TOMLDecodeError), in a few words."""
    if isinstance(e, RecursionError):
        return "arrays or tables nested too deep"
    if "digits" in str(e):  # Python's own advice (sys.set_int_max_str_digits) is no fix for a config
        return "an integer of over 4300 digits"
    return f"a value Python cannot hold ({e})"


def parse_override(item: str) -> tuple[str, str, Any]:
    """``"section.key=value"`` -> (section, key, value); value is parsed as TOML, else taken as a string."""
    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise ConfigError(f"override {item!r}: expected section.key=value, e.g. planes.method=ransac")
    lhs, rhs = item.split("=", 1)
    section, key = lhs.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {rhs.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = rhs.strip()
    except (ValueError, RecursionError) as e:  # valid TOML Python cannot hold: a traceback before
        shown = rhs.strip() if len(rhs.strip()) <= 40 else rhs.strip()[:40] + "..."
        raise ConfigError(
            f"override {lhs.strip()}={shown}: {_unparsable(e)}; expected a value such as 1, 0.5, true or [1, 2]"
        ) from None
    return section, key, value


def apply_overrides(cfg: Config, overrides: Iterable[str | tuple[str, str, Any]]) -> Config:
    """A new config with ``section.key=value`` overrides applied and validated."""
    data = cfg.to_dict()
    for item in overrides:
        section, key, value = parse_override(item) if isinstance(item, str) else item
        if section not in SCHEMA:
            raise ConfigError(f"override: unknown section [{section}]; known sections: {', '.join(SCHEMA)}")
        if key not in SCHEMA[section]:
            raise ConfigError(f"override: [{section}] unknown key {key!r}; known keys: {', '.join(SCHEMA[section])}")
        data[section][key] = _check_value("override", section, key, value)
    return Config(data, cfg.origin)
