"""Shared pytest fixtures."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def gl_context():
    """A headless (EGL) moderngl context for the whole session; skips when none can be made."""
    from garmentnerf.gl.context import GLUnavailableError, create_context

    try:
        ctx = create_context(headless=True)
    except GLUnavailableError as exc:
        pytest.skip(f"no headless OpenGL: {exc}")
    yield ctx
    ctx.release()
