"""The window: GLFW, its OpenGL context (moderngl), imgui (native backends) and HiDPI.

:class:`Window` is one GLFW window with a GL >= 3.3 core context wrapped by moderngl and an imgui
context drawn with imgui's own GLFW and OpenGL3 backends. The app drives it once per UI frame:
:meth:`Window.begin_frame` (make current, sizes, minimised?), :meth:`Window.new_ui_frame`, the app's
drawing, :meth:`Window.draw_ui`, :meth:`Window.swap`.

GLFW is process-wide: it is initialised by the first window and terminated when the last one
closes. :class:`WindowSystem` keeps that count (and the handle of the process's libEGL, see
:meth:`WindowSystem.release_egl_context`) under a lock; :func:`window_system` returns the one
instance of the process.

HiDPI: the scene renders at the framebuffer size (pixels), imgui lays out in window units and its
fonts are scaled by the window's content scale divided by the framebuffer/window ratio (on macOS the
ratio already carries the scale; on Linux/Windows the content scale does).
"""

from __future__ import annotations

import ctypes
import functools
import math
import os
import threading
from pathlib import Path

import imgui_bundle

from garmentnerf.gl.context import GLUnavailableError, create_context
from garmentnerf.viewer.gui_libs import glfw, imgui


class NoDisplayError(RuntimeError):
    """No window can be opened (no X/Wayland display, or GLFW cannot initialise)."""


def display_available() -> bool:
    """Whether a window system is named in the environment (X11 or Wayland)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _glfw_error() -> str:
    """`` (GLFW's last error)`` for a message, or ``""``."""
    try:
        code, description = glfw.get_error()
    except Exception:  # noqa: BLE001 - best effort only
        return ""
    if not code:
        return ""
    text = description.decode(errors="replace") if isinstance(description, bytes) else str(description)
    return f" ({' '.join(text.split())})" if text else ""


class WindowSystem:
    """GLFW for this process: initialised by the first window, terminated after the last (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open_windows = 0
        self._egl = None  # libEGL once the process has loaded it (it stays loaded)

    def open(self, width: int, height: int, title: str, visible: bool):
        """A new GLFW window with an OpenGL 3.3 core context (no default depth/stencil: the scene has
        its own). Raises NoDisplayError when GLFW cannot initialise, GLUnavailableError when no such
        window opens."""
        with self._lock:
            glfw.ERROR_REPORTING = "log"  # debug-level log; failures are reported below as one line
            if not glfw.init():
                raise NoDisplayError(f"GLFW cannot initialise{_glfw_error()}")
            glfw.default_window_hints()
            for hint, value in ((glfw.CONTEXT_VERSION_MAJOR, 3), (glfw.CONTEXT_VERSION_MINOR, 3),
                                (glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE), (glfw.OPENGL_FORWARD_COMPAT, True),
                                (glfw.SCALE_TO_MONITOR, True), (glfw.VISIBLE, bool(visible)),
                                (glfw.DEPTH_BITS, 0), (glfw.STENCIL_BITS, 0)):
                glfw.window_hint(hint, value)
            self._release_egl_context()
            handle = glfw.create_window(width, height, title, None, None)
            if not handle:
                if self._open_windows == 0:
                    glfw.terminate()

                raise GLUnavailableError(f"cannot open a window with an OpenGL 3.3 core context{_glfw_error()}")
            self._open_windows += 1
            return handle

    def close(self, handle) -> None:
        """Destroy a window :meth:`open` made; the last one terminates GLFW."""
        with self._lock:
            glfw.destroy_window(handle)
            self._open_windows -= 1
            if self._open_windows == 0:
                glfw.terminate()

    def make_current(self, handle) -> None:
        """Make a window's GL context current on this thread (see :meth:`release_egl_context`)."""
        self.release_egl_context()
        glfw.make_context_current(handle)

    def release_egl_context(self) -> None:
        """Unbind an EGL context current on this thread (e.g. a headless one made earlier in the process).

        With Mesa, a glXMakeCurrent fails with BadAccess while an EGL context is current on the
        thread when no GLX context was current before (seen for the process's first, and for the
        first after another window was destroyed), and Xlib's default handler then exits the
        process. A window therefore calls this before each make-current (a few microseconds).
        eglReleaseThread unbinds it; the EGL context stays valid and is made current again by
        whoever uses it next (garmentnerf's passes always make their context current first). Only
        done when libEGL is already loaded: otherwise no EGL context can be current.
        """
        with self._lock:
            self._release_egl_context()

    def _release_egl_context(self) -> None:
        if self._egl is None and hasattr(os, "RTLD_NOLOAD"):
            for name in ("libEGL.so.1", "libEGL.so"):
                try:
                    self._egl = ctypes.CDLL(name, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
                    break
                except OSError:
                    continue
        if self._egl is None:
            return
        try:
            self._egl.eglGetCurrentContext.restype = ctypes.c_void_p
            if self._egl.eglGetCurrentContext():
                self._egl.eglReleaseThread()
        except AttributeError:
            pass


@functools.cache
def window_system() -> WindowSystem:
    """The process's one :class:`WindowSystem` (GLFW itself is process-wide)."""
    return WindowSystem()


def _font_path() -> str | None:
    path = Path(imgui_bundle.__file__).parent / "assets" / "fonts" / "Roboto" / "Roboto-Regular.ttf"
    return str(path) if path.is_file() else None


class Window:
    """One GLFW window, its moderngl context (:attr:`ctx`) and its imgui context.

    Args:
        width, height: window size in screen units; title: the window's title.
        vsync: swap interval 1 (else 0: run flat out); visible: show the window (tests may hide it).
        system: the :class:`WindowSystem` (default: the process's).
    Attributes:
        handle: the GLFW window; framebuffer_size (pixels) and window_size (screen units) as
            (W, H); content_scale: the monitor's scale; minimized: nothing to draw into.
    Raises:
        NoDisplayError, GLUnavailableError: see :meth:`WindowSystem.open`.
    """

    def __init__(self, width: int, height: int, title: str, vsync: bool = True, visible: bool = True,
                 system: WindowSystem | None = None) -> None:
        self.system = system or window_system()
        self.handle = self.system.open(width, height, title, visible)
        self.framebuffer_size, self.window_size = (0, 0), (0, 0)
        self.content_scale = 1.0
        self.minimized = False
        self.imgui_ctx = None
        self._ui_scale = 1.0
        try:
            glfw.make_context_current(self.handle)
            glfw.swap_interval(1 if vsync else 0)
            self.ctx = create_context(headless=False)
            self.gl_renderer = str(self.ctx.info.get("GL_RENDERER", ""))
            self._init_imgui()
        except BaseException:
            self.system.close(self.handle)
            self.handle = None
            raise
        self.update_sizes()

    def _init_imgui(self) -> None:
        self.imgui_ctx = imgui.create_context()
        imgui.set_current_context(self.imgui_ctx)
        io = imgui.get_io()
        io.set_ini_filename("")  # no imgui.ini in the working directory
        io.set_log_filename("")
        imgui.style_colors_dark()
        style = imgui.get_style()
        style.window_rounding = 4.0
        style.frame_rounding = 3.0
        font = _font_path()
        if font:
            io.fonts.add_font_from_file_ttf(font, 15.0)
        else:
            io.fonts.add_font_default()
        imgui.backends.glfw_init_for_opengl(ctypes.cast(self.handle, ctypes.c_void_p).value, True)
        imgui.backends.opengl3_init("#version 330 core")

    # ---- per frame --------------------------------------------------------------------------------
    def make_current(self) -> None:
        """The window's GL context and imgui context current on this thread."""
        self.system.make_current(self.handle)
        imgui.set_current_context(self.imgui_ctx)

    def update_sizes(self) -> None:
        """Read the framebuffer and window sizes, the content scale and whether it is minimised."""
        self.framebuffer_size = tuple(glfw.get_framebuffer_size(self.handle))
        self.window_size = tuple(glfw.get_window_size(self.handle))
        sx, _ = glfw.get_window_content_scale(self.handle)
        self.content_scale = float(sx) if math.isfinite(sx) and sx > 0 else 1.0
        self.minimized = (min(*self.framebuffer_size, *self.window_size) <= 0
                          or bool(glfw.get_window_attrib(self.handle, glfw.ICONIFIED)))

    def begin_frame(self) -> bool:
        """Make current and read the sizes; False while minimised (nothing to draw into)."""
        self.make_current()
        self.update_sizes()
        return not self.minimized

    def new_ui_frame(self) -> None:
        """Start imgui's frame (after :meth:`begin_frame`): UI scale, backends, input."""
        self._update_ui_scale()
        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        imgui.new_frame()

    def draw_ui(self) -> None:
        """Draw imgui's frame (ended with ``imgui.render()``) on top of what the window shows."""
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())

    def _update_ui_scale(self) -> None:
        """Fonts and paddings follow the content scale (see the module doc for the HiDPI rule)."""
        fb_w, win_w = self.framebuffer_size[0], self.window_size[0]
        ratio = fb_w / win_w if fb_w > 0 and win_w > 0 else 1.0
        scale = min(4.0, max(0.5, self.content_scale / max(ratio, 1e-6)))
        if abs(scale - self._ui_scale) > 1e-3:
            style = imgui.get_style()
            style.scale_all_sizes(scale / self._ui_scale)
            style.font_scale_dpi = scale
            self._ui_scale = scale

    def swap(self) -> None:
        glfw.swap_buffers(self.handle)

    # ---- events -----------------------------------------------------------------------------------
    @staticmethod
    def poll_events() -> None:
        glfw.poll_events()

    @staticmethod
    def wait_events(timeout: float) -> None:
        glfw.wait_events_timeout(timeout)

    @property
    def should_close(self) -> bool:
        return bool(glfw.window_should_close(self.handle))

    def request_close(self) -> None:
        glfw.set_window_should_close(self.handle, True)

    def set_title(self, title: str) -> None:
        glfw.set_window_title(self.handle, title)

    def close(self) -> None:
        """Free imgui and the window (idempotent); GL objects made on :attr:`ctx` go first (the caller's)."""
        if self.handle is None:
            return
        self.make_current()
        imgui.backends.opengl3_shutdown()
        imgui.backends.glfw_shutdown()
        imgui.destroy_context(self.imgui_ctx)
        self.imgui_ctx = None
        self.system.close(self.handle)
        self.handle = None
