"""Benchmark: heterogeneous skin, the diffusion renderer against the Monte Carlo transport reference
(run on demand: ``pytest -m bench tests/bench/test_transport_scenes.py -s``).

Three scenes on Table 2's III interior, 0.1-mm pixels, the full model (n 1.40 / 1.38, the interface
absorber), isotropic scattering with σs = σs′ for the Monte Carlo (the medium diffusion describes), at
470, 560 and 650 nm:

- a 1-mm stripe of dermal blood (C_hd 0.08), uniform light: its depth 1 − min/background and its full
  width at half depth;
- a melanin step (C_m ×6 for x > 0), uniform light: the 25–75% edge width, the renderer's two edge
  pixels against the Monte Carlo's, and each plateau against the homogeneous transport value;
- a 5-mm window of light on a 9-mm patch: the exitance 0.5 mm outside the window's edge over the
  exitance at its centre (rows within 1 mm of the centre line averaged).

The two y-invariant scenes use the reference's profile mode (``TransportRenderer.profile``); the window
is a 2-D render. Writes ``transport_scenes.csv`` and ``transport_scenes.png`` (``bench_io``); the numbers
with their standard errors go into docs/transport.md. ``SKINLAYERS_SCENE_PHOTONS`` sets the photons,
``SKINLAYERS_SCENES`` the scenes run (each scene's results are kept in the output folder, so the CSV and
the figure hold every scene run there, with the time of its run).
"""

from __future__ import annotations

import math
import os
import time

import pytest
import torch

from bench_io import out_dir, write_csv  # noqa: E402 (tests/bench/conftest.py puts it on the path)

from skinlayers.model import TABLE2, ModelSettings, SkinParams
from skinlayers.model.illumination import Light
from skinlayers.model.maps import SkinMaps
from skinlayers.model.renderer import SkinRenderer
from skinlayers.model.transport import TransportRenderer

pytestmark = pytest.mark.bench

WL = torch.tensor([470.0, 560.0, 650.0], dtype=torch.float64)
MM = 0.1
PHOTONS = int(os.environ.get("SKINLAYERS_SCENE_PHOTONS", 4_000_000))
#: The scenes to run (``SKINLAYERS_SCENES``, a comma list of stripe, step, window).
SCENES = os.environ.get("SKINLAYERS_SCENES", "stripe,step,window").split(",")
#: Lit skin beyond the profiles' maps: at 650 nm the dermis's diffusion length is about 2 mm, and with
#: 3 mm the profile's ends missed 1.5% of their light (a first run; docs/transport.md).
MARGIN_MM = 8.0
BASE = TABLE2["III interior"]


def _row(width_px: int, **maps: torch.Tensor) -> SkinMaps:
    base = SkinMaps.uniform(BASE, (1, width_px), MM, dtype=torch.float64)
    return base.replace(**{k: v.reshape(1, 1, width_px).double() for k, v in maps.items()})


def _x(width_px: int) -> torch.Tensor:
    return (torch.arange(width_px, dtype=torch.float64) - (width_px - 1) / 2.0) * MM


def _diffusion_profile(row: SkinMaps, light: Light) -> torch.Tensor:
    """The renderer's profile ``(L, W)`` of a y-invariant scene: the row repeated over 16 rows, the centre one."""
    maps = SkinMaps(*(v.expand(1, 16, v.shape[-1]).contiguous() for v in row.params().values()), mm_per_pixel=MM)
    return SkinRenderer().render(maps, light, WL).exitance[0, :, 8].double()


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
    """Width of the dip of ``profile`` below ``level`` around its minimum."""
    centre = float(x[int(profile.argmin())])
    left = _crossing(profile[x <= centre], level, x[x <= centre], centre)
    right = _crossing(profile[x >= centre], level, x[x >= centre], centre)
    return right - left


def _edge_width(profile: torch.Tensor, x: torch.Tensor, plateau_light: float, plateau_dark: float) -> float:
    """Distance between the 25% and the 75% crossings of a falling step at x = 0."""
    level = lambda frac: plateau_light - frac * (plateau_light - plateau_dark)  # noqa: E731
    return _crossing(profile, level(0.75), x, 0.0) - _crossing(profile, level(0.25), x, 0.0)


def test_heterogeneous_scenes_against_transport():
    transport = TransportRenderer(ModelSettings.model_validate({"transport": {"margin_mm": MARGIN_MM}}))
    rows, curves = [], {}
    w = 80
    x = _x(w)
    dark = {**BASE, "C_m": 6 * BASE["C_m"]}
    homogeneous = {k: transport.totals(SkinParams.from_mapping(p), WL, photons=PHOTONS // 4) for k, p in (("light", BASE), ("dark", dark))}
    made = time.strftime("%Y-%m-%d %H:%M")
    runs = {"stripe": lambda c: _stripe(transport, w, x, homogeneous["light"], c), "step": lambda c: _step(transport, w, x, homogeneous, c),
            "window": lambda c: _window(transport, c)}
    for scene in SCENES:  # each scene's rows and curves kept on disk: a later run of some scenes joins them
        scene_curves: dict = {}
        scene_rows = [{**r, "run": made} for r in runs[scene](scene_curves)]
        torch.save({"rows": scene_rows, "curves": scene_curves}, out_dir() / f"transport_scene_{scene}.pt")
    for scene in runs:
        path = out_dir() / f"transport_scene_{scene}.pt"
        if path.exists():
            kept = torch.load(path, weights_only=False)
            rows += kept["rows"]
            curves.update(kept["curves"])
    write_csv("transport_scenes.csv", rows, f"{PHOTONS:,} photons a band in this run, scenes {', '.join(SCENES)}")
    _figure(curves)
    stripe_rows = [r for r in rows if r["scene"] == "blood stripe"]
    assert all(0 < r["depth_pct"] < 100 for r in stripe_rows)


def _stripe(transport: TransportRenderer, w: int, x: torch.Tensor, plane, curves: dict) -> list[dict]:
    """The dermal-blood stripe: depth and width at half depth. The Monte Carlo's background is the
    homogeneous plane's (``plane``, its totals): the profile's own ends lack light from beyond the margin."""
    rows = []
    c_hd = torch.where(x.abs() < 0.5, 0.08, BASE["C_hd"])
    stripe = _row(w, C_hd=c_hd)
    mc = transport.profile(stripe, Light("uniform"), WL, photons=PHOTONS)
    dif = _diffusion_profile(stripe, Light("uniform"))
    for j, wl in enumerate(WL.tolist()):
        for name, prof, err in (("diffusion", dif[j], None), ("transport", mc.exitance[0, j, 0], mc.exitance_std_error[0, j, 0])):
            background = float(torch.cat([prof[:10], prof[-10:]]).mean()) if err is None else float(plane.reflectance[j])
            low = float(prof[w // 2 - 1: w // 2 + 1].mean())  # the two centre pixels: the minimum by symmetry, without noise's pick
            depth = 1.0 - low / background
            fwhm = _width_at(prof, background * (1.0 - depth / 2.0), x)
            row = {"scene": "blood stripe", "wavelength_nm": wl, "physics": name, "depth_pct": round(100 * depth, 2),
                   "width_at_half_depth_mm": round(fwhm, 3), "photons": PHOTONS if err is not None else ""}
            if err is not None:
                row["seconds"] = round(mc.seconds[j], 1)
                row["depth_se_pct"] = round(100 * float(err[w // 2 - 1: w // 2 + 1].pow(2).sum().sqrt() / 2) / background, 2)
                row["pixel_se_pct"] = round(100 * float((err / prof).median()), 2)
                row["background_se_pct"] = round(100 * float(plane.std_error[j] / plane.reflectance[j]), 2)
            rows.append(row)
            curves[("stripe", wl, name)] = (x, prof, err)
    return rows


def _step(transport: TransportRenderer, w: int, x: torch.Tensor, homogeneous: dict, curves: dict) -> list[dict]:
    """The melanin step: the 25–75% edge width (the Monte Carlo's levels from the homogeneous planes),
    the renderer's edge pixels against the Monte Carlo's, the profile's plateaus against the planes."""
    rows = []
    # -- the melanin step -----------------------------------------------------------------------------
    c_m = torch.where(x > 0, 6 * BASE["C_m"], BASE["C_m"])
    step = _row(w, C_m=c_m)
    mc = transport.profile(step, Light("uniform"), WL, photons=PHOTONS)
    dif = _diffusion_profile(step, Light("uniform"))
    edge = (w // 2 - 1, w // 2)  # the last pixel on the light side, the first on the dark side
    for j, wl in enumerate(WL.tolist()):
        mc_prof, mc_err = mc.exitance[0, j, 0], mc.exitance_std_error[0, j, 0]
        for name, prof, err in (("diffusion", dif[j], None), ("transport", mc_prof, mc_err)):
            light_plateau, dark_plateau = float(prof[:8].mean()), float(prof[-8:].mean())
            h_light, h_dark = float(homogeneous["light"].reflectance[j]), float(homogeneous["dark"].reflectance[j])
            levels = (light_plateau, dark_plateau) if err is None else (h_light, h_dark)
            row = {"scene": "melanin step", "wavelength_nm": wl, "physics": name,
                   "edge_width_25_75_mm": round(_edge_width(prof, x, *levels), 3),
                   "light_plateau_vs_transport_pct": round(100 * (light_plateau / h_light - 1), 2),
                   "dark_plateau_vs_transport_pct": round(100 * (dark_plateau / h_dark - 1), 2), "photons": PHOTONS if err is not None else ""}
            if err is None:  # the renderer's edge pixels against the Monte Carlo's same pixels
                row["edge_light_pixel_vs_transport_pct"] = round(100 * float(prof[edge[0]] / mc_prof[edge[0]] - 1), 2)
                row["edge_dark_pixel_vs_transport_pct"] = round(100 * float(prof[edge[1]] / mc_prof[edge[1]] - 1), 2)
            else:
                row.update(pixel_se_pct=round(100 * float((err / prof).median()), 2), seconds=round(mc.seconds[j], 1),
                           edge_pixel_se_pct=round(100 * float((err[list(edge)] / prof[list(edge)]).max()), 2))
            rows.append(row)
            curves[("step", wl, name)] = (x, prof, err)
    return rows


def _window(transport: TransportRenderer, curves: dict) -> list[dict]:
    """The 5-mm window: the exitance 0.5 mm outside its edge over the centre's."""
    rows = []
    n = 90
    maps = SkinMaps.uniform(BASE, (n, n), MM, dtype=torch.float64)
    light = Light("window", size_mm=5.0)
    mc2 = transport.render(maps, light, WL, photons=PHOTONS)
    dif2 = SkinRenderer().render(maps.to(dtype=torch.float32), light, WL).exitance[0].double()
    xx = _x(n)
    centre_rows = slice(n // 2 - 10, n // 2 + 10)
    for j, wl in enumerate(WL.tolist()):
        for name, img, err in (("diffusion", dif2[j], None), ("transport", mc2.exitance[0, j], mc2.exitance_std_error[0, j])):
            prof = img[centre_rows].mean(0)
            centre = float(prof[n // 2 - 3: n // 2 + 3].mean())
            outside = float(prof[(xx - 3.0).abs().argmin()])  # 0.5 mm outside the edge at x = 2.5 mm
            row = {"scene": "5-mm window", "wavelength_nm": wl, "physics": name, "outside_0p5mm_over_centre_pct": round(100 * outside / centre, 2),
                   "photons": PHOTONS if err is not None else ""}
            if err is not None:
                row["seconds"] = round(mc2.seconds[j], 1)
                row["outside_se_pct"] = round(100 * float(err[centre_rows, (xx - 3.0).abs().argmin()].pow(2).mean().sqrt()) / math.sqrt(20) / centre, 2)
            rows.append(row)
            curves[("window", wl, name)] = (xx, prof, None)
    return rows


def _figure(curves: dict) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(3, 3, figsize=(12, 9), sharex="row")
    for i, scene in enumerate(("stripe", "step", "window")):
        for j, wl in enumerate(WL.tolist()):
            ax = axes[i, j]
            if (scene, wl, "diffusion") not in curves:
                continue
            for name, style in (("diffusion", "-"), ("transport", "o")):
                x, prof, err = curves[(scene, wl, name)]
                if err is None:
                    ax.plot(x, prof, style, label=name, ms=2)
                else:
                    ax.errorbar(x, prof, yerr=err, fmt=style, ms=2, label=name, elinewidth=0.5)
            ax.set_title(f"{scene}, {wl:g} nm", fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("x (mm)")
    for ax in axes[:, 0]:
        ax.set_ylabel("exitance M / E")
    fig.tight_layout()
    fig.savefig(out_dir() / "transport_scenes.png", dpi=110)
    plt.close(fig)
