"""The diffusion model against radiative transport (run on demand: ``pytest -m bench tests/bench/test_transport_chart.py -s``).

Compares the model's diffuse reflectance (and, for one slab, transmittance) with adding-doubling
(iadpython, 16 quadrature points, g = 0 with σs = σs′) and writes, relative to the repository root:

- ``docs/data/transport_error.csv``: every number (comparisons and the reference's own checks);
- ``docs/figures/transport_single_slab.png``: one 0.25 mm slab in air (R and T, both source depths)
  and a half-space (dipole), error versus σa at the scattering of 400, 550 and 700 nm;
- ``docs/figures/transport_two_layer.png``: two-layer skin (indices matched), error versus wavelength
  for the Table 2 rows, and the four-point grid with a Monte Carlo cross-check;
- ``tests/data/transport_baseline.csv``: the few points ``tests/model/test_transport.py`` guards.

Relative error = diffusion / transport − 1 (positive: diffusion too bright). With ``-s`` the markdown
tables of ``docs/transport.md`` are printed.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("iadpython")

pytestmark = pytest.mark.bench

ROOT = Path(__file__).resolve().parents[2]
import transport_reference as ref  # noqa: E402 (tests/conftest.py puts tests/model on the path)

Layer = ref.Layer
SOURCE_DEPTHS = ("mean_free_path", "capped")
SLAB_WAVELENGTHS_NM = (400.0, 550.0, 700.0)
SLAB_SIGMA_A_PER_MM = np.geomspace(0.02, 80.0, 12)
SKIN_WAVELENGTHS_NM = tuple(float(w) for w in range(400, 701, 20))
GRID_EPIDERMIS_SIGMA_A = (0.5, 2.0)
GRID_DERMIS_SIGMA_A = (0.05, 0.2)
GRID_WAVELENGTH_NM = 550.0
MONTE_CARLO_PHOTONS = 1_000_000

COLUMNS = [
    "case", "label", "wavelength_nm", "source_depth", "quantity",
    "sigma_a_1_per_mm", "sigma_s_prime_1_per_mm", "thickness_1_mm",
    "sigma_a_2_per_mm", "sigma_s_prime_2_per_mm", "thickness_2_mm",
    "reference_method", "reference", "method", "value", "relative_error", "std_error",
]

#: Points the regression guard recomputes: (case, label, wavelength, source depth, quantity, σa₁).
#: σa₁ = None selects by label (two-layer rows).
BASELINE_POINTS = [
    ("single_slab", "", 400.0, "mean_free_path", "R", SLAB_SIGMA_A_PER_MM[4]),
    ("single_slab", "", 550.0, "mean_free_path", "R", SLAB_SIGMA_A_PER_MM[6]),
    ("single_slab", "", 700.0, "mean_free_path", "R", SLAB_SIGMA_A_PER_MM[0]),
    ("single_slab", "", 700.0, "mean_free_path", "T", SLAB_SIGMA_A_PER_MM[4]),
    ("single_slab", "", 700.0, "capped", "R", SLAB_SIGMA_A_PER_MM[4]),
    ("skin_grid", "epidermis 0.5 / dermis 0.05", 550.0, "mean_free_path", "R", None),
    ("skin_grid", "epidermis 2 / dermis 0.2", 550.0, "mean_free_path", "R", None),
    ("skin_table2", "I interior", 560.0, "mean_free_path", "R", None),
    ("skin_table2", "V exterior", 420.0, "mean_free_path", "R", None),
    ("skin_table2", "IV exterior", 700.0, "capped", "R", None),
]


def _scattering(wavelength_nm) -> tuple[np.ndarray, np.ndarray]:
    """σs′ of epidermis and dermis (mm⁻¹) from the model's Eq. 13, ``(L,)`` each."""
    import torch

    from skinlayers.model import ModelSettings, chromophore_spectra

    spectra = chromophore_spectra(torch.tensor(list(wavelength_nm), dtype=torch.float64), ModelSettings().optics)
    return spectra.scattering_epidermis.numpy(), spectra.scattering_dermis.numpy()


def _row(case, label, wavelength_nm, source_depth, quantity, layers, reference_method, reference, method, value,
         std_error=None) -> dict:
    second = layers[1] if len(layers) > 1 else Layer(float("nan"), float("nan"), float("nan"))
    return {
        "case": case, "label": label, "wavelength_nm": wavelength_nm, "source_depth": source_depth,
        "quantity": quantity,
        "sigma_a_1_per_mm": layers[0].sigma_a_per_mm, "sigma_s_prime_1_per_mm": layers[0].sigma_s_per_mm,
        "thickness_1_mm": layers[0].thickness_mm,
        "sigma_a_2_per_mm": second.sigma_a_per_mm, "sigma_s_prime_2_per_mm": second.sigma_s_per_mm,
        "thickness_2_mm": second.thickness_mm,
        "reference_method": reference_method, "reference": reference, "method": method, "value": value,
        "relative_error": value / reference - 1.0, "std_error": std_error,
    }


def _reference_checks() -> list[dict]:
    """The transport reference against itself and a Monte Carlo: split slab, stacking, quadrature, depth."""
    rows = []
    whole = Layer(0.5, 7.0, 0.25)
    slab = ref.adding_doubling_slab(whole)
    for parts in (1, 2, 5):
        stack = ref.adding_doubling_stack([Layer(0.5, 7.0, 0.25 / parts)] * parts)
        for q, a, b in (("R", slab.R_diffuse, stack.R_diffuse), ("T", slab.T_diffuse, stack.T_diffuse)):
            rows.append(_row("check_split_slab", f"{parts} equal parts", "", "", q, [whole],
                             "adding-doubling Sample.rt", a, f"adding-doubling stack of {parts}", b))
    for layers in ([Layer(0.5, 7.0, 0.1), Layer(2.0, 3.0, 0.3)], [Layer(2.0, 3.0, 0.3), Layer(0.5, 7.0, 0.1)],
                   [Layer(0.5, 6.08, 0.25), Layer(0.05, 3.04, 2.0)]):
        ad = ref.adding_doubling_stack(layers)
        mc = ref.monte_carlo(layers, photons=MONTE_CARLO_PHOTONS, seed=1)
        label = " on ".join(f"({la.sigma_a_per_mm:g}, {la.sigma_s_per_mm:g}, {la.thickness_mm:g} mm)" for la in layers)
        rows.append(_row("check_monte_carlo", label, "", "", "R", layers, "adding-doubling stack", ad.R_diffuse,
                         "Monte Carlo", mc.R_diffuse, mc.R_std_error))
        rows.append(_row("check_monte_carlo", label, "", "", "T", layers, "adding-doubling stack", ad.T_diffuse,
                         "Monte Carlo", mc.T_diffuse, mc.T_std_error))
    for layer in (Layer(0.05, 4.4, 0.25), Layer(2.0, 6.08, 0.25), Layer(20.0, 12.5, 0.25)):
        fine = ref.adding_doubling_slab(layer, quad_points=64)
        coarse = ref.adding_doubling_slab(layer)
        rows.append(_row("check_quadrature", "16 vs 64 points", "", "", "R", [layer], "adding-doubling 64 points",
                         fine.R_diffuse, "adding-doubling 16 points", coarse.R_diffuse))
    for sa_derm in (0.02, 0.05):
        deep = ref.adding_doubling_stack([Layer(0.5, 4.4, 0.25), Layer(sa_derm, 2.2, 1000.0)])
        for depth in (20.0, ref.DERMIS_MM):
            layers = [Layer(0.5, 4.4, 0.25), Layer(sa_derm, 2.2, depth)]
            rows.append(_row("check_dermis_thickness", f"{depth:g} mm vs 1000 mm", "", "", "R", layers,
                             "adding-doubling, dermis 1000 mm", deep.R_diffuse, f"adding-doubling, dermis {depth:g} mm",
                             ref.adding_doubling_stack(layers).R_diffuse))
    return rows


def _versus_transport(case, label, wavelength_nm, source_depth, quantity, layers, transport, diffusion) -> dict:
    return _row(case, label, wavelength_nm, source_depth, quantity, layers, "adding-doubling", transport,
                "diffusion", diffusion)


def _single_slab() -> list[dict]:
    rows = []
    s_epi, s_derm = _scattering(SLAB_WAVELENGTHS_NM)
    for wl, ss_epi, ss_derm in zip(SLAB_WAVELENGTHS_NM, s_epi, s_derm):
        for sa in SLAB_SIGMA_A_PER_MM:
            slab = Layer(float(sa), float(ss_epi), ref.EPIDERMIS_MM)
            ad = ref.adding_doubling_slab(slab)
            for depth in SOURCE_DEPTHS:
                r, t = ref.diffusion_slab(slab, depth)
                rows.append(_versus_transport("single_slab", "", wl, depth, "R", [slab], ad.R_diffuse, r))
                rows.append(_versus_transport("single_slab", "", wl, depth, "T", [slab], ad.T_diffuse, t))
            half = Layer(float(sa), float(ss_derm), ref.DERMIS_MM)
            rows.append(_versus_transport("semi_infinite", "", wl, "", "R", [half],
                                          ref.adding_doubling_slab(half).R_diffuse, ref.diffusion_semi_infinite(half)))
    for sa in (0.05, 2.0):  # the project's own check points (σs′ = 7 mm⁻¹; docs/transport.md)
        slab = Layer(sa, 7.0, ref.EPIDERMIS_MM)
        rows.append(_versus_transport("single_slab_sigma_s_7", "", "", "mean_free_path", "R", [slab],
                                      ref.adding_doubling_slab(slab).R_diffuse, ref.diffusion_slab(slab)[0]))
    return rows


def _skin() -> list[dict]:
    from skinlayers.model import TABLE2

    rows = []
    for label in TABLE2:
        for depth in SOURCE_DEPTHS:
            c = ref.skin_row(label, SKIN_WAVELENGTHS_NM, depth)
            for i, wl in enumerate(SKIN_WAVELENGTHS_NM):
                layers = [
                    Layer(float(c.sigma_a_epidermis_per_mm[i]), float(c.sigma_s_prime_epidermis_per_mm[i]), ref.EPIDERMIS_MM),
                    Layer(float(c.sigma_a_dermis_per_mm[i]), float(c.sigma_s_prime_dermis_per_mm[i]), ref.DERMIS_MM),
                ]
                rows.append(_versus_transport("skin_table2", label, wl, depth, "R", layers,
                                              float(c.transport[i]), float(c.diffusion[i])))
    s_epi, s_derm = (float(v[0]) for v in _scattering([GRID_WAVELENGTH_NM]))
    for sa_epi in GRID_EPIDERMIS_SIGMA_A:
        for sa_derm in GRID_DERMIS_SIGMA_A:
            layers = [Layer(sa_epi, s_epi, ref.EPIDERMIS_MM), Layer(sa_derm, s_derm, ref.DERMIS_MM)]
            label = f"epidermis {sa_epi:g} / dermis {sa_derm:g}"
            ad = ref.adding_doubling_stack(layers).R_diffuse
            for depth in SOURCE_DEPTHS:
                rows.append(_versus_transport("skin_grid", label, GRID_WAVELENGTH_NM, depth, "R", layers, ad,
                                              ref.diffusion_two_layer(layers[0], layers[1], depth)))
            mc = ref.monte_carlo(layers, photons=MONTE_CARLO_PHOTONS, seed=2)
            rows.append(_row("skin_grid", label, GRID_WAVELENGTH_NM, "mean_free_path", "R", layers, "Monte Carlo",
                             mc.R_diffuse, "diffusion", ref.diffusion_two_layer(layers[0], layers[1]), mc.R_std_error))
    return rows


@pytest.fixture(scope="module")
def results() -> dict[str, list[dict]]:
    return {"checks": _reference_checks(), "single": _single_slab(), "skin": _skin()}


def _write_csv(path: Path, rows: list[dict], digits: int = 10) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: "" if v is None else f"{v:.{digits}g}" if isinstance(v, float) else v for k, v in r.items()})
    print(f"\nwrote {path.relative_to(ROOT)} ({len(rows)} rows)")


def test_reference_is_consistent(results):
    """Split slabs reproduce the slab (to 1e-5: parts not a power-of-two fraction start the doubling from
    a different thin layer); the Monte Carlo agrees within 4 standard errors plus 0.2%."""
    for r in results["checks"]:
        if r["case"] == "check_split_slab":
            assert abs(r["relative_error"]) < 1e-5, r
        elif r["case"] == "check_monte_carlo":
            assert abs(r["value"] - r["reference"]) < 4.0 * r["std_error"] + 2e-3 * r["reference"], r
        elif r["case"] == "check_quadrature":
            assert abs(r["relative_error"]) < 1e-3, r
        elif r["case"] == "check_dermis_thickness" and r["thickness_2_mm"] == ref.DERMIS_MM:
            assert abs(r["relative_error"]) < 1e-8, r
    print("\n| check | case | reference | compared | relative difference |\n|---|---|---|---|---|")
    for r in results["checks"]:
        se = f" ± {r['std_error'] / r['reference'] * 100:.2f}%" if r["std_error"] else ""
        print(f"| {r['case']} {r['quantity']} | {r['label']} | {r['reference_method']}: {r['reference']:.5f} | "
              f"{r['method']}: {r['value']:.5f} | {r['relative_error'] * 100:+.2g}%{se} |")


def test_write_error_table(results):
    """All rows to docs/data/transport_error.csv; with -s, the markdown tables of docs/transport.md."""
    _write_csv(ROOT / "docs" / "transport_error.csv", results["checks"] + results["single"] + results["skin"])
    single = [r for r in results["single"] if r["case"] == "single_slab"]
    for q in ("R", "T"):
        print(f"\nSingle slab, diffuse {q}: relative error (%) of diffusion (mean free path / capped)")
        print("| σa (mm⁻¹) | " + " | ".join(f"{w:.0f} nm (σs′ {r['sigma_s_prime_1_per_mm']:.2f})" for w, r in zip(
            SLAB_WAVELENGTHS_NM, [next(x for x in single if x["wavelength_nm"] == w) for w in SLAB_WAVELENGTHS_NM])) + " |")
        print("|---|" + "---|" * len(SLAB_WAVELENGTHS_NM))
        for sa in SLAB_SIGMA_A_PER_MM:
            cells = []
            for wl in SLAB_WAVELENGTHS_NM:
                e = {r["source_depth"]: r for r in single if r["wavelength_nm"] == wl and r["quantity"] == q
                     and r["sigma_a_1_per_mm"] == sa}
                cells.append(f"{e['mean_free_path']['relative_error'] * 100:+.1f} / {e['capped']['relative_error'] * 100:+.1f}"
                             f" (AD {e['mean_free_path']['reference']:.4f})")
            print(f"| {sa:.3g} | " + " | ".join(cells) + " |")
    half = [r for r in results["single"] if r["case"] == "semi_infinite"]
    print("\nHalf-space (dipole), diffuse R: relative error (%)")
    print("| σa (mm⁻¹) | " + " | ".join(f"σs′ {r['sigma_s_prime_1_per_mm']:.2f}" for r in half[:: len(SLAB_SIGMA_A_PER_MM)]) + " |")
    print("|---|" + "---|" * len(SLAB_WAVELENGTHS_NM))
    for k, sa in enumerate(SLAB_SIGMA_A_PER_MM):
        print(f"| {sa:.3g} | " + " | ".join(
            f"{r['relative_error'] * 100:+.1f} (AD {r['reference']:.4f})" for r in half[k:: len(SLAB_SIGMA_A_PER_MM)]) + " |")
    for r in results["single"]:
        if r["case"] == "single_slab_sigma_s_7":
            print(f"σs′ = 7, σa = {r['sigma_a_1_per_mm']:g}: AD {r['reference']:.4f}, diffusion {r['value']:.4f}, "
                  f"{r['relative_error'] * 100:+.1f}%")
    table2 = [r for r in results["skin"] if r["case"] == "skin_table2"]
    print("\nTable 2 rows, diffuse R: relative error (%) over 400–700 nm")
    print("| row | mean free path: min | max | mean abs | at 400 / 560 / 700 nm | capped: min | max | mean abs |\n"
          "|---|---|---|---|---|---|---|---|")
    for label in dict.fromkeys(r["label"] for r in table2):
        e = {d: [r for r in table2 if r["label"] == label and r["source_depth"] == d] for d in SOURCE_DEPTHS}
        m = [r["relative_error"] * 100 for r in e["mean_free_path"]]
        c = [r["relative_error"] * 100 for r in e["capped"]]
        at = {r["wavelength_nm"]: r["relative_error"] * 100 for r in e["mean_free_path"]}
        print(f"| {label} | {min(m):+.1f} | {max(m):+.1f} | {np.mean(np.abs(m)):.1f} | "
              f"{at[400.0]:+.1f} / {at[560.0]:+.1f} / {at[700.0]:+.1f} | "
              f"{min(c):+.1f} | {max(c):+.1f} | {np.mean(np.abs(c)):.1f} |")
    print("\nGrid at 550 nm (σs′ epidermis / dermis as in the model)")
    print("| σa epidermis | σa dermis | AD | MC | diffusion | vs AD | vs MC | capped vs AD |\n|---|---|---|---|---|---|---|---|")
    grid = [r for r in results["skin"] if r["case"] == "skin_grid"]
    for label in dict.fromkeys(r["label"] for r in grid):
        g = [r for r in grid if r["label"] == label]
        ad = next(r for r in g if r["reference_method"] == "adding-doubling" and r["source_depth"] == "mean_free_path")
        cap = next(r for r in g if r["source_depth"] == "capped")
        mc = next(r for r in g if r["reference_method"] == "Monte Carlo")
        print(f"| {ad['sigma_a_1_per_mm']:g} | {ad['sigma_a_2_per_mm']:g} | {ad['reference']:.4f} | "
              f"{mc['reference']:.4f} ± {mc['std_error']:.4f} | {ad['value']:.4f} | {ad['relative_error'] * 100:+.1f}% | "
              f"{mc['relative_error'] * 100:+.1f}% | {cap['relative_error'] * 100:+.1f}% |")


def test_write_baseline(results):
    """The guard's points, with the transport value and the model's error they had at this run."""
    rows = []
    every = results["single"] + results["skin"]
    for case, label, wl, depth, quantity, sigma_a in BASELINE_POINTS:
        match = [r for r in every if r["case"] == case and r["label"] == label and r["wavelength_nm"] == wl
                 and r["source_depth"] == depth and r["quantity"] == quantity and r["reference_method"] == "adding-doubling"
                 and (sigma_a is None or r["sigma_a_1_per_mm"] == sigma_a)]
        assert len(match) == 1, (case, label, wl, depth, quantity, sigma_a)
        rows.append(match[0])
    _write_csv(ROOT / "tests" / "data" / "transport_baseline.csv", rows, digits=17)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def test_single_slab_figure(results):
    plt = _pyplot()
    single = [r for r in results["single"] if r["case"] == "single_slab"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), sharex=True)
    colours = dict(zip(SLAB_WAVELENGTHS_NM, ("tab:blue", "tab:green", "tab:red")))
    for ax, q in zip(axes, ("R", "T")):
        for wl in SLAB_WAVELENGTHS_NM:
            for depth, style in zip(SOURCE_DEPTHS, ("o-", "s--")):
                pts = [r for r in single if r["wavelength_nm"] == wl and r["quantity"] == q and r["source_depth"] == depth]
                ss = pts[0]["sigma_s_prime_1_per_mm"]
                ax.plot([r["sigma_a_1_per_mm"] for r in pts], [r["relative_error"] * 100 for r in pts], style,
                        color=colours[wl], ms=3.5, lw=1.4 if depth == "mean_free_path" else 1.0,
                        label=f"{wl:.0f} nm, σs′ {ss:.1f} mm⁻¹" + ("" if depth == "mean_free_path" else ", capped ℓ"))
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("σa (mm⁻¹)")
        ax.set_ylabel(f"diffuse {q}: diffusion / transport − 1 (%)")
        ax.set_title(f"0.25 mm slab (multipole), diffuse {q}", fontsize=9)
        ax.grid(alpha=0.3)
    axes[1].set_ylim(-105, 180)
    axes[1].legend(fontsize=7, loc="upper right")
    half = [r for r in results["single"] if r["case"] == "semi_infinite"]
    ax = axes[2]
    for wl in SLAB_WAVELENGTHS_NM:
        pts = [r for r in half if r["wavelength_nm"] == wl]
        ax.plot([r["sigma_a_1_per_mm"] for r in pts], [r["relative_error"] * 100 for r in pts], "o-", color=colours[wl],
                ms=3.5, label=f"σs′ {pts[0]['sigma_s_prime_1_per_mm']:.1f} mm⁻¹ (dermis at {wl:.0f} nm)")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("σa (mm⁻¹)")
    ax.set_ylabel("diffuse R: diffusion / transport − 1 (%)")
    ax.set_title("half-space (dipole; transport: 50 mm), diffuse R", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    fig.suptitle("n = 1.40 in air, normal incidence: diffusion vs adding-doubling (g = 0, σs = σs′)", fontsize=10)
    fig.tight_layout()
    path = ROOT / "docs" / "figures" / "transport_single_slab.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def test_two_layer_figure(results):
    plt = _pyplot()
    table2 = [r for r in results["skin"] if r["case"] == "skin_table2"]
    grid = [r for r in results["skin"] if r["case"] == "skin_grid"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.4), gridspec_kw={"width_ratios": [1.6, 1]})
    labels = list(dict.fromkeys(r["label"] for r in table2))
    cmap = plt.get_cmap("viridis")
    for k, label in enumerate(labels):
        for depth, style in zip(SOURCE_DEPTHS, ("-", ":")):
            pts = [r for r in table2 if r["label"] == label and r["source_depth"] == depth]
            ax.plot([r["wavelength_nm"] for r in pts], [r["relative_error"] * 100 for r in pts], style,
                    color=cmap(k / (len(labels) - 1)), lw=1.5 if depth == "mean_free_path" else 1.0,
                    label=label if depth == "mean_free_path" else None)
    ax.plot([], [], ":", color="0.3", label="capped ℓ (dotted)")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("diffuse R: diffusion / transport − 1 (%)")
    ax.set_title("Table 2 rows (matched indices, no interface absorber)", fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    names = list(dict.fromkeys(r["label"] for r in grid))
    x = np.arange(len(names))
    for offset, (method, depth, colour) in zip((-0.25, 0.0, 0.25), (("adding-doubling", "mean_free_path", "tab:blue"),
                                                                   ("Monte Carlo", "mean_free_path", "tab:orange"),
                                                                   ("adding-doubling", "capped", "tab:gray"))):
        pts = [next(r for r in grid if r["label"] == n and r["reference_method"] == method and r["source_depth"] == depth)
               for n in names]
        err = [r["std_error"] / r["reference"] * 100 if r["std_error"] else 0.0 for r in pts]
        name = {"adding-doubling": "vs adding-doubling", "Monte Carlo": "vs Monte Carlo (±1 s.e.)"}[method]
        bx.bar(x + offset, [r["relative_error"] * 100 for r in pts], 0.25, yerr=err, color=colour,
               label=name + (", capped ℓ" if depth == "capped" else ""))
    bx.set_xticks(x, [n.replace(" / ", "\n") for n in names], fontsize=7.5)
    bx.set_ylabel("diffuse R: diffusion / transport − 1 (%)")
    bx.set_title(f"σa grid (mm⁻¹) at σs′ of {GRID_WAVELENGTH_NM:.0f} nm", fontsize=9)
    bx.legend(fontsize=7)
    bx.grid(alpha=0.3, axis="y")
    fig.suptitle("Two-layer skin: 0.25 mm epidermis on a semi-infinite dermis (transport: 50 mm), n = 1.40", fontsize=10)
    fig.tight_layout()
    path = ROOT / "docs" / "figures" / "transport_two_layer.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
