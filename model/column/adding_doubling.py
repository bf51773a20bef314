"""The transport tables' builder: adding-doubling (Prahl's ``iadpython``) computes the slab, half-space and
hand-over tables that ``layer_totals`` reads (their axes, files and meaning: ``layer_totals``' docstring).

Offline only: ``python -m skinlayers.model.column.adding_doubling`` regenerates the package's tables (its time:
docs/transport.md, "From model/column/layer_totals.py") and needs the ``test`` extra (iadpython). The
exact adding-doubling totals here are also the truths the tables are tested against
(tests/model/test_transport_profiles.py).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from .layer_totals import (
    HALF_SPACE_COLUMNS,
    HALF_SPACE_FILE,
    HALF_SPACE_OPTICAL_THICKNESS,
    HANDOVER_FILE,
    HANDOVER_NEGLIGIBLE,
    HANDOVER_X_GRID,
    HANDOVER_Y_GRID,
    QUAD_POINTS,
    SLAB_COLUMNS,
    SLAB_FILE,
    TABLE_N_ABOVE,
    TABLE_N_LAYER,
    X_GRID,
    Y_GRID,
    clear_caches,
)

__all__ = ["adding_doubling_half_space", "adding_doubling_slab", "adding_doubling_two_layers", "build", "build_handover",
           "main"]


def _layer_matrices(albedo: float, optical_thickness: float, n_layer: float, n_above: float):
    import iadpython  # noqa: PLC0415 (adding-doubling builds tables offline; iadpython is a test dependency)
    from iadpython.combine import simple_single_layer_matrices  # noqa: PLC0415 (as above)

    sample = iadpython.Sample(a=albedo, b=optical_thickness, g=0.0, d=1.0, n=n_layer, n_above=n_above,
                              n_below=n_above, quad_pts=QUAD_POINTS)
    sample.update_quadrature()
    sample.b_thinnest = None
    r, t = simple_single_layer_matrices(sample)
    return sample, r, t


def adding_doubling_slab(albedo: float, optical_thickness: float, n_layer: float = TABLE_N_LAYER,
                         n_above: float = TABLE_N_ABOVE) -> tuple[float, float, float, float]:
    """(R⁺, T⁺ diffuse, R⁻, T⁻) per unit entering power of a slab under a smooth boundary, matched below.

    iadpython's matrices R_ij carry the flux weights 2ν_i w_i of its quadrature: a Lambertian
    incidence of unit flux inside the slab is the weight vector itself, light leaving into air exists
    only above the critical cosine (the rows beyond it), the matched side takes every row.
    """
    from iadpython.combine import add_slide_above  # noqa: PLC0415 (as above)
    from iadpython.start import boundary_layer  # noqa: PLC0415 (as above)

    sample, r, t = _layer_matrices(albedo, optical_thickness, n_layer, n_above)
    r01, r10, t01, t10 = boundary_layer(sample, top=True)
    r02, r20, t02, t20 = add_slide_above(sample, r01, r10, t01, t10, r, r, t, t)
    w = sample.twonuw
    k = int(np.min(np.where(sample.nu > sample.nu_c())))
    specular = ((n_layer - n_above) / (n_layer + n_above)) ** 2
    entering = 1.0 - specular
    r_plus = (float(w[k:] @ r02[k:, -1]) - specular) / entering
    t_plus = float(w @ t02[:, -1]) / entering - math.exp(-optical_thickness)
    r_minus = float(w @ r20 @ w)
    t_minus = float(w[k:] @ t20[k:, :] @ w)
    return r_plus, t_plus, r_minus, t_minus


def adding_doubling_half_space(albedo: float, n_layer: float = TABLE_N_LAYER) -> tuple[float, float]:
    """(R collimated, R Lambertian) of a half-space, index-matched above (no boundary)."""
    sample, r, _ = _layer_matrices(albedo, HALF_SPACE_OPTICAL_THICKNESS, n_layer, TABLE_N_ABOVE)
    w = sample.twonuw
    return float(w @ r[:, -1]), float(w @ r @ w)


def _slab_under_boundary(albedo: float, optical_thickness: float, n_layer: float, n_above: float):
    """The slab's matrices with the boundary above it (both directions) and the quadrature's sample."""
    from iadpython.combine import add_slide_above  # noqa: PLC0415 (as above)
    from iadpython.start import boundary_layer  # noqa: PLC0415 (as above)

    sample, r, t = _layer_matrices(albedo, optical_thickness, n_layer, n_above)
    r01, r10, t01, t10 = boundary_layer(sample, top=True)
    return sample, add_slide_above(sample, r01, r10, t01, t10, r, r, t, t)


def _half_space(albedo: float, n_layer: float, n_above: float):
    """The half-space's matrices (r, t) on the slab's quadrature, and its R_c and R_d."""
    sample, r, t = _layer_matrices(albedo, HALF_SPACE_OPTICAL_THICKNESS, n_layer, n_above)
    w = sample.twonuw
    return r, t, float(w @ r[:, -1]), float(w @ r @ w)


def _stack_total(sample, slab_under_boundary, half_space, n_layer: float, n_above: float) -> float:
    """R of the slab (under its boundary) on the half-space, added angle by angle: normal collimated
    light, per unit power entering, specular excluded."""
    from iadpython.combine import add_layers  # noqa: PLC0415 (as above)

    r02, r20, t02, t20 = slab_under_boundary
    r, t = half_space[:2]
    r03, _, _, _ = add_layers(sample, r02, r20, t02, t20, r, r, t, t)
    w = sample.twonuw
    k = int(np.min(np.where(sample.nu > sample.nu_c())))
    specular = ((n_layer - n_above) / (n_layer + n_above)) ** 2
    return (float(w[k:] @ r03[k:, -1]) - specular) / (1.0 - specular)


def _scalar_handover(stack: float, slab: tuple[float, float, float, float], optical_thickness: float, half_space) -> float:
    """κ from the stack's total and the layers' own: R = R⁺ + T⁺ κR_d T⁻ / (1 − R⁻ κR_d) solved for κ."""
    r_plus, t_diffuse, r_minus, t_minus = slab
    r_c, r_d = half_space[2], half_space[3]
    t_plus = t_diffuse + (r_c / r_d) * math.exp(-optical_thickness)
    if t_plus * t_minus * r_d < HANDOVER_NEGLIGIBLE:
        return 1.0  # the series carries nothing (an opaque epidermis or a black dermis): any κ will do
    rest = stack - r_plus
    return rest / (r_d * (t_plus * t_minus + rest * r_minus))


def _slab_parts(x_epidermis: float, y_epidermis: float, n_layer: float, n_above: float):
    ratio = 10.0**x_epidermis
    albedo, tau = 1.0 / (1.0 + ratio), (10.0**y_epidermis) * (1.0 + ratio)
    sample, under = _slab_under_boundary(albedo, tau, n_layer, n_above)
    return sample, under, adding_doubling_slab(albedo, tau, n_layer, n_above), tau


def adding_doubling_two_layers(x_epidermis: float, y_epidermis: float, x_dermis: float, n_layer: float = TABLE_N_LAYER,
                               n_above: float = TABLE_N_ABOVE) -> float:
    """The two layers' total R by adding-doubling alone (the slab under its boundary on the half-space,
    angle by angle; the truth the hand-over table is made to match), at similarity coordinates."""
    sample, under, _, _ = _slab_parts(x_epidermis, y_epidermis, n_layer, n_above)
    return _stack_total(sample, under, _half_space(1.0 / (1.0 + 10.0**x_dermis), n_layer, n_above), n_layer, n_above)


def build_handover(folder: Path, n_layer: float = TABLE_N_LAYER, n_above: float = TABLE_N_ABOVE) -> None:
    """Compute the hand-over factors κ(x₁, y₁, x₂) by adding-doubling into ``folder``."""
    import iadpython  # noqa: PLC0415 (adding-doubling builds tables offline; iadpython is a test dependency)

    halves = {float(x2): _half_space(1.0 / (1.0 + 10.0**x2), n_layer, n_above) for x2 in HANDOVER_X_GRID}
    with (folder / HANDOVER_FILE).open("w") as f:
        f.write(
            f"# indices: n_layer {n_layer} n_above {n_above}\n"
            "# The layers' hand-over factor kappa: with the slab's and the half-space's transport totals (R+, T+ = T_diffuse\n"
            "#   + (R_c / R_d) T_c, R-, T-, R_d), R = R+ + T+ kappa R_d T- / (1 - R- kappa R_d) is the total R of the slab\n"
            "#   (index n_layer under n_above) on a half-space of the same index, stacked angle by angle by adding-doubling.\n"
            "# x = log10(sigma_a / sigma_s') of each layer, y = log10(sigma_s' * thickness) of the slab; kappa dimensionless.\n"
            f"# Computed by this project (skinlayers.model.column.adding_doubling.build_handover) with iadpython {iadpython.__version__},\n"
            f"#   {QUAD_POINTS} quadrature points, isotropic scattering (g = 0) with sigma_s = sigma_s'.\n"
            "# Regenerate: python -m skinlayers.model.column.adding_doubling (needs the test extra: iadpython).\n"
        )
        f.write("x_epidermis,y_epidermis,x_dermis,handover\n")
        for x1 in HANDOVER_X_GRID:
            for y1 in HANDOVER_Y_GRID:
                sample, under, slab, tau = _slab_parts(float(x1), float(y1), n_layer, n_above)
                for x2 in HANDOVER_X_GRID:
                    half = halves[float(x2)]
                    kappa = _scalar_handover(_stack_total(sample, under, half, n_layer, n_above), slab, tau, half)
                    f.write(f"{x1:.2f},{y1:.2f},{x2:.2f},{kappa:.8f}\n")
    clear_caches()


def build(folder: Path, n_layer: float = TABLE_N_LAYER, n_above: float = TABLE_N_ABOVE) -> None:
    """Compute the three tables by adding-doubling and write them into ``folder`` (the package's data)."""
    import iadpython  # noqa: PLC0415 (adding-doubling builds tables offline; iadpython is a test dependency)

    start = time.perf_counter()
    ratio = 10.0**X_GRID
    albedo = 1.0 / (1.0 + ratio)
    source = (
        f"# Computed by this project (skinlayers.model.column.adding_doubling.build) with iadpython {iadpython.__version__} "
        f"adding-doubling (S. Prahl), {QUAD_POINTS} quadrature points,\n"
        "#   isotropic scattering (g = 0) with sigma_s = sigma_s' (the similarity case the diffusion model rests on).\n"
        "# x = log10(sigma_a / sigma_s'); totals are dimensionless, per unit power entering the layer.\n"
        "# Regenerate: python -m skinlayers.model.column.adding_doubling (needs the test extra: iadpython).\n"
    )
    with (folder / SLAB_FILE).open("w") as f:
        f.write(
            f"# indices: n_layer {n_layer} n_above {n_above}\n"
            f"# Transport totals of a slab of index {n_layer} under a medium of index {n_above}, index-matched below.\n"
            "# y = log10(sigma_s' * thickness). R_plus: normal collimated light from above (specular excluded);\n"
            "#   T_plus_diffuse: its scattered part into the medium below (the unscattered exp(-(sigma_a + sigma_s') d)\n"
            "#   excluded); R_minus, T_minus: Lambertian light from below (T_minus leaves above).\n" + source
        )
        f.write("x,y," + ",".join(SLAB_COLUMNS) + "\n")
        for i, x in enumerate(X_GRID):
            for y in Y_GRID:
                tau = (10.0**y) * (1.0 + ratio[i])
                values = adding_doubling_slab(float(albedo[i]), float(tau), n_layer, n_above)
                f.write(f"{x:.2f},{y:.2f}," + ",".join(f"{max(v, 0.0):.10e}" for v in values) + "\n")
    with (folder / HALF_SPACE_FILE).open("w") as f:
        f.write(
            f"# Transport totals of a half-space of index {n_layer}, index-matched above (no boundary);\n"
            f"#   a slab of optical thickness {HALF_SPACE_OPTICAL_THICKNESS:g} stands in for it.\n"
            "# R_collimated: normal collimated light; R_diffuse: Lambertian light.\n" + source
        )
        f.write("x," + ",".join(HALF_SPACE_COLUMNS) + "\n")
        for i, x in enumerate(X_GRID):
            values = adding_doubling_half_space(float(albedo[i]), n_layer)
            f.write(f"{x:.2f}," + ",".join(f"{v:.10e}" for v in values) + "\n")
    clear_caches()
    build_handover(folder, n_layer, n_above)
    print(f"wrote {folder / SLAB_FILE}, {folder / HALF_SPACE_FILE} and {folder / HANDOVER_FILE} "
          f"in {time.perf_counter() - start:.0f} s")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate the transport layer-total and hand-over tables (adding-doubling).")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "data")
    parser.add_argument("--n-layer", type=float, default=TABLE_N_LAYER)
    parser.add_argument("--n-above", type=float, default=TABLE_N_ABOVE)
    args = parser.parse_args(argv)
    build(args.out, args.n_layer, args.n_above)


if __name__ == "__main__":
    main()
