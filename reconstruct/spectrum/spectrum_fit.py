"""Fit the five skin parameters to point reflectance spectra with the homogeneous model.

A point measurement (a spectrometer, one pixel ignoring its neighbours) sees no spatial structure, so
the homogeneous two-layer model is all it needs: the diffuse reflectance R_d(λ) of the two-layer
diffusion model (DWRR08 §3, Eq. 3; Donner & Jensen 2005; docs/model.md, "Radiometric convention") with
the layers' exact totals (closed form, smooth in every parameter).

All spectra (and all starts) are one batched, projected Levenberg–Marquardt problem: per spectrum and
start an N_PARAMS × N_PARAMS system (one more unknown with a free scale), Jacobians by forward-mode
autodiff, the damped step and the damping rule of ``least_squares`` (as the map fit's). Parameters are
scaled to [0, 1] by their DWRR08 Table 1 bounds and kept in that box; one resting on a bound with the
gradient pushing outward is held there (its column zeroed: ``least_squares`` then leaves it), so a
bound is reached exactly (and reported) instead of approached forever, as a sigmoid
reparameterisation would.

``fit_spectra`` is three named steps: ``_starts`` (every spectrum from every start), ``solve_box`` (the
projected LM iterations), ``_best`` (each spectrum's best end point, its residual and bounds), run on
chunks of spectra small enough that memory stays bounded (each spectrum's fit is its own: chunks change
nothing but the memory), so a file of ten thousand spectra fits in the time of ten thousand, with progress.

Shapes: spectra ``(B, L)``, wavelengths ``(L,)``; unknowns ``(B·S, n)`` spectrum-major (S starts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from ...model import N_PARAMS, PARAMETER_NAMES, SkinModel, SkinParams, parameter_bounds
from ...model.column.point_tables import PointTables
from ...model.optics.radiometry import specular_reflectance
from ..levels.least_squares import LAMBDA0, LAMBDA_MAX, damped_step, forward_jacobian, next_damping, predicted_decrease
from ..levels.unknowns import near_bound

__all__ = ["AT_BOUND_FRACTION", "PAPER_START", "BoxProblem", "SpectrumFit", "fit_spectra", "joined", "solve_box",
           "specular_offset"]

#: DWRR08 §8 ("Fit convergence"): eumelanin 0.73%, pheomelanin 0.3%, epidermal blood 0.3%, carotene 0,
#: dermal blood 0.6%.
PAPER_START = {"C_m": 0.0103, "beta_m": 0.73 / 1.03, "C_he": 0.003, "C_bc": 0.0, "C_hd": 0.006}
_EXTRA_STARTS = (
    {"C_m": 0.03, "beta_m": 0.3, "C_he": 0.005, "C_bc": 0.002, "C_hd": 0.01},
    {"C_m": 0.12, "beta_m": 0.8, "C_he": 0.01, "C_bc": 0.005, "C_hd": 0.02},
)
#: ``method`` → the fixed starts its iterations begin from (``"tables"`` adds each spectrum's nearest
#: library entries). Chosen on simulated spectra at the render bands (point_fit.csv): the library's two
#: nearest plus the two dark starts keep up with the exact fit; the nearest alone plus the paper's start
#: did not, on a few spectra (other minima of eight bands and five unknowns; docs/model.md, "From
#: reconstruct/spectrum/spectrum_fit.py").
METHODS = {"tables": _EXTRA_STARTS, "exact": (PAPER_START, *_EXTRA_STARTS)}
#: The library the tabulated fit starts from: every combination of these levels (1,440 spectra), spaced
#: about evenly in log concentration over the skin DWRR08 Table 2 spans and beyond.
LIBRARY_LEVELS = {
    "C_m": (0.001, 0.003, 0.01, 0.03, 0.1, 0.3),
    "beta_m": (0.05, 0.35, 0.65, 0.95),
    "C_he": (0.0005, 0.003, 0.01, 0.03),
    "C_bc": (0.0, 0.003, 0.02),
    "C_hd": (0.001, 0.003, 0.01, 0.03, 0.08),
}
#: Library entries each spectrum starts from (nearest first).
LIBRARY_STARTS = 2
#: The tabulated fit stops, after this many iterations, each start losing to its spectrum's best by
#: over ``PRUNE_FACTOR`` in cost: faster and no spectrum worse at the render bands, where pruning after
#: fewer iterations made some worse. The exact fit, the reference, runs every start to the end (pruned
#: the same way, a rare spectrum came out worse). The measurements: docs/model.md, "From
#: reconstruct/spectrum/spectrum_fit.py".
PRUNE_AFTER = 5
PRUNE_FACTOR = 4.0
#: A parameter within this fraction of its range of a bound is reported at the bound.
AT_BOUND_FRACTION = 1e-3
#: The free scale's log is kept within ±this (a factor e³: any calibration error is far inside).
_LOG_SCALE_LIMIT = 3.0
#: Peak memory per element of the batched problem (spectrum × start × unknown × sample; measured on
#: NIST's forearms: docs/model.md, "From reconstruct/spectrum/spectrum_fit.py") and the memory a chunk of spectra
#: may take.
_BYTES_PER_ELEMENT, _CHUNK_BYTES = 1200.0, 1 << 30


@dataclass
class SpectrumFit:
    """Per spectrum ``(B,)``: parameters, residual RMS (reflectance units), scale, bound flags; with a
    model that frees constants (``spectrum_models``), each constant's value ``(B,)`` and the names each
    spectrum freed (the rest at the settings' values)."""

    params: SkinParams
    rms_residual: torch.Tensor
    scale: torch.Tensor
    at_bound: list[list[str]]
    iterations: int
    converged: torch.Tensor
    fitted: torch.Tensor = field(repr=False)
    constants: dict[str, torch.Tensor] = field(default_factory=dict)
    freed: list[list[str]] = field(default_factory=list)


@dataclass
class BoxProblem:
    """The batched problem: ``target`` ``(B·S, L)``, the box ``[box_lo, box_hi]`` of the unknowns and
    ``predict`` ``(B·S, n)`` → ``(B·S, L)``."""

    target: torch.Tensor
    box_lo: torch.Tensor
    box_hi: torch.Tensor
    predict: Callable[[torch.Tensor], torch.Tensor]
    predict_and_jacobian: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    n_start: int  # starts per spectrum, consecutive rows


def fit_spectra(
    measured: torch.Tensor,
    wavelength_nm: torch.Tensor,
    model: SkinModel | None = None,
    *,
    free_scale: bool = False,
    specular_included: bool = False,
    max_iterations: int = 100,
    tolerance: float = 1e-7,
    starts: tuple[dict, ...] | None = None,
    method: str = "exact",
    chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SpectrumFit:
    """Least-squares fit of (C_m, β_m, C_he, C_bc, C_hd) [and a scale] to each spectrum ``(B, L)``.

    ``specular_included``: the measurement contains the smooth surface's first reflection
    (integrating sphere, specular included); it is added to the model as a constant F_r(8°).
    ``method``: ``"exact"`` (the default) iterates on the exact model (Jacobian by forward-mode
    autodiff) from the paper's start and two darker ones; ``"tables"`` iterates on the model's totals
    tabulated at these bands (``model.point_tables``: within ~1e-6 of the exact model, Jacobian in
    closed form) from each spectrum's two nearest entries of a library of model spectra and the two
    darker starts, pruning losing starts early (faster on NIST with the build and at eight bands, at
    the same residuals: docs/model.md, "From reconstruct/spectrum/spectrum_fit.py"). Either way the best end
    point is kept and its residual is the exact model's.
    ``starts`` replaces the fixed starts. ``chunk``: spectra fitted at once (default: as many as
    ``_CHUNK_BYTES`` holds); ``progress(done, total)`` after each chunk.
    """
    model = model or SkinModel()
    if method not in METHODS:
        raise ValueError(f"method must be one of {tuple(METHODS)}, got {method!r}")
    y = torch.as_tensor(measured, dtype=torch.float64)
    if y.ndim != 2:
        raise ValueError(f"measured spectra must be (B, L), got shape {tuple(y.shape)}")
    if not bool(torch.isfinite(y).all()):
        raise ValueError("measured spectra contain NaN or infinite values")
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    fixed = starts or METHODS[method]
    tables = model.point_tables(wl, y.device) if method == "tables" else None
    n_start = len(fixed) + (LIBRARY_STARTS if tables is not None and starts is None else 0)  # for the chunk size
    per_spectrum = n_start * (N_PARAMS + int(free_scale)) * wl.numel() * _BYTES_PER_ELEMENT
    size = chunk or max(1, int(_CHUNK_BYTES // per_spectrum))
    fits = []
    for first in range(0, y.shape[0], size):
        part = y[first:first + size]
        problem, x0 = _starts(part, wl, model, fixed, free_scale, specular_included, tables, library=starts is None)
        x, cost, converged, iterations = solve_box(problem, x0, max_iterations, tolerance, prune=method == "tables")
        fits.append(_best(problem, part, x, cost, converged, iterations, free_scale))
        if progress is not None:
            progress(first + part.shape[0], y.shape[0])
    return joined(fits)


def joined(fits: list[SpectrumFit]) -> SpectrumFit:
    """The chunks' fits as one, spectra in order."""
    if len(fits) == 1:
        return fits[0]
    return SpectrumFit(
        params=SkinParams.from_tensor(torch.cat([f.params.as_tensor() for f in fits])),
        rms_residual=torch.cat([f.rms_residual for f in fits]),
        scale=torch.cat([f.scale for f in fits]),
        at_bound=[names for f in fits for names in f.at_bound],
        iterations=max(f.iterations for f in fits),
        converged=torch.cat([f.converged for f in fits]),
        fitted=torch.cat([f.fitted for f in fits]),
        constants={n: torch.cat([f.constants[n] for f in fits]) for n in fits[0].constants},
        freed=[names for f in fits for names in f.freed],
    )


def specular_offset(model: SkinModel, included: bool) -> float:
    """The smooth surface's first reflection F_r(8°) a measurement with the specular included carries
    (an integrating sphere's SCI geometry), else 0."""
    if not included:
        return 0.0
    o = model.settings.optics
    return specular_reflectance(o.n_epidermis, o.n_above, cos_theta_i=math.cos(math.radians(8.0)))


def _starts(y, wl, model: SkinModel, starts, free_scale: bool, specular_included: bool, tables: PointTables | None,
            library: bool) -> tuple[BoxProblem, torch.Tensor]:
    """Every spectrum repeated once per start (its library entries first, where there are any), the
    unknowns scaled to the box, the model that predicts them and the one the iterations use."""
    lo, hi = parameter_bounds(y.dtype, y.device)
    span = hi - lo
    offset = specular_offset(model, specular_included)
    p0 = torch.tensor([[s[n] for n in PARAMETER_NAMES] for s in starts], dtype=y.dtype, device=y.device).reshape(-1, N_PARAMS)
    x = ((p0 - lo) / span)[None].expand(y.shape[0], -1, -1)  # (B, S, N_PARAMS) in [0, 1]
    log_g = torch.zeros(x.shape[:2] + (1,), dtype=y.dtype, device=y.device)
    if library and tables is not None:
        x_lib, log_g_lib = _library_start(y - offset, tables, free_scale)
        x, log_g = torch.cat([x_lib, x], 1), torch.cat([log_g_lib[..., None], log_g], 1)
    n_start = x.shape[1]
    x = x.reshape(-1, N_PARAMS)  # (B·S, N_PARAMS), spectrum-major
    box_lo, box_hi = torch.zeros(N_PARAMS, dtype=y.dtype, device=y.device), torch.ones(N_PARAMS, dtype=y.dtype, device=y.device)
    if free_scale:  # log scale, unbounded in practice
        x = torch.cat([x, log_g.reshape(-1, 1).clamp(-_LOG_SCALE_LIMIT, _LOG_SCALE_LIMIT)], dim=1)
        limit = torch.full((1,), _LOG_SCALE_LIMIT, dtype=y.dtype, device=y.device)
        box_lo, box_hi = torch.cat([box_lo, -limit]), torch.cat([box_hi, limit])

    def predict(xv: torch.Tensor) -> torch.Tensor:
        r = model.diffuse_reflectance(SkinParams.from_tensor(lo + span * xv[:, :N_PARAMS]), wl)
        if free_scale:
            r = r * torch.exp(xv[:, N_PARAMS:])
        return r + offset

    def tabulated(xv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r, jac = tables.diffuse_reflectance(lo + span * xv[:, :N_PARAMS])
        jac = jac * span
        if free_scale:
            g = torch.exp(xv[:, N_PARAMS:])
            r = r * g
            jac = torch.cat([jac * g[..., None], r[..., None]], -1)
        return r + offset, jac

    iterate = tabulated if tables is not None else (lambda xv: forward_jacobian(predict, xv))
    return BoxProblem(y.repeat_interleave(n_start, dim=0), box_lo, box_hi, predict, iterate, n_start), x


def _library_start(y: torch.Tensor, tables: PointTables, free_scale: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Each spectrum's ``LIBRARY_STARTS`` nearest entries ``(B, K, N_PARAMS)`` (box-scaled) of a lattice
    of model spectra, and their log scales ``(B, K)`` (the least-squares ones with a free scale, else 0)."""
    lo, hi = parameter_bounds(y.dtype, y.device)
    grid = torch.cartesian_prod(*(torch.tensor(LIBRARY_LEVELS[n], dtype=y.dtype, device=y.device) for n in PARAMETER_NAMES))
    entries, _ = tables.diffuse_reflectance(grid)  # (T, L)
    cross = y @ entries.T  # (B, T)
    power = (entries**2).sum(-1)
    if free_scale:
        gain = (cross / power).clamp_min(1e-12)
        score = -(cross.clamp_min(0.0) ** 2) / power
    else:
        gain = torch.ones_like(cross)
        score = power - 2.0 * cross
    pick = score.topk(LIBRARY_STARTS, dim=1, largest=False).indices  # (B, K)
    return (grid[pick] - lo) / (hi - lo), torch.log(gain.gather(1, pick))


def solve_box(problem: BoxProblem, x: torch.Tensor, max_iterations: int, tolerance: float, prune: bool = False):
    """Projected LM on the box until every problem has converged: a variable resting on a bound with the
    gradient pushing outward is held there. Only problems not yet converged are evaluated. With
    ``prune``, after ``PRUNE_AFTER`` iterations a start whose cost is over ``PRUNE_FACTOR`` times its
    spectrum's best start's is stopped where it is (it cannot be the one kept unless it would have
    overtaken). Returns the end points, their costs ‖r‖², the converged flags (a stopped start counts
    as converged) and the iterations run."""

    def residual_and_jacobian(xv, target):
        value, jac = problem.predict_and_jacobian(xv)
        return value - target, jac

    lo, hi = problem.box_lo, problem.box_hi
    damping = torch.full((x.shape[0],), LAMBDA0, dtype=x.dtype, device=x.device)
    res, jac = residual_and_jacobian(x, problem.target)
    cost = (res**2).sum(-1)
    converged = torch.zeros_like(cost, dtype=torch.bool)
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        act = (~converged).nonzero()[:, 0]
        xa, ra, ja, ca, da = x[act], res[act], jac[act], cost[act], damping[act]
        grad = (ja.transpose(1, 2) @ ra[..., None])[..., 0]
        free = (~(((xa <= lo) & (grad > 0)) | ((xa >= hi) & (grad < 0)))).to(x.dtype)
        jac_f, grad_f = ja * free[:, None, :], grad * free
        step = damped_step(jac_f.transpose(1, 2) @ jac_f, grad_f, da)
        x_new = torch.minimum(torch.maximum(xa + step, lo), hi)
        res_new, jac_new = residual_and_jacobian(x_new, problem.target[act])
        cost_new = (res_new**2).sum(-1)
        better = cost_new < ca
        moved = (x_new - xa).abs().max(-1).values
        gain = (ca - cost_new) / predicted_decrease(jac_f, x_new - xa, grad_f).clamp_min(1e-30)
        da = next_damping(da, better, gain, ~better)
        x[act] = torch.where(better[:, None], x_new, xa)
        res[act] = torch.where(better[:, None], res_new, ra)
        jac[act] = torch.where(better[:, None, None], jac_new, ja)
        cost[act] = torch.where(better, cost_new, ca)
        damping[act] = da
        relative = (ca - cost_new) / ca.clamp_min(1e-30)
        # converged: the cost stopped falling, the step vanished, or no damping makes it fall
        converged[act] = (better & ((relative < tolerance) | (moved < 1e-9))) | (~better & (moved < 1e-12)) | (da >= LAMBDA_MAX)
        if prune and problem.n_start > 1 and iterations == PRUNE_AFTER:
            per_spectrum = cost.view(-1, problem.n_start)
            losing = per_spectrum > PRUNE_FACTOR * per_spectrum.amin(1, keepdim=True)
            converged |= losing.reshape(-1)
        if bool(converged.all()):
            break
    return x, cost, converged, iterations


def _best(problem: BoxProblem, y, x, cost, converged, iterations: int, free_scale: bool) -> SpectrumFit:
    """Each spectrum's best start: its parameters, fitted spectrum, residual, scale and bounds reached."""
    n_spec, n_start = y.shape[0], problem.n_start
    pick = torch.arange(n_spec, device=y.device) * n_start + cost.reshape(n_spec, n_start).argmin(dim=1)
    x_best = x[pick]
    lo, hi = parameter_bounds(y.dtype, y.device)
    p = lo + (hi - lo) * x_best[:, :N_PARAMS]
    fitted = problem.predict(x_best)
    scale = torch.exp(x_best[:, N_PARAMS]) if free_scale else torch.ones(n_spec, dtype=y.dtype, device=y.device)
    hit = near_bound(p, AT_BOUND_FRACTION, dim=-1)
    return SpectrumFit(
        params=SkinParams.from_tensor(p),
        rms_residual=torch.sqrt(((fitted - y) ** 2).mean(-1)),
        scale=scale,
        at_bound=[[n for j, n in enumerate(PARAMETER_NAMES) if hit[b, j]] for b in range(n_spec)],
        iterations=iterations,
        converged=converged[pick],
        fitted=fitted,
    )
