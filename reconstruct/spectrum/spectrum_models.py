"""Point-spectrum fits that choose their own model: which fixed constants a spectrum supports freeing.

DWRR08 fits five chromophores with the epidermis's thickness, the dermal blood's oxygenation and the
dermis's scattering fixed (§5.1); a spectrum may support freeing some of them, and another may not.
``select_spectrum_models`` fits every candidate (the fixed model, then each subset of the freeable
constants, ``model/column/point_model.py``) and keeps, per spectrum, the one with the least Bayesian
information criterion (Schwarz 1978)

    noise σ known:   BIC = RSS/σ² + k ln n
    noise unknown:   BIC = n ln(RSS/n) + k ln n

(n samples, k unknowns): a constant is freed only where its drop in the residual pays for it. With σ
known this is the likelihood of white Gaussian noise; without, it is the profile likelihood with σ
estimated from the residual, which counts a model's own deficit, correlated across the samples, as
evidence: on real spectra it frees more than a true noise level would (docs/model.md, "Point fits that
choose their model").

The candidates are nested, and each is started from the best end point of the candidates it contains
(the added constant at the settings' value, where the smaller model had it), so a larger model's
residual is never above a smaller one's on the same spectrum: the comparison is between fits, not
between the luck of their starts. The fixed model is ``fit_spectra``'s fit; the others iterate on the
exact model (forward-mode Jacobian) with the projected Levenberg–Marquardt of ``spectrum_fit``.

Shapes: spectra ``(B, L)``; per candidate ``(B, C)``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal

import torch
from pydantic import field_validator

from ...formats.settings import Strict, load_settings
from ...model import N_PARAMS, PARAMETER_NAMES, SkinModel, SkinParams, parameter_bounds
from ...model.column.point_model import CONSTANT_NAMES, constant_bounds, constant_defaults, point_reflectance
from ..levels.least_squares import forward_jacobian
from ..settings import FitSettingsError
from .spectrum_fit import (
    _BYTES_PER_ELEMENT,
    _CHUNK_BYTES,
    _LOG_SCALE_LIMIT,
    AT_BOUND_FRACTION,
    BoxProblem,
    SpectrumFit,
    fit_spectra,
    joined,
    solve_box,
    specular_offset,
)
from ..levels.unknowns import near_bound

__all__ = [
    "EXTENDED_MAX_ITERATIONS",
    "FIXED_MODELS",
    "MODEL_CHOICES",
    "SpectrumModel",
    "SpectrumSelection",
    "candidate_label",
    "fit_with_constants",
    "load_spectrum_model",
    "select_spectrum_models",
    "spectrum_candidates",
]

Constant = Literal["epidermis_thickness_mm", "oxygenation_dermis", "dermis_scattering_ratio"]


class SpectrumModel(Strict):
    """A fixed choice of point model: the constants freed for every spectrum and whether a radiometric
    scale is free (YAML for ``fit-spectrum --model FILE``)."""

    free: list[Constant] = []
    free_scale: bool = False

    @field_validator("free")
    @classmethod
    def _ordered(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError(f"each constant at most once, got {value}")
        return [n for n in CONSTANT_NAMES if n in value]


#: The named fixed choices: DWRR08's own fit (five chromophores and a free scale: the paper's
#: measurements are calibrated only up to one) and the five chromophores alone.
FIXED_MODELS = {"paper": SpectrumModel(free_scale=True), "fixed": SpectrumModel()}
#: ``--model``'s named values; anything else is a YAML file of a ``SpectrumModel``.
MODEL_CHOICES = ("auto", *FIXED_MODELS)
#: Iterations of a fit that frees constants (``fit_spectra``'s limit). It starts at its nested model's
#: end point, so most spectra stop long before; on NIST's forearms a lower cap saved little time and left
#: some residuals higher (spectrum_models_nist.csv; docs/model.md, "Point fits that choose their model"),
#: so none is set.
EXTENDED_MAX_ITERATIONS = 100


def load_spectrum_model(path: str | Path) -> SpectrumModel:
    """A ``SpectrumModel`` from YAML; errors name the file and the key."""
    return load_settings(SpectrumModel, path, FitSettingsError, "spectrum model")


def spectrum_candidates(choice: str, free_scale: bool = False, profiles: str = "diffusion") -> tuple[list[tuple[str, ...]], bool]:
    """``--model``'s value as the candidates to weigh and whether the scale is free: ``"auto"`` every
    subset of the constants, a name of ``FIXED_MODELS`` or a YAML file its one model (``free_scale``
    adds a free scale to any of them). With ``profiles: transport`` the layers' totals are
    adding-doubling's, tabulated at the settings' constants, so ``auto`` has only the fixed model to
    weigh and a file that frees a constant is refused."""
    fixed = None if choice == "auto" else FIXED_MODELS.get(choice) or load_spectrum_model(choice)
    if profiles != "diffusion":
        if fixed is not None and fixed.free:
            raise FitSettingsError(f"{choice}: freeing {', '.join(fixed.free)} needs profiles: diffusion (the "
                                   f"transport profiles are tabulated at the settings' constants)")
        return [()], free_scale or (fixed is not None and fixed.free_scale)
    if fixed is None:
        return _candidates(None), free_scale
    return [tuple(fixed.free)], free_scale or fixed.free_scale


def candidate_label(names: tuple[str, ...]) -> str:
    """A candidate's name in reports: its freed constants joined by "+", or "fixed"."""
    return "+".join(names) or "fixed"


@dataclass
class SpectrumSelection:
    """Every candidate's evidence and each spectrum's choice.

    ``candidates`` (C) name the freed constants of each (``()`` the fixed model); ``unknowns`` (C) its
    count of unknowns k; ``rms_residual`` and ``criterion`` ``(B, C)``; ``choice`` ``(B,)`` the index
    of the least criterion; ``fit`` the chosen fit per spectrum (its ``freed`` says which); ``fits``
    every candidate's fit of every spectrum.
    """

    fit: SpectrumFit
    candidates: list[tuple[str, ...]]
    unknowns: list[int]
    rms_residual: torch.Tensor
    criterion: torch.Tensor
    choice: torch.Tensor
    criterion_name: str
    samples: int
    fits: dict[tuple[str, ...], SpectrumFit]

    def reason(self, b: int) -> str:
        """Why spectrum ``b``'s model won, in words: its criterion against the fixed model's and
        against the best candidate with one constant fewer (or more)."""
        c = int(self.choice[b])
        crit, rms = self.criterion[b], self.rms_residual[b]
        chosen = self.candidates[c]
        name = ", ".join(chosen) or "no constant"
        fixed = self.candidates.index(()) if () in self.candidates else None
        if not chosen or fixed is None:
            larger = [j for j, cand in enumerate(self.candidates) if set(chosen) < set(cand)]
            if not larger:
                return f"{name} freed: the only candidate"
            j = min(larger, key=lambda j: float(crit[j]))
            return (f"{name} freed: freeing {', '.join(sorted(set(self.candidates[j]) - set(chosen)))} would lower the "
                    f"RMS residual {float(rms[c]):.4g} → {float(rms[j]):.4g}, not enough for its unknowns "
                    f"(ΔBIC {float(crit[j] - crit[c]):+.1f})")
        return (f"freeing {name} lowered the RMS residual {float(rms[fixed]):.4g} → {float(rms[c]):.4g} "
                f"(ΔBIC {float(crit[c] - crit[fixed]):+.1f} against the fixed model)")


def select_spectrum_models(
    measured: torch.Tensor,
    wavelength_nm: torch.Tensor,
    model: SkinModel | None = None,
    *,
    candidates: list[tuple[str, ...]] | None = None,
    free_scale: bool = False,
    specular_included: bool = False,
    noise: float | None = None,
    method: str = "exact",
    max_iterations: int = EXTENDED_MAX_ITERATIONS,
    progress: Callable[[int, int], None] | None = None,
) -> SpectrumSelection:
    """Fit every candidate model to each spectrum ``(B, L)`` and keep, per spectrum, the least BIC.

    ``candidates``: tuples of constant names (default: every subset of ``CONSTANT_NAMES``, the fixed
    model ``()`` among them). ``noise``: the measurement's noise σ (reflectance units), when known.
    ``method`` is the fixed model's (``fit_spectra``). ``progress(done, total)`` in candidates fitted
    (fractions while the fixed model's chunks of spectra go by).
    """
    model = model or SkinModel()
    if noise is not None and not (math.isfinite(noise) and noise > 0):
        raise ValueError(f"noise must be a positive reflectance, got {noise}")
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    order = _candidates(candidates)
    total = len(order) + int(() not in order)
    within = (lambda done, count: progress(done / count, total)) if progress is not None else None
    base = fit_spectra(measured, wl, model, free_scale=free_scale, specular_included=specular_included, method=method,
                       progress=within)
    fits: dict[tuple[str, ...], SpectrumFit] = {(): _with_defaults(base, model)}
    y = torch.as_tensor(measured, dtype=torch.float64)
    if progress is not None:
        progress(1, total)
    for done, names in enumerate((c for c in order if c), start=2):
        start = _nested_start(fits, names)
        fits[names] = fit_with_constants(y, wl, model, names, start, free_scale=free_scale,
                                         specular_included=specular_included, max_iterations=max_iterations)
        if progress is not None:
            progress(done, total)
    samples = wl.numel()
    unknowns = [N_PARAMS + int(free_scale) + len(c) for c in order]
    rms = torch.stack([fits[c].rms_residual for c in order], 1)  # (B, C)
    criterion, name = _bic(rms, samples, torch.tensor(unknowns, dtype=rms.dtype, device=rms.device), noise)
    choice = criterion.argmin(1)
    return SpectrumSelection(_chosen([fits[c] for c in order], choice), order, unknowns, rms, criterion, choice, name,
                             samples, {c: fits[c] for c in order})


def _candidates(candidates: list[tuple[str, ...]] | None) -> list[tuple[str, ...]]:
    """The candidates in order of size (each after every candidate it contains), names in
    ``CONSTANT_NAMES`` order, without repeats."""
    if candidates is None:
        candidates = [c for k in range(len(CONSTANT_NAMES) + 1) for c in itertools.combinations(CONSTANT_NAMES, k)]
    out: list[tuple[str, ...]] = []
    for c in candidates:
        unknown = set(c) - set(CONSTANT_NAMES)
        if unknown:
            raise ValueError(f"unknown constants {sorted(unknown)}; choose from {CONSTANT_NAMES}")
        ordered = tuple(n for n in CONSTANT_NAMES if n in c)
        if ordered not in out:
            out.append(ordered)
    return sorted(out, key=len)


def _bic(rms: torch.Tensor, samples: int, unknowns: torch.Tensor, noise: float | None) -> tuple[torch.Tensor, str]:
    """BIC ``(B, C)`` from the RMS residuals: noise known, RSS/σ² + k ln n; else n ln(RSS/n) + k ln n."""
    rss = samples * rms**2
    penalty = unknowns * math.log(samples)
    if noise is not None:
        return rss / noise**2 + penalty, f"BIC, noise σ = {noise:g}"
    return samples * torch.log((rss / samples).clamp_min(1e-300)) + penalty, "BIC, noise from the residual"


def _with_defaults(fit: SpectrumFit, model: SkinModel) -> SpectrumFit:
    """The fixed model's fit with the constants it held, at the settings' values, recorded."""
    b = fit.rms_residual.shape[0]
    fit.constants = {n: torch.full((b,), v, dtype=fit.rms_residual.dtype, device=fit.rms_residual.device)
                     for n, v in constant_defaults(model).items()}
    fit.freed = [[] for _ in range(b)]
    return fit


def _nested_start(fits: dict[tuple[str, ...], SpectrumFit], names: tuple[str, ...]) -> SpectrumFit:
    """Per spectrum, the best fit among the candidates already fitted that ``names`` contains (each
    holds the constants it did not free at the settings' values, which ``names`` starts from)."""
    inside = [fit for c, fit in fits.items() if set(c) < set(names)]
    rms = torch.stack([f.rms_residual for f in inside], 1)
    return _chosen(inside, rms.argmin(1))


def _chosen(fits: list[SpectrumFit], choice: torch.Tensor) -> SpectrumFit:
    """Spectrum b's row of ``fits[choice[b]]``, for every b."""
    rows = torch.arange(choice.numel(), device=choice.device)

    def pick(values):
        return torch.stack(list(values), 0)[choice, rows]

    c = choice.tolist()
    return SpectrumFit(
        params=SkinParams.from_tensor(pick(f.params.as_tensor() for f in fits)),
        rms_residual=pick(f.rms_residual for f in fits),
        scale=pick(f.scale for f in fits),
        at_bound=[fits[k].at_bound[b] for b, k in enumerate(c)],
        iterations=max(f.iterations for f in fits),
        converged=pick(f.converged for f in fits),
        fitted=pick(f.fitted for f in fits),
        constants={n: pick(f.constants[n] for f in fits) for n in fits[0].constants},
        freed=[fits[k].freed[b] for b, k in enumerate(c)],
    )


def fit_with_constants(
    measured: torch.Tensor,
    wavelength_nm: torch.Tensor,
    model: SkinModel,
    names: tuple[str, ...],
    start: SpectrumFit,
    *,
    free_scale: bool = False,
    specular_included: bool = False,
    max_iterations: int = EXTENDED_MAX_ITERATIONS,
    tolerance: float = 1e-7,
    chunk: int | None = None,
) -> SpectrumFit:
    """Fit the five parameters [a scale] and the named constants to each spectrum ``(B, L)`` from
    ``start`` (a fit whose ``constants`` hold at least the named ones), on the exact model; the
    constants not named stay at the settings' values (a nested start has them there)."""
    y = torch.as_tensor(measured, dtype=torch.float64)
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    n = N_PARAMS + int(free_scale) + len(names)
    size = chunk or max(1, int(_CHUNK_BYTES // (n * wl.numel() * _BYTES_PER_ELEMENT)))
    parts = []
    for first in range(0, y.shape[0], size):
        rows = slice(first, first + size)
        problem, x0, unpack = _problem(y[rows], wl, model, names, start, rows, free_scale, specular_included)
        x, _, converged, iterations = solve_box(problem, x0, max_iterations, tolerance)
        parts.append(_result(problem, y[rows], x, converged, iterations, unpack, model, names))
    return joined(parts)


def _problem(y, wl, model: SkinModel, names, start: SpectrumFit, rows: slice, free_scale: bool, specular_included: bool):
    """The box-scaled problem: unknowns ``(B, n)`` = parameters, [log scale], constants, each in its
    box; the start; and ``unpack(x)`` → (params, log scale or None, constants dict)."""
    lo, hi = parameter_bounds(y.dtype, y.device)
    c_lo, c_hi = (v.to(y) for v in constant_bounds(model, wl, names))
    offset = specular_offset(model, specular_included)
    p0 = (start.params.as_tensor()[rows].to(y) - lo) / (hi - lo)
    c0 = torch.stack([start.constants[n][rows].to(y) for n in names], 1)
    parts = [p0.clamp(0.0, 1.0)]
    box_lo, box_hi = [torch.zeros(N_PARAMS, dtype=y.dtype, device=y.device)], [torch.ones(N_PARAMS, dtype=y.dtype, device=y.device)]
    if free_scale:
        limit = torch.full((1,), _LOG_SCALE_LIMIT, dtype=y.dtype, device=y.device)
        parts.append(torch.log(start.scale[rows].to(y))[:, None].clamp(-_LOG_SCALE_LIMIT, _LOG_SCALE_LIMIT))
        box_lo.append(-limit)
        box_hi.append(limit)
    parts.append(((c0 - c_lo) / (c_hi - c_lo)).clamp(0.0, 1.0))
    box_lo.append(torch.zeros(len(names), dtype=y.dtype, device=y.device))
    box_hi.append(torch.ones(len(names), dtype=y.dtype, device=y.device))
    first_constant = N_PARAMS + int(free_scale)

    def unpack(xv: torch.Tensor):
        params = SkinParams.from_tensor(lo + (hi - lo) * xv[:, :N_PARAMS])
        log_scale = xv[:, N_PARAMS] if free_scale else None
        freed = c_lo + (c_hi - c_lo) * xv[:, first_constant:]
        return params, log_scale, {n: freed[:, i] for i, n in enumerate(names)}

    def predict(xv: torch.Tensor) -> torch.Tensor:
        params, log_scale, constants = unpack(xv)
        r = point_reflectance(model, params, wl, constants)
        if log_scale is not None:
            r = r * torch.exp(log_scale)[:, None]
        return r + offset

    problem = BoxProblem(y, torch.cat(box_lo), torch.cat(box_hi), predict, lambda xv: forward_jacobian(predict, xv), 1)
    return problem, torch.cat(parts, 1), unpack


def _result(problem: BoxProblem, y, x, converged, iterations: int, unpack, model: SkinModel, names) -> SpectrumFit:
    """The end points as a ``SpectrumFit``: a freed constant within ``AT_BOUND_FRACTION`` of its range of
    a bound is listed with the parameters at theirs."""
    params, log_scale, constants = unpack(x)
    fitted = problem.predict(x)
    p = params.as_tensor()
    hit = near_bound(p, AT_BOUND_FRACTION, dim=-1)
    first_constant = x.shape[1] - len(names)
    c_hit = (x[:, first_constant:] <= AT_BOUND_FRACTION) | (x[:, first_constant:] >= 1.0 - AT_BOUND_FRACTION)
    b = y.shape[0]
    at_bound = [[n for j, n in enumerate(PARAMETER_NAMES) if hit[i, j]] + [n for j, n in enumerate(names) if c_hit[i, j]]
                for i in range(b)]
    return SpectrumFit(
        params=params,
        rms_residual=torch.sqrt(((fitted - y) ** 2).mean(-1)),
        scale=torch.exp(log_scale) if log_scale is not None else torch.ones(b, dtype=y.dtype, device=y.device),
        at_bound=at_bound,
        iterations=iterations,
        converged=converged,
        fitted=fitted,
        constants={**{n: torch.full((b,), v, dtype=y.dtype, device=y.device) for n, v in constant_defaults(model).items()},
                   **{n: v.detach() for n, v in constants.items()}},
        freed=[list(names) for _ in range(b)],
    )
