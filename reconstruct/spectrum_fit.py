"""Fit the five skin parameters to point reflectance spectra with the homogeneous model.

A point measurement (a spectrometer, one pixel ignoring its neighbours) sees no spatial structure, so
the homogeneous two-layer model is all it needs: the diffuse reflectance R_d(λ) of PHYSICS.md §2 with
the layers' exact totals (closed form, smooth in every parameter).

All spectra (and all starts) are one batched, projected Levenberg–Marquardt problem: per spectrum a
5×5 (6×6 with a free scale) normal system, Jacobians by forward-mode autodiff, damping adapted per
spectrum. Parameters are scaled to [0, 1] by their DWRR08 Table 1 bounds and kept in that box; one
resting on a bound with the gradient pushing outward is held there, so a bound is reached exactly
(and reported) instead of approached forever, as a sigmoid reparameterisation would.

Shapes: spectra ``(B, L)``, wavelengths ``(L,)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import math

import torch
import torch.autograd.forward_ad as fwAD

from ..model import PARAMETER_BOUNDS, PARAMETER_NAMES, SkinModel, SkinParams
from ..model.radiometry import specular_reflectance

__all__ = ["PAPER_START", "SpectrumFit", "fit_spectra"]

#: DWRR08 §8: eumelanin 0.73%, pheomelanin 0.3%, epidermal blood 0.3%, carotene 0, dermal blood 0.6%.
PAPER_START = {"C_m": 0.0103, "beta_m": 0.73 / 1.03, "C_he": 0.003, "C_bc": 0.0, "C_hd": 0.006}
_EXTRA_STARTS = (
    {"C_m": 0.03, "beta_m": 0.3, "C_he": 0.005, "C_bc": 0.002, "C_hd": 0.01},
    {"C_m": 0.12, "beta_m": 0.8, "C_he": 0.01, "C_bc": 0.005, "C_hd": 0.02},
)
AT_BOUND_FRACTION = 1e-3


@dataclass
class SpectrumFit:
    """Per spectrum ``(B,)``: parameters, residual RMS (reflectance units), scale, bound flags."""

    params: SkinParams
    rms_residual: torch.Tensor
    scale: torch.Tensor
    at_bound: list[list[str]]
    iterations: int
    converged: torch.Tensor
    fitted: torch.Tensor = field(repr=False)


def _bounds(dtype, device):
    lo = torch.tensor([PARAMETER_BOUNDS[n][0] for n in PARAMETER_NAMES], dtype=dtype, device=device)
    hi = torch.tensor([PARAMETER_BOUNDS[n][1] for n in PARAMETER_NAMES], dtype=dtype, device=device)
    return lo, hi


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
) -> SpectrumFit:
    """Least-squares fit of (C_m, β_m, C_he, C_bc, C_hd) [and a scale] to each spectrum ``(B, L)``.

    ``specular_included``: the measurement contains the smooth surface's first reflection
    (integrating sphere, specular included); it is added to the model as a constant F_r(8°).
    Each spectrum is started from the paper's pale-skin start and from two darker ones; the best
    end point is kept.
    """
    model = model or SkinModel()
    y = torch.as_tensor(measured, dtype=torch.float64)
    if y.ndim != 2:
        raise ValueError(f"measured spectra must be (B, L), got shape {tuple(y.shape)}")
    if not bool(torch.isfinite(y).all()):
        raise ValueError("measured spectra contain NaN or infinite values")
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    dev = y.device
    starts = starts or (PAPER_START, *_EXTRA_STARTS)
    n_spec, n_start = y.shape[0], len(starts)
    lo, hi = _bounds(y.dtype, y.device)
    p0 = torch.tensor([[s[n] for n in PARAMETER_NAMES] for s in starts], dtype=y.dtype, device=dev)
    x = ((p0 - lo) / (hi - lo)).repeat(n_spec, 1)  # (B*S, 5) in [0, 1], spectrum-major
    n_free = 5
    if free_scale:
        x = torch.cat([x, torch.zeros(x.shape[0], 1, dtype=x.dtype, device=dev)], dim=1)
    box_lo = torch.zeros(x.shape[1], dtype=x.dtype, device=dev)
    box_hi = torch.ones(x.shape[1], dtype=x.dtype, device=dev)
    if free_scale:  # log scale, unbounded in practice
        box_lo[5], box_hi[5] = -3.0, 3.0
    target = y.repeat_interleave(n_start, dim=0)
    offset = 0.0
    if specular_included:
        o = model.settings.optics
        offset = specular_reflectance(o.n_epidermis, o.n_above, cos_theta_i=math.cos(math.radians(8.0)))

    def predict(xv: torch.Tensor) -> torch.Tensor:
        p = lo + (hi - lo) * xv[:, :n_free]
        r = model.diffuse_reflectance(SkinParams.from_tensor(p), wl)
        if free_scale:
            r = r * torch.exp(xv[:, 5:6])
        return r + offset

    def residual_and_jacobian(xv: torch.Tensor, tgt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One forward-mode pass over the batch repeated once per unknown, each copy with one tangent."""
        n, b = xv.shape[1], xv.shape[0]
        tangents = torch.eye(n, dtype=xv.dtype, device=xv.device).repeat_interleave(b, dim=0)
        with fwAD.dual_level():
            out = predict(fwAD.make_dual(xv.repeat(n, 1), tangents))
            primal, tangent_out = fwAD.unpack_dual(out)
        jac = tangent_out.reshape(n, b, -1).permute(1, 2, 0)
        return primal[:b] - tgt, jac

    # Projected Levenberg–Marquardt on the box: a variable resting on a bound with the gradient
    # pushing outward is held there (its row and column replaced by the identity). Only problems not
    # yet converged are evaluated.
    damping = torch.full((x.shape[0],), 1e-3, dtype=x.dtype, device=dev)
    res, jac = residual_and_jacobian(x, target)
    cost = (res**2).sum(-1)
    converged = torch.zeros_like(cost, dtype=torch.bool)
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        act = (~converged).nonzero()[:, 0]
        xa, ra, ja, ca, da = x[act], res[act], jac[act], cost[act], damping[act]
        grad = (ja.transpose(1, 2) @ ra[..., None])[..., 0]
        held = ((xa <= box_lo) & (grad > 0)) | ((xa >= box_hi) & (grad < 0))
        free = (~held).to(x.dtype)
        jac_f = ja * free[:, None, :]
        jtj = jac_f.transpose(1, 2) @ jac_f
        diag = torch.diagonal(jtj, dim1=1, dim2=2)
        system = jtj + torch.diag_embed(da[:, None] * diag + 1e-12 + (1.0 - free))
        step = -torch.linalg.solve(system, (grad * free)[..., None])[..., 0]
        x_new = torch.minimum(torch.maximum(xa + step, box_lo), box_hi)
        res_new, jac_new = residual_and_jacobian(x_new, target[act])
        cost_new = (res_new**2).sum(-1)
        better = cost_new < ca
        gain = (ca - cost_new) / ca.clamp_min(1e-30)
        moved = (x_new - xa).abs().max(-1).values
        x[act] = torch.where(better[:, None], x_new, xa)
        res[act] = torch.where(better[:, None], res_new, ra)
        jac[act] = torch.where(better[:, None, None], jac_new, ja)
        cost[act] = torch.where(better, cost_new, ca)
        da = torch.where(better, da / 5.0, da * 4.0).clamp(1e-12, 1e12)
        damping[act] = da
        done = (better & ((gain < tolerance) | (moved < 1e-9))) | (~better & (moved < 1e-12)) | (da > 1e8)
        converged[act] = done
        if bool(converged.all()):
            break
    # keep the best start of every spectrum
    cost = cost.reshape(n_spec, n_start)
    best = cost.argmin(dim=1)
    pick = torch.arange(n_spec, device=dev) * n_start + best
    x_best = x[pick]
    p = lo + (hi - lo) * x_best[:, :5]
    fitted = predict(x_best)
    rms = torch.sqrt(((fitted - y) ** 2).mean(-1))
    scale = torch.exp(x_best[:, 5]) if free_scale else torch.ones(n_spec, dtype=y.dtype, device=dev)
    margin = AT_BOUND_FRACTION * (hi - lo)
    at_bound = [
        [n for j, n in enumerate(PARAMETER_NAMES) if p[b, j] <= lo[j] + margin[j] or p[b, j] >= hi[j] - margin[j]]
        for b in range(n_spec)
    ]
    return SpectrumFit(
        params=SkinParams.from_tensor(p),
        rms_residual=rms,
        scale=scale,
        at_bound=at_bound,
        iterations=iterations,
        converged=converged[pick],
        fitted=fitted,
    )
