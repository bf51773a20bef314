"""What of a cube the fit can use: dead bands, saturated pixels, the mask — and the per-pixel flags.

A *dead band* (a filter that let no light through, a frame that was black) would pull every pixel
towards absorbing everything at its wavelength; it is left out of the loss and reported. A
*saturated* pixel (any band at or above ``saturated_reflectance``) is not skin reflectance; like the
cube's own masked pixels it is left out of the loss, and its parameters follow the nearest visible
pixel (``unknowns.extend``). Hair and other absorbers the model lacks are fitted and show as a high
residual.

Flags are one bit field per pixel (``FLAG_BITS``), written as the ``flags`` channel of ``maps.exr``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ...formats.cube import Cube
from ...formats.errors import InputError
from ...model import N_PARAMS

__all__ = ["BAND_BIAS_LIMIT", "FLAG_BITS", "MAP_TARGETS", "MIN_BANDS", "RESIDUAL_NOISE_LIMIT", "SMOOTH_BAND_RATIO", "DataChecks",
           "band_bias", "band_bias_notes", "check_cube", "first_flag", "flag_value", "precision_notes", "residual_notes", "smooth_band_notes"]

#: Bands a pixel needs: one per parameter and one for the global scale.
MIN_BANDS = N_PARAMS + 1

#: Bit of each flag in the ``flags`` channel (value = sum of 2**bit).
FLAG_BITS = {
    "masked": 0,  # no data in the loss (cube mask, saturated): parameters copied from the nearest visible pixel
    "saturated": 1,  # a band at or above the saturation level
    "at_bound": 2,  # a parameter within at_bound_fraction of its range of a bound
    "not_converged": 3,  # the Gauss–Newton step still proposed at the end moves a parameter by > σ/2
    "high_residual": 4,  # residual RMS above high_residual_factor × the median pixel's
    "band_excluded": 5,  # a dead band was left out of the whole fit
    "hair": 6,  # on a hair or in its halo (hairs.py): the model has no hair, the maps here are biased
    "structure": 7,  # the residual has a spatial shape above the noise (structure.py): a vein, a fold, a hair
}


#: A used band whose fit stays off its measurement by more than this share of its mean reflectance, on
#: average over the fitted pixels, is one no maps can match: its calibration (the Spectralon's certified
#: value, the gray card, the filter) or the band's frames are suspect. The limit lies well above what clean
#: cubes leave and below what a miscalibrated green band leaves (docs/stability.md, "From
#: reconstruct/diagnosis/checks.py"). A blue band's error the maps absorb (melanin), leaving no trace here.
BAND_BIAS_LIMIT = 0.02

#: The residual's RMS over the cube's own noise (``grid_choice.band_noise``, Immerkær's estimate from the
#: cube itself; the same pixels and used bands) above which the model does not explain the data. The
#: limit allows for the estimate's own error above a clean fit's residual and stays below what
#: misregistered bands leave (docs/stability.md, "From reconstruct/diagnosis/checks.py").
RESIDUAL_NOISE_LIMIT = 1.5

#: A band whose own noise, relative to its reflectance, is below this share of its neighbours' (their
#: geometric mean; the one neighbour at an end of the range) was smoothed: the subject moved during its
#: frame, it was out of focus, or it was resampled. Its edges then differ from the other bands' and the
#: maps take the difference, often below the residual limit. The ratio lies below every band of clean
#: cubes and above a band blurred by a few pixels of motion (docs/stability.md, "From
#: reconstruct/diagnosis/checks.py").
SMOOTH_BAND_RATIO = 0.5

#: What the maps are meant to be read to: the median error per map (relative; β_m absolute) the demo and
#: the analyses hold a fit to (the stability matrix's targets). A map whose σ puts its median error beyond
#: its target cannot be expected to meet it: the data are too noisy for that map, and the fit says so.
MAP_TARGETS = {"C_m": 0.10, "beta_m": 0.1, "C_he": 0.25, "C_hd": 0.10}
#: The median of |e| for a normal error e of standard deviation σ, over σ: a map's expected median error.
MEDIAN_ABS_NORMAL = 0.6745


def flag_value(name: str) -> int:
    return 1 << FLAG_BITS[name]


def first_flag(flags, flag_bits: dict[str, int] = FLAG_BITS):
    """Each pixel's first flag (the lowest bit set) as bit + 1, 0 where none: a labels image of ``flags``
    (an int array or tensor of any shape; ``flag_bits``: name → bit, a file's own where it says them)."""
    first = flags * 0
    for _, bit in sorted(flag_bits.items(), key=lambda kv: -kv[1]):  # the lowest bit written last: it wins
        first[(flags >> bit) & 1 == 1] = bit + 1
    return first


@dataclass
class DataChecks:
    """``bands_used`` ``(L,)`` bool; ``fit_mask`` ``(H, W)``: pixels in the loss; ``saturated`` and
    ``cube_masked`` ``(H, W)``; ``notes``: one line per finding, for ``fit.json`` and the console."""

    bands_used: torch.Tensor
    fit_mask: torch.Tensor
    saturated: torch.Tensor
    cube_masked: torch.Tensor
    notes: list[str] = field(default_factory=list)
    excluded_bands: list[dict] = field(default_factory=list)
    #: The notes that say the maps may be wrong (a band left out or off, the residual above the noise,
    #: noise-limited maps), as against those that say how the data were handled (pixels masked).
    warnings: list[str] = field(default_factory=list)

    def warn(self, lines: list[str]) -> None:
        """Record ``lines`` as notes and as warnings."""
        self.notes.extend(lines)
        self.warnings.extend(lines)


def check_cube(cube: Cube, saturated_reflectance: float, dead_band_reflectance: float) -> DataChecks:
    """Screen a cube; raises ``InputError`` (a ``ValueError``) when fewer than ``MIN_BANDS`` bands or no
    pixel remain."""
    refl = cube.reflectance
    mask = cube.mask.to(torch.bool)
    wl = cube.wavelength_nm.tolist()
    saturated = (refl >= saturated_reflectance).any(dim=0) & mask
    usable = mask & ~saturated
    notes: list[str] = []
    warnings: list[str] = []
    excluded: list[dict] = []
    bands_used = torch.ones(len(wl), dtype=torch.bool)
    if bool(usable.any()):
        for j, w in enumerate(wl):
            med = float(refl[j][usable].median())
            if med <= dead_band_reflectance:
                bands_used[j] = False
                excluded.append({"wavelength_nm": w, "reason": f"dead band: median reflectance {med:.2g} <= {dead_band_reflectance:g}"})
                warnings.append(f"band {w:g} nm left out: dead (median reflectance {med:.2g})")
    n_sat = int(saturated.sum())
    if n_sat:
        notes.append(f"{n_sat} saturated pixel(s) (a band >= {saturated_reflectance:g}) left out of the loss and flagged")
    n_masked = int((~mask).sum())
    if n_masked:
        notes.append(f"{n_masked} pixel(s) outside the cube's mask: parameters follow the nearest visible pixel")
    if int(bands_used.sum()) < MIN_BANDS:
        raise InputError(
            f"cube has {int(bands_used.sum())} usable band(s) of {len(wl)}; the fit needs at least {MIN_BANDS} "
            f"({N_PARAMS} parameters and a scale)"
        )
    if not bool(usable.any()):
        raise InputError("cube has no usable pixel (all masked or saturated)")
    return DataChecks(bands_used, usable, saturated, ~mask, [*warnings, *notes], excluded, warnings)


def band_bias(residual: torch.Tensor, measured: torch.Tensor, used: torch.Tensor, pixels: torch.Tensor) -> dict[int, float]:
    """Per used band ``j`` its mean residual over its mean measured reflectance on ``pixels`` ``(H, W)``
    (bool): ``residual`` and ``measured`` ``(L, H, W)``, ``used`` ``(L,)``. Signed: positive where the
    fit is brighter than the band (the band reads dark)."""
    out = {}
    for j in range(residual.shape[0]):
        if bool(used[j]) and bool(pixels.any()):
            out[j] = float(residual[j][pixels].double().mean() / measured[j][pixels].double().mean().clamp_min(1e-12))
    return out


def band_bias_notes(bias: dict[int, float], wavelength_nm: list[float], limit: float = BAND_BIAS_LIMIT) -> list[str]:
    """A line naming the bands whose ``bias`` exceeds ``limit``, the largest first (the likely culprit:
    its neighbours are pulled the other way by the maps that half-match it), and what to check."""
    off = sorted(((j, b) for j, b in bias.items() if abs(b) > limit), key=lambda jb: -abs(jb[1]))
    if not off:
        return []
    listed = ", ".join(f"{wavelength_nm[j]:g} nm {abs(b):.1%} {'dark' if b > 0 else 'bright'}" for j, b in off)
    return [f"band(s) stay off the best fit of all bands by more than {limit:.0%} of their reflectance ({listed}): no maps "
            f"match them, and the maps are biased; check the calibration of {wavelength_nm[off[0][0]]:g} nm first (the "
            "Spectralon's certified value, the gray card, the filter) and its frames"]


def residual_notes(ratio: float, limit: float = RESIDUAL_NOISE_LIMIT) -> list[str]:
    """A line when the residual's RMS is ``ratio`` > ``limit`` times the cube's own noise, with where to look."""
    if not ratio > limit:
        return []
    return [f"the residual is {ratio:.1f}× the cube's noise (estimated from the cube): the model does not explain the data, "
            "and the maps take what it cannot; look at the residual maps (res_<band>) for edges doubled between bands "
            "(misregistration, the subject's motion), glints, or an absorber the skin model lacks (hair, ink)"]


def smooth_band_notes(relative_noise: list[float], wavelength_nm: list[float], used: list[bool],
                      limit: float = SMOOTH_BAND_RATIO) -> list[str]:
    """A line naming the used bands whose ``relative_noise`` (each band's noise σ over its median
    reflectance, ``(L,)``) is below ``limit`` × their used neighbours' (geometric mean): frames smoothed by
    motion or focus, whose edges the other bands do not share."""
    idx = [j for j in range(len(relative_noise)) if used[j] and relative_noise[j] > 0]
    smooth = []
    for k, j in enumerate(idx):
        neighbours = [relative_noise[i] for i in (idx[k - 1] if k > 0 else None, idx[k + 1] if k + 1 < len(idx) else None) if i is not None]
        if not neighbours:
            continue
        ratio = relative_noise[j] / (math.prod(neighbours) ** (1.0 / len(neighbours)))
        if ratio < limit:
            smooth.append((j, ratio))
    if not smooth:
        return []
    listed = ", ".join(f"{wavelength_nm[j]:g} nm {r:.2f}×" for j, r in smooth)
    return [f"band(s) smoother than their neighbours (noise {listed} theirs): the subject's motion during the frame, "
            "focus, or resampling blurred them, their edges differ from the other bands' and the maps take the "
            "difference; retake the band with the subject steady and the focus checked"]


def precision_notes(sigma_median: dict[str, float], targets: dict[str, float] = MAP_TARGETS) -> list[str]:
    """A line naming the maps whose expected median error, ``MEDIAN_ABS_NORMAL`` × their median σ (relative;
    β_m absolute), exceeds the target they are read to."""
    over = [(n, MEDIAN_ABS_NORMAL * s) for n, s in sigma_median.items() if n in targets and MEDIAN_ABS_NORMAL * s > targets[n]]
    if not over:
        return []
    listed = ", ".join(f"{n} {e:.0%}" if n != "beta_m" else f"{n} {e:.2f}" for n, e in over)
    return [f"noise-limited maps: their σ puts the median error at {listed}, beyond the targets "
            + ", ".join(f"{n} {targets[n]:g}" for n, _ in over)
            + "; more light per band (exposure, ISO, frames averaged) or coarser map grids would narrow them"]
