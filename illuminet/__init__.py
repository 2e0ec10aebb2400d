"""IllumiNet-edge: the thin entry package above the four source folders.

Use from Python: ``illuminet.open(url)`` (processed frames with their lighting estimate),
``illuminet.relight(color, depth, intrinsics, anchor_px)`` (one image); see illuminet/api.py.

Layering (imports only go downwards, never back up)::

    illuminet (this package: command line, wiring)
        |-- illuminet.hw           sources: oakd, v4l2, replay, synthetic, serial IMU   (hw/)
        |-- illuminet.models       training, export, evaluation                         (models/)
        |-- illuminet.calibration  intrinsics, stereo, photometric                      (calibration/)
        `-- illuminet.runtime      frame types, physics conventions, per-frame stages   (runtime/)

``runtime`` imports none of the others; ``hw``, ``calibration`` and ``models`` import ``runtime``
(``hw`` may also use ``calibration``); only this package imports all of them.
"""

from pathlib import Path as _Path

__version__ = "0.1.0"

#: the Python API (illuminet/api.py), imported on first use: `import illuminet` stays fast (no numpy,
#: OpenCV or GL) for the command line and for programs that only need one of these
_API = ("open", "relight", "render_preview", "align_depth", "Result", "Stream")


def __getattr__(name: str):
    if name in _API:
        from illuminet import api

        return getattr(api, name)
    raise AttributeError(f"module 'illuminet' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_API))


# In a source checkout the subpackages are the sibling folders runtime/, hw/, models/ and
# calibration/ (pyproject maps them for installs). Letting the package path include the checkout
# root makes `python -m illuminet` and tests work from a checkout even without an install.
_root = _Path(__file__).resolve().parent.parent
if (_root / "pyproject.toml").is_file() and (_root / "runtime" / "__init__.py").is_file():
    __path__.append(str(_root))  # noqa: F821 - __path__ is defined for packages
