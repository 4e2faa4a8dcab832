"""Cloth simulation of a garment on a moving body: newton's VBD solver on the CPU.

``simulate(garment, body, motion)`` drapes a :class:`~garmentnerf.data.garments.Garment` on the
body and plays the motion, returning the garment's vertices at every motion frame.

Pipeline
    * The cloth is one newton particle per garment vertex, a stable Neo-Hookean membrane per
      triangle and a dihedral bending element per interior edge (``ModelBuilder.add_cloth_mesh``),
      solved by ``SolverVBD`` (vertex block descent) with particle self-contact.
    * The body is a *deforming mesh collider*: one static triangle-mesh shape whose vertices are
      overwritten before every substep with the posed body interpolated linearly between the
      two frames (and its per-vertex velocities with the frame's finite difference, used for
      friction), followed by a BVH refit. Its local bounding box is widened to +-1 km so the
      broad phase never culls it wherever the motion goes. Only the skin takes part (no eyes,
      no teeth: :func:`~garmentnerf.data.garments.body_collision_faces`).
    * Pinned vertices (a skirt's waistband, a t-shirt's collar) are kinematic particles (mass
      0) moved every substep with the body: skinned with the blended skinning weights of their
      closest point on the rest body (linear blend skinning, as the body itself).
    * Settling: the garment starts in its rest shape on the rest body (A-pose, no
      translation), hangs there for ``settle_hold_frames`` under gravity, then the body is
      blended over ``settle_frames`` into the motion's first frame (each joint's rotation
      slerped from the identity, i.e. its rotation vector scaled by a smoothstep weight; the
      translation scaled likewise), and then the motion frames are simulated. The output frame
      0 is the settled garment on motion frame 0; frame t > 0 is the state after simulating
      from frame t-1 to t.

Penetration
    After every frame the signed distance of every garment vertex to the posed body is taken
    with warp (exact closest point on the skin; inside where the body's generalized winding
    number exceeds 1/2, which stays right where the posed body overlaps itself, e.g. a hand on
    the hip). ``penetration_max_m[t]`` is the deepest vertex inside (0 when none is). Warp's
    cheaper pseudo-normal sign is not used: it called a vertex 6 cm outside the hips
    "inside" in a test. Only vertices are tested: a body edge can still poke through the middle
    of a cloth triangle by up to about the cloth's edge length times the local curvature. With :class:`SimSettings` defaults the walk and dance clips stay below
    :data:`PENETRATION_BOUND_M` (see the module constants) -- measured values in the report of
    :func:`benchmark_kinds`.

Resuming
    With ``out_dir`` the frames are written in atomically committed chunks
    ``chunk_000000.npz`` (frames [0, C)), ``chunk_000001.npz`` (frames [C, 2C)), ... next to a
    ``manifest.json`` fingerprinting the inputs (garment, motion, body shape, settings) and a
    ``settle.npz`` holding the settled state. Each chunk also stores the particle positions and
    velocities at its last frame, and the wall-clock and CPU seconds it took (``seconds``,
    ``cpu_seconds``). The simulator is *restarted from that state at every chunk
    boundary*, in uninterrupted runs as well: the solver, the collision pipeline and the body
    collider are rebuilt from the stored positions and velocities (and the self-contact BVH
    rebuilt at every frame), so a run that is killed and resumed executes exactly the same
    sequence of floating-point operations as one that is not and produces bit-identical frames
    (warp's CPU kernels are serial, hence deterministic). A second call with the same inputs
    loads what is there and computes only the missing chunks; different inputs raise
    :class:`SimulationResumeError` rather than mixing two simulations.

Cost
    Warp CPU kernels run on one core, so sequences are best simulated in parallel processes,
    one per core. The first run on a machine compiles newton's kernels (about a minute; cached
    in warp's kernel cache afterwards).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from garmentnerf.data.garments import Garment, body_collision_faces, make_garment
from garmentnerf.io_utils import atomic_write_path, read_json_strict

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel
    from garmentnerf.motion.motion import Motion

__all__ = ["SimSettings", "SimResult", "SimulationError", "SimulationResumeError", "simulate", "benchmark_simulation",
           "PENETRATION_BOUND_M", "NEWTON_VERSION"]

#: The newton release this module is written against (its VBD API changes between releases).
NEWTON_VERSION = "1.8.0"

#: Bound on ``penetration_max_m`` that the default settings keep on the walk and dance clips at
#: 30 fps (vertices deeper than this inside the body are a simulation failure; see the tests).
PENETRATION_BOUND_M = 0.010

_MANIFEST = "manifest.json"
_SETTLE = "settle.npz"
_FORMAT = "garmentnerf.simulation"
_VERSION = 2  # 2: frames take more substeps where the skin near the cloth moves fast (frame_substeps)


class SimulationError(RuntimeError):
    """The simulation produced NaN/Inf or could not be set up."""


class SimulationResumeError(ValueError):
    """``out_dir`` holds a simulation of other inputs (or an unreadable manifest)."""


@dataclass(frozen=True)
class SimSettings:
    """Everything that determines a simulation besides the garment, body and motion.

    Units: metres, kilograms, seconds. Time step: ``1 / (fps * n)`` with the motion's fps and
    ``n`` = :func:`frame_substeps` (``substeps``, more in frames where the skin near the cloth moves fast).

    Attributes:
        substeps: solver steps per motion frame, at least (more in frames where the skin near the
            cloth moves fast: :func:`frame_substeps`). 10 at 30 fps (3.3 ms) keeps a swinging knee
            from passing more than a few millimetres per step; 5 lets it tunnel through.
        iterations: VBD iterations per substep.
        density: cloth mass per area, kg/m^2 (0.2: a medium cotton).
        stretch_stiffness: membrane Lame parameters mu = lambda of the triangles, N/m
            (``tri_ke = tri_ka``). 1e3 keeps the mean stretch under gravity below 1%.
        stretch_damping: membrane strain-rate damping (``tri_kd``).
        bend_stiffness: dihedral bending stiffness per edge (``edge_ke``), N m/rad; the rest
            angle is flat (fabric is cut flat), so the garment's designed curvature is not
            remembered.
        bend_damping: bending damping (``edge_kd``).
        contact_ke: body-cloth and cloth-cloth contact stiffness, N/m (the model's
            ``soft_contact_ke`` and the collider's material ``ke``; newton averages the two, so
            both are set to this). 1e5; 1e4 lets the knee push through.
        contact_kd: contact damping, N s/m (applied only while approaching).
        friction: Coulomb friction coefficient of body-cloth and cloth-cloth contact.
        thickness: particle radius: cloth vertices are pushed back when closer than this to the
            body surface (the collision thickness), m.
        contact_gap: extra detection distance beyond ``thickness`` for body contacts, m: a
            contact must be detected before the body reaches the particle, so this must exceed
            the body's largest per-substep displacement (knee at 3 m/s and 3.3 ms: 1 cm).
        self_contact: cloth-cloth contact (vertex-triangle and edge-edge) on/off; needed for
            folds and for the dress's two layers.
        self_contact_margin: distance cloth surfaces keep from each other, m.
        self_contact_gap: extra detection distance for self-contact, m. Also sets how far a
            vertex may move per substep: newton's penetration-free truncation (divide and
            truncate) caps it at about 0.43 (margin + gap), so (5 + 10) mm lets the cloth move
            6 mm per substep (2 m/s at 30 fps x 10). A smaller gap makes the cloth lag behind
            a fast knee, which then passes through it.
        gravity: m/s^2 along -Z.
        settle_hold_frames: frames in the rest pose before blending into the motion.
        settle_frames: frames blending from the rest pose into the motion's first frame (>= 1).
        chunk_frames: frames per saved chunk (and per simulator restart; see the module doc).
    """

    substeps: int = 10
    iterations: int = 10
    density: float = 0.2
    stretch_stiffness: float = 1.0e3
    stretch_damping: float = 1.0e-2
    bend_stiffness: float = 1.0e-3
    bend_damping: float = 0.0
    contact_ke: float = 1.0e5
    contact_kd: float = 1.0e-1
    friction: float = 0.3
    thickness: float = 0.005
    contact_gap: float = 0.015
    self_contact: bool = True
    self_contact_margin: float = 0.005
    self_contact_gap: float = 0.010
    gravity: float = 9.81
    settle_hold_frames: int = 10
    settle_frames: int = 30
    chunk_frames: int = 32

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int):
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                    raise ValueError(f"SimSettings.{f.name} must be an integer, got {value!r}")
                low = 0 if f.name == "settle_hold_frames" else 1
                if value < low:
                    raise ValueError(f"SimSettings.{f.name} must be >= {low}, got {value}")
            elif f.type in ("bool", bool):
                if not isinstance(value, (bool, np.bool_)):
                    raise ValueError(f"SimSettings.{f.name} must be True or False, got {value!r}")
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                    raise ValueError(f"SimSettings.{f.name} must be a number, got {value!r}")
                if not math.isfinite(float(value)) or float(value) < 0:
                    raise ValueError(f"SimSettings.{f.name} must be a finite number >= 0, got {value!r}")
        if self.thickness <= 0 or self.density <= 0:
            raise ValueError("SimSettings.thickness and density must be > 0")

    def to_dict(self) -> dict:
        return {k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in asdict(self).items()}

    @staticmethod
    def from_dict(d: dict) -> "SimSettings":
        known = {f.name for f in fields(SimSettings)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown simulation settings: {', '.join(unknown)}")
        return SimSettings(**d)


@dataclass
class SimResult:
    """What :func:`simulate` returns.

    Attributes:
        vertices: (T, Vg, 3) float32 garment vertices at every motion frame, world metres.
        penetration_max_m: (T,) float32 depth of the deepest garment vertex inside the body per
            frame (0 where none is inside).
        seconds_per_frame: mean wall-clock seconds per simulated motion frame (substeps,
            collision, penetration measurement; the settling and the loading of saved chunks
            excluded; over the chunks' stored timings when everything was loaded).
        fps: the motion's frame rate.
        settings: the :class:`SimSettings` used.
        frames_computed: motion frames simulated by this call (the rest came from ``out_dir``).
        cpu_seconds_per_frame: the same in process CPU time (what one core spends, independent
            of how busy the machine is; NaN when everything was loaded).
    """

    vertices: np.ndarray
    penetration_max_m: np.ndarray
    seconds_per_frame: float
    fps: float
    settings: SimSettings
    frames_computed: int = 0
    cpu_seconds_per_frame: float = float("nan")


# ------------------------------------------------------------------------------------------------
# warp / newton set-up
# ------------------------------------------------------------------------------------------------
@functools.cache
def _warp():
    """Import warp and newton (quietly), check newton's version, define our kernel: once per
    process (a failed import is not cached, so installing newton and retrying works)."""
    # local: newton costs 2.9 s and only the simulation processes need it (data make's own process
    # reads SimSettings and the chunk files); a missing newton fails here with the message below
    try:
        import warp as wp
    except ImportError as exc:  # pragma: no cover - warp comes with newton
        raise SimulationError("cloth simulation needs the 'newton' package (pip install newton==1.8.0)") from exc
    if wp.config.log_level == wp.LOG_INFO:  # the default: hide the banner and module-load messages
        wp.config.log_level = wp.LOG_WARNING
    try:
        import newton
    except ImportError as exc:
        raise SimulationError("cloth simulation needs the 'newton' package (pip install newton==1.8.0)") from exc
    if not str(newton.__version__).startswith(NEWTON_VERSION.rsplit(".", 1)[0]):
        raise SimulationError(f"garmentnerf's simulator is written for newton {NEWTON_VERSION}, found "
                              f"{newton.__version__} (pip install newton=={NEWTON_VERSION})")

    @wp.kernel
    def signed_distance_kernel(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
        i = wp.tid()
        p = points[i]
        q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e6, 2.0, 0.5)
        if q.result:
            out[i] = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v)) * q.sign
        else:
            out[i] = 1.0e6

    return wp, newton, signed_distance_kernel


#: Skin within this distance of a cloth particle at the start of a frame counts for
#: :func:`frame_substeps` (a fast hand far from a t-shirt's sleeve costs no substeps).
NEAR_CLOTH_M = 0.05

#: :func:`frame_substeps` takes at most this many times ``SimSettings.substeps``.
MAX_SUBSTEP_FACTOR = 4


def cloth_step_limit(settings: SimSettings) -> float:
    """How far (m) the skin may move in one solver step and still be met by the cloth: the
    contact detection distance (``contact_gap``), and with self-contact also the distance newton's
    penetration-free truncation lets a particle move per step (about 0.43 x (margin + gap))."""
    limit = float(settings.contact_gap)
    if settings.self_contact:
        limit = min(limit, 0.43 * (float(settings.self_contact_margin) + float(settings.self_contact_gap)))
    return limit


def frame_substeps(body0: np.ndarray, body1: np.ndarray, cloth: np.ndarray, settings: SimSettings) -> int:
    """Solver steps for one frame: ``settings.substeps``, or more when the skin near the cloth
    moves farther in one step than :func:`cloth_step_limit` (the cloth would then lag behind a
    fast arm or knee, which passes through it), at most :data:`MAX_SUBSTEP_FACTOR` times as many.

    Args:
        body0, body1: (V, 3) the skin at the start and the end of the frame.
        cloth: (Vg, 3) the cloth particles at the start of the frame.
    """
    base = int(settings.substeps)
    distance, _ = cKDTree(np.asarray(cloth, np.float64)).query(np.asarray(body0, np.float64),
                                                               distance_upper_bound=NEAR_CLOTH_M)
    near = np.isfinite(distance)
    if not near.any():
        return base
    travel = float(np.linalg.norm((body1 - body0)[near], axis=1).max())
    needed = int(np.ceil(travel / cloth_step_limit(settings)))
    return int(min(max(base, needed), base * MAX_SUBSTEP_FACTOR))


class _ClothSim:
    """One newton model (cloth + body collider), its VBD solver and collision pipeline.

    Built fresh from a particle state at every chunk boundary (see the module docstring)."""

    def __init__(self, garment: Garment, body_faces: np.ndarray, body_rest: np.ndarray, settings: SimSettings,
                 q: np.ndarray, qd: np.ndarray):
        wp, newton, self._sd_kernel = _warp()
        self.wp = wp
        s = settings
        self.settings = s
        device = "cpu"
        builder = newton.ModelBuilder(gravity=(0.0, 0.0, -float(s.gravity)))
        builder.add_cloth_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=garment.vertices.astype(np.float64).tolist(), indices=garment.faces.reshape(-1).tolist(),
            density=float(s.density), tri_ke=float(s.stretch_stiffness), tri_ka=float(s.stretch_stiffness),
            tri_kd=float(s.stretch_damping), edge_ke=float(s.bend_stiffness), edge_kd=float(s.bend_damping),
            particle_radius=float(s.thickness))
        for i in garment.pinned.tolist():
            builder.particle_mass[i] = 0.0
        cfg = newton.ModelBuilder.ShapeConfig(ke=float(s.contact_ke), kd=float(s.contact_kd), mu=float(s.friction),
                                              margin=0.0, has_shape_collision=False, has_particle_collision=True)
        self.collider = newton.Mesh(body_rest.astype(np.float32), body_faces.reshape(-1).astype(np.int32),
                                    compute_inertia=False)
        builder.add_shape_mesh(-1, mesh=self.collider, cfg=cfg, label="body")
        builder.color(include_bending=True)
        model = builder.finalize(device=device)
        model.soft_contact_ke = float(s.contact_ke)
        model.soft_contact_kd = float(s.contact_kd)
        model.soft_contact_mu = float(s.friction)
        model.edge_rest_angle.zero_()
        model.shape_collision_aabb_lower.assign(np.full((model.shape_count, 3), -1.0e3, np.float32))
        model.shape_collision_aabb_upper.assign(np.full((model.shape_count, 3), 1.0e3, np.float32))
        self.model = model
        self.mesh = self.collider.mesh  # the wp.Mesh the collision kernels query
        self.solver = newton.solvers.SolverVBD(
            model, iterations=int(s.iterations), particle_enable_self_contact=bool(s.self_contact),
            particle_self_contact_margin=float(s.self_contact_margin),
            particle_self_contact_gap=float(s.self_contact_gap))
        self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=float(s.contact_gap))
        self.contacts = self.pipeline.contacts()
        self.state = model.state()
        self.scratch = model.state()
        self.control = model.control()
        self.pinned = garment.pinned
        self.state.particle_q.assign(np.ascontiguousarray(q, np.float32))
        self.state.particle_qd.assign(np.ascontiguousarray(qd, np.float32))
        self._sd = wp.zeros(model.particle_count, dtype=float, device=device)
        # The penetration measurement uses its own copy of the body with winding-number support.
        self._measure = wp.Mesh(points=wp.array(body_rest.astype(np.float32), dtype=wp.vec3, device=device),
                                indices=wp.array(body_faces.reshape(-1).astype(np.int32), dtype=wp.int32,
                                                 device=device),
                                support_winding_number=True)

    def set_body(self, vertices: np.ndarray, velocities: np.ndarray) -> None:
        self.mesh.points.assign(vertices)
        self.mesh.velocities.assign(velocities)
        self.mesh.refit()

    def advance(self, body0: np.ndarray, body1: np.ndarray, pins0: np.ndarray, pins1: np.ndarray,
                fps: float) -> None:
        """Simulate one frame: the body goes from ``body0`` to ``body1`` (V, 3), the pinned
        vertices from ``pins0`` to ``pins1`` (P, 3), in :func:`frame_substeps` steps."""
        n = frame_substeps(body0, body1, self.state.particle_q.numpy(), self.settings)
        dt = 1.0 / (fps * n)
        body_vel = ((body1 - body0) * fps).astype(np.float32)
        pin_vel = ((pins1 - pins0) * fps).astype(np.float32)
        self.solver.rebuild_bvh(self.state)
        for k in range(n):
            a = (k + 1) / n
            self.set_body((body0 + (body1 - body0) * a).astype(np.float32), body_vel)
            if self.pinned.size:
                # CPU warp arrays: .numpy() is a view, so this writes the simulation state.
                self.state.particle_q.numpy()[self.pinned] = pins0 + (pins1 - pins0) * a
                self.state.particle_qd.numpy()[self.pinned] = pin_vel
            self.state.clear_forces()
            self.pipeline.collide(self.state, self.contacts)
            self.solver.step(self.state, self.scratch, self.control, self.contacts, dt)
            self.state, self.scratch = self.scratch, self.state

    def positions(self) -> np.ndarray:
        return self.state.particle_q.numpy().copy()

    def velocities(self) -> np.ndarray:
        return self.state.particle_qd.numpy().copy()

    def signed_distance(self, body_vertices: np.ndarray) -> np.ndarray:
        """(Vg,) signed distance of the particles to the body posed at ``body_vertices`` (V, 3),
        positive outside; the sign is the body's generalized winding number at the particle."""
        self._measure.points.assign(np.ascontiguousarray(body_vertices, np.float32))
        self._measure.refit()
        self.wp.launch(self._sd_kernel, dim=self.model.particle_count,
                       inputs=[self._measure.id, self.state.particle_q, self._sd], device="cpu")
        return self._sd.numpy().copy()


# ------------------------------------------------------------------------------------------------
# Body trajectory
# ------------------------------------------------------------------------------------------------
class _Trajectory:
    """Posed body vertices and pinned-vertex targets for the settle and motion frames.

    Settle frame k (k = 0 .. H + S): rotations ``w_k * r_0`` (rotation vectors of motion frame
    0), translation ``w_k * t_0``, with w = 0 for the first H + 1 frames and a smoothstep from
    0 to 1 over the last S; the last settle frame is motion frame 0.
    """

    def __init__(self, garment: Garment, body: "BodyModel", motion: "Motion", betas: torch.Tensor,
                 faces: np.ndarray, settings: SimSettings):
        self.body, self.motion, self.betas = body, motion, betas
        rest = body.rest(betas)[0].detach().cpu().double().numpy()
        self.rest = rest
        pins = garment.vertices[garment.pinned].astype(np.float64)
        self.pin_rest = torch.as_tensor(pins, dtype=body.dtype)
        if pins.shape[0]:
            mesh = trimesh.Trimesh(rest, faces, process=False)
            closest, _, tri = trimesh.proximity.closest_point(mesh, pins)
            bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
            corners = faces[tri]  # (P, 3)
            W = body.weights.detach().cpu().double().numpy()
            pin_w = np.einsum("pk,pkj->pj", bary, W[corners])
            self.pin_weights = torch.as_tensor(pin_w, dtype=body.dtype)
        else:
            self.pin_weights = torch.zeros(0, body.num_joints, dtype=body.dtype)
        H, S = settings.settle_hold_frames, settings.settle_frames
        x = np.arange(1, S + 1) / max(S, 1)
        self.settle_w = np.concatenate([np.zeros(H + 1), x * x * (3 - 2 * x)]) if S else np.zeros(H + 1)

    def _pins(self, posed) -> np.ndarray:
        if self.pin_weights.shape[0] == 0:
            return np.zeros((posed.vertices.shape[0], 0, 3), np.float32)
        A = torch.einsum("pj,tjab->tpab", self.pin_weights, posed.joint_transforms)  # (T, P, 3, 4)
        p = (A[..., :3] @ self.pin_rest[None, :, :, None])[..., 0] + A[..., 3] + posed.translation[:, None, :]
        return p.detach().cpu().numpy().astype(np.float32)

    def settle(self) -> tuple[np.ndarray, np.ndarray]:
        """Body vertices (K, V, 3) and pin targets (K, P, 3) of the settle frames."""
        first = self.motion.slice(0, 1)
        r0 = first.rotations_for(self.body)[0]
        t0 = first.translation[0].to(self.body.dtype)
        w = torch.as_tensor(self.settle_w, dtype=self.body.dtype)
        posed = self.body.pose(w[:, None, None] * r0[None], w[:, None] * t0[None], self.betas)
        return posed.vertices.detach().cpu().numpy().astype(np.float32), self._pins(posed)

    def frames(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Body vertices and pin targets of motion frames [start, stop)."""
        posed = self.motion.slice(start, stop).pose(self.body, self.betas)
        return posed.vertices.detach().cpu().numpy().astype(np.float32), self._pins(posed)


# ------------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------------
def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:32]


def _manifest(garment: Garment, motion: "Motion", betas: torch.Tensor, settings: SimSettings, T: int) -> dict:
    return {
        "format": _FORMAT,
        "version": _VERSION,
        "newton": NEWTON_VERSION,
        "garment": {"name": garment.name, "kind": garment.kind,
                    "digest": _digest(garment.vertices, garment.faces, garment.pinned)},
        "motion": {"name": motion.name, "fps": float(motion.fps), "frames": motion.num_frames,
                   "digest": _digest(motion.rotations.numpy(), motion.translation.numpy(),
                                     np.array([motion.fps]))},
        "betas_digest": _digest(betas.detach().cpu().numpy().astype(np.float32)),
        "settings": settings.to_dict(),
        "frames": int(T),
    }


def _check_manifest(path: Path, expected: dict) -> None:
    try:
        found = read_json_strict(path, "simulation manifest")
    except (OSError, ValueError) as exc:
        raise SimulationResumeError(f"{path}: unreadable simulation manifest ({exc}); delete the folder "
                                    f"to start over") from exc
    if not isinstance(found, dict):
        raise SimulationResumeError(f"{path}: not a simulation manifest")
    # The frame count may differ: chunks are reused when their frame range is unchanged.
    for key in ("format", "version", "newton", "garment", "motion", "betas_digest", "settings"):
        if found.get(key) != expected[key]:
            raise SimulationResumeError(
                f"{path.parent}: holds a simulation with another {key} ({found.get(key)!r} here, "
                f"{expected[key]!r} requested); use another out_dir or delete this one")


def _save_npz(path: Path, **arrays) -> None:
    with atomic_write_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _load_state_file(path: Path, Vg: int, first: int | None = None, count: int | None = None) -> dict | None:
    """A chunk or settle file's arrays if it is complete and has the expected shapes, else None."""
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except Exception:
        return None
    for key in ("q", "qd"):
        if key not in out or out[key].shape != (Vg, 3) or not np.isfinite(out[key]).all():
            return None
    if first is not None:
        n = count
        if (int(out.get("first_frame", -1)) != first or "vertices" not in out or out["vertices"].shape != (n, Vg, 3)
                or "penetration" not in out or out["penetration"].shape != (n,)):
            return None
    return out


def _chunk_path(out_dir: Path, k: int) -> Path:
    return out_dir / f"chunk_{k:06d}.npz"


# ------------------------------------------------------------------------------------------------
# The steps of a simulation
# ------------------------------------------------------------------------------------------------
def _checked_betas(garment: Garment, body: "BodyModel", betas: torch.Tensor | str | None) -> torch.Tensor:
    """(S,) shape coefficients in ``body.dtype``: ``betas`` as given (None: the garment's own),
    which must be the shape the garment was built for."""
    garment_betas = torch.as_tensor(garment.betas, dtype=body.dtype)
    if betas is None:
        betas = garment_betas
    elif not isinstance(betas, torch.Tensor):
        betas = body.betas(betas)
    betas = betas.to(body.dtype)
    if betas.shape != garment_betas.shape or not torch.allclose(betas, garment_betas, atol=1e-6):
        raise ValueError(f"garment '{garment.name}' was built for another body shape than the one simulated; "
                         f"build it with make_garment(kind, body, betas) for this shape")
    return betas


def _claim_out_dir(out_dir: Path, manifest: dict) -> None:
    """Create ``out_dir`` and write its manifest; one of other inputs raises SimulationResumeError."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / _MANIFEST
    if path.exists():
        _check_manifest(path, manifest)
    with atomic_write_path(path) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1))


def _saved_chunks(out_dir: Path | None, Vg: int, T: int, C: int) -> list[dict]:
    """The complete chunks already on disk, in order, up to the first missing or damaged one."""
    chunks: list[dict] = []
    if out_dir is None:
        return chunks
    for k in range((T + C - 1) // C):
        first, count = k * C, min(C, T - k * C)
        data = _load_state_file(_chunk_path(out_dir, k), Vg, first, count)
        if data is None:
            break
        chunks.append(data)
    return chunks


@dataclass
class _SimulationJob:
    """What every step of one :func:`simulate` call shares.

    Attributes:
        garment: the garment; ``faces`` (F, 3) the body faces that collide; ``trajectory`` the
        body and pin targets; ``settings``; ``fps`` the motion's; ``bar`` a tqdm bar or None.
    """

    garment: Garment
    faces: np.ndarray
    trajectory: _Trajectory
    settings: SimSettings
    fps: float
    bar: object | None

    def _cloth(self, q: np.ndarray, qd: np.ndarray) -> _ClothSim:
        rest = self.trajectory.rest.astype(np.float32)
        return _ClothSim(self.garment, self.faces, rest, self.settings, q, qd)

    def settle(self) -> dict:
        """Drape the garment from its rest shape (see the module docstring): ``{"q", "qd"}``
        (Vg, 3) particle positions and velocities on motion frame 0, ``"penetration"`` there."""
        body_k, pins_k = self.trajectory.settle()
        sim = self._cloth(self.garment.vertices, np.zeros_like(self.garment.vertices))
        for k in range(1, len(body_k)):
            sim.advance(body_k[k - 1], body_k[k], pins_k[k - 1], pins_k[k], self.fps)
            if self.bar is not None:
                self.bar.update(1)
        q, qd = sim.positions(), sim.velocities()
        _check_finite(q, qd, "settling")
        penetration = float(max(0.0, -sim.signed_distance(body_k[-1]).min()))
        return {"q": q, "qd": qd, "penetration": np.float32(penetration)}

    def chunk(self, q: np.ndarray, qd: np.ndarray, first: int, count: int) -> dict:
        """Motion frames [first, first + count) from the particle state ``q``, ``qd`` (Vg, 3) at
        frame ``first - 1`` (the settled state for ``first = 0``), on a freshly built simulator.

        Returns the chunk file's arrays: ``vertices`` (count, Vg, 3), ``penetration`` (count,),
        ``q``/``qd`` at the last frame, ``first_frame``, ``seconds`` and ``cpu_seconds``."""
        t_start, c_start = time.perf_counter(), time.process_time()
        lo = max(0, first - 1)
        body_f, pins_f = self.trajectory.frames(lo, first + count)
        sim = self._cloth(q, qd)
        verts = np.zeros((count, self.garment.num_vertices, 3), np.float32)
        pen = np.zeros(count, np.float32)
        for i in range(count):
            f = first + i
            if f == 0:
                sim.set_body(body_f[0], np.zeros_like(body_f[0]))
                verts[0] = q
            else:
                j = f - lo
                sim.advance(body_f[j - 1], body_f[j], pins_f[j - 1], pins_f[j], self.fps)
                verts[i] = sim.positions()
                _check_finite(verts[i], sim.velocities(), f"frame {f}")
            pen[i] = max(0.0, -float(sim.signed_distance(body_f[f - lo]).min()))
            if self.bar is not None:
                self.bar.update(1)
                self.bar.set_postfix(pen_mm=f"{pen[i] * 1000:.1f}")
        q, qd = sim.positions(), sim.velocities()
        return {"first_frame": np.int64(first), "vertices": verts, "penetration": pen, "q": q, "qd": qd,
                "seconds": np.float64(time.perf_counter() - t_start),
                "cpu_seconds": np.float64(time.process_time() - c_start)}


def _progress_bar(frames: int, description: str):
    """A tqdm bar over ``frames`` frames, or None when there are none to simulate."""
    if frames <= 0:
        return None

    return tqdm(total=frames, desc=description, unit="frame", leave=False)


def _result(chunks: list[dict], computed: list[dict], T: int, fps: float, settings: SimSettings) -> SimResult:
    """The :class:`SimResult` of all ``chunks``; timings from those ``computed`` by this call
    (from the stored timings when everything was loaded)."""
    vertices = np.concatenate([c["vertices"] for c in chunks])[:T]
    penetration = np.concatenate([c["penetration"] for c in chunks])[:T].astype(np.float32)
    frames = sum(c["vertices"].shape[0] for c in computed)
    if frames:
        spf = sum(float(c["seconds"]) for c in computed) / frames
        cpf = sum(float(c["cpu_seconds"]) for c in computed) / frames
    else:
        spf = float(sum(float(c.get("seconds", 0.0)) for c in chunks)) / max(T, 1)
        cpf = float("nan")
    return SimResult(vertices=vertices, penetration_max_m=penetration, seconds_per_frame=spf, fps=fps,
                     settings=settings, frames_computed=frames, cpu_seconds_per_frame=cpf)


# ------------------------------------------------------------------------------------------------
# Entry point
# ------------------------------------------------------------------------------------------------
def simulate(garment: Garment, body: "BodyModel", motion: "Motion", betas: torch.Tensor | str | None = None,
             settings: SimSettings = SimSettings(), out_dir: str | Path | None = None, progress: bool = True,
             max_frames: int | None = None, _stop_after_chunks: int | None = None) -> SimResult:
    """Simulate ``garment`` on ``body`` playing ``motion`` (see the module docstring).

    Args:
        garment: from :func:`~garmentnerf.data.garments.make_garment`, built for the same shape.
        body: the body model.
        motion: the motion (its fps sets the frame time).
        betas: body shape (tensor, preset name, vector); None = the garment's own shape.
        settings: solver settings.
        out_dir: folder for resumable chunks (created); None keeps everything in memory.
        progress: show a tqdm progress bar.
        max_frames: simulate only the first ``max_frames`` motion frames.
        _stop_after_chunks: test hook: raise KeyboardInterrupt after writing this many chunks.
    Returns:
        :class:`SimResult`.
    Raises:
        SimulationError: NaN/Inf in the cloth state, or newton missing/of another version.
        SimulationResumeError: ``out_dir`` holds another simulation.
        KeyboardInterrupt: passed on after the chunks finished so far are safely on disk.
    """
    if not isinstance(settings, SimSettings):
        raise TypeError(f"settings must be a SimSettings, got {type(settings).__name__}")
    betas = _checked_betas(garment, body, betas)
    T = motion.num_frames if max_frames is None else min(int(max_frames), motion.num_frames)
    if T < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    C = settings.chunk_frames
    n_chunks = (T + C - 1) // C
    faces = body_collision_faces(body)
    trajectory = _Trajectory(garment, body, motion, betas, faces, settings)
    out_path = Path(out_dir) if out_dir is not None else None
    if out_path is not None:
        _claim_out_dir(out_path, _manifest(garment, motion, betas, settings, T))

    # What is already on disk: a prefix of complete chunks, else perhaps the settled state.
    chunks = _saved_chunks(out_path, garment.num_vertices, T, C)
    settled = None
    if out_path is not None and not chunks:
        settled = _load_state_file(out_path / _SETTLE, garment.num_vertices)

    settle_frames = len(trajectory.settle_w) - 1
    todo_frames = (0 if chunks else settle_frames) + (T - sum(c["vertices"].shape[0] for c in chunks))
    bar = _progress_bar(todo_frames, f"simulate {garment.name}/{motion.name}") if progress else None
    job = _SimulationJob(garment, faces, trajectory, settings, float(motion.fps), bar)
    computed: list[dict] = []
    try:
        if chunks:
            state = chunks[-1]
        elif settled is not None:
            state = settled
        else:
            state = job.settle()
            if out_path is not None:
                _save_npz(out_path / _SETTLE, **state)
        for k in range(len(chunks), n_chunks):
            data = job.chunk(state["q"], state["qd"], k * C, min(C, T - k * C))
            if out_path is not None:
                _save_npz(_chunk_path(out_path, k), **data)
            chunks.append(data)
            computed.append(data)
            state = data
            if _stop_after_chunks is not None and len(computed) >= _stop_after_chunks:
                raise KeyboardInterrupt(f"test hook: stopped after {len(computed)} chunk(s)")
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
            bar = None
        if out_path is not None:
            print(f"simulation interrupted; {len(chunks)} of {n_chunks} chunks are saved in {out_path} "
                  f"(run again with the same out_dir to resume)", file=sys.stderr)
        raise
    finally:
        if bar is not None:
            bar.close()
    return _result(chunks, computed, T, job.fps, settings)


def _check_finite(q: np.ndarray, qd: np.ndarray, where: str) -> None:
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        raise SimulationError(f"cloth simulation diverged (NaN/Inf) at {where}; try more substeps or iterations")


def benchmark_simulation(body: "BodyModel", kinds=("skirt", "tshirt", "dress"), motion: str = "walk",
                         frames: int = 10, fps: float = 30.0, settings: SimSettings | None = None,
                         betas: str | None = "average", progress: bool = False) -> list[dict]:
    """Cost and penetration of each garment kind on the first ``frames`` frames of ``motion``.

    Uses a short settle (5 frames at rest, 10 blending) unless ``settings`` says otherwise.
    Returns one dict per kind: ``kind``, ``vertices``, ``frames``, ``seconds_per_frame`` (wall),
    ``cpu_seconds_per_frame``, ``penetration_max_mm``, ``frames_with_penetration``.
    """
    from garmentnerf.motion.library import load_motion  # local: benchmark only; brings roma (1.5 s)

    settings = settings or SimSettings(settle_hold_frames=5, settle_frames=10)
    clip = load_motion(motion, body, betas, fps=fps)
    rows = []
    for kind in kinds:
        garment = make_garment(kind, body, betas)
        # frames + 1: output frame 0 is the settled state, the next ``frames`` are simulated
        r = simulate(garment, body, clip, settings=settings, progress=progress, max_frames=frames + 1)
        rows.append({"kind": kind, "vertices": garment.num_vertices, "frames": frames,
                     "seconds_per_frame": r.seconds_per_frame, "cpu_seconds_per_frame": r.cpu_seconds_per_frame,
                     "penetration_max_mm": float(r.penetration_max_m.max() * 1000),
                     "frames_with_penetration": int((r.penetration_max_m > 0).sum())})
    return rows
