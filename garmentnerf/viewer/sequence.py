"""A posed body clip ready for the GPU, the motions the window offers, and the background loader.

The whole clip is posed once (linear blend skinning of every frame in one call) and its smooth
normals computed, so playing it only copies one frame's (V, 6) interleaved position+normal array into
the vertex buffer. About 0.3 MB per frame for the anny body (13,718 vertices).

:class:`MotionMenu` lists the motions (the run scene's sequences first: they have ground truth) and
poses the chosen one on a :class:`BackgroundLoader`'s thread, so no torch work runs on the UI thread.
"""

from __future__ import annotations

import functools
import hashlib
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.motion.library import available_motions, load_motion
from garmentnerf.render.session import resolve_motion
from garmentnerf.viewer.camera import follow_track


@dataclass
class BodySequence:
    """A posed clip.

    Attributes:
        name: the motion's name.
        fps: its frame rate.
        vertices: (T, V, 3) float32 positions (metres, world).
        faces: (F, 3) int32 triangles, counter-clockwise seen from outside.
        centers: (T, 3) float64 per-frame centre of the body (mean vertex), for the floor's contact
            shadow; :attr:`track` (smoothed on the ground) anchors a following camera.

    A frame's unit vertex normals are computed the first time it is asked for (:meth:`frame`, a few
    milliseconds), not for the whole clip at once: the window's first frame waits for the first
    clip to be posed, and the normals of 170 frames took as long as posing them.
    """

    name: str
    fps: float
    vertices: np.ndarray
    faces: np.ndarray
    centers: np.ndarray
    _data: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _ready: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _incidence: object = field(default=None, init=False, repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

    @functools.cached_property
    def track(self) -> np.ndarray:
        """(T, 3) where a following camera is anchored at each frame
        (:func:`~garmentnerf.viewer.camera.follow_track` of :attr:`centers`)."""
        return follow_track(self.centers, self.fps)

    @functools.cached_property
    def track_key(self) -> str:
        """A digest of :attr:`track` (tells the follow views of two clips apart)."""
        return hashlib.sha1(np.ascontiguousarray(self.track).tobytes()).hexdigest()[:16]

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    def frame(self, index: int) -> np.ndarray:
        """(V, 6) float32 contiguous [position, unit normal] of frame ``index`` (thread-safe)."""
        index = range(self.num_frames)[index]  # IndexError outside the clip, negative from the end
        with self._lock:
            if self._data is None:
                self._data = np.empty((self.num_frames, self.num_vertices, 6), dtype=np.float32)
                self._ready = np.zeros(self.num_frames, dtype=bool)
            if not self._ready[index]:
                if self._incidence is None:
                    self._incidence = vertex_face_incidence(self.faces, self.num_vertices)
                self._data[index, :, :3] = self.vertices[index]
                self._data[index, :, 3:] = shading_normals(self.vertices[index:index + 1], self.faces,
                                                           self._incidence)[0]
                self._ready[index] = True
            return self._data[index]

    @property
    def vertex_data(self) -> np.ndarray:
        """(T, V, 6) float32 :meth:`frame` of every frame (computes the missing ones)."""
        for index in range(self.num_frames):
            self.frame(index)
        return self._data

    def positions(self, index: int) -> np.ndarray:
        return self.vertices[index]

    @staticmethod
    def from_vertices(name: str, fps: float, vertices, faces) -> "BodySequence":
        """From (T, V, 3) positions and (F, 3) faces (normals computed per frame when asked for)."""
        if isinstance(vertices, torch.Tensor):
            vertices = vertices.detach().cpu().numpy()
        verts = np.ascontiguousarray(vertices, dtype=np.float32)
        if verts.ndim == 2:
            verts = verts[None]
        if verts.ndim != 3 or verts.shape[-1] != 3 or verts.shape[0] < 1:
            raise ValueError(f"body vertices must be (T, V, 3), got {tuple(verts.shape)}")
        if not np.isfinite(verts).all():
            raise ValueError("body vertices contain NaN or Inf")
        tris = np.asarray(faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else faces, dtype=np.int64)
        if tris.ndim != 2 or tris.shape[1] != 3 or (tris.size and (tris.min() < 0 or tris.max() >= verts.shape[1])):
            raise ValueError(f"faces must be (F, 3) indices of the {verts.shape[1]} vertices, got {tris.shape}")
        centers = verts.mean(axis=1, dtype=np.float64)
        return BodySequence(name, float(fps), verts, tris.astype(np.int32), centers)

    @staticmethod
    def load(body, betas, motion: str) -> "BodySequence":
        """Load ``motion`` (a name, names joined by ',', or a file; see
        :func:`garmentnerf.motion.library.load_motion`) and pose ``body`` with shape ``betas``."""
        clip = load_motion(motion, body, betas=betas)
        with torch.no_grad():
            posed = clip.pose(body, betas)
        return BodySequence.from_vertices(clip.name, clip.fps, posed.vertices, body.faces)


def vertex_face_incidence(faces: np.ndarray, num_vertices: int):
    """(V, F) sparse matrix with a 1 where a vertex is a corner of a face (:func:`shading_normals`)."""
    import scipy.sparse as sp  # lazy: the window imports it with the model anyway

    faces = np.asarray(faces, dtype=np.int64)
    F = len(faces)
    return sp.csr_matrix((np.ones(3 * F, np.float32), (faces.reshape(-1), np.repeat(np.arange(F), 3))),
                         shape=(int(num_vertices), F))


def shading_normals(vertices: np.ndarray, faces: np.ndarray, incidence=None) -> np.ndarray:
    """(T, V, 3) float32 area-weighted unit vertex normals of (T, V, 3) ``vertices`` (vertices of no
    face get (0, 0, 0)): :func:`garmentnerf.body.surface.vertex_normals` for the screen (within 1e-4
    of it, the sums in another order), in numpy with frames side by side (0.4 s against 1.05 s for
    170 frames of the anny body, 2 to 3 ms a frame). ``incidence``: :func:`vertex_face_incidence`
    of ``faces`` (made here when None)."""
    verts = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64)
    T, V, _ = verts.shape
    F = len(faces)
    by_vertex = np.ascontiguousarray(verts.transpose(1, 0, 2))  # (V, T, 3): a face's corners are rows
    a, b, c = (by_vertex[faces[:, i]] for i in range(3))  # (F, T, 3)
    e1, e2 = b - a, c - a
    face_n = np.empty_like(e1)  # the cross product: its length is twice the area (the weighting)
    face_n[..., 0] = e1[..., 1] * e2[..., 2] - e1[..., 2] * e2[..., 1]
    face_n[..., 1] = e1[..., 2] * e2[..., 0] - e1[..., 0] * e2[..., 2]
    face_n[..., 2] = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    if incidence is None:
        incidence = vertex_face_incidence(faces, V)
    n = np.asarray(incidence @ face_n.reshape(F, -1), dtype=np.float32).reshape(V, T, 3)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), np.float32(1e-20))
    return n.transpose(1, 0, 2)


class BackgroundLoader:
    """Runs ``load(name)`` (posing a :class:`BodySequence`, loading a run) on one background thread,
    newest request wins.

    ``request(name)`` returns at once; the app calls :meth:`poll` every frame and gets the finished
    result (or the error) exactly once. A request made while another is loading supersedes it:
    the older result is dropped when it arrives.
    """

    def __init__(self, load: Callable[[str], Any], thread_name: str = "garmentnerf-motion") -> None:
        self._load = load
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=thread_name)
        self._lock = threading.Lock()
        self._future: Future | None = None
        self._pending_name: str | None = None

    @property
    def loading(self) -> str | None:
        """The name being loaded, or None."""
        with self._lock:
            return self._pending_name

    def request(self, motion: str) -> None:
        with self._lock:
            if self._future is not None:
                self._future.cancel()  # only succeeds if it has not started; else its result is dropped
            self._pending_name = motion
            self._future = self._executor.submit(self._load, motion)

    def poll(self) -> tuple[Any, BaseException | None]:
        """(result, None) when the newest request finished, (None, error) when it failed, else (None, None)."""
        with self._lock:
            future = self._future
            if future is None or not future.done():
                return None, None
            self._future = None
            self._pending_name = None
        error = future.exception()
        return (None, error) if error is not None else (future.result(), None)

    def wait(self, timeout: float | None = None) -> tuple[Any, BaseException | None]:
        """Block until the newest request finishes (tests), then :meth:`poll`."""
        with self._lock:
            future = self._future
        if future is not None:
            try:
                future.result(timeout)
            except Exception:  # noqa: BLE001 - reported by poll()
                pass
        return self.poll()

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


def body_and_shape(run, body, betas) -> tuple[Any, Any, str]:
    """(body model, shape coefficients, shape label): the run's body (and its shape unless one is
    given), else ``body`` (default: the bundled anny body); ``betas`` may be a preset name."""
    if run is not None:
        body = run.model.body
        if getattr(run, "betas", None) is not None and betas is None:
            betas = run.betas
    if body is None:
        body = BodyModel.default()
    if betas is None or isinstance(betas, str):
        return body, body.betas(betas), betas or "average"
    return body, betas, "custom"


class MotionMenu:
    """The motions the window offers and how a chosen one becomes a posed clip.

    Args:
        body: the :class:`~garmentnerf.body.model.BodyModel`; betas: its shape coefficients.
        run: a :class:`~garmentnerf.runs.LoadedRun` whose scene sequences come first (None: none).
    """

    def __init__(self, body, betas, run=None) -> None:
        self.body, self.betas, self.run = body, betas, run
        self._infos = {m.name: m for m in available_motions()}
        self._loader = BackgroundLoader(self._load)

    def first_clip(self, motion: str | None, sequence: BodySequence | None = None) -> tuple[BodySequence, str, Any]:
        """(clip, its name in the menu, its motion spec for the neural render) the window starts with:
        ``sequence`` if given; with a run ``motion`` as its session resolves it (:meth:`pose_for_run`);
        else the library motion ``motion`` (default ``walk``). Posed here, before the window opens."""
        if sequence is not None:
            return sequence, sequence.name, sequence.name
        if self.run is not None:
            sequence, spec = self.pose_for_run(motion)
            return sequence, sequence.name, spec
        motion = motion or "walk"
        return BodySequence.load(self.body, self.betas, motion), motion, motion

    def scene_sequences(self) -> list[str]:
        run = self.run
        return list(run.scene.sequences) if run is not None and run.scene is not None else []

    def names(self, current: str) -> list[str]:
        """The run scene's sequences, then the library's motions (``current`` first if it is neither)."""
        seqs = self.scene_sequences()
        names = seqs + [n for n in self._infos if n not in seqs]
        return names if current in names else [current] + names

    def labels(self, names: list[str]) -> list[str]:
        """What the menu shows for ``names``: ``walk  (4.2 s)``, ``train  (scene sequence)``."""
        seqs = set(self.scene_sequences())
        return [f"{n}  (scene sequence)" if n in seqs else f"{n}  ({self._infos[n].duration:.1f} s)"
                if n in self._infos else n for n in names]

    def pose_for_run(self, motion: str | None) -> tuple[BodySequence, Any]:
        """(clip, its motion spec for the neural render), ``motion`` resolved as the run's render
        session resolves it (a scene sequence; None: the scene's first training sequence; else a
        library motion at the scene's frame rate)."""
        clip, seq = resolve_motion(motion, self.body, self.betas, self.run.scene)
        with torch.no_grad():
            posed = clip.pose(self.body, self.betas)
        spec = seq if seq is not None else (motion if motion is not None else clip.name)
        return BodySequence.from_vertices(seq or clip.name, clip.fps, posed.vertices, self.body.faces), spec

    def _load(self, name: str) -> tuple[BodySequence, Any]:
        """The loader thread's job: a scene sequence as :meth:`pose_for_run`; anything else from the
        motion library (spec None: the clip's own name)."""
        if name in self.scene_sequences():
            return self.pose_for_run(name)
        return BodySequence.load(self.body, self.betas, name), None

    @property
    def loading(self) -> str | None:
        """The motion being posed in the background, or None."""
        return self._loader.loading

    def request(self, name: str) -> None:
        """Pose ``name`` in the background (:meth:`poll` hands it over)."""
        self._loader.request(name)

    def poll(self) -> tuple[tuple[BodySequence, Any] | None, BaseException | None]:
        """((clip, spec), None) once the newest request is posed, (None, error) if it failed, else (None, None)."""
        return self._loader.poll()

    def close(self) -> None:
        self._loader.close()
