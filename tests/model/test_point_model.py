"""The point model with freed constants: against the model built with those constants in its settings
(an independent path: the constants reach the physics through ``SkinOptics``), its gradients, and the
slab's per-element thickness against one slab at a time."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model import PARAMETER_NAMES, TABLE2, SkinModel, SkinParams, multipole_totals
from skinlayers.model.column.point_model import CONSTANT_NAMES, constant_bounds, constant_defaults, point_reflectance

WL = torch.linspace(400.0, 700.0, 11, dtype=torch.float64)


def table2(rows: int | None = None) -> SkinParams:
    values = list(TABLE2.values())[:rows]
    return SkinParams.from_tensor(torch.tensor([[r[n] for n in PARAMETER_NAMES] for r in values], dtype=torch.float64))


def test_no_constants_and_defaults_are_the_model():
    model, params = SkinModel(), table2()
    b = params.C_m.shape[0]
    defaults = {n: torch.full((b,), v, dtype=torch.float64) for n, v in constant_defaults(model).items()}
    expected = model.diffuse_reflectance(params, WL)
    assert torch.equal(point_reflectance(model, params, WL), expected)
    assert torch.allclose(point_reflectance(model, params, WL, defaults), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("name, values", [
    ("epidermis_thickness_mm", (0.24, 0.31, 0.45)),
    ("oxygenation_dermis", (0.0, 0.35, 1.0)),
    ("dermis_scattering_ratio", (0.2, 1.0, 3.5)),
])
def test_each_constant_per_spectrum_is_the_model_with_that_setting(name, values):
    """Spectrum i with constant value v_i equals the model whose settings hold v_i, to rounding."""
    base = SkinModel()
    params = table2(len(values))
    got = point_reflectance(base, params, WL, {name: torch.tensor(values, dtype=torch.float64)})
    for i, v in enumerate(values):
        optics = base.settings.optics.model_copy(update={name: v})
        other = SkinModel(base.settings.model_copy(update={"optics": optics}))
        one = SkinParams.from_tensor(params.as_tensor()[i:i + 1])
        want = other.diffuse_reflectance(one, WL)[0]
        assert torch.allclose(got[i], want, rtol=1e-13, atol=0), (name, v)
        if v != constant_defaults(base)[name]:
            assert (want - base.diffuse_reflectance(one, WL)[0]).abs().max() > 1e-4  # the constant matters here


def test_gradients_in_every_constant():
    model, params = SkinModel(), table2(3)
    wl = torch.linspace(420.0, 680.0, 5, dtype=torch.float64)

    def reflectance(thickness, oxygenation, ratio):
        return point_reflectance(model, params, wl, dict(zip(CONSTANT_NAMES, (thickness, oxygenation, ratio))))

    values = [torch.tensor(v, dtype=torch.float64, requires_grad=True)
              for v in ((0.3, 0.25, 0.4), (0.5, 0.7, 0.9), (0.5, 1.0, 2.0))]
    assert torch.autograd.gradcheck(reflectance, values)


def test_bounds_keep_the_source_inside_the_epidermis():
    """The thickness's lower bound is where the multipole's source (one mean free path deep) still lies
    inside the layer at every band: the model evaluates there and refuses a thinner layer."""
    model = SkinModel()
    lo, hi = constant_bounds(model, WL, CONSTANT_NAMES)
    thinnest = float(lo[0])
    assert 0.1 < thinnest < 0.25 and float(hi[0]) == 0.5
    params = table2(1)
    point_reflectance(model, params, WL, {"epidermis_thickness_mm": torch.tensor([thinnest], dtype=torch.float64)})
    with pytest.raises(ValueError, match="thinner than one transport mean free path"):
        point_reflectance(model, params, WL, {"epidermis_thickness_mm": torch.tensor([0.1], dtype=torch.float64)})
    with pytest.raises(ValueError, match="unknown constants"):
        point_reflectance(model, params, WL, {"thickness": torch.tensor([0.3], dtype=torch.float64)})


def test_slab_thickness_per_element_equals_one_slab_at_a_time():
    sigma_a = torch.tensor([[0.05], [0.5], [2.0]], dtype=torch.float64).expand(3, 4)
    sigma_s = torch.tensor([5.0, 10.0, 20.0, 40.0], dtype=torch.float64)
    thickness = torch.tensor([[0.3], [0.5], [1.2]], dtype=torch.float64)
    together = multipole_totals(sigma_a, sigma_s, thickness, 1.4, 1.4 / 1.38)
    for i, d in enumerate(thickness[:, 0].tolist()):
        alone = multipole_totals(sigma_a[i], sigma_s, d, 1.4, 1.4 / 1.38)
        for got, want in zip(together, alone):
            assert torch.allclose(got[i], want, rtol=1e-14, atol=0)
    with pytest.raises(ValueError, match="finite and > 0"):
        multipole_totals(sigma_a, sigma_s, torch.tensor([[0.3], [0.0], [1.0]], dtype=torch.float64), 1.4, 1.0)
