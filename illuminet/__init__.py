"""IllumiNet-edge: the thin entry package above the four source folders.

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

# In a source checkout the subpackages are the sibling folders runtime/, hw/, models/ and
# calibration/ (pyproject maps them for installs). Letting the package path include the checkout
# root makes `python -m illuminet` and tests work from a checkout even without an install.
_root = _Path(__file__).resolve().parent.parent
if (_root / "pyproject.toml").is_file() and (_root / "runtime" / "__init__.py").is_file():
    __path__.append(str(_root))  # noqa: F821 - __path__ is defined for packages
