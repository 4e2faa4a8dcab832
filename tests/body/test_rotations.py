"""garmentnerf.body.rotations.rotvec_to_rotmat is roma.rotvec_to_rotmat, bit for bit (values and gradients)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from garmentnerf.body.rotations import rotvec_to_rotmat


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rotvec_to_rotmat_is_roma_bit_for_bit(dtype):
    roma = pytest.importorskip("roma")
    gen = torch.Generator().manual_seed(3)
    big = torch.randn(200, 3, generator=gen, dtype=dtype) * 2.0
    small = torch.randn(50, 3, generator=gen, dtype=dtype) * 1e-7  # the first-order branch
    edge = torch.tensor([[0.0, 0.0, 0.0], [1e-6, 0.0, 0.0], [0.0, 0.0, 3.14159265], [-3.0, 2.0, 1.0]], dtype=dtype)
    for rotvec in (torch.cat([big, small, edge]), big.reshape(10, 20, 3), edge[0]):
        ours, theirs = rotvec.clone().requires_grad_(True), rotvec.clone().requires_grad_(True)
        R, R_roma = rotvec_to_rotmat(ours), roma.rotvec_to_rotmat(theirs)
        assert R.shape == R_roma.shape == (*rotvec.shape[:-1], 3, 3)
        assert torch.equal(R, R_roma)
        weights = torch.randn(R.shape, generator=gen, dtype=dtype)
        (R * weights).sum().backward()
        (R_roma * weights).sum().backward()
        assert torch.equal(ours.grad, theirs.grad)


def test_rotation_matrices_are_rotations():
    R = rotvec_to_rotmat(torch.tensor([[0.0, 0.0, torch.pi / 2], [0.3, -0.2, 0.9]], dtype=torch.float64))
    assert torch.allclose(R[0] @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                          torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3), atol=1e-12)
    with pytest.raises(ValueError, match="rotation vectors"):
        rotvec_to_rotmat(torch.zeros(4, 2))


def test_posing_a_body_does_not_import_roma(tmp_path):
    """roma imports torch._dynamo (seconds): the previewer poses a scene's sequence (a saved motion,
    as the bundled demos open on) without it."""
    code = ("import sys, torch; from garmentnerf.body.model import BodyModel; "
            "from garmentnerf.motion.motion import Motion; b = BodyModel.default(); "
            "m = Motion('m', list(b.joint_names), 0.3 * torch.randn(3, b.num_joints, 3), torch.zeros(3, 3), 30.0); "
            f"m.save({str(tmp_path / 'motion.npz')!r}); Motion.load({str(tmp_path / 'motion.npz')!r}).pose(b); "
            "print('roma' in sys.modules, 'torch._dynamo' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "False"], out.stdout
