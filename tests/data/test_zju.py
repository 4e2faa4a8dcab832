"""ZJU-MoCap loader on a tiny fake capture (``support/zju_capture.py``, no real data): units, axes,
distortion, SMPL consistency with the cameras, and rejection of malformed folders."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from PIL import Image
from support.smpl_models import make_model, reference_smpl, rodrigues, write_npz
from support.zju_capture import FLIP, H, W, _params, write_capture

from garmentnerf.body.model import BodyModel
from garmentnerf.body.smpl import SMPL_PARENTS, load_smpl_asset, smpl_ground_offset
from garmentnerf.conventions import project_points
from garmentnerf.data.zju import CaptureError, CaptureScene, load_pickled_npy


@pytest.fixture(scope="module")
def smpl_body(tmp_path_factory):
    model = make_model(SMPL_PARENTS, seed=3)
    path = write_npz(tmp_path_factory.mktemp("smpl") / "SMPL_FAKE.npz", model)
    return model, BodyModel(load_smpl_asset(path), dtype=torch.float64), smpl_ground_offset(path)


def test_capture_loads(tmp_path):
    annots = write_capture(tmp_path / "cap")
    scene = CaptureScene.load(tmp_path / "cap", train_frames=2, camera_splits={"Camera_B2": "unseen_view"})
    assert scene.camera_names() == ["Camera_B1", "Camera_B2"]
    assert scene.camera_names("train") == ["Camera_B1"] and scene.camera_names("unseen_view") == ["Camera_B2"]
    assert scene.sequence_names() == ["train", "unseen_motion"]
    assert scene.num_frames("train") == 2 and scene.num_frames("unseen_motion") == 1
    assert scene.translation_unit == "mm"
    np.testing.assert_array_equal(scene.world_from_capture, np.eye(4))  # Z-up capture: kept as is
    cam = scene.camera("Camera_B2")
    assert (cam.width, cam.height) == (W, H) and cam.index == 1
    np.testing.assert_array_equal(cam.dist, np.asarray(annots["cams"]["D"][1]).reshape(-1))
    np.testing.assert_allclose(cam.camera.t, np.asarray(annots["cams"]["T"][1]).reshape(3) / 1000.0, atol=1e-12)
    assert scene.image_path("unseen_motion", "Camera_B1", 0) == tmp_path / "cap" / "Camera_B1" / "000002.png"
    assert scene.mask_path("train", "Camera_B1", 1) == tmp_path / "cap" / "mask_cihp" / "Camera_B1" / "000001.png"
    assert scene.mask_path("train", "Camera_B2", 1) == tmp_path / "cap" / "mask" / "Camera_B2" / "000001.png"
    img = scene.load_image("train", "Camera_B1", 1)
    raw = np.asarray(Image.open(scene.image_path("train", "Camera_B1", 1)), dtype=np.float32) / 255.0
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    np.testing.assert_array_equal(img, raw)  # no distortion: untouched
    for cam_name in ("Camera_B1", "Camera_B2"):
        mask = scene.load_mask("train", cam_name, 1, undistort=False)
        assert mask.dtype == bool and mask.sum() == 80 * 59
    p = scene.smpl_params("unseen_motion", 0)
    np.testing.assert_array_equal(p.poses, _params(2)["poses"].reshape(-1))
    assert p.shapes.shape == (10,) and p.Rh.shape == (3,)
    with pytest.raises(CaptureError, match="out of range"):
        scene.image_path("train", "Camera_B1", 2)
    with pytest.raises(CaptureError, match="no camera"):
        scene.camera("Camera_B9")


def test_mm_to_m_projection_matches_opencv(tmp_path):
    annots = write_capture(tmp_path / "mm")
    write_capture(tmp_path / "m", unit="m")
    rng = np.random.default_rng(1)
    X = rng.uniform(-0.5, 0.5, (40, 3)) + [0.0, 0.0, 1.0]  # ZJU world, metres
    scenes = [CaptureScene.load(tmp_path / "mm"), CaptureScene.load(tmp_path / "m"),
              CaptureScene.load(tmp_path / "mm", translation_unit="mm", align="none")]
    assert [s.translation_unit for s in scenes] == ["mm", "m", "mm"]
    for i in range(2):
        K = np.asarray(annots["cams"]["K"][i])
        R = np.asarray(annots["cams"]["R"][i])
        T_mm = np.asarray(annots["cams"]["T"][i]).reshape(3)
        expected, _ = cv2.projectPoints(X * 1000.0, cv2.Rodrigues(R)[0], T_mm, K, None)  # all in millimetres
        for scene in scenes:
            cam = scene.rig[i].camera
            uv, z = project_points(cam, torch.as_tensor(scene.capture_to_world(X)))
            np.testing.assert_allclose(uv.numpy(), expected.reshape(-1, 2), atol=1e-7)
            assert (z.numpy() > 1.0).all() and (z.numpy() < 5.0).all()  # metres, not millimetres
    # Forcing the wrong unit is visible: the camera would sit thousands of metres away.
    wrong = CaptureScene.load(tmp_path / "mm", translation_unit="m")
    assert np.linalg.norm(wrong.rig[0].camera.center) > 1000


def test_z_down_capture_is_aligned(tmp_path):
    write_capture(tmp_path / "up")
    write_capture(tmp_path / "down", zdown=True)
    up, down = CaptureScene.load(tmp_path / "up"), CaptureScene.load(tmp_path / "down")
    np.testing.assert_allclose(down.world_from_capture[:3, :3], FLIP)
    for a, b in zip(up.rig, down.rig):
        np.testing.assert_allclose(a.camera.R, b.camera.R, atol=1e-12)
        np.testing.assert_allclose(a.camera.t, b.camera.t, atol=1e-12)
        assert a.camera.center[2] > 0.5  # cameras above the floor in our Z-up world
    raw = CaptureScene.load(tmp_path / "down", align="none")
    assert raw.rig[0].camera.center[2] < -0.5


def test_undistortion_moves_points_to_the_pinhole_projection(tmp_path):
    annots = write_capture(tmp_path / "probe", frames=1)
    K, R = np.asarray(annots["cams"]["K"][1]), np.asarray(annots["cams"]["R"][1])
    T, D = np.asarray(annots["cams"]["T"][1]).reshape(3), np.asarray(annots["cams"]["D"][1])
    # The point seen at pinhole pixel (140, 105), near a corner where the distortion is large, 2.5 m away.
    x_cam = 2.5 * np.linalg.solve(K, [140.0, 105.0, 1.0])
    X = (R.T @ (x_cam - T / 1000.0)).reshape(1, 3)
    distorted = cv2.projectPoints(X * 1000, cv2.Rodrigues(R)[0], T, K, D)[0].reshape(2)
    write_capture(tmp_path / "cap", frames=1, blob_at=distorted)
    scene = CaptureScene.load(tmp_path / "cap")
    cam = scene.camera("Camera_B2")
    pinhole = project_points(cam.camera, torch.as_tensor(scene.capture_to_world(X)))[0].numpy().reshape(2)
    assert np.linalg.norm(pinhole - distorted) > 3.0  # the distortion matters here
    for undistort, target in ((False, distorted), (True, pinhole)):
        img = scene.load_image("train", "Camera_B2", 0, undistort=undistort).mean(axis=2)
        ys, xs = np.nonzero(img > 0.5)
        w = img[ys, xs]
        centroid = np.array([(xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()])
        assert np.linalg.norm(centroid - target) < 0.6, (undistort, centroid, target)
    mask = scene.load_mask("train", "Camera_B2", 0)
    assert mask.dtype == bool and 0 < mask.sum() < W * H


@pytest.mark.parametrize("zdown", [False, True], ids=["z_up", "z_down"])
def test_smpl_bodies_consistent_with_cameras(tmp_path, smpl_body, zdown):
    model, body, h = smpl_body
    annots = write_capture(tmp_path / "cap", zdown=zdown)
    scene = CaptureScene.load(tmp_path / "cap", train_frames=2)
    for seq, frame, f in (("train", 0, 0), ("train", 1, 1), ("unseen_motion", 0, 2)):
        p = load_pickled_npy(tmp_path / "cap" / "new_params" / f"{f}.npy")
        v_smpl = reference_smpl(model, p["shapes"].reshape(-1), p["poses"].reshape(24, 3), np.zeros(3))
        v_zju = v_smpl @ rodrigues(p["Rh"].reshape(3)).T + p["Th"].reshape(3)  # EasyMocap: R(Rh) v + Th
        ours = scene.smpl_vertices(seq, frame, body, h)
        np.testing.assert_allclose(ours, scene.capture_to_world(v_zju), atol=1e-6)  # float32 asset
        # The same vertices project identically through our camera and OpenCV with the raw calibration.
        for i in range(2):
            K, R = np.asarray(annots["cams"]["K"][i]), np.asarray(annots["cams"]["R"][i])
            T_mm = np.asarray(annots["cams"]["T"][i]).reshape(3)
            expected = cv2.projectPoints(v_zju * 1000, cv2.Rodrigues(R)[0], T_mm, K, None)[0].reshape(-1, 2)
            uv = project_points(scene.rig[i].camera, torch.as_tensor(ours))[0].numpy()
            np.testing.assert_allclose(uv, expected, atol=1e-5)
    motion, betas = scene.smpl_motion("train", body, h)
    assert motion.skeleton == "smpl" and motion.num_frames == 2 and motion.joint_names == body.joint_names
    posed = motion.pose(body, betas).vertices.numpy()
    np.testing.assert_allclose(posed[1], scene.smpl_vertices("train", 1, body, h), atol=1e-5)


def test_smpl_checks(tmp_path, smpl_body):
    model, body, h = smpl_body
    write_capture(tmp_path / "cap")
    scene = CaptureScene.load(tmp_path / "cap")
    bad = _params(0)
    bad["poses"] = bad["poses"][:, :71]
    np.save(tmp_path / "cap" / "new_params" / "0.npy", bad)
    with pytest.raises(CaptureError, match=r"0\.npy: 'poses' must be \(1, 3 J\)"):
        scene.smpl_params("train", 0)
    bad = _params(1)
    del bad["Th"]
    np.save(tmp_path / "cap" / "new_params" / "1.npy", bad)
    with pytest.raises(CaptureError, match=r"1\.npy: 'Th' is missing"):
        scene.smpl_params("train", 1)
    (tmp_path / "cap" / "new_params" / "2.npy").unlink()
    with pytest.raises(CaptureError, match="no SMPL parameters for capture frame 2"):
        scene.smpl_params("train", 2)
    small = _params(0)
    small["poses"] = small["poses"][:, :66]
    np.save(tmp_path / "cap" / "new_params" / "0.npy", small)
    with pytest.raises(CaptureError, match="poses has 22 joints, body 'smpl' has 24"):
        scene.smpl_motion("train", body, h, frames=[0])


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo pwned > /dev/null",))


def _annots_variant(tmp_path, change):
    annots = write_capture(tmp_path / "cap")
    change(annots)
    np.save(tmp_path / "cap" / "annots.npy", annots, allow_pickle=True)
    return tmp_path / "cap"


def _set(path, value):
    def change(annots):
        node = annots
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return change


BAD_ANNOTS = {
    "K 2x3": (_set(["cams", "K", 1], np.ones((2, 3))), "cams.K[1] must be 3x3, got shape (2, 3)"),
    "R not rotation": (_set(["cams", "R", 0], np.ones((3, 3))), "cams.R[0] is not a rotation matrix"),
    "T 4x1": (_set(["cams", "T", 0], np.ones((4, 1))), "cams.T[0] must be 3x1, got shape (4, 1)"),
    "D count": (_set(["cams", "D"], [np.zeros((5, 1))]), "cams.D has 1 entries, cams.K has 2"),
    "D shape": (_set(["cams", "D", 1], np.zeros((3, 1))), "cams.D[1] must be 5x1"),
    "no cams": (lambda a: a.pop("cams"), "'cams' is missing"),
    "no T": (lambda a: a["cams"].pop("T"), "cams.T is missing"),
    "ims count": (_set(["ims", 1, "ims"], ["Camera_B1/000001.png"]), "ims[1].ims lists 1 images for 2 cameras"),
    "missing image": (_set(["ims", 0, "ims", 1], "Camera_B2/nope.png"), "ims[0].ims[1] names a missing image"),
    "pickled code": (_set(["cams", "extra"], _Evil()), "refusing to unpickle"),
}


@pytest.mark.parametrize("case", list(BAD_ANNOTS), ids=list(BAD_ANNOTS))
def test_bad_annots_rejected(tmp_path, case):
    change, expected = BAD_ANNOTS[case]
    root = _annots_variant(tmp_path, change)
    with pytest.raises(CaptureError) as info:
        CaptureScene.load(root)
    msg = str(info.value)
    assert str(root / "annots.npy") in msg and expected in msg and "\n" not in msg, msg


def test_missing_folder_or_annots(tmp_path):
    with pytest.raises(CaptureError, match="no such capture folder"):
        CaptureScene.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match=r"annots\.npy: no such file \(not a ZJU-MoCap capture folder\)"):
        CaptureScene.load(tmp_path / "empty")
    (tmp_path / "empty" / "annots.npy").write_bytes(b"not numpy")
    with pytest.raises(CaptureError, match="not a readable .npy file"):
        CaptureScene.load(tmp_path / "empty")
    np.save(tmp_path / "empty" / "annots.npy", np.zeros(3))
    with pytest.raises(CaptureError, match="must hold a dict"):
        CaptureScene.load(tmp_path / "empty")
    write_capture(tmp_path / "cap")
    with pytest.raises(ValueError, match="camera_splits"):
        CaptureScene.load(tmp_path / "cap", camera_splits={"Camera_Z": "train"})
    with pytest.raises(ValueError, match="train_frames"):
        CaptureScene.load(tmp_path / "cap", train_frames=7)
