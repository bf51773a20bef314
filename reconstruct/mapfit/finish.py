"""The fit's last step (``fit.fit_cube``'s ``finish``): on the finest level, the residual, the flags and
each map's σ (the noise's share from the Gauss–Newton curvature, widened by ``uncertainty.py``: the
cross-talk where the renderer's fit was kept, the variation finer than the nodes, the model's floor), and
the notes the data call for. ``finish_fit`` returns plain values, which ``fit.MapFit`` carries."""

from __future__ import annotations

import math

import torch

from ...formats.cube import Cube
from ...model import N_PARAMS, PARAMETER_NAMES
from ...model.patch.maps import SkinMaps
from ..diagnosis.checks import (DataChecks, band_bias, band_bias_notes, flag_value, precision_notes, residual_notes,
                     smooth_band_notes)
from .gauss_newton import curvature_and_columns, level_step
from ..choice.grid_choice import band_noise
from ..diagnosis.hairs import HairFinding, find_hairs, hair_notes, hair_widening
from ..diagnosis.structure import find_structure, structure_notes, structure_widening
from .optimizers import OptimResult
from ..levels.problem import LevelProblem
from ..levels.schur import marginal_variance
from ..settings import FitSettings
from ..diagnosis.uncertainty import MODEL_FLOOR_ABSOLUTE, MODEL_FLOORS, crosstalk_ratio, model_floor, subnode_sd
from ..levels.unknowns import dparams_dx, near_bound, to_params

__all__ = ["cube_hairs", "cube_noise", "finish_fit", "pixel_rms"]

#: The nodes' cluster-robust variance (``schur.marginal_variance``) sums the residual's pull over squares
#: of this side: about the light's spread in red, the scale on which the model's error is correlated.
CLUSTER_MM = 1.0


def pixel_rms(problem: LevelProblem, ev) -> torch.Tensor:
    """Each loss pixel's residual RMS over the used bands, unweighted ``(N,)``."""
    used = problem.band_weight > 0
    pred = problem.at_pixels(ev.image) * torch.exp(ev.log_scale)
    return torch.sqrt(((pred - problem.target)[:, used] ** 2).mean(1))


def finish_fit(problem: LevelProblem, result: OptimResult, x, log_scale, checks: DataChecks, settings: FitSettings, mm: float,
            renderer_fit: bool = True, hairs: HairFinding | None = None) -> dict:
    """Residuals, flags and uncertainties on the finest grid (σ widened by ``uncertainty.py``: the
    cross-talk where the renderer's fit was kept, the variation finer than the nodes)."""
    ev = result.evaluation
    scale = torch.exp(log_scale)
    image = ev.image * scale
    used = problem.band_weight > 0
    residual = image - problem.level.target
    residual_rms = torch.sqrt((residual[used] ** 2).mean(0))
    p = to_params(x)
    dx = _proposed_step(problem, ev, settings)
    sigma_pix, sigma_noise, widening = _pixel_sigma(problem, ev, residual, x, settings, renderer_fit)
    # not converged: the optimiser stopped at its iteration cap and the step it still proposes moves one
    # of the pixel's own maps by more than half its uncertainty. (After a passed convergence test the
    # proposed gn-hom step is no measure: it points at the fixed point of the approximate Jacobian, not
    # at the optimum, and stays large where no step lowers the loss: docs/reconstruct.md.)
    remaining = (problem.at_pixels(dparams_dx(x)) * dx).abs()
    fine = problem.layout.fine
    moving_pix = (remaining[:, fine] > 0.5 * sigma_pix.to(remaining.dtype)[:, fine]).any(1) & (not result.converged)
    flags, nodes_at_bound = _flags(problem, checks, settings, p, residual_rms, moving_pix)
    bias, ratio = _data_notes(problem, checks, residual, used)
    if hairs is not None:
        flags[hairs.flagged.reshape(-1).to(x.device)] |= flag_value("hair")
        checks.warn(hair_notes(hairs, int((problem.mask | hairs.flagged.to(x.device)).sum())))
    fitted = problem.mask.cpu()  # the loss pixels, (H, W)
    structure = find_structure(residual, fitted, problem.wavelength_nm.tolist(), used.cpu(), mm)
    if structure.count:
        flags[structure.flagged.reshape(-1).to(x.device)] |= flag_value("structure")
        checks.warn(structure_notes(structure, int(problem.pixels.numel())))
    clear = ~hairs.flagged.reshape(-1).to(x.device)[problem.pixels] if hairs is not None else None
    precision = _sigma_median(p, sigma_pix, problem, clear)
    checks.warn(precision_notes(precision))
    h, w = problem.level.shape
    sigma = torch.full((N_PARAMS, h * w), float("nan"), dtype=x.dtype, device=x.device)
    sigma[:, problem.pixels] = sigma_pix.T.to(x.dtype)
    if hairs is not None and hairs.count:
        sigma *= hair_widening(hairs.flagged.reshape(-1).to(x.device), PARAMETER_NAMES).to(sigma)
    if structure.count:
        sigma *= structure_widening(structure.flagged, residual, used, fitted, PARAMETER_NAMES).to(sigma)
    noise_sigma = torch.full_like(sigma, float("nan"))
    noise_sigma[:, problem.pixels] = sigma_noise.T.to(x.dtype)
    return {
        "maps": _final_maps(problem, p, mm), "scale": float(scale), "image": image, "residual": residual,
        "residual_rms": residual_rms, "flags": flags.reshape(h, w), "sigma": sigma.reshape(N_PARAMS, h, w),
        "sigma_noise": noise_sigma.reshape(N_PARAMS, h, w), "maps_at_bound": nodes_at_bound,
        "band_bias": {f"{problem.wavelength_nm[j]:g}": round(b, 5) for j, b in bias.items()},
        "residual_over_noise": round(ratio, 4), "sigma_median": {n: round(v, 5) for n, v in precision.items()},
        "hairs": hairs.as_dict() if hairs is not None else None,
        "structure": structure.as_dict(int(problem.pixels.numel())),
        "uncertainty": {**widening, "noise_sigma_median": {n: float(sigma_noise[:, k].median()) for k, n in enumerate(PARAMETER_NAMES)}},
    }


def _final_maps(problem: LevelProblem, p: torch.Tensor, mm: float) -> SkinMaps:
    """The parameter maps ``p`` ``(N_PARAMS, H, W)`` as ``SkinMaps``, with the grey absorbance at every band."""
    maps = SkinMaps(*(v[None] for v in p.unbind(0)), mm_per_pixel=mm)
    if problem.absorbance is not None:
        bands = problem.wavelength_nm.numel()
        maps = maps.replace(absorbance=problem.absorbance[None, None].expand(1, bands, -1, -1).contiguous(),
                            absorbance_wavelength_nm=problem.wavelength_nm.clone())
    return maps


def _proposed_step(problem: LevelProblem, ev, settings: FitSettings) -> torch.Tensor:
    """The step ``(N, N_PARAMS)`` the optimiser still proposes for each pixel's own maps (zero where every
    map is on nodes)."""
    jac, col = curvature_and_columns(problem, ev)
    dx = torch.zeros(problem.n_pixels, N_PARAMS, dtype=jac.dtype, device=jac.device)
    if problem.layout.fine:
        lam = torch.full((problem.n_pixels,), 1e-3, dtype=jac.dtype, device=jac.device)
        grad = ev.grad if ev.grad is not None else (jac.transpose(1, 2) @ ev.residual[..., None])[..., 0]
        dx = level_step(problem, jac, col, grad, ev.residual, lam, 1e-3, settings.free_scale)[0]
    return dx


def _pixel_sigma(problem: LevelProblem, ev, residual, x, settings: FitSettings, renderer_fit: bool):
    """σ per loss pixel ``(N, N_PARAMS)``: widened, from the noise alone, and the widening's record.
    From the unweighted problem: the robust weights shape the estimate, not the camera's noise."""
    problem.pixel_weight = None
    jac, col = curvature_and_columns(problem, ev)
    plain = problem.at_pixels(residual) * problem.band_weight
    if problem.layout.per_pixel:
        sigma_noise = _sigma(problem, jac, plain, x)
    else:
        sigma_noise = _sigma_shared(problem, jac, col, plain, x, settings.free_scale)
    sigma_pix, widening = _widened(problem, ev, jac, plain, x, sigma_noise, renderer_fit)
    return sigma_pix, sigma_noise, widening


def _flags(problem: LevelProblem, checks: DataChecks, settings: FitSettings, p: torch.Tensor, residual_rms: torch.Tensor,
           moving_pix: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """The flag bits per pixel ``(H·W,)`` (masked, saturated, at a bound, not converged, high residual,
    a band excluded) and the maps on nodes that rest at a bound (share of the pixels)."""
    h, w = problem.level.shape
    device = p.device
    flags = torch.zeros(h * w, dtype=torch.int32, device=device)
    flags[~problem.mask.reshape(-1)] |= flag_value("masked")
    flags[checks.saturated.reshape(-1).to(device)] |= flag_value("saturated")
    bound_hit = near_bound(p, settings.at_bound_fraction)  # (N_PARAMS, H, W)
    # a pixel's own maps at a bound flag it; a map on nodes at a bound is the whole region's, reported once
    at_bound = bound_hit[problem.layout.fine].any(0).reshape(-1)
    nodes_at_bound = {PARAMETER_NAMES[k]: float(bound_hit[k][problem.mask].double().mean()) for k in problem.layout.coarse
                      if bool(bound_hit[k][problem.mask].any())}
    flags[at_bound & problem.mask.reshape(-1)] |= flag_value("at_bound")
    moving = torch.zeros(h * w, dtype=torch.bool, device=device)
    moving[problem.pixels] = moving_pix
    flags[moving] |= flag_value("not_converged")
    rms_pix = residual_rms.reshape(-1)[problem.pixels]
    high = torch.zeros(h * w, dtype=torch.bool, device=device)
    high[problem.pixels] = rms_pix > settings.high_residual_factor * rms_pix.median()
    flags[high] |= flag_value("high_residual")
    if not bool(checks.bands_used.all()):
        flags |= flag_value("band_excluded")
    return flags, nodes_at_bound


def _data_notes(problem: LevelProblem, checks: DataChecks, residual: torch.Tensor, used: torch.Tensor) -> tuple[dict, float]:
    """The residual's checks as notes: a band biased, the residual against the cube's own noise, a band
    too smooth for its noise. Returns the per-band bias and the residual-over-noise ratio."""
    seen = problem.mask & ~checks.saturated.to(residual.device)
    bias = band_bias(residual, problem.level.target, used, seen)
    checks.warn(band_bias_notes(bias, problem.wavelength_nm.tolist()))
    noise = cube_noise(problem.level.target, seen)
    ratio = _residual_over_noise(residual, used, seen, noise)
    checks.warn(residual_notes(ratio))
    if noise is not None:
        level = problem.level.target[:, seen].double().median(dim=1).values.clamp_min(1e-12)
        checks.warn(smooth_band_notes((noise.double() / level).tolist(), problem.wavelength_nm.tolist(), used.tolist()))
    return bias, ratio


def cube_hairs(cube: Cube, checks: DataChecks, noise: torch.Tensor | None) -> HairFinding | None:
    """The hairs in the cube (``hairs.py``) over the pixels the loss may use, given the cube's ``noise``
    (``cube_noise``); None where the cube is too small to estimate its noise."""
    if noise is None:
        return None
    return find_hairs(cube.reflectance, cube.wavelength_nm.tolist(), checks.fit_mask, cube.mm_per_pixel, noise.cpu(), checks.bands_used)


def cube_noise(target: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor | None:
    """Each band's noise σ ``(L,)`` estimated from the cube itself (``band_noise``) over ``pixels`` ``(H, W)``;
    None where too few pixels have their neighbourhood in it."""
    try:
        return band_noise(target, pixels)
    except ValueError:
        return None


def _residual_over_noise(residual: torch.Tensor, used: torch.Tensor, pixels: torch.Tensor, noise: torch.Tensor | None) -> float:
    """The residual's RMS over the cube's noise ``(L,)``, both over ``pixels`` ``(H, W)`` and the ``used`` bands."""
    if noise is None:
        return math.nan
    res = residual[used][:, pixels].double()
    return float(res.pow(2).mean().sqrt() / noise[used].double().pow(2).mean().sqrt())


def _sigma_median(p: torch.Tensor, sigma_pix: torch.Tensor, problem: LevelProblem, clear: torch.Tensor | None = None) -> dict[str, float]:
    """Each map's median σ over the fitted pixels (those ``clear`` ``(N,)`` of a hair where given): relative
    to the map's value, β_m absolute."""
    values = problem.at_pixels(p).double()  # (N, N_PARAMS)
    sigma = sigma_pix.double()
    if clear is not None and bool(clear.any()):
        values, sigma = values[clear], sigma[clear]
    return {n: float((sigma[:, k] if n == "beta_m" else sigma[:, k] / values[:, k].abs().clamp_min(1e-12)).median())
            for k, n in enumerate(PARAMETER_NAMES)}


def _widened(problem: LevelProblem, ev, jac, residual, x, sigma_pix, renderer_fit: bool) -> tuple[torch.Tensor, dict]:
    """σ ``(N, N_PARAMS)`` with the two terms ``uncertainty.py`` measures on the cube, and what they were."""
    sd_band = _band_sd(problem, residual, free_scale=False)
    rho = crosstalk_ratio(problem, ev, jac) if renderer_fit else torch.ones(N_PARAMS, dtype=torch.float64, device=jac.device)
    dpdx = problem.at_pixels(dparams_dx(x)).double()
    spread = subnode_sd(problem, jac, residual, sd_band, rho, dpdx)
    widen = torch.ones(N_PARAMS, dtype=torch.float64, device=jac.device)
    widen[problem.layout.fine] = 1.0 / rho[problem.layout.fine]
    profiles = problem.renderer.settings.profiles
    floor = model_floor(problem.at_pixels(to_params(x)), profiles)
    total = torch.sqrt((sigma_pix.double() * widen) ** 2 + spread**2 + floor**2)
    return total.to(sigma_pix.dtype), {
        "crosstalk_ratio": {n: float(rho[k]) for k, n in enumerate(PARAMETER_NAMES)},
        "crosstalk_measured": renderer_fit,
        "subnode_sd_median": {PARAMETER_NAMES[k]: float(spread[:, k].median()) for k in problem.layout.coarse},
        "model_floor": dict(MODEL_FLOORS[profiles]),
        "model_floor_relative_to_value": [n for n in PARAMETER_NAMES if n not in MODEL_FLOOR_ABSOLUTE],
    }


def _band_sd(problem: LevelProblem, residual: torch.Tensor, free_scale: bool) -> torch.Tensor:
    """Each band's residual σ ``(L,)`` from the loss pixels' residual ``(N, L)``, corrected for the degrees of
    freedom the fit took (its per-pixel maps, nodes and, with ``free_scale``, the scale)."""
    n_used = int((problem.band_weight > 0).sum())
    n_unknowns = len(problem.layout.fine) * problem.n_pixels + problem.layout.n_nodes + int(free_scale)
    dof = max(n_used * problem.n_pixels - n_unknowns, 1) / (n_used * problem.n_pixels)
    return torch.sqrt((residual.double() ** 2).mean(0) / dof).clamp_min(1e-12)


def _sigma_shared(problem: LevelProblem, jac, col, residual, x, free_scale: bool) -> torch.Tensor:
    """Per-pixel standard deviation of each parameter ``(N, N_PARAMS)`` when maps share nodes: the inverse
    Fisher information of the whole fit (``schur.marginal_variance``), each band's noise σ from the
    residual, mapped from x to the parameter at the pixel."""
    used = problem.band_weight > 0
    sd_band = _band_sd(problem, residual, free_scale)
    weight = torch.where(used, 1.0 / sd_band, torch.zeros_like(sd_band))
    h, w = problem.level.shape
    cell = max(int(round(CLUSTER_MM / problem.level.mm_per_pixel)), 1)
    rows, cols = problem.pixels // w, problem.pixels % w
    clusters = (rows // cell) * (w // cell + 1) + cols // cell
    var = marginal_variance(jac.double() * weight[None, :, None], col.double() * weight[None, :], free_scale, problem.layout,
                            problem.pixels, residual.double() * weight[None, :], clusters)
    return var.sqrt() * problem.at_pixels(dparams_dx(x)).double()


def _sigma(problem: LevelProblem, jac: torch.Tensor, residual: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Per-pixel standard deviation of each parameter ``(N, N_PARAMS)`` (sandwich covariance, float64)."""
    used = problem.band_weight > 0
    n_used = int(used.sum())
    dof = max(n_used - N_PARAMS, 1) / n_used
    var_band = (residual.double() ** 2).mean(0) / dof  # (L,)
    dpdx = problem.at_pixels(dparams_dx(x)).double()  # (N, N_PARAMS)
    jp = jac.double() / dpdx.clamp_min(1e-300)[:, None, :]
    jp = jp[:, used]
    a = jp.transpose(1, 2) @ jp
    ridge = 1e-12 * torch.diagonal(a, dim1=1, dim2=2).amax(1)[:, None, None] * torch.eye(N_PARAMS, dtype=a.dtype, device=a.device)
    a_inv = torch.linalg.pinv(a + ridge, hermitian=True)
    meat = jp.transpose(1, 2) @ (var_band[used][None, :, None] * jp)
    cov = a_inv @ meat @ a_inv
    return torch.sqrt(torch.diagonal(cov, dim1=1, dim2=2).clamp_min(0.0))

