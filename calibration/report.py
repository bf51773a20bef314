"""The contact sheet: one glance at a calibration.

Per band, a column: above, the skin frame (superpixels, dark-subtracted) with the detected window
outlined in red and the gray card's region in cyan; below, the calibrated band on one common
reflectance scale, masked pixels in magenta. A band whose title is red carries a flag.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

__all__ = ["Thumbnail", "thumbnail", "write_contact_sheet"]

_THUMB_PX = 320


@dataclass(frozen=True)
class Thumbnail:
    """A reduced skin frame ``(h, w)`` with the window ``corners`` ``(4, 2)`` and the gray card box in its pixels."""

    image: np.ndarray
    corners: np.ndarray
    card: Optional[tuple[float, float, float, float]]


def thumbnail(image: np.ndarray, corners: np.ndarray, card: Optional[Sequence[int]] = None) -> Thumbnail:
    """Reduce a superpixel frame to at most 320 px wide (area averaging), carrying the overlays along."""
    h, w = image.shape
    s = min(1.0, _THUMB_PX / max(h, w))
    small = cv2.resize(np.asarray(image, np.float32), (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    sx, sy = small.shape[1] / w, small.shape[0] / h
    scaled = (np.asarray(corners) + 0.5) * [sx, sy] - 0.5
    box = None if card is None else (card[0] * sx - 0.5, card[1] * sy - 0.5, card[2] * sx - 0.5, card[3] * sy - 0.5)
    return Thumbnail(small, scaled, box)


def write_contact_sheet(
    path: Path,
    wavelengths_nm: Sequence[float],
    thumbs: Sequence[Thumbnail],
    cube: np.ndarray,
    mask: np.ndarray,
    captions: Sequence[str],
    flagged: Sequence[bool],
    title: str,
) -> Path:
    """Write the PNG: ``cube`` ``(L, H, W)`` reflectance, ``mask`` ``(H, W)`` bool; one caption per band."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.patches import Polygon, Rectangle  # noqa: PLC0415

    n = len(wavelengths_nm)
    valid = cube[:, mask] if mask.any() else cube.reshape(n, -1)
    vmax = float(np.percentile(valid, 99.5)) if valid.size else 1.0
    vmax = vmax if np.isfinite(vmax) and vmax > 0 else 1.0
    fig, axes = plt.subplots(2, n, figsize=(2.2 * n + 1.2, 5.0), squeeze=False, constrained_layout=True)
    overlay = np.zeros((*mask.shape, 4))
    overlay[~mask] = (1.0, 0.0, 1.0, 0.8)
    im = None
    for k in range(n):
        top, bottom = axes[0, k], axes[1, k]
        t = thumbs[k]
        lo, hi = np.percentile(t.image, [1, 99.5])
        top.imshow(t.image, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1)
        top.add_patch(Polygon(t.corners, closed=True, fill=False, edgecolor="red", linewidth=1.0))
        if t.card is not None:
            x0, y0, x1, y1 = t.card
            top.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="cyan", linewidth=0.8))
        top.set_title(f"{wavelengths_nm[k]:g} nm", color="red" if flagged[k] else "black", fontsize=9)
        im = bottom.imshow(cube[k], cmap="viridis", vmin=0.0, vmax=vmax)
        bottom.imshow(overlay)
        bottom.set_title(captions[k], fontsize=7, color="red" if flagged[k] else "black")
        for ax in (top, bottom):
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(im, ax=axes[1, :].tolist(), shrink=0.8, label="reflectance")
    fig.suptitle(title, fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
