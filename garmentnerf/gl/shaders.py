"""Loading the project's GLSL (the ``garmentnerf/shaders/`` folder, the package ``garmentnerf.shaders``).

Programs are never cached here: each pass object builds its own programs on its own context, so
several contexts in one process never share GL objects.
"""

from __future__ import annotations

import re
from importlib.resources import files
from importlib.resources.abc import Traversable

import moderngl


def shader_root() -> Traversable:
    """The folder that holds the GLSL files: the package ``garmentnerf.shaders``."""
    return files("garmentnerf.shaders")


_VERSION_LINE = re.compile(r"^[ \t]*#version[^\n]*\n", re.MULTILINE)


def shader_source(name: str, defines: dict[str, object] | None = None) -> str:
    """The text of ``shaders/<name>``, with ``#define KEY VALUE`` lines inserted after ``#version``."""
    path = shader_root() / name
    if not path.is_file():
        raise FileNotFoundError(f"GLSL file {name!r} not found in {shader_root()}")
    source = path.read_text(encoding="utf-8")
    if defines:
        lines = "".join(f"#define {key} {value}\n" for key, value in defines.items())
        match = _VERSION_LINE.search(source)
        if match is None:
            source = lines + source
        else:
            source = source[: match.end()] + lines + source[match.end():]
    return source


def build_program(ctx: moderngl.Context, vertex: str, fragment: str,
                  defines: dict[str, object] | None = None) -> moderngl.Program:
    """Compile and link ``shaders/<vertex>`` + ``shaders/<fragment>`` on ``ctx``."""
    return ctx.program(vertex_shader=shader_source(vertex, defines),
                       fragment_shader=shader_source(fragment, defines))
