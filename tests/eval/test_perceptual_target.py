"""The perceptual losses send a target that wants no gradient through their network without
autograd: same loss, same gradient w.r.t. the prediction and same metric values as the plain
computation (both images in one batch, everything tracked), with about half the graph."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.model import perceptual as P
from garmentnerf.train.perceptual import VGG19Loss

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pair(seed: int, shape=(2, 3, 48, 56)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(shape, generator=g)
    pred = (target + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    return pred, target


def _saved_numel(fn, *modules: nn.Module) -> tuple[torch.Tensor, int]:
    """``fn()`` and the number of elements autograd saved for its backward, the weights and
    buffers of ``modules`` (held anyway) left out."""
    held = {t.data_ptr() for m in modules for t in (*m.parameters(), *m.buffers())}
    saved = []

    def pack(t):
        if t.data_ptr() not in held:
            saved.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = fn()
    return out, sum(saved)


# ---------------------------------------------------------------------------------------------
# Shift-tolerant LPIPS
# ---------------------------------------------------------------------------------------------

def _stlpips_concatenated(m: P.STLPIPS, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The plain computation: both images in one batch through the trunk, then the LPIPS head
    (inputs to [-1, 1], scaling layer, unit-normalised features, squared difference, linear
    layers, spatial mean, sum over the layers)."""
    lo, hi = m.input_range
    x = torch.cat([pred, target], 0)
    x = (x - lo) / (hi - lo) * 2 - 1
    x = (x - m.scaling_layer.shift) / m.scaling_layer.scale
    b = pred.shape[0]
    total = 0
    for k in range(1, 6):
        x = getattr(m.net, f"slice{k}")(x)
        f = x / torch.sqrt(x.square().sum(1, keepdim=True) + 1e-20)
        total = total + getattr(m, f"lin{k - 1}")((f[:b] - f[b:]).square()).mean(dim=(1, 2, 3))
    return total


@pytest.fixture(scope="module")
def st_alex():
    ok, reason = P.stlpips_available("alex")
    if not ok:
        pytest.skip(reason)
    return P.STLPIPS("alex")


def test_stlpips_loss_and_pred_gradient_equal_the_concatenated_computation(st_alex):
    pred, target = _pair(1)
    p_new, p_ref = pred.clone().requires_grad_(True), pred.clone().requires_grad_(True)
    loss, saved = _saved_numel(lambda: st_alex(p_new, target).mean(), st_alex)
    ref, saved_ref = _saved_numel(lambda: _stlpips_concatenated(st_alex, p_ref, target).mean(), st_alex)
    loss.backward()
    ref.backward()
    assert float(ref.detach()) > 1e-3
    torch.testing.assert_close(loss, ref, rtol=1e-5, atol=1e-7)
    # float32 sums in other orders (batch of one against two): 1e-4 of the gradient's scale
    torch.testing.assert_close(p_new.grad, p_ref.grad, rtol=1e-4, atol=1e-4 * float(p_ref.grad.abs().max()))
    assert p_new.grad.abs().max() > 0
    # the target's trunk pass holds nothing for backward: the graph is about half the plain one
    assert saved < 0.6 * saved_ref, (saved, saved_ref)


def test_stlpips_target_that_wants_a_gradient_gets_the_plain_one(st_alex):
    pred, target = _pair(2)
    t_new, t_ref = target.clone().requires_grad_(True), target.clone().requires_grad_(True)
    loss = P.STLPIPS("alex", reduction="mean")(pred, t_new)
    ref = _stlpips_concatenated(st_alex, pred, t_ref).mean()
    loss.backward()
    ref.backward()
    torch.testing.assert_close(loss, ref, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(t_new.grad, t_ref.grad, rtol=1e-4, atol=1e-4 * float(t_ref.grad.abs().max()))


def test_stlpips_metric_values_are_unchanged(st_alex):
    pred, target = _pair(3, (1, 3, 40, 52))
    with torch.no_grad():
        expected = float(_stlpips_concatenated(st_alex, pred, target)[0])
    a, b = (t[0].permute(1, 2, 0).numpy() for t in (pred, target))
    assert st_alex.distance(a, b) == pytest.approx(expected, rel=1e-6, abs=1e-9)
    assert st_alex.distance((a * 255).astype(np.uint8), (a * 255).astype(np.uint8)) == pytest.approx(0.0, abs=1e-7)


# ---------------------------------------------------------------------------------------------
# VGG19 (random weights in torchvision's layout: the computation, not the values, is checked)
# ---------------------------------------------------------------------------------------------

_VGG19_CONFIG = (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512)


def _torchvision_vgg19_features() -> nn.Sequential:
    """torchvision's VGG19 ``features`` layout, written out independently of the module."""
    layers, c = [], 3
    for v in _VGG19_CONFIG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU()]
            c = v
    return nn.Sequential(*layers)


@pytest.fixture(scope="module")
def vgg19(tmp_path_factory):
    torch.manual_seed(12)
    features = _torchvision_vgg19_features()
    path = tmp_path_factory.mktemp("vgg19") / "vgg19-fake.pth"
    torch.save({f"features.{k}": v for k, v in features.state_dict().items()}, path)
    return VGG19Loss(path), features


def _vgg19_concatenated(features: nn.Sequential, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The plain computation: both images normalised with the ImageNet mean / std in one batch,
    mean L1 distance of the relu1_2, relu3_1, relu5_1 activations."""
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    x = (torch.cat([pred, target]) - mean) / std
    b = pred.shape[0]
    losses = []
    for i, layer in enumerate(features[:30]):
        x = layer(x)
        if i in (3, 11, 29):
            losses.append(F.l1_loss(x[:b], x[b:]))
    return sum(losses) / 3


def test_vgg19_loss_and_pred_gradient_equal_the_concatenated_computation(vgg19):
    module, features = vgg19
    pred, target = _pair(4, (1, 3, 32, 32))
    p_new, p_ref = pred.clone().requires_grad_(True), pred.clone().requires_grad_(True)
    loss, saved = _saved_numel(lambda: module(p_new, target), module)
    ref, saved_ref = _saved_numel(lambda: _vgg19_concatenated(features, p_ref, target), features)
    loss.backward()
    ref.backward()
    assert float(ref.detach()) > 0
    torch.testing.assert_close(loss, ref, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(p_new.grad, p_ref.grad, rtol=1e-4, atol=1e-9)
    assert saved < 0.6 * saved_ref, (saved, saved_ref)
