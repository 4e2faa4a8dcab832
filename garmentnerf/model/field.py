"""The field interface: what the pipeline, the renderer and the trainer ask of the network that gives
each sample its density and appearance.

A field is handed the frame's features (:class:`~garmentnerf.model.frame_context.FrameFeatures`:
F^s_t, F^d_t, the posed body) and the samples' body points
(:class:`~garmentnerf.geometry.body_points.BodyPoints`: b_t, h, b_o, the atlas UV and the skin
face), and returns sigma and zeta. Where the samples come from (the sampler), which of them are
kept (a sample filter) and how they are composited (the volume rendering) are not its business.
The paper's field is :class:`~garmentnerf.model.nerf_mlp.GarmentNeRF`; another field subclasses
:class:`Field` and is built in :meth:`GarmentAnimationNeRF.__init__
<garmentnerf.model.pipeline.GarmentAnimationNeRF>`, the one place a field is chosen.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING

import torch
from torch import nn

if TYPE_CHECKING:
    from garmentnerf.geometry.body_points import BodyPoints
    from garmentnerf.model.frame_context import FrameFeatures

#: ``clock(stage)`` -> a context that adds its wall time to the render's timings of ``stage``
#: (``"features"``: reading the frame's maps at the samples; ``"mlp"``: the network).
StageClock = Callable[[str], AbstractContextManager]


class Field(nn.Module):
    """Density and appearance of samples from their body points (an interface)."""

    #: Channels of the zeta :meth:`evaluate` returns (what the volume rendering composites).
    zeta_channels: int

    def evaluate(self, frame: FrameFeatures, points: BodyPoints, *, clock: StageClock,
                 autocast: AbstractContextManager) -> tuple[torch.Tensor, torch.Tensor]:
        """sigma ``(n,)`` (1/metre, >= 0) and zeta ``(n, zeta_channels)``, float32 on the field's device, of
        the ``n`` samples whose body points are ``points`` in ``frame``; the network runs inside
        ``autocast`` (the render's precision), each stage inside ``clock(stage)``."""
        raise NotImplementedError


__all__ = ["Field", "StageClock"]
