"""The contact sheet: one glance at a calibration.

Per band, a column: above, the skin frame (superpixels, dark-subtracted) with the detected window
outlined in red and the gray card's region in cyan; below, the calibrated band on one common
reflectance scale (viridis, the scale bar on the right), masked pixels in magenta, and the band's
caption. A band whose title is red carries a flag. Drawn with OpenCV: a matplotlib figure cost a
noticeable share of a small calibration (timings: docs/calibration.md, "From calibration/report.py").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

__all__ = ["Thumbnail", "band_caption", "band_snr", "thumbnail", "write_contact_sheet"]

_THUMB_PX = 320
_PANEL_PX = 240  # width of a band's column
_GAP_PX = 12
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_RED, _CYAN, _MAGENTA, _BLACK, _WHITE = (0, 0, 220), (220, 200, 0), (255, 0, 255), (0, 0, 0), (255, 255, 255)


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


def _ascii(text: str) -> str:
    """OpenCV's Hershey fonts draw ASCII only."""
    return text.encode("ascii", "replace").decode("ascii")


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.45, colour=_BLACK) -> None:
    cv2.putText(canvas, _ascii(text), (x, y), _FONT, scale, colour, 1, cv2.LINE_AA)


def _frame_panel(t: Thumbnail) -> np.ndarray:
    """The skin frame in gray, window and card drawn on it, ``_PANEL_PX`` wide ``(h, w, 3)`` uint8."""
    lo, hi = np.percentile(t.image, [1, 99.5])
    gray = np.clip((t.image - lo) / (hi - lo if hi > lo else 1.0) * 255.0, 0, 255).astype(np.uint8)
    s = _PANEL_PX / gray.shape[1]
    panel = cv2.cvtColor(cv2.resize(gray, (_PANEL_PX, max(1, round(gray.shape[0] * s))), interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
    corners = np.round(((t.corners + 0.5) * s - 0.5) * 16).astype(np.int32)
    cv2.polylines(panel, [corners], True, _RED, 1, cv2.LINE_AA, shift=4)
    if t.card is not None:
        x0, y0, x1, y1 = (int(round((v + 0.5) * s - 0.5)) for v in t.card)
        cv2.rectangle(panel, (x0, y0), (x1, y1), _CYAN, 1)
    return panel


def _band_panel(band: np.ndarray, mask: np.ndarray, vmax: float) -> np.ndarray:
    """A cube band in viridis on ``[0, vmax]``, masked pixels magenta, ``_PANEL_PX`` square."""
    level = np.clip(np.nan_to_num(band) / vmax * 255.0, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(level, cv2.COLORMAP_VIRIDIS)
    rgb[~mask] = _MAGENTA
    return cv2.resize(rgb, (_PANEL_PX, _PANEL_PX), interpolation=cv2.INTER_NEAREST)


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
    """Write the PNG: ``cube`` ``(L, H, W)`` reflectance, ``mask`` ``(H, W)`` bool; one caption (lines
    separated by newlines) per band."""
    n = len(wavelengths_nm)
    valid = cube[:, mask] if mask.any() else cube.reshape(n, -1)
    vmax = float(np.percentile(valid, 99.5)) if valid.size else 1.0
    vmax = vmax if np.isfinite(vmax) and vmax > 0 else 1.0
    tops = [_frame_panel(t) for t in thumbs]
    top_h = max(p.shape[0] for p in tops)
    lines = max(len(c.split("\n")) for c in captions) if captions else 0
    title_h, label_h, caption_h, bar_w = 34, 22, 8 + 18 * lines, 90
    height = title_h + label_h + top_h + _GAP_PX + _PANEL_PX + caption_h
    width = _GAP_PX + n * (_PANEL_PX + _GAP_PX) + bar_w
    canvas = np.full((height, width, 3), 255, np.uint8)
    _text(canvas, title, _GAP_PX, 22, 0.55)
    for k in range(n):
        x = _GAP_PX + k * (_PANEL_PX + _GAP_PX)
        y = title_h + label_h
        _text(canvas, f"{wavelengths_nm[k]:g} nm", x, y - 6, 0.5, _RED if flagged[k] else _BLACK)
        canvas[y : y + tops[k].shape[0], x : x + _PANEL_PX] = tops[k]
        y += top_h + _GAP_PX
        canvas[y : y + _PANEL_PX, x : x + _PANEL_PX] = _band_panel(cube[k], mask, vmax)
        for j, line in enumerate(captions[k].split("\n")):
            _text(canvas, line, x, y + _PANEL_PX + 18 * (j + 1), 0.42, _RED if flagged[k] else _BLACK)
    # the common reflectance scale beside the bands
    x, y = width - bar_w + 8, title_h + label_h + top_h + _GAP_PX
    ramp = np.linspace(255, 0, _PANEL_PX).astype(np.uint8)[:, None].repeat(16, axis=1)
    canvas[y : y + _PANEL_PX, x : x + 16] = cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)
    _text(canvas, f"{vmax:.2f}", x + 20, y + 10, 0.4)
    _text(canvas, "0", x + 20, y + _PANEL_PX, 0.4)
    _text(canvas, "R", x + 20, y + _PANEL_PX // 2, 0.4)
    path = Path(path)
    if not cv2.imwrite(str(path), canvas):
        raise OSError(f"{path}: cannot write the contact sheet")
    return path


def band_snr(band: np.ndarray, mask: np.ndarray) -> float:
    """Median over the noise σ of Immerkær's estimator ("Fast noise variance estimation", CVIU 1996):
    σ = √(π/2) / 6 · mean |I ∗ N|, N = [[1, −2, 1], [−2, 4, −2], [1, −2, 1]], over valid 3×3 neighbourhoods.
    On the cube grid, after resampling: texture finer than a few pixels counts as noise (a lower bound)."""
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if inner.sum() < 16:
        return float("nan")
    response = cv2.filter2D(band.astype(np.float32), -1, kernel, borderType=cv2.BORDER_REPLICATE)
    sigma = math.sqrt(math.pi / 2) / 6.0 * float(np.mean(np.abs(response[inner])))
    return float(np.median(band[mask])) / sigma if sigma > 0 else float("inf")


def band_caption(entry: dict, reference: bool, flag_codes: Sequence[str] = ()) -> str:
    """A band's caption on the contact sheet: its flash factor, SNR, alignment shift and saturated share,
    and the flags that mark it (red) by name, so the sheet says why."""
    dx, dy = entry["alignment_shift_px"]
    if reference:
        shift = "(reference band)"
    else:
        shift = "-" if dx is None else f"{dx:+.2f}, {dy:+.2f}" + ("" if entry["alignment_applied"] else " (not applied)")
    snr = "-" if entry["snr"] is None else f"{entry['snr']:.0f}"
    caption = f"flash x{entry['flash_factor']:.3f}  SNR {snr}\nshift {shift}\nsat {entry['saturated_fraction']:.1%}"
    return caption + "".join(f"\n{code.replace('_', ' ')}" for code in dict.fromkeys(flag_codes))
