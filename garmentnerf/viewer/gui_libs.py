"""The windowing libraries, imported in the one order that works.

``imgui_bundle`` ships its own ``libglfw`` and, on import, points the ``glfw`` Python package at it;
importing ``glfw`` first would load a second libglfw, and imgui's native GLFW backend would then
talk to a library that never saw our window. Every viewer module imports them from here.
"""

from __future__ import annotations

from imgui_bundle import imgui  # noqa: I001 - must come before glfw

import glfw  # noqa: E402

__all__ = ["imgui", "glfw"]
