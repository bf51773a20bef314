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

__all__ = ["ColumnLookups", "Columns", "Lookup", "columns", "gather", "lookup", "total"]


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
            plain = Lookup(self.index, self.frac.detach())
            # filled column by column (a stack of a list would hold every column twice at its peak)
            dense = torch.empty((cols.shape.shape[0], *self.frac.shape), dtype=self.frac.dtype, device=self.frac.device)
            for j in range(cols.shape.shape[0]):
                dense[j] = _lerp(cols.shape[j], plain)
        return Lookup(self.index, self.frac, dense)

    def cache_bytes(self, cols: "Columns") -> int:
        return cols.shape.shape[0] * self.index.numel() * self.frac.element_size()


@dataclass(frozen=True)
class ColumnLookups:
    """One table position per pixel *and column*: ``index``/``frac`` ``(J, N, H, W)``, column 0 the
    identity (the pixel's own σa), column j the σa the light of that Gaussian meets on its way (the
    ``segment`` coupling: model/render/renderer.py). Totals differ per column, so each column's weight is
    T(σ̄_j)·shape_j(σ̄_j). ``weights``: optionally those weights, dense ``(J, N, H, W)``, detached."""

    index: torch.Tensor
    frac: torch.Tensor
    weights: torch.Tensor | None = None
    slopes: torch.Tensor | None = None

    def column(self, j: int) -> Lookup:
        return Lookup(self.index[j], self.frac[j])

    def cached(self, cols: "Columns") -> "ColumnLookups":
        """With the dense weights — and, when the positions carry a gradient, the weights' derivatives
        with respect to them, which the lean backward would otherwise recompute column by column."""
        want_slopes = self.frac.requires_grad and torch.is_grad_enabled()
        n_cols = cols.shape.shape[0]
        with torch.no_grad():
            plain = ColumnLookups(self.index, self.frac.detach())
            # filled column by column (no stack: these are the render's largest tensors)
            dense = torch.empty((n_cols, *self.frac.shape[1:]), dtype=self.frac.dtype, device=self.frac.device)
            slopes = torch.empty_like(dense) if want_slopes else None
            for j in range(n_cols):
                at = plain.column(j)
                t_j = torch.exp(_lerp(cols.log_total, at))
                shape_j = _lerp(cols.shape[j], at)
                torch.mul(t_j, shape_j, out=dense[j])
                if slopes is not None:
                    torch.mul(_slope(cols.log_total, at), shape_j, out=slopes[j])
                    slopes[j].add_(_slope(cols.shape[j], at)).mul_(t_j)
        return ColumnLookups(self.index, self.frac, dense, slopes)

    def cache_bytes(self, cols: "Columns") -> int:
        per = cols.shape.shape[0] * self.index[0].numel() * self.frac.element_size()
        return per * (2 if self.frac.requires_grad and torch.is_grad_enabled() else 1)


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


def total(cols: Columns, lk: Lookup | ColumnLookups) -> torch.Tensor:
    """Σ_k w_k per pixel: the profile's plane integral at each pixel's σa."""
    if isinstance(lk, ColumnLookups):
        lk = lk.column(0)
    return torch.exp(_lerp(cols.log_total, lk))


def _column_weight(c: Columns, lk: ColumnLookups, j: int) -> torch.Tensor:
    """Weight of column ``j`` per pixel, its own total included (``ColumnLookups``)."""
    at = lk.column(j)
    return torch.exp(_lerp(c.log_total, at)) * _lerp(c.shape[j], at)


def _any_weight(c: Columns, lk, j: int, tracked: bool) -> torch.Tensor:
    """Column ``j``'s weight: the shape alone for a ``Lookup`` (its total multiplies the sum), the whole
    weight for ``ColumnLookups``; from the cache unless autograd must see it."""
    if lk.weights is not None and not tracked:
        return lk.weights[j]
    return _column_weight(c, lk, j) if isinstance(lk, ColumnLookups) else _lerp(c.shape[j], lk)


def _finish(c: Columns, lk, out: torch.Tensor) -> torch.Tensor:
    return out if isinstance(lk, ColumnLookups) else total(c, lk) * out


def _plain(lk):
    """The lookup without its cache (autograd must see the weights' graph)."""
    return type(lk)(lk.index, lk.frac)


def _forward(f: torch.Tensor, sets: list, plan: BlurPlan) -> list[torch.Tensor]:
    tracked = torch.is_grad_enabled() and (f.requires_grad or any(lk.frac.requires_grad for _, lk in sets))
    if tracked:  # plain autograd: the weights must carry their graph
        sets = [(c, _plain(lk)) for c, lk in sets]
    outs = [_any_weight(c, lk, 0, tracked) * f for c, lk in sets]
    for j, blurred in enumerate(blur_stack(f, plan), start=1):
        for i, (c, lk) in enumerate(sets):
            if tracked:
                outs[i] = outs[i] + _any_weight(c, lk, j, tracked) * blurred
            else:
                outs[i].addcmul_(_any_weight(c, lk, j, tracked), blurred)
    return [_finish(c, lk, out) for (c, lk), out in zip(sets, outs)]


class _Gather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plan, cols, kinds, indices, caches, f, *fracs):
        ctx.plan, ctx.cols, ctx.kinds, ctx.indices, ctx.caches = plan, cols, kinds, indices, caches
        ctx.save_for_backward(f, *fracs)
        return tuple(_forward(f, _sets(cols, kinds, indices, caches, fracs), plan))

    @staticmethod
    def backward(ctx, *grads):
        f, *fracs = ctx.saved_tensors
        sets = _sets(ctx.cols, ctx.kinds, ctx.indices, ctx.caches, fracs)
        need_f = ctx.needs_input_grad[5]
        need_frac = ctx.needs_input_grad[6:]
        grads = [g if g is not None else torch.zeros_like(f) for g in grads]
        per_column = [isinstance(lk, ColumnLookups) for _, lk in sets]
        totals = [None if pc else total(c, lk) for pc, (c, lk) in zip(per_column, sets)]
        # ∂L/∂(the weighted sum before the total): the total's factor for a Lookup, nothing per column
        scaled = [g if pc else g * t for g, t, pc in zip(grads, totals, per_column)]
        # per column each column's gradient is written once (empty), a Lookup's accumulates (zeros)
        frac_grads = [(torch.empty_like(fr) if pc else torch.zeros_like(fr)) if need else None
                      for fr, need, pc in zip(fracs, need_frac, per_column)]
        sums = [None if pc else torch.zeros_like(f) for pc in per_column]  # Σ_j shape_j B_j, for the totals' gradient
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
                        w = _any_weight(c, lk, j, False)
                        if per_column[i]:
                            if frac_grads[i] is not None:
                                if lk.slopes is not None:
                                    dw = lk.slopes[j]
                                else:
                                    at = lk.column(j)
                                    t_j = torch.exp(_lerp(c.log_total, at))
                                    dw = t_j * (_slope(c.log_total, at) * _lerp(c.shape[j], at) + _slope(c.shape[j], at))
                                torch.mul(scaled[i], dw, out=frac_grads[i][j]).mul_(b)
                        else:
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
            if frac_grads[i] is not None and not per_column[i]:
                # T = exp(a + frac·s): ∂(T·sum)/∂frac = T·s·sum
                frac_grads[i] += grads[i] * totals[i] * _slope(c.log_total, lk) * sums[i]
        return (None, None, None, None, None, grad_f, *frac_grads)


def _sets(cols, kinds, indices, caches, fracs) -> list:
    return [(c, kind(i, fr, *w)) for c, kind, i, w, fr in zip(cols, kinds, indices, caches, fracs)]


def _cache_of(lk) -> tuple:
    return (lk.weights, lk.slopes) if isinstance(lk, ColumnLookups) else (lk.weights,)


def gather(f: torch.Tensor, sets: list, plan: BlurPlan, lean: bool = True) -> list[torch.Tensor]:
    """𝒢_P[f] for each (profile columns, pixel lookup) in ``sets``, sharing one blur stack of ``f``."""
    fracs = [lk.frac for _, lk in sets]
    needs_grad = torch.is_grad_enabled() and (f.requires_grad or any(fr.requires_grad for fr in fracs))
    if lean and needs_grad:
        return list(_Gather.apply(plan, [c for c, _ in sets], [type(lk) for _, lk in sets], [lk.index for _, lk in sets],
                                  [_cache_of(lk) for _, lk in sets], f, *fracs))
    return _forward(f, sets, plan)
