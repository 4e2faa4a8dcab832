"""Safe file handling: writes that lose nothing a user made to a crash or a second run, reading
an ``.npy``/``.npz`` array's header without loading (or unpickling) the array, and content
digests of files memoised on their size and modification time."""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import threading
import time
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import IO

import numpy as np


@contextlib.contextmanager
def atomic_write_path(path: str | Path, overwrite: bool = True):
    """Yield a temporary path next to ``path``; on success rename it over ``path``.

    The rename is atomic on POSIX, so readers see either the old file or the complete new one.
    With ``overwrite=False`` an existing file raises :class:`FileExistsError` before any work.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: already exists (refusing to overwrite)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
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
        if exc.filename is not None and Path(exc.filename) == Path(tmp):
            # name the file the user asked for, not our temporary
            raise type(exc)(exc.errno, f"{path}: cannot write ({exc.strerror})") from None
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _write_synced(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` and sync it to the disk (a full disk raises :class:`OSError`
    with its errno here, not later)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_file_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: a synced temporary beside it, renamed over ``path``.

    Readers see the old file or the complete new one; a failed write (OSError naming ``path``)
    leaves the old file and no temporary.
    """
    path = Path(path)
    try:
        with atomic_write_path(path) as tmp:
            _write_synced(tmp, data)
    except OSError as exc:
        if exc.filename is None and str(path) not in str(exc):  # write() errors name no file
            raise type(exc)(exc.errno, f"{path}: cannot write ({exc.strerror or exc})") from exc
        raise
    return path


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
