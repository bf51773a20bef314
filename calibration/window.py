"""The window: find the bright square of skin inside the dark tape, with sub-pixel corners, and rectify it.

Detection works on one superpixel image ``(H, W)``. The pipeline gives it the skin frame divided by its
band's Spectralon frame (both dark-subtracted): that ratio is the reflectance, flat across the frame —
vignetting and the flash's shape cancel — so the tape (~0.03) and the skin (0.1–0.6) differ by the same
large factor everywhere and at every band, the dark blue ones included, and the gray card (≈ 1 there) is
cut out. In four steps:

1. **Coarse.** Otsu's threshold (Otsu 1979) of the smoothed image, the gray card's region (``exclude``,
   widened by its blurred border) left out of both the threshold and the search; a separability η below
   0.75 means nothing stands out of the tape. A closing wider than a hair bridges the hairs and dark
   freckles that would split or notch the window. Every bright connected region that does not touch the
   image border or the card's region, is large enough, is well described by a quadrilateral (its area
   ≥ 90% of the four-sided polygon around it) and is surrounded by dark (the tape) is a candidate; exactly
   one must remain. Its sides are lines fitted to its outline.
2. **Edge points.** Along each side, away from the corners, the lightly smoothed image is sampled on
   lines normal to the side (cubic spline, 1/4-pixel steps); an edge point is the maximum of the inward
   derivative, refined by a parabola. A total-least-squares line through a side's points (outliers beyond
   3 robust sigma dropped: hairs, freckles at the edge) gives the side; adjacent sides meet at the
   corners. Done three times, searching ±3% of the side first (the outline lies inside the edge, the skin
   darkening towards the tape), then ±4 and ±2 px along the fitted lines.
3. **Edge model.** Under the window's light, skin near the tape is darker than in the middle (light
   entering through the window leaks under the tape and is lost there) — physics, not an error — and
   that darkening moves a derivative peak inward. Each side's angle and offset are therefore refitted
   with a physical model of the edge (``_edge_model.py``) to the pixels around it, stretch by stretch.
4. **One blur.** A side whose fitted blur strays from the others' median by more than 25% (a freckle on
   the edge led its fit astray) is fitted again with the others' blur.

Coordinates are ``(x, y)`` with the origin at the centre of the top-left pixel (OpenCV's convention);
corners are ordered top-left, top-right, bottom-right, bottom-left as seen in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence

import cv2
import numpy as np
from scipy import ndimage

from ._edge_model import fit_edge_line
from .errors import WindowNotFoundError

__all__ = ["Window", "box_filter", "find_window", "order_corners", "raw_to_superpixel_xy", "rectify", "superpixel_to_raw_xy", "window_interior"]

_INTERPOLATION = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4}
_SMOOTH_SIGMA_PX = 1.0  # pre-smoothing of the sub-pixel step: noise against a wider (still symmetric) edge
_STEP_PX = 0.25  # sampling step along the normals
_COARSE_REACH = 0.03  # first edge search, as a fraction of the window side
_HAIR_BRIDGE = 0.01  # half-width of the closing that bridges hairs, as a fraction of the frame
_CARD_MARGIN_PX = 4  # the gray card's box widened by its blurred border (superpixels)
_MIN_SEPARABILITY = 0.75  # Otsu's η below which nothing stands out of the tape
_BLUR_TOLERANCE = 0.25  # a side's fitted blur this far (relative) from the others' median is refitted with it


@dataclass(frozen=True)
class Window:
    """A detected window: ``corners`` ``(4, 2)`` (x, y) px, TL, TR, BR, BL; ``edge_rms_px``: RMS distance
    of the derivative-peak edge points to their sides (the edges' straightness and noise);
    ``edge_points``: points used over the four sides; ``model_sides``: sides refitted by the edge model
    (4 normally; a side whose fit failed keeps its derivative-peak line); ``blur_px``: the median blur σ
    the edge model found (the camera's PSF with the pixel, NaN without the model)."""

    corners: np.ndarray
    edge_rms_px: float
    edge_points: int
    model_sides: int = 0
    blur_px: float = float("nan")


def superpixel_to_raw_xy(xy: np.ndarray, centroid: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """Superpixel ``(x, y)`` → raw photosite ``(x, y)`` (pixel-centre origins): superpixel 0 spans photosites
    0–1 and samples at ``centroid`` within its cell (``raw.cell_centroid``; the cell's centre by default)."""
    return 2.0 * np.asarray(xy, dtype=np.float64) + np.asarray(centroid, dtype=np.float64)


def raw_to_superpixel_xy(xy: np.ndarray, centroid: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """Inverse of :func:`superpixel_to_raw_xy`."""
    return (np.asarray(xy, dtype=np.float64) - np.asarray(centroid, dtype=np.float64)) / 2.0


def order_corners(points: np.ndarray) -> np.ndarray:
    """Four points ``(4, 2)`` ordered clockwise in the image (y down) from the top-left one."""
    p = np.asarray(points, dtype=np.float64).reshape(4, 2)
    c = p.mean(axis=0)
    p = p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]
    return np.roll(p, -int(np.argmin(p.sum(axis=1))), axis=0)


def find_window(
    image: np.ndarray,
    *,
    exclude: Sequence[Sequence[float]] = (),
    min_area_fraction: float = 0.002,
    max_ring_ratio: float = 0.7,
    edge_model: bool = True,
    cell_weights: np.ndarray | None = None,
    name: str = "image",
) -> Window:
    """The window of a superpixel image ``(H, W)`` (bright skin inside dark tape).

    ``image`` is best the skin frame over its band's reference (``pipeline``): that ratio is the
    reflectance, flat across the frame, so the tape/skin contrast is the same everywhere and at every
    band. ``exclude``: boxes ``[x0, y0, x1, y1]`` in this image's pixels that cannot hold the window (the
    gray card). ``edge_model``: refit the sides with the physical edge model (step 3); off, the corners
    are the derivative peaks' (faster, biased inward by the skin's darkening near the tape).
    ``cell_weights`` ``(2, 2)``: each photosite's share of a superpixel at this band (``raw.cell_weights``),
    the pixel footprint the edge model integrates over (a uniform square by default). Raises
    ``WindowNotFoundError`` naming ``name`` when there is no candidate, more than one, or a side
    cannot be located.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"{name}: window detection needs a 2-D image, got shape {img.shape}")
    quad = _coarse_quad(img, exclude, min_area_fraction, max_ring_ratio, name)
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
    # The coarse outline lies inside the edge (the skin darkens towards the tape; by how much:
    # docs/calibration.md, "From calibration/window.py"); the first search reaches past that
    # (``_COARSE_REACH``), the later ones only refine.
    searches = sorted({max(4.0, float(np.ceil(_COARSE_REACH * side))), 4.0, 2.0}, reverse=True)
    # Work on the window's neighbourhood only: a camera's full frame would make the splines slow.
    pad = int(searches[0]) + 24
    x0, y0 = (max(int(np.floor(v)) - pad, 0) for v in quad.min(axis=0))
    x1, y1 = (int(np.ceil(v)) + pad + 1 for v in quad.max(axis=0))
    crop = img[y0:y1, x0:x1]
    origin = np.array([x0, y0], dtype=np.float64)
    quad = quad - origin
    coeffs = ndimage.spline_filter(cv2.GaussianBlur(crop, (0, 0), _SMOOTH_SIGMA_PX).astype(np.float64), order=3, mode="nearest")
    for search in searches:
        lines, residuals = _fit_sides(coeffs, quad, search, name)
        quad = _intersect(lines)
        if not np.all(np.isfinite(quad)):
            raise WindowNotFoundError(f"{name}: window sides are parallel; no corners")
    blur, modelled = float("nan"), 0
    if edge_model:
        quad, modelled, blur = _edge_model_corners(crop, quad, lines, cell_weights, name)
    res = np.concatenate(residuals)
    return Window(
        corners=quad + origin,
        edge_rms_px=float(np.sqrt(np.mean(res**2))),
        edge_points=int(res.size),
        model_sides=modelled,
        blur_px=blur,
    )


def _edge_model_corners(crop: np.ndarray, quad: np.ndarray, lines, cell_weights, name: str):
    """Every side refitted with the physical edge model (``_edge_model.fit_edge_line``); returns the
    corners the refitted sides meet at, how many sides the model fitted and the PSF's σ (px)."""
    refits = [fit_edge_line(crop, quad[i], quad[(i + 1) % 4], n, cell_weights) for i, (n, _) in enumerate(lines)]
    sigmas = [r[2] for r in refits if r is not None]
    if len(sigmas) >= 3:
        # One PSF blurs every side: a side whose blur strays from the others' (a freckle or a hair on
        # the edge pulled its fit into another minimum) is fitted again with theirs.
        typical = float(np.median(sigmas))
        for i, (n, _) in enumerate(lines):
            if refits[i] is None or abs(refits[i][2] - typical) > _BLUR_TOLERANCE * typical:
                refits[i] = fit_edge_line(crop, quad[i], quad[(i + 1) % 4], n, cell_weights, typical)
        sigmas = [r[2] for r in refits if r is not None]
    lines = [(r[0], r[1]) if r is not None else line for r, line in zip(refits, lines)]
    refined = _intersect(lines)
    if not np.all(np.isfinite(refined)):
        raise WindowNotFoundError(f"{name}: window sides are parallel; no corners")
    return refined, len(sigmas), float(np.median(sigmas)) if sigmas else float("nan")


def _coarse_quad(img: np.ndarray, exclude, min_area_fraction: float, max_ring_ratio: float, name: str) -> np.ndarray:
    """The one bright, four-sided, dark-surrounded region of the image as its contour's four sides'
    points; raises ``WindowNotFoundError`` saying why where there is none or more than one."""
    h, w = img.shape
    allowed, cut = _allowed_region(h, w, exclude)
    card = "; the gray card's region is left out" if exclude else ""
    bright = _bright_regions(img, allowed, card, name)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    min_area = min_area_fraction * h * w
    candidates, reasons = [], []
    for k in range(1, count):
        x, y, bw, bh, area = (int(v) for v in stats[k])
        if area < min_area:
            continue
        found = _candidate(img, labels, k, (x, y, bw, bh), cut, max_ring_ratio)
        (reasons if isinstance(found, str) else candidates).append(found)
    if not candidates:
        why = "; ".join(reasons[:3]) if reasons else f"no bright region of at least {min_area:.0f} px"
        raise WindowNotFoundError(f"{name}: no window found ({why}{card})")
    if len(candidates) > 1:
        centres = ", ".join(f"({c[:, 0].mean():.0f}, {c[:, 1].mean():.0f})" for c in candidates)
        raise WindowNotFoundError(f"{name}: {len(candidates)} window candidates at {centres} px; expected one (ambiguous)")
    return candidates[0]


def _allowed_region(h: int, w: int, exclude):
    """The pixels that may hold the window ``(H, W)`` and the cut-out boxes: the gray card's region,
    widened by its blurred border, takes no part in the threshold and can neither be taken for the
    window nor merge with it."""
    allowed, cut = np.ones((h, w), bool), []
    for e in exclude:
        ex0, ey0 = (max(int(np.floor(v)) - _CARD_MARGIN_PX, 0) for v in e[:2])
        ex1, ey1 = (max(int(np.ceil(v)) + _CARD_MARGIN_PX, 0) for v in e[2:])
        allowed[ey0:ey1, ex0:ex1] = False
        cut.append((ex0 - 1, ey0 - 1, ex1 + 1, ey1 + 1))
    return allowed, cut


def _bright_regions(img: np.ndarray, allowed: np.ndarray, card: str, name: str) -> np.ndarray:
    """Otsu's bright class of the smoothed image (uint8 mask), opened, and closed wider than a hair."""
    h, w = img.shape
    smooth = cv2.GaussianBlur(img, (0, 0), 1.5)
    values = smooth[allowed]
    if values.size == 0:
        raise WindowNotFoundError(f"{name}: no window found (the gray card's region covers the image)")
    lo, hi = np.percentile(values, [0.5, 99.5])
    if not hi > lo:
        raise WindowNotFoundError(f"{name}: no window found (the image is flat{card})")
    u8 = np.clip((smooth - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)
    level, _ = cv2.threshold(u8[allowed].reshape(1, -1), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    separability = _separability(u8[allowed], level)
    if separability < _MIN_SEPARABILITY:
        raise WindowNotFoundError(
            f"{name}: no window found (nothing bright stands out of the tape: Otsu's separability {separability:.2f} "
            f"< {_MIN_SEPARABILITY:g}{card})"
        )
    bright = ((u8 > level) & allowed).astype(np.uint8)
    bright = cv2.morphologyEx(bright, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    # Hairs and dark freckles crossing the window (or its edge) would split or notch it: a closing wider
    # than a hair bridges them. Its width follows the frame, of which the window is a large part.
    k = 2 * max(1, int(round(_HAIR_BRIDGE * min(h, w)))) + 1
    return cv2.morphologyEx(bright, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))


def _candidate(img: np.ndarray, labels: np.ndarray, k: int, box, cut, max_ring_ratio: float):
    """Region ``k`` (bounding ``box`` x, y, w, h) as a window candidate (its sides' points), or the
    reason it is none."""
    h, w = img.shape
    x, y, bw, bh = box
    where = f"region at x {x}–{x + bw}, y {y}–{y + bh}"
    if x == 0 or y == 0 or x + bw >= w or y + bh >= h:
        return f"{where} touches the image border"
    if any(x < c[2] and c[0] < x + bw and y < c[3] and c[1] < y + bh for c in cut):
        return f"{where} touches the gray card's region (the card's border?)"
    region = (labels[y : y + bh, x : x + bw] == k).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea) + np.array([x, y])
    quad = _four_sides(contour)
    if quad is None:
        return f"{where} is not four-sided"
    fill = cv2.contourArea(contour) / max(cv2.contourArea(quad.astype(np.float32)), 1.0)
    if fill < 0.9:
        return f"{where} fills only {fill:.0%} of its quadrilateral"
    ratio = _ring_ratio(img, quad)
    if not ratio < max_ring_ratio:
        return f"{where}: its surround is not dark (ratio {ratio:.2f} ≥ {max_ring_ratio:g})"
    return _contour_sides(contour.reshape(-1, 2).astype(np.float64), quad)


def _separability(values: np.ndarray, level: float) -> float:
    """Otsu's separability η = σ_between² / σ_total² of ``values`` split at ``level`` (Otsu 1979, eq. 12):
    near 1 for tape and skin, 2/π ≈ 0.64 for a single Gaussian (noise alone)."""
    v = values.astype(np.float64).ravel()
    total = v.var()
    if not total > 0:
        return 0.0
    high = v > level
    w1 = high.mean()
    if w1 in (0.0, 1.0):
        return 0.0
    return float(w1 * (1 - w1) * (v[high].mean() - v[~high].mean()) ** 2 / total)


def _four_sides(contour: np.ndarray) -> np.ndarray | None:
    hull = cv2.convexHull(contour)
    perimeter = cv2.arcLength(hull, True)
    for eps in np.linspace(0.005, 0.1, 40):
        poly = cv2.approxPolyDP(hull, eps * perimeter, True)
        if len(poly) == 4:
            return order_corners(poly.reshape(4, 2))
        if len(poly) < 4:
            return None
    return None


def _contour_sides(points: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """The corners of lines fitted to the region's outline along the middle of each side of ``quad``
    (the polygon approximation cuts the corners, which the skin's darkening rounds off most)."""
    centre = quad.mean(axis=0)
    lines = []
    for a, b in zip(quad, np.roll(quad, -1, axis=0)):
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        n = np.array([u[1], -u[0]]) if np.dot(centre - a, [u[1], -u[0]]) > 0 else np.array([-u[1], u[0]])
        t, d = (points - a) @ u, (points - a) @ n
        near = (t > 0.15 * length) & (t < 0.85 * length) & (np.abs(d) < max(3.0, 0.05 * length))
        fit = _tls_line(points[near], n)
        if fit is None:
            return quad
        lines.append(fit[0])
    corners = _intersect(lines)
    return corners if np.all(np.isfinite(corners)) else quad


def _ring_ratio(img: np.ndarray, quad: np.ndarray) -> float:
    """Median of a ring just outside the quadrilateral over the median well inside it."""
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
    pad = max(3, int(round(0.15 * side)))
    inner = np.zeros(img.shape, np.uint8)
    cv2.fillConvexPoly(inner, np.round(quad).astype(np.int32), 1)
    core = cv2.erode(inner, np.ones((pad, pad), np.uint8))
    near = cv2.dilate(inner, np.ones((5, 5), np.uint8))
    ring = cv2.dilate(inner, np.ones((2 * pad + 1, 2 * pad + 1), np.uint8)).astype(bool) & ~near.astype(bool)
    if not core.any() or not ring.any():
        return float("inf")
    inside = float(np.median(img[core.astype(bool)]))
    return float(np.median(img[ring])) / inside if inside > 0 else float("inf")


_SIDES = ("top", "right", "bottom", "left")


def _fit_sides(coeffs: np.ndarray, quad: np.ndarray, search_px: float, name: str) -> tuple[list, list]:
    """Lines ``(n, c)`` with ``n · p = c`` (``n`` the unit inward normal) through the sub-pixel edge points."""
    centre = quad.mean(axis=0)
    offsets = np.arange(-search_px, search_px + _STEP_PX / 2, _STEP_PX)
    lines, residuals = [], []
    for side, a, b in zip(_SIDES, quad, np.roll(quad, -1, axis=0)):
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        n = np.array([u[1], -u[0]])
        if np.dot(centre - a, n) < 0:
            n = -n
        margin = search_px + 3.0 + 0.04 * length
        t = np.arange(margin, length - margin, 1.0)
        if t.size < 5:
            raise WindowNotFoundError(f"{name}: the window's {side} side ({length:.1f} px) is too short to locate")
        base = a + t[:, None] * u
        pts = base[:, None, :] + offsets[None, :, None] * n
        prof = ndimage.map_coordinates(coeffs, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=3, mode="nearest", prefilter=False)
        deriv = np.gradient(prof.reshape(pts.shape[:2]), _STEP_PX, axis=1)
        k = np.argmax(deriv, axis=1)
        rows = np.arange(t.size)
        ok = (k > 0) & (k < offsets.size - 1)
        ok &= deriv[rows, k] > 0.3 * np.median(deriv[rows, k])
        k, rows = k[ok], rows[ok]
        g0, gm, gp = deriv[rows, k], deriv[rows, k - 1], deriv[rows, k + 1]
        denom = gm - 2 * g0 + gp
        delta = np.where(denom < 0, 0.5 * (gm - gp) / np.where(denom < 0, denom, -1.0), 0.0)
        points = base[rows] + (offsets[k] + delta * _STEP_PX)[:, None] * n
        fit = _tls_line(points, n)
        if fit is None:
            raise WindowNotFoundError(
                f"{name}: the window's {side} side shows too few edge points ({len(points)} of {t.size} profiles "
                f"have a tape-to-skin step within ±{search_px:g} px of the coarse outline)"
            )
        lines.append(fit[0])
        residuals.append(fit[1])
    return lines, residuals


def _tls_line(points: np.ndarray, inward: np.ndarray) -> tuple[tuple[np.ndarray, float], np.ndarray] | None:
    """Total-least-squares line through ``points`` and the residuals of those kept; points beyond 3
    robust sigma dropped, three rounds. None with fewer than 5 points."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        p = points[keep]
        if len(p) < 5:
            return None
        c = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        n = vt[1] if np.dot(vt[1], inward) > 0 else -vt[1]
        r = (points - c) @ n
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        keep = np.abs(r) <= max(3.0 * mad, 0.05)
    if keep.sum() < 5:
        return None
    return (n, float(c @ n)), r[keep]


def _intersect(lines: list) -> np.ndarray:
    """Corners from sides TL→TR, TR→BR, BR→BL, BL→TL: corner i is where side i−1 meets side i."""
    corners = []
    for i in range(4):
        (n1, c1), (n2, c2) = lines[i - 1], lines[i]
        a = np.array([n1, n2])
        if abs(np.linalg.det(a)) < 1e-9:
            return np.full((4, 2), np.nan)
        corners.append(np.linalg.solve(a, [c1, c2]))
    return np.array(corners)


def rectify(
    image: np.ndarray, corners: np.ndarray, size_px: int, interpolation: Literal["linear", "cubic", "lanczos"] = "cubic"
) -> np.ndarray:
    """Resample the quadrilateral ``corners`` (TL, TR, BR, BL) of ``image`` ``(H, W)`` to a square ``(N, N)``.

    The window's corners map to the outer corners of the square's corner pixels, so output pixel ``i``
    covers ``[i, i + 1] / N`` of the window side. OpenCV's homography (``getPerspectiveTransform``) and
    ``warpPerspective`` with the inverse map, so every output pixel is sampled exactly once.
    """
    n = int(size_px)
    dst = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]], np.float32)
    h = cv2.getPerspectiveTransform(dst, np.asarray(corners, np.float32))
    return cv2.warpPerspective(
        np.asarray(image, np.float32),
        h,
        (n, n),
        flags=_INTERPOLATION[interpolation] | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def box_filter(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean of ``factor × factor`` blocks: ``(..., H, W)`` → ``(..., H / factor, W / factor)``."""
    h, w = image.shape[-2:]
    if factor < 1 or h % factor or w % factor:
        raise ValueError(f"box filter factor {factor} does not divide the image size {h}×{w}")
    return image.reshape(*image.shape[:-2], h // factor, factor, w // factor, factor).mean(axis=(-3, -1))


def window_interior(inside: np.ndarray, blur_px: float) -> np.ndarray:
    """The window ``inside`` ``(H, W)`` bool less its edge: the superpixels within the edge's blur (2σ, at
    least one) of the tape, which are part tape and dark. They stay masked, but are not counted in the
    exposure fractions, so a clean session raises no exposure flag (docs/calibration.md, "Figures from
    the code": where a clean session's under-exposed superpixels lay)."""
    reach = max(1, math.ceil(2.0 * blur_px)) if math.isfinite(blur_px) else 1
    interior = cv2.erode(inside.astype(np.uint8), np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)
    return interior if interior.any() else inside
