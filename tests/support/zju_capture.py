"""A tiny fake ZJU-MoCap capture written to disk (no real data): 2 cameras, PNG images and masks,
SMPL parameters, in millimetres or metres and in a Z-up or Z-down world.

Shared by the ZJU-MoCap loader tests (``data/test_zju.py``) and the restricted-unpickler tests
(``test_safe_pickle.py``).
"""

from __future__ import annotations

import cv2
import numpy as np
from PIL import Image

from garmentnerf.conventions import look_at
from support.smpl_models import rodrigues

W, H = 160, 120
FLIP = np.diag([1.0, -1.0, -1.0])  # 180 degrees about X: a Z-down world
EYES = [([0.3, -3.0, 1.3], [0.0, 0.0, 1.0]), ([2.6, 1.2, 0.8], [0.1, 0.0, 0.9])]


def _rotvec(Rm):
    return cv2.Rodrigues(np.asarray(Rm, dtype=np.float64))[0].reshape(3)


def _params(seed: int):
    rng = np.random.default_rng(100 + seed)
    poses = rng.normal(0, 0.3, (1, 72))
    return {"poses": poses, "Rh": rng.normal(0, 0.8, (1, 3)), "Th": rng.normal(0, 0.3, (1, 3)) + [0, 0, 0.9],
            "shapes": np.random.default_rng(99).normal(0, 1.0, (1, 10))}  # constant over frames, as in ZJU


def write_capture(root, zdown: bool = False, unit: str = "mm", frames: int = 3, blob_at=None):
    """2 cameras (B1 undistorted, B2 with radial distortion), ``frames`` frames, PNG images and masks,
    SMPL params in new_params/. With ``zdown`` the same physical capture is expressed in a world
    whose Z points down (x_zd = FLIP x)."""
    root.mkdir(parents=True, exist_ok=True)
    Ks, Rs, Ts, Ds = [], [], [], []
    for i, (eye, target) in enumerate(EYES):
        R, t = look_at(eye, target)
        if zdown:
            R = R @ FLIP  # x_cam = R x + t = (R FLIP) x_zd + t
        Ks.append(np.array([[150.0, 0.0, 79.0], [0.0, 152.0, 61.0], [0.0, 0.0, 1.0]]))
        Rs.append(R)
        Ts.append(t.reshape(3, 1) * (1000.0 if unit == "mm" else 1.0))
        Ds.append(np.array([[0.0], [0.0], [0.0], [0.0], [0.0]]) if i == 0
                  else np.array([[-0.3], [0.05], [0.001], [-0.002], [0.0]]))
    ims = []
    rng = np.random.default_rng(0)
    for f in range(frames):
        paths = [f"Camera_B{i + 1}/{f:06d}.png" for i in range(2)]
        ims.append({"ims": paths, "kpts2d": None})
        for i, p in enumerate(paths):
            (root / p).parent.mkdir(parents=True, exist_ok=True)
            img = (rng.uniform(0, 60, (H, W, 3))).astype(np.uint8)
            if blob_at is not None and i == 1:
                u, v = blob_at
                img[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2] = 255
            Image.fromarray(img).save(root / p)
            mask_dir = "mask_cihp" if i == 0 else "mask"
            mask = np.zeros((H, W), np.uint8)
            mask[20:100, 50 + f:110] = 1 if i == 0 else 255
            (root / mask_dir / p).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(mask).save(root / mask_dir / p)
        params = _params(f)
        if zdown:
            params["Rh"] = _rotvec(FLIP @ rodrigues(params["Rh"].reshape(3))).reshape(1, 3)
            params["Th"] = (FLIP @ params["Th"].reshape(3)).reshape(1, 3)
        (root / "new_params").mkdir(exist_ok=True)
        np.save(root / "new_params" / f"{f}.npy", params)
    annots = {"cams": {"K": Ks, "R": Rs, "T": Ts, "D": Ds}, "ims": ims}
    np.save(root / "annots.npy", annots)
    return annots
