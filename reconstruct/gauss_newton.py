"""Gauss–Newton / Levenberg–Marquardt with per-pixel N_PARAMS × N_PARAMS normal equations and one global scale.

Curvature. Each pixel's block is J̃ᵢᵀJ̃ᵢ with J̃ᵢ = s · fᵢ ⊙ J_h(xᵢ): the Jacobian of the pixel's
*homogeneous* model (``LevelProblem.homogeneous_jacobian``, closed form, batched), scaled per band by
the light factor fᵢ = (heterogeneous render)/(homogeneous model) that the window's edges and the
neighbours impose, times the scale s. The scale's column is the prediction itself (∂(s·R)/∂log s =
s·R, exact); it couples every pixel and is eliminated by the Schur complement, so a step costs N
batched small solves and two reductions.

Gradient. ``gn`` takes the exact Jᵀr from one forward+backward pass of the heterogeneous renderer: a
preconditioned step whose fixed point is the heterogeneous optimum. ``gn-hom`` uses J̃ᵀr, needing no
backward pass: it is Gauss–Newton with an approximate Jacobian (the neighbours' share of a pixel's
sensitivity left out), whose fixed point satisfies J̃ᵀr = 0 instead of Jᵀr = 0 — the same point when
the model fits the data (``tests/reconstruct/test_fit_recovery.py`` fits noise-free renders of a
heterogeneous scene). With noise it is not the least-squares optimum, but it reaches a lower loss than
``gn`` and ``adam`` in a fraction of their time, with smaller parameter errors (the optimisers side by
side: ``tests/bench/test_bench_reconstruct.py``, figures in docs/speed.md). The exact gradient
preconditioned by the homogeneous curvature converges slowly: detail finer than the light's spread
reaches the gradient through J's neighbours' share twice (Jᵀ J), the curvature not at all.

Damping and acceptance (``least_squares``: the damped step and the damping rule every fit here uses):
the damped system (J̃ᵀJ̃ + λᵢ D) δ = −g with D the diagonal; a step is kept when the true loss (a full
render) falls; each pixel's λ follows its own gain ratio (actual over predicted decrease of its residual).
"""

from __future__ import annotations

import time

import torch

from ..model import N_PARAMS
from .least_squares import LAMBDA0, LAMBDA_MAX, LAMBDA_MIN, block_factor, block_solve, next_damping, predicted_decrease
from .problem import Evaluation, HomogeneousProblem, LevelProblem, OptimResult
from .schur import solve_split_step
from .unknowns import X_LIMIT

__all__ = ["curvature_and_columns", "gauss_newton", "gn_exact", "gn_homogeneous", "level_step", "solve_step"]

_MAX_STEP = 3.0  # largest change of any x in one step (a factor e³ in a small concentration)
_REJECTIONS = 5  # rejected steps in a row that end a pass: no damping lowers the loss
_FIRST_REJECTIONS = 12


def curvature_and_columns(problem: LevelProblem, ev: Evaluation) -> tuple[torch.Tensor, torch.Tensor]:
    """J̃ ``(N, L, N_PARAMS)`` (homogeneous Jacobian × light factor × scale, unused bands zeroed) and the
    scale column c ``(N, L)`` = the scaled prediction at the loss pixels."""
    hom, jac = problem.homogeneous_jacobian(problem.at_pixels(ev.x))
    het = problem.at_pixels(ev.image)  # (N, L)
    scale = torch.exp(ev.log_scale)
    factor = (het / hom.clamp_min(1e-12)).clamp(0.0, 2.0) * scale * problem.row_weight
    return jac * factor[..., None], het * scale * problem.row_weight


def solve_step(
    jac: torch.Tensor, col: torch.Tensor, grad: torch.Tensor, grad_scale: torch.Tensor, lam: torch.Tensor,
    lam_scale: float, free_scale: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Damped Gauss–Newton step: ``δx`` ``(N, N_PARAMS)``, ``δ log s`` (0-d), and ``A = J̃ᵀJ̃`` ``(N, N_PARAMS, N_PARAMS)``.

    ``grad`` ``(N, N_PARAMS)`` is ∂loss/∂x, ``grad_scale`` ∂loss/∂log s; the scale enters by the Schur
    complement of the per-pixel blocks, each solved as ``least_squares.block_factor`` solves every block."""
    dtype = grad.dtype
    j = jac.double()
    a = j.transpose(1, 2) @ j
    factor = block_factor(a, lam.double())
    a_inv_g = block_solve(factor, grad.double()[..., None])[..., 0]
    if not free_scale:
        return (-a_inv_g).to(dtype), torch.zeros((), dtype=dtype, device=grad.device), a.to(dtype)
    b = (j.transpose(1, 2) @ col.double()[..., None])[..., 0]  # (N, N_PARAMS)
    a_inv_b = block_solve(factor, b[..., None])[..., 0]
    c = (col.double() ** 2).sum()
    schur = c * (1.0 + lam_scale) - (b * a_inv_b).sum()
    d_scale = -(grad_scale.double() - (b * a_inv_g).sum()) / schur.clamp_min(1e-12 * float(c) + 1e-300)
    return (-(a_inv_g + a_inv_b * d_scale)).to(dtype), d_scale.to(dtype), a.to(dtype)


def _apply(problem: LevelProblem, x: torch.Tensor, dx: torch.Tensor, z: torch.Tensor, dz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The unknowns after a step: fine maps move at the loss pixels, coarse maps follow their nodes."""
    out = x.clone()
    flat = out.reshape(N_PARAMS, -1)
    fine = problem.layout.fine
    rows = torch.tensor(fine, dtype=torch.long, device=x.device)
    moved = (flat[rows][:, problem.pixels] + dx[:, fine].T).clamp(-X_LIMIT, X_LIMIT)
    flat[rows[:, None], problem.pixels[None, :]] = moved
    if problem.layout.per_pixel:
        return out, z
    z = (z + dz).clamp(-X_LIMIT, X_LIMIT)
    return problem.layout.assemble(out, z), z


def level_step(problem: LevelProblem, jac, col, grad, residual, lam, lam_scale, free_scale):
    """(dx ``(N, N_PARAMS)``, dz, d log s, shared decrement) of the damped system: per-pixel blocks, or
    with shared nodes."""
    if problem.layout.per_pixel:
        dx, ds, _ = solve_step(jac, col, grad, (col * residual).sum(), lam, lam_scale, free_scale)
        return dx, jac.new_zeros(0), ds, 0.0
    return solve_split_step(jac, col, grad, (col * residual).sum(1), lam, lam_scale, free_scale, problem.layout, problem.pixels)


class _Anderson:
    """Anderson acceleration of the fixed-point map z ↦ z + δ(z) (Anderson 1965; Walker & Ni 2011,
    type II): the next point combines the last ``memory`` steps so that their linearised residual is
    least — GMRES on the linearised map, at the cost of a few inner products and no render."""

    def __init__(self, memory: int) -> None:
        self.memory = memory
        self.points: list[torch.Tensor] = []
        self.steps: list[torch.Tensor] = []

    def reset(self) -> None:
        self.points, self.steps = [], []

    def next_point(self, z: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        self.points.append(z.double())
        self.steps.append(f.double())
        self.points, self.steps = self.points[-self.memory - 1:], self.steps[-self.memory - 1:]
        if len(self.points) < 2:
            return z + f
        df = torch.stack([b - a for a, b in zip(self.steps[:-1], self.steps[1:])], dim=1)
        dg = torch.stack([(b + fb) - (a + fa) for a, b, fa, fb in zip(self.points[:-1], self.points[1:], self.steps[:-1], self.steps[1:])], dim=1)
        gram = df.T @ df
        gram = gram + 1e-10 * torch.trace(gram) * torch.eye(gram.shape[0], dtype=gram.dtype, device=gram.device)
        gamma = torch.linalg.solve(gram, df.T @ self.steps[-1])
        return (self.points[-1] + self.steps[-1] - dg @ gamma).to(z.dtype)


def gauss_newton(problem: LevelProblem, x0, log_scale0, settings, progress=None, *, exact: bool) -> OptimResult:
    """LM iterations until the convergence test holds (``exact``: gradient from the backward pass)."""
    z = problem.layout.project(x0)
    if not problem.layout.per_pixel:
        x0 = problem.layout.assemble(x0, z)
    ev = problem.evaluate(x0, log_scale0, grad=exact)
    n = problem.n_pixels
    lam = torch.full((n,), LAMBDA0, dtype=x0.dtype, device=x0.device)
    lam_scale = LAMBDA0
    history = [(time.process_time(), ev.loss)]
    accel = _Anderson(settings.anderson_memory) if settings.anderson_memory > 0 and problem.layout.per_pixel else None
    rejections = 0
    converged = False
    it = 0
    step = torch.full((n,), float("nan"), dtype=x0.dtype, device=x0.device)
    jac = col = None
    decrement = 0.0
    for it in range(1, settings.max_iterations + 1):
        if jac is None:
            jac, col = curvature_and_columns(problem, ev)
        grad = ev.grad if exact else (jac.transpose(1, 2) @ ev.residual[..., None])[..., 0]
        dx, dz, ds, decrement = level_step(problem, jac, col, grad, ev.residual, lam, lam_scale, settings.free_scale)
        dx, dz = dx.clamp(-_MAX_STEP, _MAX_STEP), dz.clamp(-_MAX_STEP, _MAX_STEP)
        if not problem.layout.per_pixel:  # the coarse maps' change where the clamped nodes put it
            dx[:, problem.layout.coarse] = problem.layout.at_pixels(dz, problem.pixels)
        step = dx.abs().amax(dim=1)
        accelerated = accel is not None and rejections == 0
        if accelerated:
            point = torch.cat([problem.at_pixels(ev.x).reshape(-1), ev.log_scale.reshape(1)])
            point_next = accel.next_point(point, torch.cat([dx.reshape(-1), ds.reshape(1)]))
            dx = (point_next[:-1] - point[:-1]).reshape(n, N_PARAMS).clamp(-_MAX_STEP, _MAX_STEP)
            ds = point_next[-1] - point[-1]
        x_trial, z_trial = _apply(problem, ev.x, dx, z, dz)
        trial = problem.evaluate(x_trial, ev.log_scale + ds, grad=exact)
        before = (ev.residual**2).sum(1)
        after = (trial.residual**2).sum(1)
        predicted = predicted_decrease(jac, dx, grad, col, ds, (col * ev.residual).sum(1))
        if trial.loss < ev.loss:
            gain = (before - after) / predicted.clamp_min(1e-30)
            lam = next_damping(lam, True, gain, after > before)
            lam_scale = max(lam_scale / 3.0, LAMBDA_MIN)
            relative = (ev.loss - trial.loss) / max(ev.loss, 1e-300)
            ev, z, jac, rejections = trial, z_trial, None, 0
            history.append((time.process_time(), ev.loss))
            if progress is not None:
                progress(it, ev.loss)
            if relative < settings.ftol or float(step.max()) < settings.xtol:
                converged = True
                break
        else:
            if accelerated:  # the extrapolation failed: forget it and take the plain step next
                accel.reset()
            else:
                lam = next_damping(lam, False, torch.zeros_like(lam), after > before)
                lam_scale = min(lam_scale * 4.0, LAMBDA_MAX)
            rejections += 1
            if progress is not None:
                progress(it, ev.loss)
            if rejections >= _rejection_limit(problem, settings, kept=len(history) > 1) or float(step.max()) < settings.xtol:
                converged = True  # no step of any damping lowers the loss: a (local) optimum of this model
                break
    if jac is None:
        jac, col = curvature_and_columns(problem, ev)
    # the shared unknowns' last decrement as a χ² decrease (σ² from the residual: 2·loss per element)
    shared = decrement / max(2.0 * ev.loss / max(ev.residual.numel(), 1), 1e-300) if it else 0.0
    return OptimResult(ev.x, ev.log_scale, ev, it, converged, history, step, jac.transpose(1, 2) @ jac, shared)


def _rejection_limit(problem: LevelProblem, settings, kept: bool) -> int:
    """Rejected steps in a row that end a pass. Before any step is kept the start may be far (its shared
    nodes projected from noisy per-pixel fits): the damping may grow further. With the renderer, once a
    step is kept, ``settings.renderer_retries`` + 1: a rejection there means the homogeneous curvature
    no longer predicts the renderer's response, and each retry costs a render."""
    if not kept:
        return _FIRST_REJECTIONS
    if isinstance(problem, HomogeneousProblem):
        return _REJECTIONS
    return settings.renderer_retries + 1


def gn_exact(problem, x0, log_scale0, settings, progress=None) -> OptimResult:
    return gauss_newton(problem, x0, log_scale0, settings, progress, exact=True)


def gn_homogeneous(problem, x0, log_scale0, settings, progress=None) -> OptimResult:
    return gauss_newton(problem, x0, log_scale0, settings, progress, exact=False)
