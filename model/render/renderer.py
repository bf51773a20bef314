"""The heterogeneous, layered, spectral skin renderer (DWRR08 §4.1–4.3, Eq. 5–9; light in and out:
§5.1, §6.2 and docs/model.md, "Radiometric convention").

Per band, with per-pixel Gaussian weights w_k^P(x) = w_k^P(σa(x)) looked up from the σa tables and
the gather operator 𝒢_P[f](x) = Σ_k w_k^P(x) (f ∗ G_k)(x) (profile of the exit point), Eq. 7 reads

    M = 𝒢_{R1+}[Φ] + Σ_{n≥0} 𝒢_{T1−}[V_n],   U_0 = A·𝒢_{T1+}[Φ],
    V_n = A·𝒢_{R2+}[U_n],   U_{n+1} = A·𝒢_{R1−}[V_n],

with A = exp(-P) the thin interface layer (17.5% of the epidermal melanin plus any user absorbance).
With ``profiles: transport`` the T₁⁺ table holds the epidermis's scattered transmittance only and
U_0 = A·(𝒢_{T1+}[Φ] + q T_c Φ): the unscattered beam T_c = exp(-(σa + σs′) d) goes straight down, and
q = R_c / R_d turns the dermis's Lambertian response into its collimated one (model/column/layer_totals.py);
with ``handover: angular`` each V_n also carries the hand-over factor κ of its exit pixel (V_n =
A·κ·𝒢_{R2+}[U_n]), which makes the scalar series give the layers' total as adding-doubling stacks
them angle by angle.
Φ is the irradiance that entered (F_t(θ_i) E); the series stops when the light left in it falls below
``series_tolerance``. All bands and batch items are blurred together; each gather's backward pass
recomputes its blur stack instead of storing it (``gather.py``).

Shapes: maps ``(B, H, W)``, output ``(B, L, H, W)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ...formats.resources import require_memory
from .blur import BlurPlan, blur_stack
from .gather import ColumnLookups, columns, gather, lookup, total
from .illumination import Light
from ..column.layer_totals import collimated_transmission, handover_on_grid
from ..column.layered import SkinModel
from ..patch.maps import SkinMaps
from ..optics.radiometry import entry_transmittance, exit_factor
from ..settings import ModelSettings
from ..optics.specular import torrance_sparrow_factor
from ..column.tables import EPIDERMIS_PROFILES

__all__ = ["RenderResult", "SkinRenderer", "render_bytes"]

#: Peak memory of a forward render per pixel of the padded grid and band, in float32: the blur stacks
#: and per-pixel lookups (``_FORWARD_BYTES``); on top, the dense Gaussian weights of each profile kept
#: across terms (``_CACHE_BYTES_PER_PROFILE`` each, ``_CACHED_PROFILES`` of them, whole profiles only, as
#: many as ``weight_cache_mb`` holds: ``SkinRenderer._cached_lookups``); a backward pass needs a multiple
#: of the forward's (``_BACKWARD_FACTOR``). The forward's bytes depend on how large one pass's images
#: are: glibc serves a block of ``_MAPPED_FROM_BYTES`` or more (the ceiling of its dynamic mmap
#: threshold) from fresh pages it returns on free, smaller ones from a heap that freed blocks of other
#: sizes leave full of holes. Measured against the render command's peak across sizes, band groups and
#: tiles: tests/bench/test_bench_render_memory.py, docs/renderer.md "Speed and memory".
_FORWARD_BYTES = {"heap": 130.0, "mapped": 80.0}
_MAPPED_FROM_BYTES = 32 * 2**20
_CACHE_BYTES_PER_PROFILE, _CACHED_PROFILES, _BACKWARD_FACTOR = 70.0, 3, 2.0
#: Pixels per pass of ``series_terms_for`` (its float64 intermediates: about 100 MB at 8 bands).
SERIES_TERMS_CHUNK_PX = 1 << 16


def render_bytes(batch: int, bands: int, height: int, width: int, border_px: int, *, itemsize: int = 4,
                 weight_cache_mb: float = 0.0, backward: bool = False) -> float:
    """Estimated peak memory (bytes) of rendering ``batch`` × ``bands`` images of ``height`` × ``width``
    pixels with ``border_px`` of occluded skin on every side."""
    cells = batch * bands * (height + 2 * border_px) * (width + 2 * border_px) * itemsize / 4.0
    forward = _FORWARD_BYTES["mapped" if 4.0 * cells >= _MAPPED_FROM_BYTES else "heap"]
    profile = _CACHE_BYTES_PER_PROFILE * cells
    cached = min(_CACHED_PROFILES, math.floor(weight_cache_mb * 2**20 / profile)) if profile > 0 else 0
    need = forward * cells + cached * profile
    return need * (_BACKWARD_FACTOR if backward else 1.0)


@dataclass
class RenderResult:
    """``exitance``: M / E per band (the diffuse reflectance map under uniform light), ``(B, L, H, W)``;
    ``image``: the reflectance factor a camera at the view angle sees (plus the surface term when
    not under gel); ``terms``: inter-scattering terms used per band."""

    exitance: torch.Tensor
    image: torch.Tensor
    wavelength_nm: torch.Tensor
    terms: list[int]
    mm_per_pixel: float


@dataclass
class _Layers:
    """The layers on the padded grid: spectra, σa of epidermis and dermis ``(B, L, Hp, Wp)`` (1/mm) and
    the interface's attenuation A ``(B·L, Hp, Wp)``."""

    spectra: object
    sa_epi: torch.Tensor
    sa_derm: torch.Tensor
    attenuation: torch.Tensor


@dataclass
class _Gathers:
    """What every gather of one render shares: the blur plan, each profile's columns and lookups, the
    dermis's hand-back factor ``(B·L, Hp, Wp)`` and the number of inter-scattering terms."""

    plan: BlurPlan
    cols: dict
    at: dict
    epi: object
    derm: object
    back: torch.Tensor
    terms: int


@dataclass
class _View:
    """Where the light comes from and the camera looks (degrees), gel or none, crop or not."""

    under_gel: bool
    light_angle_deg: float
    view_angle_deg: float
    azimuth_deg: float
    crop: bool


class SkinRenderer:
    """Renders ``SkinMaps`` under a ``Light`` at any set of wavelengths, differentiably."""

    def __init__(self, settings: ModelSettings | None = None, cache_dir: str | None = None) -> None:
        self.settings = settings or ModelSettings()
        self.model = SkinModel(self.settings, cache_dir)

    def render(
        self,
        maps: SkinMaps,
        light: Light,
        wavelength_nm: torch.Tensor,
        *,
        under_gel: bool = True,
        light_angle_deg: float = 0.0,
        view_angle_deg: float = 0.0,
        azimuth_deg: float = 180.0,
        blur: str | None = None,
        series_terms: int | None = None,
        crop: bool = True,
    ) -> RenderResult:
        """Render every band of ``wavelength_nm`` ``(L,)``; ``blur`` and ``series_terms`` override the settings."""
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        border = light.border_px(maps.mm_per_pixel, self.settings.render.border_mm)
        self._require_memory(maps, wl, border)
        layers = self._layers(maps, wl, border)
        gathers = self._gathers(maps, light, layers, wl, blur, series_terms)
        irradiance = light.irradiance(*maps.shape[-2:], border, maps.mm_per_pixel, maps.dtype, maps.device)
        exitance = self._series(layers, gathers, irradiance, light_angle_deg)
        view = _View(under_gel, light_angle_deg, view_angle_deg, azimuth_deg, crop)
        return self._picture(maps, exitance, irradiance, wl, border, gathers.terms, view)

    # -- the steps of a render -------------------------------------------------------------------
    def _require_memory(self, maps: SkinMaps, wl: torch.Tensor, border: int) -> None:
        """Refuse a render whose estimated peak exceeds the memory available, before allocating."""
        rs = self.settings.render
        b, h, w = maps.shape
        backward = torch.is_grad_enabled() and any(v.requires_grad for v in maps.params().values())
        require_memory(
            render_bytes(b, wl.numel(), h, w, border, itemsize=maps.dtype.itemsize,
                         weight_cache_mb=rs.weight_cache_mb, backward=backward),
            f"rendering {b}×{wl.numel()} band(s) of {h + 2 * border}×{w + 2 * border} px ({border} px of border)",
            "Render fewer bands at once, a coarser grid, or less border (render.border_mm).", maps.device,
        )

    def _layers(self, maps: SkinMaps, wl: torch.Tensor, border: int) -> _Layers:
        """The layers' absorption on the padded grid and the interface's attenuation A = exp(-P);
        border parameters follow the nearest pixel."""
        params = maps.params()
        padded = type(params)(*(_replicate(v, border) for v in params.values()))
        spectra = self.model.spectra(wl)
        ab = self.model.absorption(padded, spectra)  # (B, Hp, Wp, L)
        sa_epi = ab.epidermis.permute(0, 3, 1, 2)
        sa_derm = ab.dermis.permute(0, 3, 1, 2)
        absorbance = ab.interface_absorbance.permute(0, 3, 1, 2)
        if maps.absorbance is not None:
            absorbance = absorbance + _pad_bands(_resample_bands(maps.absorbance, maps.absorbance_wavelength_nm, wl), border)
        attenuation = torch.exp(-absorbance).reshape(maps.shape[0] * wl.numel(), *sa_epi.shape[-2:])
        return _Layers(spectra, sa_epi, sa_derm, attenuation)

    def _gathers(self, maps: SkinMaps, light: Light, layers: _Layers, wl: torch.Tensor, blur: str | None,
                 series_terms: int | None) -> _Gathers:
        """The blur plan, each profile's columns and per-pixel lookups, the dermis's hand-back and the
        number of inter-scattering terms."""
        rs = self.settings.render
        tables = self.model.tables(wl).to(maps.device, maps.dtype)
        plan = BlurPlan.build(
            tables.variances_mm2, maps.mm_per_pixel, blur or rs.blur,
            boundary="replicate" if light.extends else "zero",
            identity_below_px=rs.identity_below_px, pyramid_min_px=rs.pyramid_min_px,
        )
        epi = lookup(tables.sigma_a_per_mm, layers.sa_epi)
        derm = lookup(tables.sigma_a_per_mm, layers.sa_derm)
        cols = {p: columns(tables, "epidermis", p, plan) for p in EPIDERMIS_PROFILES}
        cols["R2_plus"] = columns(tables, "dermis", "R_plus", plan)
        # the dermis's answer, per exit pixel: through the interface, times the hand-over factor κ
        # (transport; κ at the entry pixel or split between both draws features much like this:
        # docs/renderer.md, "From model/render/renderer.py")
        attenuation = layers.attenuation
        back = attenuation * handover_on_grid(self.model.handover_grid(wl, maps.device), epi.index, epi.frac,
                                              derm.index, derm.frac) if self._angular else attenuation
        terms = series_terms or self._series_terms(cols, epi, derm, attenuation * back, maps.shape[0], wl.numel())
        if rs.coupling == "segment":
            at = self._cached_lookups(
                cols, _column_lookups(tables.sigma_a_per_mm, layers.sa_epi, plan, rs, rs.coupling_scale_epidermis),
                _column_lookups(tables.sigma_a_per_mm, layers.sa_derm, plan, rs, rs.coupling_scale), terms)
        else:
            at = self._cached_lookups(cols, epi, derm, terms)
        return _Gathers(plan, cols, at, epi, derm, back, terms)

    def _series(self, layers: _Layers, gathers: _Gathers, irradiance: torch.Tensor,
                light_angle_deg: float) -> torch.Tensor:
        """Eq. 7's series: the exitance M ``(B·L, Hp, Wp)`` per unit of the reference irradiance."""
        rs, o = self.settings.render, self.settings.optics
        cols, at, attenuation, back = gathers.cols, gathers.at, layers.attenuation, gathers.back
        b, n_bands = layers.sa_epi.shape[:2]
        f_t = entry_transmittance(o.n_epidermis, o.n_above, math.cos(math.radians(light_angle_deg)))
        phi = (f_t * irradiance).expand(b, n_bands, *irradiance.shape[-2:]).reshape(b * n_bands, *irradiance.shape[-2:])

        def g(f, sets):
            return gather(f, sets, gathers.plan, lean=rs.checkpoint)

        m, t1 = g(phi, [(cols["R_plus"], at["R_plus"]), (cols["T_plus"], at["T_plus"])])
        if self.settings.profiles == "transport":
            t1 = t1 + self._unscattered_beam(layers).reshape(t1.shape) * phi
        u = attenuation * t1
        for n in range(gathers.terms):
            (r2,) = g(u, [(cols["R2_plus"], at["R2_plus"])])
            v = back * r2
            if n + 1 < gathers.terms:
                t_out, r1 = g(v, [(cols["T_minus"], at["T_minus"]), (cols["R_minus"], at["R_minus"])])
                u = attenuation * r1
            else:
                if rs.series_closure:
                    # the rest of the series, Σ_{k≥1} V_{n+k} ≈ V_n ρ/(1-ρ) with ρ = A² κ R₁⁻ R₂⁺ per pixel:
                    # exact for homogeneous skin under uniform light, and the rest holds little light
                    rho = attenuation * back * total(cols["R_minus"], gathers.epi) * total(cols["R2_plus"], gathers.derm)
                    v = v / (1.0 - rho)
                (t_out,) = g(v, [(cols["T_minus"], at["T_minus"])])
            m = m + t_out
        return m

    def _unscattered_beam(self, layers: _Layers) -> torch.Tensor:
        """q T_c per pixel ``(B, L, Hp, Wp)``: the beam that crossed the epidermis unscattered reaches
        the dermis below its entry point (``profiles: transport``)."""
        o = self.settings.optics
        s_epi = layers.spectra.scattering_epidermis.to(layers.sa_epi).view(1, -1, 1, 1)
        s_derm = layers.spectra.scattering_dermis.to(layers.sa_derm).view(1, -1, 1, 1)
        beam = collimated_transmission(layers.sa_epi, s_epi, o.epidermis_thickness_mm, layers.sa_derm, s_derm)
        return beam.collimated_ratio * beam.T1_collimated

    def _picture(self, maps: SkinMaps, m: torch.Tensor, irradiance: torch.Tensor, wl: torch.Tensor, border: int,
                 terms: int, view: _View) -> RenderResult:
        """Cropped exitance, the camera's reflectance factor, and the surface term when not under gel."""
        o, rs = self.settings.optics, self.settings.render
        b, h, w = maps.shape
        exitance = m.reshape(b, wl.numel(), *m.shape[-2:])
        cropped = view.crop and border
        if cropped:
            exitance = exitance[..., border:border + h, border:border + w]
        # per unit of the reference irradiance E (light of strength 1)
        image = exitance * exit_factor(o.n_epidermis, o.n_above, math.cos(math.radians(view.view_angle_deg)))
        if not view.under_gel and maps.rho_s is not None:
            spec = torrance_sparrow_factor(
                math.cos(math.radians(view.light_angle_deg)), math.cos(math.radians(view.view_angle_deg)),
                view.azimuth_deg, o.n_epidermis / o.n_above, rs.surface_roughness,
            )
            lit = irradiance if not cropped else irradiance[..., border:border + h, border:border + w]
            rho = maps.rho_s if (view.crop or not border) else _replicate(maps.rho_s, border)
            image = image + (spec * rho * lit)[:, None]
        return RenderResult(exitance, image, wl, [terms] * wl.numel(), maps.mm_per_pixel)

    def series_terms_for(self, maps: SkinMaps, wavelength_nm: torch.Tensor) -> int:
        """The inter-scattering terms ``render`` takes for these maps and bands (worst pixel of all):
        pass it as ``series_terms`` to render bands in groups exactly as at once. Pixels are taken
        ``SERIES_TERMS_CHUNK_PX`` at a time: all of a large frame at once would take the column totals'
        float64 intermediates of every pixel and band together, more than the render of a band group."""
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        worst = 1e-12
        with torch.no_grad():
            params = maps.params()
            flat = [v.detach().reshape(-1) for v in params.values()]
            extra = None
            if maps.absorbance is not None:
                extra = _resample_bands(maps.absorbance.detach(), maps.absorbance_wavelength_nm, wl)
                extra = extra.permute(0, 2, 3, 1).reshape(-1, wl.numel())
            for start in range(0, flat[0].numel(), SERIES_TERMS_CHUNK_PX):
                part = slice(start, start + SERIES_TERMS_CHUNK_PX)
                chunk = type(params)(*(v[part].double() for v in flat))
                t = self.model.layer_transforms(chunk, wl, None, "tables", None if extra is None else extra[part].double())
                worst = max(worst, float((t.attenuation**2 * t.R1_minus * t.R2_plus).max()))
        return self._terms_for(min(worst, 0.999))

    # -- pieces ----------------------------------------------------------------------------------
    @property
    def _angular(self) -> bool:
        return self.settings.profiles == "transport" and self.settings.handover == "angular"

    def _cached_lookups(self, cols, epi, derm, terms: int) -> dict:
        """Per profile, its lookup — with the dense weights computed once when the profile is gathered
        more than once and they fit in ``weight_cache_mb`` (most-used profiles first)."""
        at = {"R_plus": epi, "T_plus": epi, "T_minus": epi, "R_minus": epi, "R2_plus": derm}
        budget = self.settings.render.weight_cache_mb * 2**20
        uses = {"R2_plus": terms, "T_minus": terms, "R_minus": terms - 1}
        # per-column lookups cost a lerp of the total per column and pixel, and their backward twice
        # that: worth caching for a profile gathered once, too
        once = 0 if isinstance(epi, ColumnLookups) else 1
        if once == 0:
            uses.update(R_plus=1, T_plus=1)
        for name in sorted(uses, key=lambda k: -uses[k]):
            need = at[name].cache_bytes(cols[name])
            if uses[name] > once and need <= budget:
                at[name] = at[name].cached(cols[name])
                budget -= need
        return at

    def _series_terms(self, cols, epi, derm, round_trip, batch, bands) -> int:
        """Terms until the geometric tail (A² κ R₁⁻ R₂⁺ per bounce, worst pixel; ``round_trip`` = A² κ)
        holds < tolerance."""
        with torch.no_grad():
            r1m = total(cols["R_minus"], epi)
            r2p = total(cols["R2_plus"], derm)
            ratio = float((round_trip * r1m * r2p).max().clamp(1e-12, 0.999))
        return self._terms_for(ratio)

    def _terms_for(self, ratio: float) -> int:
        rs = self.settings.render
        n = math.ceil(math.log(rs.series_tolerance * (1.0 - ratio)) / math.log(ratio))
        return int(min(max(n, 1), rs.max_series_terms))


#: Points of the segment's parameter t at which its spread is sampled (the weights of the mixture).
_SEGMENT_SAMPLES = 2000
#: Mixture weights below this go to the pixel itself: the narrow bins near the exit hold a geometric
#: tail (halving per Gaussian), and each bin kept is an image-sized sum per column.
SEGMENT_MIN_WEIGHT = 0.02


def segment_mixture(variances_px2: list[float], scale: float, bridge: float) -> list[list[float]]:
    """For each column j (variance v_j of the plan's blurred Gaussians), the weights over
    [identity, G(v_1), …, G(v_{J-1})] of ∫₀¹ G((t² + β t(1 − t)) c v_j) dt: where light that left at Δ ~ G(v_j)
    from its entry was on its way — at tΔ from the exit along the straight segment, plus the wander of a
    Brownian bridge pinned at both ends (β; c = ``scale``). Each sampled variance goes to the nearest
    Gaussian in log variance; below half the narrowest, to the pixel itself."""
    v = np.asarray(variances_px2, dtype=np.float64)
    log_edges = np.log(np.concatenate([[v[0] / math.sqrt(2.0)], np.sqrt(v[:-1] * v[1:])]))
    t = (np.arange(_SEGMENT_SAMPLES) + 0.5) / _SEGMENT_SAMPLES
    out = []
    for vj in v:
        var = np.maximum((t * t + bridge * t * (1.0 - t)) * scale * vj, 1e-300)
        bins = np.searchsorted(log_edges, np.log(var))  # 0: identity, k: G(v_k)
        weights = np.bincount(bins, minlength=v.size + 1) / t.size
        small = weights < SEGMENT_MIN_WEIGHT
        small[0] = False
        weights[0] += weights[small].sum()
        weights[small] = 0.0
        out.append(weights.tolist())
    return out


def _column_lookups(grid: torch.Tensor, sigma_a: torch.Tensor, plan: BlurPlan, rs, scale: float) -> ColumnLookups:
    """Per column of ``plan``, the table position of the σa its light meets on its way: σa
    (the power mean of exponent ``coupling_power``; 0: the geometric mean) averaged over where that light went (``segment_mixture``).
    One blur stack of σa at the plan's own variances, mixed per column: cheap."""
    n, (h, w) = sigma_a.shape[0] * sigma_a.shape[1], sigma_a.shape[-2:]
    flat = sigma_a.reshape(n, h, w)
    p = rs.coupling_power
    value = torch.log(flat.clamp_min(1e-12)) if p == 0 else flat.clamp_min(1e-12) ** p
    v = plan.blurred
    smoothing = BlurPlan(tuple(v), (False,) * len(v), plan.strategy, "replicate", plan.pyramid_min_px)
    stack = [value] + list(blur_stack(value, smoothing))
    looks = [lookup(grid, sigma_a)]
    for weights in segment_mixture(v, scale, rs.coupling_bridge):
        mixed = sum(wt * stack[k] for k, wt in enumerate(weights) if wt > 0)
        looks.append(lookup(grid, (torch.exp(mixed) if p == 0 else mixed ** (1.0 / p)).reshape(sigma_a.shape)))
    return ColumnLookups(torch.stack([lk.index for lk in looks]), torch.stack([lk.frac for lk in looks]))


def _replicate(x: torch.Tensor, border: int) -> torch.Tensor:
    if border == 0:
        return x
    return F.pad(x[:, None], (border, border, border, border), mode="replicate")[:, 0]


def _pad_bands(x: torch.Tensor, border: int) -> torch.Tensor:
    if border == 0:
        return x
    return F.pad(x, (border, border, border, border), mode="replicate")


def _resample_bands(values: torch.Tensor, source_nm: torch.Tensor, target_nm: torch.Tensor) -> torch.Tensor:
    """Linear interpolation along the band axis ``(B, L_src, H, W)`` → ``(B, L, H, W)``, ends held."""
    src = source_nm.to(torch.float64).cpu()
    out = []
    for w in target_nm.tolist():
        j = int(torch.searchsorted(src, torch.tensor(w, dtype=torch.float64)))
        if j <= 0:
            out.append(values[:, 0])
        elif j >= src.numel():
            out.append(values[:, -1])
        else:
            t = (w - float(src[j - 1])) / float(src[j] - src[j - 1])
            out.append(values[:, j - 1] * (1 - t) + values[:, j] * t)
    return torch.stack(out, dim=1)
