"""The gather operator 𝒢_P[f](x) = Σ_k w_k^P(x) (f ∗ G_k)(x) with per-pixel weights from σa tables
(DWRR08 Eq. 6, 9), and its memory-lean gradient.

Weights at a pixel: the profile's plane integral T(σa) (log-linear in log σa between table samples)
times its shape, the weights over their sum (linear in log σa). Several profiles can gather the same
image at once: they share its blur stack.

``gather(f, sets, plan, lean=True)`` is a custom autograd function: the forward keeps only ``f`` and
the per-pixel table positions; the backward recomputes the blur stack once, accumulating the weights'
gradient on the fly and obtaining the image's gradient (the blur stack's adjoint) by autograd through
the stack alone, whose operations save almost nothing. A 256×256 patch with its 1 cm border and nine
bands thus differentiates in a few maps per gather instead of three per Gaussian. ``lean=False`` runs
the plain differentiable expression instead (a reference for tests).

A renderer gathers with the same profile and pixels once per inter-scattering term. Looking the
weights up is a gather from the table per pixel and Gaussian — a third of the forward time when done
afresh each time — so ``Lookup.cached(columns)`` may hold them as dense maps ``(1 + K', N, H, W)``,
computed once per render (outside autograd: their gradient goes through the slopes, as without the
cache). The cache is used by the lean path and by passes without gradients.

Shapes: images ``(N, H, W)`` with N = batch × bands; tables flattened per band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .blur import BlurPlan, blur_stack

__all__ = ["Columns", "Lookup", "columns", "gather", "lookup", "total"]


@dataclass(frozen=True)
class Lookup:
    """Per-pixel position in a layer's σa table: flat sample ``index`` (band·S + i0) and ``frac``.

    ``weights``: optionally the dense per-pixel weights' shape ``(1 + K', N, H, W)`` of one profile
    (see ``cached``), detached."""

    index: torch.Tensor
    frac: torch.Tensor
    weights: torch.Tensor | None = None

    def cached(self, cols: "Columns") -> "Lookup":
        """This lookup with the dense weights of ``cols`` computed once."""
        with torch.no_grad():
            frac = self.frac.detach()
            dense = torch.stack([_lerp(cols.shape[j], Lookup(self.index, frac)) for j in range(cols.shape.shape[0])])
        return Lookup(self.index, self.frac, dense)

    def cache_bytes(self, cols: "Columns") -> int:
        return cols.shape.shape[0] * self.index.numel() * self.frac.element_size()


@dataclass(frozen=True)
class Columns:
    """A profile's table for one blur plan: per column (identity first, then each blurred Gaussian)
    the value and slope of the weights' shape at every flat sample, ``(1 + K', L·S, 2)``; and the
    log of the weights' sum with its slope, ``(L·S, 2)``."""

    shape: torch.Tensor
    log_total: torch.Tensor


def lookup(sigma_a_grid: torch.Tensor, sigma_a: torch.Tensor) -> Lookup:
    """σa ``(B, L, H, W)`` → flat table positions ``(B·L, H, W)`` (clamped to the tabulated range)."""
    n = sigma_a_grid.numel()
    log_lo, log_hi = math.log(float(sigma_a_grid[0])), math.log(float(sigma_a_grid[-1]))
    step = (log_hi - log_lo) / (n - 1)
    t = (torch.log(sigma_a.clamp(float(sigma_a_grid[0]), float(sigma_a_grid[-1]))) - log_lo) / step
    i0 = torch.clamp(t.detach().floor().long(), 0, n - 2)
    frac = t - i0.to(t)
    band = torch.arange(sigma_a.shape[1], device=sigma_a.device).view(1, -1, 1, 1)
    shape = (-1, *sigma_a.shape[-2:])
    return Lookup((band * n + i0).reshape(shape), frac.reshape(shape))


def _pairs(values: torch.Tensor) -> torch.Tensor:
    """``(..., L, S)`` → ``(..., L·S, 2)``: value and slope to the next sample (last slope unused)."""
    slope = torch.zeros_like(values)
    slope[..., :-1] = values[..., 1:] - values[..., :-1]
    return torch.stack([values, slope], dim=-1).flatten(-3, -2).contiguous()


def columns(tables, layer: str, profile: str, plan: BlurPlan) -> Columns:
    shape, log_total = tables.normalized(layer, profile)  # (L, S, K), (L, S)
    ident = torch.tensor(plan.identity, device=shape.device)
    merged = torch.cat([shape[..., ident].sum(-1, keepdim=True), shape[..., ~ident]], dim=-1)
    return Columns(_pairs(merged.permute(2, 0, 1)), _pairs(log_total))


def _lerp(pairs: torch.Tensor, lk: Lookup) -> torch.Tensor:
    z = pairs.index_select(0, lk.index.reshape(-1)).view(*lk.index.shape, 2)
    return torch.addcmul(z[..., 0], lk.frac, z[..., 1])


def _slope(pairs: torch.Tensor, lk: Lookup) -> torch.Tensor:
    return pairs[:, 1].take(lk.index)


def _weight(c: Columns, lk: Lookup, j: int) -> torch.Tensor:
    """Shape weight of column ``j`` per pixel, from the cache when it holds it (no autograd)."""
    return lk.weights[j] if lk.weights is not None else _lerp(c.shape[j], lk)


def total(cols: Columns, lk: Lookup) -> torch.Tensor:
    """Σ_k w_k per pixel: the profile's plane integral at each pixel's σa."""
    return torch.exp(_lerp(cols.log_total, lk))


def _forward(f: torch.Tensor, sets: list[tuple[Columns, Lookup]], plan: BlurPlan) -> list[torch.Tensor]:
    tracked = torch.is_grad_enabled() and (f.requires_grad or any(lk.frac.requires_grad for _, lk in sets))
    if tracked:  # plain autograd: the weights must carry their graph
        sets = [(c, Lookup(lk.index, lk.frac)) for c, lk in sets]
    outs = [_weight(c, lk, 0) * f for c, lk in sets]
    for j, blurred in enumerate(blur_stack(f, plan), start=1):
        for i, (c, lk) in enumerate(sets):
            if tracked:
                outs[i] = outs[i] + _lerp(c.shape[j], lk) * blurred
            else:
                outs[i].addcmul_(_weight(c, lk, j), blurred)
    return [total(c, lk) * out for (c, lk), out in zip(sets, outs)]


class _Gather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plan, cols, indices, caches, f, *fracs):  # noqa: D102
        ctx.plan, ctx.cols, ctx.indices, ctx.caches = plan, cols, indices, caches
        ctx.save_for_backward(f, *fracs)
        sets = [(c, Lookup(i, fr, w)) for c, i, w, fr in zip(cols, indices, caches, fracs)]
        return tuple(_forward(f, sets, plan))

    @staticmethod
    def backward(ctx, *grads):  # noqa: D102
        f, *fracs = ctx.saved_tensors
        sets = [(c, Lookup(i, fr, w)) for c, i, w, fr in zip(ctx.cols, ctx.indices, ctx.caches, fracs)]
        need_f = ctx.needs_input_grad[4]
        need_frac = ctx.needs_input_grad[5:]
        grads = [g if g is not None else torch.zeros_like(f) for g in grads]
        totals = [total(c, lk) for c, lk in sets]
        scaled = [g * t for g, t in zip(grads, totals)]  # ∂L/∂(unnormalised sum)
        frac_grads = [torch.zeros_like(fr) if need else None for fr, need in zip(fracs, need_frac)]
        sums = [torch.zeros_like(f) for _ in sets]  # Σ_j shape_j B_j, for the totals' gradient
        grad_f = None
        with torch.enable_grad():
            f_leaf = f.detach().requires_grad_(need_f)
            stack = iter(blur_stack(f_leaf, ctx.plan))
            objective = None
            j = 0
            current = f_leaf
            while True:
                b = current.detach()
                h = None
                for i, (c, lk) in enumerate(sets):
                    with torch.no_grad():
                        w = _weight(c, lk, j)
                        sums[i].addcmul_(w, b)
                        if frac_grads[i] is not None:
                            frac_grads[i].addcmul_(scaled[i] * _slope(c.shape[j], lk), b)
                        term = w * scaled[i]
                    h = term if h is None else h + term
                if need_f:
                    dot = (current * h).sum()
                    objective = dot if objective is None else objective + dot
                j += 1
                try:
                    current = next(stack)
                except StopIteration:
                    break
            if need_f:
                (grad_f,) = torch.autograd.grad(objective, f_leaf)
        for i, (c, lk) in enumerate(sets):
            if frac_grads[i] is not None:
                # T = exp(a + frac·s): ∂(T·sum)/∂frac = T·s·sum
                frac_grads[i] += grads[i] * totals[i] * _slope(c.log_total, lk) * sums[i]
        return (None, None, None, None, grad_f, *frac_grads)


def gather(f: torch.Tensor, sets: list[tuple[Columns, Lookup]], plan: BlurPlan, lean: bool = True) -> list[torch.Tensor]:
    """𝒢_P[f] for each (profile columns, pixel lookup) in ``sets``, sharing one blur stack of ``f``."""
    fracs = [lk.frac for _, lk in sets]
    needs_grad = torch.is_grad_enabled() and (f.requires_grad or any(fr.requires_grad for fr in fracs))
    if lean and needs_grad:
        return list(_Gather.apply(plan, [c for c, _ in sets], [lk.index for _, lk in sets],
                                  [lk.weights for _, lk in sets], f, *fracs))
    return _forward(f, sets, plan)
