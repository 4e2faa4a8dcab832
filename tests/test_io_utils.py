"""Atomic file writing (garmentnerf.io_utils)."""

from __future__ import annotations

import os
import stat

import pytest
import torch

from garmentnerf.io_utils import atomic_write_path, next_free_path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_atomic_write_gives_usual_permissions_even_when_the_writer_recreates_the_file(tmp_path):
    from safetensors.torch import save_file

    target = tmp_path / "w.safetensors"
    with atomic_write_path(target) as tmp:
        save_file({"x": torch.zeros(2)}, str(tmp))
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~_umask()
    assert [p.name for p in tmp_path.iterdir()] == ["w.safetensors"]  # no temporary left


def test_atomic_write_never_clobbers_and_cleans_up_on_error(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("mine")
    with pytest.raises(FileExistsError):
        with atomic_write_path(target, overwrite=False) as tmp:
            tmp.write_text("theirs")
    with pytest.raises(RuntimeError):
        with atomic_write_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    assert next_free_path(target).name == "a_001.txt"
