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
from .layered import SkinModel
from .maps import SkinMaps
from .radiometry import entry_transmittance, exit_factor
from .gather import columns, gather, lookup
from .renderer import RenderResult, SkinRenderer, _replicate
from .tables import load_thin_dermis_tables

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
    settings, rs, o = renderer.settings, renderer.settings.render, renderer.settings.optics
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    b, h, w = front.shape
    dtype, device = front.dtype, front.device
    border = light.border_px(front.mm_per_pixel, rs.border_mm)
    model = renderer.model
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
    flat = lambda x: x.reshape(b * wl.numel(), *x.shape[-2:])  # noqa: E731
    att_b, att_f = flat(torch.exp(-p_b)), flat(torch.exp(-p_f))
    tables = model.tables(wl).to(device, dtype)
    thin = load_thin_dermis_tables(wl, dermis_mm, settings, model.cache_dir).to(device, dtype)
    plan = BlurPlan.build(tables.variances_mm2, front.mm_per_pixel, blur or rs.blur,
                          boundary="replicate" if light.extends else "zero",
                          identity_below_px=rs.identity_below_px, pyramid_min_px=rs.pyramid_min_px)
    lk_b, lk_f = lookup(tables.sigma_a_per_mm, epi_b), lookup(tables.sigma_a_per_mm, epi_f)
    lk_d = lookup(thin.sigma_a_per_mm, derm_f)
    col = lambda t, layer, p: columns(t, layer, p, plan)  # noqa: E731
    t1p, r1m = col(tables, "epidermis", "T_plus"), col(tables, "epidermis", "R_minus")
    r3p, t3p = col(tables, "epidermis", "R_minus"), col(tables, "epidermis", "T_minus")
    r2p, t2p, r2m = col(thin, "thin_dermis", "R_plus"), col(thin, "thin_dermis", "T_plus"), col(thin, "thin_dermis", "R_minus")

    def g(f, sets):
        return gather(f, sets, plan, lean=rs.checkpoint)


    f_t = entry_transmittance(o.n_epidermis, o.n_above)
    irradiance = light.irradiance(h, w, border, front.mm_per_pixel, dtype, device)
    phi = (f_t * irradiance).expand(b, wl.numel(), *irradiance.shape[-2:]).reshape(-1, *irradiance.shape[-2:])

    (t1,) = g(phi, [(t1p, lk_b)])
    current = att_b * t1
    into_dermis = current
    for _ in range(round_trips):
        (r2,) = g(current, [(r2p, lk_d)])
        (r1,) = g(att_b * r2, [(r1m, lk_b)])
        current = att_b * r1
        into_dermis = into_dermis + current
    (t2,) = g(into_dermis, [(t2p, lk_d)])
    current = att_f * t2
    into_front = current
    for _ in range(round_trips):
        (r3,) = g(current, [(r3p, lk_f)])
        (r2b,) = g(att_f * r3, [(r2m, lk_d)])
        current = att_f * r2b
        into_front = into_front + current
    (m,) = g(into_front, [(t3p, lk_f)])
    exitance = m.reshape(b, wl.numel(), *m.shape[-2:])
    if border:
        exitance = exitance[..., border:border + h, border:border + w]
    image = exitance * exit_factor(o.n_epidermis, o.n_above, math.cos(math.radians(view_angle_deg)))
    return RenderResult(exitance, image, wl, [round_trips] * wl.numel(), front.mm_per_pixel)
