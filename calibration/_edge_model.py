"""A physical model of the window's edge in the image, fitted to the pixels along one side.

Skin lit only through the window shows, at the tape's edge, half its plateau: for a homogeneous
medium lit on a half plane, what leaves at the edge is what full light would bring from the lit half.
Inward the skin brightens as the light that would have come from under the tape is missing ever less.
Pre-blur, at signed inward distance x from the edge:

    O(x) = t                                                      x < 0   (tape)
    O(x) = s (1 − (1 − e) (w e^{−x/ℓ1} + (1 − w) e^{−x/ℓ2}))        x ≥ 0   (skin)

Two exponentials describe the rise the model's renderer gives (Table 2 skin, 7.5 mm window, 430–670
nm) closely (how closely: docs/calibration.md, "From calibration/_edge_model.py"). The camera blurs by
a Gaussian PSF σ, whose blur of ``H(x) e^{−x/ℓ}`` is ``exp(σ²/2ℓ² − x/ℓ) Φ(x/σ − σ/ℓ)``, and
integrates over each pixel: a superpixel over its four photosites' squares, weighted by their channels'
share of the band (``raw.cell_weights``), projected exactly on the side's normal for the side's angle. The skin level varies linearly along the
side (vignetting, texture).

The edge's share ``e`` is ½ in principle, but ``s`` is the plateau the two exponentials extrapolate from
the 10 px inside that the fit sees, and where the slow part of the rise is barely seen (in the blue, the
skin is still short of its plateau well inside a full-size window) that extrapolation overshoots: held
at ½, the fitted edge moved inward on every side, more at the corners; left free it is held only by a
weak prior towards ½ (``_EDGE_PRIOR``), which steadies the small windows whose rise is too short to tell
from the step (measurements: docs/calibration.md, "From calibration/_edge_model.py").

Why a model: a derivative peak sits inside the true edge when the skin darkens towards it (by about
σ² × ramp slope / step height, a fraction of a pixel on a small window: docs/calibration.md, "From
calibration/_edge_model.py"), and interpolating a sampled edge a fraction of a pixel wide biases it with
the pixel phase. Fitting the side's angle and offset together
with the profile removes both. Last, each stretch of ``_SEGMENT_PX`` along the side is refitted for its
own offset and levels, and a robust line through those replaces the whole-side fit (``_segment_line``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_edge_line"]

_GRID_STEP_PX = 0.04  # resolution of the model along the normal
# weight of the prior e ≈ ½, per √(pixels fitted): against none it brings the worst corner of small
# windows closer to the true edge (measurements: docs/calibration.md, "From calibration/_edge_model.py")
_EDGE_PRIOR = 0.02
_INSIDE_PX, _OUTSIDE_PX = 10.0, 6.0  # pixels used on either side of the edge
_SEGMENT_PX = 8.0  # length of the stretches of a side refitted on their own
_MIN_SEGMENTS = 5  # fewer segments (kept): the whole side's fit stands
# the segments look only this far inside: a freckle a few px in shifts a segment's edge (the worst corner of
# small windows is closer with 6 px than with 10: docs/calibration.md, "From calibration/_edge_model.py")
_SEGMENT_INSIDE_PX = 6.0
_SEGMENT_REACH_PX, _SEGMENT_STEP_PX = 1.5, 0.02  # shifts of a segment's edge tried, px


def fit_edge_line(
    img: np.ndarray, a: np.ndarray, b: np.ndarray, n: np.ndarray, cell_weights: np.ndarray | None = None,
    sigma_px: float | None = None,
) -> tuple[np.ndarray, float, float] | None:
    """Refit the side ``a → b`` (``(x, y)`` px; ``n`` its unit inward normal) of ``img`` ``(H, W)``, a
    superpixel image whose pixels weigh the four photosites of their cell by ``cell_weights`` ``(2, 2)``
    (``raw.cell_weights``; equal by default). ``sigma_px``: the blur, held at this value (the other
    sides' — one PSF blurs them all); None: fitted.

    Uses pixels within −6…+10 px of the side along its middle 80%. Returns ``(n, c, sigma_px)`` — the
    line ``n · p = c`` and the fitted blur — or None when the fit fails or moves the side by 3 px or more.
    """
    from scipy.optimize import least_squares  # noqa: PLC0415
    from scipy.special import log_ndtr, ndtr  # noqa: PLC0415

    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    mid = 0.5 * (a + b)
    reach = max(_INSIDE_PX, _OUTSIDE_PX) + 1
    x0, y0 = np.maximum(np.floor(np.minimum(a, b) - reach).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(np.maximum(a, b) + reach).astype(int), [img.shape[1] - 1, img.shape[0] - 1])
    ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
    p = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64) - mid
    d, along = p @ n, p @ u
    sel = (d > -_OUTSIDE_PX) & (d < _INSIDE_PX) & (np.abs(along) < 0.4 * length)
    if sel.sum() < 50:
        return None
    p, d, along = p[sel], d[sel], along[sel] / (0.4 * length)
    values = img[ys.ravel()[sel], xs.ravel()[sel]].astype(np.float64)
    tape0, skin0 = float(np.median(values[d < -3])), float(np.median(values[d > 6]))
    if not skin0 > tape0:
        return None
    y = (values - tape0) / (skin0 - tape0)

    grid = np.arange(-_OUTSIDE_PX - 8, _INSIDE_PX + 8, _GRID_STEP_PX)
    sub, sub_weight = _footprint(cell_weights)
    half = int(np.ceil(1.1 / _GRID_STEP_PX))

    def rotated(phi: float) -> np.ndarray:
        c, s = np.cos(phi), np.sin(phi)
        return np.array([n[0] * c - n[1] * s, n[0] * s + n[1] * c])

    def blurred_rise(x, sig, ell):
        return np.exp(np.clip(sig * sig / (2 * ell * ell) - x / ell + log_ndtr(x / sig - sig / ell), -700, 50))

    def profiles(q) -> tuple[np.ndarray, np.ndarray]:
        """The tape's and the skin's share of a pixel at signed distance ``grid`` from the edge."""
        phi, _, _, _, _, sig, w, l1, l2, edge = q
        footprint = np.bincount(np.round(sub @ rotated(phi) / _GRID_STEP_PX).astype(int) + half, sub_weight, 2 * half + 1)
        footprint = footprint / footprint.sum()
        step = ndtr(grid / sig)
        rise = w * blurred_rise(grid, sig, l1) + (1 - w) * blurred_rise(grid, sig, l2)
        return np.convolve(1 - step, footprint, mode="same"), np.convolve(step - (1 - edge) * rise, footprint, mode="same")

    def model(q):
        phi, off, tape, s0, s1 = q[:5]
        dark, lit = profiles(q)
        x = p @ rotated(phi) - off
        return tape * np.interp(x, grid, dark) + (s0 + s1 * along) * np.interp(x, grid, lit)

    #        angle  offset tape  skin slope  σ    w    ℓ1    ℓ2   edge
    q0 = [0.0, 0.0, 0.0, 1.0, 0.0, 0.8, 0.7, 1.5, 8.0, 0.5]
    lower = [-0.05, -3.0, -1.0, 0.2, -1.0, 0.2, 0.0, 0.05, 0.5, 0.2]
    upper = [0.05, 3.0, 1.0, 5.0, 1.0, 4.0, 1.0, 30.0, 300.0, 0.8]
    if sigma_px is not None:
        q0[5] = float(np.clip(sigma_px, lower[5], upper[5]))
        lower[5], upper[5] = q0[5] * (1 - 1e-6), q0[5] * (1 + 1e-6)
    prior = _EDGE_PRIOR * np.sqrt(y.size)

    def residuals(q):
        return np.append(model(q) - y, prior * (q[9] - 0.5))

    try:
        # lsmr: the dense SVD solver is much slower here when BLAS threads compete for the cores
        # (docs/calibration.md, "From calibration/_edge_model.py")
        fit = least_squares(
            residuals, q0, bounds=(lower, upper), loss="soft_l1", f_scale=0.1, x_scale="jac",
            tr_solver="lsmr", ftol=1e-6, xtol=1e-6,
        )
    except (ValueError, np.linalg.LinAlgError):
        return None
    phi, off, sigma = float(fit.x[0]), float(fit.x[1]), float(fit.x[5])
    if not fit.success or not np.isfinite(off) or abs(off) > 2.9:
        return None
    nn = rotated(phi)
    t_dir = np.array([nn[1], -nn[0]])
    dark, lit = profiles(fit.x)
    line = _segment_line(p @ nn - off, p @ t_dir, y, grid, dark, lit, length)
    if line is None:
        return nn, float((mid @ nn) + off), sigma
    (n2, c2) = line
    # the segments' line in the side's frame (x inward from the whole-side fit, t along it) → image
    normal = n2[0] * nn + n2[1] * t_dir
    return normal, float(mid @ normal + c2 + off * n2[0]), sigma


def _footprint(cell_weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``(K, 2)`` (superpixels, from the point the superpixel samples: its cell's weighted
    centroid) and weights ``(K,)`` of the area a superpixel integrates: its four photosites' squares
    (half a superpixel wide each), weighted by their channel's share of the band's signal."""
    w = np.full((2, 2), 0.25) if cell_weights is None else np.asarray(cell_weights, np.float64) / np.sum(cell_weights)
    cx, cy = w[:, 1].sum(), w[1, :].sum()
    s = ((np.arange(8) + 0.5) / 8 - 0.5) * 0.5
    square = np.stack(np.meshgrid(s, s), axis=-1).reshape(-1, 2)
    points = [square + [(dx - cx) / 2, (dy - cy) / 2] for dy in (0, 1) for dx in (0, 1)]
    weights = [np.full(len(square), w[dy, dx] / len(square)) for dy in (0, 1) for dx in (0, 1)]
    return np.concatenate(points), np.concatenate(weights)


def _segment_line(
    x: np.ndarray, t: np.ndarray, y: np.ndarray, grid: np.ndarray, dark: np.ndarray, lit: np.ndarray, length: float
) -> tuple[np.ndarray, float] | None:
    """The side again, from its segments: in each stretch of ``_SEGMENT_PX`` along it, the edge's shift
    with the fitted profile shape and the segment's own tape and skin levels and skin gradient; a line through the
    segments' edge points, the outliers dropped (a freckle, a hair or a vein at the edge moves its
    segment's edge, and a whole-side fit bends towards it). ``x``: pixels' inward distance from the
    whole-side fit, ``t``: their position along it (px), ``y``: normalised values. Returns the line
    ``(n, c)``, ``n · (x, t) = c``, or None with too few segments."""
    count = int(0.8 * length // _SEGMENT_PX)
    if count < _MIN_SEGMENTS:
        return None
    edges = np.linspace(t.min(), t.max() + 1e-9, count + 1)
    which = np.digitize(t, edges) - 1
    shifts = np.arange(-_SEGMENT_REACH_PX, _SEGMENT_REACH_PX + 1e-9, _SEGMENT_STEP_PX)
    points = []
    for j in range(count):
        sel = (which == j) & (x < _SEGMENT_INSIDE_PX)
        if sel.sum() < 30:
            continue
        xs, ys = x[sel][:, None] - shifts[None, :], y[sel]
        # per shift, least squares of y ≈ tape·dark + skin·lit·(1 + g·x): the segment's own levels and a
        # gradient of the skin across the edge's reach (texture), so the shape left is the edge's alone
        lit_x = np.interp(xs, grid, lit)
        design = np.stack([np.interp(xs, grid, dark), lit_x, lit_x * np.clip(xs, 0, None) / _INSIDE_PX], axis=-1)
        gram = np.einsum("nmi,nmj->mij", design, design)
        coef = np.linalg.solve(gram + 1e-9 * np.eye(3), np.einsum("nmi,n->mi", design, ys)[..., None])[..., 0]
        tape, skin = coef[:, 0], coef[:, 1]
        sse = ((ys[:, None] - np.einsum("nmi,mi->nm", design, coef)) ** 2).sum(0)
        k = int(np.argmin(sse))
        if k == 0 or k == shifts.size - 1 or not skin[k] > tape[k]:
            continue
        den = sse[k - 1] - 2 * sse[k] + sse[k + 1]
        frac = 0.5 * (sse[k - 1] - sse[k + 1]) / den if den > 0 else 0.0
        points.append((shifts[k] + frac * _SEGMENT_STEP_PX, float(np.mean(t[sel])), float(sse[k] / sel.sum())))
    if len(points) < _MIN_SEGMENTS:
        return None
    pts = np.array(points)
    # a segment the profile does not describe (a freckle or a hair on the edge) says little of the edge
    pts = pts[pts[:, 2] <= 4.0 * np.median(pts[:, 2])]
    if len(pts) < _MIN_SEGMENTS:
        return None
    # Theil–Sen start (the median of the pairwise slopes), then least squares on the points within
    # 3 robust sigma: a bent segment neither tilts the start nor stays in the fit
    i, j = np.triu_indices(len(pts), 1)
    slope = float(np.median((pts[j, 0] - pts[i, 0]) / (pts[j, 1] - pts[i, 1])))
    coef = np.array([slope, float(np.median(pts[:, 0] - slope * pts[:, 1]))])
    for _ in range(3):
        r = pts[:, 0] - np.polyval(coef, pts[:, 1])
        mad = 1.4826 * np.median(np.abs(r - np.median(r)))
        keep = np.abs(r) <= max(3.0 * mad, 0.03)
        if keep.sum() < _MIN_SEGMENTS:
            return None
        coef = np.polyfit(pts[keep, 1], pts[keep, 0], 1)
    slope, intercept = coef
    # x = slope·t + intercept  ⇔  (1, −slope) · (x, t) = intercept
    norm = float(np.hypot(1.0, slope))
    return np.array([1.0, -slope]) / norm, float(intercept) / norm
