"""The blur passes in cache-sized slabs give the whole pass's result, and its gradient."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model.render import blur
from skinlayers.model.render.blur import BlurPlan, blur_stack


@pytest.fixture
def slabs(monkeypatch):
    """Every pass of more than 4 kB in slabs of 1 kB: a few lines each, ragged last slab."""
    monkeypatch.setattr(blur, "PASS_SLAB_ABOVE_BYTES", 4096)
    monkeypatch.setattr(blur, "PASS_SLAB_BYTES", 1024)


@pytest.mark.parametrize("dim", [-1, -2])
def test_a_pass_in_slabs_equals_the_whole_pass(slabs, dim):
    taps = blur._kernel_np(9.0)
    r = (taps.size - 1) // 2
    x = torch.rand(2, 61 + 2 * r, 83 + 2 * r, dtype=torch.float64)
    whole = blur._sums(x, taps, r, dim % 3)
    sliced = blur._symmetric_sums(x, taps, r, dim)
    assert sliced.shape == whole.shape
    assert torch.equal(sliced, whole)


def test_the_stack_and_its_gradient_are_the_same_in_slabs(monkeypatch):
    plan = BlurPlan.build(torch.tensor([0.001, 0.01, 0.05, 0.4]), 0.05, "pyramid", boundary="zero")
    x = torch.rand(3, 40, 52, dtype=torch.float64)
    weights = torch.rand(len(plan.blurred), 3, 40, 52, dtype=torch.float64)

    def stack_and_grad():
        leaf = x.clone().requires_grad_(True)
        loss = sum((w * b).sum() for w, b in zip(weights, blur_stack(leaf, plan)))
        (grad,) = torch.autograd.grad(loss, leaf)
        with torch.no_grad():
            images = torch.stack(list(blur_stack(x, plan)))
        return images, grad

    whole = stack_and_grad()
    monkeypatch.setattr(blur, "PASS_SLAB_ABOVE_BYTES", 4096)
    monkeypatch.setattr(blur, "PASS_SLAB_BYTES", 1024)
    sliced = stack_and_grad()
    assert torch.allclose(sliced[0], whole[0], rtol=0, atol=1e-14)
    assert torch.allclose(sliced[1], whole[1], rtol=0, atol=1e-14)


def test_gradcheck_of_a_pass_in_slabs(slabs):
    taps = blur._kernel_np(4.0)
    r = (taps.size - 1) // 2
    x = torch.rand(1, 12 + 2 * r, 30, dtype=torch.float64, requires_grad=True)
    assert x.numel() * 8 > blur.PASS_SLAB_ABOVE_BYTES
    assert torch.autograd.gradcheck(lambda t: blur._symmetric_pass(t, taps, r, -2), (x,))
