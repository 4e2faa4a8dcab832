"""SMPL bodies from a user's own model file (SMPL cannot be shipped or downloaded).

:func:`load_smpl_asset` reads an SMPL model file exactly as its authors distribute it -- the
Python 2 ``.pkl`` with chumpy arrays and a scipy sparse ``J_regressor``, or an ``.npz`` with the
same keys -- and converts it into a :class:`~garmentnerf.body.asset.BodyAsset` in the project's
world (Z up, character faces -Y, feet on z = 0). chumpy is *not* needed: the package's restricted
unpickler (:mod:`garmentnerf.safe_pickle`) maps chumpy objects to a stub that keeps their value
(chumpy pickles it under the state key ``'x'``), rebuilds scipy sparse matrices from their pickled
fields, calls nothing but a short allow-list of numpy/builtin reconstructors and refuses a file
naming any other global. SMPL-H (52 joints) and SMPL-X (55 joints)
files with the same keys load too; joints always come from ``kintree_table``.

Frame conversion
    SMPL's model frame is Y up with the character facing +Z. A point maps to our world by

        p_ours = C p_smpl + (0, 0, h),   C = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]   (y -> z, z -> -y)

    where ``h = -min_y(v_template)`` (:func:`smpl_ground_offset`) puts the template's feet on
    z = 0. ``C`` is a proper rotation (det +1), so face winding is kept. Template vertices, shape
    directions and joints are rotated; the template vertices *and* joints are shifted by ``h``
    (joints are regressed from the unshifted vertices, then shifted, so the relation holds
    whatever the regressor's row sums).

    Posing: local joint rotations convert as ``R_ours = C R_smpl C^T`` (rotation vectors as
    ``C r``; root orientation included) and root translations as ``t_ours = C t_smpl`` -- the
    ground shift is already in the template, so do **not** add ``h`` to the translation. Then
    ``BodyModel.pose(R_ours, t_ours, betas)`` returns exactly ``C v_smpl + (0, 0, h)`` for the
    vertices ``v_smpl`` SMPL itself computes (see :func:`smpl_rotmats_to_world`,
    :func:`smpl_translation_to_world`); any other SMPL-frame quantity (a camera, a scene point)
    maps with :func:`smpl_points_to_world`. With non-zero betas the feet are only approximately
    on z = 0 (the shift is fixed by the template, as SMPL's own origin is).

Pose correctives
    SMPL's ``posedirs`` act on the feature ``vec(R_smpl_j - I)`` (row-major, joints 1..J-1), our
    :class:`~garmentnerf.body.model.BodyModel` computes ``vec(R_j - I)`` from our-frame rotations.
    Since ``R_smpl - I = C^T (R - I) C``, the SMPL feature is ``kron(C^T, C^T)`` times ours (per
    joint, a signed 9x9 permutation); ``posedirs`` are remapped through it and their vertex
    offsets rotated by ``C`` -- exact, no approximation.

Skinning weights
    SMPL's weights are dense (V, J). They are stored *losslessly*: K = the largest number of
    non-zero weights of any vertex, each row sorted by weight, padded with weight-0 entries, with
    no renormalisation. The posed mesh is therefore bit-for-bit SMPL's blend (BodyModel densifies
    the weights to (V, J) for its GEMM anyway, so a smaller K would save nothing at run time).

UVs
    Model files carry no texture atlas. Pass ``uv_obj`` (an OBJ with ``vt`` and ``f v/vt``
    lines, as the SMPL UV file is distributed) to attach one; without it ``uv`` is (0, 2),
    ``uv_faces`` (0, 3) and ``BodyModel.has_uv`` is False.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from types import MappingProxyType

import numpy as np

from garmentnerf.body.asset import BodyAsset, BodyAssetError
from garmentnerf.safe_pickle import RefusedGlobal, StandIn, load_npy_restricted, load_restricted

#: The 24 SMPL joints in the model files' order.
SMPL_JOINT_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hand", "right_hand",
]

#: SMPL's parent of every joint (-1: root); the first 22 are shared by SMPL-H and SMPL-X.
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]

_FINGERS = [f"{finger}{k}" for finger in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
_HAND_JOINT_NAMES = [f"left_{n}" for n in _FINGERS] + [f"right_{n}" for n in _FINGERS]
#: The 52 SMPL-H joints (the 22 body joints, then 15 per hand).
SMPLH_JOINT_NAMES = SMPL_JOINT_NAMES[:22] + _HAND_JOINT_NAMES
#: The 55 SMPL-X joints (the 22 body joints, jaw, eyes, then 15 per hand).
SMPLX_JOINT_NAMES = SMPL_JOINT_NAMES[:22] + ["jaw", "left_eye_smplhf", "right_eye_smplhf"] + _HAND_JOINT_NAMES

#: Rotation from SMPL's model frame (Y up, faces +Z) to ours (Z up, faces -Y): y -> z, z -> -y.
SMPL_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

SMPL_LICENSE = ("SMPL model file supplied by the user; SMPL is licensed by the Max Planck Society, "
                "see https://smpl.is.tue.mpg.de (not redistributed)")

_REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")


# ---- public API ---------------------------------------------------------------------------------
def load_smpl_asset(path: str | Path, uv_obj: str | Path | None = None, *, num_betas: int | None = None) -> BodyAsset:
    """Read an SMPL (or SMPL-H / SMPL-X) model file and convert it to a :class:`BodyAsset`.

    Args:
        path: the model file as distributed, ``.pkl`` (chumpy not needed) or ``.npz``.
        uv_obj: optional OBJ with the model's UV atlas (``vt`` + ``f v/vt``); its faces must be
            the model's faces (any order, any corner rotation).
        num_betas: keep only the first ``num_betas`` shape coefficients (None: all in the file;
            for SMPL-X files these include the expression coefficients after the shape ones).
    Returns:
        A validated asset named ``"smpl"``, ``"smplh"`` (52 joints) or ``"smplx"`` (55 joints).
    Raises:
        BodyAssetError: naming the file and field, for any unreadable, missing or inconsistent data.
    """
    path = Path(path)
    src = str(path)
    m = _read_smpl_arrays(path)
    C = SMPL_TO_WORLD
    v_template, shapedirs, posedirs, J_reg = m["v_template"], m["shapedirs"], m["posedirs"], m["J_regressor"]
    weights, parents, faces = m["weights"], m["parents"], m["f"]
    V, J = v_template.shape[0], len(parents)
    if num_betas is not None:
        if not (0 <= num_betas <= shapedirs.shape[2]):
            raise BodyAssetError(f"{src}: field 'shapedirs' has {shapedirs.shape[2]} shape coefficients, "
                                 f"cannot keep num_betas={num_betas}")
        shapedirs = shapedirs[:, :, :num_betas]
    S = shapedirs.shape[2]

    shift = np.array([0.0, 0.0, _ground_offset(v_template)])
    template = v_template @ C.T
    template_joints = (J_reg @ v_template) @ C.T + shift
    template = template + shift
    shape_dirs = np.einsum("vcs,dc->svd", shapedirs, C)  # (S, V, 3)
    joint_shape_dirs = np.einsum("jv,svd->sjd", J_reg, shape_dirs)  # (S, J, 3)

    # vec(R_smpl - I) = kron(C^T, C^T) vec(R - I) for row-major vec; fold that into posedirs.
    K9 = np.kron(C.T, C.T)
    P4 = posedirs.reshape(V, 3, J - 1, 9)
    pose_dirs = np.einsum("vcjb,dc->jbvd", P4 @ K9, C).reshape(9 * (J - 1), V, 3)

    skin_indices, skin_weights = _compact_weights(weights)

    uv = np.zeros((0, 2), dtype=np.float32)
    uv_faces = np.zeros((0, 3), dtype=np.int64)
    if uv_obj is not None:
        uv, uv_faces = _read_uv_obj(Path(uv_obj), faces)

    name = {52: "smplh", 55: "smplx"}.get(J, "smpl")
    asset = BodyAsset(
        name=name,
        template_vertices=template.astype(np.float32),
        shape_dirs=shape_dirs.astype(np.float32),
        template_joints=template_joints.astype(np.float32),
        joint_shape_dirs=joint_shape_dirs.astype(np.float32),
        faces=faces,
        uv=uv.astype(np.float32),
        uv_faces=uv_faces,
        skin_indices=skin_indices,
        skin_weights=skin_weights.astype(np.float32),
        parents=parents,
        joint_names=_joint_names(parents),
        named_shapes={"average": np.zeros(S, dtype=np.float32)},
        pose_dirs=pose_dirs.astype(np.float32),
        license=SMPL_LICENSE,
    )
    return asset.validate(src)


def smpl_ground_offset(path: str | Path) -> float:
    """Height ``h`` (metres) added to z after rotating SMPL's frame so the template's feet touch z = 0.

    ``p_ours = SMPL_TO_WORLD @ p_smpl + (0, 0, h)``. The asset from :func:`load_smpl_asset`
    already contains the shift: posed bodies need only ``t_ours = C t_smpl``; use ``h`` to map
    other SMPL-frame points (cameras, scene geometry) with :func:`smpl_points_to_world`.
    """
    path = Path(path)
    return _ground_offset(_read_smpl_arrays(path)["v_template"])


def smpl_rotmats_to_world(rotmats):
    """(..., 3, 3) SMPL-frame rotation matrices (local joint or global) -> ours: ``C R C^T``."""
    C = _like(SMPL_TO_WORLD, rotmats)
    return C @ rotmats @ C.T


def smpl_rotvecs_to_world(rotvecs):
    """(..., 3) SMPL-frame rotation vectors -> ours: ``C r`` (C is a proper rotation)."""
    return rotvecs @ _like(SMPL_TO_WORLD, rotvecs).T


def smpl_translation_to_world(translation):
    """(..., 3) SMPL root translations -> ours: ``C t`` (the ground shift is in the template)."""
    return translation @ _like(SMPL_TO_WORLD, translation).T


def smpl_points_to_world(points, ground_offset: float):
    """(..., 3) SMPL-frame points -> our world: ``C p + (0, 0, ground_offset)``."""
    out = points @ _like(SMPL_TO_WORLD, points).T
    out[..., 2] += ground_offset
    return out


# ---- reading the model file ---------------------------------------------------------------------
def _like(matrix: np.ndarray, other):
    """``matrix`` as a numpy array or a torch tensor matching ``other``'s dtype and device."""
    if isinstance(other, np.ndarray) or not hasattr(other, "new_tensor"):
        return matrix.astype(np.result_type(np.asarray(other).dtype, np.float32))
    return other.new_tensor(matrix)


def _ground_offset(v_template: np.ndarray) -> float:
    return float(-v_template[:, 1].min())


def _read_smpl_arrays(path: Path) -> dict:
    """Load the required keys, convert them to plain arrays and check them against each other."""
    src = str(path)
    if not path.is_file():
        raise BodyAssetError(f"{src}: SMPL model file not found")
    if path.suffix == ".pkl":
        raw = _load_pickle(path)
    elif path.suffix == ".npz":
        raw = _load_npz(path)
    else:
        raise BodyAssetError(f"{src}: unsupported SMPL model file type '{path.suffix}' (expected .pkl or .npz)")
    for key in _REQUIRED_KEYS:
        if key not in raw:
            raise BodyAssetError(f"{src}: field '{key}' is missing (not an SMPL model file?)")
    a = {key: _to_array(raw[key], src, key) for key in _REQUIRED_KEYS}
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
        if a[key].dtype.kind not in "fiub":
            raise BodyAssetError(f"{src}: field '{key}' has non-numeric dtype {a[key].dtype}")
        a[key] = a[key].astype(np.float64)
        if not np.all(np.isfinite(a[key])):
            raise BodyAssetError(f"{src}: field '{key}' contains NaN or Inf")

    def bad_shape(key: str, expected: str) -> BodyAssetError:
        return BodyAssetError(f"{src}: field '{key}' has shape {a[key].shape}, expected {expected}")

    kt = a["kintree_table"]
    if kt.ndim != 2 or kt.shape[0] != 2 or kt.shape[1] < 1 or kt.dtype.kind not in "iuf":
        raise bad_shape("kintree_table", "(2, J)")
    parents = _parents_from_kintree(kt, src)
    J = len(parents)

    v = a["v_template"]
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 1:
        raise bad_shape("v_template", "(V, 3)")
    V = v.shape[0]
    if a["shapedirs"].ndim != 3 or a["shapedirs"].shape[:2] != (V, 3):
        raise bad_shape("shapedirs", f"({V}, 3, S)")
    if a["posedirs"].shape != (V, 3, 9 * (J - 1)):
        raise bad_shape("posedirs", f"({V}, 3, {9 * (J - 1)}) for {J} joints")
    if a["J_regressor"].shape != (J, V):
        raise bad_shape("J_regressor", f"({J}, {V})")
    if a["weights"].shape != (V, J):
        raise bad_shape("weights", f"({V}, {J})")
    sums = a["weights"].sum(axis=1)
    if not np.allclose(sums, 1.0, atol=1e-3):
        worst = int(np.argmax(np.abs(sums - 1.0)))
        raise BodyAssetError(f"{src}: field 'weights' rows do not sum to 1 (vertex {worst} sums to {sums[worst]:.6g})")

    f = a["f"]
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
        raise bad_shape("f", "(F, 3)")
    if f.dtype.kind == "f":
        if not np.all(np.isfinite(f)) or np.any(f != np.round(f)):
            raise BodyAssetError(f"{src}: field 'f' holds non-integer vertex indices")
    elif f.dtype.kind not in "iu":
        raise BodyAssetError(f"{src}: field 'f' has non-numeric dtype {f.dtype}")
    if f.min() < 0 or f.max() >= V:
        raise BodyAssetError(f"{src}: field 'f' indexes outside 0..{V - 1} (min {f.min()}, max {f.max()})")
    a["f"] = f.astype(np.int64)
    a["parents"] = parents
    return a


def _parents_from_kintree(kt: np.ndarray, src: str) -> np.ndarray:
    """Column i of ``kintree_table`` is joint i: (parent id, own id); unknown parent ids (-1 or
    4294967295 in the distributed files) mark the root, which must be joint 0."""
    if kt.dtype.kind == "f":
        if not np.all(np.isfinite(kt)) or np.any(kt != np.round(kt)):
            raise BodyAssetError(f"{src}: field 'kintree_table' holds non-integer joint ids")
    ids = [int(x) for x in kt[1]]
    if len(set(ids)) != len(ids):
        raise BodyAssetError(f"{src}: field 'kintree_table' repeats joint ids")
    id_to_col = {jid: col for col, jid in enumerate(ids)}
    parents = np.array([id_to_col.get(int(p), -1) for p in kt[0]], dtype=np.int64)
    J = len(parents)
    if parents[0] != -1 or np.count_nonzero(parents < 0) != 1:
        raise BodyAssetError(f"{src}: field 'kintree_table' must have exactly one root, in column 0")
    for j in range(J):  # every chain must reach the root within J steps (no cycles)
        k, steps = j, 0
        while k >= 0 and steps <= J:
            k, steps = parents[k], steps + 1
        if k >= 0:
            raise BodyAssetError(f"{src}: field 'kintree_table' contains a cycle through joint {j}")
    return parents


def _joint_names(parents: np.ndarray) -> list[str]:
    J = len(parents)
    known = {24: SMPL_JOINT_NAMES, 52: SMPLH_JOINT_NAMES, 55: SMPLX_JOINT_NAMES}.get(J)
    if known is not None and parents[:22].tolist() == SMPL_PARENTS[:22]:
        return list(known)
    return [f"joint_{i}" for i in range(J)]


def _compact_weights(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense (V, J) -> lossless (V, K) indices/weights, K = max non-zeros per vertex."""
    K = max(1, int(np.count_nonzero(weights, axis=1).max()))
    order = np.argsort(-np.abs(weights), axis=1, kind="stable")[:, :K]
    return order.astype(np.int64), np.take_along_axis(weights, order, axis=1)


# ---- chumpy-free reading through the package's restricted unpickler ------------------------------
class _ChumpyStub(StandIn):
    """A chumpy object: ``chumpy.ch.Ch`` pickles its value under the state key ``'x'``."""


class _SparseStub(StandIn):
    """A scipy sparse matrix, rebuilt from its pickled fields by :func:`_sparse_to_dense`."""


#: What an SMPL file may name beyond the allow-list of :mod:`garmentnerf.safe_pickle`: chumpy and
#: scipy.sparse classes, read as inert stand-ins (neither package is imported or run).
_SMPL_STAND_INS = MappingProxyType({"chumpy": _ChumpyStub, "scipy.sparse": _SparseStub})


def _load_pickle(path: Path) -> dict:
    src = str(path)
    try:
        with open(path, "rb") as fh:
            data = load_restricted(fh, _SMPL_STAND_INS)
    except RefusedGlobal as exc:
        raise BodyAssetError(f"{src}: {exc}") from None
    except Exception as exc:  # any failure inside pickle means the file is unusable
        raise BodyAssetError(f"{src}: not a readable SMPL pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise BodyAssetError(f"{src}: SMPL pickle holds a {type(data).__name__}, expected a dict of arrays")
    return data


def _load_npz(path: Path) -> dict:
    """The required keys of an ``.npz``; object arrays (e.g. a sparse J_regressor) are read with
    the restricted unpickler instead of numpy's unrestricted one."""
    src = str(path)
    out = {}
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in _REQUIRED_KEYS:
                if key not in data.files:
                    continue
                try:
                    out[key] = data[key]
                except ValueError as exc:
                    if "allow_pickle" not in str(exc):
                        raise
                    out[key] = _read_npz_object_member(path, key)
    except BodyAssetError:
        raise
    except Exception as exc:
        raise BodyAssetError(f"{src}: not a readable SMPL .npz ({type(exc).__name__}: {exc})") from None
    return out


def _read_npz_object_member(path: Path, key: str):
    src = str(path)
    try:
        with zipfile.ZipFile(path) as zf, zf.open(f"{key}.npy") as fp:
            return load_npy_restricted(fp, _SMPL_STAND_INS)
    except RefusedGlobal as exc:
        raise BodyAssetError(f"{src}: field '{key}': {exc}") from None
    except Exception as exc:
        raise BodyAssetError(f"{src}: field '{key}' is an unreadable object array "
                             f"({type(exc).__name__}: {exc})") from None


def _to_array(value, src: str, key: str, depth: int = 0) -> np.ndarray:
    """A plain ndarray from an ndarray, a chumpy stub, a sparse matrix (stub or real) or a list."""
    if depth > 8:
        raise BodyAssetError(f"{src}: field '{key}' is nested too deeply to read")
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            if value.shape == ():
                return _to_array(value.item(), src, key, depth + 1)
            raise BodyAssetError(f"{src}: field '{key}' is an array of Python objects, expected numbers")
        return value
    if isinstance(value, _ChumpyStub):
        if "x" not in value.__dict__:
            raise BodyAssetError(f"{src}: field '{key}' is a chumpy expression ({value._origin}) that cannot be "
                                 "evaluated without chumpy; re-save the model with plain arrays")
        return _to_array(value.__dict__["x"], src, key, depth + 1)
    if isinstance(value, _SparseStub):
        return _sparse_to_dense(value, src, key)
    if hasattr(value, "toarray") and hasattr(value, "nnz"):  # a real scipy sparse matrix
        return np.asarray(value.toarray())
    try:
        arr = np.asarray(value)
    except Exception:
        arr = None
    if arr is None or arr.dtype == object:
        raise BodyAssetError(f"{src}: field '{key}' has unsupported type {type(value).__name__}")
    return arr


def _sparse_to_dense(stub: _SparseStub, src: str, key: str) -> np.ndarray:
    """Rebuild a pickled scipy sparse matrix from its fields (robust to scipy's module moves)."""
    # local: only chumpy-era SMPL pickles hold sparse matrices, and scipy.sparse would add 0.15-0.2 s
    # to every import of garmentnerf.motion.library (through motion.amass)
    import scipy.sparse as sp

    d = stub.__dict__
    kind = stub._origin.rsplit(".", 1)[-1].split("_")[0]  # csc_matrix -> csc
    try:
        shape = tuple(int(s) for s in (d.get("_shape") or d.get("shape")))
        if kind in ("csc", "csr"):
            ctor = sp.csc_matrix if kind == "csc" else sp.csr_matrix
            m = ctor((np.asarray(d["data"]), np.asarray(d["indices"]), np.asarray(d["indptr"])), shape=shape)
        elif kind == "coo":
            row, col = d["coords"] if "coords" in d else (d["row"], d["col"])
            m = sp.coo_matrix((np.asarray(d["data"]), (np.asarray(row), np.asarray(col))), shape=shape)
        else:
            raise KeyError(f"sparse format {stub._origin}")
        return m.toarray()
    except Exception as exc:
        raise BodyAssetError(f"{src}: field '{key}' is a sparse matrix that cannot be rebuilt "
                             f"({type(exc).__name__}: {exc})") from None


# ---- UV atlas -----------------------------------------------------------------------------------
def _read_uv_obj(path: Path, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(U, 2) texture coordinates and (F, 3) uv_faces aligned with the model's ``faces``.

    A minimal reader for ``v``/``vt``/``f`` lines, keeping the file's own ``vt`` indexing (mesh
    libraries merge or split vertices on load). Faces may come in any order and start at any
    corner, as long as each one is a model face with the same orientation.
    """
    src = str(path)
    if not path.is_file():
        raise BodyAssetError(f"{src}: UV OBJ file not found")
    n_v = 0
    vt: list[list[float]] = []
    fv: list[list[int]] = []
    ft: list[list[int]] = []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise BodyAssetError(f"{src}: UV OBJ file is unreadable ({exc})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                n_v += 1
            elif parts[0] == "vt":
                vt.append([float(parts[1]), float(parts[2])])
            elif parts[0] == "f":
                corners = parts[1:]
                if len(corners) != 3:
                    raise ValueError(f"face with {len(corners)} corners, expected triangles")
                cv, ct = [], []
                for c in corners:
                    fields = c.split("/")
                    if len(fields) < 2 or not fields[1]:
                        raise ValueError(f"face corner '{c}' has no texture index (expected v/vt)")
                    iv, it = int(fields[0]), int(fields[1])
                    cv.append(iv - 1 if iv > 0 else n_v + iv)
                    ct.append(it - 1 if it > 0 else len(vt) + it)
                fv.append(cv)
                ft.append(ct)
        except (ValueError, IndexError) as exc:
            raise BodyAssetError(f"{src}: line {lineno}: cannot parse '{line.strip()[:60]}' ({exc})") from None
    if not vt or not fv:
        raise BodyAssetError(f"{src}: UV OBJ has {len(vt)} 'vt' and {len(fv)} 'f' lines, needs both")
    uv = np.asarray(vt, dtype=np.float64)
    fv_arr = np.asarray(fv, dtype=np.int64)
    ft_arr = np.asarray(ft, dtype=np.int64)
    if not np.all(np.isfinite(uv)):
        raise BodyAssetError(f"{src}: field 'vt' contains NaN or Inf")
    if ft_arr.min() < 0 or ft_arr.max() >= len(uv):
        raise BodyAssetError(f"{src}: field 'f' texture indices outside 1..{len(uv)}")
    if len(fv_arr) != len(faces):
        raise BodyAssetError(f"{src}: UV OBJ has {len(fv_arr)} faces, the SMPL model has {len(faces)}")
    if np.array_equal(fv_arr, faces):
        return uv, ft_arr

    def canonical(tri) -> tuple[tuple[int, int, int], int]:
        r = int(np.argmin(tri))  # rotate so the smallest index comes first (keeps orientation)
        return (int(tri[r]), int(tri[(r + 1) % 3]), int(tri[(r + 2) % 3])), r

    lookup = {}
    for i, tri in enumerate(fv_arr):
        lookup[canonical(tri)[0]] = (i, canonical(tri)[1])
    uv_faces = np.empty_like(faces)
    for i, tri in enumerate(faces):
        key, r_model = canonical(tri)
        if key not in lookup:
            raise BodyAssetError(f"{src}: field 'f' does not match the SMPL model's faces "
                                 f"(model face {i} {tri.tolist()} not found)")
        j, r_obj = lookup[key]
        # model corner c is canonical corner (c - r_model) % 3, which is obj corner (that + r_obj) % 3
        for c in range(3):
            uv_faces[i, c] = ft_arr[j, (c - r_model + r_obj) % 3]
    return uv, uv_faces
