"""Small synthetic scenes for tests and quick checks, made in seconds without a cloth simulation.

:func:`make_rigged_scene` writes an ordinary scene folder (``scene.json``, ``motion.npz``,
``garment.npz`` through :class:`~garmentnerf.data.scene.Scene` and
:func:`~garmentnerf.data.garment_sequence.save_sequence`), but its garment is **not simulated**:
every garment vertex is skinned rigidly to the body -- it takes the skinning weights of its
nearest rest-body vertex and is posed with the body's linear blend skinning (without the body's
pose correctives). The garment therefore moves like a second skin: no swing, no folds, no
collisions resolved (its ``penetration_max_m`` array is zeros because nothing measured it, not
because it was checked). Use real scenes (``garmentnerf data make``) for anything the paper's
dynamics matter to.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from garmentnerf.body.model import BodyModel
from garmentnerf.body.skinning import apply_transforms, blend_transforms
from garmentnerf.data.cameras import default_rig
from garmentnerf.data.garment_sequence import save_sequence
from garmentnerf.data.garments import make_garment
from garmentnerf.data.render_gt import GroundTruthRenderer
from garmentnerf.data.scene import Scene
from garmentnerf.data.scene_images import SceneImages, palette_from_images
from garmentnerf.motion.library import load_motion

__all__ = ["make_rigged_scene", "rigged_garment_vertices"]


def rigged_garment_vertices(body, betas: torch.Tensor, garment_rest: np.ndarray, posed) -> np.ndarray:
    """(T, Vg, 3) garment vertices posed by nearest-rest-vertex rigid skinning.

    Args:
        body: the :class:`~garmentnerf.body.model.BodyModel`.
        betas: (S,) shape the garment was built around (and the motion posed with).
        garment_rest: (Vg, 3) garment rest positions around ``body.rest(betas)``.
        posed: the :class:`~garmentnerf.body.model.PosedBody` of the motion (same betas).
    """
    rest_v, _ = body.rest(betas)
    tree = cKDTree(rest_v.detach().cpu().numpy().astype(np.float64))
    _, nearest = tree.query(np.asarray(garment_rest, dtype=np.float64))
    weights = body.weights[torch.as_tensor(nearest, dtype=torch.long, device=body.weights.device)]
    per_vertex = blend_transforms(weights, posed.joint_transforms.to(weights.dtype))
    pts = torch.as_tensor(np.asarray(garment_rest), dtype=weights.dtype, device=weights.device)
    verts = apply_transforms(per_vertex, pts) + posed.translation[:, None, :].to(weights.dtype)
    return verts.detach().cpu().numpy().astype(np.float32)


def _add_rigged_sequence(scene: Scene, name: str, split: str, motion, body, betas, garment) -> None:
    scene.add_sequence(name, motion, split=split, description=motion.name, simulated=False)
    posed = motion.pose(body, betas)
    verts = rigged_garment_vertices(body, betas, garment.vertices, posed)
    save_sequence(scene.garment_path(name), verts, garment.faces, color=garment.color, kind=garment.kind,
                  penetration_max_m=np.zeros(verts.shape[0], dtype=np.float32), fps=motion.fps,
                  settings={"simulated": False, "method": "rigid skinning (nearest rest-body vertex weights)"},
                  name=garment.name, motion=motion.name, betas=garment.betas, uv=garment.uv, layer=garment.layer)


def make_rigged_scene(root, *, garment: str = "skirt", motion: str = "walk", frames: int = 4, views: int = 4,
                      size: int = 64, held_out_views: int = 1, test_motion: str | None = None, test_frames: int = 0,
                      gl_context=None, palette: str = "images") -> Scene:
    """A small scene whose garment is rigidly skinned to the body (unsimulated; see the module doc).

    Args:
        root: the scene folder to write (made if needed; an existing ``scene.json`` is replaced).
        garment: garment kind (``skirt``, ``tshirt``, ``dress``).
        motion: motion name (``garmentnerf motion list``); its first ``frames`` frames are used.
        frames: training frames (sequence ``train``).
        views: training cameras on the circle (split ``train``).
        size: image side of every camera (square).
        held_out_views: cameras between the training ones (split ``unseen_view``).
        test_motion, test_frames: an optional second sequence ``test`` (split ``unseen_motion``).
        gl_context: moderngl context for ``palette="images"`` (None: a headless one is made).
        palette: ``"images"``: ``palette_init`` = mean garment/body colors of the training
            views of frame 0 (renders, and caches, those ground-truth images: needs OpenGL);
            ``"colors"``: the garment and skin base colors (no rendering); ``"none"``: null.
    Returns:
        the saved :class:`Scene`.
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    if palette not in ("images", "colors", "none"):
        raise ValueError(f"palette must be 'images', 'colors' or 'none', got {palette!r}")
    root = Path(root)
    body = BodyModel.default()
    betas = body.betas("average")
    dress = make_garment(garment, body, betas)
    clip = load_motion(motion, body, betas)
    if clip.num_frames < frames:
        raise ValueError(f"motion '{motion}' has {clip.num_frames} frames, {frames} asked")
    clip = clip.slice(0, frames)
    cams = default_rig(count=views, held_out=held_out_views, width=size, height_px=size)
    scene = Scene.create(root, cams, clip.fps, dress.kind, [float(c) for c in dress.color], body_shape="average")
    scene.extra["synthetic"] = {"garment": "rigidly skinned to the body (not simulated)", "motion": motion}
    _add_rigged_sequence(scene, "train", "train", clip, body, betas, dress)
    if test_motion is not None and test_frames > 0:
        test = load_motion(test_motion, body, betas, fps=clip.fps)
        if test.num_frames < test_frames:
            raise ValueError(f"motion '{test_motion}' has {test.num_frames} frames, {test_frames} asked")
        _add_rigged_sequence(scene, "test", "unseen_motion", test.slice(0, test_frames), body, betas, dress)
    if palette == "colors":
        scene.palette_init = {"garment": [float(c) for c in dress.color], "body": list(scene.body_color)}
    scene.save()
    if palette == "images":
        renderer = None
        if gl_context is not None:
            renderer = GroundTruthRenderer(gl_context)
        images = SceneImages(scene, renderer=renderer, body_model=body)
        try:
            pal = palette_from_images(images.image("train", cam, 0) for cam in scene.camera_names("train"))
        finally:
            images.close()
            if renderer is not None:
                renderer.release()
        if pal["garment"] is None or pal["body"] is None:
            raise ValueError(f"{scene.scene_file}: the training views of frame 0 show no "
                             f"{'garment' if pal['garment'] is None else 'body'} pixel; palette_init not set")
        scene.palette_init = pal
        scene.save()
    return Scene.load(root)
