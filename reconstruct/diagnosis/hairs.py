"""Hairs found in the cube, so that the maps they bias are flagged and the user is told.

The fit's skin has no hair (``absorbers.py`` explains why fitting one did not pay): a hair darkens every
band about alike (a grey interface absorbance, DWRR08 §4.2) and, in red light, takes light from its
neighbours up to a fraction of a millimetre away. Left alone, melanin and blood take its place and the
residual stays near the noise (docs/stability.md): a silent failure. What is done here is detection.

Where the skin's own contrast is weakest — the red bands (≥ ``RED_FROM_NM``), where melanin and blood
absorb least — a hair is the strongest thin dark feature. The mean log reflectance of those bands is
closed (grey-scale morphology) with a square ``CLOSING_MM`` either side: wider than a hair (40–80 µm),
narrower than a freckle or a vein (radius ≥ 0.12 and 0.25 mm), so the black top-hat (closing − image)
keeps hairs and leaves them. A pixel is a hair's where the top-hat exceeds ``HAIR_Z`` × the noise σ of
that mean (``grid_choice.band_noise``, the cube's own) and the other bands' top-hat is at most
``GREY_RATIO`` times it (a hair is grey; a small freckle darkens the blue, a thin vessel the green,
more than the red); connected hair pixels shorter than
``MIN_LENGTH_MM`` are dropped (noise, pores). The window's own edge, dark where its light leaks under
the tape, is not searched (the mask eroded by the closing's width and a pixel). The hair's pixels and a
``HALO_MM`` ring around them are flagged.

Shapes: reflectance ``(L, H, W)``, masks ``(H, W)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

__all__ = ["CLOSING_MM", "HAIR_SIGMA_AWAY", "HAIR_SIGMA_ON", "HAIR_Z", "HALO_MM", "MIN_LENGTH_MM", "RED_FROM_NM", "HairFinding",
           "find_hairs", "hair_notes", "hair_widening"]

#: The bands the finder looks at (nm and above).
RED_FROM_NM = 600.0
#: The closing's half-width (mm): wider than a hair, narrower than a freckle or a vein; at least a pixel.
CLOSING_MM = 0.1
#: A pixel is a hair's where the top-hat exceeds this many noise σ: above what the top-hat of hairless
#: skin reaches at its 99.9th percentile (docs/stability.md, "From reconstruct/diagnosis/hairs.py").
HAIR_Z = 6.0
#: The noise σ of the red bands' mean log reflectance is taken as at least this: a cube smoother than a
#: camera makes (a render without noise) would otherwise call every faint line of the skin a hair.
MIN_SIGMA = 2e-3
#: A hair's pixel is grey: the rest of the spectrum's top-hat at most this many times the red one's. The
#: ratio lies between hair pixels' (a hair's loss spreads wider in red light) and that of the freckles of
#: Table 2's darkest skin (V exterior) (docs/stability.md, "From reconstruct/diagnosis/hairs.py").
GREY_RATIO = 1.2
#: Connected hair pixels spanning less than this (mm; at least two pixels) are dropped.
MIN_LENGTH_MM = 0.4
#: The ring around a hair that is flagged with it (mm; at least a pixel): its halo in red light.
HALO_MM = 0.3


#: Where hairs were found, σ is widened by these factors per map: on the flagged pixels (``HAIR_SIGMA_ON``)
#: and elsewhere (``HAIR_SIGMA_AWAY``: the maps on nodes carry a hair's pull everywhere). Set on the
#: demo's scene with its five hairs (256², seed 0; docs/stability.md, "Hairs on the demo's scene"): the
#: factor each map's σ needed to cover 90% of the truth within 2σ. An uncertainty term of Type B, as
#: ``uncertainty.MODEL_FLOOR``.
HAIR_SIGMA_ON = {"C_m": 1.8, "beta_m": 1.7, "C_he": 1.0, "C_bc": 1.0, "C_hd": 2.7}
HAIR_SIGMA_AWAY = {"C_m": 1.0, "beta_m": 1.25, "C_he": 1.0, "C_bc": 1.0, "C_hd": 1.85}


@dataclass
class HairFinding:
    """``pixels`` ``(H, W)`` bool: on a hair; ``flagged``: those and their halo; ``count``: hairs (connected
    pieces) found."""

    pixels: torch.Tensor
    flagged: torch.Tensor
    count: int

    def as_dict(self) -> dict:
        return {"count": self.count, "hair_pixels": int(self.pixels.sum()), "flagged_pixels": int(self.flagged.sum())}


def find_hairs(reflectance: torch.Tensor, wavelength_nm: list[float], mask: torch.Tensor, mm_per_pixel: float,
               noise: torch.Tensor, bands_used: torch.Tensor | None = None) -> HairFinding:
    """The hairs in a cube ``(L, H, W)`` over ``mask``, with each band's noise σ ``(L,)`` (reflectance units);
    bands not in ``bands_used`` ``(L,)`` (dead ones) are not looked at."""
    h, w = mask.shape
    none = HairFinding(torch.zeros(h, w, dtype=torch.bool), torch.zeros(h, w, dtype=torch.bool), 0)
    used = [True] * len(wavelength_nm) if bands_used is None else [bool(u) for u in bands_used.tolist()]
    red = [j for j, nm in enumerate(wavelength_nm) if nm >= RED_FROM_NM and used[j]]
    inside = mask.cpu().numpy().astype(bool)
    if not red or inside.sum() < 16:
        return none
    r = reflectance[red].double().cpu().clamp_min(1e-6)
    level = r[:, torch.as_tensor(inside)].mean(1)  # (R,)
    # σ of the mean of the bands' logs: each band's σ relative to its level, averaged in quadrature
    sigma = max(float((noise[red].double().cpu() / level).pow(2).sum().sqrt() / len(red)), MIN_SIGMA)
    half = max(1, round(CLOSING_MM / mm_per_pixel))
    top_hat = _top_hat(reflectance[red], inside, half)
    # grey: no other part of the spectrum darkened much more (a freckle's melanin darkens the blue, a vein's
    # blood the green, several times the red)
    others = [j for j in range(len(wavelength_nm)) if j not in red and used[j]]
    grey = _top_hat(reflectance[others], inside, half) <= GREY_RATIO * top_hat if others else np.ones_like(inside)
    # the window's edge is a thin dark line too (its light leaks under the tape): searched only inside it
    search = ndimage.binary_erosion(inside, structure=np.ones((3, 3)), iterations=half + 1)
    hair = (top_hat > HAIR_Z * sigma) & grey & search
    labels, n = ndimage.label(hair, structure=np.ones((3, 3)))
    keep = np.zeros(n + 1, dtype=bool)
    min_px = max(2.0, MIN_LENGTH_MM / mm_per_pixel)
    for k, piece in enumerate(ndimage.find_objects(labels), start=1):
        span = max(piece[0].stop - piece[0].start, piece[1].stop - piece[1].start)
        keep[k] = span >= min_px
    hair = keep[labels]
    if not hair.any():
        return none
    ring = max(1, round(HALO_MM / mm_per_pixel))
    flagged = ndimage.binary_dilation(hair, structure=np.ones((2 * ring + 1, 2 * ring + 1))) & inside
    return HairFinding(torch.from_numpy(hair), torch.from_numpy(flagged), int(keep.sum()))


def hair_widening(flagged: torch.Tensor, names) -> torch.Tensor:
    """σ's factors ``(N_PARAMS, N)`` for pixels ``flagged`` ``(N,)`` (bool) or not, maps in the order ``names``."""
    on = torch.tensor([HAIR_SIGMA_ON[n] for n in names], dtype=torch.float64, device=flagged.device)[:, None]
    away = torch.tensor([HAIR_SIGMA_AWAY[n] for n in names], dtype=torch.float64, device=flagged.device)[:, None]
    return torch.where(flagged[None], on, away)


def _top_hat(bands: torch.Tensor, inside: np.ndarray, half: int) -> np.ndarray:
    """The black top-hat ``(H, W)`` of the mean log reflectance of ``bands`` ``(K, H, W)``: a square closing
    ``half`` pixels either side, minus the image (outside ``inside`` the image is its median: nothing there)."""
    g = bands.double().cpu().clamp_min(1e-6).log().mean(0).numpy()
    g = np.where(inside, g, np.median(g[inside]))
    return ndimage.grey_closing(g, size=(2 * half + 1, 2 * half + 1)) - g


def hair_notes(found: HairFinding, visible_pixels: int) -> list[str]:
    """A line when hairs were found: how many, what is flagged, what it means for the maps."""
    if found.count == 0:
        return []
    share = float(found.flagged.sum()) / max(visible_pixels, 1)
    return [f"{found.count} hair(s) found (thin dark lines in red light): their pixels and a {HALO_MM:g} mm halo are "
            f"flagged 'hair' ({int(found.flagged.sum())} pixels, {share:.0%} of the view); the model has no hair, so the maps "
            "there are biased (σ there is widened); shave or part the hair, or read the maps away from the flags"]
