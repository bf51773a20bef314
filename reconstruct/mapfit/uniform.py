"""Uniform skin: every map one value for the patch, fitted as one spectrum (``forward: auto`` on a cube
whose maps show no structure, ``fidelity.spatial_structure``; and, on every cube ``auto`` fits with the
homogeneous model, the skin its coarsest level's light factor is made at).

For uniform skin the model at pixel p and band b is s · m_b(θ) · f_b(p): one homogeneous spectrum
m(θ) of the five unknowns θ (R_d from the renderer's tables, the exit factor, the band correction)
times the window's light factor f (``fidelity.uniform_light_factor``) and the scale. The level's loss
½ Σ_p Σ_b w²_pb (s m_b f_pb − y_pb)² is then, up to a constant, ½ Σ_b A_b (s m_b − B_b/A_b)² with
A_b = Σ_p w² f² and B_b = Σ_p w² f y: the cube reduces to one light-weighted mean spectrum and its
weights, and the fit is a five-unknown Levenberg–Marquardt problem on nine numbers — the same optimum
as the per-pixel machinery with every map on one node, without evaluating the model at each pixel per
iteration. The pixels' robust weights w (``problem.pixel_weight``) enter A and B, so the robust passes
of ``fit_cube`` work as for every method.

Shapes: θ ``(N_PARAMS,)``; per band ``(L,)``; the unknowns returned ``(N_PARAMS, H, W)``, one value each.
"""

from __future__ import annotations

import time

import torch

from ...model import N_PARAMS
from ..levels.least_squares import LAMBDA0, LAMBDA_MAX, LAMBDA_MIN, damped_step, reverse_jacobian
from ..levels.problem import HomogeneousProblem, OptimResult
from ..levels.unknowns import X_LIMIT, to_params

__all__ = ["fit_uniform", "uniform_spectrum"]


def uniform_spectrum(problem: HomogeneousProblem, theta: torch.Tensor) -> torch.Tensor:
    """m(θ) ``(M, L)``: the homogeneous reflectance factor of each row of unknowns ``theta`` ``(M, N_PARAMS)``
    as ``problem.homogeneous_image`` gives it at every pixel (differentiable in θ)."""
    return problem.homogeneous_of(to_params(theta.T.reshape(N_PARAMS, theta.shape[0], 1)))[:, :, 0].T


def fit_uniform(problem: HomogeneousProblem, x0: torch.Tensor, log_scale0: torch.Tensor, settings, progress=None) -> OptimResult:
    """One value per map (the median of ``x0`` ``(N_PARAMS, H, W)`` over the loss pixels to start) by LM on
    the reduced problem (module docstring); the scale is held unless ``settings.free_scale``. Returns the
    unknowns broadcast to the level and the level's own evaluation at them (one homogeneous pass)."""
    dtype = torch.float64
    theta = x0.reshape(N_PARAMS, -1)[:, problem.pixels].median(dim=1).values.to(dtype)
    log_scale = log_scale0.detach().to(dtype).reshape(())
    w2 = problem.row_weight.to(dtype) ** 2
    w2 = w2.expand_as(problem.target) if w2.ndim == 1 else w2
    f = problem.at_pixels(problem.light_factor).to(dtype)
    y = problem.target.to(dtype)
    a = (w2 * f * f).sum(0)
    b = (w2 * f * y).sum(0)
    seen = a > 0
    mean = torch.where(seen, b / a.clamp_min(1e-300), torch.zeros_like(b))
    root = a.sqrt()
    free_scale = settings.free_scale

    def residual(rows: torch.Tensor) -> torch.Tensor:  # (M, L): √A_b (s m_b − B_b/A_b) of each row of unknowns
        th, ls = (rows[:, :N_PARAMS], rows[:, N_PARAMS:]) if free_scale else (rows, log_scale)
        return root * (torch.exp(ls) * uniform_spectrum(problem, th) - mean)

    point = torch.cat([theta, log_scale.view(1)]) if free_scale else theta
    r = residual(point[None])[0].detach()
    loss = 0.5 * float((r * r).sum())
    lam = torch.full((1,), LAMBDA0, dtype=dtype, device=theta.device)
    history = [(time.process_time(), loss)]
    converged, it = False, 0
    for it in range(1, settings.max_iterations + 1):
        jac = reverse_jacobian(residual, point[None])[1][0]  # (L, n)
        grad = jac.T @ r
        step = damped_step((jac.T @ jac)[None], grad[None], lam)[0]
        trial_point = point + step
        trial_point[:N_PARAMS] = trial_point[:N_PARAMS].clamp(-X_LIMIT, X_LIMIT)
        trial = residual(trial_point[None])[0].detach()
        trial_loss = 0.5 * float((trial * trial).sum())
        if trial_loss < loss:
            relative = (loss - trial_loss) / max(loss, 1e-300)
            point, r, loss = trial_point, trial, trial_loss
            lam = (lam / 3.0).clamp_min(LAMBDA_MIN)
            history.append((time.process_time(), loss))
            if progress is not None:
                progress(it, loss)
            if relative < settings.ftol or float(step.abs().max()) < settings.xtol:
                converged = True
                break
        else:
            lam = lam * 4.0
            if float(lam) > LAMBDA_MAX or float(step.abs().max()) < settings.xtol:
                converged = True  # no damping lowers the loss: the optimum
                break
    theta = point[:N_PARAMS]
    if free_scale:
        log_scale = point[N_PARAMS]
    h, w = problem.level.shape
    x = theta.to(x0.dtype).view(N_PARAMS, 1, 1).expand(N_PARAMS, h, w).contiguous()
    ev = problem.evaluate(x, log_scale.to(x0.dtype))
    return OptimResult(x, ev.log_scale, ev, it, converged, history)
