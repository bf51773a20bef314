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

from ...model import N_PARAMS
from ..levels.least_squares import LAMBDA0, LAMBDA_MAX, LAMBDA_MIN, block_factor, block_solve, next_damping, predicted_decrease
from ..levels.problem import Evaluation, HomogeneousProblem, LevelProblem, OptimResult
from ..levels.schur import solve_split_step
from ..levels.unknowns import X_LIMIT

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
    lm = _LevenbergMarquardt(problem, x0, log_scale0, settings, exact)
    it = 0
    for it in range(1, settings.max_iterations + 1):
        done = lm.iterate()
        if progress is not None:
            progress(it, lm.ev.loss)
        if done:
            break
    return lm.result(it)


class _LevenbergMarquardt:
    """The state of one level's LM fit: the evaluation, the coarse maps' nodes ``z``, the damping per
    pixel ``(N,)`` and of the shared unknowns, the Anderson memory, the curvature (re-made after an
    accepted step) and the rejections in a row."""

    def __init__(self, problem: LevelProblem, x0, log_scale0, settings, exact: bool) -> None:
        self.problem, self.settings, self.exact = problem, settings, exact
        self.z = problem.layout.project(x0)
        if not problem.layout.per_pixel:
            x0 = problem.layout.assemble(x0, self.z)
        self.ev = problem.evaluate(x0, log_scale0, grad=exact)
        n = problem.n_pixels
        self.lam = torch.full((n,), LAMBDA0, dtype=x0.dtype, device=x0.device)
        self.lam_scale = LAMBDA0
        self.history = [(time.process_time(), self.ev.loss)]
        self.accel = (_Anderson(settings.anderson_memory)
                      if settings.anderson_memory > 0 and problem.layout.per_pixel else None)
        self.rejections = 0
        self.converged = False
        self.step = torch.full((n,), float("nan"), dtype=x0.dtype, device=x0.device)
        self.jac = self.col = None
        self.decrement = 0.0

    def iterate(self) -> bool:
        """One step proposed, tried, and accepted or rejected; True once converged."""
        problem, ev = self.problem, self.ev
        if self.jac is None:
            self.jac, self.col = curvature_and_columns(problem, ev)
        grad = ev.grad if self.exact else (self.jac.transpose(1, 2) @ ev.residual[..., None])[..., 0]
        dx, dz, ds, accelerated = self._proposal(grad)
        x_trial, z_trial = _apply(problem, ev.x, dx, self.z, dz)
        trial = problem.evaluate(x_trial, ev.log_scale + ds, grad=self.exact)
        before = (ev.residual**2).sum(1)
        after = (trial.residual**2).sum(1)
        if trial.loss < ev.loss:
            predicted = predicted_decrease(self.jac, dx, grad, self.col, ds, (self.col * ev.residual).sum(1))
            return self._accept(trial, z_trial, (before - after) / predicted.clamp_min(1e-30), after > before)
        return self._reject(accelerated, after > before)

    def _proposal(self, grad):
        """The damped step (per-pixel ``dx``, coarse nodes ``dz``, scale ``ds``), clamped, and
        extrapolated by Anderson mixing after an accepted step."""
        problem, ev = self.problem, self.ev
        dx, dz, ds, self.decrement = level_step(problem, self.jac, self.col, grad, ev.residual, self.lam,
                                                self.lam_scale, self.settings.free_scale)
        dx, dz = dx.clamp(-_MAX_STEP, _MAX_STEP), dz.clamp(-_MAX_STEP, _MAX_STEP)
        if not problem.layout.per_pixel:  # the coarse maps' change where the clamped nodes put it
            dx[:, problem.layout.coarse] = problem.layout.at_pixels(dz, problem.pixels)
        self.step = dx.abs().amax(dim=1)
        accelerated = self.accel is not None and self.rejections == 0
        if accelerated:
            point = torch.cat([problem.at_pixels(ev.x).reshape(-1), ev.log_scale.reshape(1)])
            point_next = self.accel.next_point(point, torch.cat([dx.reshape(-1), ds.reshape(1)]))
            dx = (point_next[:-1] - point[:-1]).reshape(problem.n_pixels, N_PARAMS).clamp(-_MAX_STEP, _MAX_STEP)
            ds = point_next[-1] - point[-1]
        return dx, dz, ds, accelerated

    def _accept(self, trial, z_trial, gain, worse) -> bool:
        """The trial becomes the point; less damping where the model predicted the fall well."""
        self.lam = next_damping(self.lam, True, gain, worse)
        self.lam_scale = max(self.lam_scale / 3.0, LAMBDA_MIN)
        relative = (self.ev.loss - trial.loss) / max(self.ev.loss, 1e-300)
        self.ev, self.z, self.jac, self.rejections = trial, z_trial, None, 0
        self.history.append((time.process_time(), self.ev.loss))
        self.converged = relative < self.settings.ftol or float(self.step.max()) < self.settings.xtol
        return self.converged

    def _reject(self, accelerated: bool, worse) -> bool:
        """A failed extrapolation is forgotten (the plain step next); a failed plain step gets more
        damping. Converged when no step of any damping lowers the loss: a (local) optimum of this model."""
        if accelerated:
            self.accel.reset()
        else:
            self.lam = next_damping(self.lam, False, torch.zeros_like(self.lam), worse)
            self.lam_scale = min(self.lam_scale * 4.0, LAMBDA_MAX)
        self.rejections += 1
        limit = _rejection_limit(self.problem, self.settings, kept=len(self.history) > 1)
        self.converged = self.rejections >= limit or float(self.step.max()) < self.settings.xtol
        return self.converged

    def result(self, iterations: int) -> OptimResult:
        """The fit's record; the shared unknowns' last decrement as a χ² decrease (σ² from the residual:
        2·loss per element)."""
        ev = self.ev
        if self.jac is None:
            self.jac, self.col = curvature_and_columns(self.problem, ev)
        shared = (self.decrement / max(2.0 * ev.loss / max(ev.residual.numel(), 1), 1e-300)) if iterations else 0.0
        return OptimResult(ev.x, ev.log_scale, ev, iterations, self.converged, self.history, self.step,
                           self.jac.transpose(1, 2) @ self.jac, shared)


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
