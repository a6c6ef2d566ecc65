"""render.tiles.depth_order: each view's Gaussians nearest first, ties in index order, by a radix
sort on float32's bits, against torch's stable argsort."""

from __future__ import annotations

import pytest
import torch

from physmorph.render.tiles import depth_order


@pytest.mark.parametrize("n", [0, 1, 7, 5000])
def test_depth_order_is_torchs_stable_argsort(n):
    """Negative and positive depths over many magnitudes, exact ties, -0 beside +0 (equal: index
    order), the extreme finite floats, rows that differ; float64 goes to torch itself."""
    g = torch.Generator().manual_seed(n)
    depth = torch.randn(4, n, generator=g) * torch.logspace(-30, 30, n).flip(0)
    if n >= 7:
        depth[:, n // 2:] = depth[:, :n - n // 2].clone()  # every value twice
        depth[0, :4] = torch.tensor([0.0, -0.0, 0.0, -0.0])
        depth[1, :3] = torch.tensor([torch.finfo(torch.float32).max, torch.finfo(torch.float32).min, 1e-45])
        depth[3] = 2.5  # one value throughout
    order = depth_order(depth)
    assert order.dtype == torch.int32 and order.shape == depth.shape
    assert torch.equal(order.long(), torch.argsort(depth, dim=1, stable=True))
    assert torch.equal(depth_order(depth.double()), torch.argsort(depth.double(), dim=1, stable=True))
