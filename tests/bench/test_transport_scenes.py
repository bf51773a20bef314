"""Benchmark: heterogeneous skin, the renderer's models against the Monte Carlo transport reference
(run on demand: ``pytest -m bench tests/bench/test_transport_scenes.py -s``).

Scenes on Table 2's III interior, 0.1-mm pixels, the full model (n 1.40 / 1.38, the interface absorber),
isotropic scattering with σs = σs′ for the Monte Carlo (the medium the model describes), at 470, 560
and 650 nm:

- ``stripe``: a 1-mm stripe of dermal blood (C_hd 0.08), uniform light: its depth 1 − min/background
  and its full width at half depth;
- ``vessel``: a thin vessel, 0.3 mm of dermal blood C_hd 0.2, the same measures;
- ``hair``: one pixel column of interface absorbance 2 (a hair under the surface), the same measures;
- ``step``: a melanin step (C_m ×6 for x > 0), uniform light: the 25–75% edge width;
- ``window``: a 5-mm window of light on a 9-mm patch: the fall-off outside its edge (exitance 0.25,
  0.5 and 1 mm outside over the centre's, rows within 1 mm of the centre line averaged);
- ``freckle``: a 1-mm disk of melanin ×4, uniform light: its contrast and the radius at half contrast.

Every scene also gives the per-pixel error against the Monte Carlo outside the feature's first 0.1 mm
(median and worst). The renderers (``RENDERERS``): DWRR08's (diffusion profiles, each chosen at the exit
pixel), transport profiles with that rule (the default), and transport profiles with the segment coupling.

The y-invariant scenes use the reference's profile mode (``TransportRenderer.profile``); window and
freckle are 2-D renders. The Monte Carlo of each scene is kept in the output folder
(``transport_scene_<scene>.pt``); with ``SKINLAYERS_SCENES_REUSE=1`` a kept one is used again, so the
renderers can be re-measured without the hours of photons. Writes ``transport_scenes.csv`` and
``transport_scenes.png`` (``bench_io``). ``SKINLAYERS_SCENE_PHOTONS`` sets the photons,
``SKINLAYERS_SCENES`` the scenes run.
"""

from __future__ import annotations

import math
import os
import time

import pytest
import torch

from bench_io import out_dir, write_csv

from skinlayers.model import TABLE2, ModelSettings, SkinParams
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.transport import TransportRenderer

pytestmark = pytest.mark.bench

WL = torch.tensor([470.0, 560.0, 650.0], dtype=torch.float64)
MM = 0.1
PHOTONS = int(os.environ.get("SKINLAYERS_SCENE_PHOTONS", 4_000_000))
ALL_SCENES = ("stripe", "vessel", "hair", "step", "window", "freckle")
SCENES = os.environ.get("SKINLAYERS_SCENES", ",".join(ALL_SCENES)).split(",")
REUSE = os.environ.get("SKINLAYERS_SCENES_REUSE", "0") == "1"
#: Lit skin beyond the profiles' maps: at 650 nm the dermis's diffusion length is about 2 mm, and with
#: 3 mm the profile's ends missed 1.5% of their light (a first run; docs/transport.md).
MARGIN_MM = 8.0
BASE = TABLE2["III interior"]
#: The renderers compared, by name: settings over the defaults.
RENDERERS = {
    "paper": {"profiles": "diffusion", "render": {"coupling": "exit"}},
    "transport profiles, exit rule": {"profiles": "transport", "render": {"coupling": "exit"}},
    "transport profiles, segment coupling": {"profiles": "transport", "render": {"coupling": "segment"}},
    "transport profiles, segment coupling, Lambertian hand-over": {
        "profiles": "transport", "handover": "lambertian", "render": {"coupling": "segment", "coupling_scale": 1.0}},
}
WIDTH_PX = 80


def _row(width_px: int, **maps: torch.Tensor) -> SkinMaps:
    base = SkinMaps.uniform(BASE, (1, width_px), MM, dtype=torch.float64)
    return base.replace(**{k: v.reshape(1, 1, width_px).double() for k, v in maps.items()})


def _x(width_px: int) -> torch.Tensor:
    return (torch.arange(width_px, dtype=torch.float64) - (width_px - 1) / 2.0) * MM


def _renderer_profile(settings: ModelSettings, row: SkinMaps, light: Light) -> torch.Tensor:
    """A renderer's profile ``(L, W)`` of a y-invariant scene: the row repeated over 16 rows, the centre one."""
    maps = SkinMaps(*(v.expand(1, 16, v.shape[-1]).contiguous() for v in row.params().values()), mm_per_pixel=MM,
                    absorbance=None if row.absorbance is None else row.absorbance.expand(1, -1, 16, -1).contiguous(),
                    absorbance_wavelength_nm=row.absorbance_wavelength_nm)
    return SkinRenderer(settings).render(maps, light, WL).exitance[0, :, 8].double()


def _crossing(profile: torch.Tensor, level: float, x: torch.Tensor, near: float) -> float:
    """Where ``profile`` crosses ``level`` (linear between pixels), the crossing nearest ``near`` (mm):
    Monte Carlo noise can cross the level far out too."""
    d = (profile - level).tolist()
    best = None
    for k in range(1, len(d)):
        if d[k - 1] == 0 or d[k - 1] * d[k] < 0:
            at = float(x[k - 1] + (x[k] - x[k - 1]) * d[k - 1] / (d[k - 1] - d[k]))
            if best is None or abs(at - near) < abs(best - near):
                best = at
    return math.nan if best is None else best


def _width_at(profile: torch.Tensor, level: float, x: torch.Tensor) -> float:
    """Width of the dip of ``profile`` below ``level`` around x = 0."""
    left = _crossing(profile[x <= 0], level, x[x <= 0], 0.0)
    right = _crossing(profile[x >= 0], level, x[x >= 0], 0.0)
    return right - left


def _edge_width(profile: torch.Tensor, x: torch.Tensor, plateau_light: float, plateau_dark: float) -> float:
    """Distance between the 25% and the 75% crossings of a falling step at x = 0."""
    level = lambda frac: plateau_light - frac * (plateau_light - plateau_dark)  # noqa: E731
    return _crossing(profile, level(0.75), x, 0.0) - _crossing(profile, level(0.25), x, 0.0)


def _pixel_errors(prof: torch.Tensor, mc: torch.Tensor, keep: torch.Tensor) -> dict:
    rel = (prof / mc - 1.0).abs()[keep]
    return {"pixel_error_median_pct": round(100 * float(rel.median()), 2), "pixel_error_max_pct": round(100 * float(rel.max()), 2)}


def _vs(value: float, truth: float) -> float:
    return round(100 * (value / truth - 1.0), 1) if truth and math.isfinite(value) and math.isfinite(truth) else math.nan


# -- the scenes -------------------------------------------------------------------------------------------


def _line(name: str, half_width_mm: float, maps: dict):
    """A y-invariant dip (stripe, vessel, hair): its scene definition for ``_dip``."""
    return {"name": name, "half_width_mm": half_width_mm, "maps": maps}


def _scene_rows(x: torch.Tensor) -> dict:
    inside = lambda half: (x.abs() < half)  # noqa: E731
    hair = torch.zeros(1, WL.numel(), 1, WIDTH_PX, dtype=torch.float64)
    hair[..., WIDTH_PX // 2] = 2.0
    stripe = _row(WIDTH_PX, C_hd=torch.where(inside(0.5), 0.08, BASE["C_hd"]))
    vessel = _row(WIDTH_PX, C_hd=torch.where(inside(0.15), 0.2, BASE["C_hd"]))
    hair_row = _row(WIDTH_PX).replace(absorbance=hair, absorbance_wavelength_nm=WL)
    step = _row(WIDTH_PX, C_m=torch.where(x > 0, 6 * BASE["C_m"], BASE["C_m"]))
    return {"stripe": ("blood stripe", 0.5, stripe), "vessel": ("thin vessel", 0.15, vessel),
            "hair": ("hair", 0.05, hair_row), "step": ("melanin step", 0.0, step)}


def _monte_carlo(scene: str, run):
    """The scene's Monte Carlo: kept from an earlier run (``SKINLAYERS_SCENES_REUSE=1``) or run now."""
    path = out_dir() / f"transport_scene_{scene}.pt"
    if REUSE and path.exists():
        kept = torch.load(path, weights_only=False)
        if "monte_carlo" in kept:
            return kept["monte_carlo"]
    start = time.perf_counter()
    result = run()
    result["seconds_total"] = time.perf_counter() - start
    result["photons"] = PHOTONS
    result["run"] = time.strftime("%Y-%m-%d %H:%M")
    torch.save({"monte_carlo": result}, path)
    return result


def test_heterogeneous_scenes_against_transport():
    transport = TransportRenderer(ModelSettings.model_validate({"transport": {"margin_mm": MARGIN_MM}}))
    x = _x(WIDTH_PX)
    rows, curves = [], {}
    planes = _monte_carlo("planes", lambda: {
        k: transport.totals(SkinParams.from_mapping(p), WL, photons=PHOTONS // 4)
        for k, p in (("light", BASE), ("dark", {**BASE, "C_m": 6 * BASE["C_m"]}))})
    lines = _scene_rows(x)
    for scene in SCENES:
        if scene in lines:
            label, half, row = lines[scene]
            mc = _monte_carlo(scene, lambda: {"profile": transport.profile(row, Light("uniform"), WL, photons=PHOTONS)})
            made = _step_rows if scene == "step" else _dip_rows
            rows += made(label, half, row, mc, planes, x, curves)
        elif scene == "window":
            rows += _window_rows(transport, curves)
        elif scene == "freckle":
            rows += _freckle_rows(transport, planes, curves)
        else:
            raise ValueError(f"unknown scene {scene!r}; scenes are {ALL_SCENES}")
    write_csv("transport_scenes.csv", rows, f"{PHOTONS:,} photons a band (or kept runs), scenes {', '.join(SCENES)}")
    _figure(curves)
    assert all(r["renderer"] for r in rows)


def _renderers():
    return {name: ModelSettings.model_validate(over) for name, over in RENDERERS.items()}


def _dip_rows(label, half, row, mc, planes, x, curves) -> list[dict]:
    """Depth 1 − min/background and full width at half depth of a dip; the Monte Carlo's background is the
    homogeneous plane's (its profile's own ends lack light from beyond the margin)."""
    out = []
    profile = mc["profile"]
    centre = slice(WIDTH_PX // 2 - 1, WIDTH_PX // 2 + 1) if half >= 0.1 else slice(WIDTH_PX // 2, WIDTH_PX // 2 + 1)
    outside = x.abs() > half + 0.1
    ours = {name: _renderer_profile(s, row, Light("uniform")) for name, s in _renderers().items()}
    for j, wl in enumerate(WL.tolist()):
        mc_prof, mc_err = profile.exitance[0, j, 0], profile.exitance_std_error[0, j, 0]
        background = float(planes["light"].reflectance[j])
        mc_depth = 1.0 - float(mc_prof[centre].mean()) / background
        mc_width = _width_at(mc_prof, background * (1.0 - mc_depth / 2.0), x)
        se = float(mc_err[centre].pow(2).sum().sqrt()) / (centre.stop - centre.start) / background
        out.append({"scene": label, "wavelength_nm": wl, "renderer": "monte carlo", "depth_pct": round(100 * mc_depth, 2),
                    "depth_se_pct": round(100 * se, 2), "width_mm": round(mc_width, 3),
                    "pixel_se_pct": round(100 * float((mc_err / mc_prof).median()), 2), "photons": mc["profile"].photons})
        curves[(label, wl, "monte carlo")] = (x, mc_prof, mc_err)
        for name, prof in ours.items():
            p = prof[j]
            bg = float(torch.cat([p[:10], p[-10:]]).mean())
            depth = 1.0 - float(p[centre].mean()) / bg
            width = _width_at(p, bg * (1.0 - depth / 2.0), x)
            out.append({"scene": label, "wavelength_nm": wl, "renderer": name, "depth_pct": round(100 * depth, 2),
                        "width_mm": round(width, 3), "depth_vs_mc_pct": _vs(depth, mc_depth), "width_vs_mc_pct": _vs(width, mc_width),
                        **_pixel_errors(p, mc_prof, outside)})
            curves[(label, wl, name)] = (x, p, None)
    return out


def _step_rows(label, half, row, mc, planes, x, curves) -> list[dict]:
    """The 25–75% edge width (the Monte Carlo's levels from the homogeneous planes) and the pixel errors."""
    out = []
    profile = mc["profile"]
    outside = x.abs() > 0.1
    ours = {name: _renderer_profile(s, row, Light("uniform")) for name, s in _renderers().items()}
    for j, wl in enumerate(WL.tolist()):
        mc_prof, mc_err = profile.exitance[0, j, 0], profile.exitance_std_error[0, j, 0]
        h_light, h_dark = float(planes["light"].reflectance[j]), float(planes["dark"].reflectance[j])
        mc_edge = _edge_width(mc_prof, x, h_light, h_dark)
        out.append({"scene": label, "wavelength_nm": wl, "renderer": "monte carlo", "edge_width_mm": round(mc_edge, 3),
                    "pixel_se_pct": round(100 * float((mc_err / mc_prof).median()), 2), "photons": profile.photons})
        curves[(label, wl, "monte carlo")] = (x, mc_prof, mc_err)
        for name, prof in ours.items():
            p = prof[j]
            edge = _edge_width(p, x, float(p[:8].mean()), float(p[-8:].mean()))
            out.append({"scene": label, "wavelength_nm": wl, "renderer": name, "edge_width_mm": round(edge, 3),
                        "edge_width_vs_mc_pct": _vs(edge, mc_edge),
                        "dark_plateau_vs_mc_pct": _vs(float(p[-8:].mean()), h_dark), **_pixel_errors(p, mc_prof, outside)})
            curves[(label, wl, name)] = (x, p, None)
    return out


WINDOW_OUTSIDE_MM = (0.25, 0.5, 1.0)


def _window_rows(transport: TransportRenderer, curves: dict) -> list[dict]:
    """The 5-mm window: the fall-off outside its edge (at x = 2.5 mm) over the centre's exitance."""
    out = []
    n = 90
    maps = SkinMaps.uniform(BASE, (n, n), MM, dtype=torch.float64)
    light = Light("window", size_mm=5.0)
    mc = _monte_carlo("window", lambda: {"image": transport.render(maps, light, WL, photons=PHOTONS)})["image"]
    xx = _x(n)
    rows_c = slice(n // 2 - 10, n // 2 + 10)

    def falloff(img):
        prof = img[rows_c].mean(0)
        centre = float(prof[n // 2 - 3: n // 2 + 3].mean())
        return prof, centre, [float(prof[(xx - 2.5 - d).abs().argmin()]) / centre for d in WINDOW_OUTSIDE_MM]

    keep = (xx.abs() < 2.4) | ((xx.abs() > 2.6) & (xx.abs() < 3.5))
    ours = {name: SkinRenderer(s).render(maps.to(dtype=torch.float32), light, WL).exitance[0].double() for name, s in _renderers().items()}
    for j, wl in enumerate(WL.tolist()):
        mc_prof, mc_centre, mc_fall = falloff(mc.exitance[0, j])
        se = mc.exitance_std_error[0, j][rows_c].pow(2).mean(0).sqrt() / math.sqrt(20)
        row = {"scene": "5-mm window", "wavelength_nm": wl, "renderer": "monte carlo", "photons": mc.photons,
               "pixel_se_pct": round(100 * float((se / mc_prof)[keep].median()), 2)}
        for d, v in zip(WINDOW_OUTSIDE_MM, mc_fall):
            row[f"outside_{d:g}mm_over_centre_pct"] = round(100 * v, 2)
        out.append(row)
        curves[("5-mm window", wl, "monte carlo")] = (xx, mc_prof, se)
        for name, img in ours.items():
            prof, _, fall = falloff(img[j])
            row = {"scene": "5-mm window", "wavelength_nm": wl, "renderer": name, **_pixel_errors(prof, mc_prof, keep)}
            for d, v, t in zip(WINDOW_OUTSIDE_MM, fall, mc_fall):
                row[f"outside_{d:g}mm_over_centre_pct"] = round(100 * v, 2)
                row[f"outside_{d:g}mm_vs_mc_pct"] = _vs(v, t)
            out.append(row)
            curves[("5-mm window", wl, name)] = (xx, prof, None)
    return out


def _freckle_rows(transport: TransportRenderer, planes, curves: dict) -> list[dict]:
    """A 1-mm disk of melanin ×4 under uniform light: contrast 1 − centre/background and the radius at
    half contrast, from the image's radial profile (annuli of 0.1 mm)."""
    out = []
    n = 60
    xx = _x(n)
    rr = torch.sqrt(xx[:, None] ** 2 + xx[None, :] ** 2)
    c_m = torch.where(rr < 0.5, 4 * BASE["C_m"], BASE["C_m"])
    maps = SkinMaps.uniform(BASE, (n, n), MM, dtype=torch.float64).replace(C_m=c_m[None])
    mc = _monte_carlo("freckle", lambda: {"image": transport.render(maps, Light("uniform"), WL, photons=PHOTONS)})["image"]
    radii = torch.arange(0.0, 2.5, MM, dtype=torch.float64)

    def radial(img):
        return torch.stack([img[(rr >= r) & (rr < r + MM)].mean() for r in radii])

    keep = (radii + 0.5 * MM) > 0.6
    ours = {name: SkinRenderer(s).render(maps.to(dtype=torch.float32), Light("uniform"), WL).exitance[0].double()
            for name, s in _renderers().items()}
    centre_radius = radii + 0.5 * MM
    for j, wl in enumerate(WL.tolist()):
        mc_prof = radial(mc.exitance[0, j])
        background = float(planes["light"].reflectance[j])
        mc_contrast = 1.0 - float(mc.exitance[0, j][rr < 0.15].mean()) / background
        mc_radius = _crossing(mc_prof, background * (1.0 - mc_contrast / 2.0), centre_radius, 0.5)
        se = mc.exitance_std_error[0, j]
        out.append({"scene": "freckle", "wavelength_nm": wl, "renderer": "monte carlo", "contrast_pct": round(100 * mc_contrast, 2),
                    "radius_mm": round(mc_radius, 3), "photons": mc.photons,
                    "pixel_se_pct": round(100 * float((se / mc.exitance[0, j]).median()), 2)})
        curves[("freckle", wl, "monte carlo")] = (centre_radius, mc_prof, None)
        for name, img in ours.items():
            prof = radial(img[j])
            bg = float(prof[-5:].mean())
            contrast = 1.0 - float(img[j][rr < 0.15].mean()) / bg
            radius = _crossing(prof, bg * (1.0 - contrast / 2.0), centre_radius, 0.5)
            out.append({"scene": "freckle", "wavelength_nm": wl, "renderer": name, "contrast_pct": round(100 * contrast, 2),
                        "radius_mm": round(radius, 3), "contrast_vs_mc_pct": _vs(contrast, mc_contrast),
                        "radius_vs_mc_pct": _vs(radius, mc_radius), **_pixel_errors(prof, mc_prof, keep)})
            curves[("freckle", wl, name)] = (centre_radius, prof, None)
    return out


def _figure(curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(k[0] for k in curves))
    fig, axes = plt.subplots(len(scenes), 3, figsize=(12, 2.8 * len(scenes)), squeeze=False)
    styles = {"paper": ":", "transport profiles, exit rule": "-", "transport profiles, segment coupling": "--"}
    for i, scene in enumerate(scenes):
        for j, wl in enumerate(WL.tolist()):
            ax = axes[i, j]
            if (scene, wl, "monte carlo") in curves:
                x, prof, err = curves[(scene, wl, "monte carlo")]
                ax.errorbar(x, prof, yerr=err, fmt="o", ms=2, color="k", elinewidth=0.5, label="Monte Carlo")
            for name, style in styles.items():
                if (scene, wl, name) in curves:
                    x, prof, _ = curves[(scene, wl, name)]
                    ax.plot(x, prof, style, lw=1.2, label=name)
            ax.set_title(f"{scene}, {wl:g} nm", fontsize=9)
            ax.grid(alpha=0.3)
            if scene in ("blood stripe", "thin vessel", "hair", "melanin step"):
                ax.set_xlim(-3, 3)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("exitance M / E")
    fig.tight_layout()
    fig.savefig(out_dir() / "transport_scenes.png", dpi=100)
    plt.close(fig)
