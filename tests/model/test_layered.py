"""Homogeneous two-layer skin: the layer combination, its limits, batching and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from skinlayers.model import (
    PARAMETER_NAMES,
    TABLE2,
    LayerTransforms,
    ModelSettings,
    SkinModel,
    SkinOptics,
    SkinParams,
    combine_layers,
    inverse_hankel,
    multipole_totals,
)
from skinlayers.model.optics.radiometry import entry_transmittance

WL8 = torch.tensor(ModelSettings().render_wavelengths_nm, dtype=torch.float64)


def table2_params(dtype=torch.float64) -> SkinParams:
    return SkinParams.from_mapping({n: [TABLE2[row][n] for row in TABLE2] for n in PARAMETER_NAMES}, dtype=dtype)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> SkinModel:
    """The paper's diffusion model: these tests check its profiles and their combination (the transport
    profiles' checks: test_transport_profiles.py)."""
    return SkinModel(ModelSettings(profiles="diffusion"), cache_dir=str(tmp_path_factory.mktemp("tables")))


def test_combination_equals_explicit_series():
    """R₁₂ in closed form equals the explicit series R₁⁺ + Σ_n T₁⁺ (A R₂⁺ A R₁⁻)ⁿ A R₂⁺ A T₁⁻ (Eq. 3, 7)."""
    g = torch.Generator().manual_seed(1)
    t = LayerTransforms(*(torch.rand(50, generator=g, dtype=torch.float64) * 0.7 for _ in range(5)),
                        attenuation=torch.rand(50, generator=g, dtype=torch.float64))
    series = t.R1_plus.clone()
    term = t.T1_plus * t.attenuation * t.R2_plus * t.attenuation * t.T1_minus
    for _ in range(400):
        series = series + term
        term = term * t.attenuation * t.R1_minus * t.attenuation * t.R2_plus
    torch.testing.assert_close(combine_layers(t), series, rtol=1e-12, atol=1e-14)


def test_model_total_is_the_combination_of_layer_totals(model):
    """The model's total equals the combination of independently computed layer totals."""
    params = table2_params()
    o = model.settings.optics
    spectra = model.spectra(WL8)
    ab = model.absorption(params, spectra)
    epi = multipole_totals(ab.epidermis, spectra.scattering_epidermis, o.epidermis_thickness_mm,
                           o.n_epidermis / o.n_above, o.n_epidermis / o.n_dermis)
    derm = multipole_totals(ab.dermis, spectra.scattering_dermis, math.inf, o.n_dermis / o.n_epidermis, 1.0)
    a = torch.exp(-ab.interface_absorbance)
    expected = epi.R_plus + a * epi.T_plus * a * derm.R_plus * epi.T_minus / (1 - a * a * epi.R_minus * derm.R_plus)
    torch.testing.assert_close(model.total_reflectance(params, WL8), expected, rtol=1e-12, atol=0)
    f_t = entry_transmittance(o.n_epidermis, o.n_above)
    assert f_t == pytest.approx(1 - (0.4 / 2.4) ** 2, rel=1e-12)
    torch.testing.assert_close(model.diffuse_reflectance(params, WL8), f_t * expected)


def test_total_is_hankel_at_zero_frequency(model):
    params = table2_params()
    k = torch.tensor([0.0, 1e-3, 1.0], dtype=torch.float64)
    combined = model.combined_hankel(params, WL8, k)
    torch.testing.assert_close(combined[..., 0], model.total_reflectance(params, WL8), rtol=1e-12, atol=0)
    assert bool((combined[..., 2] < combined[..., 0]).all()), "a profile's transform falls with frequency"


def test_opaque_interface_leaves_only_the_epidermis(model):
    """With absorbance → ∞ at the interface only the epidermis's own R₁⁺ remains."""
    params = table2_params()
    o = model.settings.optics
    spectra = model.spectra(WL8)
    ab = model.absorption(params, spectra)
    r1 = multipole_totals(ab.epidermis, spectra.scattering_epidermis, o.epidermis_thickness_mm,
                          o.n_epidermis / o.n_above, o.n_epidermis / o.n_dermis).R_plus
    opaque = model.total_reflectance(params, WL8, extra_absorbance=torch.full((9, 8), 80.0, dtype=torch.float64))
    torch.testing.assert_close(opaque, r1, rtol=1e-12, atol=0)
    assert bool((model.total_reflectance(params, WL8) > opaque).all())


def test_energy_bounds(model):
    """0 < R_d < 1 everywhere in the parameter box and more melanin or blood never brightens."""
    g = torch.Generator().manual_seed(3)
    hi = torch.tensor([0.5, 1.0, 0.05, 0.05, 0.1], dtype=torch.float64)
    x = torch.rand(400, 5, generator=g, dtype=torch.float64) * hi
    wl = torch.arange(380.0, 801.0, 10.0, dtype=torch.float64)
    settings = ModelSettings(optics=SkinOptics(source_depth="capped"))
    r = SkinModel(settings).diffuse_reflectance(SkinParams.from_tensor(x), wl)
    assert bool(((r > 0) & (r < 1)).all())
    base = model.diffuse_reflectance(SkinParams.from_tensor(x), WL8)
    for j in (0, 2, 3, 4):
        more = x.clone()
        more[:, j] = more[:, j] * 1.5 + 1e-3
        assert bool((model.diffuse_reflectance(SkinParams.from_tensor(more), WL8) <= base + 1e-12).all()), PARAMETER_NAMES[j]


def test_batched_equals_looped(model):
    params = table2_params()
    batched = model.diffuse_reflectance(params, WL8)
    for i, row in enumerate(TABLE2.values()):
        single = model.diffuse_reflectance(SkinParams.from_mapping(row), WL8)
        torch.testing.assert_close(batched[i], single, rtol=1e-13, atol=0)
    maps = SkinParams.from_tensor(params.as_tensor().reshape(3, 3, 5))
    torch.testing.assert_close(model.diffuse_reflectance(maps, WL8).reshape(9, 8), batched)


def test_float32_follows_input_dtype(model):
    r32 = model.diffuse_reflectance(table2_params(torch.float32), WL8)
    assert r32.dtype == torch.float32
    torch.testing.assert_close(r32.double(), model.diffuse_reflectance(table2_params(), WL8), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", ["exact", "tables"])
def test_gradcheck_all_five_parameters(model, method):
    """d R_d / d(C_m, β_m, C_he, C_bc, C_hd) by autograd equals finite differences (float64)."""
    base = torch.tensor(
        [[0.012, 0.4, 0.003, 0.001, 0.008], [0.05, 0.8, 0.01, 0.004, 0.02]], dtype=torch.float64
    ).requires_grad_()
    wl = WL8[[0, 3, 7]]

    def f(x):
        return model.diffuse_reflectance(SkinParams.from_tensor(x), wl, method=method)

    assert torch.autograd.gradcheck(f, (base,), eps=1e-7, atol=1e-7, rtol=1e-5)


def test_inverse_hankel_recovers_real_space_profiles():
    """inverse_hankel of the closed-form multipole transform equals the real-space multipole sum."""
    from skinlayers.model import multipole_hankel, multipole_profiles

    sigma_a = torch.tensor([0.05, 1.0, 10.0], dtype=torch.float64)
    k = torch.linspace(0.0, 3000.0, 200_001, dtype=torch.float64)
    r = torch.logspace(-2, 0.5, 60, dtype=torch.float64)
    args = (sigma_a, torch.tensor(7.0, dtype=torch.float64), 0.25, 1.4, 1.4 / 1.38)
    space = multipole_profiles(r, *args)
    hankel = multipole_hankel(k, *args)
    for name in ("R_plus", "T_plus"):
        back = inverse_hankel(getattr(hankel, name), k, r)
        ref = getattr(space, name)
        keep = ref > 1e-3 * ref.amax(-1, keepdim=True)
        rel = ((back - ref).abs() / ref)[keep]
        assert float(rel.max()) < 2e-3, name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(model):
    params = table2_params()
    cpu = model.diffuse_reflectance(params, WL8)
    gpu_params = SkinParams(*(v.cuda() for v in params.values()))
    for method in ("exact", "tables"):
        gpu = model.diffuse_reflectance(gpu_params, WL8, method=method)
        assert gpu.device.type == "cuda"
        torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-3 if method == "tables" else 1e-10, atol=0)
