"""What a set of filters tells the fit (``skinlayers design-bands`` searches over it: ``band_design.py``): the
catalogue of filters, the photographed signal and its noise (``Radiometry``), the prior of skins, the fit's
band Jacobian, each filter's information and the model's error as a bias (``FilterTerms``), the maps'
Cramér–Rao bounds in the fit's layout (``bound_variance``) and the criterion that scores a set
(``Criterion``). The module docstring of ``band_design.py`` states each choice."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..formats.errors import InputError

__all__ = ["CATALOGUE_DEFAULT", "CRITERIA", "CRITERION_WORDS", "SCORE_BATCH_BYTES", "UNDETERMINED_SD", "Criterion", "Filter", "FilterTerms", "Radiometry", "band_jacobian", "bound_variance",
           "default_catalogue", "filter_information", "filter_terms", "joined_terms", "prior_skins", "read_catalogue", "rgb_terms", "shared_pixels"]

#: The default catalogue: 10-nm filters every 10 nm over 400–720 nm (centre, FWHM in nm).
CATALOGUE_DEFAULT = (400.0, 720.0, 10.0, 10.0)
#: Parameters of the bound, in the fit's order: log C_m, β_m, log C_he, log C_bc, log C_hd.
PARAMETERS = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
#: The spread of each chromophore across the prior: log-normal σ (the demo scene's variation amplitudes).
SPREAD = {"C_m": 0.25, "beta_m": 0.3, "C_he": 0.3, "C_bc": 0.3, "C_hd": 0.25}
PRIOR_SAMPLES = 8
PRIOR_SEED = 20
#: The criteria (``Criterion``), in the words ``design.json`` and the chart use.
CRITERION_WORDS = {
    "rig": "the worst map's expected error (mean over the prior of log(1 + (CRB + model bias²)/target²); C_m, β_m, C_he, "
           "C_hd in the fit's layout) over the same for the rig's own bands: below 1, every map improves on the rig",
    "targets": "A-optimal: the maps' expected errors (mean over the prior of log(1 + (CRB + model bias²)/target²); C_m, β_m, "
               "C_he, C_hd in the fit's layout) summed",
}
CRITERIA = tuple(CRITERION_WORDS)
#: A map whose expected σ exceeds this (relative; β_m absolute) is reported undetermined.
UNDETERMINED_SD = 10.0
#: The RGB camera of the comparison: its channels' wavelengths, every step over the span (nm).
RGB_SPAN_NM = (380.0, 780.0)
RGB_STEP_NM = 5.0
#: Bytes a batch of sets may gather at once (each set's information: count × skins × 5 × 5 float64).
SCORE_BATCH_BYTES = 64 * 2**20


@dataclass(frozen=True)
class Filter:
    """A catalogue's filter: its centre and full width at half maximum (nm)."""

    centre_nm: float
    fwhm_nm: float

    def label(self) -> str:
        return f"{self.centre_nm:g}/{self.fwhm_nm:g}"


def default_catalogue() -> list[Filter]:
    lo, hi, step, fwhm = CATALOGUE_DEFAULT
    return [Filter(float(c), fwhm) for c in np.arange(lo, hi + step / 2, step)]


def read_catalogue(path: str | Path) -> list[Filter]:
    """Filters from a CSV with columns ``centre_nm`` and ``fwhm_nm`` (one filter a row, 380–800 nm)."""
    path = Path(path)
    try:
        rows = list(csv.DictReader(path.read_text(encoding="utf-8-sig").splitlines()))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable filter catalogue ({exc})") from None
    if not rows or not {"centre_nm", "fwhm_nm"} <= set(rows[0]):
        raise InputError(f"{path}: a catalogue needs the columns centre_nm and fwhm_nm and a row per filter")
    filters = []
    for line, row in enumerate(rows, start=2):
        try:
            f = Filter(float(row["centre_nm"]), float(row["fwhm_nm"]))
        except (TypeError, ValueError):
            raise InputError(f"{path}, line {line}: centre_nm and fwhm_nm must be numbers") from None
        if not (380.0 <= f.centre_nm <= 800.0 and 0.0 < f.fwhm_nm <= 100.0):
            raise InputError(f"{path}, line {line}: centre {f.centre_nm:g} nm must lie in 380–800, FWHM in (0, 100]")
        filters.append(f)
    if len({f.centre_nm for f in filters}) != len(filters):
        raise InputError(f"{path}: two filters share a centre")
    return filters


class Radiometry:
    """The simulator's photograph of a band, reduced to what the bound needs: each filter's ISO and the
    noise of the calibrated reflectance of a cube pixel (``reflectance_sd``)."""

    def __init__(self, rig=None, simulation=None) -> None:
        from ..acquire.simulator._optics import band_spectrum  # noqa: PLC0415
        from ..acquire.hardware.rig import load_rig  # noqa: PLC0415
        from ..acquire.simulator.simulated import flash_power  # noqa: PLC0415
        from ..acquire.simulator.simulation_settings import load_simulation_settings  # noqa: PLC0415

        self.rig = rig or load_rig()
        self.settings = simulation if simulation is not None else load_simulation_settings(None)
        s = self.settings
        self._spectrum = lambda f: band_spectrum(f.centre_nm, f.fwhm_nm, s.filters.wavelength_samples, s.flash.temperature_k,
                                                 s.sensor.sensitivity)
        self.reference_signal = float(band_spectrum(550.0, 10.0, s.filters.wavelength_samples, s.flash.temperature_k,
                                                    s.sensor.sensitivity).channel_signal[1])
        spectra = {b.wavelength_nm: self._spectrum(Filter(b.wavelength_nm, b.fwhm_nm)) for b in self.rig.bands}
        self.white_electrons = float(s.sensor.white_electrons or flash_power(s, self.rig, spectra, self.reference_signal))
        g = self.rig.geometry
        span = s.camera.window_span_px or 2 * g.rectify_px
        #: Bayer superpixels averaged into one cube pixel (across the window; foreshortened along the view)
        self.superpixels = (span / 2 / g.cube_px) ** 2 * math.cos(math.radians(self.rig.camera.angle_deg))

    def electrons(self, f: Filter) -> np.ndarray:
        """Mean electrons ``(3,)`` (R, G, B photosites) per unit reflectance at the image centre, f/10."""
        return self.white_electrons * self._spectrum(f).channel_signal / self.reference_signal

    def spectralon(self, f: Filter) -> float:
        """The Spectralon's reflectance as photographed (its certified value × the polarizers' factor)."""
        return self.rig.targets.spectralon_at(f.centre_nm) * self.rig.polarization.spectralon_factor

    def iso(self, f: Filter) -> int:
        """The largest ISO at which the Spectralon (the flash at its strongest) stays within ``reference_fill``
        of the range, as the rig file's ISOs were chosen; the lowest when none does."""
        return self._exposure(float(self.electrons(f).max()) * self.spectralon(f))[0]

    def _exposure(self, peak_e: float) -> tuple[int, float]:
        """The ISO by the rig's rule for a Spectralon of ``peak_e`` electrons at its brightest photosite, and
        the share of the light (≤ 1: the aperture stopped down) that keeps it in range at the lowest ISO."""
        s = self.settings.sensor
        peak_e *= 1.0 + self.settings.flash.jitter
        limit = s.reference_fill * (s.white_level - max(s.black_level))
        fitting = [iso for iso in s.iso_values if peak_e / self._gain(iso) <= limit]
        if fitting:
            return max(fitting), 1.0
        lowest = min(s.iso_values)
        return lowest, limit * self._gain(lowest) / peak_e

    def reflectance_sd(self, f: Filter, reflectance: torch.Tensor, iso: int | None = None) -> torch.Tensor:
        """The noise (standard deviation) of a cube pixel's calibrated reflectance at ``reflectance`` (any
        shape): skin over Spectralon superpixels (R + 2G + B) less the black frame, each photosite's
        variance (μ_e + σ_e²)/g² + σ_DN² + 1/12 in DN², averaged over ``superpixels``."""
        electrons = float(self.electrons(f) @ np.array([1.0, 2.0, 1.0]))
        return self._ratio_sd(electrons, 4, self.spectralon(f), iso or self.iso(f), reflectance)

    def rgb(self) -> tuple[torch.Tensor, torch.Tensor]:
        """An RGB camera under the flash without a filter: wavelengths ``(K,)`` every ``RGB_STEP_NM`` over
        ``RGB_SPAN_NM`` and each channel's weights ``(3, K)`` (flash × sensitivity, each row summing to 1)."""
        nodes, weights = self._rgb_weights()
        return torch.from_numpy(nodes), torch.from_numpy(weights / weights.sum(1, keepdims=True))

    def rgb_sd(self, reflectance: torch.Tensor) -> torch.Tensor:
        """The noise of an RGB camera's calibrated reflectance per channel ``(M, 3)`` at ``reflectance``
        ``(M, 3)``: each channel's photosites of a superpixel (R, 2 G, B) over the Spectralon's, the
        exposure by the rig's rule with the aperture stopped down where the lowest ISO saturates."""
        signal = self._rgb_weights()[1].sum(1) * RGB_STEP_NM  # ∫ flash × sensitivity dλ, as a filter's channel signal
        electrons = self.white_electrons * signal / self.reference_signal
        spectralon = self.spectralon(Filter(550.0, 10.0))
        iso, share = self._exposure(float(electrons.max()) * spectralon)
        photosites = (1, 2, 1)
        return torch.stack([self._ratio_sd(share * electrons[c] * n, n, spectralon, iso, reflectance[:, c])
                            for c, n in enumerate(photosites)], dim=1)

    def _rgb_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Wavelengths ``(K,)`` over ``RGB_SPAN_NM`` and flash × sensitivity of each channel there ``(3, K)``."""
        from ..acquire.simulator._optics import CHANNELS, blackbody, channel_sensitivity  # noqa: PLC0415

        s = self.settings
        nodes = np.arange(RGB_SPAN_NM[0], RGB_SPAN_NM[1] + RGB_STEP_NM / 2, RGB_STEP_NM)
        return nodes, np.stack([blackbody(nodes, s.flash.temperature_k) * channel_sensitivity(s.sensor.sensitivity[c], nodes)
                                for c in CHANNELS])

    def _ratio_sd(self, electrons: float, photosites: int, spectralon: float, iso: int, reflectance: torch.Tensor) -> torch.Tensor:
        """The noise of skin over Spectralon, ``photosites`` of a superpixel gathering ``electrons`` per unit
        reflectance together, less the black frame, averaged over ``superpixels``."""
        s = self.settings.sensor
        g = self._gain(iso)
        dark_var = photosites * ((s.read_noise_e / g) ** 2 + s.read_noise_dn**2 + 1.0 / 12.0)  # read noise and DN step

        def mean_var(rho):
            mu_e = electrons * rho * self.rig.polarization.skin_factor
            return mu_e / g, mu_e / g**2 + dark_var

        skin_dn, skin_var = mean_var(reflectance)
        ref_dn, ref_var = mean_var(torch.as_tensor(spectralon / self.rig.polarization.skin_factor, dtype=reflectance.dtype))
        # the black frame is subtracted from both: its variance (read noise alone) counts once in each
        relative = (skin_var + dark_var) / skin_dn**2 + (ref_var + dark_var) / ref_dn**2
        return reflectance * torch.sqrt(relative / self.superpixels)

    def _gain(self, iso: int) -> float:
        """Electrons per DN at ``iso``."""
        return self.settings.sensor.e_per_dn_iso100 * 100.0 / iso


def prior_skins(samples: int = PRIOR_SAMPLES, seed: int = PRIOR_SEED) -> torch.Tensor:
    """The prior ``(rows × samples, 5)`` float64 in ``PARAMETERS`` order: each Table 2 row, each chromophore
    multiplied by exp(σ·z) (β_m: its logit moved by σ·z), z standard normal from ``seed``."""
    from ..model import TABLE2  # noqa: PLC0415

    generator = torch.Generator().manual_seed(seed)
    out = []
    for row in TABLE2.values():
        base = torch.tensor([max(row[n], 1e-6) for n in PARAMETERS], dtype=torch.float64)
        z = torch.randn(samples, len(PARAMETERS), generator=generator, dtype=torch.float64)
        spread = torch.tensor([SPREAD[n] for n in PARAMETERS], dtype=torch.float64)
        skins = base * torch.exp(spread * z)
        beta = base[1].clamp(1e-3, 1 - 1e-3)
        skins[:, 1] = torch.sigmoid(torch.logit(beta) + spread[1] * z[:, 1])
        out.append(skins)
    return torch.cat(out)


def band_jacobian(skins: torch.Tensor, filters: Sequence[Filter], view_angle_deg: float = 30.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The fit's band reflectance ``(M, F)`` of each skin ``(M, 5)`` through each filter, seen at
    ``view_angle_deg``, and its derivative ``(M, F, 5)`` in log C_m, β_m, log C_he, log C_bc, log C_hd
    (``reconstruct/levels/problem.py``'s band model)."""
    from ..reconstruct.levels.problem import BAND_WEIGHTS, band_nodes  # noqa: PLC0415

    nodes = band_nodes(torch.tensor([f.centre_nm for f in filters], dtype=torch.float64),
                       torch.tensor([f.fwhm_nm for f in filters], dtype=torch.float64))  # (F, 3)
    return weighted_jacobian(skins, nodes, torch.tensor(BAND_WEIGHTS, dtype=torch.float64).expand_as(nodes), view_angle_deg)


def weighted_jacobian(skins: torch.Tensor, nodes_nm: torch.Tensor, weights: torch.Tensor,
                      view_angle_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's reflectance ``(M, F)`` of each skin ``(M, 5)`` through each of F responses, each a
    weighted sum over its wavelengths (``nodes_nm``, ``weights`` ``(F, K)``, weights summing to 1), times
    the camera's exit factor; and its derivative ``(M, F, 5)`` in the bound's parameters."""
    from ..model import SkinModel  # noqa: PLC0415
    from ..model.optics.params import SkinParams  # noqa: PLC0415
    from ..model.optics.radiometry import exit_factor  # noqa: PLC0415
    from ..model.settings import ModelSettings  # noqa: PLC0415

    model = SkinModel(ModelSettings())
    o = model.settings.optics
    exit = exit_factor(o.n_epidermis, o.n_above, math.cos(math.radians(view_angle_deg)))
    u = _to_u(skins).requires_grad_(True)
    distinct, where = torch.unique(nodes_nm, return_inverse=True)  # the RGB channels share their wavelengths
    reflectance = model.diffuse_reflectance(SkinParams.from_tensor(_from_u(u)), distinct)[:, where]  # (M, F, K)
    band = exit * (reflectance * weights).sum(-1)  # (M, F)
    jac = torch.stack([torch.autograd.grad(band[:, j].sum(), u, retain_graph=True)[0] for j in range(nodes_nm.shape[0])], dim=1)
    return band.detach(), jac


def _to_u(p: torch.Tensor) -> torch.Tensor:
    u = p.clone().log()
    u[:, 1] = p[:, 1]
    return u


def _from_u(u: torch.Tensor) -> torch.Tensor:
    p = u.exp()
    return torch.cat([p[:, :1], u[:, 1:2], p[:, 2:]], dim=1)


@dataclass(frozen=True, eq=False)
class FilterTerms:
    """Each filter's share of a set's bound on each skin of the prior: the Fisher information ``(F, M, 5, 5)``
    (J Jᵀ / σ², σ the calibrated reflectance's noise, and the model's spread beside it), and for the
    model's systematic error, the fit's normal matrix J Jᵀ ``(F, M, 5, 5)`` and J b ``(F, M, 5)`` (b the
    error) — the fit weighs its bands alike (``reconstruct/levels/problem.py``), so its bias is
    (Σ J Jᵀ)⁻¹ Σ J b over the set's filters. None: the model's error left out."""

    information: torch.Tensor
    normal: torch.Tensor | None = None
    projected: torch.Tensor | None = None


def filter_terms(radiometry: Radiometry, skins: torch.Tensor, filters: Sequence[Filter], model_error=None) -> FilterTerms:
    """``FilterTerms`` of ``filters`` on ``skins``; ``model_error`` (a ``band_discrepancy.Discrepancy`` that
    measured every filter, or None) adds the model's error: its spread, relative to the skin's band
    reflectance, as noise in quadrature; its mean as the bias of every pixel."""
    band, jac = band_jacobian(skins, filters, radiometry.rig.camera.angle_deg)
    sd = torch.stack([radiometry.reflectance_sd(f, band[:, j]) for j, f in enumerate(filters)], dim=1)  # (M, F)
    if model_error is None:
        return FilterTerms(_outer(jac / sd[..., None]))
    bias_rel, spread_rel = model_error.at(filters)
    sd = torch.sqrt(sd**2 + (spread_rel * band) ** 2)
    return FilterTerms(_outer(jac / sd[..., None]), _outer(jac), torch.einsum("mfi,mf->fmi", jac, bias_rel * band))


def rgb_terms(radiometry: Radiometry, skins: torch.Tensor, model_error: bool) -> FilterTerms:
    """``FilterTerms`` of an RGB camera's three channels under the flash (``Radiometry.rgb``), as three
    filters: the camera's noise alone (the model's error through so broad a response is not measured; with
    ``model_error`` its bias is taken as nil, so the normal matrix is there to concatenate)."""
    nodes, weights = radiometry.rgb()
    band, jac = weighted_jacobian(skins, nodes.expand(len(weights), -1), weights, radiometry.rig.camera.angle_deg)
    information = _outer(jac / radiometry.rgb_sd(band)[..., None])
    if not model_error:
        return FilterTerms(information)
    return FilterTerms(information, _outer(jac), torch.zeros(len(weights), *jac.shape[::2], dtype=jac.dtype))


def joined_terms(a: FilterTerms, b: FilterTerms) -> FilterTerms:
    """The filters of ``a`` then those of ``b``."""
    if (a.normal is None) != (b.normal is None):
        raise ValueError("both sets of filters need the model's error, or neither")
    join = lambda x, y: None if x is None else torch.cat([x, y])  # noqa: E731
    return FilterTerms(join(a.information, b.information), join(a.normal, b.normal), join(a.projected, b.projected))


def filter_information(radiometry: Radiometry, skins: torch.Tensor, filters: Sequence[Filter]) -> torch.Tensor:
    """Each filter's Fisher information on each skin from the camera's noise alone, ``(F, M, 5, 5)``."""
    return filter_terms(radiometry, skins, filters).information


def _outer(weighted: torch.Tensor) -> torch.Tensor:
    """``(M, F, 5)`` → per filter and skin the outer product ``(F, M, 5, 5)``."""
    return torch.einsum("mfi,mfj->fmij", weighted, weighted)


def shared_pixels(rig=None, cells_mm: dict[str, float] | None = None) -> torch.Tensor:
    """Pixels of the rig's cube that share one value of each parameter ``(5,)`` in the fit's layout
    (``DEFAULT_MAP_CELL_MM``: a node's cell², the whole window at most; 1 per pixel)."""
    from ..acquire.hardware.rig import load_rig  # noqa: PLC0415
    from ..reconstruct.settings import DEFAULT_MAP_CELL_MM  # noqa: PLC0415

    g = (rig or load_rig()).geometry
    px_mm = g.window_mm / g.cube_px
    cells = cells_mm or DEFAULT_MAP_CELL_MM
    return torch.tensor([max(1.0, (min(cells[n], g.window_mm) / px_mm) ** 2) for n in PARAMETERS], dtype=torch.float64)


def bound_variance(fisher: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
    """The Cramér–Rao variances ``(..., 5)`` of a pixel's parameters from one pixel's Fisher information
    ``(..., 5, 5)``, each parameter estimated from ``shared`` pixels of the same skin, the cells nested
    (each larger cell made of whole smaller ones, as the fit's grids are).

    Exact for that skin: from the smallest cells up, a level's information is gathered over its cell
    (× its count over the level below's) and its parameters eliminated (the Schur complement on those
    above); from the largest down, the covariance of a level's parameters and those above follows by the
    block inverse, A⁻¹ + A⁻¹B C BᵀA⁻¹ beside −A⁻¹B C (C the covariance above) — exact for the
    block-arrow matrix of many cells beside the parameters they share."""
    information = fisher + 1e-12 * torch.eye(fisher.shape[-1], dtype=fisher.dtype)
    current, below, steps = list(range(fisher.shape[-1])), 1.0, []
    for count in sorted(set(shared.tolist())):  # up: gather over the cell, eliminate the level
        information = information * (count / below)
        below = count
        here = torch.tensor([k for k, i in enumerate(current) if float(shared[i]) == count])
        above = torch.tensor([k for k, i in enumerate(current) if float(shared[i]) != count], dtype=torch.long)
        inv_a = torch.linalg.inv(information[..., here[:, None], here])
        b = information[..., here[:, None], above]
        steps.append(([current[k] for k in here], [current[k] for k in above], inv_a, b))
        information = information[..., above[:, None], above] - b.transpose(-1, -2) @ inv_a @ b
        current = [current[k] for k in above]
    cov, order = None, []
    for level, rest, inv_a, b in reversed(steps):  # down: the covariance of this level and those above
        if rest:
            upper = cov[..., [order.index(i) for i in rest], :][..., [order.index(i) for i in rest]]
            gain = inv_a @ b
            off = -gain @ upper
            cov = torch.cat([torch.cat([inv_a - off @ gain.transpose(-1, -2), off], -1),
                             torch.cat([off.transpose(-1, -2), upper], -1)], -2)
        else:
            cov = inv_a
        order = level + rest
    out = torch.empty(fisher.shape[:-1], dtype=fisher.dtype)
    out[..., order] = cov.diagonal(dim1=-2, dim2=-1)
    return out


class Criterion:
    """A set of filters' score, lower is better. Each scored map's (``MAP_TARGETS``: C_m, β_m, C_he, C_hd;
    C_bc has none) expected error is the mean over the prior of log(1 + variance/target²), the variance
    the bound's (``bound_variance``) plus the model's bias squared where ``information`` holds it
    (``FilterTerms``): the variance over the target squared where it is small, and a skin on which a map
    cannot be determined (C_m of the palest Table 2 row, 0.013%) counts as one bad skin, not as the whole
    prior."""

    def __init__(self, information: torch.Tensor | FilterTerms, shared: torch.Tensor, kind: str = "rig",
                 reference: Sequence[int] | None = None, candidates: int | None = None):
        from ..reconstruct.diagnosis.checks import MAP_TARGETS  # noqa: PLC0415

        if kind not in CRITERIA or (kind == "rig" and reference is None):
            raise ValueError(f"criterion {kind!r}: one of {CRITERIA}; 'rig' needs the reference set")
        self.terms = information if isinstance(information, FilterTerms) else FilterTerms(information)
        self.information, self.shared, self.kind = self.terms.information, shared, kind
        #: the filters a search may choose: the first ``candidates`` (the catalogue; comparison sets after it)
        self.candidates = candidates or self.information.shape[0]
        self.maps = [PARAMETERS.index(n) for n in MAP_TARGETS]
        self.targets = torch.tensor(list(MAP_TARGETS.values()), dtype=self.information.dtype)
        self.reference = self.expected(reference)[0] if reference is not None else None

    def variance(self, chosen) -> torch.Tensor:
        """The expected squared error ``(B, M, 5)`` of each parameter on each skin for sets ``(n,)`` or ``(B, n)``."""
        index = torch.as_tensor(chosen, dtype=torch.long)
        batch = index.reshape(-1, index.shape[-1])
        variance = bound_variance(self.information[batch].sum(dim=1), self.shared).clamp_min(0)  # (B, M, 5)
        if self.terms.normal is not None:
            normal = self.terms.normal[batch].sum(dim=1) + 1e-12 * torch.eye(len(PARAMETERS), dtype=variance.dtype)
            bias = torch.linalg.solve(normal, self.terms.projected[batch].sum(dim=1)[..., None])[..., 0]
            variance = variance + bias**2
        return variance

    def expected(self, chosen) -> torch.Tensor:
        """Each scored map's expected error ``(B, maps)`` of sets ``(n,)`` or ``(B, n)``."""
        return torch.log1p(self.variance(chosen)[..., self.maps] / self.targets**2).mean(dim=1)

    def __call__(self, chosen) -> torch.Tensor:
        """The scores ``(B,)`` (a scalar for one set)."""
        expected = self.expected(chosen)
        score = (expected / self.reference).max(-1).values if self.kind == "rig" else expected.sum(-1)
        score = torch.nan_to_num(score, nan=math.inf)  # a set whose bound cannot be computed is never chosen
        return score.reshape(torch.as_tensor(chosen).shape[:-1])

    def median_sd(self, chosen: Sequence[int]) -> dict[str, float]:
        """The expected error's median σ per parameter over the prior (relative for the chromophores: σ of log C)."""
        variance = self.variance(list(chosen))[0]
        return {n: float(variance[:, i].sqrt().median()) for i, n in enumerate(PARAMETERS)}
