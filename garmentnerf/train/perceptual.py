"""The perceptual training loss: VGG19 (the authors' code) when ImageNet weights are given, else
shift-tolerant LPIPS (the only learned perceptual network with weights installable offline here).

* ``vgg19``: torchvision's VGG19 ``features`` trunk (state dict of ``vgg19-dcbb9e9d.pth``, keys
  ``features.<i>.weight/bias``; ``classifier.*`` ignored), inputs normalised with the ImageNet
  mean/std, L1 distance between the relu1_2, relu3_1 and relu5_1 activations (the layers of the
  authors' code), averaged. The path comes from :class:`~garmentnerf.train.trainer.TrainConfig`
  ``vgg19_weights`` or the environment variable :data:`VGG19_WEIGHTS_ENV`.
* ``stlpips_alex``: :class:`garmentnerf.model.perceptual.STLPIPS` (``reduction="mean"``).
* ``none``: no perceptual term (``w_perceptual`` = 0, or asked for).

:func:`make_perceptual` returns ``(module or None, name)``; the name goes to the log and to
``run.json`` (``perceptual``).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.model.perceptual import STLPIPS

VGG19_WEIGHTS_ENV = "GARMENTNERF_VGG19"
#: torchvision VGG19 ``features``: conv layer indices and channel counts ("M" = max-pool).
_VGG19_LAYOUT = (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512)
#: Indices (in ``features``) of the ReLUs after conv1_2, conv3_1 and conv5_1.
VGG19_LAYERS = (3, 11, 29)

__all__ = ["VGG19Loss", "make_perceptual", "VGG19_WEIGHTS_ENV", "PERCEPTUAL_CHOICES"]
PERCEPTUAL_CHOICES = ("auto", "vgg19", "stlpips", "none")


class VGG19Loss(nn.Module):
    """Mean L1 distance of VGG19 activations (relu1_2, relu3_1, relu5_1) of two (B, 3, H, W) images in [0, 1]."""

    def __init__(self, weights_path: str | Path, layers=VGG19_LAYERS):
        super().__init__()
        path = Path(weights_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: VGG19 weights not found")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{path}: not a readable torch state dict ({exc})") from exc
        if isinstance(state, dict) and "state_dict" in state:
            state = state["state_dict"]
        mods: list[nn.Module] = []
        in_ch = 3
        for item in _VGG19_LAYOUT:
            if item == "M":
                mods.append(nn.MaxPool2d(2, 2))
            else:
                mods += [nn.Conv2d(in_ch, item, 3, padding=1), nn.ReLU(inplace=False)]
                in_ch = item
        self.layers = tuple(layers)
        self.features = nn.Sequential(*mods[: max(self.layers) + 1])
        own = {f"features.{k}": v for k, v in self.features.state_dict().items()}
        missing = [k for k in own if k not in state]
        if missing:
            raise ValueError(f"{path}: not torchvision VGG19 weights (missing {', '.join(missing[:3])} ...)")
        for k, v in own.items():
            if tuple(state[k].shape) != tuple(v.shape):
                raise ValueError(f"{path}: {k} has shape {tuple(state[k].shape)}, VGG19 needs {tuple(v.shape)}")
        self.features.load_state_dict({k[len("features."):]: state[k] for k in own})
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()
        self.weights_path = path

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        # The target's activations are made without autograd unless the target itself wants a
        # gradient: nothing reads its input gradient, and its backward costs as much as pred's.
        with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
            target_acts = self._activations(target)
        total = pred.new_zeros(())
        for a, b in zip(self._activations(pred), target_acts):
            total = total + F.l1_loss(a, b)
        return total / len(self.layers)

    def _activations(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The activations at ``self.layers`` of a (B, 3, H, W) batch in [0, 1]."""
        x = x.sub(self.mean).div(self.std)
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.layers:
                out.append(x)
        return out


def make_perceptual(choice: str = "auto", vgg19_weights: str | Path | None = None,
                    weight: float = 1.0) -> tuple[nn.Module | None, str]:
    """The perceptual loss module and its name (see the module docstring).

    Args:
        choice: ``auto`` (VGG19 when weights are named, else shift-tolerant LPIPS),
            ``vgg19``, ``stlpips`` or ``none``.
        vgg19_weights: VGG19 ImageNet weights (default ``$GARMENTNERF_VGG19``).
        weight: the loss weight; 0 gives ``(None, "none")``.
    Raises:
        ValueError / FileNotFoundError: an unknown choice, or weights that cannot be loaded.
    """
    if choice not in PERCEPTUAL_CHOICES:
        raise ValueError(f"perceptual must be one of {', '.join(PERCEPTUAL_CHOICES)}, got {choice!r}")
    if choice == "none" or weight == 0:
        return None, "none"
    path = vgg19_weights or os.environ.get(VGG19_WEIGHTS_ENV) or None
    if choice == "vgg19" or (choice == "auto" and path):
        if not path:
            raise FileNotFoundError(f"perceptual 'vgg19' needs ImageNet VGG19 weights (vgg19-dcbb9e9d.pth): "
                                    f"pass --vgg19-weights or set ${VGG19_WEIGHTS_ENV}")
        module = VGG19Loss(path)
        return module, f"vgg19:{Path(path).name}"

    return STLPIPS("alex", reduction="mean"), "stlpips_alex"
