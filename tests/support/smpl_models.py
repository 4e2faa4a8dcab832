"""Random SMPL-structured models written as the distributed files are (.pkl with fake chumpy objects,
.npz), and an independent SMPL forward pass in SMPL's own frame to check the loaders against.

Shared by the SMPL loader tests (``body/test_smpl.py``), the ZJU-MoCap tests (``data/test_zju.py``,
through :mod:`support.zju_capture`) and the restricted-unpickler tests (``test_safe_pickle.py``).
"""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import scipy.sparse as sp

from garmentnerf.body.smpl import SMPL_PARENTS

ROOT_SENTINEL = 4294967295  # what the distributed SMPL files store as the root's parent


# ---- a random SMPL-structured model ---------------------------------------------------------------
def smplh_parents() -> list[int]:
    parents = SMPL_PARENTS[:22]
    for wrist in (20, 21):
        for _finger in range(5):
            parents += [wrist, len(parents), len(parents) + 1]
    return parents


def make_model(parents: list[int], V: int = 150, F: int = 260, S: int = 10, max_influences: int = 4,
               seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    J = len(parents)
    # A body-ish cloud in SMPL's frame: Y up, feet around y = -1.15, facing +Z.
    v = np.column_stack([rng.uniform(-0.4, 0.4, V), rng.uniform(-1.15, 0.55, V), rng.uniform(-0.15, 0.15, V)])
    J_reg = np.zeros((J, V))
    for j in range(J):
        idx = rng.choice(V, 6, replace=False)
        w = rng.uniform(0.1, 1.0, 6)
        J_reg[j, idx] = w / w.sum()
    weights = np.zeros((V, J))
    for i in range(V):
        k = rng.integers(1, max_influences + 1)
        idx = rng.choice(J, k, replace=False)
        w = rng.uniform(0.05, 1.0, k)
        weights[i, idx] = w / w.sum()
    faces = np.array([rng.choice(V, 3, replace=False) for _ in range(F)], dtype=np.uint32)
    kintree = np.array([[ROOT_SENTINEL] + parents[1:], list(range(J))], dtype=np.int64)
    return dict(
        v_template=v, shapedirs=rng.normal(0, 0.02, (V, 3, S)), posedirs=rng.normal(0, 0.01, (V, 3, 9 * (J - 1))),
        J_regressor=J_reg, weights=weights, kintree_table=kintree, f=faces,
        bs_style="lbs", bs_type="lrotmin",
    )


def write_npz(path, model: dict, sparse_regressor: bool = False):
    arrays = dict(model)
    if sparse_regressor:
        arrays["J_regressor"] = sp.csc_matrix(model["J_regressor"])  # stored as a pickled object array
    np.savez(path, **arrays)
    return path


def write_chumpy_pkl(path, model: dict, protocol: int = 2):
    """A pickle shaped like the distributed SMPL files: chumpy.ch.Ch arrays, a scipy sparse
    J_regressor under its old module path, protocol 2; chumpy itself is only faked while pickling."""
    class Ch:
        def __init__(self, x):
            self.x = np.asarray(x, dtype=np.float64)

        def __getstate__(self):  # what chumpy's Ch pickles: its __dict__ with the value under 'x'
            return {"x": self.x, "_dirty_vars": set(), "_itr": None, "_make_dense": False, "_make_sparse": False}

    Ch.__module__, Ch.__qualname__, Ch.__name__ = "chumpy.ch", "Ch", "Ch"
    chumpy, chumpy_ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    chumpy_ch.Ch = Ch
    chumpy.ch = chumpy_ch
    data = dict(model)
    for key in ("v_template", "shapedirs", "weights"):
        if key in model:
            data[key] = Ch(model[key])
    if "J_regressor" in model:
        data["J_regressor"] = sp.csc_matrix(model["J_regressor"])
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = chumpy, chumpy_ch
    try:
        blob = pickle.dumps(data, protocol=protocol)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    assert b"chumpy.ch\nCh" in blob
    # Python 2 era scipy pickled sparse matrices as scipy.sparse.csc.csc_matrix.
    if "J_regressor" in model:
        assert b"scipy.sparse._csc\ncsc_matrix" in blob
        blob = blob.replace(b"scipy.sparse._csc\n", b"scipy.sparse.csc\n")
    path.write_bytes(blob)
    return path


# ---- an independent SMPL in SMPL's own frame (numpy, per-joint loops) ------------------------------
def rodrigues(r: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(r)
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def reference_smpl(model: dict, betas: np.ndarray, pose: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """SMPL's forward pass (Loper et al. 2015) in SMPL's frame: shape, joints, pose blend shapes, LBS."""
    kt = model["kintree_table"]
    J = kt.shape[1]
    col = {int(kt[1, i]): i for i in range(J)}
    parent = {i: col[int(kt[0, i])] for i in range(1, J)}
    v_shaped = model["v_template"] + model["shapedirs"] @ betas
    joints = model["J_regressor"] @ v_shaped
    R = [rodrigues(pose[j]) for j in range(J)]
    feature = np.concatenate([(R[j] - np.eye(3)).ravel() for j in range(1, J)])
    v_posed = v_shaped + model["posedirs"] @ feature

    def rt(Rm, t):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = Rm, t
        return M

    G = [rt(R[0], joints[0])]
    for i in range(1, J):
        G.append(G[parent[i]] @ rt(R[i], joints[i] - joints[parent[i]]))
    out = np.zeros_like(v_posed)
    for i in range(J):
        A = G[i].copy()
        A[:3, 3] -= G[i][:3, :3] @ joints[i]
        out += model["weights"][:, i:i + 1] * (v_posed @ A[:3, :3].T + A[:3, 3])
    return out + trans


