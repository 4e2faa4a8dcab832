"""How a frame is baked and drawn: :class:`BakeSettings` and the measured presets (no torch here, so the command
line answers ``--help`` and refuses a bad preset without loading the model stack)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

#: The render preset every capture uses: the bake keeps what the best view shows.
CAPTURE_PRESET = "full"


@dataclass(frozen=True)
class BakeSettings:
    """How a frame is baked and drawn."""

    name: str
    """The preset's name (:data:`BAKE_PRESETS`), or ``custom``."""
    views: int
    """Capture cameras on the training ring, evenly spaced in azimuth (16: every 22.5 degrees)."""
    quality: float
    """Each capture's pixel density, as a fraction of the density the model was trained at (its cost
    goes with the square)."""
    draw_views: int = 2
    """Captures a view draws, the nearest in angle, blended by angle."""
    mesh_step: int = 1
    """Map pixels between the vertices of a view's mesh (the attributes stay at the maps' resolution)."""

    def __post_init__(self) -> None:
        if not 3 <= int(self.views) <= 64:
            raise ValueError(f"bake views must be in 3..64, got {self.views}")
        if not 0.0625 <= float(self.quality) <= 2.0:
            raise ValueError(f"bake quality must be in 0.0625..2, got {self.quality}")
        if not 1 <= int(self.draw_views) <= 4:
            raise ValueError(f"bake draw views must be in 1..4, got {self.draw_views}")
        if int(self.mesh_step) not in (1, 2, 4):
            raise ValueError(f"bake mesh step must be 1, 2 or 4, got {self.mesh_step}")

    def capture_key(self) -> dict:
        """What changes the baked files (the draw settings do not)."""
        return {"views": int(self.views), "quality": float(self.quality), "preset": CAPTURE_PRESET}

    def to_dict(self) -> dict:
        return asdict(self)


#: The measured trades (``docs/results.md``, "Baked frames"), fastest first.
BAKE_PRESETS: dict[str, BakeSettings] = {
    "draft": BakeSettings("draft", views=8, quality=0.5),
    "balanced": BakeSettings("balanced", views=16, quality=0.75),
    "fine": BakeSettings("fine", views=16, quality=1.0),
}
#: The preset ``garmentnerf bake`` and the previewer use unless told otherwise.
DEFAULT_BAKE_PRESET = "balanced"


def bake_settings(name: str) -> BakeSettings:
    """The preset ``name`` of :data:`BAKE_PRESETS`; ValueError naming the choices otherwise."""
    try:
        return BAKE_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown bake preset {name!r} (choose from {', '.join(BAKE_PRESETS)})") from None


__all__ = ["BakeSettings", "BAKE_PRESETS", "DEFAULT_BAKE_PRESET", "CAPTURE_PRESET", "bake_settings"]
