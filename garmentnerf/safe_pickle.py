"""Reading pickled data without running the code it names: the one allow-list of the package.

Pickles from outside (SMPL model files, ZJU-MoCap's ``annots.npy`` and parameter files) are read
with :class:`RestrictedUnpickler`. It resolves only the globals numpy needs to rebuild arrays and
the plain builtin containers (:data:`SAFE_BUILTINS`, :data:`SAFE_GLOBALS`). Every other global
raises :class:`RefusedGlobal` -- ``os.system``, ``builtins.eval`` and ``subprocess.Popen`` among
them -- unless the caller names its module as one to stand in for: then the global becomes an inert
:class:`StandIn` subclass that accepts any construction, keeps the pickled state in its
``__dict__`` and runs nothing (how SMPL files load without chumpy or a matching scipy).

Loaders turn :class:`RefusedGlobal` into their own one-line error naming the file, e.g.
``model.pkl: refusing to unpickle 'posix.system' (only numpy arrays and plain containers are read)``.
"""

from __future__ import annotations

import _compat_pickle  # pickle's own Python 2 -> 3 name table
import pickle
import warnings
from collections.abc import Mapping
from typing import IO

import numpy as np

from garmentnerf.io_utils import read_npy_header

__all__ = ["SAFE_BUILTINS", "SAFE_GLOBALS", "RefusedGlobal", "StandIn", "RestrictedUnpickler", "load_restricted",
           "load_npy_restricted"]

#: Builtins a pickle may name: plain containers and scalars, nothing callable with side effects.
SAFE_BUILTINS = frozenset({"object", "set", "frozenset", "list", "dict", "tuple", "int", "float", "complex", "str",
                           "bytes", "bytearray", "bool", "slice", "range"})

#: (module, name) of the other globals a pickle may name: numpy's array and scalar reconstructors
#: (under numpy 1 and 2 module paths), copyreg's object reconstructor (``copy_reg`` in Python 2),
#: ``_codecs.encode`` (Python 2 byte strings) and ``OrderedDict``. ``numpy.dtypes.*DType`` are
#: allowed too (numpy 2 pickles dtypes by class).
SAFE_GLOBALS = frozenset({
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copyreg", "_reconstructor"), ("_codecs", "encode"),
    ("collections", "OrderedDict"),
})


class RefusedGlobal(pickle.UnpicklingError):
    """A pickle names a global outside the allow-list; ``name`` is its ``module.qualname``."""

    def __init__(self, name: str) -> None:
        super().__init__(f"refusing to unpickle '{name}' (only numpy arrays and plain containers are read)")
        self.name = name


class StandIn:
    """Inert stand-in for a class a loader reads but never runs: accepts any construction and keeps
    the pickled state in ``__dict__`` (a non-dict state under ``'_state'``). Subclasses made by
    :class:`RestrictedUnpickler` carry the original global's name in ``_origin``."""

    _origin = "?"

    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        if isinstance(state, tuple) and len(state) == 2 and isinstance(state[1], dict):
            state = {**(state[0] or {}), **state[1]}  # the (dict, slots) form
        if isinstance(state, dict):
            self.__dict__.update(state)
        else:
            self.__dict__["_state"] = state


def _python3_name(module: str, name: str) -> tuple[str, str]:
    """The Python 3 name of a global a protocol 0-2 pickle names by its Python 2 name
    (``__builtin__.eval`` -> ``builtins.eval``, ``commands.Popen`` -> ``subprocess.Popen``), as
    :mod:`pickle` itself maps it: checks and refusals speak of what would actually be imported."""
    if (module, name) in _compat_pickle.NAME_MAPPING:
        return _compat_pickle.NAME_MAPPING[(module, name)]
    return _compat_pickle.IMPORT_MAPPING.get(module, module), name


def _is_allowed(module: str, name: str) -> bool:
    if module == "builtins":
        return name in SAFE_BUILTINS
    return (module, name) in SAFE_GLOBALS or (module == "numpy.dtypes" and name.endswith("DType"))


def _in_package(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


class RestrictedUnpickler(pickle.Unpickler):
    """A :class:`pickle.Unpickler` (``latin1`` for Python 2 pickles) that resolves only the
    allow-list; see the module docstring.

    Args:
        file: a binary file positioned at the pickle.
        stand_ins: package name -> :class:`StandIn` subclass; any global of that package (or its
            subpackages) becomes a subclass of it named after the global, instead of being refused.
    """

    def __init__(self, file: IO[bytes], stand_ins: Mapping[str, type[StandIn]] | None = None) -> None:
        super().__init__(file, encoding="latin1")
        self._stand_in_bases = dict(stand_ins or {})
        # (module, name) -> the stand-in class made for it; one class per global within one load.
        self._stand_in_classes: dict[tuple[str, str], type[StandIn]] = {}

    def find_class(self, module: str, name: str):
        module, name = _python3_name(module, name)
        if _is_allowed(module, name):
            with warnings.catch_warnings():  # numpy 2 warns on its numpy.core aliases
                warnings.simplefilter("ignore", DeprecationWarning)
                return super().find_class(module, name)
        for package, base in self._stand_in_bases.items():
            if _in_package(module, package):
                return self._stand_in(base, module, name)
        raise RefusedGlobal(f"{module}.{name}")

    def _stand_in(self, base: type[StandIn], module: str, name: str) -> type[StandIn]:
        key = (module, name)
        if key not in self._stand_in_classes:
            self._stand_in_classes[key] = type(name, (base,), {"_origin": f"{module}.{name}"})
        return self._stand_in_classes[key]


def load_restricted(file: IO[bytes], stand_ins: Mapping[str, type[StandIn]] | None = None):
    """Unpickle one object from ``file`` with :class:`RestrictedUnpickler`.

    Raises:
        RefusedGlobal: the pickle names a global outside the allow-list (and ``stand_ins``).
        Exception: whatever else a malformed pickle raises (callers name their file).
    """
    return RestrictedUnpickler(file, stand_ins).load()


def load_npy_restricted(file: IO[bytes], stand_ins: Mapping[str, type[StandIn]] | None = None):
    """One ``.npy`` array from a seekable binary ``file``: plain arrays as ``np.load(...,
    allow_pickle=False)`` reads them, object arrays through :func:`load_restricted` (what
    ``np.save`` pickles: the array itself, so the result may be any allowed object)."""
    start = file.tell()
    _, _, dtype = read_npy_header(file)
    if dtype.hasobject:
        return load_restricted(file, stand_ins)
    file.seek(start)
    return np.load(file, allow_pickle=False)
