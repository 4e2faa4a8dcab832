"""Baking one frame: K network renders of its garment from a ring of cameras, kept as views.

:func:`capture_frame` renders the frame from :func:`~garmentnerf.bake.views.ring_cameras` through the one
render path (:meth:`~garmentnerf.render.session.RenderSession.render`, the ``full`` preset, without the
body layer) and keeps each render as a :class:`~garmentnerf.bake.views.BakedView`. The trade between bake
time, size and fidelity is a :class:`BakeSettings`; :data:`BAKE_PRESETS` holds the measured ones.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

from garmentnerf.bake.views import BakedFrame, ring_cameras, view_from_render

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


def check_can_bake(session) -> None:
    """ValueError of one line when ``session`` cannot be baked: a bake carries the garment only, over the
    rasterised body (the ``raster_body`` composition, which needs the run's body appearance)."""
    if session.composition != "raster_body":
        raise ValueError("baking needs a run with a body appearance (the raster_body composition); "
                         "make one with `garmentnerf body fit-appearance`")


def capture_frame(session, frame: int, settings: BakeSettings, should_cancel: Callable[[], bool] | None = None,
                  on_view: Callable[[int, int], None] | None = None) -> BakedFrame:
    """Bake body frame ``frame`` of ``session``'s motion (module docstring).

    Args:
        should_cancel: polled while rendering; True raises
            :class:`~garmentnerf.model.pipeline.RenderCancelled`.
        on_view: called with (views done, views) after each capture.
    """
    check_can_bake(session)
    frame = session.check_frame(frame)
    up = 2 ** session.config.decoder.upsample_steps
    cameras = ring_cameras(session.training_views, session.body_center(frame)[:2], settings.views)
    views = []
    for i, camera in enumerate(cameras):
        nf = session.render(frame, camera, settings.quality, preset=CAPTURE_PRESET, should_cancel=should_cancel,
                            body_layer=False)
        map_camera = camera.resized(*nf.render_size)
        view = view_from_render(nf.maps, map_camera, nf.surface_depth, up)
        if view is not None:
            views.append(view)
        if on_view is not None:
            on_view(i + 1, len(cameras))
    body = session.posed.vertices[frame].detach().to("cpu").float().numpy()
    return BakedFrame(int(frame), tuple(views), body)


__all__ = ["BakeSettings", "BAKE_PRESETS", "DEFAULT_BAKE_PRESET", "CAPTURE_PRESET", "bake_settings",
           "check_can_bake", "capture_frame"]
