"""How much of a scene's garment is decided by the body's motion: matched-pose garment distances.

A model that sees the body's motion (the pose and a few frames of velocity) can at best predict the
*average* garment over the states that follow the same motion. This measures how far apart those
states are in a scene's training data: for every frame, the other frame whose body matches best
(in another sequence, or at least ``min_gap`` frames away in the same one), and the RMS distance
between the two garments. When bodies that match within a few millimetres wear garments several
centimetres apart, the garment's state is not a function of the model's inputs, and its outline
error has a floor no training removes.

Everything is compared in a body-aligned frame: each frame's body sample is rigidly aligned
(rotation and centroid, Kabsch) to the first frame's, and the same motion is applied to its
velocities and its garment, so a turn or a step sideways does not count as a different pose.

Descriptors (squared distances add up; velocities are per frame, scaled by ``velocity_weight``):

* ``pose``: the aligned body sample at frame t;
* ``pose+velocity``: plus ``x(t) - x(t-1)`` and ``x(t-1) - x(t-2)`` (the paper's k = 2 inputs);
* ``pose+velocity+history``: plus the displacements over frames t-6..t-2, t-12..t-6 and t-24..t-12.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from garmentnerf.data.scene import Scene, read_garment_arrays

__all__ = ["AmbiguityReport", "state_ambiguity", "kabsch_to"]

#: The frames of history the longest descriptor reads (t-24).
HISTORY_FRAMES = 24
DESCRIPTORS = ("pose", "pose+velocity", "pose+velocity+history")


@dataclass
class AmbiguityReport:
    """Matched-pose garment distances of one scene (metres; see the module docstring).

    Attributes:
        frames: frames compared (each sequence's frames from :data:`HISTORY_FRAMES` on).
        matched_garment_rms_m: descriptor -> median garment RMS distance to the best-matching frame.
        matched_descriptor_rms_m: descriptor -> median RMS distance per body point between the two
            frames' descriptors (for ``pose``, between the aligned bodies).
        close_pose_pairs: frames whose ``pose`` match is within ``close_m``.
        close_pose_garment_rms_m: median garment RMS distance over those frames (None: none).
        random_garment_rms_m: median garment RMS distance to a random other frame.
        close_m: the pose distance under which a match counts as close.
    """

    frames: int
    matched_garment_rms_m: dict
    matched_descriptor_rms_m: dict
    close_pose_pairs: int
    close_pose_garment_rms_m: float | None
    random_garment_rms_m: float
    close_m: float

    def to_json(self) -> dict:
        return dict(self.__dict__)


def kabsch_to(points: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (3, 3) and centroid c (3,) with ``(points - c) @ R.T`` best aligned (least
    squares, no reflection) to ``reference`` (already centred). points, reference: (N, 3)."""
    centroid = points.mean(axis=0)
    h = (points - centroid).T @ reference
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation, centroid


def _squared_distances(a: np.ndarray) -> np.ndarray:
    """(N, N) squared Euclidean distances between the rows of a (N, D)."""
    sq = np.einsum("nd,nd->n", a, a)
    return np.maximum(sq[:, None] + sq[None, :] - 2.0 * a @ a.T, 0.0)


def state_ambiguity(scene: Scene, body, sequences=None, *, min_gap: int = 15, body_points: int = 600,
                    garment_points: int = 800, velocity_weight: float = 10.0, close_m: float = 0.02,
                    seed: int = 0) -> AmbiguityReport:
    """Matched-pose garment distances over ``sequences`` (default: the scene's training ones).

    Args:
        scene: the scene.
        body: the :class:`~garmentnerf.body.model.BodyModel` the scene was made with (posed with
            the scene's shape).
        min_gap: frames of the same sequence closer than this never match each other.
        body_points, garment_points: vertices sampled (the same ones in every frame).
        velocity_weight: per-frame velocities count this many times their length.
        close_m: the RMS body distance under which a ``pose`` match counts as close.
        seed: the vertex sample's seed.
    """
    names = list(sequences) if sequences else scene.sequence_names("train")
    rng = np.random.default_rng(seed)
    betas = body.betas(scene.body.get("shape", "average"))
    body_sample = garment_sample = reference = None
    pose, velocity, history, garment, where = [], [], [], [], []
    for name in names:
        verts = scene.load_motion(name).pose(body, betas).vertices.detach().cpu().numpy()
        cloth = read_garment_arrays(scene.garment_path(name)).vertices
        if body_sample is None:
            body_sample = rng.choice(verts.shape[1], min(body_points, verts.shape[1]), replace=False)
            garment_sample = rng.choice(cloth.shape[1], min(garment_points, cloth.shape[1]), replace=False)
        b, g = verts[:, body_sample].astype(np.float64), cloth[:, garment_sample].astype(np.float64)
        for t in range(HISTORY_FRAMES, b.shape[0]):
            if reference is None:
                reference = b[t] - b[t].mean(axis=0)
            rot, centre = kabsch_to(b[t], reference)
            pose.append(((b[t] - centre) @ rot.T).ravel())
            velocity.append(np.concatenate([((b[t] - b[t - 1]) @ rot.T).ravel(),
                                            ((b[t - 1] - b[t - 2]) @ rot.T).ravel()]) * velocity_weight)
            history.append(np.concatenate([((b[t - a] - b[t - z]) @ rot.T).ravel()
                                           for a, z in ((2, 6), (6, 12), (12, 24))]))
            garment.append((g[t] - centre) @ rot.T)
            where.append((name, t))
    n = len(where)
    if n < 2:
        raise ValueError(f"{scene.scene_file}: fewer than 2 frames past the first {HISTORY_FRAMES} of "
                         f"{', '.join(names)}: nothing to compare")
    points = len(body_sample)
    d_pose = _squared_distances(np.stack(pose))
    d_velocity = _squared_distances(np.stack(velocity))
    d_history = _squared_distances(np.stack(history))
    garments = np.stack(garment)
    seq = np.array([s for s, _ in where])
    frame = np.array([t for _, t in where])
    excluded = (seq[:, None] == seq[None, :]) & (np.abs(frame[:, None] - frame[None, :]) < min_gap)

    def garment_rms(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return np.sqrt(((garments[i] - garments[j]) ** 2).sum(-1).mean(-1))

    valid = ~excluded.all(axis=1)  # frames with a partner at all
    if not valid.any():
        raise ValueError(f"{scene.scene_file}: no frame has a partner {min_gap} or more frames away")
    rows = np.arange(n)
    matched_garment, matched_descriptor, pose_match = {}, {}, None
    for label, distance in zip(DESCRIPTORS, (d_pose, d_pose + d_velocity, d_pose + d_velocity + d_history)):
        best = np.where(excluded, np.inf, distance).argmin(axis=1)
        matched_garment[label] = float(np.median(garment_rms(rows[valid], best[valid])))
        matched_descriptor[label] = float(np.median(np.sqrt(distance[rows[valid], best[valid]] / points)))
        if label == "pose":
            pose_match = (rows[valid], best[valid])
    i, j = pose_match
    close = np.sqrt(d_pose[i, j] / points) < close_m
    others = (rows + 1 + rng.integers(0, n - 1, n)) % n  # a random frame other than itself
    return AmbiguityReport(
        frames=n, matched_garment_rms_m=matched_garment, matched_descriptor_rms_m=matched_descriptor,
        close_pose_pairs=int(close.sum()),
        close_pose_garment_rms_m=float(np.median(garment_rms(i[close], j[close]))) if close.any() else None,
        random_garment_rms_m=float(np.median(garment_rms(rows, others))), close_m=close_m)
