"""The transport-matched layer responses (``profiles: transport``, model/column/layer_totals.py) against truths
the model did not make: adding-doubling (iadpython) at points off the tables' grid and for whole
two-layer stacks with the interface absorber, and the stored Monte Carlo of Table 2 with the paper's
index step (tests/data/transport_table2_mc.csv, from tests/bench/test_transport_homogeneous.py).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import transport_reference as ref  # tests/conftest.py puts tests/model on the path

from skinlayers.model import TABLE2, ModelSettings, SkinModel, SkinParams
from skinlayers.model.column import adding_doubling as ad
from skinlayers.model.column import layer_totals as lt
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.illumination import Light
from skinlayers.model.render.renderer import SkinRenderer

F64 = torch.float64
TRANSPORT = ModelSettings(profiles="transport")
WL_DENSE = torch.arange(400.0, 701.0, 10.0, dtype=F64)
MC_TABLE = Path(__file__).resolve().parents[1] / "data" / "transport_table2_mc.csv"
#: The issue's homogeneous target: within 1.5% of transport, relative.
HOMOGENEOUS_TARGET = 0.015
#: Epidermal slab totals: within 2% of transport over skin's σa range.
SLAB_TARGET = 0.02
#: The angular hand-over against the adding-doubling stack it was made to match (the interface absorber
#: and an off-node interpolation between them; measured −0.08 … −0.03% over Table 2).
HANDOVER_TARGET = 0.0015


def _t(x):
    return torch.tensor(float(x), dtype=F64)


def test_slab_and_half_space_tables_match_adding_doubling_off_their_grid():
    """The shipped tables, read between their nodes, against iadpython run afresh at those points."""
    pytest.importorskip("iadpython")
    rng = np.random.default_rng(15)
    worst_slab, worst_half = 0.0, 0.0
    for _ in range(25):
        x, y = rng.uniform(-3.4, 2.2), rng.uniform(-0.9, 0.9)
        ss = 5.0
        sa, d = ss * 10.0**x, 10.0**y / ss
        albedo, tau = 1.0 / (1.0 + 10.0**x), (sa + ss) * d
        truth = np.array(ad.adding_doubling_slab(albedo, tau))
        tab = lt.slab_totals(_t(sa), _t(ss), d)
        got = np.array([float(tab.R_plus), float(tab.T_plus_diffuse), float(tab.R_minus), float(tab.T_minus)])
        keep = truth > 1e-6
        worst_slab = max(worst_slab, float(np.abs(got[keep] / truth[keep] - 1.0).max()))
        half = np.array(ad.adding_doubling_half_space(albedo))
        h = lt.half_space_totals(_t(sa), _t(ss))
        worst_half = max(worst_half, float(np.abs(np.array([float(h.R_collimated), float(h.R_diffuse)]) / half - 1.0).max()))
    assert worst_slab < 2e-3 and worst_half < 1e-4, (worst_slab, worst_half)


def test_epidermal_slab_within_two_percent_over_skin_absorption():
    """The model's epidermis (R⁺, all of T⁺, R⁻, T⁻; index-matched below) over σa 0.02–80 mm⁻¹ at the
    epidermis's σs′ of 400, 550 and 700 nm, against adding-doubling through the tests' own reference
    (iadpython's single-layer doubling and slide, not the package's tables); diffusion is far off."""
    pytest.importorskip("iadpython")
    from skinlayers.model.column.profiles import multipole_totals

    settings = ModelSettings.model_validate({"optics": {"n_dermis": 1.40, "interface_melanin_fraction": 0.0}})
    spectra = SkinModel(settings).spectra(torch.tensor([400.0, 550.0, 700.0], dtype=F64))
    worst, diffusion_worst = 0.0, 0.0
    for ss in spectra.scattering_epidermis.tolist():
        for sa in np.geomspace(0.02, 80.0, 8):
            truth = np.array(ref.adding_doubling_slab_matched_below(ref.Layer(float(sa), ss, 0.25)))
            tab = lt.slab_totals(_t(sa), _t(ss), 0.25)
            model = np.array([float(tab.R_plus), float(tab.T_plus_diffuse + tab.T_plus_collimated),
                              float(tab.R_minus), float(tab.T_minus)])
            keep = truth > 1e-3  # a transmittance below 10⁻³ of the light carries nothing the skin shows
            worst = max(worst, float(np.abs(model[keep] / truth[keep] - 1.0).max()))
            diff = multipole_totals(_t(sa), _t(ss), 0.25, ref.N_SKIN, 1.0)
            diffusion = np.array([float(diff.R_plus), float(diff.T_plus)])
            diffusion_worst = max(diffusion_worst, float(np.abs(diffusion / truth[:2] - 1.0)[keep[:2]].max()))
    assert worst < SLAB_TARGET, worst
    assert diffusion_worst > 0.2, diffusion_worst  # the check separates the two models


def _table2_adding_doubling(model: SkinModel, row: str) -> np.ndarray:
    params = SkinParams.from_mapping(TABLE2[row])
    spectra = model.spectra(WL_DENSE)
    ab = model.absorption(params, spectra)
    attenuation = torch.exp(-ab.interface_absorbance)
    return np.array([
        ref.adding_doubling_stack(
            [ref.Layer(float(ab.epidermis[j]), float(spectra.scattering_epidermis[j]), 0.25),
             ref.Layer(float(ab.dermis[j]), float(spectra.scattering_dermis[j]), ref.DERMIS_MM)],
            attenuation=[float(attenuation[j])],
        ).R_diffuse
        for j in range(WL_DENSE.numel())
    ])


def test_table2_every_10nm_within_target_of_adding_doubling():
    """Nine rows × 400–700 nm every 10 nm, the interface absorber per crossing, one index (what
    adding-doubling can stack): transport profiles within 1.5%, and within 0.15% with the angular
    hand-over, where Eq. 7's Lambertian one is up to +0.5% off; diffusion up to +31.7% off."""
    pytest.importorskip("iadpython")
    errors = {}
    truth = None
    for name, over in (("angular", {"profiles": "transport", "handover": "angular"}),
                       ("lambertian", {"profiles": "transport", "handover": "lambertian"}),
                       ("diffusion", {"profiles": "diffusion"})):
        model = SkinModel(ModelSettings.model_validate({**over, "optics": {"n_dermis": 1.40}}))
        if truth is None:
            truth = np.stack([_table2_adding_doubling(model, row) for row in TABLE2])
        ours = np.stack([model.diffuse_reflectance(SkinParams.from_mapping(TABLE2[row]), WL_DENSE).numpy() for row in TABLE2])
        errors[name] = ours / truth - 1.0
    assert np.abs(errors["angular"]).max() < HANDOVER_TARGET, np.abs(errors["angular"]).max()
    assert np.abs(errors["lambertian"]).max() < HOMOGENEOUS_TARGET, np.abs(errors["lambertian"]).max()
    assert errors["lambertian"].max() > 0.004  # the check separates the two hand-overs
    assert errors["diffusion"].max() > 0.25 and errors["diffusion"].min() < -0.04


def test_handover_table_between_its_nodes():
    """The shipped hand-over factor κ, read between its nodes (Catmull-Rom in x₁, y₁, x₂): the two
    layers' total it gives against fresh adding-doubling of the stack at those points, within 10⁻⁴
    (measured 1.6·10⁻⁵ on 60 points), where the Lambertian hand-over is up to 1% off; and κ is 1 where
    the layers hand nothing over."""
    pytest.importorskip("iadpython")
    rng = np.random.default_rng(4)
    worst = {"angular": 0.0, "lambertian": 0.0}
    s1, s2 = 6.0, 3.0
    for x1, y1, x2 in zip(rng.uniform(-3.0, 0.5, 12), rng.uniform(-0.2, 0.6, 12), rng.uniform(-3.5, 0.5, 12)):
        truth = ad.adding_doubling_two_layers(float(x1), float(y1), float(x2))
        for handover in worst:
            t = lt.layer_totals(_t(s1 * 10.0**x1), _t(s1), 10.0**y1 / s1, _t(s2 * 10.0**x2), _t(s2),
                                1.0, lt.TABLE_N_LAYER, lt.TABLE_N_LAYER, handover)
            total = float(t.R1_plus + t.T1_plus * t.R2_plus * t.T1_minus / (1.0 - t.R1_minus * t.R2_plus))
            worst[handover] = max(worst[handover], abs(total / truth - 1.0))
    assert worst["angular"] < 1e-4, worst
    assert worst["lambertian"] > 3e-3, worst
    opaque = lt.handover_factor(_t(600.0), _t(6.0), 2.0, _t(0.3), _t(3.0))  # σa d = 1200: nothing crosses
    assert float(opaque) == pytest.approx(1.0)


def test_handover_grid_is_the_factor_at_its_nodes():
    """The renderer's κ (bilinear on the tables' σa grid) is ``handover_factor`` at the grid's nodes,
    and between them within 2·10⁻⁴ (measured 7.7·10⁻⁵: the grid's 256 log-spaced samples against κ's
    curvature; on the total it is a fraction of that)."""
    model = SkinModel(TRANSPORT)
    wl = torch.tensor([430.0, 560.0, 670.0], dtype=F64)
    grid, tab, spectra = model.handover_grid(wl), model.tables(wl), model.spectra(wl)
    s1, s2 = spectra.scattering_epidermis, spectra.scattering_dermis
    sa = tab.sigma_a_per_mm
    i, j = torch.tensor([3, 90, 200]), torch.tensor([10, 120, 250])
    at_nodes = lt.handover_factor(sa[i][:, None], s1, 0.25, sa[j][:, None], s2)  # (3 points, 3 bands)
    torch.testing.assert_close(grid[:, i, j].T, at_nodes, rtol=1e-12, atol=0)
    g = torch.Generator().manual_seed(1)
    sa_epi = torch.exp(torch.empty(40, 3, dtype=F64).uniform_(math.log(0.02), math.log(50.0), generator=g))
    sa_derm = torch.exp(torch.empty(40, 3, dtype=F64).uniform_(math.log(0.02), math.log(20.0), generator=g))
    read = model._handover_at(tab, wl, sa_epi, sa_derm)
    torch.testing.assert_close(read, lt.handover_factor(sa_epi, s1, 0.25, sa_derm, s2), rtol=2e-4, atol=0)


def _stored_monte_carlo() -> list[dict]:
    with MC_TABLE.open() as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


def test_table2_against_stored_monte_carlo_with_the_index_step():
    """The paper's indices (1.40 over 1.38) and absorber, against the project's Monte Carlo: every stored
    point within 1.5% plus two of its standard errors (the truth's own noise), both models reported."""
    rows = _stored_monte_carlo()
    assert len(rows) >= 9 * 4
    worst = {}
    for profiles in ("transport", "diffusion"):
        model = SkinModel(ModelSettings(profiles=profiles))
        excess = []
        for r in rows:
            value = float(model.diffuse_reflectance(SkinParams.from_mapping(TABLE2[r["row"]]),
                                                    torch.tensor([float(r["wavelength_nm"])], dtype=F64))[0])
            mc, se = float(r["monte_carlo"]), float(r["std_error"])
            excess.append(abs(value / mc - 1.0) - (HOMOGENEOUS_TARGET + 2.0 * se / mc))
        worst[profiles] = max(excess)
    assert worst["transport"] < 0.0, worst
    assert worst["diffusion"] > 0.05, worst


def test_layer_totals_gradients_are_exact():
    sa = torch.tensor([0.05, 0.9, 6.0], dtype=F64, requires_grad=True)
    ss = torch.tensor([6.0, 4.4, 12.5], dtype=F64, requires_grad=True)
    torch.autograd.gradcheck(lambda a, s: torch.stack(list(lt.slab_totals(a, s, 0.25))), (sa, ss))
    torch.autograd.gradcheck(lambda a, s: torch.stack(list(lt.half_space_totals(a, s))), (sa, ss))
    model = SkinModel(TRANSPORT)
    x = torch.tensor([[0.02, 0.3, 0.01, 0.05, 0.002]], dtype=F64, requires_grad=True)
    wl = torch.tensor([470.0, 650.0], dtype=F64)
    for method in ("exact", "tables"):  # κ by Catmull-Rom from its table / bilinear from the σa grid
        torch.autograd.gradcheck(lambda v: model.diffuse_reflectance(SkinParams.from_tensor(v), wl, method=method), (x,))
    a1 = torch.tensor([0.3, 4.0], dtype=F64, requires_grad=True)
    a2 = torch.tensor([0.05, 0.9], dtype=F64, requires_grad=True)
    torch.autograd.gradcheck(lambda p, q: lt.handover_factor(p, ss[:2], 0.25, q, 0.5 * ss[:2]), (a1, a2))


def test_renderer_under_uniform_light_equals_the_homogeneous_model():
    """The heterogeneous renderer with transport profiles (the unscattered beam added per pixel) gives
    the homogeneous model's totals on uniform skin: the same physics by two routes."""
    renderer = SkinRenderer(TRANSPORT)
    wl = torch.tensor([420.0, 560.0, 650.0], dtype=F64)
    for row in ("I interior", "V exterior"):
        params = SkinParams.from_mapping(TABLE2[row])
        maps = SkinMaps(*(torch.full((1, 8, 8), float(v), dtype=F64) for v in params.values()), mm_per_pixel=0.1)
        result = renderer.render(maps, Light("uniform"), wl)
        expected = SkinModel(TRANSPORT).diffuse_reflectance(params, wl)
        torch.testing.assert_close(result.exitance[0, :, 4, 4], expected, rtol=2e-3, atol=0)


def test_other_indices_are_refused_with_the_way_out(tmp_path):
    """Optics the tables cannot serve are refused when the settings are made (a settings file: with
    the key named), not in the middle of a render."""
    from skinlayers.model import SettingsError, load_model_settings

    for optics, match in (({"n_epidermis": 1.45}, "index"), ({"epidermis_thickness_mm": 3.0}, "σs′·d")):
        with pytest.raises(ValueError, match=match):
            ModelSettings.model_validate({"profiles": "transport", "optics": optics})
    bad = tmp_path / "bad.yaml"
    bad.write_text("profiles: transport\noptics:\n  n_epidermis: 1.45\n")
    with pytest.raises(SettingsError, match="profiles: diffusion"):
        load_model_settings(bad)
    diffusion = ModelSettings.model_validate({"profiles": "diffusion", "optics": {"n_epidermis": 1.45}})
    assert math.isfinite(float(SkinModel(diffusion).diffuse_reflectance(SkinParams.from_mapping(TABLE2["I interior"]), WL_DENSE[:2])[0]))


def test_transforms_from_tables_match_the_transport_shapes():
    """The Hankel transforms of the combined profile, transport profiles: the renderer's Gaussian
    tables against the layers they were fitted to (adding-doubling's totals with the Monte Carlo's
    tabulated line spreads, the unscattered beam constant in k), relative to the total, over k up to
    20 mm⁻¹: within 0.6% (measured: 0.42% at worst)."""
    model = SkinModel(TRANSPORT)
    wl = torch.tensor([430.0, 560.0, 670.0], dtype=F64)
    k = torch.linspace(0.0, 20.0, 41, dtype=F64)
    for row in ("I interior", "V exterior"):
        params = SkinParams.from_mapping(TABLE2[row])
        exact = model.combined_hankel(params, wl, k, method="exact")
        tables = model.combined_hankel(params, wl, k, method="tables")
        assert float(((tables - exact).abs() / exact[..., :1]).max()) < 0.006
        torch.testing.assert_close(exact[..., 0], model.total_reflectance(params, wl), rtol=1e-10, atol=0)


def test_fitting_monte_carlo_spectra_recovers_table2():
    """The inverse on light the model did not make: the stored Monte Carlo spectra of Table 2's nine rows
    (7 wavelengths, 400–700 nm) fitted with each model (no scale). Transport profiles recover melanin,
    its β_m, epidermal and dermal blood within the demo's targets in the median (measured 1.4%, 0.025,
    2.8%, 5.2%; with the Lambertian hand-over dermal blood was 11%); diffusion's melanin is off by more
    than 20% and its dermal blood by 14%."""
    from skinlayers.model import PARAMETER_NAMES
    from skinlayers.reconstruct import fit_spectra

    rows = _stored_monte_carlo()
    names = list(TABLE2)
    wl = torch.tensor(sorted({float(r["wavelength_nm"]) for r in rows}), dtype=F64)
    spectra = torch.zeros(len(names), wl.numel(), dtype=F64)
    for r in rows:
        spectra[names.index(r["row"]), int((wl == float(r["wavelength_nm"])).nonzero()[0, 0])] = float(r["monte_carlo"])
    truth = torch.tensor([[TABLE2[n][p] for p in PARAMETER_NAMES] for n in names], dtype=F64)
    median = {}
    for profiles in ("transport", "diffusion"):
        fit = fit_spectra(spectra, wl, SkinModel(ModelSettings(profiles=profiles)))
        x = fit.params.as_tensor()
        err = {p: ((x[:, j] - truth[:, j]).abs() if p == "beta_m" else ((x[:, j] - truth[:, j]) / truth[:, j]).abs())
               for j, p in enumerate(PARAMETER_NAMES) if p != "C_bc"}
        median[profiles] = {p: float(e.median()) for p, e in err.items()}
    t, d = median["transport"], median["diffusion"]
    assert t["C_m"] < 0.10 and t["beta_m"] < 0.10 and t["C_he"] < 0.25 and t["C_hd"] < 0.10, t
    assert d["C_m"] > 0.20, d
    assert t["C_hd"] < d["C_hd"], (t, d)
