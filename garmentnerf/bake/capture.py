"""Baking one frame: K network renders of its garment from a ring of cameras, kept as views.

:func:`capture_frame` renders the frame from :func:`~garmentnerf.bake.views.ring_cameras` through the one
render path (:meth:`~garmentnerf.render.session.RenderSession.render`, the ``full`` preset, without the
body layer) and keeps each render as a :class:`~garmentnerf.bake.views.BakedView`. The trade between bake
time, size and fidelity is a :class:`~garmentnerf.bake.settings.BakeSettings`
(:data:`~garmentnerf.bake.settings.BAKE_PRESETS` holds the measured ones).
"""

from __future__ import annotations

from collections.abc import Callable

from garmentnerf.bake.settings import CAPTURE_PRESET, BakeSettings
from garmentnerf.bake.views import BakedFrame, ring_cameras, view_from_render


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


__all__ = ["check_can_bake", "capture_frame"]
