"""Grow a scene's training set with a sequence simulated for another scene, without simulating again.

A sequence is a body motion and the garment simulated on it (``motion.npz``, ``garment.npz``);
the ground-truth images are rendered on demand from those and the *receiving* scene's cameras, so
a sequence made by ``garmentnerf data make`` for one scene can train another when both dress the
same body (model and shape) in the same garment at the same frame rate. :func:`import_sequence`
checks exactly that (the garment's mesh must have the receiving scene's topology), copies the
folder under a temporary name, renames it into place and only then saves ``scene.json``
(atomically), so an interrupted import leaves the scene as it was. :func:`add_sequence` (``garmentnerf
data add-sequence``) does it holding the receiving scene's writer lock (:mod:`garmentnerf.folder_lock`),
taken before the scene is read: a ``data make`` or another import writing the scene meanwhile is
refused, naming its PID, instead of one ``scene.json`` overwriting the other's.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from garmentnerf.data.scene import Scene, SceneError, SequenceInfo, read_garment_arrays
from garmentnerf.data.scene_schema import SEQUENCE_SPLITS, SchemaChecker
from garmentnerf.folder_lock import lock_folder

__all__ = ["add_sequence", "import_sequence", "garment_difference"]


def garment_difference(ours: dict, theirs: dict, whose: str = "this scene's") -> str | None:
    """Why a scene dressed in garment ``theirs`` (``scene.json``'s ``garment``) cannot stand for one in
    ``ours`` (None: the same kind), as the end of a message: ``its garment is a dress, <whose> a skirt``."""
    if ours.get("kind") != theirs.get("kind"):
        return f"its garment is a {theirs.get('kind')}, {whose} a {ours.get('kind')}"
    return None


def _incompatibility(target: Scene, source: Scene) -> str | None:
    """Why ``source``'s sequences cannot train ``target`` (None: they can)."""
    garment = garment_difference(target.garment, source.garment)
    if garment:
        return garment
    for key in ("model", "shape"):
        if target.body.get(key) != source.body.get(key):
            return f"its body {key} is {source.body.get(key)!r}, this scene's {target.body.get(key)!r}"
    if abs(target.fps - source.fps) > 1e-6 * target.fps:
        return f"its fps is {source.fps:g}, this scene's {target.fps:g}"
    return None


def import_sequence(target: Scene, source: Scene, name: str, *, as_name: str | None = None,
                    split: str | None = None) -> SequenceInfo:
    """Copy ``source``'s sequence ``name`` into ``target`` as ``as_name`` (default: ``name``).

    Args:
        target: the scene that receives the sequence; its ``scene.json`` is saved.
        source: the scene the sequence was simulated for.
        name: the sequence in ``source``.
        as_name: its name in ``target``; must be new there.
        split: its split in ``target`` (default: its split in ``source``).
    Returns:
        the new :class:`SequenceInfo` of ``target``.
    Raises:
        SceneError: one line naming the scene file and the problem (unknown or taken name, a
            different garment, body or fps, another garment topology).
    """
    new_name = as_name or name
    checker = SchemaChecker(str(target.scene_file))
    info = source.sequence(name)  # raises for an unknown name, naming the source file
    checker.name(new_name, f"sequences.{new_name}")
    split = info.split if split is None else split
    checker.choice(split, f"sequences.{new_name}.split", SEQUENCE_SPLITS)
    if new_name in target.sequences:
        raise checker.fail(f"sequences.{new_name}", "already exists (choose another name with --as)")
    problem = _incompatibility(target, source)
    if problem:
        raise SceneError(f"{source.scene_file}: cannot train {target.scene_file}: {problem}")
    existing = next(iter(target.sequences), None)  # every sequence of a scene shares its garment's topology
    if existing is not None:
        faces = read_garment_arrays(source.garment_path(name)).faces
        own = read_garment_arrays(target.garment_path(existing)).faces
        if own.shape != faces.shape or not np.array_equal(own, faces):
            raise SceneError(f"{source.garment_path(name)}: the garment mesh ({len(faces)} faces) differs from "
                             f"{target.garment_path(existing)} ({len(own)} faces)")

    destination = target.root / "sequences" / new_name
    if destination.exists():
        raise SceneError(f"{destination}: exists but is not a sequence of {target.scene_file}; remove it first")
    staging = destination.with_name(f".{new_name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(source.sequence_dir(name), staging)
    staging.rename(destination)
    copied = SequenceInfo(new_name, info.motion, info.frames, split,
                          {**info.extra, "copied_from": f"{Path(source.root).resolve()}:{name}"})
    target.sequences[new_name] = copied
    if name in source.simulation:
        target.simulation[new_name] = source.simulation[name]
    try:
        target.save()
    except BaseException:
        target.sequences.pop(new_name, None)
        target.simulation.pop(new_name, None)
        shutil.rmtree(destination, ignore_errors=True)
        raise
    return copied


def add_sequence(target_dir, source_dir, name: str, *, as_name: str | None = None,
                 split: str | None = None) -> tuple[Scene, SequenceInfo]:
    """:func:`import_sequence` of the scene folders ``target_dir`` and ``source_dir``, holding the writer
    lock of ``target_dir`` from before it is read until its ``scene.json`` is saved.

    Returns:
        (the receiving scene as saved, the new :class:`SequenceInfo`).
    Raises:
        SceneError: as :func:`import_sequence`, and for a folder that holds no scene (checked before the
            lock, which would make the folders of a mistyped path).
        FolderBusyError: another process writes ``target_dir`` (one line naming its PID and command).
    """
    Scene.load(target_dir, check_files=False)  # no scene there: refused as such, before the lock
    with lock_folder(target_dir, "garmentnerf data add-sequence", what="scene"):
        target, source = Scene.load(target_dir), Scene.load(source_dir)
        return target, import_sequence(target, source, name, as_name=as_name, split=split)
