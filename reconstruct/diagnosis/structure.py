"""Residual with a shape: where the fit leaves structure the model does not hold (a vein, a fold, a hair).

The noise of a camera is white: neighbouring pixels' residuals are independent. What the model cannot
render (a vein's blood under the interface, a hair, a fold's shading) leaves a residual that is the same
in neighbouring pixels: after smoothing over ``SMOOTH_MM`` the noise shrinks by the kernel's norm and the
structure stays. Per used band j the smoothed residual is divided by what white noise of the residual's
own σ_j (``grid_choice.band_noise`` of the residual: Immerkær's kernel, which a smooth structure does not
answer) would leave after the same smoothing, giving z_j; a pixel's statistic is Σ_j z_j² over the used
bands, χ² with as many degrees of freedom under white noise. A pixel is flagged where that exceeds the
χ² quantile ``1 − FALSE_ALARM`` and the smoothed residual's RMS over the bands is at least ``AMPLITUDE`` of a
pixel's noise (a shape that matters), its own residual is unlikely for noise (``LOCAL_FALSE_ALARM``) and its
connected region spans at least ``MIN_LENGTH_MM`` (a vein or a fold, not a chance clump of noise). The bands it shows in: those whose |z| exceeds ``BAND_Z`` on at least
half the flagged pixels.

Cubes whose pixels are coarser than ``SMOOTH_MM`` are not searched: there a shape and one pixel's noise
look alike (a pixel far off on its own is the ``high_residual`` flag's).

Shapes: residual ``(L, H, W)``, masks ``(H, W)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy import ndimage, stats

from ..choice.grid_choice import band_noise

__all__ = ["AMPLITUDE", "BAND_Z", "FALSE_ALARM", "MIN_LENGTH_MM", "SMOOTH_MM", "STRUCTURE_SIGMA_ON", "StructureFinding", "find_structure", "structure_notes",
           "structure_widening"]

#: The Gaussian's σ (mm; at least a pixel) over which residuals are averaged: a vein's width
#: (0.5–1 mm across), wider than a camera's noise grain.
SMOOTH_MM = 0.15
#: The chance a pixel of white noise is flagged before the region test.
FALSE_ALARM = 1e-4
#: The smoothed residual's RMS over the used bands, as a share of a pixel's noise σ, from which a shape
#: matters: smaller ones (what a map on coarse nodes leaves over smooth variation, a freckle's edge) are
#: real but below what changes a map beyond its σ. Set on the demo's scene (256², seed 0): clean skin at
#: least 17 px from the vein reaches 0.33 at its 99.9th percentile (0.37 at most), the vein's pixels 0.45
#: at their 10th (docs/reconstruct.md, "A residual with a shape").
AMPLITUDE = 0.4
#: A pixel of a found region is flagged where its own residual (smoothed over a pixel) is this unlikely
#: for white noise: the wide smoothing finds a vein, the narrow one says which pixels are on it.
LOCAL_FALSE_ALARM = 0.05
#: A flagged region spans at least this (mm; at least three pixels).
MIN_LENGTH_MM = 0.6
#: On flagged pixels σ is widened further by these factors per map (an uncertainty term of Type B, as
#: ``hairs.HAIR_SIGMA_ON``): the fit puts a vein's blood, which the model has no layer for, into the dermis's
#: blood. Set on the demo's scene (256², seed 0) as the factor C_hd's σ needed to cover 90% of the truth
#: within 2σ on the flagged pixels after the residual's own widening (3.48); checked on seed 1
#: (docs/reconstruct.md, "A residual with a shape").
STRUCTURE_SIGMA_ON = {"C_m": 1.0, "beta_m": 1.0, "C_he": 1.0, "C_bc": 1.0, "C_hd": 3.5}
#: A band shows the structure where its |z| exceeds this on at least half the flagged pixels.
BAND_Z = 3.0


@dataclass
class StructureFinding:
    """Flagged pixels ``(H, W)`` (bool), the bands (nm) the structure shows in, the regions' count."""

    flagged: torch.Tensor
    bands_nm: list[float] = field(default_factory=list)
    regions: int = 0

    @property
    def count(self) -> int:
        return int(self.flagged.sum())

    def as_dict(self, fitted_pixels: int) -> dict:
        return {"pixels": self.count, "share": self.count / max(fitted_pixels, 1), "regions": self.regions,
                "bands_nm": self.bands_nm}


def find_structure(residual: torch.Tensor, mask: torch.Tensor, wavelength_nm: list[float], used: torch.Tensor,
                   mm_per_pixel: float) -> StructureFinding:
    """The pixels whose residual has a spatial structure above the noise (see the module docstring);
    ``mask`` the fitted pixels, ``used`` ``(L,)`` the bands in the loss."""
    r = residual.detach().double().cpu()
    valid = mask.detach().bool().cpu()
    bands = [j for j in range(r.shape[0]) if bool(used[j])]
    empty = StructureFinding(torch.zeros_like(valid))
    # pixels coarser than the smoothing (a cube of a few dozen pixels across the window): one pixel's
    # residual cannot be told from a shape there, and a pixel off on its own is ``high_residual``'s
    if len(bands) == 0 or int(valid.sum()) < 16 or mm_per_pixel > SMOOTH_MM:
        return empty
    try:
        sigma = band_noise(r[bands], valid)
    except ValueError:  # too few pixels with their neighbourhood in the mask
        return empty
    width_px = max(SMOOTH_MM / mm_per_pixel, 1.0)
    # a band's offset over the whole patch is no shape (the band-bias check's business): taken out first
    r = r[bands] - r[bands][:, valid].median(dim=1).values[:, None, None]
    bands_nm = [wavelength_nm[j] for j in bands]
    smoothed, white = _smoothed(r, valid, sigma, width_px)
    z = smoothed / white
    statistic = (z**2).sum(0)
    # found on the wide smoothing, placed on a pixel's own neighbourhood: the wide kernel spreads a vein's
    # residual over its sides, where the pixel's own (one-pixel smoothing) residual is the noise's
    narrow, narrow_white = _smoothed(r, valid, sigma, 1.0)
    near = ((narrow / narrow_white) ** 2).sum(0) > stats.chi2.isf(LOCAL_FALSE_ALARM, len(bands))
    # and large enough to matter: the smoothed residual's RMS over the bands at least AMPLITUDE of a pixel's noise
    amplitude = np.sqrt((smoothed**2).mean(0))
    candidate = (statistic > stats.chi2.isf(FALSE_ALARM, len(bands))) & (amplitude >= AMPLITUDE) & near & valid.numpy()
    labels, count = ndimage.label(candidate, structure=np.ones((3, 3)))
    keep = np.zeros_like(candidate)
    regions = 0
    min_px = max(MIN_LENGTH_MM / mm_per_pixel, 3.0)
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        span = math.hypot(box[0].stop - box[0].start, box[1].stop - box[1].start)
        if span >= min_px:
            keep |= labels == k
            regions += 1
    if not keep.any():
        return empty
    shows = [w for i, w in enumerate(bands_nm) if float((np.abs(z[i][keep]) > BAND_Z).mean()) >= 0.5]
    return StructureFinding(torch.from_numpy(keep), [float(w) for w in shows], regions)


def _smoothed(r: torch.Tensor, valid: torch.Tensor, sigma: torch.Tensor, width_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Per band, the residual averaged over a Gaussian of ``width_px`` (the mask's pixels only) in units of
    the band's noise σ, ``(L, H, W)``; and what white noise leaves of σ there, ``(H, W)``: σ‖k‖₂ for the
    normalised kernel k (‖k‖₂² of a 2-D Gaussian of σ_k px: 1/(4π σ_k²)), over the mask's share w of the
    kernel about σ‖k‖₂/√w."""
    weight = np.maximum(ndimage.gaussian_filter(valid.numpy().astype(np.float64), width_px, mode="constant"), 1e-12)
    out = np.empty((r.shape[0], *valid.shape))
    for j in range(r.shape[0]):
        total = ndimage.gaussian_filter(np.where(valid.numpy(), r[j].numpy(), 0.0), width_px, mode="constant")
        out[j] = total / weight / float(sigma[j])
    return out, 1.0 / (2.0 * math.sqrt(math.pi) * width_px) / np.sqrt(weight)


def structure_notes(finding: StructureFinding, fitted_pixels: int) -> list[str]:
    """One line for the user where structure was found."""
    if finding.count == 0:
        return []
    where = f" in {', '.join(f'{w:g}' for w in finding.bands_nm)} nm" if finding.bands_nm else ""
    return [f"the residual has a shape the model does not hold (a vein, a hair, a fold?) on {finding.count} pixel(s) "
            f"({finding.count / max(fitted_pixels, 1):.1%}) in {finding.regions} region(s){where}: flagged 'structure'; "
            "the maps there carry the model's error as well as the noise's"]


def structure_widening(flagged: torch.Tensor, residual: torch.Tensor, used: torch.Tensor, fitted: torch.Tensor,
                       names: list[str]) -> torch.Tensor:
    """Per map of ``names`` and pixel ``(len(names), H·W)``, the factor σ is widened by: on a flagged pixel
    the ratio of its residual's RMS over the used bands to the noise's (the Birge ratio: the residual the
    model left says how far its maps may be off, beyond the noise), at least 1, times the map's
    ``STRUCTURE_SIGMA_ON``; 1 elsewhere."""
    r = residual.detach().double().cpu()
    bands = [j for j in range(r.shape[0]) if bool(used[j])]
    mask = flagged.cpu()
    try:
        sigma = band_noise(r[bands], fitted.cpu() & ~mask)  # the white part, on the fitted pixels away from the structure
    except ValueError:  # the structure covers nearly everything: the white part over all fitted pixels
        sigma = band_noise(r[bands], fitted.cpu())
    ratio = ((r[bands] / sigma[:, None, None]) ** 2).mean(0).sqrt().clamp_min(1.0)
    per_map = torch.tensor([STRUCTURE_SIGMA_ON[n] for n in names], dtype=ratio.dtype)[:, None, None] * ratio
    return torch.where(mask, per_map, torch.ones_like(per_map)).reshape(len(names), -1)
