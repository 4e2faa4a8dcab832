"""One garment's trained weights as the start of another garment's run (``garmentnerf train --init-weights``).

The motion encoder E, the field and the decoder's trunk of a trained run know the character and a garment
on it; a new garment's run can start from them instead of from nothing (the layered dress from the skirt's
run: docs/lab/ledger.md, "The dress from the skirt's weights" and "The dress from the skirt's field, with
codes": the figures of a from-scratch run for a fifth of its CPU, and 2.9 dB more after the codes). Three
differences between the two runs are bridged here:

* **a palette of another size** (one colour per layer of a layered garment): the decoder head's
  per-colour channels (three offsets and a blend weight) of the new garment layer ``k`` are those of the
  file's layer ``min(k, file_layers - 1)``, and the body's (always the last colour) are the body's. So the
  start decodes the file's radiance, mask and offsets, and its blend weights in the file's proportion of
  garment to body. The palette's colours themselves are left at the new model's initialisation (the new
  scene's label colours, :func:`~garmentnerf.model.palette.palette_from_labels`): the file's are another
  garment's.
* **another garment's colours** (a palette of the same size from another garment's run; the t-shirt from
  the skirt): the palette is the new model's, so the new garment's colour is its palette colour and not an
  offset the decoder learns over the file's colour (which a recolouring would keep: the t-shirt TTC of
  docs/lab/ledger.md rendered magenta when recoloured blue). A continuation of the same garment keeps the
  colours it learned. Which of the two a file is, the caller says (``same_garment``: the trainer compares
  the garment of the scene recorded in the ``run.json`` beside the file with its own scene's,
  :func:`~garmentnerf.runs.run_garment`). Where nobody can say, the file's ``palette.initial`` (the
  label colours its run started from) is compared with the new scene's, float16 rounding allowed: that
  test takes a file of the same garment whose run started from other colours (the bundled dress, whose
  first weights were made by a script that started both layers at another gold) for another garment's.
* **a decoder that reads more channels** (``shading_normals``: the body's normal after zeta): the first
  convolution's new input columns start at zero, so it computes what the file's did.

Usage (what :class:`~garmentnerf.train.trainer.Trainer` does with ``--init-weights``)::

    garment = run_garment(path.parent)      # None: no run.json naming a readable scene
    same = None if garment is None else garment == scene.garment
    load_weights(path, model, adapt=functools.partial(transfer_garment_state, same_garment=same))
"""

from __future__ import annotations

import torch

from garmentnerf.model.palette import palette_head_rows

__all__ = ["transfer_garment_state", "palette_channel_sources"]

#: State-dict keys of the decoder's per-colour output convolution and of the palette.
_HEAD_KEYS = ("decoder.head.weight", "decoder.head.bias")
_PALETTE_KEYS = ("palette.colors", "palette.initial")

#: Two palettes' starting colours within this (per channel, in [0, 1]) are the same garment's: float16
#: rounding of a packed demo moves them by less than 1e-3, two garments' label colours differ by far more.
SAME_GARMENT_COLOUR_TOLERANCE = 1e-2


def palette_channel_sources(file_size: int, model_size: int) -> list[int]:
    """For each colour of a ``model_size`` palette, the colour of a ``file_size`` palette whose decoder
    channels it starts from: garment layer ``k`` from layer ``min(k, file layers - 1)``, body from body.

    >>> palette_channel_sources(2, 3)    # the skirt's garment colour for both of the dress's layers
    [0, 0, 1]
    """
    if file_size < 2 or model_size < 2:
        raise ValueError(f"palettes of a garment and the body have at least 2 colours, got {file_size} and "
                         f"{model_size}")
    file_layers, model_layers = file_size - 1, model_size - 1
    return [min(k, file_layers - 1) for k in range(model_layers)] + [file_size - 1]


def _head_row_index(radiance_channels: int, file_size: int, model_size: int) -> list[int]:
    """Row of the file's decoder head that each row of the model's head takes."""
    src = palette_channel_sources(file_size, model_size)
    old, new = palette_head_rows(radiance_channels, file_size), palette_head_rows(radiance_channels, model_size)
    index = [0] * sum(len(rows) for rows in new.values())
    for r_new, r_old in zip(new["radiance"], old["radiance"]):
        index[r_new] = r_old
    for c in range(model_size):
        for i in range(3):
            index[new["offsets"][3 * c + i]] = old["offsets"][3 * src[c] + i]
        index[new["weights"][c]] = old["weights"][src[c]]
    index[new["mask"][0]] = old["mask"][0]
    return index


def transfer_garment_state(state: dict[str, torch.Tensor], own: dict[str, torch.Tensor],
                           same_garment: bool | None = None) -> list[str]:
    """Fit ``state`` (weights read from a file, changed in place) to a model whose state dict is ``own``
    where the two differ as described in the module's docstring; every other tensor is left as it is (the
    caller's shape check names any other difference).

    Args:
        same_garment: whether the file was trained on this model's garment (its learned palette is kept),
            or on another (the palette is the model's); None decides by the palettes' starting colours.

    Returns:
        The keys changed, sorted.
    """
    changed = []
    if all(k in state and k in own for k in _PALETTE_KEYS + _HEAD_KEYS):
        file_size, model_size = state["palette.colors"].shape[0], own["palette.colors"].shape[0]
        if file_size != model_size:
            # the radiance rows are what the file's head holds beyond its per-colour and mask rows
            radiance_channels = state["decoder.head.bias"].shape[0] - sum(
                len(rows) for rows in palette_head_rows(0, file_size).values())
            index = torch.tensor(_head_row_index(radiance_channels, file_size, model_size))
            for key in _HEAD_KEYS:
                state[key] = state[key][index].clone()
            changed += list(_HEAD_KEYS)
        if same_garment is None and file_size == model_size:
            same_garment = torch.allclose(state["palette.initial"].float(), own["palette.initial"].float(),
                                          atol=SAME_GARMENT_COLOUR_TOLERANCE)
        if file_size != model_size or not same_garment:
            for key in _PALETTE_KEYS:  # another garment's colours: the new scene's instead
                state[key] = own[key].detach().clone()
            changed += list(_PALETTE_KEYS)
    for key, value in list(state.items()):
        want = own.get(key)
        if (want is None or not key.startswith("decoder.") or value.dim() != 4 or want.dim() != 4
                or value.shape[0] != want.shape[0] or value.shape[2:] != want.shape[2:]
                or value.shape[1] >= want.shape[1]):
            continue
        extra = torch.zeros(value.shape[0], want.shape[1] - value.shape[1], *value.shape[2:], dtype=value.dtype)
        state[key] = torch.cat([value, extra], dim=1)
        changed.append(key)
    return sorted(changed)
