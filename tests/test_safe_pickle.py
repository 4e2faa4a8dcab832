"""The package's one restricted unpickler (garmentnerf.safe_pickle), directly and through the real
loaders of SMPL model files (.pkl, .npz) and ZJU-MoCap annotations and parameter files: a pickle
naming code to run is refused with one line naming the file and the global, and nothing runs."""

from __future__ import annotations

import builtins
import io
import os
import pickle
import subprocess
from collections import OrderedDict

import numpy as np
import pytest
from support.smpl_models import make_model, write_chumpy_pkl, write_npz
from support.zju_capture import write_capture

from garmentnerf.body.asset import BodyAssetError
from garmentnerf.body.smpl import SMPL_PARENTS, load_smpl_asset
from garmentnerf.data.zju import CaptureError, CaptureScene
from garmentnerf.safe_pickle import RefusedGlobal, StandIn, load_npy_restricted, load_restricted


def _payloads(marker):
    """(callable, arguments) pairs that would create ``marker`` if the pickle ran them."""
    return {
        "os.system": (os.system, (f"touch {marker}",)),
        "builtins.eval": (builtins.eval, (f"open({str(marker)!r}, 'w').close()",)),
        "subprocess.Popen": (subprocess.Popen, (["touch", str(marker)],)),
    }


class _Attack:
    """Pickles as a call of ``fn(*args)``: what a malicious file holds."""

    def __init__(self, fn, args) -> None:
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


def _global_name(fn) -> str:
    """How the refusal names ``fn``: its module (``posix`` for ``os.system`` on Linux) and name."""
    return f"{fn.__module__}.{fn.__name__}"


def _object_array(value) -> np.ndarray:
    a = np.empty((), dtype=object)
    a[()] = value
    return a


def _assert_refused(exc_info, path, fn, marker) -> None:
    """One line: ``<file>: refusing to unpickle '<global>' (...)``, and the call never ran."""
    msg = str(exc_info.value)
    assert msg == (f"{path}: refusing to unpickle '{_global_name(fn)}' "
                   "(only numpy arrays and plain containers are read)"), msg
    assert not marker.exists(), "the pickled call ran"


PAYLOADS = ["os.system", "builtins.eval", "subprocess.Popen"]


@pytest.fixture(scope="module")
def smpl_model():
    return make_model(SMPL_PARENTS, V=60, F=90)


# ---- through the real loaders ---------------------------------------------------------------------
@pytest.mark.parametrize("payload", PAYLOADS)
@pytest.mark.parametrize("protocol", [0, 2, 5])
def test_smpl_pkl_naming_code_is_refused(tmp_path, smpl_model, payload, protocol):
    marker = tmp_path / "ran"
    fn, args = _payloads(marker)[payload]
    model = dict(smpl_model, bs_type=_Attack(fn, args))
    path = tmp_path / "evil.pkl"
    if protocol <= 2:  # as the SMPL files are distributed: chumpy arrays, Python 2 names
        write_chumpy_pkl(path, model, protocol=protocol)
    else:
        path.write_bytes(pickle.dumps(model, protocol=protocol))
    with pytest.raises(BodyAssetError) as info:
        load_smpl_asset(path)
    _assert_refused(info, path, fn, marker)


@pytest.mark.parametrize("payload", PAYLOADS)
def test_smpl_npz_object_member_naming_code_is_refused(tmp_path, smpl_model, payload):
    marker = tmp_path / "ran"
    fn, args = _payloads(marker)[payload]
    path = tmp_path / "evil.npz"
    np.savez(path, **dict(smpl_model, J_regressor=_object_array(_Attack(fn, args))))
    with pytest.raises(BodyAssetError) as info:
        load_smpl_asset(path)
    assert str(info.value) == (f"{path}: field 'J_regressor': refusing to unpickle '{_global_name(fn)}' "
                               "(only numpy arrays and plain containers are read)")
    assert not marker.exists()


@pytest.mark.parametrize("payload", PAYLOADS)
def test_zju_annots_naming_code_are_refused(tmp_path, payload):
    marker = tmp_path / "ran"
    fn, args = _payloads(marker)[payload]
    annots = write_capture(tmp_path / "cap", frames=1)
    annots["cams"]["extra"] = _Attack(fn, args)
    path = tmp_path / "cap" / "annots.npy"
    np.save(path, annots, allow_pickle=True)
    with pytest.raises(CaptureError) as info:
        CaptureScene.load(tmp_path / "cap")
    _assert_refused(info, path, fn, marker)


@pytest.mark.parametrize("payload", PAYLOADS)
def test_zju_smpl_params_naming_code_are_refused(tmp_path, payload):
    marker = tmp_path / "ran"
    fn, args = _payloads(marker)[payload]
    write_capture(tmp_path / "cap", frames=1)
    scene = CaptureScene.load(tmp_path / "cap")
    path = tmp_path / "cap" / "new_params" / "0.npy"
    np.save(path, {"poses": np.zeros((1, 72)), "Rh": _Attack(fn, args)}, allow_pickle=True)
    with pytest.raises(CaptureError) as info:
        scene.smpl_params("train", 0)
    _assert_refused(info, path, fn, marker)


def test_legit_smpl_files_still_load(tmp_path, smpl_model):
    """The chumpy pickle and the .npz with a pickled sparse regressor read the values written."""
    for path in (write_chumpy_pkl(tmp_path / "m.pkl", smpl_model),
                 write_npz(tmp_path / "m.npz", smpl_model, sparse_regressor=True)):
        asset = load_smpl_asset(path)
        np.testing.assert_array_equal(asset.faces, smpl_model["f"].astype(np.int64))
        assert asset.template_vertices.shape == smpl_model["v_template"].shape


# ---- the unpickler itself -------------------------------------------------------------------------
def test_plain_containers_and_arrays_round_trip():
    value = {"a": [1, 2.5, "s", b"raw", None, True], "b": (np.arange(6, dtype=np.int16).reshape(2, 3),),
             "c": OrderedDict(x=np.float32(1.5)), "d": {frozenset({1, 2}), 3}, "e": np.array(["u", "v"]),
             "f": np.zeros(3, dtype=[("p", "<f4"), ("q", "<i8")])}
    for protocol in (0, 2, 4, 5):
        back = load_restricted(io.BytesIO(pickle.dumps(value, protocol=protocol)))
        assert back.keys() == value.keys() and back["a"] == value["a"] and back["d"] == value["d"]
        assert isinstance(back["c"], OrderedDict) and back["c"]["x"] == np.float32(1.5)
        np.testing.assert_array_equal(back["b"][0], value["b"][0])
        assert back["b"][0].dtype == np.int16
        np.testing.assert_array_equal(back["e"], value["e"])
        np.testing.assert_array_equal(back["f"], value["f"])


def test_npy_reader_reads_plain_and_object_arrays():
    plain = np.arange(12.0).reshape(3, 4).T  # Fortran order on disk
    buf = io.BytesIO()
    np.save(buf, plain)
    buf.seek(0)
    np.testing.assert_array_equal(load_npy_restricted(buf), plain)
    buf = io.BytesIO()
    np.save(buf, _object_array({"k": np.ones(2)}), allow_pickle=True)
    buf.seek(0)
    back = load_npy_restricted(buf)
    assert back.dtype == object and back.shape == ()
    np.testing.assert_array_equal(back.item()["k"], np.ones(2))


def test_refusal_names_the_global_and_stand_ins_run_nothing(tmp_path):
    marker = tmp_path / "ran"
    fn, args = _payloads(marker)["os.system"]
    blob = pickle.dumps(_Attack(fn, args), protocol=2)
    with pytest.raises(RefusedGlobal) as info:
        load_restricted(io.BytesIO(blob))
    assert info.value.name == _global_name(fn)

    class Inert(StandIn):
        pass

    # Standing in for the module turns the call into an inert object of a class named after it.
    obj = load_restricted(io.BytesIO(blob), {fn.__module__: Inert})
    assert isinstance(obj, Inert) and type(obj)._origin == _global_name(fn)
    assert not marker.exists()
    # One class per global within one load; the stand-in of a package covers its subpackages only.
    two = load_restricted(io.BytesIO(pickle.dumps([_Attack(fn, args), _Attack(fn, args)], protocol=2)),
                          {fn.__module__: Inert})
    assert type(two[0]) is type(two[1])
    with pytest.raises(RefusedGlobal):
        load_restricted(io.BytesIO(blob), {fn.__module__[:-1]: Inert})
