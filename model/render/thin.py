"""Thin geometry (DWRR08 §4.4, §7.1): light through epidermis – thin dermis – epidermis.

For parts thin enough to glow when lit from behind (ears, webs of the fingers) the paper builds a
three-layer material on the fly — the lit side's epidermis, a dermis as thick as the mean distance to
the lit points, the viewed side's epidermis — and keeps the transmission terms with at most two
inter-scattering round trips per pair of layers:

    T₁⁺ ∗ (R₂⁺ ∗ R₁⁻)^{0..2} ∗ T₂⁺ ∗ (R₃⁺ ∗ R₂⁻)^{0..2} ∗ T₃⁺,

each crossing of an epidermis–dermis interface attenuated by that interface's A = e^{-P}. Here for a
flat slab: the back maps are the lit side, the front maps the viewed side, aligned pixel for pixel;
the dermis takes the front maps' dermal blood. Reflected and transmitted light blend by Eq. 10,
L = ½(1 + n_s·n_l) R + ½(1 − n_s·n_l) T (``blend_thin``). The layers are the paper's diffusion
profiles whatever ``profiles`` says: the transport tables cover the two-layer skin only.
"""

from __future__ import annotations

import math

import torch

from .blur import BlurPlan
from .illumination import Light
from ..column.layered import SkinModel
from ..patch.maps import SkinMaps
from ..optics.radiometry import entry_transmittance, exit_factor
from .gather import columns, gather, lookup
from .renderer import RenderResult, SkinRenderer, _replicate
from ..column.tables import load_thin_dermis_tables

__all__ = ["blend_thin", "render_transmission"]


def blend_thin(reflected: torch.Tensor, transmitted: torch.Tensor, cos_normals: float | torch.Tensor) -> torch.Tensor:
    """Eq. 10: ½(1 + n_s·n_l) R + ½(1 − n_s·n_l) T; ``cos_normals`` = n_s·n_l (−1: lit from straight behind)."""
    c = torch.as_tensor(cos_normals, dtype=reflected.dtype, device=reflected.device)
    return 0.5 * (1 + c) * reflected + 0.5 * (1 - c) * transmitted


def render_transmission(
    renderer: SkinRenderer,
    front: SkinMaps,
    light: Light,
    wavelength_nm: torch.Tensor,
    dermis_mm: float,
    back: SkinMaps | None = None,
    *,
    round_trips: int = 2,
    view_angle_deg: float = 0.0,
    blur: str | None = None,
) -> RenderResult:
    """Light of ``light`` falling on the back of a flat slab, seen from the front, ``(B, L, H, W)``."""
    back = back or front
    if back.shape != front.shape or abs(back.mm_per_pixel - front.mm_per_pixel) > 1e-9:
        raise ValueError("front and back maps must have the same grid")
    rs, o = renderer.settings.render, renderer.settings.optics
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    b, h, w = front.shape
    border = light.border_px(front.mm_per_pixel, rs.border_mm)
    s = _Slab.build(renderer, front, back, light, wl, dermis_mm, border, blur)

    def g(f, sets):
        return gather(f, sets, s.plan, lean=rs.checkpoint)

    f_t = entry_transmittance(o.n_epidermis, o.n_above)
    irradiance = light.irradiance(h, w, border, front.mm_per_pixel, front.dtype, front.device)
    phi = (f_t * irradiance).expand(b, wl.numel(), *irradiance.shape[-2:]).reshape(-1, *irradiance.shape[-2:])
    c, lk_b, lk_f, lk_d = s.cols, s.lk_back, s.lk_front, s.lk_dermis
    (t1,) = g(phi, [(c["T1_plus"], lk_b)])
    into_dermis = _round_trips(g, s.att_back * t1, s.att_back, (c["R2_plus"], lk_d), (c["R1_minus"], lk_b), round_trips)
    (t2,) = g(into_dermis, [(c["T2_plus"], lk_d)])
    into_front = _round_trips(g, s.att_front * t2, s.att_front, (c["R3_plus"], lk_f), (c["R2_minus"], lk_d), round_trips)
    (m,) = g(into_front, [(c["T3_plus"], lk_f)])
    exitance = m.reshape(b, wl.numel(), *m.shape[-2:])
    if border:
        exitance = exitance[..., border:border + h, border:border + w]
    image = exitance * exit_factor(o.n_epidermis, o.n_above, math.cos(math.radians(view_angle_deg)))
    return RenderResult(exitance, image, wl, [round_trips] * wl.numel(), front.mm_per_pixel)


def _round_trips(g, current: torch.Tensor, attenuation: torch.Tensor, down, up, round_trips: int) -> torch.Tensor:
    """The light that enters a pair of layers plus what ``round_trips`` inter-reflections between them
    send back the same way: each trip reflected by the layer below (``down``: its column and lookup),
    through the interface, reflected by the layer above (``up``) and through the interface again."""
    total = current
    for _ in range(round_trips):
        (reflected,) = g(current, [down])
        (returned,) = g(attenuation * reflected, [up])
        current = attenuation * returned
        total = total + current
    return total


class _Slab:
    """What the slab's gathers share: the blur plan, the interfaces' attenuation on the back (lit) and
    front (viewed) side ``(B·L, Hp, Wp)``, the lookups of both epidermes and of the thin dermis, and the
    layers' profile columns (T1+ … T3+ in the order the light meets them)."""

    def __init__(self, plan, att_back, att_front, lk_back, lk_front, lk_dermis, cols) -> None:
        self.plan, self.att_back, self.att_front = plan, att_back, att_front
        self.lk_back, self.lk_front, self.lk_dermis, self.cols = lk_back, lk_front, lk_dermis, cols

    @classmethod
    def build(cls, renderer: SkinRenderer, front: SkinMaps, back: SkinMaps, light: Light, wl: torch.Tensor,
              dermis_mm: float, border: int, blur: str | None) -> _Slab:
        settings, rs, model = renderer.settings, renderer.settings.render, renderer.model
        if settings.profiles != "diffusion":
            # the transport tables hold the two-layer skin's layers (air above the epidermis, dermis below);
            # this geometry's layers (a dermis slab between epidermes) exist in diffusion only
            settings = settings.model_copy(update={"profiles": "diffusion"})
            model = SkinModel(settings, model.cache_dir)
        spectra = model.spectra(wl)

        def absorption(maps: SkinMaps):
            p = maps.params()
            padded = type(p)(*(_replicate(v, border) for v in p.values()))
            ab = model.absorption(padded, spectra)
            return [x.permute(0, 3, 1, 2) for x in (ab.epidermis, ab.dermis, ab.interface_absorbance)]

        epi_b, _, p_b = absorption(back)
        epi_f, derm_f, p_f = absorption(front)
        n = front.shape[0] * wl.numel()
        tables = model.tables(wl).to(front.device, front.dtype)
        thin = load_thin_dermis_tables(wl, dermis_mm, settings, model.cache_dir).to(front.device, front.dtype)
        plan = BlurPlan.build(tables.variances_mm2, front.mm_per_pixel, blur or rs.blur,
                              boundary="replicate" if light.extends else "zero",
                              identity_below_px=rs.identity_below_px, pyramid_min_px=rs.pyramid_min_px)
        names = {"T1_plus": (tables, "epidermis", "T_plus"), "R1_minus": (tables, "epidermis", "R_minus"),
                 "R3_plus": (tables, "epidermis", "R_minus"), "T3_plus": (tables, "epidermis", "T_minus"),
                 "R2_plus": (thin, "thin_dermis", "R_plus"), "T2_plus": (thin, "thin_dermis", "T_plus"),
                 "R2_minus": (thin, "thin_dermis", "R_minus")}
        cols = {k: columns(t, layer, prof, plan) for k, (t, layer, prof) in names.items()}
        return cls(plan, torch.exp(-p_b).reshape(n, *p_b.shape[-2:]), torch.exp(-p_f).reshape(n, *p_f.shape[-2:]),
                   lookup(tables.sigma_a_per_mm, epi_b), lookup(tables.sigma_a_per_mm, epi_f),
                   lookup(thin.sigma_a_per_mm, derm_f), cols)
