"""Sampling only where the garment can be: an inflated-body shell, a height band, early termination.

On a 2-core CPU the paper's sampling (128 x 128 rays x 64 samples through a 6 x 256 MLP) costs
seconds per frame; the MLP runs at about 0.25 M points/s, so speed has to come from evaluating
fewer points. Three culls, each exact for a model with no density where it culls:

1. **Shell bounds per ray** (:class:`ShellRaster`, ``shaders/shell_bounds.*``). The skin (the
   projector's main component) is inflated: every vertex pushed out along its unit vertex normal
   by ``shell_margin`` (default: the height range's ``h_max`` + 3 cm, per vertex where the
   range has a per-vertex bound). One GL draw at the
   feature-image resolution, no depth test, MIN blending into an RGBA32F target, writes per
   pixel-centre ray the distance of the nearest *entering* face (the face plane faces the
   camera: near), minus the farthest distance of any face (far) and the nearest *leaving* face.
   A ray whose first crossing leaves the shell starts inside it (camera inside the body or the
   shell, or the entry clipped by the near plane): its near is 0. Rays that cross no face get no
   samples. The raster's near/far planes are fitted to the shell (not the camera's), so cameras
   1 km away still see it.
2. **Height band** ``h_min <= h <= h_max`` (:class:`HeightRange`, measured from the training
   garments by :func:`measure_height_range`; the upper bound per skin vertex where measured, so
   the shell hugs the skin wherever the garment never goes): samples whose signed distance to the posed body
   lies outside are dropped after the (cheap, ~0.4 us/point) projection and before the (~4
   us/point) MLP. Dropping a sample is giving its interval zero density: the render of a model
   whose density is zero outside the band is unchanged.
3. **Occlusion by the body** (``occlusion``): the same raster pass, drawn with the posed skin
   itself, gives per ray the distance of the first skin crossing; the ray's far bound becomes
   that distance plus ``occlusion_margin`` (default ``-h_min``: the band's depth under the
   skin). The model renders the body opaque (the ground truth's body is), so what lies behind
   the skin adds nothing but the transmittance left after ``-h_min`` of skin, the same order of
   approximation as the early termination, and this cull needs no projection. Cameras that may
   be inside the body skip it.
4. **Early ray termination**: samples are evaluated front to back in segments (a few samples of
   every live ray at a time, about ``chunk_points`` per segment); a ray stops once its
   transmittance falls below ``termination_eps``. The samples skipped then carry weights summing
   to at most eps, so the feature image changes by at most ``eps * max|zeta|`` and the opacity by
   at most eps. Default eps = 1e-3 (``TERMINATION_EPS``); 0 disables it.

Sample placement (``spacing``)
    ``"box"`` (default): the padded body box of the paper's sampler is cut into S equal bins
    exactly as :class:`~garmentnerf.model.samplers.BoxStratifiedSampler` does, and only the
    bins that overlap the ray's shell segment are kept. In eval mode the samples *are* the
    reference sampler's samples (same positions, same intervals), a subset of them: with
    zero density outside the shell and the band, the culled render equals the reference render
    up to float rounding. In training mode each kept sample is drawn uniformly in its bin and
    stands for its bin (a valid stratified estimate; the reference's intervals meet halfway
    between jittered neighbours instead).
    ``"shell"``: S stratified samples between the ray's shell near and far (finer steps for the
    same S, different quadrature from the reference).

Use
    :class:`ShellSampler` implements :class:`~garmentnerf.model.samplers.Sampler`. The
    pipeline's sampler interface carries no body or camera, so the sampler is *bound* before
    sampling: :meth:`ShellSampler.bind` (posed vertices and, when known, the feature camera whose
    pixel centres the rays go through). Rays through the bound camera's pixel centres read the
    raster exactly; other rays sharing one origin get a conservative lookup in a raster fitted to
    them (3 x 3 neighbourhood min/max); anything else falls back to the whole padded box.
    :func:`render_features_culled` is a drop-in for
    :meth:`GarmentAnimationNeRF.render_features` that binds the sampler, applies the height band
    and terminates rays early; :func:`install_culled_renderer` puts it (and a
    :class:`ShellSampler`) on a loaded model, :func:`uninstall_culled_renderer` takes it off
    (``garmentnerf.perf.presets`` does both).
"""

from __future__ import annotations

import functools
import math
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np
import torch

from garmentnerf.conventions import Camera, camera_rays, gl_projection_from_intrinsics
from garmentnerf.model import volume_rendering as vr
from garmentnerf.model.samplers import RaySamples, ray_aabb_intersect, stratified_intervals

#: Default transmittance below which a ray stops (see the module docstring).
TERMINATION_EPS = 1e-3
#: Added to the measured h_max to get the inflation of the shell (metres).
SHELL_EXTRA_MARGIN = 0.03
#: Margins added to the measured garment heights (metres): above the garment, and below the skin
#: (samples just inside the body carry the skin's density ramp).
HEIGHT_MARGIN_OUT = 0.03
HEIGHT_MARGIN_IN = 0.05
#: Used when no training data is at hand to measure the band (generous: a skirt's hem swings
#: about 0.3 m from the legs).
DEFAULT_HEIGHT_RANGE = (-0.10, 0.40)
#: Mesh rings over which a garment vertex's height spreads in the per-vertex band.
VERTEX_BAND_RINGS = 4
SPACINGS = ("box", "shell")
PRECISIONS = ("float32", "bfloat16", "float16", "auto")
_BIG = 1.0e37


# ---------------------------------------------------------------------------------------------
# height band
# ---------------------------------------------------------------------------------------------
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

    def shell_margins(self, extra: float = SHELL_EXTRA_MARGIN) -> float | torch.Tensor:
        """The shell inflation: a scalar ``h_max + extra`` or, per vertex, ``vertex_h_max + extra``."""
        if self.vertex_h_max is None:
            return self.h_max + extra
        return self.vertex_h_max + extra

    def upper_bound(self, face: torch.Tensor | None, bary: torch.Tensor | None, faces: torch.Tensor) -> torch.Tensor | float:
        """(n,) the largest h allowed above surface points given by ``face (n,)`` and ``bary (n, 3)``
        of the skin ``faces (F, 3)``; the scalar ``h_max`` without a per-vertex bound."""
        if self.vertex_h_max is None or face is None or bary is None:
            return self.h_max
        corner = self.vertex_h_max[faces.detach().cpu()[face.long().cpu()]]  # (n, 3)
        return (corner * bary.float()).sum(-1)

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
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.scene import read_garment_arrays
    from garmentnerf.geometry.body_points import BodyPointProjector

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
        garment = read_garment_arrays(scene.garment_path(name))
        T = garment.vertices.shape[0]
        frames = np.unique(np.linspace(0, T - 1, min(T, max_frames)).round().astype(int))
        motion = scene.load_motion(name)
        with torch.no_grad():
            for f in frames:
                posed = motion.slice(int(f), int(f) + 1).pose(body, betas).vertices[0].detach().cpu().float()
                pts = torch.from_numpy(np.ascontiguousarray(garment.vertices[f], dtype=np.float32))
                proj = projector.project(pts, posed)
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


# ---------------------------------------------------------------------------------------------
# the GL pass
# ---------------------------------------------------------------------------------------------
def inflate_surface(vertices: torch.Tensor, faces: torch.Tensor, margin: float | torch.Tensor) -> torch.Tensor:
    """(V, 3) float32 vertices pushed out along their unit (area-weighted) normals by ``margin``
    (metres: a scalar, or (V,) per vertex)."""
    from garmentnerf.body.surface import vertex_normals

    v = vertices.detach().to("cpu", torch.float32)
    m = torch.as_tensor(margin, dtype=torch.float32).reshape(-1, 1) if torch.is_tensor(margin) else float(margin)
    return v + m * vertex_normals(v, faces.detach().cpu().long())


def winding_number(point, vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Generalised winding number of ``point (3,)`` w.r.t. the triangle mesh (about 1 inside a
    closed outward-oriented surface, 0 outside; Jacobson et al. 2013, solid angles by
    Van Oosterom and Strackee)."""
    v = vertices.detach().to("cpu", torch.float64) - torch.as_tensor(np.asarray(point, dtype=np.float64))
    f = faces.detach().cpu().long()
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
    num = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
    return float(2.0 * torch.atan2(num, den).sum() / (4.0 * math.pi))


def point_in_shell(point, vertices: torch.Tensor, faces: torch.Tensor, margin: float) -> bool:
    """Whether ``point`` may lie inside the body inflated by ``margin`` (conservative: inside the
    body by winding number, or within ``margin`` + the longest edge of a vertex)."""
    v = vertices.detach().to("cpu", torch.float64)
    f = faces.detach().cpu().long()
    p = torch.as_tensor(np.asarray(point, dtype=np.float64))
    edge = float((v[f[:, 0]] - v[f[:, 1]]).norm(dim=-1).max()) if len(f) else 0.0
    used = torch.unique(f.reshape(-1))
    if float((v[used] - p).norm(dim=-1).min()) <= margin + edge:
        return True
    return winding_number(p, v, f) > 0.5


@dataclass
class ShellBounds:
    """Per-pixel ray distances of a shell raster (H, W): near, far (0 where not ``hit``)."""

    near: torch.Tensor
    far: torch.Tensor
    hit: torch.Tensor


class ShellRaster:
    """Rasterises the distance range of a closed shell along every pixel-centre ray (one draw).

    Args:
        ctx: a moderngl context; None makes (and owns) a headless one on first use.
    """

    def __init__(self, ctx=None):
        self._ctx = ctx
        self._own = ctx is None
        self._program = None
        self._buffers: list = []
        self._vao = None
        self._capacity = 0
        self._targets: dict = {}

    @property
    def ctx(self):
        if self._ctx is None:
            from garmentnerf.gl.context import create_context

            self._ctx = create_context(headless=True)
        return self._ctx

    def _setup(self):
        from garmentnerf.gl.shaders import build_program

        if self._program is None:
            self._program = build_program(self.ctx, "shell_bounds.vert", "shell_bounds.frag")

    def _upload(self, corners: np.ndarray) -> None:
        if self._vao is None or corners.nbytes > self._capacity:
            self._release_buffers()
            self._capacity = max(2 * corners.nbytes, 64)
            self._buffers = [self.ctx.buffer(reserve=self._capacity, dynamic=True)]
            self._vao = self.ctx.vertex_array(self._program, [(self._buffers[0], "3f", "in_position")])
        self._buffers[0].write(corners)

    def _target(self, width: int, height: int):
        key = (width, height)
        if key not in self._targets:
            while len(self._targets) >= 4:
                tex, fbo = self._targets.pop(next(iter(self._targets)))
                fbo.release()
                tex.release()
            tex = self.ctx.texture(key, 2, dtype="f4")
            self._targets[key] = (tex, self.ctx.framebuffer(color_attachments=[tex]))
        return self._targets[key]

    def render(self, vertices: torch.Tensor, faces: torch.Tensor, camera: Camera,
               origin_inside: bool = False) -> ShellBounds:
        """Near/far ray distances of the closed shell ``(vertices, faces)`` seen by ``camera``:
        the nearest and farthest crossing of any face per pixel-centre ray; ``origin_inside``
        (the camera centre lies inside the shell): every ray starts at 0 and every ray hits."""
        import moderngl

        from garmentnerf.gl.context import current

        verts = vertices.detach().to("cpu", torch.float32).numpy()
        tris = faces.detach().cpu().numpy().astype(np.int64)
        W, H = camera.width, camera.height
        centre = np.asarray(camera.center, dtype=np.float64)
        # Fit the clip planes to the shell: cameras inside it, very near or very far all see it.
        reach = float(np.sqrt(((verts.astype(np.float64) - centre) ** 2).sum(-1).max())) if len(verts) else 1.0
        far = max(reach * 1.01 + 1e-3, 1e-2)
        near = max(far * 1e-6, 1e-6)
        with current(self.ctx):
            self._setup()
            corners = np.ascontiguousarray(verts[tris.reshape(-1)], dtype=np.float32)
            tex, fbo = self._target(W, H)
            prog = self._program
            prog["u_view"].write(camera.world_to_camera().T.astype(np.float32).tobytes())
            prog["u_proj"].write(gl_projection_from_intrinsics(camera.K, W, H, near, far).T.astype(np.float32).tobytes())
            out = np.empty((H, W, 2), dtype=np.float32)
            with self.ctx.scope(fbo, enable_only=moderngl.BLEND):
                try:
                    self.ctx.blend_equation = moderngl.MIN
                    fbo.clear(_BIG, _BIG, 0.0, 0.0)
                    if len(tris):
                        self._upload(corners)
                        self._vao.render(moderngl.TRIANGLES, vertices=3 * len(tris))
                    fbo.read_into(out, components=2, dtype="f4")
                finally:
                    self.ctx.blend_equation = moderngl.FUNC_ADD
        raw = torch.from_numpy(out)
        hit = (raw[..., 0] < _BIG * 0.5) & (raw[..., 1] < _BIG * 0.5)
        near_t = torch.where(hit, raw[..., 0], torch.zeros_like(raw[..., 0]))
        far_t = torch.where(hit, -raw[..., 1], torch.zeros_like(raw[..., 1]))
        if origin_inside:
            hit = torch.ones_like(hit)
            near_t = torch.zeros_like(near_t)
            far_t = torch.where(far_t > 0, far_t, torch.full_like(far_t, far))
        return ShellBounds(near_t, far_t, hit)

    def _release_buffers(self) -> None:
        if self._vao is not None:
            self._vao.release()
            self._vao = None
        for b in self._buffers:
            b.release()
        self._buffers = []

    def release(self) -> None:
        from garmentnerf.gl.context import is_released

        if self._ctx is None or is_released(self._ctx):
            return
        from garmentnerf.gl.context import current

        with current(self._ctx):
            self._release_buffers()
            for tex, fbo in self._targets.values():
                fbo.release()
                tex.release()
            self._targets.clear()
            if self._program is not None:
                self._program.release()
                self._program = None
        if self._own:
            self._ctx.release()
            self._ctx = None


# ---------------------------------------------------------------------------------------------
# the sampler
# ---------------------------------------------------------------------------------------------
def _fit_camera(origin: np.ndarray, directions: torch.Tensor, max_side: int = 1024) -> tuple[Camera, torch.Tensor] | None:
    """A pinhole camera at ``origin`` whose image covers every direction, with about one pixel per
    ray spacing; and the continuous pixel coordinates (R, 2) of the rays. None if the rays span
    more than a hemisphere-ish cone."""
    d = directions.detach().to("cpu", torch.float64)
    axis = d.mean(0)
    if float(axis.norm()) < 1e-6:
        return None
    z = axis / axis.norm()
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(z @ helper)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(helper, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z]).numpy()  # world -> camera rows
    dz = d @ z
    if float(dz.min()) < 0.2:
        return None
    px, py = (d @ x) / dz, (d @ y) / dz
    lo = torch.stack([px.min(), py.min()])
    ext = torch.stack([px.max(), py.max()]) - lo
    n = d.shape[0]
    spacing = math.sqrt(max(float(ext[0] * ext[1]), 1e-12) / n) if n > 1 else 1e-3
    spacing = max(spacing, float(ext.max()) / max_side, 1e-6)
    f = 1.0 / spacing
    W, H = int(math.ceil(float(ext[0]) * f)) + 3, int(math.ceil(float(ext[1]) * f)) + 3
    K = np.array([[f, 0.0, 1.0 - float(lo[0]) * f], [0.0, f, 1.0 - float(lo[1]) * f], [0.0, 0.0, 1.0]])
    t = -R @ origin
    cam = Camera(K, R, t, W, H)
    pix = torch.stack([px * f + K[0, 2], py * f + K[1, 2]], -1)
    return cam, pix


class ShellSampler:
    """Samples only inside the inflated body shell (see the module docstring).

    Args:
        num_samples: S, bins of the padded box (``spacing="box"``) or samples per shell segment.
        height_range: the band h may occupy (:class:`HeightRange`); default
            :meth:`HeightRange.default`. Used by :func:`render_features_culled`.
        faces: (F, 3) the skin faces to inflate (the model's ``projector.faces``); needed before
            :meth:`bind`.
        shell_margin: inflation in metres, a scalar or (V,) per skin vertex (default
            :meth:`HeightRange.shell_margins`: the band's per-vertex bound where it has one, else
            ``h_max``, plus ``SHELL_EXTRA_MARGIN``).
        padding: the box padding of the reference sampler (paper code: 0.05).
        spacing: ``"box"`` or ``"shell"``.
        termination_eps: transmittance below which a ray stops (0: never).
        precision: MLP precision in :func:`render_features_culled`: ``float32``, ``bfloat16``,
            ``float16`` (autocast) or ``auto`` (float16 on CUDA, float32 on the CPU, where
            bfloat16 autocast is slower).
        gl_context: moderngl context of the shell raster (None: a headless one of its own).
        occlusion: cut every ray ``occlusion_margin`` behind its first skin crossing.
        occlusion_margin: metres (default ``max(0, -height_range.h_min)``).
    """

    def __init__(self, num_samples: int = 64, height_range: HeightRange | None = None, *, faces=None,
                 shell_margin: float | torch.Tensor | None = None, padding: float = 0.05, spacing: str = "box",
                 termination_eps: float = TERMINATION_EPS, precision: str = "float32", gl_context=None,
                 occlusion: bool = False, occlusion_margin: float | None = None):
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if spacing not in SPACINGS:
            raise ValueError(f"spacing must be one of {SPACINGS}, got {spacing!r}")
        if not 0.0 <= termination_eps < 1.0:
            raise ValueError(f"termination_eps must be in [0, 1), got {termination_eps}")
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        if padding < 0:
            raise ValueError(f"padding must be >= 0, got {padding}")
        self.num_samples = int(num_samples)
        self.height_range = height_range if height_range is not None else HeightRange.default()
        margin = shell_margin if shell_margin is not None else self.height_range.shell_margins()
        margin = margin.detach().cpu().float() if torch.is_tensor(margin) else float(margin)
        if float(torch.as_tensor(margin).min()) <= 0 or not bool(torch.isfinite(torch.as_tensor(margin)).all()):
            raise ValueError("shell_margin must be finite and > 0")
        self.shell_margin = margin
        self.padding = float(padding)
        self.occlusion = bool(occlusion)
        self.occlusion_margin = (float(occlusion_margin) if occlusion_margin is not None
                                 else max(0.0, -self.height_range.h_min))
        if self.occlusion_margin < 0:
            raise ValueError(f"occlusion_margin must be >= 0, got {occlusion_margin}")
        self.spacing = spacing
        self.termination_eps = float(termination_eps)
        self.precision = precision
        self.faces = None if faces is None else torch.as_tensor(faces).detach().cpu().long()
        self.raster = ShellRaster(gl_context)
        self._shell: tuple[torch.Tensor, torch.Tensor] | None = None
        self._shell_key = None
        self._camera: Camera | None = None
        self._bounds: ShellBounds | None = None
        self.last_stats: dict = {}

    # ---- binding ---------------------------------------------------------------------------------
    def bind(self, posed_vertices: torch.Tensor, camera: Camera | None = None) -> "ShellSampler":
        """Use the body posed as ``posed_vertices (V, 3)``; ``camera``: the (feature-resolution)
        camera the next rays go through (its shell raster is made now). Re-binding the same
        vertices tensor reuses the inflated shell."""
        if self.faces is None:
            raise ValueError("ShellSampler needs the skin faces (faces=model.projector.faces) before bind()")
        key = (id(posed_vertices), posed_vertices.data_ptr(), tuple(posed_vertices.shape), posed_vertices._version)
        if key != self._shell_key:
            body = posed_vertices.detach().to("cpu", torch.float32).clone()
            self._shell = (inflate_surface(body, self.faces, self.shell_margin), body)
            self._shell_key = key
        self._camera, self._bounds = None, None
        if camera is not None:
            self._bounds = self.camera_bounds(camera)
            self._camera = camera
        return self

    def unbind(self) -> None:
        self._shell, self._shell_key, self._camera, self._bounds = None, None, None, None

    @property
    def bound(self) -> bool:
        return self._shell is not None

    def camera_bounds(self, camera: Camera) -> ShellBounds:
        """The shell raster (H, W) seen by ``camera`` (after :meth:`bind`)."""
        if self._shell is None:
            raise RuntimeError("ShellSampler.bind() first")
        inside = point_in_shell(camera.center, self._shell[1], self.faces, float(torch.as_tensor(self.shell_margin).max()))
        bounds = self.raster.render(self._shell[0], self.faces, camera, origin_inside=inside)
        if self.occlusion and not point_in_shell(camera.center, self._shell[1], self.faces, 0.0):
            skin = self.raster.render(self._shell[1], self.faces, camera)
            far = torch.where(skin.hit, torch.minimum(bounds.far, skin.near + self.occlusion_margin), bounds.far)
            bounds = ShellBounds(bounds.near, far, bounds.hit)
        return bounds

    # ---- per-ray bounds --------------------------------------------------------------------------
    def ray_bounds(self, origins: torch.Tensor, directions: torch.Tensor,
                   pixel_index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """(near, far, hit) per ray from the shell, or None when the rays cannot be matched to a
        raster (not bound, or rays without a common origin)."""
        if self._shell is None:
            return None
        R = origins.shape[0]
        if pixel_index is not None and self._bounds is not None:
            b = self._bounds
            idx = pixel_index.to("cpu").long()
            return b.near.reshape(-1)[idx], b.far.reshape(-1)[idx], b.hit.reshape(-1)[idx]
        if R == 0:
            z = torch.zeros(0)
            return z, z, torch.zeros(0, dtype=torch.bool)
        o = origins.detach().to("cpu", torch.float64)
        origin = o[0]
        if float((o - origin).abs().max()) > 1e-6:
            return None
        d = directions.detach().to("cpu", torch.float64)
        if self._camera is not None and np.allclose(self._camera.center, origin.numpy(), atol=1e-6):
            cam = self._camera
            x_cam = d @ torch.as_tensor(cam.R, dtype=torch.float64).T
            if float(x_cam[:, 2].min()) > 0:
                pix = (x_cam @ torch.as_tensor(cam.K, dtype=torch.float64).T)
                pix = pix[:, :2] / pix[:, 2:]
                rc = pix.round()
                inside = (rc[:, 0] >= 0) & (rc[:, 0] < cam.width) & (rc[:, 1] >= 0) & (rc[:, 1] < cam.height)
                if bool(inside.all()) and float((pix - rc).abs().max()) < 1e-3:
                    idx = rc[:, 1].long() * cam.width + rc[:, 0].long()
                    b = self._bounds
                    return b.near.reshape(-1)[idx], b.far.reshape(-1)[idx], b.hit.reshape(-1)[idx]
        fitted = _fit_camera(origin.numpy(), d)
        if fitted is None:
            return None
        cam, pix = fitted
        b = self.camera_bounds(cam)
        # Conservative lookup: the 3 x 3 pixel centres around each ray (min near, max far, any hit).
        c0, r0 = pix[:, 0].round().long(), pix[:, 1].round().long()
        big = torch.full((R,), float("inf"))
        near, far, hit = big.clone(), torch.zeros(R), torch.zeros(R, dtype=torch.bool)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r, c = (r0 + dr).clamp(0, cam.height - 1), (c0 + dc).clamp(0, cam.width - 1)
                h = b.hit[r, c]
                near = torch.where(h, torch.minimum(near, b.near[r, c]), near)
                far = torch.where(h, torch.maximum(far, b.far[r, c]), far)
                hit |= h
        # Between pixel centres depths vary by about one pixel's footprint: pad by it.
        pad = far / float(cam.K[0, 0]) * 2.0
        near = torch.where(hit, (near - pad).clamp_min(0.0), torch.zeros(R))
        far = torch.where(hit, far + pad, torch.zeros(R))
        return near.float(), far.float(), hit

    # ---- Sampler ---------------------------------------------------------------------------------
    def sample(self, origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, *,
               training: bool = False, generator: torch.Generator | None = None,
               pixel_index: torch.Tensor | None = None) -> RaySamples:
        """Packed samples inside the shell (see the module docstring); ``pixel_index``: the
        row-major pixel of each ray in the bound camera, when the caller knows it."""
        if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
            raise ValueError(f"origins and directions must both be (R, 3), got {tuple(origins.shape)} "
                             f"and {tuple(directions.shape)}")
        if aabb.shape != (2, 3):
            raise ValueError(f"aabb must be (2, 3) [min, max], got {tuple(aabb.shape)}")
        R, dev, dt = origins.shape[0], origins.device, origins.dtype
        pad = torch.tensor([[-self.padding], [self.padding]], dtype=aabb.dtype, device=aabb.device)
        tb0, tb1, box_hit = ray_aabb_intersect(origins, directions, aabb + pad, 0.0)
        bounds = self.ray_bounds(origins, directions, pixel_index)
        if bounds is None:  # cannot cull: the whole padded box
            near, far, hit = tb0, tb1, box_hit
            self.last_stats = {"culled_by_shell": False}
        else:
            near, far, hit = (x.to(dev) for x in bounds)
            near, far = near.to(dt), far.to(dt)
            self.last_stats = {"culled_by_shell": True}
        S = self.num_samples
        if self.spacing == "shell":
            if bounds is None:
                lo, hi, ok = tb0, tb1, box_hit
            else:
                lo, hi, ok = near, far, hit & (far > near)
            idx = ok.nonzero().squeeze(1)
            t, ts, te = stratified_intervals(lo[idx], hi[idx], S, training, generator)
            ray_ids = idx.repeat_interleave(S)
            t, ts, te = t.reshape(-1), ts.reshape(-1), te.reshape(-1)
        else:
            ok = box_hit & (hit if bounds is not None else box_hit)
            L = tb1 - tb0
            bw = L / S
            safe = torch.where(bw > 0, bw, torch.ones_like(bw))
            first = torch.floor((torch.maximum(near, tb0) - tb0) / safe).clamp(0, S - 1)
            last = (torch.ceil((torch.minimum(far, tb1) - tb0) / safe) - 1).clamp(0, S - 1)
            ok = ok & (far > tb0) & (near < tb1) & (last >= first)
            first = first.long()
            counts = torch.where(ok, last.long() - first + 1, torch.zeros_like(first))
            ray_ids = torch.repeat_interleave(torch.arange(R, device=dev), counts)
            starts = torch.cumsum(counts, 0) - counts
            i = (torch.arange(ray_ids.shape[0], device=dev) - starts[ray_ids] + first[ray_ids]).to(dt)
            t0, Lr = tb0[ray_ids], L[ray_ids]
            # The reference sampler's formulas (samplers.stratified_intervals), bin for bin.
            if training:
                u = i + torch.rand(i.shape, dtype=dt, device=dev, generator=generator)
                t = t0 + Lr * (u / S)
                ts = t0 + Lr * (i / S)
                te = torch.where(i == S - 1, tb1[ray_ids], t0 + Lr * ((i + 1) / S))
            else:
                t = t0 + Lr * ((i + 0.5) / S)
                t_prev = t0 + Lr * ((i - 0.5) / S)
                t_next = t0 + Lr * ((i + 1.5) / S)
                ts = torch.where(i == 0, t0, (t_prev + t) * 0.5)
                te = torch.where(i == S - 1, tb1[ray_ids], (t + t_next) * 0.5)
        positions = origins[ray_ids] + t.unsqueeze(-1) * directions[ray_ids]
        counts_all = torch.bincount(ray_ids, minlength=R)
        self.last_stats.update(candidates=int(ray_ids.shape[0]), rays_sampled=int((counts_all > 0).sum()))
        return RaySamples(positions, ts, te, ray_ids, R, counts_all > 0)

    def release(self) -> None:
        self.raster.release()


# ---------------------------------------------------------------------------------------------
# the culled renderer
# ---------------------------------------------------------------------------------------------
def _autocast(precision: str, device: torch.device):
    if precision == "auto":
        precision = "float16" if device.type == "cuda" else "float32"
    if precision == "float32":
        return nullcontext()
    return torch.autocast(device_type=device.type, dtype=getattr(torch, precision))


def render_features_culled(model, frame, camera: Camera, rays=None, *, feature_size=None, training=None,
                           generator=None, should_cancel=None, chunk_points=None, timings=None,
                           sampler=None, height_range: HeightRange | None = None,
                           termination_eps: float | None = None) -> dict:
    """:meth:`GarmentAnimationNeRF.render_features` with the culls of this module.

    Same arguments and result keys (``feature_image``, ``opacity``, ``depth``,
    ``points_evaluated``, ``rays_evaluated``, ``rays_total``), plus ``samples_candidate``
    (samples the sampler placed), ``points_projected`` (samples projected on the body: the
    candidates the early termination did not skip), ``rays_terminated``. Any sampler works;
    the height band and early termination settings come from a :class:`ShellSampler` (others:
    no band, :data:`TERMINATION_EPS`); ``height_range`` / ``termination_eps`` override them.
    ``points_evaluated`` counts MLP points.
    """
    from garmentnerf.gl.uv_raster import sample_uv_map
    from garmentnerf.model.pipeline import RenderCancelled, _Stopwatch

    cfg = model.cfg
    sampler = model.sampler if sampler is None else sampler
    shell = sampler if isinstance(sampler, ShellSampler) else None
    fw, fh = feature_size if feature_size is not None else (cfg.feature_image_resolution,) * 2
    training = model.training if training is None else training
    chunk = model.chunk_points if chunk_points is None else int(chunk_points)
    dev = model.device
    timings = {} if timings is None else timings
    sw = _Stopwatch(timings, dev)
    C = cfg.appearance_dim
    n_pixels = fw * fh
    eps = shell.termination_eps if shell is not None else TERMINATION_EPS
    eps = eps if termination_eps is None else float(termination_eps)
    band = shell.height_range if shell is not None else None
    band = band if height_range is None else height_range
    precision = shell.precision if shell is not None else "float32"

    with sw("rays"):
        fcam = camera.resized(fw, fh)
        origins, dirs = camera_rays(fcam)
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        subset = model._ray_subset(rays, n_pixels, (fh, fw))
        pixel_index = torch.arange(n_pixels) if subset is None else subset.cpu()
        if subset is not None:
            origins, dirs = origins[subset], dirs[subset]
        aabb = frame.aabb.to(origins.dtype)
        if shell is not None:
            shell.bind(frame.posed_vertices, fcam)
            samples = shell.sample(origins, dirs, aabb, training=training, generator=generator,
                                   pixel_index=pixel_index)
        else:
            samples = sampler.sample(origins, dirs, aabb, training=training, generator=generator)
        if not samples.is_packed:
            samples = samples.to_packed(drop_missed=True)
        n_rays = samples.n_rays
        ray_ids_all = samples.ray_ids.to("cpu")
        index, counts = vr.packed_layout(ray_ids_all, n_rays)

    feat = torch.zeros(n_rays, C, device=dev)
    opacity = torch.zeros(n_rays, device=dev)
    depth = torch.zeros(n_rays, device=dev)
    tau_acc = torch.zeros(n_rays)  # CPU, detached: which rays are still live
    tau_acc_d = torch.zeros(n_rays, device=dev)  # differentiable: the transmittance of later segments
    active = torch.ones(n_rays, dtype=torch.bool)
    points = projected = 0
    seg0 = 0
    max_count = int(counts.max()) if counts.numel() else 0
    while seg0 < max_count:
        live = active & (counts > seg0)
        n_live = int(live.sum())
        if n_live == 0:
            break
        K = max(1, chunk // n_live)
        with sw("compositing"):
            sel = (live[ray_ids_all] & (index >= seg0) & (index < seg0 + K)).nonzero().squeeze(1)
        seg0 += K
        n = sel.shape[0]
        if n == 0:
            continue
        pos = samples.positions[sel.to(samples.positions.device)]
        sigma_parts, zeta_parts = [], []
        for c0 in range(0, n, chunk):
            if should_cancel is not None and should_cancel():
                raise RenderCancelled(points)
            c1 = min(n, c0 + chunk)
            with sw("projection"):
                geo = model.sample_geometry(frame, pos[c0:c1])
                keep = torch.ones(c1 - c0, dtype=torch.bool)
                if band is not None:
                    h = geo.distance.cpu()
                    keep = (h >= band.h_min) & (h <= band.upper_bound(geo.face, geo.bary, model.projector.faces))
                kidx = keep.nonzero().squeeze(1)
            projected += c1 - c0
            sigma_c = torch.zeros(c1 - c0, device=dev)
            zeta_c = torch.zeros(c1 - c0, C, device=dev)
            if kidx.numel():
                with sw("features"):
                    closest = geo.closest[kidx]
                    normal = None if geo.normal is None else geo.normal[kidx]
                    dynamic = detail = None
                    if cfg.use_dynamic_feature:
                        fmap = frame.dynamic_features.permute(1, 2, 0)
                        dynamic = sample_uv_map(fmap, geo.uv[kidx].to(dev))
                    if cfg.use_detail_feature:
                        detail, _ = model.detail_features(frame, closest, normal)
                with sw("mlp"), _autocast(precision, dev):
                    s, z = model.nerf(geo.canonical[kidx].to(dev), geo.distance[kidx].to(dev), detail, dynamic)
                s, z = s.float(), z.float()
                kd = kidx.to(dev)
                sigma_c = sigma_c.index_copy(0, kd, s)
                zeta_c = zeta_c.index_copy(0, kd, z)
                points += int(kidx.numel())
            sigma_parts.append(sigma_c)
            zeta_parts.append(zeta_c)
        with sw("compositing"):
            sigma = torch.cat(sigma_parts)
            zeta = torch.cat(zeta_parts)
            rid = ray_ids_all[sel]
            sdev = sel.to(samples.t_starts.device)
            ts = samples.t_starts[sdev].to(dev, torch.float32)
            te = samples.t_ends[sdev].to(dev, torch.float32)
            tau = vr.optical_thickness(sigma, te - ts)
            rid_d = rid.to(dev)
            before = vr._packed_exclusive_cumsum(tau, rid_d, n_rays) + tau_acc_d[rid_d]
            w = torch.exp(-before) * -torch.expm1(-tau)
            feat = feat.index_add(0, rid_d, w.unsqueeze(-1) * zeta)
            opacity = opacity.index_add(0, rid_d, w)
            depth = depth.index_add(0, rid_d, w * (ts + te) * 0.5)
            tau_acc_d = tau_acc_d.index_add(0, rid_d, tau)
            tau_acc = tau_acc.index_add(0, rid, tau.detach().cpu())
            if eps > 0:
                active = torch.exp(-tau_acc) >= eps

    with sw("compositing"):
        depth = torch.where(opacity > 0, depth / opacity.clamp_min(1e-10), torch.zeros_like(depth))
        if subset is not None:
            idx = subset.to(dev)
            feat = feat.new_zeros(n_pixels, C).index_copy(0, idx, feat)
            opacity = opacity.new_zeros(n_pixels).index_copy(0, idx, opacity)
            depth = depth.new_zeros(n_pixels).index_copy(0, idx, depth)
        feature_image = feat.T.reshape(C, fh, fw)
    stats = {"points_evaluated": points, "rays_evaluated": int((counts > 0).sum()), "rays_total": n_rays,
             "samples_candidate": int(ray_ids_all.shape[0]), "points_projected": projected,
             "rays_terminated": int(((~active) & (counts > 0)).sum()) if eps > 0 else 0}
    if shell is not None:
        shell.last_stats.update(stats)
    return {"feature_image": feature_image, "opacity": opacity.reshape(fh, fw), "depth": depth.reshape(fh, fw),
            **stats}


def install_culled_renderer(model, sampler: ShellSampler) -> None:
    """Make ``model.render`` (and everything built on it: RenderSession, the viewer, evaluation)
    use ``sampler`` and :func:`render_features_culled`. The weights are untouched; undo with
    :func:`uninstall_culled_renderer`.

    The override is an instance attribute shadowing the class method (the pipeline's sampler
    interface carries no body or camera, so the culled path needs its own ``render_features``).
    """
    if sampler.faces is None:
        sampler.faces = model.projector.faces.detach().cpu().long()
    model.sampler = sampler
    model.render_features = functools.partial(render_features_culled, model)


def uninstall_culled_renderer(model, sampler=None) -> None:
    """Back to the pipeline's own ``render_features`` (and ``sampler``, default the config's
    :class:`~garmentnerf.model.samplers.BoxStratifiedSampler`)."""
    from garmentnerf.model.samplers import BoxStratifiedSampler

    model.__dict__.pop("render_features", None)
    old = model.sampler
    model.sampler = sampler if sampler is not None else BoxStratifiedSampler.from_config(model.cfg)
    if isinstance(old, ShellSampler) and old is not model.sampler:
        old.release()


__all__ = ["ShellSampler", "ShellRaster", "ShellBounds", "HeightRange", "measure_height_range", "inflate_surface",
           "winding_number", "point_in_shell",
           "render_features_culled", "install_culled_renderer", "dilate_vertex_values", "uninstall_culled_renderer", "TERMINATION_EPS",
           "SHELL_EXTRA_MARGIN", "DEFAULT_HEIGHT_RANGE", "SPACINGS", "PRECISIONS"]
