"""First-order optimisers: the paper's forward-difference gradient descent and Adam on autograd.

``paper-fd`` is DWRR08 §6.3 as a runnable baseline: every step renders the patch once and once more
per parameter with that parameter's map shifted by ``fd_step`` everywhere at once, so each pixel's
forward difference includes the cross-talk of its shifted neighbours (the paper's "simultaneously
evaluating all forward differences"); 1 + N_PARAMS renders a step. The paper gives no step rule; this one is
generous to it: each parameter's gradient is divided by that parameter's mean squared sensitivity over
the patch (one number per parameter map, from the same differences: plain descent in x stalls far
above the noise because the sensitivities differ by orders of magnitude; docs/reconstruct.md), and
the step length grows by 1.2 after every success and halves after a failure ("bold
driver", Battiti 1989), starting so that the largest change is ``learning_rate``.

``adam`` is Adam (Kingma & Ba 2015) on the exact gradient of one forward+backward render per step.

Both test convergence over a window of steps (their single steps are too small for the per-step
test, which stopped the baseline after a few steps far above the noise): relative loss decrease over the last
``_WINDOW`` steps below ftol; at most ``FIRST_ORDER_CAP`` × max_iterations steps (600 by default; the
paper ran 200–500).
"""

from __future__ import annotations

import time

import torch

from ...model import N_PARAMS
from ..levels.problem import LevelProblem, OptimResult
from ..levels.unknowns import X_LIMIT

__all__ = ["FIRST_ORDER_CAP", "adam", "paper_forward_differences"]

_WINDOW = 20
FIRST_ORDER_CAP = 10  # first-order methods get this many times the Gauss–Newton iteration cap


def _window_converged(history: list[tuple[float, float]], ftol: float) -> bool:
    if len(history) <= _WINDOW:
        return False
    old, new = history[-1 - _WINDOW][1], history[-1][1]
    return (old - new) / max(old, 1e-300) < ftol


def paper_forward_differences(problem: LevelProblem, x0, log_scale0, settings, progress=None) -> OptimResult:
    """DWRR08 §6.3: gradient descent, gradient by forward differences of whole-map shifts."""
    ev = problem.evaluate(x0, log_scale0)
    h = settings.fd_step
    history = [(time.process_time(), ev.loss)]
    eta = None
    converged = False
    it = 0
    for it in range(1, FIRST_ORDER_CAP * settings.max_iterations + 1):
        grad = torch.empty(problem.n_pixels, N_PARAMS, dtype=x0.dtype, device=x0.device)
        for k in range(N_PARAMS):
            shifted = ev.x.clone()
            shifted[k] = (shifted[k] + h).clamp(-X_LIMIT, X_LIMIT)
            moved = problem.evaluate(shifted, ev.log_scale)
            derivative = (moved.residual - ev.residual) / h  # the residual's change = the prediction's
            grad[:, k] = (derivative * ev.residual).sum(1) / (derivative**2).sum(1).mean().clamp_min(1e-30)
        col = problem.at_pixels(ev.image) * torch.exp(ev.log_scale) * problem.row_weight
        grad_scale = (col * ev.residual).sum() / (col**2).sum().clamp_min(1e-30) if settings.free_scale else torch.zeros((), dtype=x0.dtype)
        if eta is None:
            eta = settings.learning_rate / max(float(grad.abs().max()), float(grad_scale.abs()), 1e-30)
        accepted = False
        while eta > 1e-30:
            x_new = ev.x.clone().reshape(N_PARAMS, -1)
            x_new[:, problem.pixels] = (x_new[:, problem.pixels] - eta * grad.T).clamp(-X_LIMIT, X_LIMIT)
            trial = problem.evaluate(x_new.reshape(ev.x.shape), ev.log_scale - eta * grad_scale)
            if trial.loss < ev.loss:
                ev, accepted = trial, True
                eta *= 1.2
                break
            eta *= 0.5
        history.append((time.process_time(), ev.loss))
        if progress is not None:
            progress(it, ev.loss)
        if not accepted or _window_converged(history, settings.ftol):
            converged = True
            break
    return OptimResult(ev.x, ev.log_scale, ev, it, converged, history)


def adam(problem: LevelProblem, x0, log_scale0, settings, progress=None) -> OptimResult:
    """Adam (``torch.optim.Adam``) on the exact gradient; the iterate with the lowest loss is returned.
    The unknowns are one row per pixel ``(N, N_PARAMS + 1)``: its maps, then its share of the scale, whose
    gradient is spread over the pixels so its moments stay comparable with the maps' (the scale moves by
    the mean of the shares' steps)."""
    x = x0.detach().clone()
    log_scale = log_scale0.detach().clone()
    ev = problem.evaluate(x, log_scale, grad=True)
    best = ev
    history = [(time.process_time(), ev.loss)]
    unknowns = torch.zeros(problem.n_pixels, N_PARAMS + 1, dtype=x.dtype, device=x.device)
    optimizer = torch.optim.Adam([unknowns], lr=settings.learning_rate, betas=(0.9, 0.999), eps=1e-8)
    converged = False
    it = 0
    for it in range(1, FIRST_ORDER_CAP * settings.max_iterations + 1):
        col = problem.at_pixels(ev.image) * torch.exp(ev.log_scale) * problem.row_weight
        g_scale = (col * ev.residual).sum() if settings.free_scale else torch.zeros((), dtype=x.dtype)
        with torch.no_grad():  # from the point evaluated (a map on coarse nodes moves all its pixels)
            unknowns[:, :N_PARAMS] = problem.at_pixels(ev.x)
            unknowns[:, N_PARAMS] = 0.0
        unknowns.grad = torch.cat([ev.grad, (g_scale / problem.n_pixels).expand(problem.n_pixels, 1)], dim=1)
        optimizer.step()
        flat = ev.x.clone().reshape(N_PARAMS, -1)
        flat[:, problem.pixels] = unknowns.detach()[:, :N_PARAMS].T.clamp(-X_LIMIT, X_LIMIT)
        new_scale = ev.log_scale + (unknowns.detach()[:, N_PARAMS].mean() if settings.free_scale else 0.0)
        ev = problem.evaluate(flat.reshape(x.shape), new_scale, grad=True)
        if ev.loss < best.loss:
            best = ev
        history.append((time.process_time(), best.loss))
        if progress is not None:
            progress(it, best.loss)
        if _window_converged(history, settings.ftol):
            converged = True
            break
    return OptimResult(best.x, best.log_scale, best, it, converged, history)
