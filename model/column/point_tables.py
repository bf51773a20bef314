"""The homogeneous model's layer totals tabulated over both layers' σa at a set of bands: point fits
at a fraction of the cost, with their Jacobian in closed form.

A point fit (``reconstruct.spectrum_fit``) evaluates the homogeneous model and its Jacobian at every
iteration of every spectrum, and the layers' totals (multipole sums, or adding-doubling's tables with
the hand-over factor) are nearly all of that cost. At one band the five totals R₁⁺, T₁⁺, R₁⁻, T₁⁻, R₂⁺
depend on the two layers' σa alone (scattering, thickness and indices are the settings'; the
interface absorbance only attenuates, DWRR08 Eq. 7), so they are tabulated once per set of bands on
a grid of log σa_epidermis × log σa_dermis spanning every skin DWRR08 Table 1's bounds allow, and
read by bicubic Hermite interpolation from the exact values and first derivatives at the nodes
(autodiff; the cross derivative by central differences of the exact first derivatives). One read gives each total
and its two partials; the attenuation and the layer combination (Eq. 7 summed, ``combine_layers``)
stay in closed form, so the Jacobian with respect to the five parameters is the chain rule through
Eq. 11–12, with no autodiff in the fit's loop. The tables' error against the model they stand for is
measured in docs/model.md ("Point fits from tabulated totals") and tested.

Shapes: parameters ``(M, N_PARAMS)``, spectra ``(M, L)``, Jacobians ``(M, L, N_PARAMS)``; the table's
coefficients ``(L·(S-1)², 5·16)`` for S nodes per axis.
"""

from __future__ import annotations

import itertools
from typing import Protocol

import torch

from ..optics.params import N_PARAMS, SkinParams, layer_absorption_jacobian, parameter_bounds
from ..optics.radiometry import entry_transmittance

__all__ = ["POINT_TABLE_NODES", "ColumnModel", "PointTables"]

#: Nodes per axis of log σa. Error against the exact model (docs/model.md): the interpolation is
#: fourth order, so doubling the nodes divides it by ~16; 48 keeps the fit's model within 1e-6
#: (relative) of the exact one over the whole box.
POINT_TABLE_NODES = 48
#: Bands whose node totals are differentiated at once in ``build`` (the autodiff graph's memory).
_BUILD_BANDS = 16
#: The five totals, in ``LayerTransforms`` order.
_N_TOTALS = 5
#: Hermite basis on [0, 1]: rows are the coefficients of t⁰…t³ for (f(0), f(1), f'(0), f'(1)).
_HERMITE = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [-3.0, 3.0, -2.0, -1.0], [2.0, -2.0, 1.0, 1.0]],
                        dtype=torch.float64)


class ColumnModel(Protocol):
    """What the tables need of the homogeneous column (``layered.SkinModel``, which builds them: named by
    its shape, not imported, so that the two modules do not import each other)."""

    settings: object

    def spectra(self, wavelength_nm: torch.Tensor): ...

    def absorption(self, params: SkinParams, spectra): ...

    def transforms_at(self, *args, **kwargs): ...


class PointTables:
    """The model's five layer totals at L bands on an S × S grid of (log σa_epi, log σa_derm).

    Made by ``PointTables.build(model, wavelength_nm)``; ``diffuse_reflectance(p)`` gives R_d and its
    Jacobian with respect to the parameters, as ``SkinModel.diffuse_reflectance`` (specular excluded).
    """

    def __init__(self, model: ColumnModel, wavelength_nm: torch.Tensor, log_lo: torch.Tensor, log_step: torch.Tensor,
                 coefficients: torch.Tensor, nodes: int) -> None:
        self.model = model
        self.wavelength_nm = wavelength_nm
        self.log_lo = log_lo  # (2, L): log σa of the first node, epidermis then dermis
        self.log_step = log_step  # (2, L)
        self.coefficients = coefficients  # (L·(S-1)², 5·16)
        self.nodes = nodes
        o = model.settings.optics
        self.entry = entry_transmittance(o.n_epidermis, o.n_above)
        self.spectra = model.spectra(wavelength_nm)

    @classmethod
    def build(cls, model: ColumnModel, wavelength_nm: torch.Tensor, nodes: int = POINT_TABLE_NODES) -> "PointTables":
        """Exact totals and their log-σa derivatives at the nodes (one backward pass per total), then each
        cell's bicubic Hermite coefficients."""
        if nodes < 4:
            raise ValueError(f"point tables need at least 4 nodes per axis, got {nodes}")
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        spectra = model.spectra(wl)
        lo, hi = _absorption_range(model, spectra)  # (2, L) each
        log_lo, log_hi = torch.log(lo), torch.log(hi)
        step = (log_hi - log_lo) / (nodes - 1)
        grid = log_lo[..., None] + step[..., None] * torch.arange(nodes, dtype=torch.float64)  # (2, L, S)
        u_epi = grid[0].T[:, None, :].expand(nodes, nodes, wl.numel()).contiguous()  # (S_epi, S_derm, L)
        u_derm = grid[1].T[None, :, :].expand(nodes, nodes, wl.numel()).contiguous()

        def totals(ue, ud, bands):
            t = model.transforms_at(torch.exp(ue), torch.exp(ud), torch.zeros_like(ue), wl[bands], None, "exact",
                                    model.spectra(wl[bands]))
            return torch.stack([t.R1_plus, t.T1_plus, t.R1_minus, t.T1_minus, t.R2_plus])  # (5, S, S, l)

        # every total at a node depends on that node's two σa alone, so the gradient of a total's sum
        # over the grid is its derivative at each node: one backward pass per total (reverse mode;
        # torch 2.13's forward mode takes a slow path at every operation with a constant operand, and
        # its first use in a process is slow too: docs/model.md, "Point fits from tabulated totals"),
        # bands in chunks (the graph's memory)
        parts = []
        for first in range(0, wl.numel(), _BUILD_BANDS):
            bands = slice(first, first + _BUILD_BANDS)
            ue, ud = u_epi[..., bands].clone().requires_grad_(True), u_derm[..., bands].clone().requires_grad_(True)
            with torch.enable_grad():
                graph = totals(ue, ud, bands)
                partials = [torch.autograd.grad(graph[t].sum(), (ue, ud), retain_graph=t + 1 < _N_TOTALS)
                            for t in range(_N_TOTALS)]
            parts.append((graph.detach(), torch.stack([p[0] for p in partials]), torch.stack([p[1] for p in partials])))
        value, d_epi, d_derm = (torch.cat([part[i] for part in parts], -1) for i in range(3))
        d_cross = 0.5 * (torch.gradient(d_epi, dim=2, edge_order=2)[0] / step[1]
                         + torch.gradient(d_derm, dim=1, edge_order=2)[0] / step[0])
        # to cell coordinates in [0, 1]²: derivatives times the steps
        s_epi, s_derm = step[0], step[1]
        coefficients = _hermite_cells(value, d_epi * s_epi, d_derm * s_derm, d_cross * s_epi * s_derm)
        return cls(model, wl, log_lo, step, coefficients, nodes)

    def to(self, device=None) -> "PointTables":
        return PointTables(self.model, self.wavelength_nm.to(device), self.log_lo.to(device), self.log_step.to(device),
                           self.coefficients.to(device), self.nodes)

    def totals(self, sigma_a_epidermis_per_mm: torch.Tensor, sigma_a_dermis_per_mm: torch.Tensor):
        """The five totals ``(5, M, L)`` at σa ``(M, L)`` of each layer, and their partials with respect to
        log σa_epidermis and log σa_dermis (each ``(5, M, L)``)."""
        m, n_band = sigma_a_epidermis_per_mm.shape
        s = self.nodes
        dev = sigma_a_epidermis_per_mm.device
        u = torch.stack([torch.log(sigma_a_epidermis_per_mm), torch.log(sigma_a_dermis_per_mm)])  # (2, M, L)
        pos = (u - self.log_lo[:, None, :]) / self.log_step[:, None, :]
        cell = pos.floor().clamp(0, s - 2)
        t = (pos - cell).clamp(0.0, 1.0)  # the box's edges are nodes: rounding may step outside by 1e-15
        band = torch.arange(n_band, device=dev)
        flat = (band * (s - 1) + cell[0].long()) * (s - 1) + cell[1].long()  # (M, L)
        c = self.coefficients.index_select(0, flat.reshape(-1)).view(m * n_band, _N_TOTALS, 16)
        te, td = t[0].reshape(-1), t[1].reshape(-1)
        one, zero = torch.ones_like(te), torch.zeros_like(te)
        pe = torch.stack([one, te, te * te, te * te * te], -1)  # (ML, 4): powers of t along the epidermis axis
        pd = torch.stack([one, td, td * td, td * td * td], -1)
        de = torch.stack([zero, one, 2 * te, 3 * te * te], -1)  # their derivatives
        dd = torch.stack([zero, one, 2 * td, 3 * td * td], -1)
        weights = torch.stack([(pe[:, :, None] * pd[:, None, :]).reshape(-1, 16), (de[:, :, None] * pd[:, None, :]).reshape(-1, 16),
                               (pe[:, :, None] * dd[:, None, :]).reshape(-1, 16)], -1)  # (ML, 16, 3)
        out = torch.bmm(c, weights).permute(2, 1, 0).reshape(3, _N_TOTALS, m, n_band)  # (value, ∂t_e, ∂t_d)
        value = out[0]
        d_epi = out[1] / self.log_step[0]
        d_derm = out[2] / self.log_step[1]
        return value, d_epi, d_derm

    def diffuse_reflectance(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """R_d ``(M, L)`` and ∂R_d/∂params ``(M, L, N_PARAMS)`` for parameters ``(M, N_PARAMS)``."""
        o = self.model.settings.optics
        skin = SkinParams.from_tensor(params)
        spectra = self.spectra.to(params.device, params.dtype)
        ab = self.model.absorption(skin, spectra)
        sa_epi, sa_derm, absorbance = ab.epidermis, ab.dermis, ab.interface_absorbance
        d_absorption = layer_absorption_jacobian(skin, spectra, o.interface_melanin_fraction, o.epidermis_thickness_mm)
        (r1p, t1p, r1m, t1m, r2p), de, dd = self.totals(sa_epi, sa_derm)
        a2 = torch.exp(-2.0 * absorbance)
        denom = 1.0 - a2 * r1m * r2p
        through = a2 * t1p * r2p * t1m / denom
        r = self.entry * (r1p + through)
        # ∂R₁₂ / ∂(R₁⁺, T₁⁺, R₁⁻, T₁⁻, R₂⁺) of R₁⁺ + A² T₁⁺ R₂⁺ T₁⁻ / (1 − A² R₁⁻ R₂⁺)
        partial = torch.stack([torch.ones_like(r1p), through / t1p, through * a2 * r2p / denom, through / t1m,
                               through / r2p + through * a2 * r1m / denom])
        d_log_epi = (partial * de).sum(0)  # ∂R₁₂/∂log σa_epi, (M, L)
        d_log_derm = (partial * dd).sum(0)
        d_absorbance = -2.0 * (through + through * a2 * r1m * r2p / denom)
        jac = (d_log_epi[..., None] * d_absorption[0] / sa_epi[..., None] + d_log_derm[..., None] * d_absorption[1] / sa_derm[..., None]
               + d_absorbance[..., None] * d_absorption[2])
        return r, self.entry * jac


def _absorption_range(model: ColumnModel, spectra) -> tuple[torch.Tensor, torch.Tensor]:
    """Least and greatest σa of each layer ``(2, L)`` over the parameter box: σa is multilinear in the
    parameters (Eq. 11–12), so its extremes are at the box's corners."""
    lo, hi = parameter_bounds(torch.float64)
    corners = torch.tensor(list(itertools.product((0.0, 1.0), repeat=N_PARAMS)), dtype=torch.float64)
    ab = model.absorption(SkinParams.from_tensor(lo + (hi - lo) * corners), spectra)
    both = torch.stack([ab.epidermis, ab.dermis])  # (2, 32, L)
    if bool((both.amin(1) <= 0).any()):
        raise ValueError("point tables need σa > 0 everywhere in the parameter box (a baseline absorption)")
    return both.amin(1), both.amax(1)


def _hermite_cells(f: torch.Tensor, fe: torch.Tensor, fd: torch.Tensor, fed: torch.Tensor) -> torch.Tensor:
    """Bicubic Hermite coefficients a_ij (of tᵉⁱ tᵈʲ) of every cell from node values and cell-scaled
    derivatives ``(5, S, S, L)`` → ``(L·(S-1)², 5·16)``."""

    def corners(g):  # (5, S-1, S-1, L, 2, 2): [epi corner, derm corner]
        return torch.stack([torch.stack([g[:, :-1, :-1], g[:, :-1, 1:]], -1), torch.stack([g[:, 1:, :-1], g[:, 1:, 1:]], -1)], -2)

    fv, e, d, ed = corners(f), corners(fe), corners(fd), corners(fed)
    # F = [[f, ∂d f], [∂e f, ∂e∂d f]] by blocks: rows (f(0), f(1), f'(0), f'(1)) along epi, columns along derm
    top = torch.cat([fv, d], -1)
    bottom = torch.cat([e, ed], -1)
    big = torch.cat([top, bottom], -2)  # (5, S-1, S-1, L, 4, 4)
    h = _HERMITE.to(f)
    a = h @ big @ h.T  # a[i, j]: coefficient of te^i td^j
    n_band = f.shape[-1]
    return a.permute(3, 1, 2, 0, 4, 5).reshape(n_band * (f.shape[1] - 1) * (f.shape[2] - 1), _N_TOTALS * 16).contiguous()

