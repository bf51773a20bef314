"""Uncertainty that covers the error: the noise's share, widened by the two things it leaves out.

The noise's share is the inverse Fisher information of the whole fit (``schur.marginal_variance``; per
pixel the sandwich of ``fit._sigma``) with each pixel's *homogeneous* Jacobian J̃. Two things make the
error larger than that, and both are measured on the cube itself:

Cross-talk (every map, at the pixel's scale). ``gn-hom`` stops where J̃ᵀr = 0. Linearised, a noise ε
then moves a pixel's maps by (J̃ᵀJ)⁻¹J̃ᵀε, with J the renderer's own sensitivity of the pixel to its own
maps: a pixel's melanin darkens the light that leaves through it, while the light that entered
through it leaves mostly through its neighbours, so J ≈ ρ J̃ with ρ < 1 and the noise share is σ/ρ.
ρ per map is measured by one render (``crosstalk_ratio``): every loss pixel's unknowns moved by ±ε
with independent random signs, the render's change regressed on J̃ δx pixel by pixel (the neighbours'
moves, of random sign, average out). Only where the renderer's fit was kept: the homogeneous model
answers each pixel's own noise alone.

Variation finer than the nodes (maps on nodes). A map on nodes is the cube's best smooth map; the skin
differs from it between the nodes, and its σ (the nodes' noise, averaged over hundreds of pixels) says
nothing of that. Each pixel's own evidence of it (``subnode_sd``) is its residual projected on the
map's direction once the pixel's own maps are taken out, whitened by each band's noise:
δᵢ = aᵢᵀrᵢ / aᵢᵀaᵢ with noise variance 1/aᵢᵀaᵢ, and a skin deviation d shows as ρd. The mean of
(δ² − 1/aᵀa)/ρ² over a node cell around the pixel (clamped at 0) estimates the variance of the skin
about the node map there; its square root, in the parameter's units, is added to σ in quadrature.
What the cube cannot show (detail the light's spread blurs below the noise) it cannot add either.

Nodes' noise share (``schur.marginal_variance`` with clusters): the larger of the inverse Fisher
information and the cluster-robust sandwich over 1-mm squares, since the residual of a fit whose model
is not the skin's is correlated in space and a node's pixels are worth fewer independent ones.

The model's own error (``MODEL_FLOOR``): what the data cannot reveal — the fit's physics against a
scene rendered finer, through optics and a calibration — measured on simulated sessions and added in
quadrature (a Type B component in the GUM's terms). The coverage each term brings, and where these
floors were measured and checked, is in docs/reconstruct.md, "Uncertainty".

Shapes: per-pixel rows ``(N, ·)``; Jacobians ``(N, L, N_PARAMS)`` in the unconstrained x.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from ...model import N_PARAMS, PARAMETER_NAMES
from ..levels.problem import Evaluation, LevelProblem

__all__ = ["FLOOR_COVERAGE", "MODEL_FLOOR", "MODEL_FLOORS", "MODEL_FLOOR_ABSOLUTE", "PROBE_STEP", "crosstalk_ratio",
           "floor_for_coverage", "model_floor", "subnode_sd"]

#: The model's own error per map, relative to the value (β_m: absolute, it is a share), added to σ in
#: quadrature: for each map the smallest floor with which 90% of the visible, unflagged pixels lie within
#: ±2σ of the truth, pooled over the simulated demo sessions of seeds 1 and 2 (Fitzpatrick III interior,
#: no hairs, the rig's camera noise, fitted at 256²; docs/reconstruct.md "Uncertainty"; seed 0 held out).
#: Carotene's is five times its value: at this noise the bands do not hold it (its map is reported
#: undetermined where it rests at a bound).
MODEL_FLOOR = {"C_m": 0.010, "beta_m": 0.028, "C_he": 0.19, "C_bc": 5.1, "C_hd": 0.066}
#: The floor by the fit's physics (``model.profiles``). Diffusion's is ``MODEL_FLOOR``, from its own
#: light (the demo's sessions). Transport's comes from the light it was made to match, the shipped
#: Monte Carlo sessions, by the same rule (``tests/bench/test_transport_session_64.py``; where and how
#: well it holds: docs/transport.md, "Sessions at the size a user fits").
#: Carotene keeps diffusion's five times its value: it rests at a bound on most of those sessions, where a
#: floor relative to the value says nothing.
MODEL_FLOORS = {"diffusion": MODEL_FLOOR,
                "transport": {"C_m": 0.13, "beta_m": 0.18, "C_he": 0.11, "C_bc": 5.1, "C_hd": 0.25}}
MODEL_FLOOR_ABSOLUTE = ("beta_m",)
#: The share of the scored pixels a floor is set to cover within ±2σ (``floor_for_coverage``).
FLOOR_COVERAGE = 0.9

#: The probe's move of every unknown (x units: ~5% of a concentration), small enough to be linear.
PROBE_STEP = 0.05
#: The probe's signs come from this seed: the same cube gives the same σ.
PROBE_SEED = 0
#: ρ is kept within these: below, the probe found no response to speak of (an unknown the bands do
#: not see); above 1 the pixel would answer more than its homogeneous model says (not physical).
RHO_MIN, RHO_MAX = 0.05, 1.0


def crosstalk_ratio(problem: LevelProblem, ev: Evaluation, jac: torch.Tensor) -> torch.Tensor:
    """ρ ``(N_PARAMS,)``: the renderer's own-pixel response to each map over its homogeneous model's,
    from one probe render at ``ev``'s unknowns; ``jac`` ``(N, L, N_PARAMS)`` is J̃ (row-weighted as the
    unweighted problem's: robust weights off)."""
    n = problem.n_pixels
    g = torch.Generator().manual_seed(PROBE_SEED)
    signs = (torch.randint(0, 2, (N_PARAMS, n), generator=g) * 2 - 1).to(ev.x.dtype).to(ev.x.device)
    probe_x = ev.x.clone()
    flat = probe_x.reshape(N_PARAMS, -1)
    flat[:, problem.pixels] = flat[:, problem.pixels] + PROBE_STEP * signs
    probe = problem.evaluate(probe_x, ev.log_scale)
    change = problem.at_pixels(probe.image - ev.image).double() * float(torch.exp(ev.log_scale)) * problem.band_weight.double()
    predicted = jac.double() * (PROBE_STEP * signs.T.double())[:, None, :]  # (N, L, N_PARAMS)
    rho = (change[..., None] * predicted).sum((0, 1)) / (predicted**2).sum((0, 1)).clamp_min(1e-300)
    return rho.clamp(RHO_MIN, RHO_MAX)


def subnode_sd(problem: LevelProblem, jac: torch.Tensor, residual: torch.Tensor, sd_band: torch.Tensor, rho: torch.Tensor,
               dpdx: torch.Tensor) -> torch.Tensor:
    """The skin's spread about each map on nodes, per loss pixel ``(N, N_PARAMS)`` in the parameter's
    units (0 for the per-pixel maps): ``jac`` J̃ ``(N, L, N_PARAMS)``, ``residual`` ``(N, L)`` unweighted
    (unused bands 0), ``sd_band`` ``(L,)`` each band's noise, ``rho`` ``(N_PARAMS,)`` the cross-talk
    ratio, ``dpdx`` ``(N, N_PARAMS)`` ∂p/∂x at the pixels."""
    layout = problem.layout
    out = torch.zeros(problem.n_pixels, N_PARAMS, dtype=torch.float64, device=jac.device)
    if layout.per_pixel:
        return out
    used = problem.band_weight > 0
    jw = jac.double()[:, used] / sd_band.double()[used][None, :, None]
    rw = residual.double()[:, used] / sd_band.double()[used]
    own = jw[..., layout.fine]  # (N, L_used, n_fine); n_fine may be 0 (every map on nodes)
    gram = own.transpose(1, 2) @ own
    if layout.fine:
        ridge = 1e-9 * torch.diagonal(gram, dim1=1, dim2=2).amax(1).clamp_min(1e-300)[:, None, None]
        gram = gram + ridge * torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    h, w = problem.level.shape
    mask = problem.mask.cpu().numpy()
    pixels = problem.pixels.cpu().numpy()
    for k in layout.coarse:
        col = jw[..., k]
        a = col - (own @ torch.linalg.solve(gram, (own.transpose(1, 2) @ col[..., None])))[..., 0] if layout.fine else col
        aa = (a * a).sum(1).clamp_min(1e-300)
        excess = (((a * rw).sum(1) / aa) ** 2 - 1.0 / aa) / float(rho[k]) ** 2  # (N,) in x², noise removed
        image = np.zeros(h * w)
        image[pixels] = excess.cpu().numpy()
        cell_px = max(int(round(layout_cell_mm(problem, k) / problem.level.mm_per_pixel)), 1)
        size = min(cell_px, max(h, w))
        summed = ndimage.uniform_filter(image.reshape(h, w), size=size, mode="constant")
        count = ndimage.uniform_filter(mask.astype(float), size=size, mode="constant")
        local = np.where(count > 0, summed / np.maximum(count, 1e-12), 0.0).reshape(-1)[pixels]
        out[:, k] = torch.from_numpy(np.sqrt(np.clip(local, 0.0, None))).to(out) * dpdx[:, k].double()
    return out


def floor_for_coverage(error: torch.Tensor, sigma: torch.Tensor, floor: float, scale: torch.Tensor,
                       share: float = FLOOR_COVERAGE) -> tuple[torch.Tensor, float]:
    """The rule that sets a map's model floor, on one fit: ``error`` = |fit − truth| and ``sigma`` (σ as written,
    with ``floor`` × ``scale`` in quadrature) per pixel ``(N,)``; ``scale`` the value a floor is relative to
    (the fit's |value|, or 1 for an absolute floor). Returns σ's data terms alone ``(N,)`` (the floor taken
    out) and the smallest floor, in units of ``scale``, that puts ``share`` of the pixels within ±2σ."""
    data = torch.sqrt((sigma**2 - (floor * scale) ** 2).clamp_min(0.0))
    needed = torch.sqrt(((error / 2) ** 2 - data**2).clamp_min(0.0)) / scale
    return data, float(torch.quantile(needed, share))


def model_floor(p: torch.Tensor, profiles: str = "diffusion") -> torch.Tensor:
    """The model floor of the physics ``profiles`` (``MODEL_FLOORS``) at parameters ``p`` ``(N, N_PARAMS)``:
    ``(N, N_PARAMS)`` in the parameters' units."""
    floors = MODEL_FLOORS[profiles]
    out = torch.empty_like(p, dtype=torch.float64)
    for k, name in enumerate(PARAMETER_NAMES):
        f = floors[name]
        out[:, k] = f if name in MODEL_FLOOR_ABSOLUTE else f * p[:, k].double().abs()
    return out


def layout_cell_mm(problem: LevelProblem, k: int) -> float:
    """Map ``k``'s node spacing on this level (mm): the level's side over its nodes (``grids.node_count``)."""
    grid = problem.layout.grids[k]
    h, w = problem.level.shape
    return max(h / grid.nodes[0], w / grid.nodes[1]) * problem.level.mm_per_pixel
