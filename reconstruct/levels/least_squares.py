"""The pieces every least-squares fit here is built of, written once: the Jacobian of a batch of small
problems (forward or reverse mode, whichever is cheaper for their shape), the damped (Levenberg–Marquardt) step of their normal equations, and the rule
that adapts each problem's damping.

Both fits use them: the point-spectrum fit (``spectrum_fit``: one small problem per spectrum and start)
and the map fit (``gauss_newton``, ``schur``: one per pixel, plus the nodes and the scale they share).

Step (Marquardt 1963). Each problem's damped system (A + λ diag A) δ = −g is solved after Jacobi scaling
(unit diagonal): the step is then invariant to the scale of each unknown — a parameter near a bound,
where the logistic map is flat, moves as freely as one in the middle — and Marquardt's λ·diag A becomes
λ·I. An unknown no residual sees (a zero column: a parameter held at its bound, a node no pixel touches)
does not move.

Damping (Nielsen's gain ratio, Madsen, Nielsen & Tingleff 2004 §3.2): after an accepted step a problem
whose actual decrease was more than ¾ of the predicted one is damped less (÷3), less than ¼ more (×2);
after a rejected step, ×4 where that problem got worse (×2 where it did not: another one's failure
rejected the step).

Shapes: per-problem rows ``(N, ·)``: unknowns ``(N, n)``, Jacobians ``(N, L, n)``, blocks ``(N, n, n)``.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.autograd.forward_ad as fwAD

__all__ = [
    "LAMBDA0", "LAMBDA_MAX", "LAMBDA_MIN", "block_factor", "block_solve", "damped_step", "forward_jacobian", "next_damping",
    "predicted_decrease", "reverse_jacobian",
]

#: The damping a problem starts with, and the range it is kept in.
LAMBDA0, LAMBDA_MIN, LAMBDA_MAX = 1e-3, 1e-7, 1e7


def forward_jacobian(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``fn(x)`` ``(N, L)`` and its Jacobian ``(N, L, n)`` for ``x`` ``(N, n)``, where row i of ``fn``'s output
    depends on row i of its input only: one forward-mode pass over the batch repeated n times, copy k
    carrying the tangent e_k."""
    rows, n = x.shape
    tangents = torch.eye(n, dtype=x.dtype, device=x.device).repeat_interleave(rows, dim=0)
    with fwAD.dual_level():
        out = fn(fwAD.make_dual(x.repeat(n, 1), tangents))
        value, tangent = fwAD.unpack_dual(out)
    return value[:rows], tangent.reshape(n, rows, -1).permute(1, 2, 0)


def reverse_jacobian(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``forward_jacobian``'s answer by reverse mode: one backward pass per output column, batched
    (``is_grads_batched``), each row's gradient its own (rows independent). For problems with few
    outputs per row (a cube's bands, not a spectrometer's hundred samples): forward mode pays a fixed
    cost per operation with a non-dual operand (a constant, a scalar: its zero tangent takes a slow
    path in torch 2.13), which reverse mode does not; with many outputs per row forward mode wins
    (timings: docs/reconstruct.md, "From reconstruct/levels/least_squares.py")."""
    xx = x.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        out = fn(xx)
    rows, outputs = out.shape
    seeds = torch.eye(outputs, dtype=out.dtype, device=out.device)[:, None, :].expand(outputs, rows, outputs)
    (grad,) = torch.autograd.grad(out, xx, seeds, is_grads_batched=True)  # (outputs, rows, n)
    return out.detach(), grad.permute(1, 0, 2)


def block_factor(a: torch.Tensor, lam: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cholesky factor of the Jacobi-scaled blocks ``a`` ``(N, n, n)`` damped by ``lam`` ``(N,)`` (or one
    number): (factor, scale s, seen). An unknown no row sees (zero column) gets an identity row."""
    n = a.shape[-1]
    diag = torch.diagonal(a, dim1=-2, dim2=-1)
    top = diag.amax(dim=-1, keepdim=True) if n else diag.new_ones(diag.shape[:-1] + (1,))  # no unknowns: every map on nodes
    seen = diag > 1e-24 * top.clamp_min(1e-300)
    s = torch.where(seen, torch.sqrt(diag), torch.ones_like(diag))
    scaled = a / (s[..., :, None] * s[..., None, :])
    scaled = torch.where(seen[..., :, None] & seen[..., None, :], scaled, torch.zeros_like(scaled))
    eye = torch.eye(n, dtype=a.dtype, device=a.device)
    lam = torch.as_tensor(lam, dtype=a.dtype, device=a.device)
    damped = scaled + eye * (lam.reshape(lam.shape + (1, 1)) + 1e-9) + torch.diag_embed((~seen).to(a.dtype))
    chol, info = torch.linalg.cholesky_ex(damped)
    if bool(info.any()):  # numerically indefinite: fall back to the damped diagonal
        bad = info > 0
        chol[bad] = eye * torch.sqrt(1.0 + lam.expand(info.shape)[bad].reshape(-1, 1, 1))
    return chol, s, seen


def block_solve(factor, rhs: torch.Tensor) -> torch.Tensor:
    """A⁻¹ rhs for rhs ``(N, n, k)`` with ``factor`` from ``block_factor`` (unseen unknowns: 0)."""
    chol, s, seen = factor
    mask = seen.to(rhs.dtype)[..., None]
    return torch.cholesky_solve(rhs / s[..., None] * mask, chol) / s[..., None] * mask


def damped_step(a: torch.Tensor, grad: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """δ ``(N, n)`` of (A + λ diag A) δ = −g for blocks ``a`` ``(N, n, n)``, gradients ``grad`` ``(N, n)``
    and damping ``lam`` ``(N,)``, solved in float64."""
    return -block_solve(block_factor(a.double(), lam.double()), grad.double()[..., None])[..., 0].to(grad.dtype)


def predicted_decrease(
    jac: torch.Tensor, step: torch.Tensor, grad: torch.Tensor, column: torch.Tensor | None = None,
    column_step: torch.Tensor | float = 0.0, column_grad: torch.Tensor | float = 0.0,
) -> torch.Tensor:
    """The decrease of ‖r‖² the linearised model predicts for each row's step, −(2 δ·g + ‖Jδ‖²) ``(N,)``:
    ``jac`` ``(N, L, n)``, ``step`` and ``grad`` ``(N, n)``; optionally one more unknown that every row
    shares (the map fit's scale): its column ``(N, L)``, its step and each row's share of its gradient."""
    v = (jac @ step[..., None])[..., 0]
    inner = (step * grad).sum(-1)
    if column is not None:
        v = v + column * column_step
        inner = inner + column_step * column_grad
    return -(2.0 * inner + (v * v).sum(-1))


def next_damping(lam: torch.Tensor, accepted: torch.Tensor | bool, gain: torch.Tensor, worse: torch.Tensor) -> torch.Tensor:
    """Each problem's damping after a step (see the module docstring): ``accepted`` the step was kept,
    ``gain`` its actual over predicted decrease, ``worse`` its own residual grew."""
    kept = torch.where(gain > 0.75, lam / 3.0, torch.where(gain < 0.25, lam * 2.0, lam))
    refused = torch.where(worse, lam * 4.0, lam * 2.0)
    return torch.where(torch.as_tensor(accepted, device=lam.device), kept, refused).clamp(LAMBDA_MIN, LAMBDA_MAX)
