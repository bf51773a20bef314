"""Radial reflectance and transmittance profiles of one homogeneous layer: dipole and multipole.

Jensen et al. 2001 (dipole, semi-infinite) and Donner & Jensen 2005 (multipole, slab); DWRR08 §3
summarises the model. Every profile is radiant exitance per unit incident power (mm⁻²), radially
symmetric, with internal reflection at both boundaries folded in through the extrapolated boundaries
``z_b = 2 A D``.

Two evaluations of the same model are offered:

* in space, ``multipole_profiles(r, ...)``: the sum over dipole pairs ``i = -n..n``, with ``n`` chosen
  per element from a tolerance on the energy of the pairs left out;
* in the Hankel (2D Fourier) domain, ``multipole_hankel(k, ...)``: the sum over *all* pairs in closed
  form. Each source term ``z (1 + σ d) e^{-σ d} / d³`` has the 2D transform ``2π sgn(z) e^{-|z| s}``
  with ``s = sqrt(σ² + k²)``, and the pair positions form arithmetic series, so the infinite sums are
  geometric. At ``k = 0`` these are the plane integrals (totals).

The two share no code beyond the layer constants, so each checks the other.

Shapes: ``sigma_a`` and ``sigma_s_prime`` broadcast against each other to ``(...)``; ``r`` or ``k``
is ``(N,)``; results are ``(..., N)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..optics.fresnel import extrapolation_factor

__all__ = [
    "LayerProfiles",
    "SlabOptics",
    "dipole_hankel",
    "dipole_profile",
    "dipole_total",
    "multipole_hankel",
    "multipole_pair_count",
    "multipole_profiles",
    "multipole_totals",
]

SOURCE_DEPTHS = ("mean_free_path", "capped")


class LayerProfiles(NamedTuple):
    """The four profiles of a layer: light arriving from above (+) or from below (-)."""

    R_plus: torch.Tensor
    T_plus: torch.Tensor
    R_minus: torch.Tensor
    T_minus: torch.Tensor


@dataclass(frozen=True)
class SlabOptics:
    """Derived diffusion constants of a layer (Jensen et al. 2001; Donner & Jensen 2005), broadcast
    over ``(...)``.

    ``z_b_top`` and ``z_b_bottom`` are the extrapolation distances of the boundary the light
    enters through and of the opposite one; ``source_depth_mm`` is ℓ (or its cap). ``thickness_mm`` is
    one number, or a tensor broadcast with the coefficients (a point fit that frees the epidermis's
    thickness per spectrum; the totals and transforms take it, the real-space pair sum does not).
    """

    albedo: torch.Tensor
    sigma_tr_per_mm: torch.Tensor
    source_depth_mm: torch.Tensor
    z_b_top_mm: torch.Tensor
    z_b_bottom_mm: torch.Tensor
    thickness_mm: float | torch.Tensor

    @classmethod
    def build(
        cls,
        sigma_a_per_mm: torch.Tensor,
        sigma_s_prime_per_mm: torch.Tensor,
        thickness_mm: float | torch.Tensor,
        eta_top: float,
        eta_bottom: float,
        source_depth: str = "mean_free_path",
    ) -> "SlabOptics":
        sigma_a, sigma_s = torch.broadcast_tensors(
            torch.as_tensor(sigma_a_per_mm), torch.as_tensor(sigma_s_prime_per_mm)
        )
        if source_depth not in SOURCE_DEPTHS:
            raise ValueError(f"source_depth must be one of {SOURCE_DEPTHS}, got {source_depth!r}")
        if bool((sigma_a < 0).any()) or bool((sigma_s <= 0).any()):
            raise ValueError("sigma_a must be >= 0 and sigma_s_prime > 0 (mm^-1)")
        sigma_t = sigma_a + sigma_s
        albedo = sigma_s / sigma_t
        ell = 1.0 / sigma_t
        per_element = isinstance(thickness_mm, torch.Tensor)
        if per_element:
            thickness_mm = thickness_mm.to(sigma_t)
            if not bool(torch.isfinite(thickness_mm).all()) or bool((thickness_mm <= 0).any()):
                raise ValueError("a per-element thickness must be finite and > 0 (mm)")
        if per_element or math.isfinite(thickness_mm):
            if bool((sigma_a <= 0).any()):
                raise ValueError(
                    "sigma_a must be > 0 for a slab: the image series sums geometrically only with some "
                    "absorption (a clear slab is the limit sigma_a -> 0; use e.g. 1e-9 /mm)"
                )
            if source_depth == "capped":
                ell = torch.minimum(ell, torch.as_tensor(0.5 * thickness_mm).to(ell))
            elif bool((ell >= thickness_mm).any()):
                worst = float(ell.max())
                raise ValueError(
                    f"a layer of {float(torch.as_tensor(thickness_mm).min()):g} mm is thinner than one transport mean free path "
                    f"(l = {worst:.4f} mm): the multipole's source would lie below it. Use shorter "
                    "wavelengths or source_depth='capped'"
                )
        diffusion = 1.0 / (3.0 * sigma_t)
        sigma_tr = torch.sqrt(3.0 * sigma_a * sigma_t)
        z_top = 2.0 * extrapolation_factor(eta_top).to(sigma_t) * diffusion
        z_bottom = 2.0 * extrapolation_factor(eta_bottom).to(sigma_t) * diffusion
        return cls(albedo, sigma_tr, ell, z_top, z_bottom, thickness_mm if per_element else float(thickness_mm))


def _flux_term(z: torch.Tensor, r2: torch.Tensor, sigma_tr: torch.Tensor) -> torch.Tensor:
    """z (1 + σ d) e^{-σ d} / d³ with d = sqrt(r² + z²): the flux of a unit point source at height z."""
    d = torch.sqrt(r2 + z * z)
    return z * (1.0 + sigma_tr * d) * torch.exp(-sigma_tr * d) / d**3


def dipole_profile(
    r_mm: torch.Tensor,
    sigma_a_per_mm: torch.Tensor,
    sigma_s_prime_per_mm: torch.Tensor,
    eta: float,
) -> torch.Tensor:
    """Diffuse reflectance profile R(r) of a semi-infinite medium (Jensen et al. 2001), mm⁻², (..., N)."""
    opt = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, math.inf, eta, 1.0)
    z_r = opt.source_depth_mm[..., None]
    z_v = -(opt.source_depth_mm + 2.0 * opt.z_b_top_mm)[..., None]
    r2 = torch.as_tensor(r_mm).to(z_r) ** 2
    s = opt.sigma_tr_per_mm[..., None]
    return opt.albedo[..., None] / (4.0 * math.pi) * (_flux_term(z_r, r2, s) - _flux_term(z_v, r2, s))


def dipole_total(sigma_a_per_mm: torch.Tensor, sigma_s_prime_per_mm: torch.Tensor, eta: float) -> torch.Tensor:
    """Closed-form plane integral of the dipole: R_d = (α'/2)(1 + e^{-(4/3)A sqrt(3(1-α'))}) e^{-sqrt(3(1-α'))}."""
    sigma_a, sigma_s = torch.broadcast_tensors(torch.as_tensor(sigma_a_per_mm), torch.as_tensor(sigma_s_prime_per_mm))
    if bool((sigma_a < 0).any()) or bool((sigma_s <= 0).any()):
        raise ValueError("sigma_a must be >= 0 and sigma_s_prime > 0 (mm^-1)")
    albedo = sigma_s / (sigma_a + sigma_s)
    root = torch.sqrt(3.0 * (1.0 - albedo))
    a = extrapolation_factor(eta).to(albedo)
    return 0.5 * albedo * (1.0 + torch.exp(-4.0 / 3.0 * a * root)) * torch.exp(-root)


def dipole_hankel(
    k_per_mm: torch.Tensor, sigma_a_per_mm: torch.Tensor, sigma_s_prime_per_mm: torch.Tensor, eta: float
) -> torch.Tensor:
    """2D Fourier (Hankel) transform of ``dipole_profile``; equals ``dipole_total`` at k = 0."""
    opt = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, math.inf, eta, 1.0)
    k = torch.as_tensor(k_per_mm).to(opt.albedo)
    s = torch.sqrt(opt.sigma_tr_per_mm[..., None] ** 2 + k**2)
    a = opt.source_depth_mm[..., None]
    b = (opt.source_depth_mm + 2.0 * opt.z_b_top_mm)[..., None]
    return 0.5 * opt.albedo[..., None] * (torch.exp(-a * s) + torch.exp(-b * s))


def multipole_pair_count(opt: SlabOptics, tol: float, max_pairs: int = 100_000) -> torch.Tensor:
    """Dipole pairs n per element so that the pairs with |i| > n carry less than ``tol`` of R and of T.

    The energy of pair i falls as e^{-σ_tr (2|i|L - c)} with L = d + z_b1 + z_b2 and
    c = d + ℓ + 2 max(z_b); the tail is a geometric series bounded in closed form.
    """
    d = opt.thickness_mm
    period = d + opt.z_b_top_mm + opt.z_b_bottom_mm
    offset = d + opt.source_depth_mm + 2.0 * torch.maximum(opt.z_b_top_mm, opt.z_b_bottom_mm)
    refl, trans = multipole_totals_from(opt)
    # Relative to the smaller profile, so a faint T (thick or dark layer) is as accurate as R; a T
    # below 1e-12 of R + T is noise for any use and does not set the count.
    reference = torch.maximum(torch.minimum(refl, trans), 1e-12 * (refl + trans))
    sigma = opt.sigma_tr_per_mm.clamp_min(1e-300)
    one_minus_q = -torch.expm1(-2.0 * period * sigma)
    log_needed = torch.log(opt.albedo / (tol * reference * one_minus_q)).clamp_min(0.0)
    n = torch.ceil((log_needed / sigma + offset) / (2.0 * period)) - 1.0
    n = n.clamp_min(0.0)
    if bool((n > max_pairs).any()):
        raise ValueError(
            f"the multipole needs more than {max_pairs} dipole pairs at this tolerance "
            f"(sigma_tr down to {float(opt.sigma_tr_per_mm.min()):.3g} /mm); use the Hankel closed form"
        )
    return n.to(torch.long)


def multipole_profiles(
    r_mm: torch.Tensor,
    sigma_a_per_mm: torch.Tensor,
    sigma_s_prime_per_mm: torch.Tensor,
    thickness_mm: float,
    eta_top: float,
    eta_bottom: float,
    *,
    tol: float = 1e-8,
    source_depth: str = "mean_free_path",
    max_pairs: int = 100_000,
) -> LayerProfiles:
    """R⁺, T⁺, R⁻, T⁻ of a slab in space (the multipole of Donner & Jensen 2005), mm⁻², (..., N).

    ``eta_top`` is the relative index at the top boundary (layer over medium above), ``eta_bottom``
    at the bottom one. The ``-`` profiles swap the roles of the two boundaries. ``tol`` bounds the
    energy of the dipole pairs left out, relative to the smaller of R and T.
    """
    down = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_top, eta_bottom, source_depth)
    up = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_bottom, eta_top, source_depth)
    r_plus, t_plus = _slab_profiles_space(torch.as_tensor(r_mm), down, tol, max_pairs)
    r_minus, t_minus = _slab_profiles_space(torch.as_tensor(r_mm), up, tol, max_pairs)
    return LayerProfiles(r_plus, t_plus, r_minus, t_minus)


def _slab_profiles_space(
    r_mm: torch.Tensor, opt: SlabOptics, tol: float, max_pairs: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Real-space sum over pairs; elements are sorted by their pair count so each pair i is only
    evaluated where it is needed (dark layers need one pair, clear thin ones hundreds)."""
    batch_shape = opt.albedo.shape
    n_pairs = multipole_pair_count(opt, tol, max_pairs).reshape(-1)
    order = torch.argsort(n_pairs, descending=True)
    n_sorted = n_pairs[order]
    flat = lambda x: x.reshape(-1)[order][:, None]  # noqa: E731
    d = opt.thickness_mm
    period = flat(d + opt.z_b_top_mm + opt.z_b_bottom_mm)
    ell = flat(opt.source_depth_mm)
    z_b1 = flat(opt.z_b_top_mm)
    s = flat(opt.sigma_tr_per_mm)
    r2 = r_mm.to(period) ** 2
    refl = torch.zeros(period.shape[0], r2.shape[-1], dtype=period.dtype, device=period.device)
    trans = torch.zeros_like(refl)
    n_max = int(n_sorted[0]) if n_sorted.numel() else 0
    for i in range(-n_max, n_max + 1):
        m = int((n_sorted >= abs(i)).sum())
        z_r = 2.0 * i * period[:m] + ell[:m]
        z_v = 2.0 * i * period[:m] - ell[:m] - 2.0 * z_b1[:m]
        refl[:m] += _flux_term(z_r, r2, s[:m]) - _flux_term(z_v, r2, s[:m])
        trans[:m] += _flux_term(d - z_r, r2, s[:m]) - _flux_term(d - z_v, r2, s[:m])
    scale = flat(opt.albedo) / (4.0 * math.pi)
    inverse = torch.argsort(order)
    shape = (*batch_shape, r2.shape[-1])
    return (scale * refl)[inverse].reshape(shape), (scale * trans)[inverse].reshape(shape)


def multipole_hankel(
    k_per_mm: torch.Tensor,
    sigma_a_per_mm: torch.Tensor,
    sigma_s_prime_per_mm: torch.Tensor,
    thickness_mm: float,
    eta_top: float,
    eta_bottom: float,
    *,
    source_depth: str = "mean_free_path",
) -> LayerProfiles:
    """Hankel transforms of R⁺, T⁺, R⁻, T⁻ summed over all dipole pairs in closed form, (..., N).

    A semi-infinite layer (``thickness_mm = inf``) gives the dipole for R⁺ and zeros elsewhere.
    """
    k = torch.as_tensor(k_per_mm)
    if not math.isfinite(thickness_mm):
        SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, math.inf, eta_top, eta_bottom)  # refuses bad coefficients
        r_plus = dipole_hankel(k, sigma_a_per_mm, sigma_s_prime_per_mm, eta_top)
        zero = torch.zeros_like(r_plus)
        return LayerProfiles(r_plus, zero, zero, zero)
    down = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_top, eta_bottom, source_depth)
    up = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_bottom, eta_top, source_depth)
    r_plus, t_plus = _slab_hankel(k, down)
    r_minus, t_minus = _slab_hankel(k, up)
    return LayerProfiles(r_plus, t_plus, r_minus, t_minus)


def _slab_hankel(k: torch.Tensor, opt: SlabOptics, unsqueeze: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form infinite multipole sums (see the module docstring)."""
    expand = (lambda x: x[..., None]) if unsqueeze else (lambda x: x)
    d = opt.thickness_mm
    period = expand(d + opt.z_b_top_mm + opt.z_b_bottom_mm)
    if isinstance(d, torch.Tensor):
        d = expand(d.expand_as(opt.albedo))
    a = expand(opt.source_depth_mm)
    b = expand(opt.source_depth_mm + 2.0 * opt.z_b_top_mm)
    sigma = expand(opt.sigma_tr_per_mm)
    s = torch.sqrt(sigma**2 + k.to(sigma) ** 2) if unsqueeze else sigma
    q = torch.exp(-2.0 * period * s)
    one_minus_q = -torch.expm1(-2.0 * period * s)
    e = torch.exp
    refl = e(-a * s) + e(-b * s) + (q * e(-a * s) + q * e(-b * s) - e(-(2 * period - b) * s) - e(-(2 * period - a) * s)) / one_minus_q
    trans = (
        e(-(d - a) * s)
        - e(-(d + b) * s)
        + (e(-(d - a) * s) * q - e(-(d + b) * s) * q - e(-(2 * period - d + a) * s) + e(-(2 * period - d - b) * s))
        / one_minus_q
    )
    half_albedo = 0.5 * expand(opt.albedo)
    return half_albedo * refl, half_albedo * trans


def multipole_totals_from(opt: SlabOptics) -> tuple[torch.Tensor, torch.Tensor]:
    """Plane integrals (R, T) of a slab's profiles, all pairs in closed form; shapes ``(...)``."""
    return _slab_hankel(torch.zeros(()), opt, unsqueeze=False)


def multipole_totals(
    sigma_a_per_mm: torch.Tensor,
    sigma_s_prime_per_mm: torch.Tensor,
    thickness_mm: float | torch.Tensor,
    eta_top: float,
    eta_bottom: float,
    *,
    source_depth: str = "mean_free_path",
) -> LayerProfiles:
    """Plane integrals of R⁺, T⁺, R⁻, T⁻ (all pairs, closed form), differentiable, shapes ``(...)``;
    ``thickness_mm`` may be a tensor broadcast with the coefficients (differentiable in it too)."""
    if not isinstance(thickness_mm, torch.Tensor) and not math.isfinite(thickness_mm):
        r_plus = dipole_total(sigma_a_per_mm, sigma_s_prime_per_mm, eta_top)
        zero = torch.zeros_like(r_plus)
        return LayerProfiles(r_plus, zero, zero, zero)
    down = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_top, eta_bottom, source_depth)
    up = SlabOptics.build(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm, eta_bottom, eta_top, source_depth)
    r_plus, t_plus = multipole_totals_from(down)
    r_minus, t_minus = multipole_totals_from(up)
    return LayerProfiles(r_plus, t_plus, r_minus, t_minus)
