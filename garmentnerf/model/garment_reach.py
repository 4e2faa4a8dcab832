"""How far a scene's garment reaches from the body, against where the model can put it.

The model samples each frame inside the body's bounding box grown by :data:`~garmentnerf.model.config.BBOX_PADDING`
(:func:`~garmentnerf.model.samplers.padded_box`): garment outside that box can never be rendered.
And the field's density starts from a body prior (``body_prior_strength``, ``body_prior_width`` w:
:func:`~garmentnerf.model.nerf_mlp.body_density_prior`) that is negative beyond h = w and at its floor
beyond 2 w, where the trunc_exp density's gradient is ``e^-strength`` times smaller: cloth out there
is learned slowly, if at all. :func:`garment_reach` measures both on a scene's simulated garments,
every frame, with heights h measured to the posed skin exactly as the model measures its samples
(:func:`~garmentnerf.model.height_band.garment_frame_heights`), so a recipe's padding and prior can be
checked against a garment before any training (``garmentnerf data reach``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from garmentnerf.model.height_band import garment_frame_heights
from garmentnerf.model.samplers import body_aabb, padded_box

__all__ = ["SequenceReach", "garment_reach", "box_excess"]


def box_excess(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """(N,) how far each point of ``points (N, 3)`` lies outside the box ``box (2, 3)`` [min, max]
    along the axis where it sticks out most (0 inside): the padding that would take it in."""
    below = (box[0] - points).clamp_min(0.0)
    above = (points - box[1]).clamp_min(0.0)
    return torch.maximum(below, above).amax(dim=1)


@dataclass
class SequenceReach:
    """One sequence's garment against the sampling box and the density prior (metres, shares in [0, 1]).

    Attributes:
        sequence: its name; frames: frames measured (all of them).
        padding: the box padding measured against; prior_width: the prior's w.
        frames_outside_box: frames with garment vertices outside the padded body box.
        worst_outside_share, worst_outside_frame: the largest share of a frame's vertices outside it, and where.
        farthest_outside_m: the farthest a vertex lies outside it (so ``padding + farthest_outside_m`` holds all).
        h_p95_m: 95th percentile of the vertices' heights over all frames.
        h_max_m, h_max_frame: the largest height, and where.
        beyond_prior_zero_share: share of all vertices with h > w (where the prior is negative).
        worst_beyond_prior_zero_share, worst_beyond_prior_zero_frame: the largest such share in one frame, and where.
        at_prior_floor_share: share of all vertices with h > 2 w (the prior at -strength).
    """

    sequence: str
    frames: int
    padding: float
    prior_width: float
    frames_outside_box: int
    worst_outside_share: float
    worst_outside_frame: int
    farthest_outside_m: float
    h_p95_m: float
    h_max_m: float
    h_max_frame: int
    beyond_prior_zero_share: float
    worst_beyond_prior_zero_share: float
    worst_beyond_prior_zero_frame: int
    at_prior_floor_share: float

    def to_json(self) -> dict:
        return asdict(self)


def garment_reach(scene, body, padding: float, prior_width: float, sequences=None, projector=None,
                  betas=None) -> list[SequenceReach]:
    """Every frame of each sequence of ``scene`` (default: all) measured against the body box grown by
    ``padding`` and the density prior of width ``prior_width`` (see the module docstring)."""
    if padding < 0:
        raise ValueError(f"padding must be >= 0, got {padding}")
    if prior_width <= 0:
        raise ValueError(f"prior_width must be > 0, got {prior_width}")
    names = list(sequences) if sequences else scene.sequence_names()
    out = []
    for name in names:
        ids, outside, excess, heights = [], [], [], []
        for f, posed, garment, points in garment_frame_heights(scene, name, body, betas=betas, projector=projector):
            e = box_excess(garment, padded_box(body_aabb(posed), padding))
            ids.append(f)
            outside.append(float((e > 0).double().mean()))
            excess.append(float(e.max()))
            heights.append(points.signed_distance.double().numpy())
        outside, excess = np.array(outside), np.array(excess)
        h_all = np.concatenate(heights)
        h_max = np.array([h.max() for h in heights])
        beyond = np.array([(h > prior_width).mean() for h in heights])
        out.append(SequenceReach(
            sequence=name, frames=len(heights), padding=float(padding), prior_width=float(prior_width),
            frames_outside_box=int((outside > 0).sum()), worst_outside_share=float(outside.max()),
            worst_outside_frame=ids[int(outside.argmax())], farthest_outside_m=float(excess.max()),
            h_p95_m=float(np.quantile(h_all, 0.95)), h_max_m=float(h_max.max()),
            h_max_frame=ids[int(h_max.argmax())], beyond_prior_zero_share=float((h_all > prior_width).mean()),
            worst_beyond_prior_zero_share=float(beyond.max()),
            worst_beyond_prior_zero_frame=ids[int(beyond.argmax())],
            at_prior_floor_share=float((h_all > 2 * prior_width).mean())))
    return out
