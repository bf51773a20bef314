"""The diffusion model's error (DWRR08 §3; Donner & Jensen 2005) against radiative transport must not grow
(docs/transport.md).

Two parts:

* the transport reference checks itself: the layer stacking built on iadpython reproduces a single
  slab split in two, and a small Monte Carlo agrees with it for two different layers;
* the regression guard: at the points of ``tests/data/transport_baseline.csv`` (written by
  ``pytest -m bench tests/bench/test_transport_chart.py``) the model's relative error against
  adding-doubling is recomputed and must satisfy |error now| ≤ |error at baseline| + 0.5 percentage
  points. The error itself is large in places (diffusion is an approximation): the guard only fails
  if a change of the model moves it further from transport. Re-run the bench to move the baseline
  after an intended change.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

pytest.importorskip("iadpython")

import transport_reference as ref

BASELINE = Path(__file__).resolve().parents[1] / "data" / "transport_baseline.csv"
#: Allowed growth of |relative error|, absolute (0.005 = 0.5 percentage points).
MARGIN = 0.005
#: The transport values must reproduce exactly (deterministic adding-doubling) up to round-off.
REFERENCE_RTOL = 1e-8

Layer = ref.Layer


def _baseline_rows() -> list[dict]:
    with BASELINE.open(newline="") as f:
        return list(csv.DictReader(f))


def _point_id(row: dict) -> str:
    where = f"sa={float(row['sigma_a_1_per_mm']):.3g}" if row["case"] == "single_slab" else row["label"]
    return f"{row['case']}-{row['quantity']}-{float(row['wavelength_nm']):.0f}nm-{row['source_depth']}-{where}"


@pytest.mark.parametrize("parts", [2, 4])
def test_stacked_halves_reproduce_the_slab(parts):
    """Equal parts stacked by ``adding_doubling_stack`` give iadpython's own single-slab result."""
    whole = Layer(0.5, 7.0, 0.25)
    slab = ref.adding_doubling_slab(whole)
    stack = ref.adding_doubling_stack([Layer(0.5, 7.0, 0.25 / parts)] * parts)
    assert stack.R_diffuse == pytest.approx(slab.R_diffuse, rel=1e-10)
    assert stack.T_diffuse == pytest.approx(slab.T_diffuse, rel=1e-10)
    assert stack.R_unscattered == pytest.approx(slab.R_unscattered, rel=1e-12)


def test_stacking_of_different_layers_agrees_with_monte_carlo():
    """Two different layers, both orders: adding-doubling within 4 Monte Carlo standard errors + 0.2%."""
    top, bottom = Layer(0.5, 7.0, 0.1), Layer(2.0, 3.0, 0.3)
    for layers in ([top, bottom], [bottom, top]):
        ad = ref.adding_doubling_stack(layers)
        mc = ref.monte_carlo(layers, photons=100_000, seed=3)
        assert abs(mc.R_diffuse - ad.R_diffuse) < 4.0 * mc.R_std_error + 2e-3 * ad.R_diffuse
        assert abs(mc.T_diffuse - ad.T_diffuse) < 4.0 * mc.T_std_error + 2e-3 * ad.T_diffuse
    # the order matters, so the check above would catch a stack added the wrong way round
    swapped = ref.adding_doubling_stack([bottom, top]).R_diffuse
    assert abs(ref.adding_doubling_stack([top, bottom]).R_diffuse - swapped) > 0.05


def _recompute(row: dict) -> tuple[float, float]:
    """(transport, diffusion) at a baseline point, both computed now."""
    case, depth, quantity = row["case"], row["source_depth"], row["quantity"]
    first = Layer(float(row["sigma_a_1_per_mm"]), float(row["sigma_s_prime_1_per_mm"]), float(row["thickness_1_mm"]))
    if case == "single_slab":
        ad = ref.adding_doubling_slab(first)
        r, t = ref.diffusion_slab(first, depth)
        return (ad.R_diffuse, r) if quantity == "R" else (ad.T_diffuse, t)
    second = Layer(float(row["sigma_a_2_per_mm"]), float(row["sigma_s_prime_2_per_mm"]), float(row["thickness_2_mm"]))
    if case == "skin_grid":
        return ref.adding_doubling_stack([first, second]).R_diffuse, ref.diffusion_two_layer(first, second, depth)
    if case == "skin_table2":
        c = ref.skin_row(row["label"], [float(row["wavelength_nm"])], depth)
        return float(c.transport[0]), float(c.diffusion[0])
    raise ValueError(f"{BASELINE.name}: unknown case {case!r}")


@pytest.mark.parametrize("row", _baseline_rows(), ids=_point_id)
def test_model_error_does_not_grow(row):
    """|diffusion / transport − 1| now ≤ its baseline value + MARGIN (0.5 percentage points)."""
    transport, diffusion = _recompute(row)
    if row["case"] != "skin_table2":  # Table 2 points take σa from the model's spectra, which may move
        assert transport == pytest.approx(float(row["reference"]), rel=REFERENCE_RTOL), "the transport reference moved"
    error_now = diffusion / transport - 1.0
    error_then = float(row["relative_error"])
    assert math.isfinite(error_now)
    assert abs(error_now) <= abs(error_then) + MARGIN, (
        f"diffusion's error against transport grew from {error_then:+.2%} to {error_now:+.2%} "
        f"(allowed: |error| up to {abs(error_then) + MARGIN:.2%})"
    )
