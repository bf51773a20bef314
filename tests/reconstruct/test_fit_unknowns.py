"""The fit's unknowns: bounded reparameterisation, the extension onto masked pixels, the pyramid."""

from __future__ import annotations

import torch

from skinlayers.model import PARAMETER_BOUNDS, PARAMETER_NAMES
from skinlayers.reconstruct.levels.unknowns import (
    X_LIMIT,
    dparams_dx,
    extend,
    extension_index,
    from_params,
    pyramid,
    to_params,
    upsample,
)


def test_parameters_stay_within_bounds_for_any_x():
    x = torch.linspace(-50, 50, 101, dtype=torch.float64).expand(5, 101).clone()
    p = to_params(x)
    for i, n in enumerate(PARAMETER_NAMES):
        lo, hi = PARAMETER_BOUNDS[n]
        assert float(p[i].min()) >= lo and float(p[i].max()) <= hi


def test_round_trip_and_log_like_small_values():
    p = torch.tensor([[1e-4, 0.3, 0.001, 0.0005, 0.004], [0.04, 0.9, 0.02, 0.01, 0.05]], dtype=torch.float64).T
    back = to_params(from_params(p))
    assert torch.allclose(back, p, rtol=1e-9, atol=0)
    # logarithmic where skin lives: a unit step in x multiplies a small concentration by ≈ e
    x = from_params(torch.tensor([1e-4, 0.5, 1e-4, 1e-4, 1e-4], dtype=torch.float64).view(5, 1))
    ratio = to_params(x + 1.0) / to_params(x)
    assert abs(float(ratio[0]) - torch.e) < 0.01 * torch.e


def test_derivative_matches_finite_difference():
    x = torch.tensor([-6.0, 0.3, -2.0, -4.0, 1.0], dtype=torch.float64).view(5, 1)
    h = 1e-6
    fd = (to_params(x + h) - to_params(x - h)) / (2 * h)
    assert torch.allclose(dparams_dx(x), fd, rtol=1e-6)


def test_from_params_clamps_bounds():
    p = torch.tensor([0.0, 1.0, 0.05, 0.0, 0.1], dtype=torch.float64).view(5, 1)
    x = from_params(p)
    assert float(x.abs().max()) == X_LIMIT
    assert float(from_params(p, limit=6.0).abs().max()) == 6.0


def test_extension_copies_the_nearest_visible_pixel_and_routes_gradients():
    mask = torch.zeros(6, 7, dtype=torch.bool)
    mask[2:4, 3:5] = True
    idx = extension_index(mask)
    x = torch.arange(6 * 7, dtype=torch.float64).view(1, 6, 7).requires_grad_(True)
    y = extend(x, idx)
    # every pixel takes a visible pixel's value; visible pixels keep their own
    assert bool(mask.reshape(-1)[idx].all())
    assert torch.equal(y[0][mask], x[0][mask])
    assert float(y[0, 0, 0].detach()) == float(x[0, 2, 3].detach())  # top-left corner → nearest visible (2, 3)
    assert float(y[0, 5, 6].detach()) == float(x[0, 3, 4].detach())
    y.sum().backward()
    assert float(x.grad[0][~mask].abs().sum()) == 0.0
    assert float(x.grad.sum()) == 6 * 7  # every pixel's value came from exactly one visible pixel


def test_extension_refuses_an_empty_mask():
    import pytest

    with pytest.raises(ValueError, match="no visible pixel"):
        extension_index(torch.zeros(4, 4, dtype=torch.bool))


def test_pyramid_halves_keeps_window_size_and_masks_partial_cells():
    target = torch.rand(3, 32, 32)
    mask = torch.ones(32, 32, dtype=torch.bool)
    mask[0] = False
    levels = pyramid(target, mask, 0.25, coarsest_px=8)
    assert [lv.shape for lv in levels] == [(8, 8), (16, 16), (32, 32)]
    for lv in levels:
        assert abs(lv.shape[0] * lv.mm_per_pixel - 8.0) < 1e-12
    assert not bool(levels[1].mask[0].any()) and bool(levels[1].mask[1:].all())
    assert torch.allclose(levels[1].target[:, 3, 5], target[:, 6:8, 10:12].mean(dim=(1, 2)))
    assert len(pyramid(target, mask, 0.25, coarsest_px=0)) == 1
    assert len(pyramid(target[:, :31, :31], mask[:31, :31], 0.25, coarsest_px=8)) == 1  # odd: no level


def test_upsample_preserves_constant_maps():
    x = torch.full((5, 4, 4), -3.0)
    assert torch.allclose(upsample(x, (8, 8)), torch.full((5, 8, 8), -3.0))
