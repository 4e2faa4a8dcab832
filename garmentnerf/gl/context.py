"""Creating the OpenGL context the passes run on.

Headless (tests, baking, the CLI) uses an EGL standalone context: on a machine without a GPU, Mesa's
llvmpipe software rasteriser provides GL 4.5 core. The desktop viewer wraps the context its window
already made current. There are no module-level GL objects: every program, buffer and framebuffer
belongs to a pass object built on one context, so several contexts can live in one process.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import moderngl

#: Lowest GL version the passes need (core profile): MRT, float targets, gl_PrimitiveID.
REQUIRED_GL_VERSION = 330

#: Debian/Ubuntu packages that provide headless EGL + Mesa.
EGL_DEBIAN_PACKAGES = "libegl1 libegl-mesa0 libgl1-mesa-dri"


class GLUnavailableError(RuntimeError):
    """No OpenGL >= 3.3 core context could be created."""


def create_context(headless: bool = True) -> moderngl.Context:
    """A moderngl context with GL >= 3.3 core.

    Args:
        headless: True for an EGL standalone context (no window, no display needed); False to wrap
            the GL context that is current on this thread (e.g. a GLFW window's).

    Raises:
        GLUnavailableError: when no such context can be created (message names the fix).
    """
    try:
        if headless:
            ctx = moderngl.create_standalone_context(require=REQUIRED_GL_VERSION, backend="egl")
        else:
            ctx = moderngl.create_context(require=REQUIRED_GL_VERSION)
    except Exception as exc:  # moderngl raises plain Exception subclasses from its loaders
        what = "a headless EGL" if headless else "the current window's"
        detail = " ".join(str(exc).split()) or type(exc).__name__
        hint = (f"install the Debian packages {EGL_DEBIAN_PACKAGES}" if headless
                else "make a GL >= 3.3 core context current first")
        raise GLUnavailableError(
            f"cannot create {what} OpenGL >= 3.3 context ({detail}); {hint}") from exc
    if ctx.version_code < REQUIRED_GL_VERSION:
        version = ctx.version_code
        ctx.release()
        raise GLUnavailableError(
            f"OpenGL {version // 100}.{version % 100 // 10} found, 3.3 core needed; "
            f"install the Debian packages {EGL_DEBIAN_PACKAGES}")
    return ctx


def context_info(ctx: moderngl.Context) -> dict[str, str]:
    """Vendor, renderer and version strings of ``ctx`` (for logs and benchmarks)."""
    make_current(ctx)
    return {key: str(ctx.info.get(key, "")) for key in ("GL_VENDOR", "GL_RENDERER", "GL_VERSION")}


def make_current(ctx: moderngl.Context) -> moderngl.Context:
    """Make ``ctx`` the current GL context of this thread, and leave it current.

    moderngl puts new objects and draws on whichever context is current, so code that may share a
    process with other contexts makes its own current first. moderngl's ``with ctx:`` is not used
    for this: on exit it leaves *no* context current (EGL standalone), which breaks callers that
    go on using ``ctx`` directly. Costs a few microseconds.
    """
    ctx.__enter__()
    return ctx


def is_released(ctx: moderngl.Context) -> bool:
    """True once ``ctx.release()`` has run (its objects are gone with it)."""
    return type(ctx.mglo).__name__ == "InvalidObject"


@contextmanager
def current(ctx: moderngl.Context) -> Iterator[moderngl.Context]:
    """``with current(ctx):`` -- :func:`make_current` for a block; ``ctx`` stays current after it."""
    yield make_current(ctx)
