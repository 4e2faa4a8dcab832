"""Fitting the rasterised body's appearance to a scene's training images.

The body layer (:mod:`garmentnerf.render.body_layer`) needs no network, so its appearance is
learned on its own, from the same images the NeRF is trained on: every training camera at every
``frame_stride``-th frame of the training sequences, at the scene's resolution. A pixel is a sample
when the ground truth labels it body, the rasterised body covers it too, and so do its 8
neighbours (the anti-aliased outline and the body/garment border are left out: their colour mixes
two surfaces). The loss is the squared error of ``clamp(p_body * a(uv, n))`` (the colour the
hybrid composition draws, :func:`~garmentnerf.model.palette.compose`) against the ground truth,
minimised with Adam over random batches of samples. The body's palette colour ``p_body`` is the
run's learned one and stays fixed, so recolouring the body tints the fitted texture.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from garmentnerf.body.surface import vertex_normals
from garmentnerf.data.scene_images import SceneImages
from garmentnerf.gl.camera_pass import CameraPass
from garmentnerf.model.body_appearance import BodyAppearance
from garmentnerf.render.body_layer import body_surface
from garmentnerf.folder_lock import lock_folder

#: Weight of the albedo prior ``mean((A(uv) - 1)^2)`` over a batch's samples: it settles the scale
#: that the texture and the shading could trade (their product is what is seen), so a texel no
#: training view saw (albedo 1) agrees with its neighbours, and keeps the texture from absorbing
#: what the shading model lacks (the view-dependent highlight) in texels seen from one side only.
ALBEDO_PRIOR = 0.01


@dataclass
class BodySamples:
    """Body pixels of the training images.

    Attributes:
        uv: (N, 2) atlas UV; normals: (N, 3) unit world normals; colors: (N, 3) ground truth in [0, 1].
        views: how many images they came from.
    """

    uv: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    views: int

    def __len__(self) -> int:
        return int(self.colors.shape[0])


def interior_body_pixels(labels: np.ndarray, raster_mask: np.ndarray, body_label: int = 1) -> np.ndarray:
    """(H, W) bool: pixels labelled ``body_label`` and covered by the raster, together with their
    8 neighbours (a 3 x 3 erosion of both masks)."""
    both = ((labels == body_label) & raster_mask).astype(np.uint8)
    return cv2.erode(both, np.ones((3, 3), np.uint8), borderValue=0).astype(bool)


def collect_body_samples(scene, body, cameras: list[str], gl_ctx, *, frame_stride: int = 5,
                         per_view: int = 20000, seed: int = 0, progress: bool = True) -> BodySamples:
    """Body samples (see the module docstring) from ``cameras`` at every ``frame_stride``-th frame
    of the scene's training sequences, at most ``per_view`` random ones per image; the body is
    posed with the scene's shape, as its images show it."""
    if frame_stride < 1:
        raise ValueError(f"frame_stride must be >= 1, got {frame_stride}")
    rng = np.random.default_rng(seed)
    images = SceneImages(scene, body_model=body)
    camera_pass = CameraPass(gl_ctx)
    jobs = [(seq, f) for seq in scene.sequence_names("train") for f in range(0, scene.num_frames(seq), frame_stride)]
    bar = tqdm(total=len(jobs) * len(cameras), desc="body samples", unit="view", file=sys.stderr,
               dynamic_ncols=True, disable=not progress)
    uvs, normals, colors = [], [], []
    views = 0
    try:
        betas = body.betas(scene.body.get("shape", "average"))
        posed_clips = {seq: scene.load_motion(seq).pose(body, betas) for seq in scene.sequence_names("train")}
        for seq, frame in jobs:
            with torch.no_grad():
                verts = posed_clips[seq].vertices[frame].detach().float()
                vnormals = vertex_normals(verts, body.faces)
            for name in cameras:
                cam = scene.camera(name).camera
                rgb, labels = images.image(seq, name, frame)
                px = body_surface(camera_pass, verts, body.faces, body.uv, body.uv_faces, cam, vnormals)
                keep = interior_body_pixels(np.asarray(labels), px.mask.numpy())
                # px.uv / px.normals follow px.mask's row-major order: pick the kept ones among them
                keep_in_mask = torch.from_numpy(keep[px.mask.numpy()])
                index = torch.nonzero(keep_in_mask).squeeze(1)
                if len(index) > per_view:
                    index = index[torch.from_numpy(rng.choice(len(index), per_view, replace=False))]
                flat = torch.nonzero(px.mask.reshape(-1)).squeeze(1)[index]
                uvs.append(px.uv[index])
                normals.append(px.normals[index])
                colors.append(torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).reshape(-1, 3)[flat])
                views += 1
                bar.update(1)
    finally:
        bar.close()
        camera_pass.release()
        images.close()
    if not colors or sum(len(c) for c in colors) == 0:
        raise ValueError(f"{scene.root}: no body pixel in the training images of cameras {', '.join(cameras)}")
    return BodySamples(torch.cat(uvs), torch.cat(normals), torch.cat(colors).clamp(0.0, 1.0), views)


def fit_body_appearance(samples: BodySamples, body_color: torch.Tensor, *, steps: int = 2000, batch: int = 65536,
                        lr: float = 0.02, albedo_prior: float = ALBEDO_PRIOR, appearance: BodyAppearance | None = None,
                        seed: int = 0,
                        should_cancel: Callable[[], bool] | None = None,
                        progress: bool = True) -> tuple[BodyAppearance, dict]:
    """Fit a :class:`BodyAppearance` to ``samples`` under the fixed palette colour ``body_color`` (3,).

    Returns:
        the appearance and a summary: ``psnr`` over every sample at the end, ``psnr_start`` (the
        untextured, unshaded palette colour), ``samples``, ``views``, ``steps``, ``seconds``.
    Raises:
        KeyboardInterrupt when ``should_cancel()`` turns True (nothing is returned).
    """
    t0 = time.perf_counter()
    model = appearance if appearance is not None else BodyAppearance()
    tint = torch.as_tensor(body_color, dtype=torch.float32).view(1, 3)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, steps), eta_min=lr * 0.05)

    def psnr_all() -> float:
        with torch.no_grad():
            err = 0.0
            for i in range(0, len(samples), 262144):
                sl = slice(i, i + 262144)
                pred = (tint * model(samples.uv[sl], samples.normals[sl])).clamp(0.0, 1.0)
                err += float(((pred - samples.colors[sl]) ** 2).sum())
            mse = err / (3 * len(samples))
        return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))

    start = psnr_all()
    with tqdm(total=steps, desc="fit body appearance", unit="step", file=sys.stderr, dynamic_ncols=True,
              disable=not progress) as bar:
        for _ in range(steps):
            if should_cancel is not None and should_cancel():
                raise KeyboardInterrupt
            idx = torch.randint(0, len(samples), (min(batch, len(samples)),), generator=gen)
            albedo = model.albedo_at(samples.uv[idx])
            pred = tint * albedo * model.irradiance(samples.normals[idx])
            loss = ((pred.clamp(0.0, 1.0) - samples.colors[idx]) ** 2).mean()
            if albedo_prior > 0:
                loss = loss + albedo_prior * ((albedo - 1.0) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            bar.update(1)
    model.eval()
    summary = {"psnr": psnr_all(), "psnr_start": start, "samples": len(samples), "views": samples.views,
               "steps": int(steps), "seconds": time.perf_counter() - t0}
    return model, summary


def fit_run_appearance(run_dir, out, *, scene=None, frame_stride: int = 5, steps: int = 3000,
                       albedo_prior: float | None = None, progress: bool = True) -> dict:
    """Fit the body appearance of the run in ``run_dir`` (what ``garmentnerf body fit-appearance``
    does): samples from its training cameras at every ``frame_stride``-th frame of its scene's (or
    ``scene``'s) training sequences, fitted for ``steps`` steps under the run's learned body colour
    (``albedo_prior`` None: :data:`ALBEDO_PRIOR`), and written atomically to ``out``. When ``out`` is in
    the run folder, the folder's writer lock (:func:`~garmentnerf.folder_lock.lock_folder`) is held throughout.

    Returns:
        the fit's summary (:func:`fit_body_appearance`).
    Raises:
        ValueError: the run's scene is missing (pass ``scene``), or an impossible setting.
    """
    if frame_stride < 1:
        raise ValueError(f"--frame-stride must be at least 1, got {frame_stride}")
    if steps < 1:
        raise ValueError(f"--steps must be at least 1, got {steps}")
    if albedo_prior is not None and not (math.isfinite(albedo_prior) and albedo_prior >= 0):
        raise ValueError(f"--albedo-prior must be a number >= 0, got {albedo_prior}")
    with contextlib.ExitStack() as stack:
        if Path(out).resolve().parent == Path(run_dir).resolve():
            stack.enter_context(lock_folder(run_dir, "garmentnerf body fit-appearance"))
        return _fit_run_appearance(run_dir, out, scene, frame_stride, steps, albedo_prior, progress)


def _fit_run_appearance(run_dir, out, scene, frame_stride: int, steps: int, albedo_prior: float | None,
                        progress: bool) -> dict:
    # lazy: the evaluation and GL stacks are only needed here
    from garmentnerf.gl.context import create_context
    from garmentnerf.model.body_appearance import save_body_appearance
    from garmentnerf.runs import load_run, run_train_cameras

    run = load_run(run_dir, scene=scene)
    if run.scene is None:
        raise ValueError(f"{run_dir}: the run's scene ({run.info.get('scene') or 'not recorded'}) is missing; "
                         f"pass --scene DIR")
    ctx = create_context(headless=True)
    try:
        samples = collect_body_samples(run.scene, run.model.body, run_train_cameras(run, run.scene), ctx,
                                       frame_stride=frame_stride, progress=progress)
    finally:
        ctx.release()
    prior = {} if albedo_prior is None else {"albedo_prior": albedo_prior}
    appearance, summary = fit_body_appearance(samples, run.palette()[-1], steps=steps, progress=progress, **prior)
    save_body_appearance(out, appearance)
    return summary


__all__ = ["BodySamples", "collect_body_samples", "fit_body_appearance", "fit_run_appearance", "interior_body_pixels"]
