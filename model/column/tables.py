"""σa lookup tables of Gaussian weights per layer, wavelength and profile (DWRR08 §4.5).

Scattering is fixed per layer and wavelength, so a profile's Gaussian weights depend on σa alone.
For each layer and wavelength the tables hold ``n_sigma_a`` log-spaced σa samples × K weights:
the epidermis's R⁺, T⁺, R⁻, T⁻ (slab, multipole) and the dermis's R⁺ (semi-infinite, dipole) — or,
with ``profiles: transport``, the same five with the Monte Carlo's shapes (``layer_shapes``) and
adding-doubling's totals (``layer_totals``).
Lookups interpolate linearly in log σa and are differentiable with respect to σa.

Tables are a cache of the profile model: they are written to disk under a key over every setting
that shapes them (scattering, indices, thickness, source depth, the Gaussian basis, the σa grid,
the fit grid, the wavelengths and this module's version) and rebuilt when the key differs.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import layer_shapes, layer_totals
from .gaussians import fit_gaussian_weights, plane_quadrature
from .profiles import dipole_profile, dipole_total, multipole_profiles, multipole_totals
from ..settings import ModelSettings
from ..optics.spectra import chromophore_spectra

__all__ = [
    "EPIDERMIS_PROFILES",
    "ProfileTables",
    "build_profile_tables",
    "default_cache_dir",
    "load_profile_tables",
    "load_thin_dermis_tables",
    "SlabTables",
    "table_key",
]

TABLE_FORMAT_VERSION = 4  # 2: extrapolation distances in float64; 3: profiles (transport | diffusion); 4: transport's shapes
EPIDERMIS_PROFILES = ("R_plus", "T_plus", "R_minus", "T_minus")
DERMIS_PROFILES = ("R_plus",)

Progress = Callable[[int, int], None]


def default_cache_dir() -> Path:
    """``$SKINLAYERS_CACHE`` if set, else ``$XDG_CACHE_HOME/skinlayers`` (``~/.cache/skinlayers``)."""
    if os.environ.get("SKINLAYERS_CACHE"):
        return Path(os.environ["SKINLAYERS_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "skinlayers"


def table_key(settings: ModelSettings, wavelength_nm: torch.Tensor) -> dict:
    """Every setting that shapes the tables, as a JSON-able dict."""
    o = settings.optics
    shaping = {
        k: getattr(o, k)
        for k in (
            "epidermis_thickness_mm",
            "n_epidermis",
            "n_dermis",
            "n_above",
            "scattering_mie_coeff",
            "scattering_mie_exponent",
            "scattering_rayleigh_coeff",
            "scattering_rayleigh_exponent",
            "dermis_scattering_ratio",
            "source_depth",
        )
    }
    if settings.profiles == "transport":
        shaping["transport_tables"] = layer_totals.tables_digest()
        shaping["transport_shapes"] = layer_shapes.shapes_digest()
    return {
        "version": TABLE_FORMAT_VERSION,
        "profiles": settings.profiles,
        "optics": shaping,
        "tables": settings.tables.model_dump(mode="json"),
        "wavelength_nm": [round(float(w), 6) for w in torch.as_tensor(wavelength_nm).reshape(-1)],
    }


def _digest(key: dict) -> str:
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]


@dataclass(frozen=True)
class ProfileTables:
    """Gaussian weights: ``epidermis`` ``(L, 4, S, K)`` (R⁺, T⁺, R⁻, T⁻), ``dermis`` ``(L, 1, S, K)``."""

    wavelength_nm: torch.Tensor
    sigma_a_per_mm: torch.Tensor
    variances_mm2: torch.Tensor
    epidermis: torch.Tensor
    dermis: torch.Tensor
    key: dict

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "ProfileTables":
        cast = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return ProfileTables(
            self.wavelength_nm.to(device=device),
            cast(self.sigma_a_per_mm),
            cast(self.variances_mm2),
            cast(self.epidermis),
            cast(self.dermis),
            self.key,
        )

    def lookup(self, layer: str, profile: str, sigma_a_per_mm: torch.Tensor) -> torch.Tensor:
        """Gaussian weights ``(..., L, K)`` for σa ``(..., L)`` (last axis: this table's wavelengths).

        Between samples the weights' *shape* (weights over their sum) is interpolated linearly in
        log σa and their *sum* log-linearly: transmittances fall exponentially with σa (a factor of
        two between neighbouring samples for the darkest epidermis), which linear interpolation of
        the weights themselves would miss by up to a quarter. Values outside the range take the end
        sample.
        """
        shape, log_total = self.normalized(layer, profile)
        t, i0 = self._position(sigma_a_per_mm, shape.shape[0])
        total = torch.exp(self._lerp(log_total[..., None], t, i0))[..., 0]
        return total[..., None] * self._lerp(shape, t, i0)

    def totals(self, layer: str, profile: str, sigma_a_per_mm: torch.Tensor) -> torch.Tensor:
        """Plane integral of the tabulated profile, Σ_k w_k, ``(..., L)`` (log-linear in log σa)."""
        _, log_total = self.normalized(layer, profile)
        t, i0 = self._position(sigma_a_per_mm, log_total.shape[0])
        return torch.exp(self._lerp(log_total[..., None], t, i0))[..., 0]

    def normalized(self, layer: str, profile: str) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L, S, K)`` weights over their sum, and ``(L, S)`` log of the sum (floored at 1e-300)."""
        weights = self.table(layer, profile)
        total = weights.sum(-1).clamp_min(1e-300)
        return weights / total[..., None], torch.log(total)

    def _position(self, sigma_a_per_mm: torch.Tensor, n_bands: int) -> tuple[torch.Tensor, torch.Tensor]:
        sa = torch.as_tensor(sigma_a_per_mm)
        if sa.shape[-1:] != (n_bands,):
            raise ValueError(f"sigma_a must end in the tables' {n_bands} wavelengths, got shape {tuple(sa.shape)}")
        grid = self.sigma_a_per_mm
        log_lo, log_hi = math.log(float(grid[0])), math.log(float(grid[-1]))
        step = (log_hi - log_lo) / (grid.numel() - 1)
        t = (torch.log(sa.clamp(float(grid[0]), float(grid[-1]))) - log_lo) / step
        i0 = torch.clamp(t.detach().floor().long(), 0, grid.numel() - 2)
        return t, i0

    def flat_position(self, sigma_a_per_mm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """σa ``(..., L)`` → its flat sample index band·S + i₀ and fraction ``(..., L)``: the renderer's
        ``gather.lookup`` convention, for tables of the bands × σa grid (the hand-over factor's)."""
        bands = self.wavelength_nm.numel()
        t, i0 = self._position(sigma_a_per_mm, bands)
        flat = torch.arange(bands, device=i0.device) * self.sigma_a_per_mm.numel() + i0
        return flat, t - i0.to(t)

    @staticmethod
    def _lerp(table: torch.Tensor, t: torch.Tensor, i0: torch.Tensor) -> torch.Tensor:
        """``table`` ``(L, S, K)`` at fractional sample positions ``t`` ``(..., L)`` → ``(..., L, K)``."""
        n = table.shape[1]
        frac = (t - i0.to(t)).unsqueeze(-1)
        flat = table.to(t).reshape(-1, table.shape[-1])
        index = (torch.arange(table.shape[0], device=t.device) * n + i0).reshape(-1)
        w0 = flat.index_select(0, index).reshape(*i0.shape, -1)
        w1 = flat.index_select(0, index + 1).reshape(*i0.shape, -1)
        return w0 + frac * (w1 - w0)

    def table(self, layer: str, profile: str) -> torch.Tensor:
        """The weights of one profile, ``(L, S, K)``."""
        if layer == "epidermis":
            names, data = EPIDERMIS_PROFILES, self.epidermis
        elif layer == "dermis":
            names, data = DERMIS_PROFILES, self.dermis
        else:
            raise ValueError(f"layer must be 'epidermis' or 'dermis', got {layer!r}")
        if profile not in names:
            raise ValueError(f"the {layer} has profiles {names}, not {profile!r}")
        return data[:, names.index(profile)]

    def out_of_range(self, sigma_a_per_mm: torch.Tensor) -> torch.Tensor:
        """Boolean mask of σa values outside the tabulated range (they are clamped on lookup)."""
        return (sigma_a_per_mm < self.sigma_a_per_mm[0]) | (sigma_a_per_mm > self.sigma_a_per_mm[-1])


def build_profile_tables(
    wavelength_nm: torch.Tensor, settings: ModelSettings | None = None, progress: Progress | None = None
) -> ProfileTables:
    """Fit the Gaussian weights of every profile at every tabulated σa and wavelength (float64).

    ``settings.profiles == "diffusion"``: the multipole (epidermis) and dipole (dermis) profiles, DWRR08
    §4.1–4.5. ``"transport"``: each profile's shape from the Monte Carlo (``layer_shapes``, its line
    spread fitted) and its plane integral from adding-doubling (``layer_totals``). The epidermis's T⁺
    is then its *scattered* part only; the renderer adds the unscattered beam per pixel.
    """
    settings = settings or ModelSettings()
    opt, tab = settings.optics, settings.tables
    spectra = chromophore_spectra(wavelength_nm, opt)
    sigma_a = torch.logspace(
        math.log10(tab.sigma_a_min_per_mm), math.log10(tab.sigma_a_max_per_mm), tab.n_sigma_a, dtype=torch.float64
    )
    variances = np.array(tab.gaussian_variances_mm2())
    r, q = plane_quadrature(tab.fit_r_min_mm, tab.fit_r_max_mm, tab.fit_r_samples)
    r_t = torch.from_numpy(r)
    n_wl = spectra.wavelength_nm.numel()
    epi = np.zeros((n_wl, len(EPIDERMIS_PROFILES), tab.n_sigma_a, tab.n_gaussians))
    derm = np.zeros((n_wl, len(DERMIS_PROFILES), tab.n_sigma_a, tab.n_gaussians))
    eta_top, eta_mid = opt.n_epidermis / opt.n_above, opt.n_epidermis / opt.n_dermis
    eta_derm = opt.n_dermis / opt.n_epidermis
    for j in range(n_wl):
        s_epi = spectra.scattering_epidermis[j]
        s_derm = spectra.scattering_dermis[j]
        if settings.profiles == "transport":
            epi[j], derm[j] = _transport_weights(sigma_a, s_epi, s_derm, opt, variances)
        else:
            prof = multipole_profiles(
                r_t, sigma_a, s_epi, opt.epidermis_thickness_mm, eta_top, eta_mid,
                tol=tab.multipole_tolerance, source_depth=opt.source_depth,
            )
            tot = multipole_totals(sigma_a, s_epi, opt.epidermis_thickness_mm, eta_top, eta_mid,
                                   source_depth=opt.source_depth)
            for p in range(len(EPIDERMIS_PROFILES)):
                epi[j, p] = fit_gaussian_weights(prof[p].numpy(), tot[p].numpy(), variances, r, q)
            derm[j, 0] = fit_gaussian_weights(
                dipole_profile(r_t, sigma_a, s_derm, eta_derm).numpy(),
                dipole_total(sigma_a, s_derm, eta_derm).numpy(),
                variances, r, q,
            )
        if progress is not None:
            progress(j + 1, n_wl)
    return ProfileTables(
        wavelength_nm=spectra.wavelength_nm,
        sigma_a_per_mm=sigma_a,
        variances_mm2=torch.from_numpy(variances),
        epidermis=torch.from_numpy(epi),
        dermis=torch.from_numpy(derm),
        key=table_key(settings, spectra.wavelength_nm),
    )


def _transport_weights(sigma_a: torch.Tensor, s_epi: torch.Tensor, s_derm: torch.Tensor, opt,
                       variances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One wavelength's weights ``(4, S, K)`` and ``(1, S, K)``: Monte Carlo shapes, adding-doubling totals."""
    tt = layer_totals.layer_totals(sigma_a, s_epi, opt.epidermis_thickness_mm, sigma_a, s_derm,
                                   opt.n_above, opt.n_epidermis, opt.n_dermis, handover="lambertian")
    sa, se, sd = sigma_a.numpy(), float(s_epi), float(s_derm)
    slab = layer_shapes.slab_shapes(np.log10(sa / se), math.log10(se * opt.epidermis_thickness_mm))
    targets = (tt.R1_plus, tt.T1_diffuse, tt.R1_minus, tt.T1_minus)
    epi = np.stack([layer_shapes.fit_line_spread_weights(slab[p], sa + se, t.numpy(), variances)
                    for p, t in enumerate(targets)])
    derm = layer_shapes.fit_line_spread_weights(layer_shapes.half_space_shape(np.log10(sa / sd)), sa + sd,
                                                tt.R2_plus.numpy(), variances)
    return epi, derm[None]


def load_profile_tables(
    wavelength_nm: torch.Tensor,
    settings: ModelSettings | None = None,
    cache_dir: Path | str | None = None,
    progress: Progress | None = None,
    rebuild: bool = False,
) -> ProfileTables:
    """Tables for these wavelengths and settings from the disk cache, built and stored if missing or stale."""
    settings = settings or ModelSettings()
    wavelength_nm = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    key = table_key(settings, wavelength_nm)
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = folder / f"profile-tables-{_digest(key)}.pt"
    if path.exists() and not rebuild:
        try:
            stored = torch.load(path, map_location="cpu", weights_only=True)
            if json.loads(stored["key"]) == key:
                return ProfileTables(
                    stored["wavelength_nm"], stored["sigma_a_per_mm"], stored["variances_mm2"],
                    stored["epidermis"], stored["dermis"], key,
                )
        except Exception:  # noqa: BLE001 (any unreadable cache file is rebuilt, never trusted)
            warnings.warn(f"profile table cache {path} is unreadable; rebuilding it", stacklevel=2)
    tables = build_profile_tables(wavelength_nm, settings, progress)
    _save(tables, path)
    return tables


def _save(tables: ProfileTables, path: Path) -> None:
    """Write atomically: a reader never sees a half-written cache file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "key": json.dumps(tables.key, sort_keys=True),
            "wavelength_nm": tables.wavelength_nm,
            "sigma_a_per_mm": tables.sigma_a_per_mm,
            "variances_mm2": tables.variances_mm2,
            "epidermis": tables.epidermis,
            "dermis": tables.dermis,
        }
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".pt")
        os.close(fd)
        torch.save(payload, tmp)
        os.replace(tmp, path)
    except OSError as exc:
        warnings.warn(f"could not cache profile tables in {path.parent}: {exc}", stacklevel=3)


@dataclass(frozen=True)
class SlabTables:
    """Tables of a thin dermis slab between two epidermis layers (thin geometry, DWRR08 §4.4):
    ``weights`` ``(L, 4, S, K)`` for R⁺, T⁺, R⁻, T⁻ of a dermis of ``thickness_mm``."""

    wavelength_nm: torch.Tensor
    sigma_a_per_mm: torch.Tensor
    variances_mm2: torch.Tensor
    weights: torch.Tensor
    thickness_mm: float
    key: dict

    def to(self, device=None, dtype=None) -> "SlabTables":
        cast = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return SlabTables(self.wavelength_nm.to(device=device), cast(self.sigma_a_per_mm), cast(self.variances_mm2),
                          cast(self.weights), self.thickness_mm, self.key)

    def table(self, layer: str, profile: str) -> torch.Tensor:
        if layer != "thin_dermis" or profile not in EPIDERMIS_PROFILES:
            raise ValueError(f"a thin dermis has profiles {EPIDERMIS_PROFILES}, not {layer} {profile}")
        return self.weights[:, EPIDERMIS_PROFILES.index(profile)]

    def normalized(self, layer: str, profile: str) -> tuple[torch.Tensor, torch.Tensor]:
        weights = self.table(layer, profile)
        total = weights.sum(-1).clamp_min(1e-300)
        return weights / total[..., None], torch.log(total)


def load_thin_dermis_tables(
    wavelength_nm: torch.Tensor, thickness_mm: float, settings: ModelSettings | None = None,
    cache_dir: Path | str | None = None,
) -> SlabTables:
    """Tables of a dermis slab of ``thickness_mm`` bounded by epidermis on both sides, cached like the others."""
    settings = settings or ModelSettings()
    if not thickness_mm > 0:
        raise ValueError(f"thin dermis thickness must be > 0 mm, got {thickness_mm}")
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    key = {**table_key(settings, wl), "thin_dermis_mm": round(float(thickness_mm), 9)}
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = folder / f"thin-dermis-tables-{_digest(key)}.pt"
    if path.exists():
        try:
            stored = torch.load(path, map_location="cpu", weights_only=True)
            if json.loads(stored["key"]) == key:
                return SlabTables(stored["wavelength_nm"], stored["sigma_a_per_mm"], stored["variances_mm2"],
                                  stored["weights"], float(thickness_mm), key)
        except Exception:  # noqa: BLE001
            warnings.warn(f"thin-dermis table cache {path} is unreadable; rebuilding it", stacklevel=2)
    opt, tab = settings.optics, settings.tables
    spectra = chromophore_spectra(wl, opt)
    sigma_a = torch.logspace(math.log10(tab.sigma_a_min_per_mm), math.log10(tab.sigma_a_max_per_mm), tab.n_sigma_a,
                             dtype=torch.float64)
    variances = np.array(tab.gaussian_variances_mm2())
    r, q = plane_quadrature(tab.fit_r_min_mm, tab.fit_r_max_mm, tab.fit_r_samples)
    eta = opt.n_dermis / opt.n_epidermis
    weights = np.zeros((wl.numel(), 4, tab.n_sigma_a, tab.n_gaussians))
    for j in range(wl.numel()):
        s = spectra.scattering_dermis[j]
        prof = multipole_profiles(torch.from_numpy(r), sigma_a, s, float(thickness_mm), eta, eta,
                                  tol=tab.multipole_tolerance, source_depth="capped")
        tot = multipole_totals(sigma_a, s, float(thickness_mm), eta, eta, source_depth="capped")
        for p in range(4):
            weights[j, p] = fit_gaussian_weights(prof[p].numpy(), tot[p].numpy(), variances, r, q)
    tables = SlabTables(wl, sigma_a, torch.from_numpy(variances), torch.from_numpy(weights), float(thickness_mm), key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".pt")
        os.close(fd)
        torch.save({"key": json.dumps(key, sort_keys=True), "wavelength_nm": wl, "sigma_a_per_mm": sigma_a,
                    "variances_mm2": tables.variances_mm2, "weights": tables.weights}, tmp)
        os.replace(tmp, path)
    except OSError as exc:
        warnings.warn(f"could not cache thin-dermis tables in {path.parent}: {exc}", stacklevel=2)
    return tables
