"""The band of signed body distances the garment occupies, and the sample filter made of it.

A garment stays within a few centimetres to a few decimetres of the skin. :class:`HeightRange`
is that band ``h_min <= h <= h_max`` (metres, positive outside the skin), optionally tightened
per skin vertex (a skirt reaches 0.3 m out from the thighs but only a few centimetres from the
face), measured on a scene's training garments by :func:`measure_height_range` exactly as the
model measures its samples (:class:`~garmentnerf.geometry.body_points.BodyPointProjector`).

:class:`HeightBandFilter` is the band as a sample filter
(:class:`~garmentnerf.model.samplers.SampleFilter`): after the (cheap) body projection and before
the (costly) MLP, samples outside the band are dropped. Dropping a sample is giving its interval
zero density: the render of a model whose density is zero outside the band is unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.geometry.body_points import BodyPointProjector, BodyPoints

#: Margins added to the measured garment heights (metres): above the garment, and below the skin
#: (samples just inside the body carry the skin's density ramp).
HEIGHT_MARGIN_OUT = 0.03
HEIGHT_MARGIN_IN = 0.05
#: Used when no training data is at hand to measure the band (generous: a skirt's hem swings
#: about 0.3 m from the legs).
DEFAULT_HEIGHT_RANGE = (-0.10, 0.40)
#: Mesh rings over which a garment vertex's height spreads in the per-vertex band.
VERTEX_BAND_RINGS = 4


@dataclass(frozen=True)
class HeightRange:
    """The band of signed body distances h (metres, positive outside) the model may occupy.

    ``vertex_h_max`` (V,) optionally tightens the upper bound per skin vertex: above vertex v the
    model may reach ``vertex_h_max[v]`` (<= ``h_max``), interpolated over the skin faces. A skirt
    reaches 0.3 m out from the thighs but only a few centimetres from the face or the arms, so a
    per-vertex bound shrinks the shell around everything the garment does not cover.
    """

    h_min: float
    h_max: float
    source: str = "given"
    vertex_h_max: torch.Tensor | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.h_min) and math.isfinite(self.h_max) and self.h_min < self.h_max):
            raise ValueError(f"HeightRange needs finite h_min < h_max, got [{self.h_min}, {self.h_max}]")
        if self.h_max <= 0:
            raise ValueError(f"HeightRange.h_max must be > 0 (the shell is the body inflated by it), got {self.h_max}")
        if self.vertex_h_max is not None:
            v = torch.as_tensor(self.vertex_h_max, dtype=torch.float32).detach().cpu().reshape(-1)
            if not bool(torch.isfinite(v).all()) or float(v.min()) <= 0 or float(v.max()) > self.h_max + 1e-6:
                raise ValueError(f"HeightRange.vertex_h_max must be finite and in (0, h_max={self.h_max}]")
            object.__setattr__(self, "vertex_h_max", v)

    @classmethod
    def default(cls) -> "HeightRange":
        return cls(*DEFAULT_HEIGHT_RANGE, source="default")

    def shell_margins(self, extra: float) -> float | torch.Tensor:
        """The shell inflation: a scalar ``h_max + extra`` or, per vertex, ``vertex_h_max + extra``."""
        if self.vertex_h_max is None:
            return self.h_max + extra
        return self.vertex_h_max + extra

    def upper_bound(self, face: torch.Tensor, bary: torch.Tensor, faces: torch.Tensor) -> torch.Tensor | float:
        """(n,) the largest h allowed above surface points given by skin face ids ``face (n,)``
        and ``bary (n, 3)`` of the skin ``faces (F, 3)``; the scalar ``h_max`` without a
        per-vertex bound."""
        if self.vertex_h_max is None:
            return self.h_max
        corner = self.vertex_h_max[faces.detach().cpu()[face.long().cpu()]]  # (n, 3)
        return (corner * bary.detach().cpu().float()).sum(-1)

    def sample_filter(self, faces: torch.Tensor) -> "HeightBandFilter":
        """This band as a sample filter for the skin ``faces (F, 3)`` (the projector's)."""
        return HeightBandFilter(self, torch.as_tensor(faces).detach().cpu().long())

    def to_dict(self) -> dict:
        d = {"h_min": self.h_min, "h_max": self.h_max, "source": self.source}
        if self.vertex_h_max is not None:
            v = self.vertex_h_max
            d["vertex_h_max"] = {"vertices": int(v.numel()), "min": float(v.min()),
                                 "median": float(v.median()), "max": float(v.max())}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "HeightRange":
        return cls(float(d["h_min"]), float(d["h_max"]), str(d.get("source", "given")))


def dilate_vertex_values(values: torch.Tensor, faces: torch.Tensor, rings: int) -> torch.Tensor:
    """(V,) ``values`` replaced by their maximum over the ``rings``-ring mesh neighbourhood."""
    f = faces.detach().cpu().long()
    src = torch.cat([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    dst = torch.cat([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    out = values.clone()
    for _ in range(int(rings)):
        out = out.scatter_reduce(0, dst, out[src], reduce="amax")
    return out


def garment_frame_heights(scene, sequence: str, body, frames=None, betas=None, projector=None):
    """Yields ``(frame, posed (V, 3), garment (Vg, 3), BodyPoints)`` for ``frames`` of ``sequence``
    (default: all): the body posed with the scene's shape, the simulated garment's vertices (float32,
    CPU) and their body coordinates, h measured to the posed skin exactly as the model measures its
    samples (``BodyPoints.face`` holds skin face ids, rows of ``projector.faces``).

    ``scene`` is a :class:`~garmentnerf.data.scene.Scene` (or anything with its ``body``,
    ``garment_arrays`` and ``load_motion``): the scene's files are read through it."""
    betas = body.betas(scene.body.get("shape", "average")) if betas is None else betas
    projector = BodyPointProjector(body) if projector is None else projector
    garment = scene.garment_arrays(sequence)
    motion = scene.load_motion(sequence)
    frames = range(garment.vertices.shape[0]) if frames is None else frames
    with torch.no_grad():
        for f in frames:
            posed = motion.slice(int(f), int(f) + 1).pose(body, betas).vertices[0].detach().cpu().float()
            pts = torch.from_numpy(np.ascontiguousarray(garment.vertices[f], dtype=np.float32))
            yield int(f), posed, pts, projector.bind(posed).project(pts)


def measure_height_range(scene, body=None, betas=None, projector=None, sequences=None, max_frames: int = 24,
                         margin_out: float = HEIGHT_MARGIN_OUT, margin_in: float = HEIGHT_MARGIN_IN,
                         per_vertex: bool = True, rings: int = VERTEX_BAND_RINGS) -> HeightRange:
    """The band ``[min(0, h_garment) - margin_in, max(h_garment) + margin_out]`` over the garment
    vertices of the scene's training sequences (up to ``max_frames`` frames spread over each),
    h measured to the posed skin exactly as the model measures its samples. The body itself
    (h = 0) is always inside the band: the model renders it too.

    ``per_vertex``: also the per-skin-vertex upper bound: every garment vertex raises the three
    corners of the skin face it projects to to its h; the maxima are spread over ``rings`` mesh
    rings (the garment moves between the sampled frames, and unseen motions swing it further),
    and ``margin_out`` is added (so bare skin gets ``margin_out``: the body's own density)."""
    body = BodyModel.default() if body is None else body
    betas = body.betas(scene.body.get("shape", "average")) if betas is None else betas
    projector = BodyPointProjector(body) if projector is None else projector
    names = list(sequences) if sequences is not None else (scene.sequence_names("train") or scene.sequence_names())
    if not names:
        raise ValueError(f"{scene.scene_file}: no sequence to measure the garment's height range from")
    faces = projector.faces.detach().cpu().long()
    vmax = None
    lo, hi = 0.0, 0.0
    for name in names:
        T = scene.sequence(name).frames
        frames = np.unique(np.linspace(0, T - 1, min(T, max_frames)).round().astype(int))
        for _, posed, _, proj in garment_frame_heights(scene, name, body, frames, betas, projector):
            h = proj.signed_distance.float()
            lo, hi = min(lo, float(h.min())), max(hi, float(h.max()))
            if per_vertex:
                if vmax is None:
                    vmax = torch.zeros(posed.shape[0])
                corners = faces[proj.face.long()].reshape(-1)
                vmax = vmax.scatter_reduce(0, corners, h.clamp_min(0).repeat_interleave(3), reduce="amax")
    vertex_h_max = None
    if vmax is not None:
        vertex_h_max = (dilate_vertex_values(vmax, faces, rings) + margin_out).clamp(max=hi + margin_out)
    return HeightRange(lo - margin_in, hi + margin_out, source=f"measured on {', '.join(names)}",
                       vertex_h_max=vertex_h_max)


@dataclass(frozen=True)
class HeightBandFilter:
    """Keeps the samples whose signed distance lies in ``band`` (a
    :class:`~garmentnerf.model.samplers.SampleFilter`).

    Attributes:
        band: the height band.
        faces: (F, 3) the skin faces the projection's face ids index (``projector.faces``).
    """

    band: HeightRange
    faces: torch.Tensor = field(repr=False)

    def keep(self, points: BodyPoints) -> torch.Tensor:
        """(n,) bool on the CPU: ``h_min <= h <= upper bound`` at each point."""
        h = points.signed_distance.detach().cpu()
        return (h >= self.band.h_min) & (h <= self.band.upper_bound(points.face, points.bary, self.faces))


__all__ = ["HeightRange", "HeightBandFilter", "measure_height_range", "garment_frame_heights",
           "dilate_vertex_values", "DEFAULT_HEIGHT_RANGE",
           "HEIGHT_MARGIN_IN", "HEIGHT_MARGIN_OUT", "VERTEX_BAND_RINGS"]
