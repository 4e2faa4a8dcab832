"""The trainer's part of a run folder (:mod:`garmentnerf.runs` has the rest: ``run.json`` and the weights).

Layout of what the trainer adds::

    <run>/checkpoints/ckpt_<step>.safetensors       model weights at <step>
    <run>/checkpoints/ckpt_<step>.state.pt          optimiser, step, RNG states (exact resume)
    <run>/tb/                                       TensorBoard logs

Each file is written atomically; :func:`remove_run_temporaries` deletes the temporaries of killed
writes before a run is resumed. :func:`load_module_weights` starts a part of the model (G_img) from
another run's weights.
"""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors.torch import load_file

from garmentnerf.io_utils import remove_stale_temporaries
from garmentnerf.runs import MODEL_FILE, RUN_FILE

CHECKPOINT_DIR = "checkpoints"
TB_DIR = "tb"

__all__ = ["CHECKPOINT_DIR", "TB_DIR", "remove_run_temporaries", "load_module_weights"]


def remove_run_temporaries(run_dir) -> list[Path]:
    """Delete the temporaries of killed writes of a run's own files (``run.json``,
    ``model.safetensors`` and the checkpoints; nothing else). Returns what was deleted.

    Only for a run folder that no process is writing (the trainer calls it before it resumes).
    """
    run_dir = Path(run_dir)
    removed = []
    for name in (RUN_FILE, MODEL_FILE):
        removed += remove_stale_temporaries(run_dir, name, min_age=0)
    for name in ("ckpt_*.safetensors", "ckpt_*.state.pt"):
        removed += remove_stale_temporaries(run_dir / CHECKPOINT_DIR, name, min_age=0)
    return removed


def load_module_weights(path, model: torch.nn.Module, prefix: str) -> None:
    """Load only the tensors under ``prefix.`` (e.g. ``image_generator``) from a weights file.

    Raises:
        FileNotFoundError / ValueError naming the file: missing or unreadable file, or tensors
        under ``prefix`` that are absent or shaped differently from ``model``'s.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing")
    try:
        state = load_file(str(path), device="cpu")
    except Exception as exc:
        raise ValueError(f"{path}: not a readable safetensors file ({type(exc).__name__}: {exc})") from exc
    own = {k: v for k, v in model.state_dict().items() if k.startswith(prefix + ".")}
    missing = sorted(k for k in own if k not in state)
    shapes = sorted(k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape))
    if not own or missing or shapes:
        raise ValueError(f"{path}: no matching '{prefix}' weights (missing {len(missing)}, "
                         f"differently shaped {len(shapes)} of {len(own)} tensors)")
    with torch.no_grad():
        for k, v in own.items():
            v.copy_(state[k].to(v.dtype))
