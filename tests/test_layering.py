"""The folders import one way: runtime is the floor, the entry package is the top (DESIGN.md §1).

Inside runtime: the per-frame stages (``runtime/stages``) and the renderer (``runtime/render``) never
import ground truth (``runtime/groundtruth``: only the synthetic camera, training and evaluation use
it), and nothing below the entry package imports its own modules (``illuminet.cli``,
``illuminet.pipeline``, ``illuminet.commands``...)."""

from __future__ import annotations

import ast

from .conftest import REPO

#: folder -> folders it may import from (besides itself)
ALLOWED = {
    "runtime": set(),
    "calibration": {"runtime"},
    "hw": {"runtime", "calibration"},
    "models": {"runtime", "hw"},
    "illuminet": {"runtime", "calibration", "hw", "models"},
}
VENDOR_HW = ("depthai", "serial")


def _imports(path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_no_folder_imports_one_that_imports_it_back():
    bad = []
    for folder, allowed in ALLOWED.items():
        for py in (REPO / folder).rglob("*.py"):
            for mod in _imports(py):
                parts = mod.split(".")
                if parts[0] == "illuminet" and len(parts) > 1 and parts[1] in ALLOWED:
                    target = parts[1]
                    if target != folder and target not in allowed:
                        bad.append(f"{py.relative_to(REPO)} imports {mod}")
    assert not bad, "layering violations:\n" + "\n".join(bad)


#: subpackages of runtime that must not import ground truth
NO_GROUNDTRUTH = ("runtime/stages", "runtime/render", "runtime/stream")
#: modules of the runtime floor (runtime/*.py) may import only the floor itself
FLOOR_MAY_IMPORT = (
    "illuminet.runtime.frame",
    "illuminet.runtime.scene",
    "illuminet.runtime.stage",
    "illuminet.runtime.physics",
    "illuminet.runtime.config",
    "illuminet.runtime.sh",
    "illuminet.runtime.errors",
    "illuminet.runtime.files",
)


def test_lower_layers_do_not_import_the_entry_package():
    bad = []
    for folder in ALLOWED:
        if folder == "illuminet":
            continue
        for py in (REPO / folder).rglob("*.py"):
            for mod in _imports(py):
                parts = mod.split(".")
                if parts[0] == "illuminet" and (len(parts) == 1 or parts[1] not in ALLOWED):
                    if mod != "illuminet" or "__version__" not in py.read_text():
                        bad.append(f"{py.relative_to(REPO)} imports {mod}")
    assert not bad, "a lower layer imports the entry package:\n" + "\n".join(bad)


def test_stages_and_renderer_do_not_import_ground_truth():
    bad = []
    for sub in NO_GROUNDTRUTH:
        for py in (REPO / sub).rglob("*.py"):
            for mod in _imports(py):
                if mod.startswith("illuminet.runtime.groundtruth"):
                    bad.append(f"{py.relative_to(REPO)} imports {mod}")
    assert not bad, "ground truth used by a per-frame module:\n" + "\n".join(bad)


def test_the_runtime_floor_imports_only_the_floor():
    bad = []
    for py in (REPO / "runtime").glob("*.py"):
        if py.name == "relight.py":  # the one-shot relight API runs the stages (documented in runtime/__init__)
            continue
        for mod in _imports(py):
            if mod.startswith("illuminet.") and mod not in FLOOR_MAY_IMPORT and mod != "illuminet.runtime":
                bad.append(f"{py.relative_to(REPO)} imports {mod}")
    assert not bad, "the runtime floor imports a higher layer:\n" + "\n".join(bad)


def test_only_hw_touches_vendor_hardware_libraries():
    bad = []
    for folder in ALLOWED:
        if folder == "hw":
            continue
        for py in (REPO / folder).rglob("*.py"):
            src = py.read_text()
            for mod in _imports(py):
                if mod.split(".")[0] in VENDOR_HW:
                    bad.append(f"{py.relative_to(REPO)} imports {mod}")
            if "VideoCapture(" in src:
                bad.append(f"{py.relative_to(REPO)} uses cv2.VideoCapture")
    assert not bad, "hardware access outside hw/:\n" + "\n".join(bad)
