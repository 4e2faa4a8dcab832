"""Learned perceptual distances: LPIPS (v0.1, AlexNet) and shift-tolerant LPIPS.

Both are defined here in plain torch, because the reference packages cannot be imported beside
the project's CPU torch wheel (``lpips`` and ``stlpips-pytorch`` import ``torchvision`` at top
level, ``stlpips-pytorch`` also ``IPython`` and ``torchsummary``). Only their weight files are
used. Both modules take ``(B, 3, H, W)`` RGB batches and return one distance per image. Training
(:mod:`garmentnerf.train.perceptual`, the loss) and evaluation (:mod:`garmentnerf.eval.evaluate`, the
metric) both use them.

LPIPS (Zhang et al. 2018), reported as ``lpips_alex``
    The paper's LPIPS: torchvision's ImageNet AlexNet feature trunk + the v0.1 linear layers.
    No installable package here ships the ImageNet backbone, so it runs only when the user
    supplies it: the torchvision file ``alexnet-owt-7be5be79.pth`` (or any state dict with keys
    ``features.{0,3,6,8,10}.{weight,bias}``), passed as a path or through the environment
    variable :data:`LPIPS_BACKBONE_ENV`. :func:`lpips_available` says whether it can run and
    why not; without it the metric is reported unavailable, never replaced by another one.
    The linear layers (6 KB, BSD-2-Clause, Copyright (c) 2018 Richard Zhang, Phillip Isola,
    Alexei A. Efros, Eli Shechtman, Oliver Wang) are read from, in order: an explicit path,
    ``garmentnerf/assets/lpips_alex_v0.1_lin.npz`` if vendored, the installed ``lpips`` package
    (``lpips/weights/v0.1/alex.pth``; found on disk, not imported).

Shift-tolerant LPIPS (Ghildyal and Liu, ECCV 2022), reported as ``stlpips_alex`` / ``stlpips_vgg``
    A *different* metric (its own trunk, trained from scratch by its authors, with anti-aliased
    stride-1 + blur-pool downsampling so that a one-pixel shift barely changes the distance):
    never report it as LPIPS. Weights (complete: trunk and linear layers) come from the
    installed ``stlpips-pytorch`` 0.0.2 package (BSD-2-Clause, Copyright (c) 2022 Abhijay
    Ghildyal, Feng Liu), ``stlpips_pytorch/weights/vST0.0/{alex,vgg}_shift_tolerant.pth``, found
    on disk. The architecture below mirrors that package's ``variant="shift_tolerant"`` path
    (``invariant_networks.py``, ``models_lpf``) with the same state-dict keys, so the files load
    strictly. Differentiable with respect to both inputs: it is the project's offline perceptual
    training loss.

Shared head (LPIPS v0.1)
    inputs mapped to [-1, 1], then ``(x - shift) / scale`` with shift (-0.030, -0.088, -0.188),
    scale (0.458, 0.448, 0.450); five feature maps; each unit-normalised over channels;
    squared difference; 1x1 conv to one channel (non-negative weights); spatial mean; sum over
    the five layers.
    One deliberate difference from the packages: the channel norm is ``sqrt(sum x^2 + eps^2)``
    instead of ``sqrt(sum x^2) + eps`` (eps = 1e-10). Values agree to ~1e-7 relative, but the
    packages' form has a NaN gradient wherever a feature vector is exactly zero (every ReLU of a
    pixel off), which would poison a training run. Not observed with the shipped weights on
    black, white or random images: cheap insurance for a loss, not a fix of a seen failure.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

#: Environment variable that may hold the path of the AlexNet ImageNet weights for LPIPS.
LPIPS_BACKBONE_ENV = "GARMENTNERF_LPIPS_ALEXNET"

#: The AlexNet feature trunk of torchvision: (index in ``features``, out, in, kernel) of each conv.
ALEXNET_CONVS = ((0, 64, 3, 11), (3, 192, 64, 5), (6, 384, 192, 3), (8, 256, 384, 3), (10, 256, 256, 3))

_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
_NORM_EPS = 1e-10

_STLPIPS_FILES = {"alex": "weights/vST0.0/alex_shift_tolerant.pth", "vgg": "weights/vST0.0/vgg_shift_tolerant.pth"}
_VENDORED_LPIPS_LIN = Path(__file__).resolve().parent.parent / "assets" / "lpips_alex_v0.1_lin.npz"


# ---------------------------------------------------------------------------------------------
# Finding weight files
# ---------------------------------------------------------------------------------------------

def _package_file(package: str, relative: str) -> Path | None:
    """Path of a file inside an installed top-level package, found without importing it (both
    reference packages import torchvision on import)."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        p = Path(root) / relative
        if p.is_file():
            return p
    return None


def stlpips_weights_path(variant: str = "alex") -> Path | None:
    """The shift-tolerant LPIPS weights file of the installed ``stlpips-pytorch``, or None."""
    if variant not in _STLPIPS_FILES:
        raise ValueError(f"shift-tolerant LPIPS variant must be one of {sorted(_STLPIPS_FILES)}, got {variant!r}")
    return _package_file("stlpips_pytorch", _STLPIPS_FILES[variant])


def lpips_lin_path() -> Path | None:
    """The LPIPS v0.1 AlexNet linear-layer weights: vendored asset, else the installed ``lpips``."""
    if _VENDORED_LPIPS_LIN.is_file():
        return _VENDORED_LPIPS_LIN
    return _package_file("lpips", "weights/v0.1/alex.pth")


def _load_state(path: str | Path) -> dict[str, torch.Tensor]:
    """A flat name -> tensor dict from a ``.pth`` state dict or an ``.npz`` archive (whose
    non-numeric entries, e.g. a vendored file's licence text, are skipped)."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return {k: torch.from_numpy(z[k].copy()) for k in z.files if np.issubdtype(z[k].dtype, np.number)}
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a state dict, got {type(state).__name__}")
    return state


def _check_alexnet_backbone(state: dict[str, torch.Tensor], source: str) -> None:
    for idx, out_c, in_c, k in ALEXNET_CONVS:
        for name, shape in ((f"features.{idx}.weight", (out_c, in_c, k, k)), (f"features.{idx}.bias", (out_c,))):
            if name not in state:
                raise ValueError(f"{source}: not a torchvision AlexNet state dict (missing {name!r})")
            if tuple(state[name].shape) != shape:
                raise ValueError(f"{source}: {name} has shape {tuple(state[name].shape)}, expected {shape}")


def lpips_available(backbone_path: str | Path | None = None, lin_path: str | Path | None = None) -> tuple[bool, str]:
    """Whether LPIPS (AlexNet, v0.1) can be computed, and if not, why.

    Args:
        backbone_path: torchvision AlexNet ImageNet weights; default: ``$GARMENTNERF_LPIPS_ALEXNET``.
        lin_path: v0.1 linear-layer weights; default :func:`lpips_lin_path`.
    Returns:
        ``(True, description)`` or ``(False, reason)``. Reads and checks the backbone file.
    """
    backbone_path = backbone_path or os.environ.get(LPIPS_BACKBONE_ENV) or None
    if backbone_path is None:
        return False, ("LPIPS needs the ImageNet AlexNet backbone weights (torchvision's alexnet-owt-7be5be79.pth), "
                       f"which no installable package here ships: pass its path or set ${LPIPS_BACKBONE_ENV}")
    if not Path(backbone_path).is_file():
        return False, f"LPIPS backbone weights file not found: {backbone_path}"
    lin = lin_path or lpips_lin_path()
    if lin is None:
        return False, ("LPIPS v0.1 linear-layer weights not found: install the 'lpips' package (its wheel ships "
                       "lpips/weights/v0.1/alex.pth) or pass lin_path")
    if not Path(lin).is_file():
        return False, f"LPIPS linear-layer weights file not found: {lin}"
    try:
        _check_alexnet_backbone(_load_state(backbone_path), str(backbone_path))
    except Exception as exc:  # any unreadable file is a reason, not a crash
        return False, f"LPIPS backbone weights unusable: {exc}"
    return True, f"LPIPS v0.1 AlexNet: backbone {backbone_path}, linear layers {lin}"


# ---------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------

class BlurPool(nn.Module):
    """Anti-aliased stride-2 downsampling (Zhang 2019, ``models_lpf.Downsample``, ``pad_more=True``).

    Reflection padding of ``filt_size - 1`` on every side, then a depthwise binomial filter
    (``[1, 2, 1] x [1, 2, 1] / 16`` for size 3) with stride 2. ``(B, C, H, W)`` ->
    ``(B, C, floor((H + 2 (k - 1) - k) / 2) + 1, ...)``. The filter is a buffer named ``filt``,
    as in the package's state dicts.
    """

    def __init__(self, channels: int, filt_size: int = 3, stride: int = 2):
        super().__init__()
        a = _binomial(filt_size)
        filt = a[:, None] * a[None, :]
        self.register_buffer("filt", (filt / filt.sum())[None, None].repeat(channels, 1, 1, 1))
        self.pad = filt_size - 1
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pad(x, (self.pad,) * 4, mode="reflect")
        return F.conv2d(x, self.filt.to(x.dtype), stride=self.stride, groups=x.shape[1])


def _reflect(index: int, size: int) -> int:
    """``index`` reflected into ``[0, size)`` as ``F.pad(mode="reflect")`` does (the edge not
    repeated); valid for indices less than ``size`` outside."""
    if index < 0:
        return -index
    if index >= size:
        return 2 * (size - 1) - index
    return index


def _blurpool_interior(size: int, filt_size: int, pad: int) -> tuple[int, int, int]:
    """(first, last, count) output index of a BlurPool over ``size`` inputs: ``first..last`` read
    no reflected input (output ``i`` reads inputs ``2 i - pad .. 2 i - pad + filt_size - 1``)."""
    count = (size + 2 * pad - filt_size) // 2 + 1
    return (pad + 1) // 2, (size - filt_size + pad) // 2, count


def conv_blurpool(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, padding: int,
                  filt: torch.Tensor, pad: int) -> torch.Tensor:
    """``blur(F.conv2d(x, weight, bias, padding=padding))``, ``blur`` being a :class:`BlurPool`
    (reflection padding ``pad``, the depthwise filter ``filt`` (f, f) on every channel, stride 2),
    computed without the stride-1 convolution's full output.

    Both steps are linear, so away from the borders the pair is one stride-2 convolution with the
    composed kernel (``weight`` convolved with ``filt``: k + f - 1 wide), about a third of the
    stride-1 convolution's work and none of the blur's, forward and backward. The outputs within
    ``pad`` of a border read the convolution's output reflected: those rows and columns are
    computed from the few convolution rows and columns they read, with the reflection applied to
    them, so the result is the plain composition's up to float rounding (tested against it).

    Args:
        x: (B, I, H, W); weight: (O, I, k, k); bias: (O,) or None; padding: the convolution's zero
            padding; filt: (f, f) the blur filter; pad: the blur's reflection padding (< the
            convolution's output size).
    Returns:
        (B, O, Ho, Wo) as the plain composition.
    """
    O, I, k, _ = weight.shape
    f = filt.shape[-1]
    H, W = x.shape[-2:]
    Hy, Wy = H + 2 * padding - k + 1, W + 2 * padding - k + 1
    r_lo, r_hi, Ho = _blurpool_interior(Hy, f, pad)
    c_lo, c_hi, Wo = _blurpool_interior(Wy, f, pad)
    blur = filt.to(x.dtype).expand(O, 1, f, f)
    if r_hi < r_lo or c_hi < c_lo or pad >= min(Hy, Wy):
        # too small to have an interior: the plain composition (which refuses a pad beyond the size)
        y = F.pad(F.conv2d(x, weight, bias, padding=padding), (pad,) * 4, mode="reflect")
        return F.conv2d(y, blur, stride=2, groups=O)
    xp = F.pad(x, (padding,) * 4)
    composed = F.conv2d(weight.reshape(O * I, 1, k, k), filt.to(weight.dtype).flip(-2, -1)[None, None],
                        padding=f - 1).reshape(O, I, k + f - 1, k + f - 1)
    r0, c0 = 2 * r_lo - pad, 2 * c_lo - pad
    interior = F.conv2d(xp[..., r0:, c0:], composed, bias, stride=2)[..., :r_hi - r_lo + 1, :c_hi - c_lo + 1]

    def conv_rows(first: int, last: int) -> torch.Tensor:  # rows first..last of the convolution's output
        return F.conv2d(xp[..., first:last + k, :], weight, bias)

    def conv_cols(first: int, last: int) -> torch.Tensor:
        return F.conv2d(xp[..., first:last + k], weight, bias)

    def border_rows(outputs: range) -> torch.Tensor:  # (B, O, len(outputs), Wo), corners included
        reads = [[_reflect(2 * i - pad + a, Hy) for a in range(f)] for i in outputs]
        first, last = min(min(r) for r in reads), max(max(r) for r in reads)
        y = conv_rows(first, last)
        y = y[..., [j - first for r in reads for j in r], :]
        return F.conv2d(F.pad(y, (pad, pad, 0, 0), mode="reflect"), blur, stride=(f, 2), groups=O)

    def border_cols(outputs: range) -> torch.Tensor:  # (B, O, interior rows, len(outputs))
        reads = [[_reflect(2 * j - pad + a, Wy) for a in range(f)] for j in outputs]
        first, last = min(min(r) for r in reads), max(max(r) for r in reads)
        y = conv_cols(first, last)[..., r0:2 * r_hi - pad + f, :]
        y = y[..., [j - first for r in reads for j in r]]
        return F.conv2d(y, blur, stride=(2, f), groups=O)

    middle = [interior]
    if c_lo > 0:
        middle.insert(0, border_cols(range(0, c_lo)))
    if c_hi + 1 < Wo:
        middle.append(border_cols(range(c_hi + 1, Wo)))
    rows = [torch.cat(middle, dim=-1)]
    if r_lo > 0:
        rows.insert(0, border_rows(range(0, r_lo)))
    if r_hi + 1 < Ho:
        rows.append(border_rows(range(r_hi + 1, Ho)))
    # in the input's memory format: the layers after it (a max pool) are several times slower on
    # a tensor pieced together in another
    channels_last = x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()
    return torch.cat(rows, dim=-2).contiguous(memory_format=torch.channels_last if channels_last
                                              else torch.contiguous_format)


class ConvBlurPool(nn.Sequential):
    """A stride-1 ``nn.Conv2d``, a :class:`BlurPool` and what follows them (ST-LPIPS AlexNet's
    first slice), run through :func:`conv_blurpool`; :meth:`reference` runs the layers one by
    one. The children and their state-dict keys are those of the plain ``nn.Sequential``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        conv, blur = self[0], self[1]
        x = conv_blurpool(x, conv.weight, conv.bias, conv.padding[0], blur.filt[0, 0], blur.pad)
        for layer in list(self)[2:]:
            x = layer(x)
        return x

    def reference(self, x: torch.Tensor) -> torch.Tensor:
        """The layers one by one (the plain ``nn.Sequential``)."""
        return super().forward(x)


def _binomial(n: int) -> torch.Tensor:
    """Row ``n - 1`` of Pascal's triangle: 3 -> (1, 2, 1)."""
    row = [1.0]
    for _ in range(n - 1):
        row = [a + b for a, b in zip([0.0] + row, row + [0.0])]
    return torch.tensor(row, dtype=torch.float32)


class _LinLayer(nn.Module):
    """LPIPS's 1x1 conv from C channels to 1; ``model.1`` as in the packages' keys (their
    ``model.0`` is a Dropout, here an Identity: a training-mode parent must not drop features of
    a metric)."""

    def __init__(self, channels: int):
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class _ScalingLayer(nn.Module):
    def __init__(self):
        super().__init__()
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE)[None, :, None, None])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.shift.to(x.dtype)) / self.scale.to(x.dtype)


def _sequential(layers: dict[int, nn.Module], kind: type[nn.Sequential] = nn.Sequential) -> nn.Sequential:
    """An nn.Sequential (or ``kind``) whose children are named by the given indices (the packages' keys)."""
    s = kind()
    for idx, layer in layers.items():
        s.add_module(str(idx), layer)
    return s


def _unit_normalise(x: torch.Tensor) -> torch.Tensor:
    """Divide each pixel's feature vector by its L2 norm (see the module docstring for the eps)."""
    return x * torch.rsqrt(x.square().sum(dim=1, keepdim=True) + _NORM_EPS ** 2)


def _alexnet_lpips_trunk() -> nn.Module:
    """torchvision's AlexNet ``features`` cut into LPIPS's 5 slices (relu1..relu5)."""
    net = nn.Module()
    r = lambda: nn.ReLU(inplace=False)  # noqa: E731 - not in place: the outputs are kept
    net.slice1 = _sequential({0: nn.Conv2d(3, 64, 11, stride=4, padding=2), 1: r()})
    net.slice2 = _sequential({2: nn.MaxPool2d(3, 2), 3: nn.Conv2d(64, 192, 5, padding=2), 4: r()})
    net.slice3 = _sequential({5: nn.MaxPool2d(3, 2), 6: nn.Conv2d(192, 384, 3, padding=1), 7: r()})
    net.slice4 = _sequential({8: nn.Conv2d(384, 256, 3, padding=1), 9: r()})
    net.slice5 = _sequential({10: nn.Conv2d(256, 256, 3, padding=1), 11: r()})
    return net


def _alexnet_shift_tolerant_trunk(fused: bool = True) -> nn.Module:
    """stlpips-pytorch ``invariant_networks.alexnet(variant="shift_tolerant", filter_size=3)``:
    AlexNet with stride-1 first conv and stride-1 max pools, every stride-2 step a BlurPool. The
    first conv and its BlurPool run as one (:class:`ConvBlurPool`) unless ``fused`` is false: at
    256 x 256 that slice's forward and backward are about twice as cheap."""
    net = nn.Module()
    r = lambda: nn.ReLU(inplace=False)  # noqa: E731
    net.slice1 = _sequential({0: nn.Conv2d(3, 64, 11, stride=1, padding=2), 1: BlurPool(64), 2: r()},
                             ConvBlurPool if fused else nn.Sequential)
    net.slice2 = _sequential({3: nn.MaxPool2d(3, 1), 4: BlurPool(64), 5: nn.Conv2d(64, 192, 5, padding=2), 6: r()})
    net.slice3 = _sequential({7: nn.MaxPool2d(3, 1), 8: BlurPool(192), 9: nn.Conv2d(192, 384, 3, padding=1), 10: r()})
    net.slice4 = _sequential({11: nn.Conv2d(384, 256, 3, padding=1), 12: r()})
    net.slice5 = _sequential({13: nn.Conv2d(256, 256, 3, padding=1), 14: r()})
    return net


def _vgg16_shift_tolerant_trunk() -> nn.Module:
    """stlpips-pytorch ``invariant_networks.vggnet(variant="shift_tolerant")``: VGG16 (config D)
    whose max pools are ``MaxPool2d(2, stride=1)`` followed by a BlurPool; slices end at
    relu1_2, relu2_2, relu3_3, relu4_3, relu5_3."""
    layers: list[nn.Module] = []
    in_c = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512):
        if v == "M":
            layers += [nn.MaxPool2d(2, stride=1), BlurPool(in_c)]
        else:
            layers += [nn.Conv2d(in_c, v, 3, padding=1), nn.ReLU(inplace=False)]
            in_c = v
    net = nn.Module()
    for k, (a, b) in enumerate(((0, 4), (4, 10), (10, 18), (18, 26), (26, 34)), start=1):
        setattr(net, f"slice{k}", _sequential({i: layers[i] for i in range(a, b)}))
    return net


def image_batch(images) -> torch.Tensor:
    """(B, 3, H, W) float32 tensor from one (H, W, 3) image or a sequence / (B, H, W, 3) array of
    them, in [0, 1] (uint8 is divided by 255). Tensors already (B, 3, H, W) pass through."""
    if isinstance(images, torch.Tensor) and images.ndim == 4 and images.shape[1] == 3:
        return images.float()
    if isinstance(images, (list, tuple)):
        images = np.stack([i.detach().cpu().numpy() if isinstance(i, torch.Tensor) else np.asarray(i)
                           for i in images])
    a = images.detach().cpu().numpy() if isinstance(images, torch.Tensor) else np.asarray(images)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"expected (H, W, 3) or (B, H, W, 3) images, got shape {a.shape}")
    a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
    return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))


class _PerceptualDistance(nn.Module):
    """LPIPS-style head on a 5-slice trunk; see the module docstring."""

    metric_name = ""

    def __init__(self, trunk: nn.Module, channels: Sequence[int], input_range=(0.0, 1.0), reduction: str = "none"):
        super().__init__()
        lo, hi = (float(v) for v in input_range)
        if not hi > lo:
            raise ValueError(f"input_range must be (low, high) with high > low, got {input_range}")
        if reduction not in ("none", "mean"):
            raise ValueError(f"reduction must be 'none' or 'mean', got {reduction!r}")
        self.input_range = (lo, hi)
        self.reduction = reduction
        self.scaling_layer = _ScalingLayer()
        self.net = trunk
        for k, c in enumerate(channels):
            setattr(self, f"lin{k}", _LinLayer(c))
        self.num_layers = len(channels)

    def _finish(self) -> None:
        # A fixed metric: no parameter is ever trained, gradients flow only to the inputs.
        self.requires_grad_(False)
        self.eval()
        # Channels-last convolutions are ~1.6x faster on the CPU (oneDNN), same values.
        self.to(memory_format=torch.channels_last)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The trunk's 5 feature maps of an already scaled (B, 3, H, W) batch."""
        out = []
        for k in range(1, self.num_layers + 1):
            x = getattr(self.net, f"slice{k}")(x)
            out.append(x)
        return out

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Distance of each image pair.

        Args:
            pred, target: (B, 3, H, W) RGB in ``input_range`` (default [0, 1]).
        Returns:
            (B,) distances (>= 0, 0 for identical images), or their mean if ``reduction="mean"``.
        """
        if pred.shape != target.shape or pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(f"expected two (B, 3, H, W) batches of equal shape, got {tuple(pred.shape)} "
                             f"and {tuple(target.shape)}")
        # The target's features are made without autograd unless the target itself wants a
        # gradient: as a training loss nothing reads the target's input gradient, and its
        # backward through the trunk costs as much as the prediction's (~40 % of the loss's
        # forward + backward at 256x256 on the CPU).
        with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
            target_feats = self._normalised_features(target)
        total = pred.new_zeros(pred.shape[0])
        for k, (f, g) in enumerate(zip(self._normalised_features(pred), target_feats)):
            total = total + getattr(self, f"lin{k}")((f - g).square()).mean(dim=(1, 2, 3))
        return total.mean() if self.reduction == "mean" else total

    def _normalised_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The trunk's 5 feature maps of a (B, 3, H, W) batch in ``input_range``, each unit-normalised
        over channels."""
        lo, hi = self.input_range
        x = x.to(self.scaling_layer.shift.dtype)
        x = ((x - lo) * (2.0 / (hi - lo)) - 1.0).contiguous(memory_format=torch.channels_last)
        return [_unit_normalise(f) for f in self.features(self.scaling_layer(x))]

    @torch.no_grad()
    def distance(self, pred, target) -> float:
        """Distance of one image pair given as (H, W, 3) arrays in [0, 1] (metric use)."""
        p, t = image_batch(pred), image_batch(target)
        lo, hi = self.input_range
        p, t = p * (hi - lo) + lo, t * (hi - lo) + lo
        dev = self.scaling_layer.shift.device
        return float(self(p.to(dev), t.to(dev))[0])


class STLPIPS(_PerceptualDistance):
    """Shift-tolerant LPIPS (``stlpips_alex`` or ``stlpips_vgg``), weights from ``stlpips-pytorch``.

    Args:
        variant: ``"alex"`` (9.9 MB of weights) or ``"vgg"`` (58.9 MB, ~10x the compute).
        input_range: value range of the inputs, mapped linearly to the [-1, 1] the network was
            trained on; default (0, 1) (the project's images); (-1, 1) is the packages' convention.
        reduction: ``"none"`` -> (B,) distances; ``"mean"`` -> a scalar (for use as a loss, e.g.
            the ``perceptual`` callable of :func:`garmentnerf.model.losses.garment_losses`).
        weights_path: override the weights file.
        fused: run AlexNet's first convolution and its BlurPool as one (:func:`conv_blurpool`;
            the same values up to float rounding, the loss's forward and backward about 1.2 times
            faster at 256 x 256); false runs the layers one by one.
    Raises:
        FileNotFoundError: without ``weights_path`` when ``stlpips-pytorch`` is not installed.

    The parameters are frozen (``requires_grad=False``) and there is no dropout or batch norm,
    so ``train()``/``eval()`` change nothing; gradients flow to both inputs.
    """

    def __init__(self, variant: str = "alex", input_range=(0.0, 1.0), reduction: str = "none",
                 weights_path: str | Path | None = None, fused: bool = True):
        if variant == "alex":
            trunk, channels = _alexnet_shift_tolerant_trunk(fused), (64, 192, 384, 256, 256)
        elif variant == "vgg":
            trunk, channels = _vgg16_shift_tolerant_trunk(), (64, 128, 256, 512, 512)
        else:
            raise ValueError(f"shift-tolerant LPIPS variant must be 'alex' or 'vgg', got {variant!r}")
        super().__init__(trunk, channels, input_range, reduction)
        self.variant = variant
        self.metric_name = f"stlpips_{variant}"
        path = weights_path or stlpips_weights_path(variant)
        if path is None:
            raise FileNotFoundError(f"shift-tolerant LPIPS weights not found: install stlpips-pytorch==0.0.2 "
                                    f"(it ships {_STLPIPS_FILES[variant]}) or pass weights_path")
        self.weights_path = Path(path)
        self.load_state_dict(_load_state(path), strict=True)
        self._finish()


def stlpips_available(variant: str = "alex") -> tuple[bool, str]:
    """Whether shift-tolerant LPIPS weights are installed, and if not, why."""
    path = stlpips_weights_path(variant)
    if path is None:
        return False, f"stlpips-pytorch is not installed (it ships {_STLPIPS_FILES[variant]})"
    return True, f"shift-tolerant LPIPS ({variant}) weights: {path}"


class LPIPS(_PerceptualDistance):
    """LPIPS v0.1 with torchvision's ImageNet AlexNet trunk (``lpips_alex``, the paper's LPIPS).

    Args:
        backbone_path: torchvision AlexNet state dict (``alexnet-owt-7be5be79.pth``; the
            ``classifier.*`` entries are ignored); default ``$GARMENTNERF_LPIPS_ALEXNET``.
        lin_path: v0.1 linear layers (``lpips/weights/v0.1/alex.pth`` or the vendored ``.npz``
            with keys ``lin0.model.1.weight`` ...); default :func:`lpips_lin_path`.
        input_range, reduction: as :class:`STLPIPS`.
    Raises:
        FileNotFoundError / ValueError: with :func:`lpips_available`'s reason when it cannot run.
    """

    metric_name = "lpips_alex"

    def __init__(self, backbone_path: str | Path | None = None, lin_path: str | Path | None = None,
                 input_range=(0.0, 1.0), reduction: str = "none"):
        super().__init__(_alexnet_lpips_trunk(), (64, 192, 384, 256, 256), input_range, reduction)
        backbone_path = backbone_path or os.environ.get(LPIPS_BACKBONE_ENV) or None
        ok, reason = lpips_available(backbone_path, lin_path)
        if not ok:
            raise FileNotFoundError(reason)
        backbone = _load_state(backbone_path)
        _check_alexnet_backbone(backbone, str(backbone_path))
        slice_of = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
        state = {}
        for idx, _, _, _ in ALEXNET_CONVS:
            for p in ("weight", "bias"):
                state[f"net.slice{slice_of[idx]}.{idx}.{p}"] = backbone[f"features.{idx}.{p}"]
        lin = _load_state(lin_path or lpips_lin_path())
        for k in range(5):
            key = f"lin{k}.model.1.weight"
            if key not in lin:
                raise ValueError(f"LPIPS linear-layer weights lack {key!r}")
            state[key] = lin[key]
        state["scaling_layer.shift"] = self.scaling_layer.shift
        state["scaling_layer.scale"] = self.scaling_layer.scale
        self.load_state_dict(state, strict=True)
        self.backbone_path = Path(backbone_path)
        self._finish()
