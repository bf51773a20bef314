"""Point tables (model/column/point_tables.py): the tabulated homogeneous model against the exact one it
stands for (value and Jacobian, diffusion and transport), and the closed-form absorption Jacobian
against forward-mode autodiff of Eq. 11–12."""

from __future__ import annotations

import pytest
import torch
import torch.autograd.forward_ad as fwAD

from skinlayers.model import N_PARAMS, ModelSettings, SkinModel, SkinParams, parameter_bounds
from skinlayers.model.optics.params import layer_absorption, layer_absorption_jacobian
from skinlayers.model.column.point_tables import POINT_TABLE_NODES, PointTables


def random_params(n: int, seed: int) -> torch.Tensor:
    """Parameters spread over the whole box: concentrations log-uniform from a floor to the upper
    bound (skin spans decades), β_m uniform."""
    _, hi = parameter_bounds(torch.float64)
    floor = torch.tensor([1e-3, 1.0, 1e-4, 1e-5, 1e-4], dtype=torch.float64)  # β_m is replaced below
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, N_PARAMS, generator=g, dtype=torch.float64)
    p = floor * (hi / floor) ** u
    p[:, 1] = hi[1] * u[:, 1]  # β_m is a fraction in [0, 1]
    return p


def exact_jacobian(model: SkinModel, p: torch.Tensor, wl: torch.Tensor) -> torch.Tensor:
    """∂R_d/∂p ``(M, L, N_PARAMS)`` of the exact model, one forward-mode pass per parameter."""
    columns = []
    for j in range(N_PARAMS):
        with fwAD.dual_level():
            dual = fwAD.make_dual(p, torch.nn.functional.one_hot(torch.full((p.shape[0],), j), N_PARAMS).to(p))
            columns.append(fwAD.unpack_dual(model.diffuse_reflectance(SkinParams.from_tensor(dual), wl)).tangent)
    return torch.stack(columns, -1)


@pytest.mark.parametrize("settings, wl, nodes, r_tol, jac_tol", [
    (ModelSettings(), torch.arange(400.0, 701.0, 15.0), POINT_TABLE_NODES, 5e-6, 1e-4),
    (ModelSettings(profiles="transport"), torch.tensor([470.0, 560.0, 650.0]), 24, 1e-4, 5e-3),
])
def test_tables_match_the_exact_model(settings, wl, nodes, r_tol, jac_tol):
    """R_d and its Jacobian from the tables against the exact model at random skins over the whole
    box. Measured (300 skins): diffusion, 21 bands, 48 nodes: R max relative error 1.1e-6, Jacobian
    1.7e-5 of each column's scale; transport, 3 bands, 24 nodes: 2.4e-5 and 1.7e-3. The transport
    model's own totals are read from adding-doubling tables, so its exact Jacobian is that of an
    interpolant, with kinks a smooth table cannot follow: more nodes barely help (48: 1.3e-5, 9e-4)."""
    model = SkinModel(settings)
    wl = wl.to(torch.float64)
    tables = PointTables.build(model, wl, nodes=nodes)
    p = random_params(300, seed=3)
    exact = model.diffuse_reflectance(SkinParams.from_tensor(p), wl)
    r, jac = tables.diffuse_reflectance(p)
    assert float(((r - exact).abs() / exact).max()) < r_tol
    ref = exact_jacobian(model, p, wl)
    scale = ref.abs().amax(dim=(0, 1))  # each parameter's column scale
    assert float(((jac - ref).abs() / scale).max()) < jac_tol


def test_coarser_tables_are_less_accurate():
    """The interpolation error shrinks with the nodes (fourth order: ≈ 16× per doubling), so the test
    above measures the tables and not a fallback to the exact model."""
    model = SkinModel()
    wl = torch.tensor([420.0, 545.0, 610.0], dtype=torch.float64)
    p = random_params(300, seed=5)
    exact = model.diffuse_reflectance(SkinParams.from_tensor(p), wl)
    errors = [float(((PointTables.build(model, wl, nodes=s).diffuse_reflectance(p)[0] - exact).abs() / exact).max())
              for s in (8, 16)]
    assert errors[1] < errors[0] / 6, errors
    assert errors[0] > 1e-6


def test_absorption_jacobian_matches_forward_mode():
    """Eq. 11–12's derivatives in closed form against forward-mode autodiff."""
    model = SkinModel()
    wl = torch.arange(450.0, 651.0, 50.0, dtype=torch.float64)
    spectra = model.spectra(wl)
    o = model.settings.optics
    p = random_params(7, seed=9)
    jac = layer_absorption_jacobian(SkinParams.from_tensor(p), spectra, o.interface_melanin_fraction, o.epidermis_thickness_mm)
    assert jac.shape == (3, 7, wl.numel(), N_PARAMS)
    for j in range(N_PARAMS):
        with fwAD.dual_level():
            dual = fwAD.make_dual(p, torch.nn.functional.one_hot(torch.full((7,), j), N_PARAMS).to(p))
            ab = layer_absorption(SkinParams.from_tensor(dual), spectra, o.interface_melanin_fraction, o.epidermis_thickness_mm)
            ref = torch.stack([fwAD.unpack_dual(t).tangent for t in (ab.epidermis, ab.dermis, ab.interface_absorbance)])
        torch.testing.assert_close(jac[..., j], ref, rtol=1e-12, atol=1e-15)


def test_tables_are_cached_per_bands_and_device():
    model = SkinModel()
    wl = torch.tensor([500.0, 600.0], dtype=torch.float64)
    first = model.point_tables(wl)
    assert model.point_tables(wl.clone()) is first
    assert model.point_tables(torch.tensor([500.0, 610.0], dtype=torch.float64)) is not first
    with pytest.raises(ValueError, match="at least 4 nodes"):
        PointTables.build(model, wl, nodes=3)
