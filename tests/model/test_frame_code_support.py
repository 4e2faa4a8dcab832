"""Sparse per-frame codes (:mod:`garmentnerf.model.frame_codes`): the footprint of bilinear reads
against grid_sample's own gradient, the grown support against scipy's dilation, and sparse codes
against the dense ones they were resampled from."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy import ndimage

from garmentnerf.model.frame_codes import FrameCodes, adapt_frame_codes, garment_texels, grow_texels, resample_codes
from garmentnerf.model.uv_maps import sample_uv_map


def test_garment_texels_are_those_a_bilinear_read_weighs():
    """The reference: the texels of a map that get a gradient when it is read at the points
    (sample_uv_map, the field's own read), border texels included."""
    gen = torch.Generator().manual_seed(0)
    r = 16
    uv = torch.cat([torch.rand(40, 2, generator=gen, dtype=torch.float64),
                    torch.tensor([[0.01, 0.5], [0.995, 0.999], [0.5, 0.02]], dtype=torch.float64)])
    values = torch.zeros(r, r, 1, dtype=torch.float64, requires_grad=True)
    sample_uv_map(values, uv).sum().backward()
    reference = values.grad[..., 0] != 0
    assert torch.equal(garment_texels(uv, r), reference)
    assert 40 < int(reference.sum()) < r * r


@pytest.mark.parametrize("margin", [0, 1, 3])
def test_grow_texels_is_a_dilation_by_a_square(margin):
    gen = torch.Generator().manual_seed(margin)
    mask = torch.rand(20, 20, generator=gen) > 0.97
    mask[0, 0] = mask[19, 10] = True  # at the border too
    reference = ndimage.binary_dilation(mask.numpy(), structure=np.ones((3, 3), bool), iterations=margin) \
        if margin else mask.numpy()
    np.testing.assert_array_equal(grow_texels(mask, margin).numpy(), reference)


def _sparse_from(dense: torch.Tensor, support: torch.Tensor) -> FrameCodes:
    """A sparse FrameCodes on ``support`` loaded from a file holding the dense codes ``dense``."""
    count, channels = dense.shape[:2]
    codes = FrameCodes(count, channels, support.shape[-1], sparse=True)
    codes.set_support(support)
    state = {"frame_codes.codes": dense.clone()}
    changed = adapt_frame_codes(state, {f"frame_codes.{k}": v for k, v in codes.state_dict().items()})
    assert changed == ["frame_codes.codes", "frame_codes.support"]
    codes.adopt_state(state, "frame_codes.")
    codes.load_state_dict({"codes": state["frame_codes.codes"], "support": state["frame_codes.support"]})
    return codes


def test_sparse_codes_compute_the_dense_codes_they_came_from_on_their_support():
    gen = torch.Generator().manual_seed(1)
    dense = torch.randn(3, 2, 8, 8, generator=gen)
    support = torch.rand(16, 16, generator=gen) > 0.6
    codes = _sparse_from(dense, support)
    assert codes.codes.shape == (3, 2, int(support.sum()))
    # at its own resolution: the dense codes upsampled as FrameCodes.forward upsamples, zero off the support
    reference = F.interpolate(dense, size=(16, 16), mode="bilinear", align_corners=False)
    out = codes(1, 16)
    torch.testing.assert_close(out[:, support], reference[1][:, support])
    assert torch.count_nonzero(out[:, ~support]) == 0
    # at E's resolution: upsampled from the support-restricted code
    torch.testing.assert_close(codes(1, 32), F.interpolate(out[None], size=(32, 32), mode="bilinear",
                                                           align_corners=False)[0])
    # the gradient reaches exactly the support's texels of the code drawn
    weights = torch.randn(2, 16, 16, generator=gen)
    (codes(2, 16) * weights).sum().backward()
    torch.testing.assert_close(codes.codes.grad[2], weights[:, support])
    assert torch.count_nonzero(codes.codes.grad[[0, 1]]) == 0
    with pytest.raises(ValueError, match="out of range"):
        codes(3, 16)


def test_codes_move_between_layouts_and_resolutions():
    gen = torch.Generator().manual_seed(2)
    dense = torch.randn(2, 3, 4, 4, generator=gen)
    support = torch.rand(8, 8, generator=gen) > 0.5
    sparse = _sparse_from(dense, support)
    file_state = {f"frame_codes.{k}": v.detach().clone() for k, v in sparse.state_dict().items()}
    # the same support: nothing to change
    same = dict(file_state)
    assert adapt_frame_codes(same, {f"frame_codes.{k}": v for k, v in sparse.state_dict().items()}) == []
    # into dense codes at the file's resolution: the sparse values in place, zero elsewhere
    to_dense = dict(file_state)
    assert adapt_frame_codes(to_dense, {"frame_codes.codes": torch.zeros(2, 3, 8, 8)}) == ["frame_codes.codes"]
    assert "frame_codes.support" not in to_dense
    torch.testing.assert_close(to_dense["frame_codes.codes"][1], sparse(1, 8).detach())
    # into another support: the values of the texels both hold are kept
    other = torch.rand(8, 8, generator=gen) > 0.5
    moved = _sparse_from(to_dense["frame_codes.codes"], other)
    both = support & other
    torch.testing.assert_close(moved(0, 8)[:, both], sparse(0, 8).detach()[:, both])
    # dense into dense of the same shape: untouched; of another count: left for the shape check to refuse
    assert adapt_frame_codes({"frame_codes.codes": dense}, {"frame_codes.codes": torch.zeros(2, 3, 4, 4)}) == []
    assert adapt_frame_codes({"frame_codes.codes": dense}, {"frame_codes.codes": torch.zeros(5, 3, 8, 8)}) == []
    torch.testing.assert_close(resample_codes(dense, 4), dense)
    with pytest.raises(ValueError, match="support of shape"):
        FrameCodes(2, 3, 8, sparse=True).set_support(torch.ones(4, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="dense per-frame codes"):
        FrameCodes(2, 3, 8).set_support(support)
