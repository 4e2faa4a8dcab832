"""Colors on the command line and in the viewer: ``#rrggbb`` / ``#rgb`` hex, and palettes.

Palette order is the model's: the garment's colors first (one, p_G; or one per layer of a layered
garment, inner first), the body/other (p_B) last (:func:`garmentnerf.model.pipeline.palette_initial_colors`,
:func:`garmentnerf.model.palette.palette_names`).
"""

from __future__ import annotations

import re

import numpy as np
import torch

from garmentnerf.ranges import parse_list

_HEX = re.compile(r"^#?([0-9a-fA-F]{6}|[0-9a-fA-F]{3})$")


def parse_hex_color(text: str, what: str = "color") -> tuple[float, float, float]:
    """``'#c03030'`` (or ``c03030``, ``#c33``) -> RGB in [0, 1]; ValueError with a one-line message."""
    t = str(text).strip()
    m = _HEX.match(t)
    if not m:
        raise ValueError(f"{what} '{text}' is not a hex color; use #rrggbb (e.g. #c03030)")
    h = m.group(1)
    if len(h) == 3:
        h = "".join(c * 2 for c in h)
    return tuple(int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4))


def to_hex(rgb) -> str:
    """RGB in [0, 1] -> ``'#rrggbb'``."""
    r, g, b = (int(round(float(np.clip(c, 0.0, 1.0)) * 255)) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"


def build_palette(learned: torch.Tensor, colors: str | None = None, body: str | None = None) -> torch.Tensor:
    """The palette to compose with: the learned one, with colors replaced.

    Args:
        learned: (P, 3) learned palette.
        colors: ``'#garment'`` or ``'#c0,#c1,...'`` replacing colors 0, 1, ... (``-`` keeps that learned
            color; an empty item or list is refused: :func:`~garmentnerf.ranges.parse_list`); None keeps
            them all.
        body: replaces the last color (the body/other color).
    """
    pal = learned.detach().to("cpu", torch.float32).clone()
    P = pal.shape[0]
    if colors is not None:
        items = parse_list(colors, "--palette", kind="colour ('-' keeps one)")
        if all(item == "-" for item in items):
            raise ValueError(f"--palette {colors!r} names no color (give '#rrggbb' items; '-' keeps one)")
        if len(items) > P:
            raise ValueError(f"--palette has {len(items)} colors but the model's palette has {P}")
        for i, item in enumerate(items):
            if item == "-":
                continue
            pal[i] = torch.tensor(parse_hex_color(item, f"palette color {i}"))
    if body is not None:
        if P < 2:
            raise ValueError("the model's palette has no body color (palette size 1)")
        pal[-1] = torch.tensor(parse_hex_color(body, "body color"))
    return pal


__all__ = ["parse_hex_color", "to_hex", "build_palette"]
