"""Each map's grid chosen on the cube: the spacing whose expected error — the noise the data leave on it
plus the detail it cannot hold — is least ("model no more than a scene needs").

Why. The right node spacing of a map moves with the cube: its pixel size, its noise, the forward model
(under transport profiles a dermal-blood change spreads its light over the neighbours, so neighbouring
pixels' C_hd cannot be told apart at the spacing diffusion holds: docs/transport.md) and the scene's
own detail. One fixed ``map_cell_mm`` cannot be right for all of them (0.75-mm C_hd nodes help 32²
transport sessions and cost 64² ones: docs/data/transport_session_grid.csv).

How, at the fit's coarsest level (``fit.fit_cube`` with ``map_grids: auto``), for map k at spacing s:

    risk_k(s) = variance_k(s) + bias_k(s)²       (unconstrained parameter x, ≈ log C, per pixel)

- *variance*: the Cramér–Rao bound of the heterogeneous fit with every map on its grid, for the bulk
  of a homogeneous patch at the start's median (``crb_pixel_variance``). The renderer's response to a
  change of one pixel's unknown (``sensitivity_kernels``: one forward difference per map, float64)
  is a convolution kernel per band; on a periodic patch the Fisher information of maps on nested
  lattices block-diagonalises in the Fourier domain (per-pixel maps eliminated frequency by
  frequency, node maps coupled only between the aliases of one coarse-lattice frequency), so the
  bound for any combination of spacings costs milliseconds. Noise per band from the cube itself
  (``band_noise``). Per-pixel candidates are charged the finest level's variance (the coarsest
  level's times the binning factor squared): a map fitted per pixel is fitted per pixel of the cube.
- *bias*: what projecting the map onto nodes s apart loses, estimated from the start's per-pixel
  maps by Mallows' C_p: mean squared projection residual minus the part the start's own noise
  explains, σ²_start·(1 − nodes/pixels), σ²_start each pixel's homogeneous Cramér–Rao bound.
  The start is a homogeneous inversion: it sees the dermis blurred by the light's spread, so this
  understates fine dermal detail — the choice leans coarse where the data are weak anyway.

The maps are chosen one at a time with the others held (two sweeps from the fixed defaults); what was
considered, each candidate's variance, bias and risk, and the winner go into ``fit.json``.

Shapes: kernels ``(K, L, M, M)`` (maps, bands, a periodic M×M patch, the changed pixel at [0, 0]);
noise ``(L,)``; maps ``(H, W)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from ...model import N_PARAMS, PARAMETER_NAMES
from ..levels.grids import _MIN_CELL_PX, MapGrid, node_count
from ..levels.problem import LevelProblem

__all__ = [
    "GridChoice", "PATCH", "PER_PIXEL", "band_noise", "choose_map_grids", "crb_pixel_variance", "sensitivity_kernels",
    "smoothing_bias",
]

#: Spacing codes of ``crb_pixel_variance``: a map per pixel, one value for the whole patch, or known.
PER_PIXEL = 1
PATCH = 0
KNOWN = None
#: Relative step of the forward differences that make the kernels (in x; the render is float64).
KERNEL_STEP = 1e-3
#: Sweeps of the one-map-at-a-time choice (the second changed nothing on the scenes measured).
SWEEPS = 2
#: Order the maps are chosen in: the best determined first, so the weak ones are chosen given them.
CHOICE_ORDER = ("C_m", "C_he", "C_hd", "beta_m", "C_bc")
#: The robust noise estimator's kernel (Immerkær 1996): the difference of two Laplacians, blind to
#: linear ramps; Σ N² = 36.
_NOISE_KERNEL = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]], dtype=torch.float64)
#: Median absolute deviation → σ of a Gaussian.
_MAD_TO_SIGMA = 1.4826


def band_noise(reflectance: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Each band's per-pixel noise σ ``(L,)`` of a cube ``(L, H, W)``: the median absolute response to
    Immerkær's kernel over pixels whose 3×3 neighbourhood is in ``mask`` ``(H, W)``, divided by its
    norm 6 — the scene's smooth shading and straight edges do not answer, a hair's few pixels do not
    move a median."""
    r = reflectance.double()[:, None]
    k = _NOISE_KERNEL.to(r.device)[None, None]
    resp = F.conv2d(r, k)[:, 0]  # (L, H−2, W−2)
    inner = F.conv2d(mask.double()[None, None].to(r.device), torch.ones(1, 1, 3, 3, dtype=torch.float64, device=r.device))[0, 0] > 8.5
    if int(inner.sum()) < 16:
        raise ValueError("band_noise: fewer than 16 pixels with their 3×3 neighbourhood in the mask")
    med = resp[:, inner].abs().median(dim=1).values
    return (_MAD_TO_SIGMA * med / 6.0).clamp_min(1e-9)


def sensitivity_kernels(problem: LevelProblem, x0: torch.Tensor, size: int) -> torch.Tensor:
    """The render's change per unit change of one pixel's unknown, each map in turn, for homogeneous
    skin at ``x0`` ``(N_PARAMS,)`` under the level's light: ``(N_PARAMS, L, size, size)`` float64 on a
    periodic patch with the changed pixel at [0, 0] (the level's centre pixel; the response beyond
    ``size``/2 pixels is cut)."""
    h, w = problem.level.shape
    x = x0.double().view(N_PARAMS, 1, 1).expand(N_PARAMS, h, w).contiguous()
    cy, cx = h // 2, w // 2
    with torch.no_grad():
        base = problem.render(x).double()
        out = []
        for k in range(N_PARAMS):
            xk = x.clone()
            xk[k, cy, cx] += KERNEL_STEP
            out.append((problem.render(xk).double() - base) / KERNEL_STEP)
    resp = torch.stack(out)  # (K, L, H, W)
    kern = torch.zeros(N_PARAMS, resp.shape[1], size, size, dtype=torch.float64, device=resp.device)
    half = size // 2
    ys = torch.arange(h, device=resp.device) - cy
    xs = torch.arange(w, device=resp.device) - cx
    keep_y, keep_x = (ys >= -half) & (ys < half), (xs >= -half) & (xs < half)
    sub = resp[:, :, keep_y][:, :, :, keep_x]
    iy, ix = ys[keep_y] % size, xs[keep_x] % size
    kern[:, :, iy[:, None], ix[None, :]] = sub
    return kern


def _hat(spacing: int, size: int, dtype, device) -> torch.Tensor:
    """Node 0's bilinear weight over a periodic ``size``² patch (``MapGrid``'s rule: nodes at the
    centres of ``spacing``-pixel cells); all ones for the patch; a delta per pixel."""
    if spacing == PATCH:
        return torch.ones(size, size, dtype=dtype, device=device)
    if spacing == PER_PIXEL:
        h = torch.zeros(size, size, dtype=dtype, device=device)
        h[0, 0] = 1.0
        return h
    d = torch.arange(size, dtype=dtype, device=device)
    d = torch.minimum((d - (spacing - 1) / 2.0) % size, (-(d - (spacing - 1) / 2.0)) % size)
    tri = (1.0 - d / spacing).clamp_min(0.0)
    return tri[:, None] * tri[None, :]


def crb_pixel_variance(kernels: torch.Tensor, noise: torch.Tensor, spacing: list[int | None], ridge: float = 1e-12) -> torch.Tensor:
    """Mean per-pixel variance ``(K,)`` of each map's estimate (inf where ``spacing[k]`` is None: known)
    by the Cramér–Rao bound on a periodic ``M``² patch: map k per pixel (``PER_PIXEL``), on nodes every
    ``spacing[k]`` pixels (a power of two dividing M), one value (``PATCH``) or known (None); white
    noise σ ``noise`` ``(L,)`` per pixel and band. Exact for the linear model the kernels define
    (checked against the dense Fisher matrix, ``tests/reconstruct/test_grid_choice.py``)."""
    n_maps, bands, m, _ = kernels.shape
    free = [k for k in range(n_maps) if spacing[k] is not KNOWN]
    fine = [k for k in free if spacing[k] == PER_PIXEL]
    coarse = [k for k in free if spacing[k] != PER_PIXEL]
    for k in coarse:
        s = spacing[k]
        if s != PATCH and (s < 1 or m % s or s & (s - 1)):
            raise ValueError(f"spacing {s} must be a power of two dividing the patch's {m} pixels")
    dev, cdt = kernels.device, torch.complex128
    g = torch.fft.fft2(kernels.to(torch.float64)) / noise.to(torch.float64).view(1, bands, 1, 1)  # whitened
    lattice = {k: (1 if spacing[k] == PATCH else m // spacing[k]) for k in free}  # nodes per side
    hats = {k: torch.fft.fft2(_hat(spacing[k], m, torch.float64, dev)) for k in free}
    # a_k(q) = N_k Ĝ_k(q) Ĥ_k(q): the unitary node basis's column at pixel frequency q, (L, M, M)
    cols = {k: lattice[k] * g[k] * hats[k] for k in free}
    var = torch.full((n_maps,), math.inf, dtype=torch.float64)

    def stack(ks):  # (M, M, L, n)
        return torch.stack([cols[k] for k in ks], -1).permute(1, 2, 0, 3).to(cdt)

    scale = 1.0 / m**2
    if fine:
        af = stack(fine)
        bff = scale * af.conj().transpose(-1, -2) @ af
        bff = bff + ridge * torch.eye(len(fine), dtype=cdt, device=dev) * bff.diagonal(dim1=-2, dim2=-1).real.amax(-1, keepdim=True)[..., None]
        bff_inv = torch.linalg.inv(bff)
    if not coarse:
        var[fine] = (bff_inv.diagonal(dim1=-2, dim2=-1).real.sum((0, 1)) * scale).cpu()
        return var
    ac = stack(coarse)
    scc = scale * ac.conj().transpose(-1, -2) @ ac
    if fine:
        bfc = scale * af.conj().transpose(-1, -2) @ ac
        gain = bff_inv @ bfc  # K(q) = B_ff⁻¹ B_fc
        scc = scc - bfc.conj().transpose(-1, -2) @ gain
    # blocks: pixel frequencies q = ν + n_min·j share node frequencies; patch maps live in block ν = 0
    nodes = [lattice[k] for k in coarse if spacing[k] != PATCH]
    n_min = min(nodes) if nodes else m
    rk = {k: (1 if spacing[k] == PATCH else lattice[k] // n_min) for k in coarse}
    offset, n_b = {}, 0
    for k in coarse:
        offset[k] = n_b
        n_b += rk[k] ** 2
    j = torch.arange(m, device=dev) // n_min  # q = j·n_min + ν along each axis
    nu = torch.arange(m, device=dev) % n_min
    block = (nu[:, None] * n_min + nu[None, :]).reshape(-1)  # (M²,)
    slot = {}
    for k in coarse:
        r = rk[k]
        local = ((j % r)[:, None] * r + (j % r)[None, :]).reshape(-1)
        slot[k] = offset[k] + local  # (M²,) this q's unknown within its block
    flat = scc.reshape(m * m, len(coarse), len(coarse))
    prec = torch.zeros(n_min * n_min, n_b, n_b, dtype=cdt, device=dev)
    for a, k in enumerate(coarse):
        for b, k2 in enumerate(coarse):
            prec.index_put_((block, slot[k], slot[k2]), flat[:, a, b], accumulate=True)
    # a patch map has no information outside block 0: hold it there so the blocks stay invertible
    diag = prec.diagonal(dim1=-2, dim2=-1)
    for k in coarse:
        if spacing[k] == PATCH:
            diag[1:, offset[k]] += 1.0
    top = diag.real.amax(-1).clamp_min(1e-300)
    prec = prec + ridge * top[:, None, None] * torch.eye(n_b, dtype=cdt, device=dev)
    cov = torch.linalg.inv(prec)  # (blocks, n_b, n_b)
    cdiag = cov.diagonal(dim1=-2, dim2=-1).real
    for k in coarse:
        # mean pixel variance (N_k²/M⁴) Σ_q |Ĥ_k(q)|² Var ζ_k(q mod N_k)
        v = cdiag[block, slot[k]]  # (M²,) the variance of the node frequency each q aliases to
        if spacing[k] == PATCH:
            v = torch.where(block == 0, v, torch.zeros_like(v))
        var[k] = float((lattice[k] ** 2 / m**4) * (hats[k].abs().reshape(-1) ** 2 * v).sum())
    if fine:
        # fine maps: B_ff⁻¹ plus what the coarse maps' uncertainty adds through K(q)
        cq = cov[block[:, None, None], torch.stack([slot[k] for k in coarse], -1)[:, :, None], torch.stack([slot[k] for k in coarse], -1)[:, None, :]]
        gq = gain.reshape(m * m, len(fine), len(coarse))
        extra = (gq @ cq @ gq.conj().transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).real
        base = bff_inv.reshape(m * m, len(fine), len(fine)).diagonal(dim1=-2, dim2=-1).real
        var[fine] = ((base + extra).sum(0) * scale).cpu()
    return var


def smoothing_bias(values: torch.Tensor, mask: torch.Tensor, nodes: tuple[int, int], noise_var: float) -> float:
    """Mallows' C_p estimate of the mean squared detail ``values`` ``(H, W)`` loses on a ``nodes`` grid:
    the projection's mean squared residual over ``mask`` minus ``noise_var``·(1 − nodes/pixels), ≥ 0."""
    h, w = values.shape
    v = values.double()
    if nodes == (h, w):
        return 0.0  # (no clipping of outliers: a freckle is a few pixels, and exactly the detail to keep)
    grid = MapGrid.build((h, w), nodes, torch.float64, v.device)
    resid = (v - grid.up(grid.project(v)))[mask]
    n = int(mask.sum())
    return max(0.0, float((resid**2).mean()) - noise_var * (1.0 - grid.n_nodes / n))


@dataclass
class GridChoice:
    """The chosen ``cells_mm`` (``map_cell_mm``'s form) and the evidence: for each map, each candidate's
    spacing (mm; 0 per pixel), variance, bias², risk, and the winner; the noise and the level."""

    cells_mm: dict[str, float]
    candidates: dict[str, list[dict]] = field(default_factory=dict)
    noise: list[float] = field(default_factory=list)
    level_shape: tuple[int, int] = (0, 0)
    level_mm_per_pixel: float = 0.0
    analysis_px: int = 0

    def as_dict(self) -> dict:
        return {
            "rule": "each map's spacing minimises Cramér–Rao variance + Mallows C_p bias² (reconstruct/choice/grid_choice.py)",
            "cells_mm": self.cells_mm, "candidates": self.candidates, "noise_per_band": self.noise,
            "level_shape": list(self.level_shape), "level_mm_per_pixel": self.level_mm_per_pixel, "analysis_px": self.analysis_px,
        }


def _candidates(size: int) -> list[int]:
    """Per pixel, node spacings in powers of two up to half the patch, and the patch."""
    out, s = [PER_PIXEL], 2
    while s <= size // 2:
        out.append(s)
        s *= 2
    return out + [PATCH]


def _spacing_of(cell_mm: float, mm: float, size: int, cands: list[int]) -> int:
    """A ``map_cell_mm`` value as the nearest candidate spacing (pixels of the level)."""
    if cell_mm < _MIN_CELL_PX * mm:
        return PER_PIXEL
    s = cell_mm / mm
    if s >= size:
        return PATCH
    nodes = [c for c in cands if c not in (PER_PIXEL, PATCH)]
    return min(nodes, key=lambda c: abs(math.log(c / s))) if nodes else PATCH


def choose_map_grids(
    problem: LevelProblem, x_start: torch.Tensor, noise: torch.Tensor, start_cells_mm: dict[str, float], finest_mm_per_pixel: float,
) -> GridChoice:
    """Each map's spacing at ``problem``'s level (the module docstring): ``x_start`` ``(N_PARAMS, H, W)``
    the start's unknowns, ``noise`` ``(L,)`` the level's σ per band, ``start_cells_mm`` the sweep's
    first guess (the fixed defaults)."""
    level = problem.level
    h, w = level.shape
    mm = level.mm_per_pixel
    size = 1 << max(3, math.ceil(math.log2(max(h, w))))
    used = problem.band_weight > 0
    noise = noise.double().to(x_start.device)
    x_pix = problem.at_pixels(x_start.double())  # (N, N_PARAMS)
    x0 = x_pix.median(0).values
    kernels = sensitivity_kernels(problem, x0, size)[:, used.cpu()]
    sig = noise[used.to(noise.device)]
    # the start's own noise: each pixel's homogeneous Cramér–Rao bound
    _, jac = problem.homogeneous_jacobian(x_pix.to(problem.target.dtype))
    jw = jac.double()[:, used] / sig[None, :, None]
    info = jw.transpose(1, 2) @ jw
    info = info + 1e-9 * info.diagonal(dim1=1, dim2=2).amax(1)[:, None, None] * torch.eye(N_PARAMS, dtype=torch.float64, device=info.device)
    start_var = torch.linalg.inv(info).diagonal(dim1=1, dim2=2).median(0).values  # (N_PARAMS,)
    binning = (mm / finest_mm_per_pixel) ** 2
    cands = _candidates(size)
    spacing = [_spacing_of(start_cells_mm.get(n, 0.0), mm, size, cands) for n in PARAMETER_NAMES]
    mask = level.mask

    def cell_mm(s: int) -> float:
        return 0.0 if s == PER_PIXEL else (max(h, w) * mm if s == PATCH else s * mm)

    def grid_nodes(s: int) -> tuple[int, int]:
        c = cell_mm(s)
        return (h, w) if c == 0.0 else (node_count(h * mm, c, h), node_count(w * mm, c, w))

    bias = {(k, s): smoothing_bias(x_start[k], mask, grid_nodes(s), float(start_var[k])) for k in range(N_PARAMS) for s in cands}
    table: dict[str, list[dict]] = {}
    for _ in range(SWEEPS):
        for name in CHOICE_ORDER:
            k = PARAMETER_NAMES.index(name)
            rows = []
            for s in cands:
                trial = list(spacing)
                trial[k] = s
                v = float(crb_pixel_variance(kernels, sig, trial)[k]) * (binning if s == PER_PIXEL else 1.0)
                b2 = bias[(k, s)]
                rows.append({"cell_mm": round(cell_mm(s), 4), "variance": v, "bias2": b2, "risk": v + b2})
            best = min(range(len(cands)), key=lambda i: rows[i]["risk"])
            spacing[k] = cands[best]
            for i, row in enumerate(rows):
                row["chosen"] = i == best
            table[name] = rows
    cells = {n: cell_mm(spacing[k]) for k, n in enumerate(PARAMETER_NAMES)}
    return GridChoice(cells, table, [float(v) for v in noise.cpu()], (h, w), mm, size)
