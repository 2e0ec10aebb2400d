"""Shared test fixtures: the one GL context, the path to ../shared/data, and markers' skips."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("DEPTHAI_TELEMETRY", "0")

REPO = Path(__file__).resolve().parent.parent

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


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real captured data); tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (tests on real captures need it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def gl_ctx():
    """One standalone EGL OpenGL context for the whole run (created in one place, as moderngl's tests do)."""
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
    err = gl_ctx.error
    assert err == "GL_NO_ERROR", f"test left a GL error: {err}"
