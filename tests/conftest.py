"""Shared test fixtures: the one GL context, the path to ../shared/data, and markers' skips."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

os.environ.setdefault("DEPTHAI_TELEMETRY", "0")

REPO = Path(__file__).resolve().parent.parent


def relight_argv(tmp_path: Path, change: dict) -> list[str]:
    """``illuminet relight`` on the small 64x48 inputs (``c.png``, ``d.png`` in ``tmp_path``) with the
    flags in ``change`` (``{"--flag": value}``) replaced or added; ``{tmp}`` in a value is ``tmp_path``.
    Written ``--flag=value``: values such as "-5,100" or "" would read as flags otherwise."""
    opts = {
        "--color": "{tmp}/c.png",
        "--depth": "{tmp}/d.png",
        "--intrinsics": "60,60,32,24",
        "--anchor": "32,40",
        "--out": "{tmp}/r.npz",
        **change,
    }
    return ["relight"] + [f"{k}={v}".replace("{tmp}", str(tmp_path)) for k, v in opts.items()]


def _shared_data_dir() -> Path:
    """../shared/data beside the checkout; ILLUMINET_SHARED_DATA overrides (e.g. for git worktrees)."""
    env = os.environ.get("ILLUMINET_SHARED_DATA")
    if env:
        return Path(env)
    for base in (REPO.parent, REPO.parent.parent):  # a checkout, or a worktree one level deeper
        if (base / "shared" / "data").is_dir():
            return base / "shared" / "data"
    return REPO.parent / "shared" / "data"


SHARED_DATA = _shared_data_dir()

# ---- Hypothesis (tests/test_fuzz.py) ------------------------------------------------------------------
# "illuminet": the default suite's profile. No deadline: on a shared 2-core machine an example's time is
# no property (the fuzz tests bound wall-clock time themselves, generously). "illuminet-slow": loaded for
# `-m slow` runs, where the fuzz tests' "thorough" variants run 25x the examples; it prints statistics.
# HYPOTHESIS_PROFILE=NAME picks one explicitly.
try:
    from hypothesis import HealthCheck, settings

    _slow_checks = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
    settings.register_profile("illuminet", max_examples=20, deadline=None, suppress_health_check=_slow_checks)
    settings.register_profile(
        "illuminet-slow", max_examples=500, deadline=None, suppress_health_check=_slow_checks, print_blob=True
    )
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "illuminet"))
except ImportError:  # pragma: no cover - hypothesis is in the test extra; only the fuzz tests need it
    settings = None


def pytest_configure(config):
    markexpr = config.getoption("markexpr", "") or ""
    if settings is not None and "HYPOTHESIS_PROFILE" not in os.environ:
        if "slow" in markexpr and "not slow" not in markexpr:
            settings.load_profile("illuminet-slow")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real captured data); tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (tests on real captures need it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def gl_ctx():
    """One standalone EGL OpenGL context for the whole run (created in one place, as moderngl's tests do).

    Desktop GL or OpenGL ES as ``$ILLUMINET_GL_API`` says (default auto): ``ILLUMINET_GL_API=gles``
    runs every GL test on an ES 3.x context (tests/test_render_gles.py does so for test_render.py).
    """
    pytest.importorskip("moderngl")
    from illuminet.runtime.render.gl import GLError, get_context

    try:
        ctx = get_context("egl")  # the runtime's own shared context (illuminet.runtime.render.gl)
    except GLError as e:  # no EGL / GL driver on this machine
        pytest.skip(f"no OpenGL context via EGL: {e}")
    yield ctx


@pytest.fixture
def gl(gl_ctx):
    """The GL context, checked for GL errors before and after the test."""
    from illuminet.runtime.render.gl import make_current

    make_current(gl_ctx)  # another test may have created and released a context of its own
    assert gl_ctx.error == "GL_NO_ERROR", f"GL error left by an earlier test: {gl_ctx.error}"
    yield gl_ctx
    make_current(gl_ctx)  # the renderer lets the context go after drawing (gl.using): read its errors
    err = gl_ctx.error
    assert err == "GL_NO_ERROR", f"test left a GL error: {err}"


# ---- browser tests (marker ``browser``): Playwright driving Debian's Chromium ------------------------
# Playwright's own browser download does not work everywhere (no network, no glibc match); the system
# Chromium does (apt-get install chromium). ILLUMINET_CHROMIUM names another executable.
CHROMIUM = os.environ.get("ILLUMINET_CHROMIUM", "/usr/bin/chromium")
#: WebGL without a GPU: Chromium's software rasteriser (SwiftShader), which it only uses when asked
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--mute-audio"]


def browser_unavailable() -> str | None:
    """Why the browser tests cannot run here, or None when Playwright and Chromium are present."""
    if importlib.util.find_spec("playwright") is None:
        return "Playwright is not installed (pip install playwright)"
    if not os.access(CHROMIUM, os.X_OK):
        return f"no Chromium at {CHROMIUM} (apt-get install chromium, or set ILLUMINET_CHROMIUM)"
    return None


def pytest_report_header(config):
    why = browser_unavailable()
    return f"browser tests: {'run with ' + CHROMIUM if why is None else 'SKIPPED: ' + why}"


@pytest.fixture(scope="session")
def chromium():
    """One headless Chromium for the session (launching costs ~1 s); skips with the reason when absent."""
    why = browser_unavailable()
    if why is not None:
        pytest.skip(f"browser tests skipped: {why}")
    from playwright.sync_api import sync_playwright

    pw = sync_playwright().start()
    try:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    except Exception:
        pw.stop()
        raise
    yield browser
    browser.close()
    pw.stop()


@pytest.fixture
def page(chromium):
    """A fresh page (320x240) that records console errors and uncaught exceptions in ``page.problems``."""
    ctx = chromium.new_context(viewport={"width": 320, "height": 240})
    pg = ctx.new_page()
    problems: list[str] = []
    pg.on("console", lambda m: problems.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))
    pg.problems = problems
    yield pg
    ctx.close()
