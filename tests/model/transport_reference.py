"""Radiative-transport references for the diffusion model, and the model's side of each comparison.

Not a test file (pytest does not collect it): ``tests/model/test_transport.py`` and
``tests/bench/test_transport_chart.py`` load it by path with ``importlib.util.spec_from_file_location``
(registered in ``sys.modules`` under one private name), which works under ``--import-mode=importlib``.

**Transport** (numpy and iadpython only, nothing of skinlayers): totals of plane-parallel slabs under
normal collimated light from air, per unit *incident* power.

* ``adding_doubling_slab``: one homogeneous slab through iadpython's own ``Sample.rt()``;
* ``adding_doubling_stack``: layers stacked with iadpython's adding functions on one quadrature
  (iadpython's ``Sample`` does not stack layers: array-valued ``a``, ``b`` are evaluated as separate
  samples by ``rt()``, and ``combine.simple_layer_matrices`` returns the *upward* reflection of the
  stack; so the stacking is done here and checked against a split slab and a Monte Carlo);
* ``monte_carlo``: a vectorised photon walk through the same stack, with standard errors.

All layers share one refractive index ``n`` (no interfaces between layers), air above and below (an
iadpython "slide" is always bounded by air, so a matched lower medium cannot be expressed; a thick
lower layer stands in for a semi-infinite one). Scattering is isotropic (g = 0) with ``sigma_s`` the
*reduced* scattering coefficient σs′: the similarity relation the diffusion model itself rests on, so
both sides see the same medium. "Diffuse" excludes the specular reflection and all unscattered light
(which diffusion does not model).

**Diffusion** (skinlayers): the same quantities from the closed-form multipole/dipole totals, so the
bench and the regression guard compute exactly the same thing.

Units: lengths mm, coefficients mm⁻¹, wavelengths nm.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np

N_SKIN = 1.40
QUAD_POINTS = 16
EPIDERMIS_MM = 0.25
#: Stand-in for the semi-infinite dermis: R within 1e-12 of a 1000 mm one for dermis σa ≥ 0.02 mm⁻¹ (bench check).
DERMIS_MM = 50.0


class Layer(NamedTuple):
    """One homogeneous layer: absorption and (reduced, isotropic) scattering in mm⁻¹, thickness in mm."""

    sigma_a_per_mm: float
    sigma_s_per_mm: float
    thickness_mm: float

    @property
    def optical_thickness(self) -> float:
        return (self.sigma_a_per_mm + self.sigma_s_per_mm) * self.thickness_mm

    @property
    def albedo(self) -> float:
        return self.sigma_s_per_mm / (self.sigma_a_per_mm + self.sigma_s_per_mm)


class Totals(NamedTuple):
    """Diffuse reflectance and transmittance per unit incident power, with the unscattered parts."""

    R_diffuse: float
    T_diffuse: float
    R_unscattered: float
    T_unscattered: float


class MonteCarloTotals(NamedTuple):
    """Diffuse R and T per unit incident power and their standard errors (one photon = one sample)."""

    R_diffuse: float
    T_diffuse: float
    R_std_error: float
    T_std_error: float


# -- adding-doubling ------------------------------------------------------------------------------


def _sample(layer: Layer, n: float, quad_points: int):
    import iadpython

    return iadpython.Sample(
        a=layer.albedo, b=layer.optical_thickness, g=0.0, d=layer.thickness_mm,
        n=n, n_above=1.0, n_below=1.0, quad_pts=quad_points,
    )


def _unscattered(total_optical_thickness: float, n: float) -> tuple[float, float]:
    """Specular reflection plus unscattered light (all orders) of a slab of index n in air, normal incidence."""
    import iadpython

    r, t = iadpython.specular_rt(1.0, n, 1.0, total_optical_thickness, 1.0)
    return float(r), float(t)


def adding_doubling_slab(layer: Layer, n: float = N_SKIN, quad_points: int = QUAD_POINTS) -> Totals:
    """One slab in air through iadpython's ``Sample(...).rt()``: (UR1, UT1) minus ``unscattered_rt()``."""
    sample = _sample(layer, n, quad_points)
    ur1, ut1, _, _ = sample.rt()
    r0, t0 = (float(v) for v in sample.unscattered_rt())
    return Totals(float(ur1) - r0, float(ut1) - t0, r0, t0)


def adding_doubling_stack(layers: Sequence[Layer], n: float = N_SKIN, quad_points: int = QUAD_POINTS,
                          attenuation: Sequence[float] | None = None) -> Totals:
    """Layers (top first) of one index ``n`` in air, by adding-doubling on one quadrature.

    Each layer's matrices come from iadpython's doubling (``simple_single_layer_matrices``); they are
    added top-down with ``add_layers`` (keeping both directions, since the stack is asymmetric), then
    the air boundaries with ``add_slide_above`` and ``add_slide_below``, as ``Sample.rt_matrices``
    does for one layer.

    ``attenuation``: per boundary between layers (len(layers) - 1 values), a transmittance A applied at
    every crossing, whatever the angle (the model's and the Monte Carlo's interface absorber): the
    stack below a boundary is seen through it as A²·R (down and back) and A·T.
    """
    from iadpython.combine import add_layers, add_slide_above, add_slide_below, simple_single_layer_matrices
    from iadpython.start import boundary_layer

    if not layers:
        raise ValueError("at least one layer is needed")
    sample = _sample(layers[0], n, quad_points)
    sample.update_quadrature()
    down_r = up_r = down_t = up_t = None
    if attenuation is not None and len(attenuation) != len(layers) - 1:
        raise ValueError("one attenuation per boundary between layers")
    for index, layer in enumerate(layers):
        sample.a, sample.b, sample.b_thinnest = layer.albedo, layer.optical_thickness, None
        r, t = simple_single_layer_matrices(sample)  # a homogeneous layer: same both ways
        if down_r is None:
            down_r, up_r, down_t, up_t = r, r, t, t
        else:
            a = 1.0 if attenuation is None else float(attenuation[index - 1])
            # the boundary's absorber folded into the layer below it, on its side facing the stack above
            down_r, up_r, down_t, up_t = add_layers(sample, down_r, up_r, down_t, up_t, a * a * r, r, a * t, a * t)
    r01, r10, t01, t10 = boundary_layer(sample, top=True)
    r02, r20, t02, t20 = add_slide_above(sample, r01, r10, t01, t10, down_r, up_r, down_t, up_t)
    r23, r32, t23, t32 = boundary_layer(sample, top=False)
    r03, _, t03, _ = add_slide_below(sample, r02, r20, t02, t20, r23, r32, t23, t32)
    ur1, ut1, _, _ = sample.UX1_and_UXU(r03, t03)
    r0, t0 = _unscattered(sum(layer.optical_thickness for layer in layers), n)
    return Totals(float(ur1) - r0, float(ut1) - t0, r0, t0)


def adding_doubling_slab_matched_below(layer: Layer, n: float = N_SKIN, quad_points: int = 32) -> tuple[float, ...]:
    """One slab under air, index-matched below (no boundary there), per unit *entering* power:
    (R⁺ diffuse, T⁺ all of it, R⁻, T⁻) — R⁺/T⁺ for normal light from air, R⁻/T⁻ for Lambertian light from
    below in the slab. iadpython's matrices carry the flux weights 2ν_i w_i: a Lambertian incidence is the
    weight vector, light leaving into air exists only beyond the critical cosine, the matched side takes
    every row."""
    from iadpython.combine import add_slide_above, simple_single_layer_matrices
    from iadpython.start import boundary_layer

    sample = _sample(layer, n, quad_points)
    sample.update_quadrature()
    sample.b_thinnest = None
    r, t = simple_single_layer_matrices(sample)
    r01, r10, t01, t10 = boundary_layer(sample, top=True)
    r02, r20, t02, t20 = add_slide_above(sample, r01, r10, t01, t10, r, r, t, t)
    w, k = sample.twonuw, int(np.min(np.where(sample.nu > sample.nu_c())))
    specular = ((n - 1.0) / (n + 1.0)) ** 2
    entering = 1.0 - specular
    return ((float(w[k:] @ r02[k:, -1]) - specular) / entering, float(w @ t02[:, -1]) / entering,
            float(w @ r20 @ w), float(w[k:] @ t20[k:, :] @ w))


# -- Monte Carlo ----------------------------------------------------------------------------------


def fresnel_reflectance(cos_i: np.ndarray, n_ratio: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance; ``n_ratio`` = index beyond the boundary over index of arrival."""
    cos_i = np.abs(cos_i)
    sin2_t = (1.0 - cos_i**2) / n_ratio**2
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    r_s = (cos_i - n_ratio * cos_t) / (cos_i + n_ratio * cos_t)
    r_p = (n_ratio * cos_i - cos_t) / (n_ratio * cos_i + cos_t)
    return np.where(sin2_t >= 1.0, 1.0, 0.5 * (r_s**2 + r_p**2))


def monte_carlo(
    layers: Sequence[Layer], n: float = N_SKIN, photons: int = 100_000, seed: int = 0, roulette_weight: float = 1e-3
) -> MonteCarloTotals:
    """Photon walk through layers (top first) of index ``n`` in air, isotropic scattering, normal incidence.

    Plane-parallel totals need only depth and direction cosine. Absorption by weight (w ← w·albedo at
    each interaction), Russian roulette below ``roulette_weight``, Fresnel reflection sampled at the
    outer boundaries; optical depth carries across layer boundaries. Only photons that scattered at
    least once are counted, and the result is scaled by the entry transmittance (per incident power).
    """
    rng = np.random.default_rng(seed)
    sigma_t = np.array([lay.sigma_a_per_mm + lay.sigma_s_per_mm for lay in layers])
    albedo = np.array([lay.albedo for lay in layers])
    bounds = np.concatenate([[0.0], np.cumsum([lay.thickness_mm for lay in layers])])
    count = len(layers)
    z = np.zeros(photons)
    mu = np.ones(photons)
    layer = np.zeros(photons, dtype=np.int64)
    weight = np.ones(photons)
    tau = rng.exponential(size=photons)
    scattered = np.zeros(photons, dtype=bool)
    reflected = np.zeros(photons)
    transmitted = np.zeros(photons)
    alive = np.arange(photons)
    while alive.size:
        lay, m = layer[alive], mu[alive]
        to_boundary = np.where(m > 0, bounds[lay + 1] - z[alive], bounds[lay] - z[alive]) / m
        path = tau[alive] / sigma_t[lay]
        crosses = path >= to_boundary

        i = alive[~crosses]
        z[i] += mu[i] * path[~crosses]
        weight[i] *= albedo[layer[i]]
        scattered[i] = True
        mu[i] = rng.uniform(-1.0, 1.0, i.size)
        tau[i] = rng.exponential(size=i.size)

        j = alive[crosses]
        tau[j] -= sigma_t[layer[j]] * to_boundary[crosses]
        down = mu[j] > 0
        z[j] = np.where(down, bounds[layer[j] + 1], bounds[layer[j]])
        beyond = layer[j] + np.where(down, 1, -1)
        inside = (beyond >= 0) & (beyond < count)
        layer[j[inside]] = beyond[inside]
        k = j[~inside]
        bounce = rng.random(k.size) < fresnel_reflectance(mu[k], 1.0 / n)
        mu[k[bounce]] *= -1.0
        out = k[~bounce]
        up = mu[out] < 0
        counted = weight[out] * scattered[out]
        reflected[out[up]] = counted[up]
        transmitted[out[~up]] = counted[~up]
        weight[out] = 0.0

        low = alive[(weight[alive] > 0) & (weight[alive] < roulette_weight)]
        survive = rng.random(low.size) < 0.1
        weight[low[survive]] *= 10.0
        weight[low[~survive]] = 0.0
        alive = alive[weight[alive] > 0]
    entry = 1.0 - float(fresnel_reflectance(np.array(1.0), n))
    root_n = math.sqrt(photons)
    return MonteCarloTotals(
        entry * float(reflected.mean()), entry * float(transmitted.mean()),
        entry * float(reflected.std()) / root_n, entry * float(transmitted.std()) / root_n,
    )


# -- the diffusion model's side -------------------------------------------------------------------


def _scalar(value: float):
    """A float64 scalar tensor (the model's functions take tensors)."""
    import torch

    return torch.tensor(float(value), dtype=torch.float64)


def diffusion_slab(layer: Layer, source_depth: str = "mean_free_path") -> tuple[float, float]:
    """Diffuse (R, T) of one slab of index 1.40 in air from the multipole: F_t(0)·(R⁺, T⁺)."""
    from skinlayers.model.column.profiles import multipole_totals
    from skinlayers.model.optics.radiometry import entry_transmittance

    tot = multipole_totals(
        _scalar(layer.sigma_a_per_mm), _scalar(layer.sigma_s_per_mm), layer.thickness_mm, N_SKIN, N_SKIN,
        source_depth=source_depth,
    )
    f_t = entry_transmittance(N_SKIN, 1.0)
    return f_t * float(tot.R_plus), f_t * float(tot.T_plus)


def diffusion_semi_infinite(layer: Layer) -> float:
    """Diffuse reflectance of a half-space of index 1.40 under air from the dipole: F_t(0)·R_d."""
    from skinlayers.model.column.profiles import dipole_total
    from skinlayers.model.optics.radiometry import entry_transmittance

    r_d = dipole_total(_scalar(layer.sigma_a_per_mm), _scalar(layer.sigma_s_per_mm), N_SKIN)
    return entry_transmittance(N_SKIN, 1.0) * float(r_d)


def diffusion_two_layer(epidermis: Layer, dermis: Layer, source_depth: str = "mean_free_path") -> float:
    """Diffuse reflectance F_t(0)·R₁₂ of a slab on a semi-infinite dipole, indices matched (η = 1 inside).

    ``dermis.thickness_mm`` is ignored (the model's dermis is semi-infinite); no interface absorber.
    """
    from skinlayers.model.column.layered import LayerTransforms, combine_layers
    from skinlayers.model.column.profiles import dipole_total, multipole_totals
    from skinlayers.model.optics.radiometry import entry_transmittance

    epi = multipole_totals(
        _scalar(epidermis.sigma_a_per_mm), _scalar(epidermis.sigma_s_per_mm), epidermis.thickness_mm, N_SKIN, 1.0,
        source_depth=source_depth,
    )
    r2 = dipole_total(_scalar(dermis.sigma_a_per_mm), _scalar(dermis.sigma_s_per_mm), 1.0)
    r12 = combine_layers(LayerTransforms(epi.R_plus, epi.T_plus, epi.R_minus, epi.T_minus, r2, _scalar(1.0)))
    return entry_transmittance(N_SKIN, 1.0) * float(r12)


class SkinComparison(NamedTuple):
    """One Table 2 row at L wavelengths: the layers' coefficients and both reflectances, each ``(L,)``."""

    sigma_a_epidermis_per_mm: np.ndarray
    sigma_s_prime_epidermis_per_mm: np.ndarray
    sigma_a_dermis_per_mm: np.ndarray
    sigma_s_prime_dermis_per_mm: np.ndarray
    transport: np.ndarray
    diffusion: np.ndarray


def skin_row(row: str, wavelength_nm: Sequence[float], source_depth: str = "mean_free_path") -> SkinComparison:
    """A Table 2 row through ``SkinModel`` with matched indices and no interface absorber, and transport.

    The model side is ``SkinModel(ModelSettings(optics=SkinOptics(n_dermis=1.40,
    interface_melanin_fraction=0, source_depth=...))).diffuse_reflectance``; the transport side stacks
    the epidermis (0.25 mm) on a ``DERMIS_MM`` dermis with the model's own σa and σs′.
    """
    import torch

    from skinlayers.model import TABLE2, ModelSettings, SkinModel, SkinOptics, SkinParams

    optics = SkinOptics(n_dermis=N_SKIN, interface_melanin_fraction=0.0, source_depth=source_depth)
    model = SkinModel(ModelSettings(optics=optics))
    wl = torch.as_tensor(list(wavelength_nm), dtype=torch.float64)
    params = SkinParams.from_mapping(TABLE2[row])
    spectra = model.spectra(wl)
    ab = model.absorption(params, spectra)
    sa1, sa2 = ab.epidermis.numpy(), ab.dermis.numpy()
    ss1, ss2 = spectra.scattering_epidermis.numpy(), spectra.scattering_dermis.numpy()
    d_epi = optics.epidermis_thickness_mm
    transport = np.array([
        adding_doubling_stack([Layer(float(a1), float(s1), d_epi), Layer(float(a2), float(s2), DERMIS_MM)]).R_diffuse
        for a1, s1, a2, s2 in zip(sa1, ss1, sa2, ss2)
    ])
    diffusion = model.diffuse_reflectance(params, wl).numpy()
    return SkinComparison(sa1, ss1, sa2, ss2, transport, diffusion)
