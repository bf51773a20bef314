"""Normal equations of the map fit when some maps live on nodes (``grids.MapLayout``): the per-pixel
blocks eliminated by the Schur complement, the shared unknowns solved densely.

Unknowns: each pixel's fine maps (n_f of them), and the global vector g = (z, log s) of every coarse
map's nodes and the scale. Pixel p sees its fine maps through J_f ``(L, n_f)`` and its four nodes per
coarse map through G = [J_c[:, k]·w_kj …, s·R] ``(L, m)`` (bilinear weights w; m = 4·n_c + 1), so

    [ A_p   B_p ] [δf_p]     [g_f]          A_p = J_fᵀJ_f + λ_p D,  B_p = J_fᵀG,  C_p = GᵀG,
    [ B_pᵀ  Σ C ] [δg  ] = − [Σ g_g]

and with X_p = A_p⁻¹B_p, y_p = A_p⁻¹g_f the reduced system over g is
S = Σ_p (C_p − B_pᵀX_p) (scattered onto the nodes each pixel touches), right side Σ_p (g_g − B_pᵀy_p);
then δf_p = −(y_p + X_p δg_p). A step costs N batched n_f×n_f solves and one dense solve of the
nodes (a few hundred to a few thousand). Damping (``least_squares.block_factor``, as every fit here):
Jacobi-scaled blocks, λ_p per pixel on the fine block, one λ on the shared block; an unknown no pixel sees stays.

The same elimination with no damping on whitened Jacobians gives the marginal covariance of every
pixel's parameters (``marginal_variance``): Cov(g) = S⁻¹, Cov(f_p) = A_p⁻¹ + X_p Cov(g)_p X_pᵀ.
"""

from __future__ import annotations

import torch

from ...model import N_PARAMS
from .grids import MapLayout
from .least_squares import block_factor, block_solve

__all__ = ["marginal_variance", "solve_split_step"]


def _local_columns(jac, col, layout: MapLayout, pixels, free_scale: bool):
    """J_f ``(N, L, n_f)``, G ``(N, L, m)`` and the z index of G's columns ``(N, m)`` (the scale: n_nodes)."""
    n, bands, _ = jac.shape
    nc = len(layout.coarse)
    idx, wts = layout.local(pixels)
    jf = jac[:, :, layout.fine]
    g = (jac[:, :, layout.coarse][..., None] * wts.to(jac.dtype).reshape(n, 1, nc, 4)).reshape(n, bands, 4 * nc)
    if free_scale:
        g = torch.cat([g, col[..., None].to(jac.dtype)], 2)
        idx = torch.cat([idx, torch.full((n, 1), layout.n_nodes, dtype=idx.dtype, device=idx.device)], 1)
    return jf, g, idx, wts


def _scatter(local: torch.Tensor, idx: torch.Tensor, size: int) -> torch.Tensor:
    """Σ_p of ``local`` ``(N, m, m)`` onto a dense ``(size, size)`` at ``idx`` ``(N, m)``."""
    out = torch.zeros(size * size, dtype=local.dtype, device=local.device)
    out.index_add_(0, (idx[:, :, None] * size + idx[:, None, :]).reshape(-1), local.reshape(-1))
    return out.reshape(size, size)


def _reduced(jf, g, idx, size, lam_f):
    factor = block_factor(jf.transpose(1, 2) @ jf, lam_f)
    b = jf.transpose(1, 2) @ g  # (N, n_f, m)
    x = block_solve(factor, b)
    s_loc = g.transpose(1, 2) @ g - b.transpose(1, 2) @ x
    return factor, b, x, _scatter(s_loc, idx, size)


def solve_split_step(
    jac: torch.Tensor, col: torch.Tensor, grad: torch.Tensor, grad_scale: torch.Tensor, lam: torch.Tensor, lam_shared: float,
    free_scale: bool, layout: MapLayout, pixels: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Damped Gauss–Newton step with shared node unknowns.

    ``jac`` ``(N, L, N_PARAMS)`` and ``col`` ``(N, L)`` as in ``gauss_newton.curvature_and_columns``; ``grad``
    ``(N, N_PARAMS)`` each pixel's ∂loss/∂x (for a coarse map: the derivative by the map's value at the
    pixel); ``grad_scale`` ``(N,)`` each pixel's share of ∂loss/∂log s; ``lam`` ``(N,)``.
    Returns ``dx`` ``(N, N_PARAMS)`` (a coarse map's column: its interpolated change at the pixel),
    ``dz`` ``(n_nodes,)``, ``d log s`` (0-d) and the shared unknowns' decrement −bᵀδg (b the reduced
    right side): twice the loss decrease the step predicts from the nodes and scale (after the fine
    maps have followed), the measure of whether the shared unknowns have converged."""
    dtype = grad.dtype
    n = jac.shape[0]
    nc = len(layout.coarse)
    jf, g, idx, wts = _local_columns(jac.double(), col.double(), layout, pixels, free_scale)
    size = layout.n_nodes + int(free_scale)
    factor, b, x, s = _reduced(jf, g, idx, size, lam.double())
    gf = grad[:, layout.fine].double()
    gg = (grad[:, layout.coarse].double()[..., None] * wts.double().reshape(n, nc, 4)).reshape(n, 4 * nc)
    if free_scale:
        gg = torch.cat([gg, grad_scale.double()[:, None]], 1)
    y = block_solve(factor, gf[..., None])[..., 0]
    rhs = torch.zeros(size, dtype=torch.float64, device=jac.device)
    rhs.index_add_(0, idx.reshape(-1), (gg - (b.transpose(1, 2) @ y[..., None])[..., 0]).reshape(-1))
    chol, sc, seen = block_factor(s[None], lam_shared)
    step = -torch.cholesky_solve((rhs / sc[0] * seen[0])[None, :, None], chol)[0, :, 0] / sc[0] * seen[0]
    local = step[idx]
    dxf = -(y + (x @ local[..., None])[..., 0])
    dx = torch.empty(n, N_PARAMS, dtype=torch.float64, device=jac.device)
    dx[:, layout.fine] = dxf
    dx[:, layout.coarse] = (local[:, : 4 * nc].reshape(n, nc, 4) * wts.double().reshape(n, nc, 4)).sum(-1)
    ds = step[layout.n_nodes] if free_scale else torch.zeros((), dtype=torch.float64, device=jac.device)
    return dx.to(dtype), step[: layout.n_nodes].to(dtype), ds.to(dtype), float(-(rhs * step).sum())


def marginal_variance(jac: torch.Tensor, col: torch.Tensor, free_scale: bool, layout: MapLayout, pixels: torch.Tensor,
                      residual: torch.Tensor | None = None, clusters: torch.Tensor | None = None) -> torch.Tensor:
    """Variance of every pixel's unknowns in x ``(N, N_PARAMS)`` from whitened ``jac`` ``(N, L, N_PARAMS)`` and
    ``col`` ``(N, L)`` (rows divided by each band's noise σ): the inverse Fisher information with every
    other unknown, shared ones included, free.

    With the whitened ``residual`` ``(N, L)`` and a cluster label per pixel ``clusters`` ``(N,)``, the
    shared unknowns' covariance is the larger (per node) of that and the cluster-robust sandwich
    S⁻¹ (Σ_c u_c u_cᵀ) S⁻¹, u_c the reduced score Σ_{p∈c} (G_p − J_f,p X_p)ᵀ r_p of a cluster's pixels
    (Liang & Zeger 1986): where the residual is correlated in space (model error, not the camera's
    white noise) a node's hundreds of pixels are worth far fewer independent ones."""
    n = jac.shape[0]
    nc = len(layout.coarse)
    jf, g, idx, wts = _local_columns(jac.double(), col.double(), layout, pixels, free_scale)
    size = layout.n_nodes + int(free_scale)
    factor, _, x, s = _reduced(jf, g, idx, size, 0.0)
    d = torch.diagonal(s).clamp_min(1e-300).sqrt()
    cov = torch.linalg.pinv(s / (d[:, None] * d[None, :]), hermitian=True) / (d[:, None] * d[None, :])
    if residual is not None and clusters is not None:
        score = ((g - jf @ x).transpose(1, 2) @ residual.double()[..., None])[..., 0]  # (N, m)
        labels, cluster = torch.unique(clusters, return_inverse=True)
        u = torch.zeros(labels.numel() * size, dtype=torch.float64, device=jac.device)
        u.index_add_(0, (cluster[:, None] * size + idx).reshape(-1), score.reshape(-1))
        u = u.reshape(labels.numel(), size)
        robust = cov @ (u.T @ u) @ cov
        scale = torch.sqrt((torch.diagonal(robust) / torch.diagonal(cov).clamp_min(1e-300)).clamp_min(1.0))
        cov = cov * scale[:, None] * scale[None, :]  # each node's variance the larger, correlations kept
    var = torch.empty(n, N_PARAMS, dtype=torch.float64, device=jac.device)
    if layout.fine:
        local = cov[idx[:, :, None], idx[:, None, :]]  # (N, m, m)
        eye = torch.eye(len(layout.fine), dtype=torch.float64, device=jac.device).expand(n, -1, -1)
        a_inv = block_solve(factor, eye.clone())
        var[:, layout.fine] = torch.diagonal(a_inv + x @ local @ x.transpose(1, 2), dim1=1, dim2=2)
    w = wts.double().reshape(n, nc, 4)
    for q, k in enumerate(layout.coarse):
        corners = idx[:, 4 * q: 4 * q + 4]
        block = cov[corners[:, :, None], corners[:, None, :]]  # (N, 4, 4): the map's own nodes only
        var[:, k] = (w[:, q, :, None] * block * w[:, q, None, :]).sum((1, 2))
    return var.clamp_min(0.0)
