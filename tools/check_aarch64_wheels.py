#!/usr/bin/env python3
"""Does every runtime dependency install from a wheel on 64-bit ARM Linux (Raspberry Pi 5, Jetson)?

    python3 tools/check_aarch64_wheels.py                     (CPython 3.10, 3.11, 3.12, 3.13)
    python3 tools/check_aarch64_wheels.py --python 3.11       (one version; repeatable)

For each CPython version and each runtime dependency of pyproject.toml ([project] dependencies, with
their environment markers evaluated for linux/aarch64 and that version) it asks pip what it would
install there, with pip's own resolver and PyPI:

    pip download --no-deps --platform manylinux2014_aarch64 --platform manylinux_2_28_aarch64
                 --python-version 3.X -d TMP "<requirement>"

A wheel is what a board gets. A source archive means ``pip install`` on the board compiles (pip
prefers the newest version, even without a wheel); the check then asks again with
``--only-binary=:all:`` for the newest release that has a wheel, which is the bound to put into
pyproject.toml (see the moderngl/glcontext lines there). Prints one table per Python version
(requirement, what pip picks, its wheel tag) and exits 1 when anything is not a wheel, 2 when pip
or the network failed. Downloads go to a temporary folder that is removed (about 150 MB per
version pass through it). Needs network access to PyPI; run from anywhere.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PYTHONS = ("3.10", "3.11", "3.12", "3.13")
PLATFORMS = ("manylinux2014_aarch64", "manylinux_2_28_aarch64")


def _packaging():
    try:
        from packaging.requirements import Requirement
    except ImportError:  # pip vendors it
        from pip._vendor.packaging.requirements import Requirement
    return Requirement


def _load_toml(path: Path) -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            from pip._vendor import tomli as tomllib
    return tomllib.loads(path.read_text())


def requirements(python: str, pyproject: Path = REPO / "pyproject.toml") -> list[str]:
    """The runtime requirements that apply on linux/aarch64 under CPython ``python`` (markers dropped)."""
    Requirement = _packaging()
    env = {
        "python_version": python,
        "python_full_version": f"{python}.0",
        "platform_machine": "aarch64",
        "platform_system": "Linux",
        "sys_platform": "linux",
        "os_name": "posix",
        "implementation_name": "cpython",
        "platform_python_implementation": "CPython",
    }
    out = []
    for spec in _load_toml(pyproject)["project"]["dependencies"]:
        req = Requirement(spec)
        if req.marker is None or req.marker.evaluate(env):
            req.marker = None
            out.append(str(req))
    return out


_WHEEL = re.compile(r"^(?P<name>[^-]+)-(?P<version>[^-]+)(-\d[^-]*)?-(?P<py>[^-]+)-(?P<abi>[^-]+)-(?P<plat>.+)\.whl$")


def pip_pick(req: str, python: str, platforms, only_binary: bool, timeout: float) -> tuple[str, str]:
    """('wheel' | 'sdist' | 'none' | 'error', detail) for what pip downloads for ``req``."""
    tmp = Path(tempfile.mkdtemp(prefix="aarch64-wheels-"))
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check", "-q"]
    for p in platforms:
        cmd += ["--platform", p]
    cmd += ["--python-version", python, "-d", str(tmp)]
    if only_binary:
        cmd += ["--only-binary=:all:"]
    cmd.append(req)
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        files = [f.name for f in tmp.iterdir()]
    except subprocess.TimeoutExpired:
        return "error", f"pip timed out after {timeout:.0f} s"
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if r.returncode != 0:
        err = (r.stderr or r.stdout).strip().splitlines()
        last = err[-1] if err else f"pip exited {r.returncode}"
        if "No matching distribution" in last or "Could not find a version" in "\n".join(err):
            return "none", "no release matches"
        return "error", last
    if not files:
        return "error", "pip downloaded nothing"
    m = _WHEEL.match(files[0])
    if m:
        tag = m["plat"].split(".")
        return "wheel", f"{m['version']}  {m['py']}  {tag[-1] if len(tag) > 1 else tag[0]}"
    return "sdist", files[0]


def check(pythons, platforms, timeout: float) -> int:
    worst = 0
    for py in pythons:
        rows = []
        for req in requirements(py):
            kind, detail = pip_pick(req, py, platforms, only_binary=False, timeout=timeout)
            status = {"wheel": "ok", "sdist": "MISS", "none": "MISS", "error": "ERROR"}[kind]
            if kind == "sdist":
                k2, d2 = pip_pick(req, py, platforms, only_binary=True, timeout=timeout)
                newest = d2.split()[0] if k2 == "wheel" else "none"
                detail = f"{detail} (compiles on the board; newest wheel: {newest})"
            elif kind == "none":
                detail = "no release for this Python on aarch64"
            rows.append((req, status, detail))
            worst = max(worst, 2 if kind == "error" else (1 if status == "MISS" else 0))
        w = max(len(r[0]) for r in rows)
        print(f"\nCPython {py}, linux aarch64 ({', '.join(platforms)}):")
        print(f"  {'requirement':<{w}}  status  pip picks (version  python tag  platform tag)")
        for req, status, detail in rows:
            print(f"  {req:<{w}}  {status:<6}  {detail}")
        sys.stdout.flush()
    print()
    print(
        {
            0: "every runtime dependency installs from a wheel",
            1: "MISS: some dependency has no wheel (pip compiles it on the board, or cannot install it)",
            2: "ERROR: pip or the network failed (PyPI must be reachable)",
        }[worst]
    )
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--python", action="append", help=f"CPython version (repeatable; default {' '.join(PYTHONS)})")
    ap.add_argument("--platform", action="append", help=f"pip platform tag (repeatable; default {' '.join(PLATFORMS)})")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per pip download (default 300)")
    a = ap.parse_args(argv)
    return check(a.python or PYTHONS, a.platform or PLATFORMS, a.timeout)


if __name__ == "__main__":
    sys.exit(main())
