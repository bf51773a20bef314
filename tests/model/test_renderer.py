"""The heterogeneous renderer against the homogeneous model, the Fourier-domain combination, energy,
the albedo-texture shortcut, its own strategies, and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from skinlayers.model import TABLE2, ModelSettings, SkinModel, SkinParams
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.optics.radiometry import entry_transmittance
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.settings import RenderSettings

F64 = torch.float64
WL = torch.tensor([450.0, 550.0, 650.0], dtype=F64)


@pytest.fixture(scope="module")
def renderer(tmp_path_factory) -> SkinRenderer:
    """The paper's diffusion profiles: these checks are of the renderer's numerics, designed on them (the
    transport profiles' renderer checks: test_transport_profiles.py)."""
    return SkinRenderer(ModelSettings(profiles="diffusion"), cache_dir=str(tmp_path_factory.mktemp("tables")))


def fourier_reference(renderer: SkinRenderer, row: dict, irradiance: torch.Tensor, mm: float, method: str) -> torch.Tensor:
    """Exitance by the Fourier-domain combination of the layers (DWRR08 §3, Eq. 3; Donner & Jensen 2005)
    applied to an irradiance image: FFT(E) · R̂₁₂(|k|) · (pixel box)² per axis, entering light F_t E.
    ``(L, H, W)``."""
    h, w = irradiance.shape
    n = 1 << int(math.ceil(math.log2(max(h, w) * 2)))
    ky = 2 * math.pi * torch.fft.fftfreq(n, d=mm, dtype=F64)
    kx = 2 * math.pi * torch.fft.rfftfreq(n, d=mm, dtype=F64)
    kk = torch.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    unique, inverse = torch.unique(kk.flatten(), return_inverse=True)
    r12 = renderer.model.combined_hankel(SkinParams.from_mapping(row), WL, unique, method=method)
    transfer = r12[:, inverse].reshape(-1, *kk.shape)
    box = (torch.sinc(ky * mm / (2 * math.pi)) ** 2)[:, None] * (torch.sinc(kx * mm / (2 * math.pi)) ** 2)[None, :]
    padded = torch.zeros(n, n, dtype=F64)
    padded[:h, :w] = irradiance
    out = torch.fft.irfft2(torch.fft.rfft2(padded) * transfer * box, s=(n, n))
    f_t = entry_transmittance(renderer.settings.optics.n_epidermis)
    return f_t * out[:, :h, :w]


@pytest.mark.parametrize("row", ["I interior", "III exterior", "V exterior"])
def test_uniform_light_reproduces_the_homogeneous_model(renderer, row):
    maps = SkinMaps.uniform(TABLE2[row], (24, 24), 0.05)
    result = renderer.render(maps, Light("uniform"), WL)
    expected = SkinModel(renderer.settings).diffuse_reflectance(SkinParams.from_mapping(TABLE2[row]), WL)
    rel = (result.exitance[0].double() / expected[:, None, None] - 1).abs()
    assert float(rel.max()) < 0.005


def test_point_light_radial_profile(renderer):
    """Unit power into one pixel: the image's radial profile against the Fourier-domain combination,
    annulus by annulus out to where 99.5% of the energy lies (2%), and its encircled energy against
    the combination of the exact profiles (2%)."""
    mm = 0.05
    row = TABLE2["III interior"]
    maps = SkinMaps.uniform(row, (1, 1), mm, dtype=F64)
    light = Light("point", border_mm=12.0)
    image = renderer.render(maps, light, WL, crop=False).exitance[0]
    size = image.shape[-1]
    impulse = torch.zeros(size, size, dtype=F64)
    impulse[size // 2, size // 2] = 1 / mm**2
    half = size // 2
    yy, xx = torch.meshgrid(torch.arange(size) - half, torch.arange(size) - half, indexing="ij")
    rr = torch.sqrt((yy**2 + xx**2).to(F64))
    order = torch.argsort(rr.flatten())
    radii = rr.flatten()[order]
    for method, check in (("tables", "annuli"), ("exact", "encircled")):
        ref = fourier_reference(renderer, row, impulse, mm, method)
        for band in range(WL.numel()):
            e, f = image[band], ref[band]
            cum_f = torch.cumsum(f.flatten()[order], 0)
            cum_f = cum_f / cum_f[-1]
            r_995 = float(radii[int((cum_f < 0.995).sum())])
            if check == "annuli":
                for r0 in range(0, int(r_995) + 1):
                    ring = (rr >= r0) & (rr < r0 + 1)
                    assert float((e[ring].sum() / f[ring].sum() - 1).abs()) < 0.02, (float(WL[band]), r0)
            else:
                cum_e = torch.cumsum(e.flatten()[order], 0)
                inside = radii <= r_995
                enc = (cum_e[inside] / torch.cumsum(f.flatten()[order], 0)[inside] - 1).abs()
                assert float(enc.max()) < 0.02, float(WL[band])


def test_window_edges_match_the_fourier_combination_and_are_symmetric(renderer):
    mm = 0.08
    row = TABLE2["II exterior"]
    maps = SkinMaps.uniform(row, (60, 60), mm, dtype=F64)
    light = Light("window", size_mm=3.2, border_mm=6.0)
    image = renderer.render(maps, light, WL, crop=False).exitance[0]
    border = light.border_px(mm)
    irradiance = light.irradiance(60, 60, border, mm, F64)
    ref = fourier_reference(renderer, row, irradiance, mm, "tables")
    peak = ref.amax((-1, -2), keepdim=True)
    assert float(((image - ref).abs() / peak).max()) < 0.02
    lit = ref > 0.1 * peak
    assert float(((image - ref).abs() / ref)[lit].max()) < 0.02
    # symmetric fall-off on all four edges (the pyramid pads odd sizes on one side: 1e-6 of the peak)
    for mirrored in (torch.flip(image, (-1,)), torch.flip(image, (-2,)), image.transpose(-1, -2)):
        assert float(((image - mirrored).abs() / peak).max()) < 1e-5
    exact = fourier_reference(renderer, row, irradiance, mm, "exact")
    assert float(((image - exact).abs() / peak).max()) < 0.02


def freckled_maps(size: int, mm: float, dtype=torch.float32) -> SkinMaps:
    """Smooth variation, freckles and a blood-poor scar: a heterogeneous scene."""
    g = torch.Generator().manual_seed(3)
    maps = SkinMaps.uniform(TABLE2["III interior"], (size, size), mm, dtype=dtype)
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    c_m = 0.006 * (1 + 0.5 * torch.sin(6 * x) * torch.cos(4 * y))
    for _ in range(6):
        cy, cx = torch.rand(2, generator=g)
        c_m = c_m + 0.06 * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 0.004)
    scar = (torch.abs(y - 0.3 - 0.2 * x) < 0.05).to(torch.float32)
    c_hd = 0.006 * (1 - 0.8 * scar) + 0.004 * y
    return maps.replace(C_m=c_m[None].to(dtype), C_hd=c_hd[None].to(dtype))


def test_energy_never_exceeds_what_entered(renderer):
    maps = freckled_maps(40, 0.1)
    light = Light("window", size_mm=3.0, border_mm=5.0)
    result = renderer.render(maps, light, WL, crop=False)
    border = light.border_px(0.1)
    entered = entry_transmittance(1.4) * light.irradiance(40, 40, border, 0.1).sum()
    out = result.exitance[0].sum((-1, -2))
    assert bool((out < entered).all()) and bool((result.exitance >= -1e-6).all())


def test_opaque_interface_leaves_only_the_epidermis(renderer):
    """Absorbance → ∞ at the interface: only the epidermis's own R₁⁺ comes back."""
    row = TABLE2["IV interior"]
    maps = SkinMaps.uniform(row, (16, 16), 0.05)
    opaque = maps.replace(absorbance=torch.full((1, 1, 16, 16), 200.0), absorbance_wavelength_nm=torch.tensor([500.0]))
    result = renderer.render(opaque, Light("uniform"), WL)
    model = SkinModel(renderer.settings)
    params = SkinParams.from_mapping(row)
    epi_only = model.diffuse_reflectance(params, WL, extra_absorbance=torch.full((3,), 200.0, dtype=F64))
    assert float((result.exitance[0].double() / epi_only[:, None, None] - 1).abs().max()) < 0.005
    assert bool((result.exitance[0].double() < model.diffuse_reflectance(params, WL)[:, None, None]).all())


def test_heterogeneity_is_not_an_albedo_texture(renderer):
    """DWRR08 Fig. 9: a homogeneous render times the per-pixel ratio (an albedo texture) agrees with
    the heterogeneous render under uniform light by construction, but not under stripes."""
    maps = freckled_maps(64, 0.05)
    mean = {n: float(getattr(maps, n).mean()) for n in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")}
    homogeneous = SkinMaps.uniform(mean, (64, 64), 0.05)
    uniform_het = renderer.render(maps, Light("uniform"), WL).exitance
    uniform_hom = renderer.render(homogeneous, Light("uniform"), WL).exitance
    albedo = uniform_het / uniform_hom
    stripes = Light("stripes", period_mm=1.0, duty=0.5, border_mm=5.0)
    striped_het = renderer.render(maps, stripes, WL).exitance
    striped_albedo = renderer.render(homogeneous, stripes, WL).exitance * albedo
    torch.testing.assert_close(uniform_hom * albedo, uniform_het)
    lit_mean = striped_het.mean()
    difference = (striped_het - striped_albedo).abs() / lit_mean
    print(f"\nstripes, heterogeneous vs albedo texture: max {float(difference.max()):.3f} of the mean")
    assert float(difference.max()) > 0.05


def test_strategies_agree(renderer):
    maps = freckled_maps(40, 0.1, F64)
    light = Light("window", size_mm=3.0, border_mm=4.0)
    results = {b: renderer.render(maps, light, WL, blur=b).exitance for b in ("fft", "chain", "pyramid")}
    scale = results["fft"].amax((-1, -2), keepdim=True)
    for b in ("chain", "pyramid"):
        assert float(((results[b] - results["fft"]).abs() / scale).max()) < 0.005, b


def test_gradients_match_finite_differences(renderer):
    """gradcheck (float64) of a small heterogeneous render with respect to the melanin and dermal
    blood maps, through the checkpointed gathers."""
    base = freckled_maps(4, 0.1, F64)
    light = Light("window", size_mm=0.4, border_mm=0.3)
    wl = WL[:2]

    def render(c_m, c_hd):
        return renderer.render(base.replace(C_m=c_m, C_hd=c_hd), light, wl, series_terms=2).exitance

    c_m = base.C_m.clone().requires_grad_()
    c_hd = base.C_hd.clone().requires_grad_()
    assert torch.autograd.gradcheck(render, (c_m, c_hd), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(renderer):
    maps = freckled_maps(32, 0.1)
    light = Light("window", size_mm=2.0, border_mm=3.0)
    cpu = renderer.render(maps, light, WL).exitance
    gpu = renderer.render(maps.to("cuda"), light, WL).exitance
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-6)


def test_series_count_follows_the_tolerance(tmp_path):
    maps = SkinMaps.uniform(TABLE2["I interior"], (8, 8), 0.1)
    loose = SkinRenderer(ModelSettings(render=RenderSettings(series_tolerance=1e-2, series_closure=False)), str(tmp_path))
    tight = SkinRenderer(ModelSettings(render=RenderSettings(series_tolerance=1e-5, series_closure=False)), str(tmp_path))
    a = loose.render(maps, Light("uniform"), WL)
    b = tight.render(maps, Light("uniform"), WL)
    assert a.terms[0] < b.terms[0]
    expected = SkinModel(loose.settings).diffuse_reflectance(SkinParams.from_mapping(TABLE2["I interior"]), WL)
    err_a = float((a.exitance[0].double().mean((-1, -2)) / expected - 1).abs().max())
    err_b = float((b.exitance[0].double().mean((-1, -2)) / expected - 1).abs().max())
    assert err_b < err_a < 0.01


@pytest.mark.parametrize("blur", ["pyramid", "fft"])
def test_lean_backward_equals_autograd(tmp_path, blur):
    """The memory-lean backward (recomputed blur stacks) gives autograd's gradients, pyramid levels included."""
    maps = freckled_maps(24, 0.1, F64)
    light = Light("window", size_mm=1.6, border_mm=2.0)
    grads = {}
    for lean in (True, False):
        r = SkinRenderer(ModelSettings(render=RenderSettings(checkpoint=lean)), str(tmp_path))
        c_m = maps.C_m.clone().requires_grad_()
        c_he = maps.C_he.clone().requires_grad_()
        out = r.render(maps.replace(C_m=c_m, C_he=c_he), light, WL[:2], blur=blur, series_terms=3).exitance
        weights = torch.linspace(0.5, 1.5, out.numel(), dtype=F64).reshape(out.shape)
        (out * weights).sum().backward()
        grads[lean] = (c_m.grad, c_he.grad)
    for lean_g, plain_g in zip(grads[True], grads[False]):
        torch.testing.assert_close(lean_g, plain_g, rtol=1e-9, atol=1e-12)


def test_series_closure(tmp_path):
    """The closed series: exact after one term for homogeneous skin under uniform light; on freckled
    skin under the window it beats plain truncation at every count, and the default term count stays
    within 0.1% of the peak of a 30-term reference."""
    plain = SkinRenderer(ModelSettings(render=RenderSettings(series_closure=False, max_series_terms=30)), str(tmp_path))
    closed = SkinRenderer(ModelSettings(), str(tmp_path))
    row = TABLE2["I interior"]
    uniform = closed.render(SkinMaps.uniform(row, (8, 8), 0.1, dtype=F64), Light("uniform"), WL, series_terms=1).exitance
    expected = SkinModel(closed.settings).diffuse_reflectance(SkinParams.from_mapping(row), WL)
    assert float((uniform[0].mean((-1, -2)) / expected - 1).abs().max()) < 1e-3
    assert float((plain.render(SkinMaps.uniform(row, (8, 8), 0.1, dtype=F64), Light("uniform"), WL, series_terms=1)
                  .exitance[0].mean((-1, -2)) / expected - 1).abs().max()) > 0.05
    maps = freckled_maps(40, 0.1, F64)
    light = Light("window", size_mm=3.0, border_mm=4.0)
    ref = plain.render(maps, light, WL, series_terms=30).exitance
    peak = ref.amax((-1, -2), keepdim=True)

    def err(x):
        return float(((x - ref).abs() / peak).max())

    for n in (1, 2, 3, 4):
        assert err(closed.render(maps, light, WL, series_terms=n).exitance) < err(plain.render(maps, light, WL, series_terms=n).exitance)
    auto = closed.render(maps, light, WL)
    print(f"\nclosed series, default count {auto.terms[0]}: max error {err(auto.exitance):.1e} of the peak")
    assert err(auto.exitance) < 1e-3


def test_weight_cache_changes_nothing(tmp_path):
    """Dense weights kept across the series give the same image and gradients as fresh lookups."""
    maps = freckled_maps(20, 0.1, F64)
    light = Light("window", size_mm=1.6, border_mm=1.5)
    out = {}
    for budget in (0.0, 1024.0):
        r = SkinRenderer(ModelSettings(render=RenderSettings(weight_cache_mb=budget)), str(tmp_path))
        c_m = maps.C_m.clone().requires_grad_()
        img = r.render(maps.replace(C_m=c_m), light, WL[:2], series_terms=3).exitance
        img.sum().backward()
        out[budget] = (img.detach(), c_m.grad)
    torch.testing.assert_close(out[0.0], out[1024.0], rtol=1e-12, atol=1e-15)
