"""Layer totals from radiative transport: the plane integrals of the five profiles the skin model combines,
tabulated by similarity from adding-doubling (the ``transport`` choice of ``ModelSettings.profiles``).

Diffusion's layer totals are far off where absorption is not small against scattering and for the
transmittance of a thin epidermis (docs/transport.md, "Diffusion against radiative transport", and
"From model/column/layer_totals.py"). Transport's totals of a homogeneous layer depend on the albedo and the
optical thickness alone (lengths scale with 1/σt′), so one table over

    x = log10(σa / σs′),    y = log10(σs′ d)   (the half-space: x alone)

serves every wavelength, scattering law and thickness. The tables are computed once by
adding-doubling (Prahl's ``iadpython``, isotropic scattering with σs = σs′, the similarity case the
diffusion model rests on) and ship as package data; ``python -m skinlayers.model.column.adding_doubling``
regenerates them (its time: docs/transport.md, "From model/column/layer_totals.py"; needs the ``test``
extra). Reading them needs nothing but numpy.

What each table holds, per unit power *entering* the layer (the model's convention, DWRR08 §3):

* the epidermis slab, index 1.40 under air, index-matched below: R⁺ (normal collimated light from
  above), T⁺ *diffuse* (the light that scattered at least once, into the medium below), R⁻ and T⁻
  (Lambertian light from below in the slab's index; T⁻ leaves into air). The unscattered part of T⁺,
  ``T_c = exp(-(σa + σs′) d)``, is closed form and kept apart: it reaches the dermis as a collimated
  beam straight below its entry point.
* the half-space (dermis), index-matched above: R for collimated normal light (``R_c``) and for
  Lambertian light (``R_d``).

``combine`` then builds the five totals the renderer gathers with, with two steps diffusion does not
need: (1) the dermis answers the collimated beam with ``R_c``, not ``R_d``, so T₁⁺ enters the
combination as ``T_d + (R_c / R_d) T_c`` — with ``R₂⁺ = R_d`` the Eq. 7 series then reproduces
``T_c R_c + T_d R_d`` exactly for homogeneous skin (against a stack by adding-doubling it comes far
closer than treating all of T⁺ as Lambertian: docs/transport.md, "From model/column/layer_totals.py"); (2) the
small index step between the layers (1.40 over 1.38, total internal reflection beyond 80°) is added as a thin
Fresnel interface with hemispherical reflectances from either side, by the scalar adding rule.

A third table, ``transport_handover.csv``, holds the *hand-over factor* κ(x₁, y₁, x₂): Eq. 7's
series hands light between the layers as if it were Lambertian, and κ on R₂⁺ makes it give the two
layers' total as adding-doubling stacks them angle by angle (``handover_factor``; the setting
``handover: angular``). With it the model comes far closer to the adding-doubling stack on Table 2
(400–700 nm) than without (docs/transport.md, "Homogeneous skin", and "From model/column/layer_totals.py").

Shapes: coefficients broadcast to ``(...)``; results ``(...)``. Lookups are Catmull-Rom cubic in
(x, y), differentiable (C¹) with respect to σa and σs′.
"""

from __future__ import annotations

import functools
import hashlib
from importlib.resources import files
from typing import NamedTuple

import numpy as np
import torch

from ..optics.fresnel import fresnel_reflectance
from ..optics.spectra import MAX_WAVELENGTH_NM, MIN_WAVELENGTH_NM, epidermis_scattering

__all__ = [
    "HalfSpaceTotals",
    "LayerTotals",
    "SlabTotals",
    "TABLE_N_ABOVE",
    "TABLE_N_LAYER",
    "table_notes",
    "tables_digest",
    "CollimatedPart",
    "check_indices",
    "check_optics",
    "collimated_transmission",
    "combine",
    "diffuse_interface_reflectance",
    "half_space_totals",
    "handover_factor",
    "handover_grid",
    "handover_on_grid",
    "slab_totals",
]

#: The indices the tables are built for by default: the epidermis (1.40, DWRR08 §5.1) under air (the
#: shipped files say theirs in an ``# indices:`` line, and the reader holds to it).
TABLE_N_LAYER, TABLE_N_ABOVE = 1.40, 1.0
#: Grid of x = log10(σa/σs′) and y = log10(σs′ d); outside x the end values hold (albedo → 1 or → 0).
X_MIN, X_MAX, X_STEP = -4.0, 2.5, 0.05
Y_MIN, Y_MAX, Y_STEP = -1.0, 1.0, 0.05
#: Adding-doubling quadrature points (doubling them changes no total noticeably: docs/transport.md,
#: "From model/column/layer_totals.py").
QUAD_POINTS = 32
#: Optical thickness that stands in for a half-space (the clearest tabulated medium, σa/σs′ = 10⁻⁴,
#: has a diffusion length of 58 optical depths: e^{-2·10⁵/58} of its light reaches the far side).
HALF_SPACE_OPTICAL_THICKNESS = 1e5
#: Values are stored as logs; totals below this count as zero (a thick dark slab's T).
_FLOOR = 1e-280

#: The hand-over table's grid: the same axes, coarser (the factor stays near 1 and is smooth in all three;
#: its range: docs/transport.md, "From model/column/layer_totals.py").
HANDOVER_X_STEP, HANDOVER_Y_STEP = 0.25, 0.1
#: Up to this many values of the epidermis's σs′ (one a band, as a rule), κ is read in y once per value.
_HANDOVER_Y_SLICES = 4096
#: Where the light handed between the layers (T⁺ R_d T⁻) is below this, κ is set to 1: it changes nothing.
HANDOVER_NEGLIGIBLE = 1e-9

SLAB_FILE, HALF_SPACE_FILE = "transport_slab_totals.csv", "transport_half_space_totals.csv"
HANDOVER_FILE = "transport_handover.csv"
SLAB_COLUMNS = ("R_plus", "T_plus_diffuse", "R_minus", "T_minus")
HALF_SPACE_COLUMNS = ("R_collimated", "R_diffuse")


class SlabTotals(NamedTuple):
    """Totals of the epidermis slab (see the module docstring), each ``(...)``."""

    R_plus: torch.Tensor
    T_plus_diffuse: torch.Tensor
    T_plus_collimated: torch.Tensor
    R_minus: torch.Tensor
    T_minus: torch.Tensor


class HalfSpaceTotals(NamedTuple):
    R_collimated: torch.Tensor
    R_diffuse: torch.Tensor


class LayerTotals(NamedTuple):
    """What the model's layer combination takes: R₁⁺, T₁⁺ (diffuse part), T_c, R₁⁻, T₁⁻, R₂⁺ and the
    dermis's collimated-over-diffuse ratio ``q``; T₁⁺ as the combination sees it is ``T1_diffuse + q T_c``."""

    R1_plus: torch.Tensor
    T1_diffuse: torch.Tensor
    T1_collimated: torch.Tensor
    R1_minus: torch.Tensor
    T1_minus: torch.Tensor
    R2_plus: torch.Tensor
    collimated_ratio: torch.Tensor

    @property
    def T1_plus(self) -> torch.Tensor:
        return self.T1_diffuse + self.collimated_ratio * self.T1_collimated


def _axis(lo: float, hi: float, step: float) -> np.ndarray:
    return np.round(np.linspace(lo, hi, int(round((hi - lo) / step)) + 1), 10)


X_GRID, Y_GRID = _axis(X_MIN, X_MAX, X_STEP), _axis(Y_MIN, Y_MAX, Y_STEP)
HANDOVER_X_GRID, HANDOVER_Y_GRID = _axis(X_MIN, X_MAX, HANDOVER_X_STEP), _axis(Y_MIN, Y_MAX, HANDOVER_Y_STEP)


# -- reading ------------------------------------------------------------------------------------


def read_table(name: str) -> tuple[np.ndarray, list[str], list[str]]:
    """A package data CSV: rows (comments dropped), the header's names and the comment lines (source and units)."""
    text = files("skinlayers.model").joinpath("data", name).read_text()
    comments = [line for line in text.splitlines() if line.startswith("#")]
    body = [line for line in text.splitlines() if line and not line.startswith("#")]
    header = body[0].split(",")
    return np.array([[float(v) for v in line.split(",")] for line in body[1:]]), header, comments


@functools.lru_cache(maxsize=None)
def _tables() -> dict:
    """The shipped tables as float64 log-values: slab ``(4, X, Y)``, half-space ``(2, X)``."""
    slab, header, slab_notes = read_table(SLAB_FILE)
    if header != ["x", "y", *SLAB_COLUMNS]:
        raise ValueError(f"{SLAB_FILE}: unexpected columns {header}")
    nx, ny = X_GRID.size, Y_GRID.size
    if slab.shape[0] != nx * ny or not np.allclose(slab[:, 0].reshape(nx, ny)[:, 0], X_GRID) \
            or not np.allclose(slab[:, 1].reshape(nx, ny)[0], Y_GRID):
        raise ValueError(f"{SLAB_FILE}: the grid is not the one this module reads (x, y as in layer_totals)")
    half, header, half_notes = read_table(HALF_SPACE_FILE)
    if header != ["x", *HALF_SPACE_COLUMNS] or not np.allclose(half[:, 0], X_GRID):
        raise ValueError(f"{HALF_SPACE_FILE}: unexpected columns or grid")
    indices = [line.split()[2:] for line in slab_notes if line.startswith("# indices:")]
    if not indices:
        raise ValueError(f"{SLAB_FILE}: no '# indices:' line")
    words = indices[0]
    log = lambda v: np.log(np.maximum(v, _FLOOR))  # noqa: E731
    return {
        "n_layer": float(words[words.index("n_layer") + 1]),
        "n_above": float(words[words.index("n_above") + 1]),
        "slab": torch.from_numpy(log(slab[:, 2:]).T.reshape(len(SLAB_COLUMNS), nx, ny).copy()),
        "half": torch.from_numpy(log(half[:, 1:]).T.copy()),
        "notes": tuple(slab_notes + half_notes),
    }


@functools.lru_cache(maxsize=None)
def tables_digest() -> str:
    """A short hash of the totals' data files (part of the Gaussian tables' cache key; the hand-over
    table is not: the Gaussian tables do not hold it)."""
    data = files("skinlayers.model").joinpath("data")
    text = "".join(data.joinpath(name).read_text() for name in (SLAB_FILE, HALF_SPACE_FILE))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=None)
def _handover_table() -> torch.Tensor:
    """The shipped hand-over factors κ as float64 ``(X, Y, X)`` over (x₁, y₁, x₂)."""
    rows, header, notes = read_table(HANDOVER_FILE)
    if header != ["x_epidermis", "y_epidermis", "x_dermis", "handover"]:
        raise ValueError(f"{HANDOVER_FILE}: unexpected columns {header}")
    nx, ny = HANDOVER_X_GRID.size, HANDOVER_Y_GRID.size
    if rows.shape[0] != nx * ny * nx or not np.allclose(rows[:, 0].reshape(nx, ny, nx)[:, 0, 0], HANDOVER_X_GRID) \
            or not np.allclose(rows[:, 1].reshape(nx, ny, nx)[0, :, 0], HANDOVER_Y_GRID) \
            or not np.allclose(rows[:, 2].reshape(nx, ny, nx)[0, 0], HANDOVER_X_GRID):
        raise ValueError(f"{HANDOVER_FILE}: the grid is not the one this module reads")
    if not any(line.startswith(f"# indices: n_layer {_tables()['n_layer']} n_above {_tables()['n_above']}") for line in notes):
        raise ValueError(f"{HANDOVER_FILE}: made for other indices than {SLAB_FILE}; regenerate both")
    return torch.from_numpy(rows[:, 3].reshape(nx, ny, nx).copy())


def clear_caches() -> None:
    """Forget the tables read so far (after the builder, ``adding_doubling``, wrote new ones)."""
    _tables.cache_clear()
    tables_digest.cache_clear()
    _handover_table.cache_clear()


def table_notes() -> tuple[str, ...]:
    """The data files' header comments (their source, units and how they were made)."""
    return _tables()["notes"]


def _catmull_rom(t: torch.Tensor) -> torch.Tensor:
    """Cubic convolution weights of the 4 neighbours (i-1, i, i+1, i+2) for a fraction t, ``(..., 4)``."""
    t2, t3 = t * t, t * t * t
    return torch.stack([
        0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2),
    ], dim=-1)


def _position(value: torch.Tensor, lo: float, step: float, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour indices ``(..., 4)`` (clamped at the ends) and cubic weights for grid coordinates."""
    u = ((value - lo) / step).clamp(0.0, n - 1.0)
    i = u.detach().floor().clamp(0, n - 2).long()
    idx = (i[..., None] + torch.arange(-1, 3, device=u.device)).clamp(0, n - 1)
    return idx, _catmull_rom(u - i.to(u))


def _x(sigma_a_per_mm: torch.Tensor, sigma_s_prime_per_mm: torch.Tensor) -> torch.Tensor:
    if bool((sigma_a_per_mm < 0).any()) or bool((sigma_s_prime_per_mm <= 0).any()):
        raise ValueError("sigma_a must be >= 0 and sigma_s_prime > 0 (mm^-1)")
    return torch.log10(sigma_a_per_mm.clamp_min(1e-300) / sigma_s_prime_per_mm)


def slab_totals(sigma_a_per_mm, sigma_s_prime_per_mm, thickness_mm: float) -> SlabTotals:
    """Transport totals of the epidermis slab (index 1.40 under air, matched below), shapes ``(...)``."""
    sa, ss = torch.broadcast_tensors(torch.as_tensor(sigma_a_per_mm), torch.as_tensor(sigma_s_prime_per_mm))
    if not thickness_mm > 0:
        raise ValueError(f"slab thickness must be > 0 mm, got {thickness_mm}")
    y = torch.log10(ss * thickness_mm)
    lo, hi = 10.0**Y_MIN, 10.0**Y_MAX
    if bool((y < Y_MIN - 1e-9).any()) or bool((y > Y_MAX + 1e-9).any()):
        raise ValueError(
            f"transport layer totals are tabulated for σs′·d within {lo:g}–{hi:g} (got "
            f"{float((ss * thickness_mm).min()):.3g}–{float((ss * thickness_mm).max()):.3g}); use profiles: diffusion"
        )
    table = _tables()["slab"].to(device=sa.device, dtype=sa.dtype)
    ix, wx = _position(_x(sa, ss), X_MIN, X_STEP, X_GRID.size)
    iy, wy = _position(y, Y_MIN, Y_STEP, Y_GRID.size)
    flat = table.reshape(table.shape[0], -1)
    index = (ix[..., :, None] * Y_GRID.size + iy[..., None, :]).reshape(-1)
    batch = ix.shape[:-1]
    values = flat.index_select(1, index).reshape(table.shape[0], *batch, 16)
    weights = (wx[..., :, None] * wy[..., None, :]).reshape(*batch, 16)
    logs = (values * weights).sum(-1)
    r_plus, t_diffuse, r_minus, t_minus = torch.exp(logs).unbind(0)
    t_collimated = torch.exp(-(sa + ss) * thickness_mm)
    return SlabTotals(r_plus, t_diffuse, t_collimated, r_minus, t_minus)


def half_space_totals(sigma_a_per_mm, sigma_s_prime_per_mm) -> HalfSpaceTotals:
    """Transport totals of a half-space (index-matched above), shapes ``(...)``."""
    sa, ss = torch.broadcast_tensors(torch.as_tensor(sigma_a_per_mm), torch.as_tensor(sigma_s_prime_per_mm))
    table = _tables()["half"].to(device=sa.device, dtype=sa.dtype)
    ix, wx = _position(_x(sa, ss), X_MIN, X_STEP, X_GRID.size)
    values = table.index_select(1, ix.reshape(-1)).reshape(table.shape[0], *ix.shape)
    r_c, r_d = torch.exp((values * wx).sum(-1)).unbind(0)
    return HalfSpaceTotals(r_c, r_d)


def handover_factor(sigma_a_epidermis, sigma_s_prime_epidermis, thickness_mm: float, sigma_a_dermis,
                    sigma_s_prime_dermis) -> torch.Tensor:
    """κ: the factor on the dermis's Lambertian reflectance R₂⁺ that makes Eq. 7's scalar series give the
    two layers' transport total, ``(...)`` (shapes broadcast; Catmull-Rom in x₁, y₁, x₂, C¹).

    The series hands light between the layers as if it were Lambertian each way. It is not: the
    epidermis's scattered transmission leans towards grazing angles, where the dermis returns more and
    the epidermis passes less back out. Adding-doubling stacks the layers angle by angle (32 streams);
    κ is what the scalar hand-over would need for R₂⁺ to give that stack's total, from the same
    tables' layer totals: R₁₂ = R₁⁺ + T₁⁺ κR₂⁺ T₁⁻ / (1 − R₁⁻ κR₂⁺). It is a little below 1 for skin
    (the scalar series is too bright in the green on homogeneous skin: docs/transport.md, "From
    model/column/layer_totals.py").
    """
    sa1, ss1, sa2, ss2 = (torch.as_tensor(v) for v in (sigma_a_epidermis, sigma_s_prime_epidermis, sigma_a_dermis,
                                                        sigma_s_prime_dermis))
    shape = torch.broadcast_shapes(sa1.shape, ss1.shape, sa2.shape, ss2.shape)
    table = _handover_table().to(device=sa1.device, dtype=torch.result_type(sa1, ss1))
    nx, ny = HANDOVER_X_GRID.size, HANDOVER_Y_GRID.size
    # y first, on the epidermis's scattering as given (usually one value a band): then 16 points per
    # element, not 64 (the time and memory of a point fit's every step)
    if ss1.numel() > _HANDOVER_Y_SLICES:  # scattering per element: all 64 neighbours of each
        return _handover_3d(table, *(v.expand(shape) for v in (sa1, ss1, sa2, ss2)), thickness_mm)
    iy, wy = _position(torch.log10(ss1 * thickness_mm), Y_MIN, HANDOVER_Y_STEP, ny)
    slices = (table.permute(1, 0, 2).index_select(0, iy.reshape(-1)).reshape(*iy.shape, nx, nx)
              * wy[..., None, None]).sum(-3)  # (*y, X, X)
    slot = torch.arange(max(ss1.numel(), 1), device=sa1.device).reshape(ss1.shape).expand(shape)
    i1, w1 = _position(_x(sa1.expand(shape), ss1.expand(shape)), X_MIN, HANDOVER_X_STEP, nx)
    i2, w2 = _position(_x(sa2.expand(shape), ss2.expand(shape)), X_MIN, HANDOVER_X_STEP, nx)
    index = (slot[..., None, None] * nx + i1[..., :, None]) * nx + i2[..., None, :]
    values = slices.reshape(-1).index_select(0, index.reshape(-1)).reshape(index.shape)
    return (values * (w1[..., :, None] * w2[..., None, :])).sum((-2, -1))


def _handover_3d(table: torch.Tensor, sa1, ss1, sa2, ss2, thickness_mm: float) -> torch.Tensor:
    """``handover_factor`` element by element: Catmull-Rom over the 4 × 4 × 4 neighbours."""
    nx, ny = HANDOVER_X_GRID.size, HANDOVER_Y_GRID.size
    i1, w1 = _position(_x(sa1, ss1), X_MIN, HANDOVER_X_STEP, nx)
    iy, wy = _position(torch.log10(ss1 * thickness_mm), Y_MIN, HANDOVER_Y_STEP, ny)
    i2, w2 = _position(_x(sa2, ss2), X_MIN, HANDOVER_X_STEP, nx)
    index = (i1[..., :, None, None] * ny + iy[..., None, :, None]) * nx + i2[..., None, None, :]
    weights = w1[..., :, None, None] * wy[..., None, :, None] * w2[..., None, None, :]
    values = table.reshape(-1).index_select(0, index.reshape(-1)).reshape(index.shape)
    return (values * weights).sum((-3, -2, -1))


def handover_grid(sigma_a_grid_per_mm: torch.Tensor, sigma_s_prime_epidermis: torch.Tensor, thickness_mm: float,
                  sigma_s_prime_dermis: torch.Tensor) -> torch.Tensor:
    """κ on a σa grid ``(S,)`` for each band's scattering ``(L,)``: ``(L, S, S)`` [band, σa epidermis,
    σa dermis] — what the renderer and the per-pixel fits interpolate (``handover_on_grid``): with the
    scattering fixed per band, κ varies per pixel with the two absorptions alone."""
    grid = torch.as_tensor(sigma_a_grid_per_mm, dtype=torch.float64)
    s1 = torch.as_tensor(sigma_s_prime_epidermis, dtype=torch.float64).reshape(-1)
    s2 = torch.as_tensor(sigma_s_prime_dermis, dtype=torch.float64).reshape(-1)
    with torch.no_grad():
        return torch.stack([handover_factor(grid[:, None], s1[j], thickness_mm, grid[None, :], s2[j])
                            for j in range(s1.numel())])


def handover_on_grid(grid: torch.Tensor, index_epidermis: torch.Tensor, frac_epidermis: torch.Tensor,
                     index_dermis: torch.Tensor, frac_dermis: torch.Tensor) -> torch.Tensor:
    """``handover_grid``'s ``(L, S, S)`` at table positions: flat ``index`` = band·S + i₀ and ``frac`` of
    each layer's σa (the same positions the Gaussian weights are looked up at, linear in log σa),
    bilinear; any shape. The gradient flows through the fractions."""
    n = grid.shape[1]
    flat = grid.reshape(-1).to(frac_epidermis)
    base = index_epidermis * n + index_dermis % n
    k00, k01 = flat[base], flat[base + 1]
    k10, k11 = flat[base + n], flat[base + n + 1]
    low = k00 + frac_dermis * (k01 - k00)
    high = k10 + frac_dermis * (k11 - k10)
    return low + frac_epidermis * (high - low)


@functools.lru_cache(maxsize=64)
def diffuse_interface_reflectance(n_from: float, n_to: float, points: int = 400) -> float:
    """Hemispherical reflectance 2∫F(μ)μ dμ of Lambertian light in index ``n_from`` meeting ``n_to``
    (Fresnel, unpolarised, total internal reflection included), by Gauss–Legendre quadrature."""
    nodes, weights = np.polynomial.legendre.leggauss(points)
    mu = 0.5 * (nodes + 1.0)
    # fresnel_reflectance takes the cosine on the side the light comes from and the ratio beyond/here
    f = fresnel_reflectance(torch.from_numpy(mu), n_to / n_from).numpy()
    return float(np.sum(weights * 0.5 * 2.0 * f * mu))


def check_indices(n_above: float, n_epidermis: float) -> None:
    """Refuse indices the shipped tables were not computed for (they shape every total)."""
    tab = _tables()
    if abs(n_epidermis - tab["n_layer"]) > 1e-9 or abs(n_above - tab["n_above"]) > 1e-9:
        raise ValueError(
            f"transport profiles are tabulated for an epidermis of index {tab['n_layer']} under {tab['n_above']} "
            f"(got {n_epidermis} under {n_above}); regenerate model/data/{SLAB_FILE} with "
            "`python -m skinlayers.model.column.adding_doubling --n-layer … --n-above …`, or use profiles: diffusion"
        )


def check_optics(optics) -> None:
    """Refuse, when the settings are made, optics the tables cannot serve: other indices, or an
    epidermis whose σs′·d (over every wavelength the model takes) leaves the tabulated range."""
    check_indices(optics.n_above, optics.n_epidermis)
    wavelength = torch.linspace(MIN_WAVELENGTH_NM, MAX_WAVELENGTH_NM, 43, dtype=torch.float64)
    tau = epidermis_scattering(wavelength, optics) * optics.epidermis_thickness_mm
    lo, hi = 10.0**Y_MIN, 10.0**Y_MAX
    if float(tau.min()) < lo or float(tau.max()) > hi:
        raise ValueError(
            f"transport profiles are tabulated for an epidermis of σs′·d within {lo:g}–{hi:g}; these optics give "
            f"{float(tau.min()):.3g}–{float(tau.max()):.3g} over {MIN_WAVELENGTH_NM:g}–{MAX_WAVELENGTH_NM:g} nm "
            "(thickness or scattering); use profiles: diffusion"
        )


def combine(slab: SlabTotals, half: HalfSpaceTotals, n_epidermis: float, n_dermis: float) -> LayerTotals:
    """The model's five layer totals from the two tables, the index step between the layers added.

    The step is a smooth boundary with hemispherical reflectances r_d (from the epidermis) and r_u
    (from the dermis); by the scalar adding rule, with D = 1 / (1 - r_d R⁻):
    R⁺ += T_d r_d T⁻ D,  T_d ← T_d (1 - r_d) D,  R⁻ ← r_u + (1 - r_u)(1 - r_d) R⁻ D,  T⁻ ← (1 - r_u) T⁻ D.
    The collimated beam crosses it at normal incidence (reflectance 5·10⁻⁵ for 1.40/1.38, neglected).
    """
    r_d = diffuse_interface_reflectance(n_epidermis, n_dermis)
    r_u = diffuse_interface_reflectance(n_dermis, n_epidermis)
    d = 1.0 / (1.0 - r_d * slab.R_minus)
    r_plus = slab.R_plus + slab.T_plus_diffuse * r_d * slab.T_minus * d
    t_diffuse = slab.T_plus_diffuse * (1.0 - r_d) * d
    r_minus = r_u + (1.0 - r_u) * (1.0 - r_d) * slab.R_minus * d
    t_minus = (1.0 - r_u) * slab.T_minus * d
    ratio = half.R_collimated / half.R_diffuse
    return LayerTotals(r_plus, t_diffuse, slab.T_plus_collimated, r_minus, t_minus, half.R_diffuse, ratio)


def layer_totals(sigma_a_epidermis, sigma_s_prime_epidermis, thickness_mm: float, sigma_a_dermis,
                 sigma_s_prime_dermis, n_above: float, n_epidermis: float, n_dermis: float,
                 handover: str = "lambertian") -> LayerTotals:
    """``combine`` of the slab and half-space tables at these coefficients (indices checked); with
    ``handover="angular"`` R₂⁺ carries the hand-over factor κ (``handover_factor``)."""
    check_indices(n_above, n_epidermis)
    totals = combine(slab_totals(sigma_a_epidermis, sigma_s_prime_epidermis, thickness_mm),
                     half_space_totals(sigma_a_dermis, sigma_s_prime_dermis), n_epidermis, n_dermis)
    if handover == "lambertian":
        return totals
    if handover != "angular":
        raise ValueError(f"handover must be 'angular' or 'lambertian', got {handover!r}")
    kappa = handover_factor(sigma_a_epidermis, sigma_s_prime_epidermis, thickness_mm, sigma_a_dermis, sigma_s_prime_dermis)
    return totals._replace(R2_plus=totals.R2_plus * kappa)


class CollimatedPart(NamedTuple):
    T1_collimated: torch.Tensor
    collimated_ratio: torch.Tensor


def collimated_transmission(sigma_a_epidermis, sigma_s_prime_epidermis, thickness_mm: float, sigma_a_dermis,
                            sigma_s_prime_dermis) -> CollimatedPart:
    """The unscattered beam through the epidermis, T_c = exp(-(σa + σs′) d), and the dermis's
    collimated-over-Lambertian reflectance ratio q at its σa: what the renderer adds per pixel to the
    light its T₁⁺ gather sends down (``q T_c Φ``), without a profile: the beam goes straight down."""
    t_c = torch.exp(-(torch.as_tensor(sigma_a_epidermis) + sigma_s_prime_epidermis) * thickness_mm)
    half = half_space_totals(sigma_a_dermis, sigma_s_prime_dermis)
    return CollimatedPart(t_c, half.R_collimated / half.R_diffuse)
