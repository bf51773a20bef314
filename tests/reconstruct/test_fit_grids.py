"""Maps on their own node grids (``reconstruct/levels/grids.py``) and the Schur-complement step (``schur.py``).

References: ``F.interpolate`` for the bilinear operator; the dense least-squares (Gauss–Newton) step
and the dense inverse Fisher information over every unknown — fine maps per pixel, nodes, scale —
assembled column by column, for the eliminated solver.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from skinlayers.model import PARAMETER_NAMES
from skinlayers.reconstruct.levels.grids import MapGrid, MapLayout, node_count
from skinlayers.reconstruct.levels.schur import marginal_variance, solve_split_step
from skinlayers.reconstruct.settings import DEFAULT_MAP_CELL_MM, FitSettings


@pytest.mark.parametrize("shape,nodes", [((64, 64), (16, 16)), ((37, 50), (5, 7)), ((8, 8), (1, 1)), ((10, 12), (10, 3))])
def test_the_grid_interpolates_as_torch_bilinear(shape, nodes):
    g = MapGrid.build(shape, nodes, torch.float64)
    z = torch.randn(nodes[0] * nodes[1], dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    reference = F.interpolate(z.reshape(1, 1, *nodes), size=shape, mode="bilinear", align_corners=False)[0, 0]
    torch.testing.assert_close(g.up(z), reference, rtol=0, atol=1e-12)
    torch.testing.assert_close(g.project(g.up(z)), z, rtol=0, atol=1e-8)
    torch.testing.assert_close(g.weight.sum(1), torch.ones(shape[0] * shape[1], dtype=torch.float64))


def test_node_count_and_bad_grids():
    assert node_count(7.5, 0.375, 256) == 20
    assert node_count(7.5, 100.0, 256) == 1  # larger than the window: one value for the patch
    assert node_count(7.5, 0.01, 64) == 64  # never finer than the pixels
    assert node_count(7.5, 0.0, 64) == 64
    with pytest.raises(ValueError, match="does not fit"):
        MapGrid.build((8, 8), (9, 2))
    with pytest.raises(ValueError, match="unknown map"):
        MapLayout((8, 8), 0.1, {"C_x": 1.0})


def test_layout_assembles_and_projects():
    layout = MapLayout((12, 12), 0.5, {"C_hd": 1.5, "C_bc": 100.0})  # 6 mm: 4×4 nodes and one node
    assert layout.fine == [0, 1, 2] and layout.coarse == [3, 4]
    assert layout.describe()["C_hd"] == [4, 4] and layout.describe()["C_bc"] == [1, 1]
    assert layout.describe()["C_m"] == "pixel" and layout.n_nodes == 17
    x = torch.randn(5, 12, 12)
    z = layout.project(x)
    y = layout.assemble(x, z)
    torch.testing.assert_close(y[:3], x[:3])
    torch.testing.assert_close(y[3], torch.full((12, 12), float(x[3].mean())), atol=1e-5, rtol=0)
    assert torch.allclose(layout.project(y), z, atol=1e-5)
    assert MapLayout((12, 12), 0.5, {"C_hd": 0.5}).per_pixel  # a node per pixel is per pixel
    assert MapLayout((12, 12), 0.5, {"C_hd": 0.9}).per_pixel  # nodes under two pixels apart: per pixel
    assert not MapLayout((12, 12), 0.5, {"C_hd": 1.0}).per_pixel


#: The default's kind of layout (three maps on nodes), and every map on nodes (no per-pixel block at all).
LAYOUTS = {"some on nodes": {"beta_m": 3.0, "C_hd": 2.0, "C_bc": 100.0},
           "all on nodes": {"C_m": 2.0, "beta_m": 3.0, "C_he": 3.0, "C_hd": 2.0, "C_bc": 100.0}}


def _dense_problem(seed=0, free_scale=True, cells=LAYOUTS["some on nodes"]):
    """A small random problem: the per-pixel blocks, the layout, and the dense Jacobian over
    [fine maps of every pixel, nodes, log s] with its residual."""
    gen = torch.Generator().manual_seed(seed)
    h = w = 6
    layout = MapLayout((h, w), 1.0, cells, torch.float64)
    pixels = torch.tensor([i for i in range(h * w) if i not in (7, 20)])  # two pixels out of the loss
    n, bands = pixels.numel(), 9
    jac = torch.randn(n, bands, 5, dtype=torch.float64, generator=gen)
    col = torch.rand(n, bands, dtype=torch.float64, generator=gen) + 0.2
    residual = torch.randn(n, bands, dtype=torch.float64, generator=gen) * 0.1
    nf = len(layout.fine)
    size = nf * n + layout.n_nodes + int(free_scale)
    dense = torch.zeros(n * bands, size, dtype=torch.float64)
    idx, wts = layout.local(pixels)
    for p in range(n):
        rows = slice(p * bands, (p + 1) * bands)
        for q, k in enumerate(layout.fine):
            dense[rows, q * n + p] = jac[p, :, k]
        for q, k in enumerate(layout.coarse):
            for j in range(4):
                dense[rows, nf * n + int(idx[p, 4 * q + j])] += jac[p, :, k] * wts[p, 4 * q + j]
        if free_scale:
            dense[rows, -1] = col[p]
    return layout, pixels, jac, col, residual, dense


@pytest.mark.parametrize("cells", LAYOUTS.values(), ids=LAYOUTS.keys())
@pytest.mark.parametrize("free_scale", [True, False])
def test_the_eliminated_step_is_the_dense_gauss_newton_step(free_scale, cells):
    layout, pixels, jac, col, residual, dense = _dense_problem(free_scale=free_scale, cells=cells)
    n, nf = pixels.numel(), len(layout.fine)
    grad = (jac.transpose(1, 2) @ residual[..., None])[..., 0]
    lam = torch.zeros(n, dtype=torch.float64)
    dx, dz, ds, decrement = solve_split_step(jac, col, grad, (col * residual).sum(1), lam, 0.0, free_scale, layout, pixels)
    step = -torch.linalg.lstsq(dense, residual.reshape(-1, 1)).solution[:, 0]
    for q, k in enumerate(layout.fine):
        torch.testing.assert_close(dx[:, k], step[q * n: (q + 1) * n], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(dz, step[nf * n: nf * n + layout.n_nodes], rtol=1e-5, atol=1e-7)
    if free_scale:
        torch.testing.assert_close(ds, step[-1], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(dx[:, layout.coarse], layout.at_pixels(dz, pixels))
    # the shared unknowns' decrement: bᵀ S⁻¹ b of the dense system reduced onto them
    h, g = dense.T @ dense, dense.T @ residual.reshape(-1)
    f, sh = slice(0, nf * n), slice(nf * n, None)
    x = torch.linalg.solve(h[f, f], torch.cat([h[f, sh], g[f, None]], 1))
    s_red = h[sh, sh] - h[sh, f] @ x[:, :-1]
    b_red = g[sh] - h[sh, f] @ x[:, -1]
    assert math.isclose(decrement, float(b_red @ torch.linalg.solve(s_red, b_red)), rel_tol=1e-5)


def test_damping_shortens_the_step_and_keeps_its_descent():
    layout, pixels, jac, col, residual, _ = _dense_problem(seed=3)
    grad = (jac.transpose(1, 2) @ residual[..., None])[..., 0]
    args = (jac, col, grad, (col * residual).sum(1))
    small = solve_split_step(*args, torch.full((pixels.numel(),), 1e-6, dtype=torch.float64), 1e-6, True, layout, pixels)
    large = solve_split_step(*args, torch.full((pixels.numel(),), 1e3, dtype=torch.float64), 1e3, True, layout, pixels)
    assert large[0].norm() < 0.05 * small[0].norm()
    assert float((large[0] * grad).sum()) < 0.0  # a descent direction of ½‖r‖²


@pytest.mark.parametrize("cells", LAYOUTS.values(), ids=LAYOUTS.keys())
def test_marginal_variance_is_the_dense_inverse_fisher_information(cells):
    layout, pixels, jac, col, _, dense = _dense_problem(seed=5, cells=cells)
    n, nf = pixels.numel(), len(layout.fine)
    cov = torch.linalg.inv(dense.T @ dense)
    var = marginal_variance(jac, col, True, layout, pixels)
    for q, k in enumerate(layout.fine):
        torch.testing.assert_close(var[:, k], cov.diagonal()[q * n: (q + 1) * n], rtol=1e-6, atol=0)
    idx, wts = layout.local(pixels)
    for q, k in enumerate(layout.coarse):
        cols = nf * n + idx[:, 4 * q: 4 * q + 4]
        block = cov[cols[:, :, None], cols[:, None, :]]
        expected = (wts[:, 4 * q: 4 * q + 4, None] * block * wts[:, None, 4 * q: 4 * q + 4]).sum((1, 2))
        torch.testing.assert_close(var[:, k], expected, rtol=1e-6, atol=0)


def test_settings_fill_unnamed_maps_and_refuse_what_cannot_run():
    s = FitSettings(map_cell_mm={"C_hd": 0.5})
    assert set(s.map_cell_mm) == set(PARAMETER_NAMES) and s.map_cell_mm["C_hd"] == 0.5
    with pytest.raises(ValueError, match="unknown map"):
        FitSettings(map_cell_mm={"melanin": 1.0})
    with pytest.raises(ValueError, match="≥ 0"):
        FitSettings(map_cell_mm={"C_hd": -1.0})
    with pytest.raises(ValueError, match="puts C_hd on nodes"):  # only what the user named
        FitSettings(method="adam", map_cell_mm={"C_hd": 0.5})
    assert FitSettings(method="adam", map_cell_mm={"C_m": 0.0}).coarse_maps == []  # unnamed: the method's default
    assert FitSettings(method="adam", map_cell_mm=dict.fromkeys(PARAMETER_NAMES, 0.0)).coarse_maps == []
    assert FitSettings(method="paper-fd").cells == dict.fromkeys(PARAMETER_NAMES, 0.0)  # the paper's per-pixel fit
    assert FitSettings(method="gn").coarse_maps == []
    with pytest.raises(ValueError, match="fits every map per pixel"):
        FitSettings(method="gn", map_cell_mm={"beta_m": 1.0})
    assert FitSettings().cells == DEFAULT_MAP_CELL_MM


def test_a_fit_with_every_map_on_nodes_runs_and_fits(small_cube):
    """No per-pixel unknown at all (every map on 1.5-mm nodes, carotene one value): the step has no
    per-pixel block (once a crash in the block factor and the step's index: the step itself is
    checked against the dense solve above); the fit runs and lowers the loss. How well such a layout
    fits is the layout's question, not the solver's (melanin's freckles do not fit 1.5-mm nodes)."""
    from skinlayers.reconstruct.mapfit.fit import fit_cube

    cells = dict.fromkeys(PARAMETER_NAMES, 1.5) | {"C_bc": 100.0}
    fit = fit_cube(small_cube.cube, FitSettings(map_cell_mm=cells, max_iterations=4))
    losses = [h[1] for h in fit.history]
    assert losses[-1] < 0.5 * losses[0]
    assert all(bool(torch.isfinite(v).all()) for v in fit.maps.params().values())


def test_transport_profiles_take_their_own_node_spacings():
    """gn-hom's spacings follow the model's physics; a file naming some maps keeps that physics' others;
    the per-pixel methods stay per pixel."""
    from skinlayers.reconstruct.settings import TRANSPORT_MAP_CELL_MM

    transport = {"profiles": "transport"}
    assert FitSettings.model_validate({"model": transport}).cells == TRANSPORT_MAP_CELL_MM != DEFAULT_MAP_CELL_MM
    assert FitSettings.model_validate({"model": transport, "map_cell_mm": {"C_hd": 0.75}}).cells == {**TRANSPORT_MAP_CELL_MM, "C_hd": 0.75}
    assert FitSettings.model_validate({"map_cell_mm": {"C_hd": 0.75}}).cells == {**DEFAULT_MAP_CELL_MM, "C_hd": 0.75}
    assert set(FitSettings.model_validate({"model": transport, "method": "gn"}).cells.values()) == {0.0}
