"""The folders import one way: runtime is the floor, the entry package is the top (DESIGN.md §1)."""

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
