"""Each map's grid from the cube's information (``reconstruct/choice/grid_choice.py``): the Fourier-domain
Cramér–Rao bound against the dense Fisher matrix it stands for, the noise estimator against noise of a
known σ, and the C_p bias against maps of known detail."""

from __future__ import annotations

import pytest
import torch

from skinlayers.reconstruct.choice.grid_choice import PATCH, PER_PIXEL, band_noise, crb_pixel_variance, smoothing_bias
from skinlayers.reconstruct.levels.grids import MapGrid


def _basis(spacing, m: int) -> list[torch.Tensor]:
    """Every unknown's image on the periodic m² patch (the rule crb_pixel_variance states)."""
    if spacing == PATCH:
        return [torch.ones(m, m, dtype=torch.float64)]
    if spacing == PER_PIXEL:
        out = []
        for i in range(m * m):
            e = torch.zeros(m * m, dtype=torch.float64)
            e[i] = 1.0
            out.append(e.reshape(m, m))
        return out
    d = torch.arange(m, dtype=torch.float64)
    out = []
    for iy in range(m // spacing):
        for ix in range(m // spacing):
            cy, cx = spacing * iy + (spacing - 1) / 2, spacing * ix + (spacing - 1) / 2
            dy = torch.minimum((d - cy) % m, (cy - d) % m)
            dx = torch.minimum((d - cx) % m, (cx - d) % m)
            out.append((1 - dy / spacing).clamp_min(0)[:, None] * (1 - dx / spacing).clamp_min(0)[None, :])
    return out


def _dense_variance(kernels: torch.Tensor, noise: torch.Tensor, spacing: list) -> torch.Tensor:
    n_maps, bands, m, _ = kernels.shape
    columns, owner = [], []
    for k in range(n_maps):
        if spacing[k] is None:
            continue
        for b in _basis(spacing[k], m):
            img = torch.fft.ifft2(torch.fft.fft2(kernels[k]) * torch.fft.fft2(b)).real  # (L, m, m) circular
            columns.append((img / noise[:, None, None]).reshape(-1))
            owner.append((k, b))
    jac = torch.stack(columns, 1)
    cov = torch.linalg.inv(jac.T @ jac)
    var = torch.full((n_maps,), float("inf"), dtype=torch.float64)
    for k in range(n_maps):
        idx = [i for i, (q, _) in enumerate(owner) if q == k]
        if not idx:
            continue
        u = torch.stack([owner[i][1].reshape(-1) for i in idx], 1)  # (m², n_k)
        var[k] = torch.trace(u @ cov[idx][:, idx] @ u.T) / m**2
    return var


@pytest.mark.parametrize("spacing", [
    [PER_PIXEL, PER_PIXEL, PER_PIXEL], [PER_PIXEL, 2, None], [PER_PIXEL, 4, PATCH], [2, 4, PER_PIXEL],
    [PATCH, PER_PIXEL, 2], [2, 2, PATCH], [4, PATCH, None],
])
def test_fourier_bound_is_the_dense_fisher_bound(spacing):
    g = torch.Generator().manual_seed(3)
    m, bands = 8, 4
    kernels = torch.randn(3, bands, m, m, generator=g, dtype=torch.float64)
    kernels[:, :, 0, 0] += 6.0  # each map's own pixel answers most, as in skin
    noise = 0.5 + torch.rand(bands, generator=g, dtype=torch.float64)
    fast = crb_pixel_variance(kernels, noise, spacing)
    dense = _dense_variance(kernels, noise, spacing)
    for k in range(3):
        if spacing[k] is None:
            assert fast[k] == float("inf")
        else:
            assert abs(float(fast[k]) / float(dense[k]) - 1) < 1e-8, (k, float(fast[k]), float(dense[k]))


def test_coarser_nodes_are_better_determined():
    g = torch.Generator().manual_seed(4)
    kernels = torch.randn(2, 3, 16, 16, generator=g, dtype=torch.float64) * 0.2
    kernels[:, :, 0, 0] += 3.0
    noise = torch.ones(3, dtype=torch.float64)
    var = [float(crb_pixel_variance(kernels, noise, [PER_PIXEL, s])[1]) for s in (PER_PIXEL, 2, 4, 8, PATCH)]
    assert all(a > b for a, b in zip(var, var[1:])), var


def test_noise_estimate_of_known_white_noise_on_a_scene():
    g = torch.Generator().manual_seed(5)
    h = w = 96
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64), torch.linspace(0, 1, w, dtype=torch.float64), indexing="ij")
    scene = 0.3 + 0.1 * xx + 0.05 * torch.sin(6 * yy) + 0.1 * (xx > 0.5)  # ramp, shading, an edge
    sigma = torch.tensor([0.002, 0.005, 0.01], dtype=torch.float64)
    cube = scene[None] + sigma[:, None, None] * torch.randn(3, h, w, generator=g, dtype=torch.float64)
    est = band_noise(cube, torch.ones(h, w, dtype=torch.bool))
    assert torch.allclose(est, sigma, rtol=0.06), est


def test_bias_of_a_map_the_grid_holds_is_zero_and_of_detail_is_its_power():
    g = torch.Generator().manual_seed(6)
    h = w = 32
    grid = MapGrid.build((h, w), (4, 4), torch.float64)
    smooth = grid.up(torch.randn(16, generator=g, dtype=torch.float64))
    noise_sd = 0.1
    mask = torch.ones(h, w, dtype=torch.bool)
    noisy = smooth + noise_sd * torch.randn(h, w, generator=g, dtype=torch.float64)
    assert smoothing_bias(noisy, mask, (4, 4), noise_sd**2) < 0.1 * noise_sd**2
    detail = 0.3 * torch.randn(h, w, generator=g, dtype=torch.float64)
    b2 = smoothing_bias(smooth + detail + noise_sd * torch.randn(h, w, generator=g, dtype=torch.float64), mask, (4, 4), noise_sd**2)
    assert 0.7 * 0.09 < b2 < 1.1 * 0.09, b2
    assert smoothing_bias(noisy, mask, (h, w), noise_sd**2) == 0.0


def test_auto_grids_fit_says_what_it_considered_and_takes_the_least_risk(small_cube):
    from skinlayers.reconstruct.mapfit.fit import fit_cube
    from skinlayers.reconstruct.settings import FitSettings

    fit = fit_cube(small_cube.cube, FitSettings(map_grids="auto"))
    choice = fit.grid_choice
    assert choice is not None and set(choice["candidates"]) == {"C_m", "beta_m", "C_he", "C_bc", "C_hd"}
    for name, rows in choice["candidates"].items():
        best = min(rows, key=lambda r: r["risk"])
        assert best["chosen"] and sum(r["chosen"] for r in rows) == 1
        assert choice["cells_mm"][name] == best["cell_mm"]
    grids = fit.levels[-1]["map_grids"]
    for name, cell in choice["cells_mm"].items():
        assert (grids[name] == "pixel") == (cell == 0.0), (name, cell, grids[name])
    assert float(fit.residual_rms.median()) < 0.01  # the fit on the chosen grids still fits


def test_auto_grids_need_a_node_method():
    from skinlayers.reconstruct.settings import FitSettings

    with pytest.raises(ValueError, match="map_grids"):
        FitSettings(method="adam", map_grids="auto")
