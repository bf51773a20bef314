"""The Monte Carlo transport reference (``model/transport``) against adding-doubling and itself.

Truths: iadpython's adding-doubling (``transport_reference.py``: one slab; two layers stacked on one
quadrature), energy conservation, translation invariance, the seed. Monte Carlo results are compared
within 3 of their own standard errors (the spread of independent batches). Adding-doubling cannot
express an index step inside the stack, so the two-layer comparisons use one index (n = 1.40) and no
interface absorber, as docs/transport.md explains; the index step and the absorber are checked by
limits.
"""

from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("iadpython")

import transport_reference as ref

from skinlayers.model import TABLE2, ModelSettings, SkinModel, SkinParams
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.optics.radiometry import entry_transmittance
from skinlayers.model.transport import Medium, TransportRenderer, walk

#: The 3-standard-error band every comparison must fall in.
Z = 3.0
#: Adding-doubling's own error: 32 quadrature points against 64 change R by < 10⁻⁴ here.
AD_QUADRATURE = 32


def _batches(medium: Medium, photons: int, seed: int, batches: int = 16):
    """One walk of ``batches`` labelled batches entering at the centre, normal incidence: the tally."""
    per = photons // batches
    zero = torch.zeros(per * batches, dtype=torch.float64)
    entering = entry_transmittance(medium.n[0], medium.n_above)
    return walk(medium, zero, zero, torch.ones_like(zero), torch.full_like(zero, entering), torch.Generator().manual_seed(seed),
                label=torch.arange(batches).repeat_interleave(per), labels=batches), per


def _mean_se(values: torch.Tensor) -> tuple[float, float]:
    return float(values.mean()), float(values.std(unbiased=True) / math.sqrt(values.numel()))


def _slab(sigma_a: float, sigma_s: float, thickness_mm: float, photons: int, seed: int = 0):
    """(R, SE, T, SE, R + T + unscattered + lost, SE) of a slab in air, normal incidence, per unit incident power."""
    medium = Medium((thickness_mm,), (ref.N_SKIN,), 1.0, 1.0, (sigma_s,), 0.0, torch.full((1, 1, 1), sigma_a, dtype=torch.float64),
                    torch.ones(0, 1, 1, dtype=torch.float64), 1.0)
    t, per = _batches(medium, photons, seed)
    out = t.reflected + t.transmitted + t.unscattered_reflected + t.unscattered_transmitted + t.lost
    return [*_mean_se(t.reflected / per), *_mean_se(t.transmitted / per), *_mean_se(out / per)]


@pytest.mark.parametrize("sigma_a", [0.05, 2.0, 30.0])
@pytest.mark.parametrize("sigma_s", [4.40, 12.54])  # the epidermis's σs′ at 700 and 400 nm (Eq. 13)
def test_the_thin_epidermis_slab_against_adding_doubling(sigma_a, sigma_s):
    r, r_se, t, t_se, _, _ = _slab(sigma_a, sigma_s, 0.25, 64_000)
    ad = ref.adding_doubling_slab(ref.Layer(sigma_a, sigma_s, 0.25), quad_points=AD_QUADRATURE)
    assert abs(r - ad.R_diffuse) <= Z * r_se + 1e-4 * ad.R_diffuse, (r, r_se, ad.R_diffuse)
    assert abs(t - ad.T_diffuse) <= Z * t_se + 1e-4 * ad.T_diffuse + 1e-7, (t, t_se, ad.T_diffuse)


@pytest.mark.parametrize("g", [0.8, -0.3])
def test_henyey_greenstein_scattering_against_adding_doubling(g):
    """Anisotropic scattering (skin's forward g = 0.8, and a backward one): the walk's phase function
    and its rotation against adding-doubling of the same slab with the same Henyey–Greenstein g."""
    import iadpython

    sigma_a, sigma_s, d = 2.0, 30.0, 0.25
    medium = Medium((d,), (ref.N_SKIN,), 1.0, 1.0, (sigma_s,), g, torch.full((1, 1, 1), sigma_a, dtype=torch.float64),
                    torch.ones(0, 1, 1, dtype=torch.float64), 1.0)
    t, per = _batches(medium, 24_000, 21)
    r, r_se = _mean_se(t.reflected / per)
    tr, t_se = _mean_se(t.transmitted / per)
    sample = iadpython.Sample(a=sigma_s / (sigma_a + sigma_s), b=(sigma_a + sigma_s) * d, g=g, d=d, n=ref.N_SKIN, n_above=1.0,
                              n_below=1.0, quad_pts=64)
    ur1, ut1, _, _ = sample.rt()
    r0, t0 = (float(v) for v in sample.unscattered_rt())
    assert abs(r - (float(ur1) - r0)) <= Z * r_se + 1e-3 * r, (r, r_se, float(ur1) - r0)
    assert abs(tr - (float(ut1) - t0)) <= Z * t_se + 1e-3 * tr, (tr, t_se, float(ut1) - t0)


def test_energy_is_conserved_in_a_clear_slab():
    """No absorption: everything that entered leaves (scattered or not) or is still inside, within noise."""
    _, _, _, _, out, out_se = _slab(0.0, 6.08, 0.25, 32_000)
    assert abs(out - entry_transmittance(ref.N_SKIN)) <= Z * out_se + 1e-9


def _same_index_settings(**transport) -> ModelSettings:
    return ModelSettings.model_validate({"optics": {"n_dermis": 1.40, "interface_melanin_fraction": 0.0}, "transport": transport})


def _skin_layers(settings: ModelSettings, row: str, wl: torch.Tensor):
    model = SkinModel(settings)
    spectra = model.spectra(wl)
    ab = model.absorption(SkinParams.from_mapping(TABLE2[row]), spectra)
    return [(ref.Layer(float(ab.epidermis[j]), float(spectra.scattering_epidermis[j]), 0.25),
             ref.Layer(float(ab.dermis[j]), float(spectra.scattering_dermis[j]), ref.DERMIS_MM)) for j in range(wl.numel())]


def _check_rows(rows, photons):
    settings = _same_index_settings()
    wl = torch.tensor([470.0, 560.0, 650.0], dtype=torch.float64)
    for row in rows:
        totals = TransportRenderer(settings).totals(SkinParams.from_mapping(TABLE2[row]), wl, photons=photons)
        for j, layers in enumerate(_skin_layers(settings, row, wl)):
            ad = ref.adding_doubling_stack(list(layers), quad_points=AD_QUADRATURE).R_diffuse
            r, se = float(totals.reflectance[j]), float(totals.std_error[j])
            assert abs(r - ad) <= Z * se + 1e-4 * ad, (row, float(wl[j]), r, se, ad)


def test_two_layer_skin_against_adding_doubling():
    """Table 2's III interior at 470, 560 and 650 nm: epidermis over a semi-infinite dermis."""
    _check_rows(["III interior"], 40_000)


@pytest.mark.slow
def test_every_table2_row_against_adding_doubling():
    """All nine rows at 400,000 photons a band (a standard error near 0.1%: a bias of 0.3% fails)."""
    _check_rows(list(TABLE2), 400_000)


@pytest.mark.slow
@pytest.mark.parametrize("sigma_a", [0.02, 0.2, 2.0, 20.0, 80.0])
@pytest.mark.parametrize("sigma_s", [4.40, 6.08, 12.54])
def test_the_thin_slab_over_skins_whole_absorption_range(sigma_a, sigma_s):
    """The 0.25-mm epidermis over skin's σa range (0.02–80 mm⁻¹) at the epidermis's σs′ of 700, 550 and
    400 nm, 10⁶ photons each."""
    r, r_se, t, t_se, _, _ = _slab(sigma_a, sigma_s, 0.25, 1_000_000, seed=11)
    ad = ref.adding_doubling_slab(ref.Layer(sigma_a, sigma_s, 0.25), quad_points=64)
    assert abs(r - ad.R_diffuse) <= Z * r_se + 1e-4 * ad.R_diffuse, (r, r_se, ad.R_diffuse)
    assert abs(t - ad.T_diffuse) <= Z * t_se + 1e-4 * ad.T_diffuse + 1e-7, (t, t_se, ad.T_diffuse)


def test_uniform_light_on_homogeneous_skin_is_flat_and_equals_the_totals():
    """Launch over the maps and their margin, tally per pixel: every pixel, and their mean, is the total
    diffuse reflectance (translation invariance; checks the launch's and the tally's normalisation).
    The plain walk: the twin's version is below."""
    settings = ModelSettings.model_validate({"transport": {"margin_mm": 3.0, "twin": False}})
    renderer = TransportRenderer(settings)
    params = TABLE2["IV interior"]
    maps = SkinMaps.uniform(params, (6, 6), 0.25, dtype=torch.float64)
    wl = torch.tensor([560.0], dtype=torch.float64)
    image = renderer.render(maps, Light("uniform"), wl, photons=96_000)
    totals = renderer.totals(SkinParams.from_mapping(params), wl, photons=48_000)
    pixel, se = image.exitance[0, 0], image.exitance_std_error[0, 0]
    z = (pixel - totals.reflectance[0]) / torch.sqrt(se**2 + totals.std_error[0] ** 2)
    assert float(z.abs().max()) < 4.0, z  # 36 pixels: the largest of 36 normal deviates stays under 4
    mean_se = float(torch.sqrt((se**2).mean() / se.numel() + totals.std_error[0] ** 2))
    assert abs(float(pixel.mean() - totals.reflectance[0])) <= Z * mean_se


def test_a_profile_of_homogeneous_skin_is_flat_and_equals_the_totals():
    """The y-invariant tally (maps of one row, every exit counted in its column): per unit length of
    the line source, each column and their mean is the plane's total (checks its normalisation)."""
    renderer = TransportRenderer(ModelSettings.model_validate({"transport": {"margin_mm": 3.0}}))
    params = TABLE2["II exterior"]
    row = SkinMaps.uniform(params, (1, 8), 0.25, dtype=torch.float64)
    wl = torch.tensor([520.0], dtype=torch.float64)
    profile = renderer.profile(row, Light("uniform"), wl, photons=48_000)
    totals = renderer.totals(SkinParams.from_mapping(params), wl, photons=48_000, seed=9)
    pixel, se = profile.exitance[0, 0, 0], profile.exitance_std_error[0, 0, 0]
    z = (pixel - totals.reflectance[0]) / torch.sqrt(se**2 + totals.std_error[0] ** 2)
    assert float(z.abs().max()) < 3.5, z  # 8 columns
    mean_se = float(torch.sqrt((se**2).mean() / se.numel() + totals.std_error[0] ** 2))
    assert abs(float(pixel.mean() - totals.reflectance[0])) <= Z * mean_se
    assert torch.equal(renderer.render(row, Light("uniform"), wl, photons=48_000).exitance, profile.exitance)


def test_the_same_seed_gives_the_same_image_and_another_seed_another():
    renderer = TransportRenderer(ModelSettings.model_validate({"transport": {"batches_min": 4}}))
    maps = SkinMaps.uniform(TABLE2["III interior"], (4, 4), 0.2, dtype=torch.float64)
    wl = torch.tensor([600.0], dtype=torch.float64)
    a = renderer.render(maps, Light("window", size_mm=0.8), wl, photons=1_000, seed=5)
    b = renderer.render(maps, Light("window", size_mm=0.8), wl, photons=1_000, seed=5)
    c = renderer.render(maps, Light("window", size_mm=0.8), wl, photons=1_000, seed=6)
    assert torch.equal(a.image, b.image) and not torch.equal(a.image, c.image)
    among = renderer.render(maps, Light("window", size_mm=0.8), torch.tensor([550.0, 600.0]), photons=1_000, seed=5)
    assert torch.equal(among.image[:, 1:], a.image)  # a band's photons do not depend on the bands beside it


def test_a_melanin_step_reaches_each_sides_own_reflectance_far_from_the_edge():
    """Heterogeneous lookups: half the patch six times the melanin; 2 mm from the edge each side is
    its homogeneous self (the light's spread at 470 nm is well under that)."""
    settings = ModelSettings.model_validate({"transport": {"margin_mm": 2.5}})
    renderer = TransportRenderer(settings)
    light, wl = TABLE2["III interior"], torch.tensor([470.0], dtype=torch.float64)
    dark = {**light, "C_m": 6 * light["C_m"]}
    maps = SkinMaps.uniform(light, (2, 10), 0.5, dtype=torch.float64)
    maps = maps.replace(C_m=torch.cat([torch.full((1, 2, 5), light["C_m"]), torch.full((1, 2, 5), dark["C_m"])], dim=2).double())
    image = renderer.render(maps, Light("uniform"), wl, photons=80_000)
    for side, params, cols in (("light", light, slice(0, 1)), ("dark", dark, slice(9, 10))):
        totals = renderer.totals(SkinParams.from_mapping(params), wl, photons=32_000)
        pixel = image.exitance[0, 0, :, cols].mean()
        se = torch.sqrt((image.exitance_std_error[0, 0, :, cols] ** 2).mean() / 2 + totals.std_error[0] ** 2)
        assert abs(float(pixel - totals.reflectance[0])) <= Z * float(se), (side, float(pixel), float(totals.reflectance[0]))
    assert float(image.exitance[0, 0, :, 4].mean()) > float(image.exitance[0, 0, :, 5].mean())  # the edge is there


def test_the_interface_absorber_takes_light_at_each_crossing():
    """A black interface (A = 0): the epidermis alone over a dermis that returns nothing — the same as a
    slab of epidermis whose light is lost below the 1.40/1.38 boundary (Fresnel reflection kept)."""
    wl = torch.tensor([560.0], dtype=torch.float64)
    params = SkinParams.from_mapping(TABLE2["III interior"])
    settings = ModelSettings.model_validate({"optics": {"interface_melanin_fraction": 1e6}})
    skin = TransportRenderer(settings).totals(params, wl, photons=48_000)
    o, model = settings.optics, SkinModel(settings)
    spectra = model.spectra(wl)
    sigma_a = float(model.absorption(params, spectra).epidermis[0])
    slab = Medium((o.epidermis_thickness_mm,), (o.n_epidermis,), o.n_above, o.n_dermis, (float(spectra.scattering_epidermis[0]),), 0.0,
                  torch.full((1, 1, 1), sigma_a, dtype=torch.float64), torch.ones(0, 1, 1, dtype=torch.float64), 1.0)
    t, per = _batches(slab, 48_000, 77)
    slab_r, slab_se = _mean_se(t.reflected / per)
    assert abs(float(skin.reflectance[0]) - slab_r) <= Z * math.hypot(float(skin.std_error[0]), slab_se)
    clear = TransportRenderer(ModelSettings()).totals(params, wl, photons=16_000)
    assert float(skin.reflectance[0]) < float(clear.reflectance[0]) - 0.05  # the dermis's light is gone


def _diffuse_launch(medium: Medium, x_mm: float, pixel_mm: float, photons: int, batches: int, seed: int):
    """Light from a Lambertian source in air along one column of a y-invariant medium (centred at
    ``x_mm``, ``pixel_mm`` wide): positions uniform across it, directions cosine-weighted in air,
    refracted in, weighted by the Fresnel transmittance; every exit tallied in its column."""
    from skinlayers.model.optics.fresnel import fresnel_reflectance

    g = torch.Generator().manual_seed(seed)
    per = photons // batches
    u = torch.rand(4, per * batches, dtype=torch.float64, generator=g)
    cos_air = torch.sqrt(u[0])
    eta = medium.n[0] / medium.n_above
    cos_in = torch.sqrt(1.0 - (1.0 - cos_air**2) / eta**2)
    weight = 1.0 - fresnel_reflectance(cos_air, eta).to(torch.float64)
    x = x_mm + (u[1] - 0.5) * pixel_mm
    return walk(medium, x, torch.zeros_like(x), cos_in, weight, g, label=torch.arange(batches).repeat_interleave(per),
                labels=batches, azimuth=2 * math.pi * u[3], across_y=True), per


def test_reciprocity_between_two_columns_across_an_edge():
    """Lambertian light in along column a, all light out along column b equals the reverse (the
    reciprocity of radiative transport, integrated along the columns: exact for this pair of
    measurements), 0.75 mm apart across an edge where one side has six times the melanin and an
    interface absorbance of 1 (A = e⁻¹, ink): an asymmetric error (the interface's transmittance taken
    at the wrong crossing, a lookup shifted by a pixel) breaks it."""
    from skinlayers.model.patch.edits import add_absorbance

    mm, w = 0.25, 12
    renderer = TransportRenderer(ModelSettings())
    light = TABLE2["III interior"]
    right = (torch.arange(w) >= w // 2).reshape(1, 1, w)
    maps = SkinMaps.uniform(light, (1, w), mm, dtype=torch.float64)
    maps = maps.replace(C_m=torch.where(right, 6 * light["C_m"], light["C_m"]).double())
    maps = add_absorbance(maps, right.double(), torch.tensor([560.0]))
    medium = renderer._medium(maps, 0, torch.tensor([560.0], dtype=torch.float64))
    a, b = w // 2 - 2, w // 2 + 1  # columns either side of the edge
    centre = lambda k: (k + 0.5 - w / 2) * mm  # noqa: E731
    forward, per = _diffuse_launch(medium, centre(a), mm, 64_000, 16, 1)
    backward, _ = _diffuse_launch(medium, centre(b), mm, 64_000, 16, 2)
    ab, ab_se = _mean_se(forward.surface[:, 0, b] / per)
    ba, ba_se = _mean_se(backward.surface[:, 0, a] / per)
    assert abs(ab - ba) <= Z * math.hypot(ab_se, ba_se), (ab, ab_se, ba, ba_se)
    # the two sides differ: each column's own light is far from the other's
    assert float(forward.surface[:, 0, a].mean()) > 1.15 * float(backward.surface[:, 0, b].mean())


# -- the homogeneous twin (a control variate) ---------------------------------------------------------

def _twin_settings(twin: bool, **transport) -> ModelSettings:
    return ModelSettings.model_validate({"transport": {"twin": twin, **transport}})


def test_a_twin_equal_to_the_medium_tallies_what_the_medium_does():
    """Skin that is its own twin: every photon's two weights stay equal (no ratio events, the same
    attenuation, the same interface), so the two tallies are identical."""
    medium = TransportRenderer(ModelSettings())._medium(SkinMaps.uniform(TABLE2["III interior"], (3, 3), 0.3, dtype=torch.float64),
                                                         0, torch.tensor([520.0], dtype=torch.float64))
    twin = (tuple(float(v[0, 0]) for v in medium.sigma_a_per_mm), (float(medium.interface_transmittance[0, 0, 0]),))
    x = (torch.rand(4000, generator=torch.Generator().manual_seed(3), dtype=torch.float64) - 0.5) * 0.9
    t = walk(medium, x, torch.zeros_like(x), torch.ones_like(x), torch.ones_like(x), torch.Generator().manual_seed(4), twin=twin)
    assert float(t.surface.sum()) > 0 and torch.allclose(t.surface, t.surface_twin, rtol=1e-12, atol=0)


def test_the_kernel_convolution_is_the_sum_over_lit_cells():
    """``_convolve_kernel`` against the sum written out: E(cell) K(pixel − cell + border)."""
    from skinlayers.model.transport.reference import _convolve_kernel

    g = torch.Generator().manual_seed(0)
    h, w, b, c = 3, 4, 2, 1
    irradiance = torch.rand(h + 2 * b, w + 2 * c, dtype=torch.float64, generator=g)
    kernel = torch.rand(2, 2 * (h + b) - 1, 2 * (w + c) - 1, dtype=torch.float64, generator=g)
    hk, wk = h + b - 1, w + c - 1
    expected = torch.zeros(2, h, w, dtype=torch.float64)
    for pi in range(h):
        for pj in range(w):
            for ci in range(h + 2 * b):
                for cj in range(w + 2 * c):
                    expected[:, pi, pj] += irradiance[ci, cj] * kernel[:, pi - ci + b + hk, pj - cj + c + wk]
    assert torch.allclose(_convolve_kernel(irradiance, kernel, (h, w)), expected, rtol=1e-12)


def test_the_twin_renders_a_heterogeneous_patch_as_the_plain_walk_does_with_far_less_noise():
    """A freckle (six times the melanin), a patch of dermal blood and an absorbing interface stripe,
    under a window: the twin's render and the plain walk's agree pixel by pixel within their standard
    errors (the estimator is unbiased), and the twin's error is several times smaller."""
    base = TABLE2["III interior"]
    maps = SkinMaps.uniform(base, (8, 8), 0.25, dtype=torch.float64)
    c_m, c_hd = maps.C_m.clone(), maps.C_hd.clone()
    c_m[:, 2:4, 2:4] *= 6.0
    c_hd[:, 5:7, 4:8] *= 3.0
    absorbance = torch.zeros(1, 1, 8, 8, dtype=torch.float64)
    absorbance[..., :, 6] = 0.7
    maps = maps.replace(C_m=c_m, C_hd=c_hd, absorbance=absorbance, absorbance_wavelength_nm=torch.tensor([500.0], dtype=torch.float64))
    wl, light = torch.tensor([500.0], dtype=torch.float64), Light("window", size_mm=1.75)
    plain = TransportRenderer(_twin_settings(False)).render(maps, light, wl, photons=60_000, seed=2)
    twin = TransportRenderer(_twin_settings(True)).render(maps, light, wl, photons=60_000, seed=3)
    lit = (slice(1, 7), slice(1, 7))
    a, sa = plain.exitance[0, 0][lit], plain.exitance_std_error[0, 0][lit]
    b, sb = twin.exitance[0, 0][lit], twin.exitance_std_error[0, 0][lit]
    z = (a - b) / torch.sqrt(sa**2 + sb**2)
    assert float(z.abs().max()) < 4.0, z  # 36 pixels
    assert abs(float(z.mean())) < Z / 6.0  # their mean: 36 deviates, standard error 1/6
    assert float((sa / sb).median()) > 2.0, sa / sb


def test_uniform_light_on_homogeneous_skin_through_the_twin_is_the_totals_with_the_kernels_error_alone():
    """Skin equal to its twin under uniform light (lit beyond the maps): the difference is exactly
    zero, so the image is the twin's kernel convolved with the light — flat, equal to the totals."""
    settings = _twin_settings(True, margin_mm=2.0, twin_kernel_share=1.0)
    params = TABLE2["IV interior"]
    maps = SkinMaps.uniform(params, (5, 5), 0.25, dtype=torch.float64)
    wl = torch.tensor([560.0], dtype=torch.float64)
    image = TransportRenderer(settings).render(maps, Light("uniform"), wl, photons=32_000)
    totals = TransportRenderer(settings).totals(SkinParams.from_mapping(params), wl, photons=32_000, seed=4)
    pixel, se = image.exitance[0, 0], image.exitance_std_error[0, 0]
    z = (pixel - totals.reflectance[0]) / torch.sqrt(se**2 + totals.std_error[0] ** 2)
    assert float(z.abs().max()) < 4.0, z
