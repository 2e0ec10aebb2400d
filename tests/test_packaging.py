"""The package list in pyproject.toml covers every folder with Python code, and a built wheel imports."""

from __future__ import annotations

import subprocess
import sys
import zipfile

import tomllib

from .conftest import REPO


def _declared():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    return cfg["packages"], cfg["package-dir"]


def _folder(pkg: str, package_dir: dict[str, str]) -> str:
    """The source folder of ``pkg`` under the package-dir mapping (longest mapped prefix wins)."""
    best = max((p for p in package_dir if pkg == p or pkg.startswith(p + ".")), key=len)
    rest = pkg[len(best) :].lstrip(".")
    return "/".join([package_dir[best]] + ([rest.replace(".", "/")] if rest else []))


def test_every_python_folder_is_a_declared_package():
    packages, package_dir = _declared()
    declared = {_folder(p, package_dir) for p in packages}
    on_disk = set()
    for top in ("illuminet", "runtime", "hw", "models", "calibration"):
        for init in (REPO / top).rglob("__init__.py"):
            on_disk.add(str(init.parent.relative_to(REPO)))
    assert on_disk - declared == set(), f"folders missing from pyproject's packages: {sorted(on_disk - declared)}"
    assert declared - on_disk == set(), f"declared packages without a folder: {sorted(declared - on_disk)}"
    for d in on_disk:  # a folder of modules without __init__.py would silently drop out of the wheel
        for py in (REPO / d).iterdir():
            if py.is_dir() and any(py.glob("*.py")):
                assert (py / "__init__.py").is_file(), f"{py.relative_to(REPO)} has modules but no __init__.py"


def test_built_wheel_imports_every_package(tmp_path):
    """Build the wheel (pip fetches the build backend pyproject names: setuptools>=69), unpack it into a fresh
    target folder and import every declared package from there."""
    packages, _ = _declared()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "-q",
            "-w",
            str(tmp_path / "dist"),
            str(REPO),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    whl = next((tmp_path / "dist").glob("illuminet-*.whl"))
    names = zipfile.ZipFile(whl).namelist()
    for p in packages:
        assert p.replace(".", "/") + "/__init__.py" in names, f"{p} is not in the wheel"
    assert any(n.startswith("illuminet/models/bundles/") for n in names), "the shipped bundles are not in the wheel"
    # the browser pages work offline: pages, three.js (module build + addons + licence) and the schema ship
    stream = "illuminet/runtime/stream/"
    for f in (
        "light_estimate.schema.json",
        "static/index.html",
        "static/viewer.html",
        "static/viewer.js",
        "static/three/three.module.js",
        "static/three/three.core.js",
        "static/three/LICENSE",
        "static/three/addons/loaders/GLTFLoader.js",
        "static/three/addons/utils/BufferGeometryUtils.js",
    ):
        assert stream + f in names, f"{f} is not in the wheel (pyproject package-data)"
    zipfile.ZipFile(whl).extractall(tmp_path / "site")
    code = "import importlib,sys; [importlib.import_module(p) for p in sys.argv[1:]]; import illuminet.cli"
    r = subprocess.run(
        [sys.executable, "-c", code, *packages],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={"PYTHONPATH": str(tmp_path / "site"), "PATH": "/usr/bin:/bin"},
    )
    assert r.returncode == 0, r.stderr[-2000:]


def _wheel_check():
    """tools/check_aarch64_wheels.py as a module (tools/ is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("check_aarch64_wheels", REPO / "tools" / "check_aarch64_wheels.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_aarch64_requirements_take_the_releases_with_wheels():
    """On aarch64 with CPython <= 3.11 moderngl/glcontext are bounded to the last releases with aarch64
    wheels (else pip compiles the newest sources); elsewhere only moderngl >= 5.8 applies. The network
    side (what PyPI has) is tools/check_aarch64_wheels.py's, run by hand (docs/edge.md)."""
    check = _wheel_check()
    for py in ("3.10", "3.11"):
        reqs = check.requirements(py)
        assert "moderngl<5.9,>=5.8" in reqs and "glcontext<2.4,>=2.3.6" in reqs, reqs
        assert ("tomli>=2.0" in reqs) == (py == "3.10")
    for py in ("3.12", "3.13"):
        reqs = check.requirements(py)
        assert "moderngl>=5.8" in reqs and not any(r.startswith("glcontext") for r in reqs), reqs
    names = {r.split(">")[0].split("<")[0].split("=")[0] for r in check.requirements("3.11")}
    assert {"depthai", "opencv-contrib-python-headless", "onnxruntime", "moderngl", "numpy", "av"} <= names
