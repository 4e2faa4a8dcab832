"""Safe file handling: writes that lose nothing a user made to a crash or a second run, the one
strict reader of the project's JSON files, reading an ``.npy``/``.npz`` array's header without
loading (or unpickling) the array, and content digests of files memoised on their size and
modification time."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import tempfile
import threading
import time
import zipfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np


@contextlib.contextmanager
def atomic_write_path(path: str | Path, overwrite: bool = True):
    """Yield a temporary path next to ``path``; on success rename it over ``path``.

    The rename is atomic on POSIX, so readers see either the old file or the complete new one.
    With ``overwrite=False`` an existing file raises :class:`FileExistsError` before any work.
    A write the operating system refuses (a full disk or quota, a read-only file system: an
    :class:`OSError` of the block naming no file, or naming the temporary) removes the temporary,
    leaves any old file as it was and is raised again as one line naming ``path``
    (:func:`write_error`), for every command that writes through here.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: already exists (refusing to overwrite)")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # no inode left, or a folder not writable: it names a temporary the user never saw
        raise write_error(exc, path, exc.filename) from None
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield Path(tmp)
        # mkstemp makes 0600 (and some writers recreate the file): give it the usual permissions
        os.chmod(tmp, 0o666 & ~umask)
        if not overwrite:
            # link() fails if the target appeared meanwhile: never clobber.
            os.link(tmp, path)
            os.unlink(tmp)
        else:
            os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise write_error(exc, path, tmp) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_error(exc: OSError, path: str | Path, temporary: str | Path | None = None) -> OSError:
    """``exc``, raised while writing ``path`` (through ``temporary``), as the error to report: when the
    operating system raised it (it has an errno) naming no file or ``temporary``, an error of the same
    type and errno whose message is one line naming ``path``: ``<path>: cannot write (No space left
    on device)``; any other error as it is (it names its own file, or is a writer's own message)."""
    named = exc.filename
    ours = named is None or (temporary is not None and Path(named) == Path(temporary))
    if exc.errno is None or not ours:
        return exc
    reason = exc.strerror or os.strerror(exc.errno)
    error = type(exc)(f"{path}: cannot write ({reason})")
    error.errno = exc.errno  # set after construction: the message stays this one line, without "[Errno N]"
    return error


def _write_synced(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` and sync it to the disk (a full disk raises :class:`OSError`
    with its errno here, not later)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_file_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a synced temporary beside it, renamed over ``path``.

    Readers see the old file or the complete new one; a failed write (OSError naming ``path``,
    :func:`write_error`) leaves the old file and no temporary.
    """
    path = Path(path)
    with atomic_write_path(path) as tmp:
        _write_synced(tmp, data)
    return path


def user_cache_dir(kind: str) -> Path:
    """Where the package keeps what it measured or made once, of one ``kind`` (a folder name):
    ``$GARMENTNERF_CACHE_DIR/<kind>``, else ``$XDG_CACHE_HOME/garmentnerf/<kind>``, else
    ``~/.cache/garmentnerf/<kind>``. Losing it only means doing the work again."""
    root = os.environ.get("GARMENTNERF_CACHE_DIR", "").strip()
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
        root = str(Path(xdg) / "garmentnerf") if xdg else str(Path.home() / ".cache" / "garmentnerf")
    return Path(root) / kind


#: A temporary file of :func:`atomic_write_path` untouched for this long is a leftover of a killed
#: write (a live write touches its file continuously; a PNG takes milliseconds).
STALE_TEMPORARY_SECONDS = 60.0


def save_tagged_tensors(path, tensors: dict, kind: str, metadata: dict[str, str] | None = None) -> Path:
    """Write ``tensors`` (name -> torch tensor) to a ``.safetensors`` file atomically, with the
    metadata ``format`` = ``kind`` (plus ``metadata``) that :func:`load_tagged_tensors` checks.
    Returns the path."""
    from safetensors.torch import save  # lazy: importing this module costs no torch

    data = save({k: v.detach().cpu().contiguous() for k, v in tensors.items()},
                metadata={"format": kind, **(metadata or {})})
    return write_file_atomic(Path(path), data)


def load_tagged_tensors(path, kind: str, what: str) -> tuple[dict, dict[str, str]]:
    """(tensors, metadata) of a ``.safetensors`` file :func:`save_tagged_tensors` wrote as ``kind``.

    Raises:
        ValueError naming the file: unreadable, or not a ``what`` file (another ``format``).
    """
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for damaged files
        raise ValueError(f"{path}: not a readable safetensors file ({type(exc).__name__}: {exc})") from exc
    if meta.get("format") != kind:
        raise ValueError(f"{path}: not a {what} file")
    return tensors, meta


def temporary_pattern(name: str) -> str:
    """The glob of the temporaries :func:`atomic_write_path` makes for a file called ``name``
    (``name`` may itself be a glob, e.g. ``frame_*.png``)."""
    return f".{name}.*.tmp"


def remove_stale_temporaries(folder: str | Path, name: str, min_age: float = STALE_TEMPORARY_SECONDS) -> list[Path]:
    """Delete the temporaries of writes of ``name`` into ``folder`` (see :func:`temporary_pattern`)
    that were killed: those not modified for ``min_age`` seconds. Returns what was deleted."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    now = time.time()
    removed = []
    for tmp in folder.glob(temporary_pattern(name)):
        with contextlib.suppress(FileNotFoundError):
            if tmp.is_file() and now - tmp.stat().st_mtime >= min_age:
                tmp.unlink()
                removed.append(tmp)
    return removed


def next_free_path(path: str | Path) -> Path:
    """``path`` if free, else ``stem_001.ext``, ``stem_002.ext``, ... (first free)."""
    path = Path(path)
    if not path.exists():
        return path
    for i in range(1, 100000):
        candidate = path.with_name(f"{path.stem}_{i:03d}{path.suffix}")
        if not candidate.exists():
            return candidate
    raise FileExistsError(f"{path}: no free numbered name left")


# ---- JSON: one strict reader for every file the project reads ------------------------------------------
@dataclass(frozen=True)
class _NonFinite:
    """A number JSON holds that is no finite float: NaN, Infinity, 1e999, an integer of hundreds of digits."""

    text: str


def _float(text: str):
    value = float(text)
    return value if math.isfinite(value) else _NonFinite(text)


def _int(text: str):
    return int(text) if len(text.lstrip("-")) <= 308 else _NonFinite(text)  # beyond that, no float holds it


class _DuplicateKey(ValueError):
    pass


def _shown_key(key: str) -> str:
    """A JSON key as a message shows it: as it is when it is a plain name, else quoted and escaped."""
    return key if _PLAIN_KEY.fullmatch(key) else json.dumps(key)


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_.\- ]{1,64}")


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    seen = set()
    for key, _ in pairs:
        if key in seen:
            raise _DuplicateKey(f"key '{_shown_key(key)}' is given twice in one object")
        seen.add(key)
    return dict(pairs)


def _first_non_finite(value, where: str = "") -> tuple[str, str] | None:
    """(key path, number text) of the first non-finite number in ``value``, or None."""
    if isinstance(value, _NonFinite):
        return where, value.text
    if isinstance(value, dict):
        for key, item in value.items():
            found = _first_non_finite(item, f"{where}.{_shown_key(key)}" if where else _shown_key(key))
            if found is not None:
                return found
    elif isinstance(value, list):
        for i, item in enumerate(value):
            found = _first_non_finite(item, f"{where}[{i}]")
            if found is not None:
                return found
    return None


def parse_json_strict(text: str, where: str):
    """The JSON value of ``text`` (the contents of ``where``, named in errors).

    Refused, as a ValueError of one line naming ``where`` (and the key, as ``a.b[2].c``): NaN,
    Infinity and numbers beyond a float (``1e999``), which Python's ``json`` would otherwise accept;
    a key given twice in one object; text that is not JSON (with its line and column).
    """
    try:
        value = json.loads(text, parse_constant=_NonFinite, parse_float=_float, parse_int=_int,
                           object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise ValueError(f"{where}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})") from None
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"{where}: not valid JSON ({type(exc).__name__}: {exc})") from None
    found = _first_non_finite(value)
    if found is not None:
        key, number = found
        if len(number) > 24:
            number = f"{number[:12]}... ({len(number)} characters)"
        raise ValueError(f"{where}: {key + ': ' if key else ''}{number} is not a finite number")
    return value


def read_json_strict(path, what: str):
    """The JSON value of the file ``path``, a ``what`` file (e.g. ``camera path``), read by
    :func:`parse_json_strict`.

    Raises:
        FileNotFoundError: no such file (``<path>: no such <what> file``).
        IsADirectoryError: ``path`` is a folder.
        ValueError: anything else, one line naming the file (and the key).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such {what} file") from None
    except IsADirectoryError:
        raise IsADirectoryError(f"{path}: is a folder, not a {what} file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a {what} file (not UTF-8 text)") from None
    except OSError as exc:
        raise ValueError(f"{path}: unreadable ({exc.strerror or exc})") from None
    return parse_json_strict(text, str(path))


def json_number(value, where: str, low: float | None = None, high: float | None = None, *,
                low_open: bool = False) -> float:
    """``value`` as a float: a JSON number (not a boolean) in ``[low, high]`` (``(low, high]`` with
    ``low_open``); ValueError naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    if low is not None and (number <= low if low_open else number < low):
        raise ValueError(f"{where} must be {'>' if low_open else '>='} {low:g}, got {value!r}")
    if high is not None and number > high:
        raise ValueError(f"{where} must be <= {high:g}, got {value!r}")
    return number


def json_whole(value, where: str, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int: a whole JSON number (``3`` or ``3.0``, not a boolean) in ``[low, high]``;
    ValueError naming ``where`` otherwise."""
    number = json_number(value, where)
    if number != int(number):
        raise ValueError(f"{where} must be a whole number, got {value!r}")
    whole = int(value) if isinstance(value, int) else int(number)
    if (low is not None and whole < low) or (high is not None and whole > high):
        bounds = f"{low if low is not None else ''}..{high if high is not None else ''}"
        raise ValueError(f"{where} must be a whole number in {bounds}, got {value!r}")
    return whole


def json_bool(value, where: str) -> bool:
    """``value`` when it is a JSON boolean (``true``/``false``; not ``"false"``, not ``0``);
    ValueError naming ``where`` otherwise."""
    if not isinstance(value, bool):
        raise ValueError(f"{where} must be true or false, got {value!r}")
    return value


def read_npy_header(file: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran_order, dtype) of the ``.npy`` array at ``file``'s position, leaving ``file``
    at the array's data. Raises ValueError for a bad magic string or an unsupported format version."""
    version = np.lib.format.read_magic(file)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(file)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(file)
    else:
        raise ValueError(f"unsupported .npy format version {version[0]}.{version[1]}")
    return tuple(int(n) for n in shape), bool(fortran), dtype


def npz_member_shape(path: str | Path, key: str) -> tuple[int, ...] | None:
    """Shape of array ``key`` of an ``.npz`` from its header alone (None if the file has no such
    array). Raises OSError, ValueError or zipfile.BadZipFile for an unreadable file."""
    with zipfile.ZipFile(path) as zf:
        member = f"{key}.npy"
        if member not in zf.namelist():
            return None
        with zf.open(member) as fh:
            return read_npy_header(fh)[0]


class FileDigests:
    """SHA-256 of files' content, memoised on (resolved path, size, mtime) -- the ``capacity``
    most recent -- so a file is hashed once while it is unchanged, and a copy hashes the same.

    Thread-safe: one instance may be shared by threads (a scene read by the viewer's UI, its
    render worker and its exporter); hashing itself runs outside the lock.
    """

    def __init__(self, capacity: int = 256) -> None:
        self.capacity = int(capacity)
        self._lock = threading.Lock()
        self._digests: OrderedDict[tuple[str, int, int], str] = OrderedDict()  # guarded by _lock

    def digest(self, path: str | Path) -> str | None:
        """64 hex digits of the file's SHA-256, or None if it does not exist."""
        path = Path(path)
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
        with self._lock:
            digest = self._digests.get(key)
            if digest is not None:
                self._digests.move_to_end(key)
                return digest
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        digest = h.hexdigest()
        with self._lock:
            self._digests[key] = digest
            while len(self._digests) > self.capacity:
                self._digests.popitem(last=False)
        return digest
