"""Small scenes written by the tests: a folded skirt mesh, and a scene folder (8 training cameras, 2 held
out and the 2 references at 48 x 48; a ``train`` and a 2-frame ``test_run`` sequence whose skirt sways
sideways instead of being simulated).

Shared by the ground-truth renderer tests (``data/test_render_gt.py``), the scene tests
(``data/test_scene.py``) and the ``garmentnerf data`` command tests (``data/test_data_cli.py``).
"""

from __future__ import annotations

import numpy as np
import torch

from garmentnerf.data.cameras import default_rig
from garmentnerf.data.scene import Scene
from garmentnerf.motion.motion import Motion


def make_skirt(waist_z: float = 1.0, hem_z: float = 0.5, r_top: float = 0.17, r_bottom: float = 0.36,
               n_around: int = 96, n_down: int = 24, folds: int = 9, amp: float = 0.025):
    """An open truncated cone with sinusoidal folds around the z axis; faces wound counter-clockwise
    seen from outside. Sized for the anny body (hips at about z = 1)."""
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    rings = []
    for i in range(n_down + 1):
        a = i / n_down
        z = waist_z + (hem_z - waist_z) * a
        r = r_top + (r_bottom - r_top) * a + amp * a * np.sin(folds * th)
        rings.append(np.stack([r * np.cos(th), r * np.sin(th), np.full_like(th, z)], 1))
    faces = []
    for i in range(n_down):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            faces += [[a, a + n_around, b], [b, a + n_around, b + n_around]]
    return np.concatenate(rings).astype(np.float32), np.array(faces, dtype=np.int64)


SIZE = 48
FPS = 30.0


def _motion(name: str, frames: int) -> Motion:
    rot = torch.zeros(frames, 1, 3)
    rot[:, 0, 2] = torch.linspace(0.0, 0.3, frames)  # the root turns a little
    return Motion(name, ["root"], rot, torch.zeros(frames, 3), FPS, "anny")


def _write_garment(path, frames: int, sway: float = 0.0) -> None:
    v, f = make_skirt(n_around=32, n_down=6)
    verts = np.stack([v + np.array([sway * t, 0.0, 0.0], dtype=np.float32) for t in range(frames)])
    np.savez(path, vertices=verts, faces=f)


def build_scene(root, train_frames: int = 3) -> Scene:
    cams = default_rig(count=8, held_out=2, width=SIZE, height_px=SIZE)
    scene = Scene.create(root, cams, fps=FPS, garment_kind="skirt", garment_color=(0.2, 0.4, 0.8))
    for name, split, n, desc in (("train", "train", train_frames, "walk,dance_a"),
                                 ("test_run", "unseen_motion", 2, "run")):
        scene.add_sequence(name, _motion(name, n), split, description=desc)
        _write_garment(scene.root / "sequences" / name / "garment.npz", n, sway=0.01)
    scene.simulation = {"train": {"max_penetration_m": 0.002, "seconds_per_frame": 2.1}}
    scene.palette_init = {"garment": [0.1, 0.2, 0.5], "body": [0.6, 0.5, 0.4]}
    scene.save()
    return scene
