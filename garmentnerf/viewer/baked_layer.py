"""The baked layer: a baked frame's garment drawn from the window's camera, at display rate.

:class:`BakedLayer` is a scene renderable (drawn after the body, before the neural layer). It draws the
:class:`~garmentnerf.bake.views.BakedFrame` it is given with :class:`~garmentnerf.bake.draw.BakeDrawer`
(the nearest captures, blended by angle, hidden behind the body by depth) and composes it with the
palette in the fragment shader, premultiplied over the body the scene drew in its learned appearance:
the same sum as :func:`~garmentnerf.model.palette.compose`, so recolouring stays exact and costs no
network call. The neural view chooses when it shows (:mod:`~garmentnerf.viewer.neural_view`): a baked
frame while the camera moves or the clip plays, a reprojection of the last neural image of the frame
when the frame has no bake, and the exact neural image once the camera rests.
"""

from __future__ import annotations

import moderngl
import numpy as np

from garmentnerf.bake.draw import BakeDrawer
from garmentnerf.bake.views import BakedFrame
from garmentnerf.viewer.renderables import PassState, ViewParams

#: Map pixels between the vertices of the view meshes the window draws: llvmpipe's cost goes with the
#: triangles (the attributes stay textures at the maps' resolution).
WINDOW_MESH_STEP = 2
#: The bake's own passes set their state; the scene's pass state for this layer is "nothing".
_OWN_STATE = PassState(moderngl.NOTHING)


class BakedLayer:
    """See the module docstring.

    Attributes:
        visible: draw :attr:`frame` (set by the neural view every UI frame).
        frame: the :class:`~garmentnerf.bake.views.BakedFrame` to draw, or None.
        palette: (P, 3) the palette (the body's colour last).
    """

    def __init__(self, ctx: moderngl.Context, draw_views: int = 2, mesh_step: int = WINDOW_MESH_STEP) -> None:
        self.ctx = ctx
        self.drawer = BakeDrawer(ctx, draw_views, mesh_step)
        self.visible = False
        self.frame: BakedFrame | None = None
        self.palette: np.ndarray | None = None
        self.body_key: object = None
        self._body: tuple | None = None  # (vertices (V, 3), faces (F, 3)) of body_key, until uploaded

    def set_body(self, key: object, vertices: np.ndarray, faces: np.ndarray) -> None:
        """The posed body the garment is hidden behind (uploaded at the next draw when ``key`` is new)."""
        if key != self.body_key:
            self.body_key = key
            self._body = (np.ascontiguousarray(vertices[:, :3], np.float32), np.asarray(faces))

    @property
    def showing(self) -> bool:
        """Whether a draw now shows a garment."""
        return self.visible and self.frame is not None and bool(self.frame.views) and self.palette is not None

    def prepare(self, view: ViewParams | None = None) -> None:
        if self._body is not None:
            self.drawer.set_body(self.body_key, *self._body)
            self._body = None

    def pass_state(self) -> PassState:
        return _OWN_STATE

    def draw(self, view: ViewParams) -> None:
        if not self.showing:
            return
        target, viewport = self.ctx.fbo, self.ctx.viewport
        depth = target.depth_attachment
        body_depth = depth if isinstance(depth, moderngl.Texture) and viewport[:2] == (0, 0) else None
        self.drawer.compose_into(target, viewport, self.frame, view.camera, self.palette, view.proj, body_depth)
        target.use()
        self.ctx.viewport = viewport

    def release(self) -> None:
        self.drawer.release()


__all__ = ["BakedLayer", "WINDOW_MESH_STEP"]
