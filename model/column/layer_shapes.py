"""Layer profile *shapes* from radiative transport: how far from its entry point each layer returns or
passes its light, tabulated by similarity from the project's Monte Carlo (the ``transport`` choice of
``ModelSettings.profiles``, with the totals of ``layer_totals``).

Diffusion's shapes put too little light near the entry point and too much far from it, and under the
7.5-mm window that tilts the bands against each other, which the fit reads as blood (measurements:
docs/transport.md, "The layers' shapes from the Monte Carlo" and "From model/column/layer_shapes.py").
Transport's shapes of a homogeneous layer depend on the albedo and the optical thickness alone once
lengths are measured in units of 1/σt′, so tables over

    x = log10(σa / σs′),    y = log10(σs′ d)   (the half-space: x alone),    ξ = |lateral offset| · σt′

serve every wavelength, scattering law and thickness. What is tabulated is the **line spread**: the
share of a point source's exitance that leaves at a lateral offset (along one axis, the other
integrated out) within each bin of ξ, both sides folded together, normalised to 1. A sum of
Gaussians fits its line spread exactly as it fits its radial profile (each 2-D Gaussian's marginal
is the 1-D Gaussian of the same variance), and the line spread is what an edge or a stripe shows.
The bins are exact sums of the Monte Carlo's tally columns, so a Gaussian's share of a bin is
closed form (differences of erf) and the fit interpolates nothing.

What each shape is the shape of (the same light as ``layer_totals``' totals, per unit power entering):

* the epidermis slab, index 1.40 under air, index-matched below: R⁺ and T⁺ (scattered part) for a
  normal collimated beam from above; R⁻ and T⁻ for Lambertian light from below (R⁻ and T⁻ include the
  light that crosses without scattering, reflected at or transmitted through the surface, as the
  adding-doubling totals do: in closed form, by quadrature over the angle).
* the half-space (the dermis), index 1.38 under the epidermis's 1.40, lit by Lambertian light from
  the epidermis (refracted, Fresnel-weighted): what the epidermis hands it.

The Monte Carlo is ``model.transport.walk`` (isotropic scattering with σs = σs′, as the totals), on a
row of tally columns 0.0025/σt′ wide out to ±200/σt′, every exit counted in its column
(``across_y``). ``python -m skinlayers.model.column.layer_shapes`` regenerates the tables (its time:
docs/transport.md, "From model/column/layer_shapes.py"); reading them needs nothing but numpy and torch.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import math
import time
from importlib.resources import files
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import nnls
from scipy.special import erf

from .layer_totals import read_table

__all__ = [
    "HALF_SPACE_X",
    "SLAB_PROFILES",
    "SLAB_X",
    "SLAB_Y",
    "fit_line_spread_weights",
    "half_space_shape",
    "shape_edges",
    "shapes_digest",
    "slab_shapes",
    "shape_transforms",
]

#: Tally columns in units of 1/σt′, and how many on each side of the source (reach: 200/σt′).
PIXEL = 0.0025
HALF_PIXELS = 80_000
#: Bins: column groups |i| in [start_b, start_{b+1}), geometric beyond the first few columns.
N_BIN_STARTS = 110
#: Similarity nodes; outside them the end shapes hold.
HALF_SPACE_X = np.round(np.arange(-3.0, 2.0 + 1e-9, 0.25), 6)
SLAB_X = np.round(np.arange(-3.0, 2.0 + 1e-9, 0.5), 6)
SLAB_Y = np.round(np.arange(-1.0, 1.0 + 1e-9, 0.25), 6)
SLAB_PROFILES = ("R_plus", "T_plus", "R_minus", "T_minus")
#: Indices the shapes are walked with (the defaults of ``ModelSettings.optics``; the totals' check holds to them).
N_ABOVE, N_EPIDERMIS, N_DERMIS = 1.0, 1.40, 1.38
PHOTONS_HALF_SPACE, PHOTONS_SLAB = 500_000, 300_000
#: The fit weights bins by 1/max(share, this): relative errors, but MC noise in near-empty bins ignored.
SHARE_FLOOR = 1e-5

SLAB_FILE, HALF_SPACE_FILE = "transport_slab_shapes.csv", "transport_half_space_shapes.csv"


@functools.lru_cache(maxsize=None)
def _bin_starts() -> np.ndarray:
    return np.unique(np.concatenate([[0], np.round(np.geomspace(1, HALF_PIXELS + 1, N_BIN_STARTS))])).astype(np.int64)


def shape_edges() -> np.ndarray:
    """Bin edges in ξ (units of 1/σt′), ``(B + 1,)``: the first bin is the source's own column's half."""
    starts = _bin_starts()
    edges = (starts - 0.5) * PIXEL
    edges[0] = 0.0
    return edges


def _fold(columns: np.ndarray) -> np.ndarray:
    """Column tallies ``(..., 2·HALF_PIXELS + 1)`` → bin sums ``(..., B)`` (both sides folded)."""
    folded = columns[..., HALF_PIXELS:].copy()
    folded[..., 1:] += columns[..., :HALF_PIXELS][..., ::-1]
    starts = _bin_starts()
    return np.add.reduceat(folded, starts[:-1], axis=-1)[..., : starts.size - 1]


# -- reading ------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _tables() -> dict:
    """Shares per bin: slab ``(4, X, Y, B)``, half-space ``(X, B)``."""
    edges = shape_edges()
    n_bins = edges.size - 1
    slab, header, slab_notes = read_table(SLAB_FILE)
    if header != ["x", "y", "xi_lo", "xi_hi", *SLAB_PROFILES] or slab.shape[0] != SLAB_X.size * SLAB_Y.size * n_bins:
        raise ValueError(f"{SLAB_FILE}: the columns or grid are not the ones this module reads")
    if not np.allclose(slab[:n_bins, 2], edges[:-1], rtol=1e-5, atol=1e-9):  # written to 6 digits
        raise ValueError(f"{SLAB_FILE}: bin edges differ from this module's")
    half, header, half_notes = read_table(HALF_SPACE_FILE)
    if header != ["x", "xi_lo", "xi_hi", "share"] or half.shape[0] != HALF_SPACE_X.size * n_bins:
        raise ValueError(f"{HALF_SPACE_FILE}: the columns or grid are not the ones this module reads")
    return {
        "slab": slab[:, 4:].T.reshape(len(SLAB_PROFILES), SLAB_X.size, SLAB_Y.size, n_bins).copy(),
        "half": half[:, 3].reshape(HALF_SPACE_X.size, n_bins).copy(),
        "notes": tuple(slab_notes + half_notes),
    }


@functools.lru_cache(maxsize=None)
def shapes_digest() -> str:
    """A short hash of both data files (part of the Gaussian tables' cache key)."""
    data = files("skinlayers.model").joinpath("data")
    return hashlib.sha256("".join(data.joinpath(n).read_text() for n in (SLAB_FILE, HALF_SPACE_FILE)).encode()).hexdigest()[:16]


def _linear(nodes: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower node index and fraction for each value (ends held)."""
    v = np.clip(value, nodes[0], nodes[-1])
    i = np.clip(np.searchsorted(nodes, v, side="right") - 1, 0, nodes.size - 2)
    return i, (v - nodes[i]) / (nodes[i + 1] - nodes[i])


def half_space_shape(x: np.ndarray) -> np.ndarray:
    """Line-spread shares ``(S, B)`` of the half-space at x = log10(σa/σs′) ``(S,)`` (linear in x)."""
    table = _tables()["half"]
    i, t = _linear(HALF_SPACE_X, np.asarray(x, dtype=np.float64).reshape(-1))
    return table[i] * (1.0 - t)[:, None] + table[i + 1] * t[:, None]


def slab_shapes(x: np.ndarray, y: float) -> np.ndarray:
    """Line-spread shares ``(4, S, B)`` (R⁺, T⁺, R⁻, T⁻) of the slab at x ``(S,)`` and y (bilinear)."""
    table = _tables()["slab"]
    i, t = _linear(SLAB_X, np.asarray(x, dtype=np.float64).reshape(-1))
    j, u = _linear(SLAB_Y, np.asarray([float(y)]))
    j, u = int(j[0]), float(u[0])
    at_y = table[:, :, j] * (1.0 - u) + table[:, :, j + 1] * u  # (4, X, B)
    return at_y[:, i] * (1.0 - t)[None, :, None] + at_y[:, i + 1] * t[None, :, None]


def fit_line_spread_weights(shares: np.ndarray, sigma_t_prime_per_mm: np.ndarray, totals: np.ndarray,
                            variances_mm2: np.ndarray) -> np.ndarray:
    """Non-negative Gaussian weights ``(S, K)`` whose line spread matches ``shares`` ``(S, B)``.

    Bin b spans ξ in [e_b, e_{b+1}) (``shape_edges``), i.e. lateral offsets e/σt′ mm at each row's
    ``sigma_t_prime_per_mm`` ``(S,)``; a Gaussian of variance v puts erf(e_{b+1}/√(2v)) − erf(e_b/√(2v))
    of its (folded) line spread there. Least squares with each bin weighted by 1/max(share, floor)
    (relative errors: the far tail carries the fall-off at the window's edge), a heavily weighted row
    asking Σ w = 1, then Σ w scaled to ``totals`` ``(S,)`` (transport's plane integral).
    """
    edges = shape_edges()
    v = np.asarray(variances_mm2, dtype=np.float64)
    out = np.zeros((shares.shape[0], v.size))
    for s in range(shares.shape[0]):
        if not totals[s] > 0.0:
            continue
        if not shares[s].sum() > 0.0:  # no light reached the tally (a thick dark slab's T): shape immaterial
            out[s, 0] = totals[s]
            continue
        bound = erf(edges[:, None] / sigma_t_prime_per_mm[s] / np.sqrt(2.0 * v)[None, :])  # (B + 1, K)
        basis = bound[1:] - bound[:-1]
        target = shares[s] / shares[s].sum()
        scale = 1.0 / np.sqrt(np.maximum(target, SHARE_FLOOR))
        system = scale[:, None] * basis
        mu = 10.0 * max(np.linalg.norm(scale * target), 1.0)
        w, _ = nnls(np.vstack([system, np.full((1, v.size), mu)]), np.concatenate([scale * target, [mu]]),
                    maxiter=50 * v.size)
        out[s] = w * (totals[s] / w.sum()) if w.sum() > 0 else 0.0
    return out


def _bin_transform(shares: np.ndarray, sigma_t_prime_per_mm: np.ndarray, k_per_mm: np.ndarray) -> np.ndarray:
    """Hankel transforms ``(S, N)`` of unit-total shapes ``(S, B)``: the 1-D cosine transform of the line
    spread (projection–slice), each bin's share spread evenly over it."""
    edges = shape_edges()[None, :, None] / sigma_t_prime_per_mm[:, None, None]  # (S, B + 1, 1) mm
    k = np.asarray(k_per_mm, dtype=np.float64)[None, None, :]
    lo, hi = edges[:, :-1], edges[:, 1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_cos = np.where(k > 0, (np.sin(k * hi) - np.sin(k * lo)) / (k * (hi - lo)), 1.0)
    total = shares.sum(-1, keepdims=True)
    return np.einsum("sb,sbn->sn", shares / np.where(total > 0, total, 1.0), mean_cos)


def shape_transforms(sigma_a_epidermis: torch.Tensor, sigma_s_prime_epidermis: torch.Tensor, thickness_mm: float,
                     sigma_a_dermis: torch.Tensor, sigma_s_prime_dermis: torch.Tensor, k_per_mm: torch.Tensor):
    """Unit-total Hankel transforms of the tabulated shapes: the epidermis's R⁺, T⁺, R⁻, T⁻ and the
    dermis's R, each ``(..., L, N)`` for σa ``(..., L)``, σs′ ``(L,)`` and k ``(N,)`` (mm⁻¹). The reference
    the Gaussian tables are checked against; not differentiated (the shapes are data)."""
    like = sigma_a_epidermis
    sa_e = sigma_a_epidermis.detach().cpu().double().numpy()
    sa_d = torch.broadcast_to(sigma_a_dermis, sigma_a_epidermis.shape).detach().cpu().double().numpy()
    se = torch.as_tensor(sigma_s_prime_epidermis).detach().cpu().double().numpy().reshape(-1)
    sd = torch.as_tensor(sigma_s_prime_dermis).detach().cpu().double().numpy().reshape(-1)
    k = torch.as_tensor(k_per_mm).detach().cpu().double().numpy().reshape(-1)
    lead, n_wl = sa_e.shape[:-1], sa_e.shape[-1]
    epi = np.zeros((len(SLAB_PROFILES), *lead, n_wl, k.size))
    derm = np.zeros((*lead, n_wl, k.size))
    for j in range(n_wl):
        a_e, a_d = sa_e[..., j].reshape(-1), sa_d[..., j].reshape(-1)
        slab = slab_shapes(np.log10(a_e / se[j]), math.log10(se[j] * thickness_mm))
        for p in range(len(SLAB_PROFILES)):
            epi[p, ..., j, :] = _bin_transform(slab[p], a_e + se[j], k).reshape(*lead, k.size)
        derm[..., j, :] = _bin_transform(half_space_shape(np.log10(a_d / sd[j])), a_d + sd[j], k).reshape(*lead, k.size)
    cast = lambda a: torch.from_numpy(a).to(like)  # noqa: E731
    return tuple(cast(e) for e in epi), cast(derm)


# -- generating ----------------------------------------------------------------------------------


def _unscattered(tau: float, albedo: float, n: int = 400_000) -> tuple[np.ndarray, np.ndarray]:
    """Bin shares (before normalising, per unit launched) of the light from a Lambertian point source
    below a slab of optical thickness ``tau`` (σt = 1) that crosses it without scattering: transmitted
    into air (T⁻) and reflected by the surface back out below (R⁻). Midpoint quadrature over the
    cosine and the azimuth; each ray lands at lateral offset ρ·cos φ."""
    from ..optics.fresnel import fresnel_reflectance  # noqa: PLC0415

    k = int(math.sqrt(n))
    mu = (np.arange(k) + 0.5) / k  # u ~ U(0, 1), cos θ = √u: Lambertian
    cos = np.sqrt(mu)
    phi = (np.arange(k) + 0.5) / k * 2.0 * math.pi
    tan = np.sqrt(1.0 - cos**2) / cos
    r = fresnel_reflectance(torch.from_numpy(cos), N_ABOVE / N_EPIDERMIS).numpy()
    weight = 1.0 / (k * k)
    edges = shape_edges()
    out = []
    for path, share in ((1.0, (1.0 - r) * np.exp(-tau / cos)), (2.0, r * np.exp(-2.0 * tau / cos))):
        offset = np.abs(path * tau * tan[:, None] * np.cos(phi)[None, :])
        out.append(np.histogram(offset.reshape(-1), bins=edges, weights=np.repeat(share * weight, k))[0])
    return out[0], out[1]


def _walk(x: float, thickness: float, lambertian: bool, photons: int, seed: int, n_layer: float, n_above: float,
          n_below: float, refract_from: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Surface and bottom line spreads ``(B,)`` per launched photon, in reduced units (σt′ = 1)."""
    from ..optics.fresnel import fresnel_reflectance  # noqa: PLC0415
    from ..transport import Medium, walk  # noqa: PLC0415

    ratio = 10.0**x
    sigma_s, sigma_a = 1.0 / (1.0 + ratio), ratio / (1.0 + ratio)
    cols = 2 * HALF_PIXELS + 1
    f64 = torch.float64
    medium = Medium((thickness,), (n_layer,), n_above, n_below, (sigma_s,), 0.0, torch.full((1, 1, cols), sigma_a, dtype=f64),
                    torch.ones(0, 1, cols, dtype=f64), PIXEL)
    g = torch.Generator().manual_seed(seed)
    weight = torch.ones(photons, dtype=f64)
    if not lambertian:
        cos_in = torch.ones(photons, dtype=f64)
    elif refract_from is None:
        cos_in = torch.sqrt(torch.rand(photons, dtype=f64, generator=g)).clamp_min(1e-9)
    else:  # Lambertian in the medium above, refracted into this one with Fresnel's transmittance
        cos_above, eta = torch.sqrt(torch.rand(photons, dtype=f64, generator=g)), n_layer / refract_from
        sin2 = (1.0 - cos_above**2) / eta**2
        weight = torch.where(sin2 < 1.0, 1.0 - fresnel_reflectance(cos_above, eta).to(f64), torch.zeros_like(cos_above))
        cos_in = torch.sqrt((1.0 - sin2).clamp_min(0.0)).clamp_min(1e-9)
    tally = walk(medium, torch.zeros(photons, dtype=f64), torch.zeros(photons, dtype=f64), cos_in, weight, g, across_y=True,
                 azimuth=2.0 * math.pi * torch.rand(photons, dtype=f64, generator=g), tally_bottom=math.isfinite(thickness))
    top = _fold(tally.surface[0, 0].numpy()) / photons
    bottom = None if tally.bottom is None else _fold(tally.bottom[0, 0].numpy()) / photons
    return top, bottom


def build(folder: Path, scale: float = 1.0) -> None:
    """Walk every node and write both tables into ``folder`` (the package's data)."""
    start = time.perf_counter()
    edges = shape_edges()
    n_half, n_slab = int(PHOTONS_HALF_SPACE * scale), int(PHOTONS_SLAB * scale)
    source = (
        "# Computed by this project (skinlayers.model.column.layer_shapes.build) with its Monte Carlo (model.transport.walk):\n"
        "#   isotropic scattering with sigma_s = sigma_s', lengths in units of 1/sigma_t' (sigma_t' = sigma_a + sigma_s').\n"
        "# x = log10(sigma_a / sigma_s'); xi_lo, xi_hi: a bin of |lateral offset| * sigma_t' (dimensionless);\n"
        "#   each value: the share of the exitance whose offset along one axis (the other integrated) falls in the bin,\n"
        "#   both sides folded; the shares of one node sum to 1 (the totals are layer_totals').\n"
        "# Regenerate: python -m skinlayers.model.column.layer_shapes\n"
    )
    rows = []
    for i, x in enumerate(HALF_SPACE_X):
        top, _ = _walk(float(x), math.inf, True, n_half, 1000 + i, N_DERMIS, N_EPIDERMIS, N_EPIDERMIS, refract_from=N_EPIDERMIS)
        rows.append(top / top.sum())
        print(f"half-space x {x:+.2f}: R {top.sum():.4f} ({time.perf_counter() - start:.0f} s)", flush=True)
    with (folder / HALF_SPACE_FILE).open("w") as f:
        f.write(f"# Line-spread shapes of a half-space of index {N_DERMIS} under {N_EPIDERMIS}, lit by Lambertian light from\n"
                f"#   the medium above (refracted, Fresnel-weighted); {n_half:,} photons a node.\n" + source)
        f.write("x,xi_lo,xi_hi,share\n")
        for x, share in zip(HALF_SPACE_X, rows):
            for b in range(edges.size - 1):
                f.write(f"{x:.2f},{edges[b]:.6g},{edges[b + 1]:.6g},{share[b]:.6e}\n")
    slab = np.zeros((len(SLAB_PROFILES), SLAB_X.size, SLAB_Y.size, edges.size - 1))
    for i, x in enumerate(SLAB_X):
        albedo = 1.0 / (1.0 + 10.0**x)
        for j, y in enumerate(SLAB_Y):
            tau = 10.0**y * (1.0 + 10.0**x)  # σt′ d in units where σt′ = 1
            seed = 10_000 + 100 * i + j
            r_plus, t_plus = _walk(float(x), tau, False, n_slab, seed, N_EPIDERMIS, N_ABOVE, N_EPIDERMIS)
            r_minus, t_minus = _walk(float(x), tau, True, n_slab, seed + 50, N_EPIDERMIS, N_EPIDERMIS, N_ABOVE)
            t_direct, r_direct = _unscattered(tau, albedo)
            for p, share in enumerate((r_plus, t_plus, r_minus + r_direct, t_minus + t_direct)):
                slab[p, i, j] = share / max(share.sum(), 1e-300)
        print(f"slab x {x:+.2f} done ({time.perf_counter() - start:.0f} s)", flush=True)
    with (folder / SLAB_FILE).open("w") as f:
        f.write(f"# Line-spread shapes of a slab of index {N_EPIDERMIS} under {N_ABOVE}, index-matched below; y = log10(sigma_s' d).\n"
                "#   R_plus, T_plus: a normal collimated beam from above (T_plus: its scattered part); R_minus, T_minus:\n"
                "#   Lambertian light from below, with the part that crosses unscattered (closed form);\n"
                f"#   {n_slab:,} photons a node and launch.\n" + source)
        f.write("x,y,xi_lo,xi_hi," + ",".join(SLAB_PROFILES) + "\n")
        for i, x in enumerate(SLAB_X):
            for j, y in enumerate(SLAB_Y):
                for b in range(edges.size - 1):
                    f.write(f"{x:.2f},{y:.2f},{edges[b]:.6g},{edges[b + 1]:.6g},"
                            + ",".join(f"{slab[p, i, j, b]:.6e}" for p in range(len(SLAB_PROFILES))) + "\n")
    _tables.cache_clear()
    shapes_digest.cache_clear()
    print(f"wrote {folder / HALF_SPACE_FILE} and {folder / SLAB_FILE} in {time.perf_counter() - start:.0f} s")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate the transport layer-shape tables (Monte Carlo).")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "data")
    parser.add_argument("--photons-scale", type=float, default=1.0, help="photons a node, as a multiple of the default")
    args = parser.parse_args(argv)
    if not args.photons_scale > 0:
        parser.error(f"--photons-scale must be > 0, got {args.photons_scale}")
    build(args.out, args.photons_scale)


if __name__ == "__main__":
    main()
