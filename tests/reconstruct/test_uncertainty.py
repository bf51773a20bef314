"""The terms that widen σ beyond the noise's share (``reconstruct/diagnosis/uncertainty.py``, ``schur.marginal_variance``
with clusters), each against a case whose answer is known by construction."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model import N_PARAMS, PARAMETER_NAMES
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.reconstruct.mapfit.gauss_newton import curvature_and_columns
from skinlayers.reconstruct.levels.grids import MapLayout
from skinlayers.reconstruct.levels.problem import LevelProblem
from skinlayers.reconstruct.levels.schur import marginal_variance
from skinlayers.reconstruct.diagnosis.uncertainty import crosstalk_ratio, subnode_sd
from skinlayers.reconstruct.levels.unknowns import Level, from_params

CELLS = {"C_m": 0.0, "beta_m": 1.5, "C_he": 0.0, "C_bc": 100.0, "C_hd": 0.375}


def _problem(syn, cells=CELLS) -> LevelProblem:
    cube = syn.cube
    level = Level(cube.reflectance, cube.mask, cube.mm_per_pixel)
    return LevelProblem(SkinRenderer(), level, cube.wavelength_nm, torch.ones(cube.shape[0], dtype=torch.bool),
                        view_angle_deg=30.0, border_mm=3.0, band_fwhm_nm=10.0, map_cell_mm=cells)


def _truth_x(syn) -> torch.Tensor:
    return from_params(torch.stack([getattr(syn.truth, n)[0] for n in PARAMETER_NAMES]).float())


def test_crosstalk_ratio_falls_as_pixels_shrink_below_the_light_spread(synthetic):
    """A pixel's own share of its response to its own maps. Melanin's about half at any pixel size (it
    darkens the light leaving through the pixel; the light that entered through it leaves mostly
    through its neighbours: measured 0.61 at 0.47 mm, 0.54 at 0.12 mm); dermal blood's, whose light
    spreads furthest, falls with the pixel (0.59 and 0.14)."""
    rho = {}
    for size in (16, 64):
        syn = synthetic.make_cube(size, seed=3, features=False, variation=0.0, noise=0.0, blur="pyramid", fine=1)
        problem = _problem(syn)
        ev = problem.evaluate(_truth_x(syn), torch.zeros(()))
        jac, _ = curvature_and_columns(problem, ev)
        rho[size] = crosstalk_ratio(problem, ev, jac)
    cm, hd = PARAMETER_NAMES.index("C_m"), PARAMETER_NAMES.index("C_hd")
    assert float(rho[16][hd]) > float(rho[64][hd]) + 0.25, rho
    assert float(rho[64][hd]) < float(rho[64][cm]), rho
    assert all(0.4 < float(rho[size][cm]) < 0.8 for size in rho), rho


def test_subnode_spread_is_found_where_the_residual_carries_it_and_not_in_noise(synthetic):
    """Residuals made of a known deviation of β_m along each pixel's own direction plus white noise: the
    spread found is the deviation's size; from the noise alone it is near zero."""
    syn = synthetic.make_cube(32, seed=5, features=False, variation=0.0, noise=0.0, blur="pyramid", fine=1)
    problem = _problem(syn)
    n, bands = problem.n_pixels, syn.cube.shape[0]
    g = torch.Generator().manual_seed(7)
    jac = torch.randn(n, bands, N_PARAMS, generator=g, dtype=torch.float64)
    sd_band = torch.full((bands,), 0.01, dtype=torch.float64)
    noise = 0.01 * torch.randn(n, bands, generator=g, dtype=torch.float64)
    k = PARAMETER_NAMES.index("beta_m")
    deviation = 0.05 * (torch.randint(0, 2, (n,), generator=g) * 2 - 1).double()  # x units
    ones, dpdx = torch.ones(N_PARAMS, dtype=torch.float64), torch.ones(n, N_PARAMS, dtype=torch.float64)
    # the residual a deviation leaves once the pixel's own maps took what they can: project them out
    own = jac[..., problem.layout.fine]
    signal = jac[..., k] * deviation[:, None]
    coef = torch.linalg.solve(own.transpose(1, 2) @ own, own.transpose(1, 2) @ signal[..., None])
    signal = signal - (own @ coef)[..., 0]
    found = subnode_sd(problem, jac, signal + noise, sd_band, ones, dpdx)[:, k]
    quiet = subnode_sd(problem, jac, noise, sd_band, ones, dpdx)[:, k]
    assert abs(float(found.median()) - 0.05) < 0.01, float(found.median())
    assert float(quiet.median()) < 0.01, float(quiet.median())
    assert bool((subnode_sd(problem, jac, noise, sd_band, ones, dpdx)[:, problem.layout.fine] == 0).all())


def test_cluster_robust_node_variance_grows_with_a_correlated_residual():
    """Nodes' variance: with white residuals the plain inverse Fisher information (the robust sandwich
    is no larger on average); with residuals shared within each cluster (model error, correlated in
    space) it grows by about the square root of the pixels per cluster, as it must."""
    layout = MapLayout((32, 32), 0.1, {"C_m": 0.0, "beta_m": 1.6, "C_he": 0.0, "C_bc": 3.2, "C_hd": 0.8})
    pixels = torch.arange(32 * 32)
    g = torch.Generator().manual_seed(11)
    # skin alike from pixel to pixel: Jacobians close to one another (as in a real patch)
    jac = torch.randn(1, 9, N_PARAMS, generator=g, dtype=torch.float64) + 0.2 * torch.randn(pixels.numel(), 9, N_PARAMS, generator=g, dtype=torch.float64)
    col = torch.zeros(pixels.numel(), 9, dtype=torch.float64)
    clusters = (pixels // 32 // 8) * 4 + (pixels % 32) // 8  # 8×8-pixel squares
    plain = marginal_variance(jac, col, False, layout, pixels)
    white = marginal_variance(jac, col, False, layout, pixels, torch.randn(pixels.numel(), 9, generator=g, dtype=torch.float64), clusters)
    shared = torch.randn(16, 9, generator=g, dtype=torch.float64)[clusters]
    correlated = marginal_variance(jac, col, False, layout, pixels, shared, clusters)
    hd = PARAMETER_NAMES.index("C_hd")
    assert torch.allclose(plain[:, layout.fine], white[:, layout.fine], rtol=0.5)
    assert float((white[:, hd] / plain[:, hd]).median()) < 2.0
    assert float((correlated[:, hd] / plain[:, hd]).median()) > 8.0


@pytest.mark.parametrize("cells", [{"C_m": 0.0, "beta_m": 0.8, "C_he": 0.0, "C_bc": 100.0, "C_hd": 0.4},
                                   dict.fromkeys(PARAMETER_NAMES, 100.0)], ids=["pixels and nodes", "every map one value"])
def test_marginal_variance_is_the_dense_inverse_fisher_information(cells):
    """Each pixel's variance from the Schur elimination equals the diagonal of the dense (JᵀJ)⁻¹ over
    every unknown at once (each pixel's own maps, every node, the scale), mapped onto the pixel by the
    bilinear weights: with maps per pixel and on nodes, and with every map one value (uniform skin)."""
    size = 8
    layout = MapLayout((size, size), 0.1, cells)
    pixels = torch.arange(size * size)
    g = torch.Generator().manual_seed(5)
    n, bands = pixels.numel(), 9
    jac = torch.randn(n, bands, N_PARAMS, generator=g, dtype=torch.float64)
    col = torch.rand(n, bands, generator=g, dtype=torch.float64) + 0.5
    var = marginal_variance(jac, col, True, layout, pixels)
    n_f, fine = len(layout.fine), layout.fine
    columns = n * n_f + layout.n_nodes + 1
    dense = torch.zeros(n * bands, columns, dtype=torch.float64)
    idx, wts = layout.local(pixels)
    for p in range(n):
        rows = slice(p * bands, (p + 1) * bands)
        dense[rows, p * n_f:(p + 1) * n_f] = jac[p][:, fine]
        for q, k in enumerate(layout.coarse):
            for c in range(4):
                dense[rows, n * n_f + idx[p, 4 * q + c]] += jac[p, :, k] * wts[p, 4 * q + c].double()
        dense[rows, -1] = col[p]
    cov = torch.linalg.inv(dense.T @ dense)
    # 1e-7: ``least_squares.block_factor`` adds 1e-9 to the Jacobi-scaled blocks' diagonal (measured 1.1e-9 apart)
    for p in range(n):
        for j, k in enumerate(fine):
            torch.testing.assert_close(var[p, k], cov[p * n_f + j, p * n_f + j], rtol=1e-7, atol=0)
        for q, k in enumerate(layout.coarse):
            nodes = n * n_f + idx[p, 4 * q: 4 * q + 4]
            w = wts[p, 4 * q: 4 * q + 4].double()
            torch.testing.assert_close(var[p, k], w @ cov[nodes][:, nodes] @ w, rtol=1e-7, atol=0)


def test_the_floor_rule_covers_the_share_it_is_set_for():
    """``floor_for_coverage``: the floor it returns, added in quadrature to σ's data terms, puts the share of
    pixels within ±2σ it was asked for; with no data terms it is the error's quantile over twice the scale."""
    from skinlayers.reconstruct.diagnosis.uncertainty import floor_for_coverage

    g = torch.Generator().manual_seed(3)
    error = torch.rand(4000, generator=g, dtype=torch.float64) * 0.2
    scale = 0.5 + torch.rand(4000, generator=g, dtype=torch.float64)
    data_sd = torch.rand(4000, generator=g, dtype=torch.float64) * 0.03
    shipped = 0.02
    sigma = torch.sqrt(data_sd**2 + (shipped * scale) ** 2)
    data, floor = floor_for_coverage(error, sigma, shipped, scale, 0.9)
    assert torch.allclose(data, data_sd)
    covered = (error <= 2 * torch.sqrt(data**2 + (floor * scale) ** 2)).double().mean()
    assert 0.9 <= float(covered) <= 0.905
    _, bare = floor_for_coverage(error, shipped * scale, shipped, scale, 0.9)
    assert bare == pytest.approx(float(torch.quantile(error / 2 / scale, 0.9)))
