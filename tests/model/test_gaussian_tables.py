"""Sum-of-Gaussians fits and σa lookup tables: accuracy over skin's whole σa range, interpolation,
totals against the closed forms, and the disk cache."""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
import pytest
import torch

from skinlayers.model import (
    PARAMETER_BOUNDS,
    PARAMETER_NAMES,
    TABLE2,
    ModelSettings,
    SkinModel,
    SkinOptics,
    SkinParams,
    TableSettings,
    chromophore_spectra,
    dipole_hankel,
    fit_gaussian_weights,
    gaussian_sum_hankel,
    gaussian_sum_profile,
    layer_absorption,
    multipole_hankel,
)
from skinlayers.model.gaussians import plane_quadrature
from skinlayers.model.tables import build_profile_tables, load_profile_tables

F64 = torch.float64
K_GRID = torch.logspace(-4, 5, 6000, dtype=F64)
PROFILES = ("R_plus", "T_plus", "R_minus", "T_minus")


def skin_sigma_a_range(wavelength_nm: torch.Tensor) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Min and max σa per wavelength over the corners of Table 1's parameter box, per layer.

    σa is linear in each parameter except through the product C_m β_m, which is bilinear: extremes of
    a multilinear function over a box lie on its corners.
    """
    corners = torch.tensor(list(itertools.product(*(PARAMETER_BOUNDS[n] for n in PARAMETER_NAMES))), dtype=F64)
    s = chromophore_spectra(wavelength_nm)
    ab = layer_absorption(SkinParams.from_tensor(corners), s, 0.175, 0.25)
    return {"epidermis": (ab.epidermis.min(0).values, ab.epidermis.max(0).values),
            "dermis": (ab.dermis.min(0).values, ab.dermis.max(0).values)}


def parseval_norm(transform: torch.Tensor) -> torch.Tensor:
    """Plane L2 norm from the Hankel transform: ||f||² = (1/2π) ∫ |f̂(k)|² k dk (log-k trapezoid)."""
    u = torch.log(K_GRID)
    return torch.sqrt(torch.trapezoid(transform**2 * K_GRID**2, u, dim=-1) / (2 * math.pi))


def exact_transforms(sigma_a: torch.Tensor, wavelength: float) -> dict[str, torch.Tensor]:
    o = SkinOptics()
    s = chromophore_spectra(torch.tensor([wavelength], dtype=F64))
    epi = multipole_hankel(K_GRID, sigma_a, s.scattering_epidermis[0], o.epidermis_thickness_mm,
                           o.n_epidermis / o.n_above, o.n_epidermis / o.n_dermis)
    out = {f"epidermis {p}": getattr(epi, p) for p in PROFILES}
    out["dermis R_plus"] = dipole_hankel(K_GRID, sigma_a, s.scattering_dermis[0], o.n_dermis / o.n_epidermis)
    return out


def _max(x: torch.Tensor) -> float:
    return float(x.max()) if x.numel() else 0.0


def check_tables(wavelengths: list[float], tmp_cache) -> dict:
    """Worst relative plane-L2 error and energy error at every table node inside skin's range, and the
    increase from interpolating at the midpoints; returns the report, asserts the acceptance."""
    wl = torch.tensor(wavelengths, dtype=F64)
    tables = load_profile_tables(wl, ModelSettings(), tmp_cache)
    ranges = skin_sigma_a_range(wl)
    grid = tables.sigma_a_per_mm
    report = {}
    for j, w in enumerate(wavelengths):
        for layer in ("epidermis", "dermis"):
            lo, hi = float(ranges[layer][0][j]), float(ranges[layer][1][j])
            inside = (grid >= lo / 1.05) & (grid <= hi * 1.05)
            nodes = grid[inside]
            mids = torch.sqrt(nodes[:-1] * nodes[1:])
            exact_nodes = exact_transforms(nodes, w)
            exact_mids = exact_transforms(mids, w)
            names = PROFILES if layer == "epidermis" else ("R_plus",)
            r_plus_norm = parseval_norm(exact_nodes[f"{layer} R_plus"])
            for p in names:
                key = f"{layer} {p}"
                weights = tables.table(layer, p)[j][inside]
                fit = gaussian_sum_hankel(weights, tables.variances_mm2, K_GRID)
                ref = exact_nodes[key]
                err = parseval_norm(fit - ref) / parseval_norm(ref)
                total = ref[:, 0]
                energy = (weights.sum(-1) - total).abs() / total
                interp_w = tables.lookup(layer, p, mids[:, None].expand(-1, len(wavelengths)))[:, j]
                interp = gaussian_sum_hankel(interp_w, tables.variances_mm2, K_GRID)
                ref_mid = exact_mids[key]
                err_mid = parseval_norm(interp - ref_mid) / parseval_norm(ref_mid)
                added = err_mid - 0.5 * (err[:-1] + err[1:])
                energy_mid = (interp_w.sum(-1) - ref_mid[:, 0]).abs() / ref_mid[:, 0]
                meaningful = total >= 1e-6
                invisible = parseval_norm(fit - ref) / r_plus_norm
                entry = report.setdefault(key, {"worst_l2": 0.0, "at": None, "worst_energy": 0.0, "worst_added": 0.0,
                                                "faint_worst_l2": 0.0, "faint_worst_abs": 0.0})
                if bool(meaningful.any()):
                    i = int(torch.argmax(torch.where(meaningful, err, torch.zeros_like(err))))
                    if float(err[i]) > entry["worst_l2"]:
                        entry.update(worst_l2=float(err[i]), at=(float(nodes[i]), w))
                if bool((~meaningful).any()):
                    entry["faint_worst_l2"] = max(entry["faint_worst_l2"], float(err[~meaningful].max()))
                    entry["faint_worst_abs"] = max(entry["faint_worst_abs"], float(invisible[~meaningful].max()))
                mid_meaningful = ref_mid[:, 0] >= 1e-6
                entry["worst_energy"] = max(entry["worst_energy"], _max(energy[meaningful]), _max(energy_mid[mid_meaningful]))
                entry["worst_added"] = max(entry["worst_added"], _max(added[mid_meaningful]))
    print("\nGaussian table accuracy over skin's σa range (Table 1 box), wavelengths", wavelengths[0], "…", wavelengths[-1])
    for key, e in report.items():
        at = f"σa {e['at'][0]:.3g} /mm, {e['at'][1]:g} nm" if e["at"] else "-"
        print(f"  {key:18s} worst L2 {e['worst_l2']:.4f} ({at}); energy {e['worst_energy']:.1e}; "
              f"interpolation adds {e['worst_added']:.4f}; faint (<1e-6) L2 {e['faint_worst_l2']:.3f}, "
              f"abs/R+ {e['faint_worst_abs']:.1e}")
    for key, e in report.items():
        assert e["worst_l2"] < 0.02, key
        assert e["worst_energy"] < 0.005, key
        assert e["worst_added"] < 0.005, key
        assert e["faint_worst_abs"] < 1e-6, key
    return report


def test_fit_recovers_an_exact_sum():
    v = np.array(TableSettings().gaussian_variances_mm2())
    r, q = plane_quadrature(2e-4, 80.0, 300)
    true = np.zeros((2, v.size))
    true[0, [3, 7, 12]] = [0.2, 0.5, 0.1]
    true[1, [0, 18]] = [0.3, 0.05]
    profiles = gaussian_sum_profile(torch.from_numpy(true), torch.from_numpy(v), torch.from_numpy(r)).numpy()
    w = fit_gaussian_weights(profiles, true.sum(1), v, r, q)
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(1), true.sum(1), rtol=1e-12)
    np.testing.assert_allclose(w, true, atol=2e-5)
    assert (fit_gaussian_weights(profiles[:1], np.array([0.0]), v, r, q) == 0).all()


def test_gaussian_transform_and_profile_agree():
    v = torch.tensor(TableSettings().gaussian_variances_mm2(), dtype=F64)
    w = torch.rand(3, v.numel(), dtype=F64)
    k = torch.tensor([0.0, 0.5, 3.0], dtype=F64)
    hank = gaussian_sum_hankel(w, v, k)
    torch.testing.assert_close(hank[:, 0], w.sum(-1))
    r = torch.logspace(-6, 2, 20001, dtype=F64)
    prof = gaussian_sum_profile(w, v, r)
    j0 = torch.special.bessel_j0(k[:, None] * r[None, :])
    numeric = torch.trapezoid(prof[:, None, :] * j0 * 2 * math.pi * r * r, torch.log(r), dim=-1)
    torch.testing.assert_close(numeric, hank, rtol=1e-6, atol=1e-9)


def test_tables_accuracy_three_wavelengths(tmp_path):
    check_tables([400.0, 550.0, 700.0], tmp_path)


@pytest.mark.slow
def test_tables_accuracy_every_wavelength(tmp_path):
    """Every wavelength 400–700 nm (5 nm steps), both layers, every node in skin's σa range."""
    check_tables([float(w) for w in range(400, 701, 5)], tmp_path)


def test_totals_from_tables_agree_with_closed_forms(tmp_path):
    model = SkinModel(cache_dir=str(tmp_path))
    wl = torch.tensor(ModelSettings().render_wavelengths_nm, dtype=F64)
    g = torch.Generator().manual_seed(5)
    hi = torch.tensor([PARAMETER_BOUNDS[n][1] for n in PARAMETER_NAMES], dtype=F64)
    random = torch.rand(200, 5, generator=g, dtype=F64) * hi
    rows = torch.tensor([[TABLE2[r][n] for n in PARAMETER_NAMES] for r in TABLE2], dtype=F64)
    params = SkinParams.from_tensor(torch.cat([rows, random]))
    exact = model.total_reflectance(params, wl, method="exact")
    tables = model.total_reflectance(params, wl, method="tables")
    worst = float(((tables - exact).abs() / exact).max())
    print(f"\ntotals, tables vs closed form: worst relative difference {worst:.2e}")
    assert worst < 0.005


def test_cache_is_keyed_by_what_shapes_the_tables(tmp_path):
    small = ModelSettings(tables=TableSettings(n_sigma_a=16))
    wl = torch.tensor([450.0, 600.0], dtype=F64)
    first = load_profile_tables(wl, small, tmp_path)
    files = list(tmp_path.glob("profile-tables-*.pt"))
    assert len(files) == 1
    again = load_profile_tables(wl, small, tmp_path)
    torch.testing.assert_close(again.epidermis, first.epidermis, rtol=0, atol=0)
    carotene = small.model_copy(update={"optics": small.optics.model_copy(update={"carotene_reference_mol_per_l": 0.01})})
    load_profile_tables(wl, carotene, tmp_path)
    assert len(list(tmp_path.glob("profile-tables-*.pt"))) == 1, "absorption constants do not shape the tables"
    other = small.model_copy(update={"optics": small.optics.model_copy(update={"n_epidermis": 1.45})})
    load_profile_tables(wl, other, tmp_path)
    assert len(list(tmp_path.glob("profile-tables-*.pt"))) == 2
    files[0].write_bytes(b"not a torch file")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rebuilt = load_profile_tables(wl, small, tmp_path)
    assert any("rebuilding" in str(w.message) for w in caught)
    torch.testing.assert_close(rebuilt.epidermis, first.epidermis)


def test_lookup_nodes_gradient_and_range(tmp_path):
    tables = build_profile_tables(torch.tensor([500.0], dtype=F64), ModelSettings(tables=TableSettings(n_sigma_a=32)))
    nodes = tables.sigma_a_per_mm[:, None]
    torch.testing.assert_close(tables.lookup("epidermis", "T_plus", nodes)[:, 0], tables.table("epidermis", "T_plus")[0])
    sa = torch.tensor([[0.123], [4.56]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: tables.lookup("dermis", "R_plus", x), (sa,))
    outside = torch.tensor([[1e-4], [1e4]], dtype=F64)
    assert bool(tables.out_of_range(outside).all())
    torch.testing.assert_close(tables.lookup("epidermis", "R_plus", outside)[0, 0], tables.table("epidermis", "R_plus")[0, 0])
    with pytest.raises(ValueError, match="profiles"):
        tables.lookup("dermis", "T_plus", nodes)
    with pytest.raises(ValueError, match="wavelengths"):
        tables.lookup("epidermis", "R_plus", torch.ones(3, 2, dtype=F64))
