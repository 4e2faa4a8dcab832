"""SMPL model files (.pkl with fake chumpy objects, .npz) against an independent SMPL reference.

No SMPL data is committed: every test builds a random SMPL-structured model in tmp_path (the builders
and the reference are in ``support/smpl_models.py``).
"""

from __future__ import annotations

import pickle
import sys

import numpy as np
import pytest
import torch
from support.smpl_models import (
    ROOT_SENTINEL,
    make_model,
    reference_smpl,
    rodrigues,
    smplh_parents,
    write_chumpy_pkl,
    write_npz,
)

from garmentnerf.body.asset import BodyAssetError
from garmentnerf.body.model import BodyModel
from garmentnerf.body.smpl import (
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    SMPL_TO_WORLD,
    load_smpl_asset,
    smpl_ground_offset,
    smpl_points_to_world,
    smpl_rotmats_to_world,
    smpl_rotvecs_to_world,
    smpl_translation_to_world,
)

C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def smpl_to_ours(points: np.ndarray, model: dict) -> np.ndarray:
    return points @ C.T + np.array([0.0, 0.0, -model["v_template"][:, 1].min()])


# ---- fixtures -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def smpl_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("smpl")
    model = make_model(SMPL_PARENTS)
    return model, write_chumpy_pkl(tmp / "SMPL_FAKE.pkl", model), write_npz(tmp / "SMPL_FAKE.npz", model)


# ---- tests ----------------------------------------------------------------------------------------
def test_pkl_and_npz_give_identical_assets(smpl_files, tmp_path):
    model, pkl, npz = smpl_files
    assert "chumpy" not in sys.modules
    a, b = load_smpl_asset(pkl), load_smpl_asset(npz)
    c = load_smpl_asset(write_npz(tmp_path / "sparse.npz", model, sparse_regressor=True))
    d = load_smpl_asset(write_chumpy_pkl(tmp_path / "protocol0.pkl", model, protocol=0))  # copy_reg path
    for other in (b, c, d):
        for field in ("template_vertices", "shape_dirs", "template_joints", "joint_shape_dirs", "faces", "uv",
                      "uv_faces", "skin_indices", "skin_weights", "parents", "pose_dirs"):
            np.testing.assert_array_equal(getattr(a, field), getattr(other, field), err_msg=field)
        assert (a.name, a.joint_names, a.license) == (other.name, other.joint_names, other.license)
    assert a.name == "smpl" and a.joint_names == SMPL_JOINT_NAMES
    assert a.parents.tolist() == SMPL_PARENTS
    assert "Max Planck" in a.license
    assert list(a.named_shapes) == ["average"] and not a.named_shapes["average"].any()
    assert a.uv.shape == (0, 2) and a.uv_faces.shape == (0, 3) and not BodyModel(a).has_uv


@pytest.mark.parametrize("parents", [SMPL_PARENTS, smplh_parents()], ids=["smpl24", "smplh52"])
def test_posing_matches_reference_smpl(parents, tmp_path):
    model = make_model(parents, seed=len(parents))
    asset = load_smpl_asset(write_npz(tmp_path / "model.npz", model))
    J = len(parents)
    assert asset.name == ("smpl" if J == 24 else "smplh")
    if J == 52:
        assert asset.joint_names[22] == "left_index1" and asset.joint_names[-1] == "right_thumb3"
    rng = np.random.default_rng(7)
    T = 4
    poses = rng.normal(0, 0.5, (T, J, 3))
    trans = rng.normal(0, 0.3, (T, 3))
    betas = rng.normal(0, 1.5, model["shapedirs"].shape[2])
    smpl_R = np.stack([[rodrigues(p) for p in pose] for pose in poses])
    ours_R = np.einsum("ab,tjbc,dc->tjad", C, smpl_R, C)  # C R C^T
    np.testing.assert_allclose(smpl_rotmats_to_world(smpl_R), ours_R, atol=1e-12)
    expected = np.stack([smpl_to_ours(reference_smpl(model, betas, poses[t], trans[t]), model) for t in range(T)])
    for dtype, tol in ((torch.float64, 1e-6), (torch.float32, 1e-5)):
        body = BodyModel(asset, dtype=dtype)
        posed = body.pose(torch.as_tensor(ours_R), torch.as_tensor(trans @ C.T), body.betas(betas))
        err = np.abs(posed.vertices.double().numpy() - expected).max()
        assert err < tol, (dtype, err)
    # Rotation vectors convert as C r.
    body = BodyModel(asset, dtype=torch.float64)
    via_rotvec = body.pose(torch.as_tensor(smpl_rotvecs_to_world(poses)),
                           torch.as_tensor(smpl_translation_to_world(trans)), body.betas(betas))
    assert np.abs(via_rotvec.vertices.numpy() - expected).max() < 1e-6


def test_posedirs_matter(smpl_files):
    """Guard against a vacuous comparison: without the correctives the reference differs."""
    model, _, npz = smpl_files
    asset = load_smpl_asset(npz)
    rng = np.random.default_rng(3)
    pose = rng.normal(0, 0.5, (24, 3))
    R = np.stack([C @ rodrigues(p) @ C.T for p in pose])[None]
    body = BodyModel(asset, dtype=torch.float64)
    with_dirs = body.pose(torch.as_tensor(R)).vertices[0].numpy()
    body.pose_dirs = None
    without = body.pose(torch.as_tensor(R)).vertices[0].numpy()
    assert np.abs(with_dirs - without).max() > 1e-3
    expected = smpl_to_ours(reference_smpl(model, np.zeros(10), pose, np.zeros(3)), model)
    assert np.abs(with_dirs - expected).max() < 1e-6


def test_rest_pose_reproduces_converted_template(smpl_files):
    model, pkl, _ = smpl_files
    asset = load_smpl_asset(pkl)
    h = -model["v_template"][:, 1].min()
    assert smpl_ground_offset(pkl) == pytest.approx(h)
    converted = model["v_template"] @ C.T + [0.0, 0.0, h]
    np.testing.assert_allclose(asset.template_vertices, converted, atol=1e-6)
    np.testing.assert_allclose(asset.template_joints, smpl_to_ours(model["J_regressor"] @ model["v_template"], model),
                               atol=1e-6)
    np.testing.assert_allclose(smpl_points_to_world(model["v_template"], h), converted, atol=1e-12)
    assert asset.template_vertices[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    body = BodyModel(asset, dtype=torch.float64)
    posed = body.pose(body.zero_pose(2), betas=body.betas("average"))
    np.testing.assert_allclose(posed.vertices.numpy(), np.broadcast_to(converted, (2,) + converted.shape), atol=1e-6)
    assert np.array_equal(SMPL_TO_WORLD, C) and np.linalg.det(C) == pytest.approx(1.0)


def test_skin_weights_are_lossless(tmp_path):
    model = make_model(SMPL_PARENTS, max_influences=24, seed=5)
    asset = load_smpl_asset(write_npz(tmp_path / "dense.npz", model))
    assert asset.skin_indices.shape[1] == np.count_nonzero(model["weights"], axis=1).max()
    dense = np.zeros_like(model["weights"])
    np.put_along_axis(dense, asset.skin_indices, asset.skin_weights, axis=1)
    np.testing.assert_allclose(dense, model["weights"], atol=1e-7)


def test_from_file_dispatches_both_formats(smpl_files):
    _, pkl, npz = smpl_files
    for path in (pkl, npz):
        body = BodyModel.from_file(path, dtype=torch.float64)
        assert body.name == "smpl" and body.num_joints == 24 and body.asset.pose_dirs is not None


def _break(model: dict, **changes) -> dict:
    broken = dict(model)
    for key, value in changes.items():
        if value is None:
            del broken[key]
        else:
            broken[key] = value
    return broken


@pytest.mark.parametrize("key, change", [
    ("v_template", None),
    ("kintree_table", None),
    ("v_template", lambda m: m["v_template"][:, :2]),
    ("shapedirs", lambda m: np.where(np.arange(m["shapedirs"].size).reshape(m["shapedirs"].shape) == 17, np.nan,
                                     m["shapedirs"])),
    ("posedirs", lambda m: m["posedirs"][:, :, :-9]),
    ("J_regressor", lambda m: m["J_regressor"][:, :-1]),
    ("weights", lambda m: m["weights"] * 1.1),
    ("f", lambda m: np.where(m["f"] == m["f"].max(), 10_000, m["f"])),
    ("kintree_table", lambda m: np.vstack([np.full(24, ROOT_SENTINEL), np.arange(24)])),
])
def test_bad_files_raise_naming_file_and_field(smpl_files, tmp_path, key, change):
    model = smpl_files[0]
    broken = _break(model, **{key: None if change is None else change(model)})
    path = write_npz(tmp_path / "broken_model.npz", broken)
    with pytest.raises(BodyAssetError, match=rf"broken_model\.npz.*'{key}'"):
        load_smpl_asset(path)
    pkl = write_chumpy_pkl(tmp_path / "broken_model.pkl", broken)
    with pytest.raises(BodyAssetError, match=rf"broken_model\.pkl.*'{key}'"):
        load_smpl_asset(pkl)


def test_unreadable_or_missing_files(tmp_path):
    garbage = tmp_path / "garbage.pkl"
    garbage.write_bytes(b"\x80\x02not really a pickle")
    with pytest.raises(BodyAssetError, match="garbage.pkl.*not a readable SMPL pickle"):
        load_smpl_asset(garbage)
    not_a_dict = tmp_path / "list.pkl"
    not_a_dict.write_bytes(pickle.dumps([1, 2, 3], protocol=2))
    with pytest.raises(BodyAssetError, match="list.pkl"):
        load_smpl_asset(not_a_dict)
    with pytest.raises(BodyAssetError, match="nowhere.npz.*not found"):
        load_smpl_asset(tmp_path / "nowhere.npz")
    bad_zip = tmp_path / "bad.npz"
    bad_zip.write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(BodyAssetError, match="bad.npz"):
        load_smpl_asset(bad_zip)


def test_pickle_runs_no_foreign_code(smpl_files, tmp_path, capsys):
    """A global outside the allow-list is never called: the file is refused, naming it."""
    model = smpl_files[0]

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    data = dict(model, f=Evil())
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps(data, protocol=2))
    with pytest.raises(BodyAssetError, match=r"evil.pkl: refusing to unpickle 'builtins.print'"):
        load_smpl_asset(path)
    assert "pwned" not in capsys.readouterr().out


def _write_uv_obj(path, faces: np.ndarray, V: int, seed: int = 0, shuffle: bool = False) -> np.ndarray:
    """An OBJ whose corners get their own vt (seams!); returns the expected per-model-face corner uv."""
    rng = np.random.default_rng(seed)
    F = len(faces)
    vt = rng.uniform(0, 1, (3 * F, 2))
    corner_vt = np.arange(3 * F).reshape(F, 3)
    expected = vt[corner_vt]  # (F, 3, 2): uv of each model-face corner
    order = rng.permutation(F) if shuffle else np.arange(F)
    lines = ["# uv test", *(f"v 0 0 {i}" for i in range(V)), *(f"vt {u:.9f} {v:.9f}" for u, v in vt)]
    for i in order:
        roll = int(rng.integers(3)) if shuffle else 0
        corners = [(int(faces[i, (c + roll) % 3]) + 1, int(corner_vt[i, (c + roll) % 3]) + 1) for c in range(3)]
        lines.append("f " + " ".join(f"{a}/{b}/1" for a, b in corners))
    path.write_text("\n".join(lines) + "\n")
    return expected


@pytest.mark.parametrize("shuffle", [False, True])
def test_uv_obj_is_read_and_attached(smpl_files, tmp_path, shuffle):
    model, pkl, _ = smpl_files
    faces = model["f"].astype(np.int64)
    obj = tmp_path / "smpl_uv.obj"
    expected = _write_uv_obj(obj, faces, len(model["v_template"]), shuffle=shuffle)
    asset = load_smpl_asset(pkl, uv_obj=obj)
    assert BodyModel(asset).has_uv
    assert asset.uv_faces.shape == asset.faces.shape
    np.testing.assert_allclose(asset.uv[asset.uv_faces], expected, atol=1e-6)


def test_uv_obj_mismatch_raises(smpl_files, tmp_path):
    model, _, npz = smpl_files
    faces = model["f"].astype(np.int64)
    short = tmp_path / "short.obj"
    _write_uv_obj(short, faces[:-1], len(model["v_template"]))
    with pytest.raises(BodyAssetError, match="short.obj.*faces"):
        load_smpl_asset(npz, uv_obj=short)
    other = tmp_path / "other.obj"
    _write_uv_obj(other, faces[:, ::-1].copy(), len(model["v_template"]))  # flipped winding: not the same faces
    with pytest.raises(BodyAssetError, match="other.obj.*'f'"):
        load_smpl_asset(npz, uv_obj=other)
    with pytest.raises(BodyAssetError, match="missing.obj.*not found"):
        load_smpl_asset(npz, uv_obj=tmp_path / "missing.obj")


def test_num_betas_truncates(smpl_files):
    _, _, npz = smpl_files
    asset = load_smpl_asset(npz, num_betas=4)
    full = load_smpl_asset(npz)
    assert asset.num_shape_coeffs == 4
    np.testing.assert_array_equal(asset.shape_dirs, full.shape_dirs[:4])
    with pytest.raises(BodyAssetError, match="num_betas"):
        load_smpl_asset(npz, num_betas=11)
