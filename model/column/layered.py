"""Homogeneous two-layer skin: the Fourier-domain layer combination (DWRR08 §3, Eq. 3; §4.2, Eq. 7–8;
Donner & Jensen 2005).

For homogeneous layers the heterogeneous transport of Eq. 7 collapses to products of 2D Fourier
(Hankel) transforms. With the interface attenuation A = exp(-P) met twice per crossing,

    R₁₂ = R₁⁺ + A² T₁⁺ R₂⁺ T₁⁻ / (1 - A² R₁⁻ R₂⁺)

at every frequency k; at k = 0 it combines the plane integrals (totals). The layer transforms come
either from the exact multipole (closed form, all dipole pairs: ``method="exact"``) or from the
Gaussian tables (``method="tables"``), so each checks the other. With ``profiles: transport`` the
"exact" layers are adding-doubling's totals (``layer_totals``) with the Monte Carlo's tabulated shapes
(``layer_shapes``), which the Gaussian tables are fitted to, and (``handover: angular``) R₂⁺ carries
the factor κ that makes the scalar combination give the layers' total as adding-doubling stacks them
angle by angle (``layer_totals.handover_factor``; the same at every k: the correction is to the
light's angles, not to where it goes).

Shapes: parameters ``(...)``, wavelengths ``(L,)`` → spectra ``(..., L)``; with frequencies ``(N,)``
→ ``(..., L, N)``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from .gaussians import gaussian_sum_hankel
from .layer_shapes import shape_transforms
from .layer_totals import collimated_transmission, handover_grid, handover_on_grid, layer_totals
from ..optics.params import LayerAbsorption, SkinParams, layer_absorption
from .point_tables import PointTables
from .profiles import multipole_hankel, multipole_totals
from ..optics.radiometry import entry_transmittance
from ..settings import ModelSettings
from ..optics.spectra import ChromophoreSpectra, chromophore_spectra
from .tables import ProfileTables, load_profile_tables, table_key

__all__ = ["LayerTransforms", "SkinModel", "combine_layers", "inverse_hankel"]

METHODS = ("exact", "tables")


class LayerTransforms(NamedTuple):
    """Transforms (or totals) of the five profiles the skin needs, plus the interface attenuation."""

    R1_plus: torch.Tensor
    T1_plus: torch.Tensor
    R1_minus: torch.Tensor
    T1_minus: torch.Tensor
    R2_plus: torch.Tensor
    attenuation: torch.Tensor


def combine_layers(t: LayerTransforms) -> torch.Tensor:
    """R₁₂ = R₁⁺ + A² T₁⁺ R₂⁺ T₁⁻ / (1 - A² R₁⁻ R₂⁺): Eq. 7's series summed in the Fourier domain."""
    a2 = t.attenuation**2
    return t.R1_plus + a2 * t.T1_plus * t.R2_plus * t.T1_minus / (1.0 - a2 * t.R1_minus * t.R2_plus)


def inverse_hankel(transform: torch.Tensor, k_per_mm: torch.Tensor, r_mm: torch.Tensor) -> torch.Tensor:
    """f(r) = (1/2π) ∫ f̂(k) J₀(kr) k dk on a (log-spaced) k grid by the trapezoid rule, ``(..., R)``."""
    k = k_per_mm.to(transform)
    kernel = torch.special.bessel_j0(r_mm.to(transform)[:, None] * k[None, :]) * k[None, :]
    dk = torch.diff(k)
    w = torch.zeros_like(k)
    w[:-1] += 0.5 * dk
    w[1:] += 0.5 * dk
    return (transform * w) @ kernel.T / (2.0 * math.pi)


class SkinModel:
    """The homogeneous two-layer skin model with fixed settings; delegates to the pure functions."""

    def __init__(self, settings: ModelSettings | None = None, cache_dir: str | None = None) -> None:
        self.settings = settings or ModelSettings()
        self.cache_dir = cache_dir
        self._tables: dict[tuple[float, ...], ProfileTables] = {}
        self._handover: dict[tuple, torch.Tensor] = {}
        self._point: dict[tuple, object] = {}

    # -- inputs --------------------------------------------------------------------------------
    def spectra(self, wavelength_nm: torch.Tensor) -> ChromophoreSpectra:
        return chromophore_spectra(wavelength_nm, self.settings.optics)

    def absorption(self, params: SkinParams, spectra: ChromophoreSpectra) -> LayerAbsorption:
        o = self.settings.optics
        ref = params.C_m
        return layer_absorption(
            params, spectra.to(ref.device, ref.dtype), o.interface_melanin_fraction, o.epidermis_thickness_mm
        )

    def tables(self, wavelength_nm: torch.Tensor, progress=None) -> ProfileTables:
        w = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        key = tuple(round(float(x), 6) for x in w)
        if key not in self._tables:
            self._tables[key] = self._from_loaded(key) or load_profile_tables(w, self.settings, self.cache_dir, progress)
        return self._tables[key]

    def _from_loaded(self, key: tuple[float, ...]) -> ProfileTables | None:
        """These wavelengths' rows of a table already loaded that holds them all, or None. Each wavelength's
        weights are fitted on their own (``build_profile_tables``), so the rows are the table the set would
        get built alone: the simulator's one-node renders then take its band's three-node table instead
        of building each node's again."""
        for rounded, table in self._tables.items():
            at = {x: i for i, x in enumerate(rounded)}
            if all(x in at for x in key):
                rows = torch.tensor([at[x] for x in key], dtype=torch.long)
                return ProfileTables(table.wavelength_nm[rows], table.sigma_a_per_mm, table.variances_mm2,
                                     table.epidermis[rows], table.dermis[rows], table_key(self.settings, table.wavelength_nm[rows]))
        return None

    def point_tables(self, wavelength_nm: torch.Tensor, device: torch.device | str | None = None) -> PointTables:
        """The homogeneous model's totals tabulated at these bands for point fits
        (``point_tables.PointTables``), made once per set of bands and kept on each device asked for."""
        w = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        key = ("point", tuple(round(float(x), 6) for x in w), str(torch.device(device or "cpu")))
        if key not in self._point:
            home = ("point", key[1], "cpu")
            if home not in self._point:
                self._point[home] = PointTables.build(self, w)
            self._point[key] = self._point[home].to(device)
        return self._point[key]

    def handover_grid(self, wavelength_nm: torch.Tensor, device: torch.device | str | None = None) -> torch.Tensor:
        """The hand-over factor κ on the tables' σa grid, ``(L, S, S)`` float64 (``handover: angular``
        with ``profiles: transport``; ``layer_totals.handover_grid``), made once per set of bands and
        kept on each device it is asked for."""
        w = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        key = tuple(round(float(x), 6) for x in w)
        if key not in self._handover:
            spectra = self.spectra(w)
            self._handover[key] = handover_grid(
                self.tables(w).sigma_a_per_mm, spectra.scattering_epidermis, self.settings.optics.epidermis_thickness_mm,
                spectra.scattering_dermis)
        if device is None or torch.device(device) == self._handover[key].device:
            return self._handover[key]
        where = (key, str(torch.device(device)))
        if where not in self._handover:
            self._handover[where] = self._handover[key].to(device)
        return self._handover[where]

    def _etas(self) -> tuple[float, float, float]:
        o = self.settings.optics
        return o.n_epidermis / o.n_above, o.n_epidermis / o.n_dermis, o.n_dermis / o.n_epidermis

    # -- layer transforms -------------------------------------------------------------------------
    def layer_transforms(
        self,
        params: SkinParams,
        wavelength_nm: torch.Tensor,
        k_per_mm: torch.Tensor | None = None,
        method: str = "exact",
        extra_absorbance: torch.Tensor | None = None,
    ) -> LayerTransforms:
        """Totals (``k_per_mm=None``: ``(..., L)``) or Hankel transforms (``(..., L, N)``) of the layers.

        ``extra_absorbance`` ``(..., L)`` adds to the interface layer's absorbance (veins, tattoos).
        """
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        spectra = self.spectra(wavelength_nm)
        ab = self.absorption(params, spectra)
        absorbance = ab.interface_absorbance if extra_absorbance is None else ab.interface_absorbance + extra_absorbance
        return self.transforms_at(ab.epidermis, ab.dermis, absorbance, wavelength_nm, k_per_mm, method, spectra)

    def transforms_at(
        self,
        sigma_a_epidermis_per_mm: torch.Tensor,
        sigma_a_dermis_per_mm: torch.Tensor,
        interface_absorbance: torch.Tensor,
        wavelength_nm: torch.Tensor,
        k_per_mm: torch.Tensor | None = None,
        method: str = "exact",
        spectra: ChromophoreSpectra | None = None,
        thickness_mm: torch.Tensor | None = None,
    ) -> LayerTransforms:
        """The layers' totals or transforms at given absorption, each ``(..., L)``: at one band they
        depend on the two layers' σa and the interface absorbance alone (scattering, thickness and
        indices are the settings'), which is what lets ``point_tables`` tabulate them. ``spectra`` may
        carry other scattering (``point_model``); ``thickness_mm`` ``(..., 1)`` replaces the
        epidermis's thickness per element, for the exact diffusion totals only."""
        o = self.settings.optics
        if thickness_mm is not None and (method != "exact" or k_per_mm is not None or self.settings.profiles != "diffusion"):
            raise ValueError("a per-element epidermis thickness needs the exact diffusion totals (profiles: diffusion)")
        spectra = spectra if spectra is not None else self.spectra(wavelength_nm)
        ab = LayerAbsorption(sigma_a_epidermis_per_mm, sigma_a_dermis_per_mm, interface_absorbance)
        attenuation = torch.exp(-interface_absorbance)
        s_epi = spectra.scattering_epidermis.to(ab.epidermis)
        s_derm = spectra.scattering_dermis.to(ab.epidermis)
        d = o.epidermis_thickness_mm if thickness_mm is None else thickness_mm
        if method == "exact" and self.settings.profiles == "transport":
            epi, r2 = self._transport_exact(ab, s_epi, s_derm, d, k_per_mm)
        elif method == "exact":
            epi, r2 = self._diffusion_exact(ab, s_epi, s_derm, d, k_per_mm)
        else:
            epi, r2 = self._tabulated(ab, s_epi, s_derm, d, wavelength_nm, k_per_mm)
        if k_per_mm is not None:
            attenuation = attenuation[..., None]
        return LayerTransforms(epi[0], epi[1], epi[2], epi[3], r2, attenuation)

    def _transport_exact(self, ab: LayerAbsorption, s_epi, s_derm, d, k_per_mm):
        """transport: adding-doubling's totals, the Monte Carlo's shapes (model/column/layer_shapes.py); the
        epidermis's four profiles and the dermis's R₂⁺."""
        o = self.settings.optics
        tt = layer_totals(ab.epidermis, s_epi, d, ab.dermis, s_derm, o.n_above, o.n_epidermis, o.n_dermis,
                          self.settings.handover)
        targets = (tt.R1_plus, tt.T1_diffuse, tt.R1_minus, tt.T1_minus)
        if k_per_mm is None:
            epi, r2 = list(targets), tt.R2_plus
        else:
            shape_epi, shape_r2 = shape_transforms(ab.epidermis, s_epi, d, ab.dermis, s_derm, k_per_mm)
            epi = [t[..., None] * shape for t, shape in zip(targets, shape_epi)]
            r2 = tt.R2_plus[..., None] * shape_r2
        epi[1] = epi[1] + self._collimated(tt, k_per_mm)
        return epi, r2

    def _diffusion_exact(self, ab: LayerAbsorption, s_epi, s_derm, d, k_per_mm):
        """diffusion: the multipole's totals or Hankel transforms (DWRR08 §3)."""
        o = self.settings.optics
        eta_top, eta_mid, eta_derm = self._etas()
        if k_per_mm is None:
            epi = multipole_totals(ab.epidermis, s_epi, d, eta_top, eta_mid, source_depth=o.source_depth)
            r2 = multipole_totals(ab.dermis, s_derm, math.inf, eta_derm, 1.0).R_plus
        else:
            k = torch.as_tensor(k_per_mm).to(ab.epidermis)
            epi = multipole_hankel(k, ab.epidermis, s_epi, d, eta_top, eta_mid, source_depth=o.source_depth)
            r2 = multipole_hankel(k, ab.dermis, s_derm, math.inf, eta_derm, 1.0).R_plus
        return epi, r2

    def _tabulated(self, ab: LayerAbsorption, s_epi, s_derm, d, wavelength_nm, k_per_mm):
        """From the renderer's own tables (their totals, or their Gaussian sums' Hankel transforms), with
        the unscattered beam and the hand-over factor under ``profiles: transport``."""
        tab = self.tables(wavelength_nm).to(ab.epidermis.device, ab.epidermis.dtype)
        if k_per_mm is None:
            value = tab.totals
        else:
            k = torch.as_tensor(k_per_mm).to(ab.epidermis)

            def value(layer, profile, sa):
                return gaussian_sum_hankel(tab.lookup(layer, profile, sa), tab.variances_mm2, k)

        epi = [value("epidermis", p, ab.epidermis) for p in ("R_plus", "T_plus", "R_minus", "T_minus")]
        r2 = value("dermis", "R_plus", ab.dermis)
        if self.settings.profiles == "transport":
            epi[1] = epi[1] + self._collimated(collimated_transmission(ab.epidermis, s_epi, d, ab.dermis, s_derm),
                                               k_per_mm)
            if self.settings.handover == "angular":
                kappa = self._handover_at(tab, wavelength_nm, ab.epidermis, ab.dermis)
                r2 = r2 * (kappa if k_per_mm is None else kappa[..., None])
        return epi, r2

    def _handover_at(self, tab: ProfileTables, wavelength_nm, sa_epidermis, sa_dermis) -> torch.Tensor:
        """κ ``(..., L)`` from the grid at the tables' positions of both layers' σa (as the renderer)."""
        grid = self.handover_grid(wavelength_nm, sa_epidermis.device)
        return handover_on_grid(grid, *tab.flat_position(sa_epidermis), *tab.flat_position(sa_dermis))

    @staticmethod
    def _collimated(tt, k_per_mm) -> torch.Tensor:
        """The unscattered beam's share of T₁⁺ as the dermis's diffuse response sees it, q·T_c: a delta
        in space, so the same at every frequency."""
        value = tt.collimated_ratio * tt.T1_collimated
        return value if k_per_mm is None else value[..., None]

    # -- results ------------------------------------------------------------------------------------
    def total_reflectance(
        self, params: SkinParams, wavelength_nm: torch.Tensor, method: str = "exact", extra_absorbance=None
    ) -> torch.Tensor:
        """Plane integral of the combined profile R₁₂ per unit *entering* power, ``(..., L)``."""
        return combine_layers(self.layer_transforms(params, wavelength_nm, None, method, extra_absorbance))

    def diffuse_reflectance(
        self, params: SkinParams, wavelength_nm: torch.Tensor, method: str = "exact", extra_absorbance=None
    ) -> torch.Tensor:
        """Hemispherical diffuse reflectance R_d = F_t(0) R₁₂ for normal, collimated light, ``(..., L)``.

        Specular reflection excluded (see ``radiometry`` for the convention).
        """
        o = self.settings.optics
        f_t = entry_transmittance(o.n_epidermis, o.n_above)
        return f_t * self.total_reflectance(params, wavelength_nm, method, extra_absorbance)

    def combined_hankel(
        self, params: SkinParams, wavelength_nm: torch.Tensor, k_per_mm: torch.Tensor, method: str = "exact"
    ) -> torch.Tensor:
        """Hankel transform of the combined reflectance profile R₁₂(k), ``(..., L, N)``."""
        return combine_layers(self.layer_transforms(params, wavelength_nm, k_per_mm, method))
